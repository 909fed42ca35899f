// Stages of unorganized detection after the angle passes (docs/SPEC.md, "Unorganized clouds:
// floating groups and height test"). Internal to the core; detect_points (unorganized.cpp) runs
// them in order: angle passes, floating groups, height passes, plane, heights, defects.
#pragma once

#include <cstdint>
#include <vector>

#include "cloud_kernels.hpp"

namespace miem::cloud {

/// Saturation value of the neighbour counts passed to floating_points.
inline constexpr std::uint16_t kCountSaturated = 0xFFFF;

/// Usable points (labels NORMAL or EDGE) whose group, usable points linked by distance <=
/// `radius`, has fewer than `min_group` points; ascending. Bounded searches from the points with
/// fewer than `min_group - 1` usable neighbours, so the cost is small when few are.
/// `counts[i]`: the finite points other than i within `radius` of i (saturated at
/// kCountSaturated, then recounted); it is consumed (the ABNORMAL neighbours are subtracted).
template <typename T>
std::vector<std::uint32_t> floating_points(const NeighborGrid<T>& grid, const PointsView<T>& points,
                                           const std::uint8_t* labels, std::uint16_t* counts,
                                           double radius, int min_group, int num_threads);

/// The height test's settings, resolved (lengths in the points' units).
struct HeightTest {
  double abs = 0.0;            ///< > 0: |h| above this
  double k = 0.0;              ///< > 0: |h| above k * rms
  double radius = 0.0;         ///< height-plane radius
  double inner = 0.0;          ///< the plane is fitted to the NORMAL points beyond this
  double link = 0.0;           ///< EDGE grouping distance
  double compact_len = 0.0;    ///< EDGE groups at most this across are compact
  int max_iterations = 1;
  /// Optional: the first pass also writes the height of every tested point over the plane of
  /// the NORMAL points within `radius` (as the heights stage does) into `height[i]`, sets
  /// `have[i] = 1`, and appends to `*unnormal` every NORMAL point a later verdict makes
  /// ABNORMAL (whose neighbours' heights are then stale).
  double* height = nullptr;
  std::uint8_t* have = nullptr;
  std::vector<std::uint32_t>* unnormal = nullptr;
};

/// Height passes: NORMAL and compact-EDGE points farther than the tolerance from the plane of
/// the NORMAL points at distances in (`t.inner`, `t.radius`] (the surroundings, not the point's
/// own bump) become ABNORMAL, unless a feature-line EDGE point is within `t.radius`. Returns the
/// number of passes run.
template <typename T>
int height_passes(const NeighborGrid<T>& grid, const PointsView<T>& points, std::uint8_t* labels,
                  const HeightTest& t, std::vector<JudgeScratch>& scratch, int num_threads);

}  // namespace miem::cloud
