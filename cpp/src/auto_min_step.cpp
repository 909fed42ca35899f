// min_step = "auto" (docs/SPEC.md "min_step='auto'"): per grid axis (along a profile, across
// profiles) the median distance of finite neighbour pairs and the robust z noise
// 1.4826 median|z[i-1] - 2 z[i] + z[i+1]| / sqrt(6) of finite triples; min_step is
// 4 * max(noise) when that exceeds min(spacing), else off (-1).
#include "auto_min_step.hpp"

#include <algorithm>
#include <cmath>

#include <Eigen/Core>

#include "miem/organized.hpp"

namespace miem {
namespace detail {
namespace {

// np.median: the middle value, or the mean of the two middle values.
double median(std::vector<double>& v) {
  const std::size_t n = v.size(), mid = n / 2;
  std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(mid), v.end());
  const double hi = v[mid];
  if (n % 2 == 1) return hi;
  const double lo = *std::max_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(mid));
  return (lo + hi) / 2.0;
}

}  // namespace

template <typename T>
double auto_min_step(const GridView<T>& g, std::vector<double>& buf) {
  double spacing = 0.0, noise = 0.0;
  bool any = false;
  for (int axis = 0; axis < 2; ++axis) {  // 0: along a profile (columns), 1: across (rows)
    // neighbours one step along the axis; the cells are visited row by row (a median does not
    // depend on the order)
    const std::ptrdiff_t dr = axis, dc = 1 - axis;
    buf.clear();
    for (std::ptrdiff_t r = 0; r + dr < g.rows; ++r) {
      for (std::ptrdiff_t c = 0; c + dc < g.cols; ++c) {
        if (!g.finite(r, c) || !g.finite(r + dr, c + dc)) continue;
        const Eigen::Vector3d d = g(r + dr, c + dc) - g(r, c);
        buf.push_back(std::sqrt(d.x() * d.x() + d.y() * d.y() + d.z() * d.z()));
      }
    }
    if (buf.empty()) continue;
    const double dist = median(buf);
    buf.clear();
    for (std::ptrdiff_t r = 0; r + 2 * dr < g.rows; ++r) {
      for (std::ptrdiff_t c = 0; c + 2 * dc < g.cols; ++c) {
        if (!g.finite(r, c) || !g.finite(r + dr, c + dc) || !g.finite(r + 2 * dr, c + 2 * dc)) {
          continue;
        }
        const double z0 = g(r, c).z(), z1 = g(r + dr, c + dc).z();
        const double z2 = g(r + 2 * dr, c + 2 * dc).z();
        buf.push_back(std::abs(z0 - 2.0 * z1 + z2));
      }
    }
    if (buf.empty()) continue;
    const double sigma = 1.4826 * median(buf) / std::sqrt(6.0);
    spacing = any ? std::min(spacing, dist) : dist;
    noise = any ? std::max(noise, sigma) : sigma;
    any = true;
  }
  if (!any) return -1.0;
  const double m = 4.0 * noise;
  return m > spacing ? m : -1.0;
}

template double auto_min_step<float>(const GridView<float>&, std::vector<double>&);
template double auto_min_step<double>(const GridView<double>&, std::vector<double>&);

}  // namespace detail

template <typename T>
double auto_min_step(const GridView<T>& grid) {
  std::vector<double> buf;
  return detail::auto_min_step(grid, buf);
}

template double auto_min_step<float>(const GridView<float>&);
template double auto_min_step<double>(const GridView<double>&);

}  // namespace miem
