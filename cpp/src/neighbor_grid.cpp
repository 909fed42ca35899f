// The uniform neighbour grid: cell keys from coordinates relative to the minimum corner, a stable
// LSD radix sort of (key, index) pairs (linear in N, ascending index within a cell), and
// ring-by-ring nearest-neighbour search shared by all the points of a cell.
#include "miem/neighbor_grid.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

#include "finite_bounds.hpp"
#include "parallel.hpp"
#include "radix_sort.hpp"

namespace miem {

namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

}  // namespace

template <typename T>
NeighborGrid<T>::NeighborGrid(const PointsView<T>& points, double cell_size, int num_threads)
    : points_(points) {
  if (!std::isfinite(cell_size) || !(cell_size > 0.0)) {
    throw std::invalid_argument("cell_size: must be finite and > 0, got " +
                                std::to_string(cell_size));
  }
  if (points.size < 0 || (points.size > 0 && points.data == nullptr)) {
    throw std::invalid_argument("points: null data");
  }
  if (points.size >= static_cast<std::ptrdiff_t>(std::numeric_limits<std::uint32_t>::max())) {
    throw std::invalid_argument("points: at most 2^32 - 2 points are supported");
  }
  const std::ptrdiff_t n = points.size;
  const int nt = detail::thread_count(num_threads, n);

  // Bounds of the finite points.
  const detail::FiniteBounds fb = detail::finite_bounds(points, nt);
  const Eigen::Vector3d lo = fb.lo, hi = fb.hi;
  const std::ptrdiff_t n_finite = fb.count;
  if (n_finite == 0) {
    origin_.setZero();
    cell_ = cell_size;
    inv_cell_ = 1.0 / cell_size;
    starts_.assign(1, 0);
    return;
  }
  origin_ = lo;

  // Cell size: the request, enlarged when the key would not fit (each axis < 2^31 cells, the
  // product < 2^62).
  double cell = cell_size;
  const Eigen::Vector3d extent = hi - lo;
  for (int attempt = 0;; ++attempt) {
    const double inv = 1.0 / cell;
    double prod = 1.0;
    bool ok = std::isfinite(inv) && inv > 0.0;
    for (int a = 0; a < 3 && ok; ++a) {
      const double d = std::floor(extent[a] * inv) + 1.0;
      if (!(d < 2147483000.0)) ok = false;
      prod *= d;
    }
    if (ok && prod < 4.0e18) break;
    if (attempt > 200) throw std::invalid_argument("points: extent too large to index");
    const double emax = extent.maxCoeff();
    cell = std::max(cell * 1.5, emax / 1.0e6);
  }
  cell_ = cell;
  inv_cell_ = 1.0 / cell;
  for (int a = 0; a < 3; ++a) {
    dims_[a] = static_cast<std::int64_t>(std::floor(extent[a] * inv_cell_)) + 1;
  }

  // Keys of the finite points, in index order.
  std::vector<std::uint64_t> keys(static_cast<std::size_t>(n_finite));
  std::vector<std::uint32_t> ids(static_cast<std::size_t>(n_finite));
  detail::compact_ranges(
      nt, n, [&points](std::ptrdiff_t i) { return points[i].allFinite(); },
      [](std::ptrdiff_t) {},
      [&ids](std::ptrdiff_t k, std::ptrdiff_t i) { ids[k] = static_cast<std::uint32_t>(i); });
  std::uint64_t max_key = 0;
#pragma omp parallel for schedule(static) num_threads(nt) if (nt > 1) reduction(max : max_key)
  for (std::ptrdiff_t k = 0; k < n_finite; ++k) {
    const std::uint64_t key = key_of(points[ids[k]]);
    keys[k] = key;
    max_key = std::max(max_key, key);
  }
  {
    std::vector<std::uint64_t> tmp_keys(keys.size());
    std::vector<std::uint32_t> tmp_ids(ids.size());
    if (detail::radix_sort(keys.data(), ids.data(), tmp_keys.data(), tmp_ids.data(),
                           keys.size(), max_key, nt)) {
      keys.swap(tmp_keys);
      ids.swap(tmp_ids);
    }
  }

  // Occupied cells and their point ranges: where the sorted keys change.
  detail::compact_ranges(
      nt, n_finite, [&keys](std::ptrdiff_t k) { return k == 0 || keys[k] != keys[k - 1]; },
      [this](std::ptrdiff_t ncells) {
        keys_.resize(static_cast<std::size_t>(ncells));
        starts_.resize(static_cast<std::size_t>(ncells) + 1);
      },
      [&](std::ptrdiff_t c, std::ptrdiff_t k) {
        keys_[c] = keys[k];
        starts_[c] = static_cast<std::uint32_t>(k);
      });
  starts_.back() = static_cast<std::uint32_t>(n_finite);
  std::vector<std::uint64_t>().swap(keys);
  order_ = std::move(ids);
  sorted_.resize(3 * static_cast<std::size_t>(n_finite));
#pragma omp parallel for schedule(static) num_threads(nt) if (nt > 1)
  for (std::ptrdiff_t k = 0; k < n_finite; ++k) {
    const T* p = points.data + static_cast<std::ptrdiff_t>(order_[k]) * points.point_stride;
    T* dst = sorted_.data() + 3 * k;
    dst[0] = p[0];
    dst[1] = p[points.coord_stride];
    dst[2] = p[2 * points.coord_stride];
  }
}

