// Duplicate points: union of the rows within merge_distance, smallest row index as the
// representative. Partners of a row with nn <= tol also have nn <= tol, so only those rows are
// indexed and searched.
#include "duplicates.hpp"

#include <algorithm>
#include <cmath>
#include <numeric>

#include "miem/neighbor_grid.hpp"

namespace miem::cloud {

namespace {

std::int64_t find_root(std::vector<std::int64_t>& parent, std::int64_t i) {
  while (parent[i] != i) {
    parent[i] = parent[parent[i]];
    i = parent[i];
  }
  return i;
}

}  // namespace

template <typename T>
Duplicates find_duplicates(const PointsView<T>& points, const std::vector<double>& nn, double tol,
                           int num_threads) {
  Duplicates d;
  const std::ptrdiff_t N = points.size;
  std::vector<std::int64_t> cand;
  for (std::ptrdiff_t i = 0; i < N; ++i) {
    if (nn[i] <= tol) cand.push_back(i);  // NaN (non-finite) compares false
  }
  if (cand.empty()) return d;
  // A compact copy of the candidates, indexed by a grid.
  const std::size_t m = cand.size();
  std::vector<T> buf(3 * m);
  for (std::size_t k = 0; k < m; ++k) {
    const T* q = points.data + cand[k] * points.point_stride;
    for (int a = 0; a < 3; ++a) buf[3 * k + a] = q[a * points.coord_stride];
  }
  const PointsView<T> view{buf.data(), static_cast<std::ptrdiff_t>(m), 3, 1};
  Eigen::Vector3d lo = view[0], hi = view[0];
  for (std::size_t k = 1; k < m; ++k) {
    lo = lo.cwiseMin(view[k]);
    hi = hi.cwiseMax(view[k]);
  }
  const double ext = (hi - lo).maxCoeff();
  const double cell = std::max({tol, ext / std::cbrt(static_cast<double>(m)), ext * 1e-9, 1e-300});
  const NeighborGrid<T> grid(view, cell, num_threads);
  std::vector<std::int64_t> parent(m);
  std::iota(parent.begin(), parent.end(), 0);
  for (std::size_t k = 0; k < m; ++k) {
    grid.for_each_in_radius(view[k], tol, [&](std::ptrdiff_t j, double) {
      const std::int64_t a = find_root(parent, static_cast<std::int64_t>(k));
      const std::int64_t b = find_root(parent, j);
      if (a != b) parent[std::max(a, b)] = std::min(a, b);  // roots are the smallest positions
    });
  }
  d.rep.resize(static_cast<std::size_t>(N));
  for (std::ptrdiff_t i = 0; i < N; ++i) d.rep[i] = std::isnan(nn[i]) ? -1 : i;
  for (std::size_t k = 0; k < m; ++k) {
    const std::int64_t root = cand[find_root(parent, static_cast<std::int64_t>(k))];
    d.rep[cand[k]] = root;  // candidates ascend, so the root is the group's smallest row
    d.merged += root != cand[k];
  }
  for (std::ptrdiff_t i = 0; i < N; ++i) {
    if (d.rep[i] == i) d.distinct.push_back(i);
  }
  return d;
}

template Duplicates find_duplicates<float>(const PointsView<float>&, const std::vector<double>&,
                                           double, int);
template Duplicates find_duplicates<double>(const PointsView<double>&, const std::vector<double>&,
                                            double, int);

}  // namespace miem::cloud
