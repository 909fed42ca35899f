// Defect summaries shared by the organized and unorganized detectors (docs/SPEC.md "Defects"):
// centroid, peak and mean height, extent, kind, and the output order.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include <Eigen/Core>

#include "miem/organized.hpp"

namespace miem::detail {

/// Fills centroid, peak_height and mean_height of a defect whose indices are set (ascending),
/// the height of index i being height_at(i); returns the peak point's index, or -1 when no
/// member has a finite height.
template <typename HeightAt, typename PointAt>
std::int64_t summarize_defect_at(Defect& d, HeightAt height_at, PointAt point_at) {
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  double hsum = 0.0;
  int hcount = 0;
  std::int64_t peak_idx = -1;
  d.peak_height = std::numeric_limits<double>::quiet_NaN();
  for (std::int64_t i : d.indices) {
    sum += point_at(i);
    const double h = height_at(i);
    if (std::isfinite(h)) {
      hsum += h;
      ++hcount;
      if (peak_idx < 0 || std::abs(h) > std::abs(d.peak_height)) {  // first on ties
        d.peak_height = h;
        peak_idx = i;
      }
    }
  }
  d.centroid = sum / static_cast<double>(d.indices.size());
  d.mean_height = hcount > 0 ? hsum / hcount : std::numeric_limits<double>::quiet_NaN();
  return peak_idx;
}

/// summarize_defect_at with the heights of a grid or cloud (height[i]).
template <typename PointAt>
std::int64_t summarize_defect(Defect& d, const double* height, PointAt point_at) {
  return summarize_defect_at(d, [height](std::int64_t i) { return height[i]; }, point_at);
}

/// Fills extent (diameter in the tangent plane of d.normal, 3-D when it is NaN) and kind.
template <typename PointAt>
void finish_defect(Defect& d, PointAt point_at, bool touches_surface) {
  const bool has_normal = d.normal.allFinite();
  double max_r = 0.0;
  for (std::int64_t i : d.indices) {
    Eigen::Vector3d w = point_at(i) - d.centroid;
    if (has_normal) w -= w.dot(d.normal) * d.normal;
    max_r = std::max(max_r, w.norm());
  }
  d.extent = 2.0 * max_r;
  if (!touches_surface || std::isnan(d.peak_height)) {
    d.kind = DefectKind::kIsolated;
  } else {
    d.kind = d.peak_height < 0 ? DefectKind::kPit : DefectKind::kProtrusion;
  }
}

/// Orders defects by |peak_height| descending (NaN last, ties by first index) and numbers them.
inline void order_defects(std::vector<Defect>& defects) {
  std::stable_sort(defects.begin(), defects.end(), [](const Defect& a, const Defect& b) {
    const bool na = std::isnan(a.peak_height), nb = std::isnan(b.peak_height);
    if (na != nb) return nb;
    if (!na && std::abs(a.peak_height) != std::abs(b.peak_height)) {
      return std::abs(a.peak_height) > std::abs(b.peak_height);
    }
    return a.indices.front() < b.indices.front();
  });
  for (std::size_t k = 0; k < defects.size(); ++k) defects[k].id = static_cast<int>(k);
}

}  // namespace miem::detail