template <typename T>
void NeighborGrid<T>::radius_query(std::ptrdiff_t index, double r,
                                   std::vector<std::int64_t>& out) const {
  if (index < 0 || index >= points_.size) {
    throw std::invalid_argument("index: " + std::to_string(index) + " is out of range for " +
                                std::to_string(points_.size) + " points");
  }
  out.clear();
  const Eigen::Vector3d q = points_[index];
  if (!q.allFinite()) {
    if (!std::isfinite(r) || r < 0.0) throw std::invalid_argument("r: must be finite and >= 0");
    return;
  }
  radius_query(q, r, out);
}

template <typename T>
void NeighborGrid<T>::radius_query(const Eigen::Vector3d& q, double r,
                                   std::vector<std::int64_t>& out) const {
  if (!std::isfinite(r) || r < 0.0) {
    throw std::invalid_argument("r: must be finite and >= 0, got " + std::to_string(r));
  }
  if (!q.allFinite()) throw std::invalid_argument("query point: coordinates must be finite");
  out.clear();
  for_each_in_radius(q, r, [&](std::ptrdiff_t j, double) { out.push_back(j); });
  std::sort(out.begin(), out.end());
}

template <typename T>
void NeighborGrid<T>::nearest_in_cell(const std::int64_t center[3], const std::uint32_t* ids,
                                      std::ptrdiff_t count, std::ptrdiff_t first_pos,
                                      std::vector<Eigen::Vector3d>& pts, double* best2) const {
  pts.resize(static_cast<std::size_t>(count));
  for (std::ptrdiff_t a = 0; a < count; ++a) {
    pts[a] = first_pos >= 0 ? sorted_point(static_cast<std::uint32_t>(first_pos + a))
                            : Eigen::Vector3d(points_[ids[a]]);
    best2[a] = kInf;
  }
  const Eigen::Vector3d* __restrict P = pts.data();
  double* __restrict B = best2;
  auto visit_cell = [&](std::ptrdiff_t cell) {
    const std::uint32_t e = starts_[cell + 1];
    for (std::uint32_t k = starts_[cell]; k < e; ++k) {
      const std::uint32_t j = order_[k];
      const Eigen::Vector3d q = sorted_point(k);
      for (std::ptrdiff_t a = 0; a < count; ++a) {
        const double dx = q.x() - P[a].x(), dy = q.y() - P[a].y(), dz = q.z() - P[a].z();
        const double d2 = ids[a] == j ? kInf : dx * dx + dy * dy + dz * dz;
        B[a] = std::min(B[a], d2);  // branch-free
      }
    }
  };
  const std::int64_t cx = center[0], cy = center[1], cz = center[2];
  std::int64_t reach = 0;  // rings needed to cover the whole grid
  for (int a = 0; a < 3; ++a) reach = std::max({reach, center[a], dims_[a] - 1 - center[a]});
  const std::uint64_t ncells = keys_.size();
  for (std::int64_t m = 0; m <= reach; ++m) {
    const std::uint64_t side = static_cast<std::uint64_t>(2 * m + 1);
    if (m > 1 && side * side > ncells / 8 + 8) {
      // Far from everything: scan the cells not yet visited, skipping those too far to help.
      double worst = 0.0;
      for (std::ptrdiff_t a = 0; a < count; ++a) worst = std::max(worst, best2[a]);
      for (std::size_t cell = 0; cell < ncells; ++cell) {
        std::int64_t cc[3];
        cell_coords(static_cast<std::ptrdiff_t>(cell), cc);
        const std::int64_t cheb =
            std::max({std::abs(cc[0] - cx), std::abs(cc[1] - cy), std::abs(cc[2] - cz)});
        if (cheb < m) continue;
        const double lb = (static_cast<double>(cheb) - 1.001) * cell_;
        if (lb > 0.0 && lb * lb > worst) continue;
        visit_cell(static_cast<std::ptrdiff_t>(cell));
      }
      return;
    }
    // Ring m: the cells at Chebyshev distance m. Ring 0 is visited together with ring 1 (one
    // 3 x 3 x 3 box), unless the grid is a single cell.
    if (m == 0 && reach > 0) continue;
    const std::int64_t lo_ring = m == 1 ? 0 : m;
    CellBox b;
    for (int a = 0; a < 3; ++a) {
      b.lo[a] = std::max<std::int64_t>(center[a] - m, 0);
      b.hi[a] = std::min(center[a] + m, dims_[a] - 1);
    }
    for_each_cell_xyz(b, [&](std::ptrdiff_t cell, std::int64_t ix, std::int64_t iy,
                             std::int64_t iz) {
      const std::int64_t cheb = std::max({std::abs(ix - cx), std::abs(iy - cy), std::abs(iz - cz)});
      if (cheb >= lo_ring) visit_cell(cell);
    });
    // Every point outside the rings 0..m is more than m cells (less rounding slack) away.
    const double bound = (static_cast<double>(m) - 0.001) * cell_;
    if (bound <= 0.0) continue;
    bool done = true;
    for (std::ptrdiff_t a = 0; a < count && done; ++a) done = best2[a] < bound * bound;
    if (done) return;
  }
}

