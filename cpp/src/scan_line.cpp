// Angles and eq. 20 heights along one scan line.
#include "miem/scan_line.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>

namespace miem {

namespace {
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kRadToDeg = 57.29577951308232;  // 180 / pi
}  // namespace

template <typename T>
void scan_line_angles(const PointsView<T>& line, int step, double* out_deg) {
  if (step < 1) throw std::invalid_argument("step: must be an integer >= 1");
  const std::ptrdiff_t n = line.size;
  for (std::ptrdiff_t i = 0; i < n; ++i) {
    out_deg[i] = kNaN;
    if (i - step < 0 || i + step >= n) continue;
    const Eigen::Vector3d p = line[i], a = line[i - step], b = line[i + step];
    if (!p.allFinite() || !a.allFinite() || !b.allFinite()) continue;
    const Eigen::Vector3d u = a - p, v = b - p;
    const double uu = u.squaredNorm(), vv = v.squaredNorm();
    if (uu == 0.0 || vv == 0.0) continue;
    const double c = std::clamp(u.dot(v) / std::sqrt(uu * vv), -1.0, 1.0);
    out_deg[i] = std::acos(c) * kRadToDeg;
  }
}

template <typename T>
void scan_line_heights(const PointsView<T>& line, int step, double* out) {
  if (step < 1) throw std::invalid_argument("step: must be an integer >= 1");
  const std::ptrdiff_t n = line.size;
  for (std::ptrdiff_t i = 0; i < n; ++i) {
    out[i] = kNaN;
    const std::ptrdiff_t j = i - step;  // the predecessor whose angle is used
    if (j - step < 0 || j + step >= n) continue;
    const Eigen::Vector3d p = line[i], a = line[j - step], q = line[j];
    if (!p.allFinite() || !a.allFinite() || !q.allFinite()) continue;
    const Eigen::Vector3d u = a - q, v = p - q;
    const double uu = u.squaredNorm(), vv = v.squaredNorm();
    if (uu == 0.0 || vv == 0.0) continue;
    const double c = std::clamp(u.dot(v) / std::sqrt(uu * vv), -1.0, 1.0);
    out[i] = std::sin(std::acos(c)) * std::sqrt(vv);
  }
}

template void scan_line_angles<float>(const PointsView<float>&, int, double*);
template void scan_line_angles<double>(const PointsView<double>&, int, double*);
template void scan_line_heights<float>(const PointsView<float>&, int, double*);
template void scan_line_heights<double>(const PointsView<double>&, int, double*);

}  // namespace miem