template <typename T>
double NeighborGrid<T>::nearest_distance(std::ptrdiff_t index) const {
  if (index < 0 || index >= points_.size) {
    throw std::invalid_argument("index: " + std::to_string(index) + " is out of range for " +
                                std::to_string(points_.size) + " points");
  }
  const Eigen::Vector3d p = points_[index];
  if (!p.allFinite()) return kNaN;
  const std::int64_t c[3] = {coord(p.x(), 0), coord(p.y(), 1), coord(p.z(), 2)};
  const std::uint32_t id = static_cast<std::uint32_t>(index);
  std::vector<Eigen::Vector3d> scratch;
  double best2 = kInf;
  nearest_in_cell(c, &id, 1, -1, scratch, &best2);
  return std::sqrt(best2);
}

template <typename T>
void NeighborGrid<T>::nearest_distances(double* out, int num_threads) const {
  const std::ptrdiff_t n = points_.size;
  for (std::ptrdiff_t i = 0; i < n; ++i) out[i] = kNaN;
  const std::ptrdiff_t ncells = num_cells();
  const int nt = detail::thread_count(num_threads, num_indexed(), 4096);
#pragma omp parallel num_threads(nt) if (nt > 1)
  {
    std::vector<Eigen::Vector3d> scratch;
    std::vector<double> best2;
#pragma omp for schedule(dynamic, 64)
    for (std::ptrdiff_t cell = 0; cell < ncells; ++cell) {
      const std::uint32_t b = starts_[cell], e = starts_[cell + 1];
      std::int64_t cc[3];
      cell_coords(cell, cc);
      best2.resize(e - b);
      nearest_in_cell(cc, order_.data() + b, e - b, b, scratch, best2.data());
      for (std::uint32_t k = b; k < e; ++k) out[order_[k]] = std::sqrt(best2[k - b]);
    }
  }
}

template class NeighborGrid<float>;
template class NeighborGrid<double>;

}  // namespace miem
