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

/// A pass over a cell's points (grid order) prefetches the per-point outputs of the point this
/// many places on: they are indexed by input order, so a shuffled cloud scatters them.
inline constexpr std::uint32_t kPrefetchAhead = 4;

/// Usable points (labels NORMAL or EDGE) whose group, usable points linked by distance <=
/// `radius`, has fewer than `min_group` points; ascending. Bounded searches from the points with
/// fewer than `min_group - 1` usable neighbours, so the cost is small when few are.
/// `counts[i]`: the finite points other than i within `radius` of i (saturated at
/// kCountSaturated, then recounted); it is consumed (the ABNORMAL neighbours are subtracted).
template <typename T>
std::vector<std::uint32_t> floating_points(const NeighborGrid<T>& grid, const PointsView<T>& points,
                                           const std::uint8_t* labels, std::uint16_t* counts,
                                           double radius, int min_group, int num_threads);

/// The isolated-point rule of the height test: the median |height| of the point's inner NORMAL
/// neighbours over the surroundings plane must be at least this multiple of the plane's rms.
inline constexpr double kIsolatedMedian = 0.5;
// The bead rule (SPEC "Unorganized clouds: floating groups and height test", step 3): the run
// (the points within kBeadLevel |h| of p's level) is a line at most kBeadWidth spacings wide
// (rms across), reaching within kBeadMargin spacings of the farthest usable points both ways,
// with at least kBeadSide of the others on each side.
inline constexpr double kBeadLevel = 0.5;
inline constexpr double kBeadWidth = 0.25;
inline constexpr double kBeadMargin = 2.0;
inline constexpr double kBeadSide = 0.25;

/// The height test's settings, resolved (lengths in the points' units).
struct HeightTest {
  double abs = 0.0;            ///< > 0: |h| above this
  double k = 0.0;              ///< > 0: |h| above k * rms
  double iso_k = 0.0;          ///< > 0: the isolated-point rule, |h| above iso_k * rms
  double radius = 0.0;         ///< height-plane radius
  double inner = 0.0;          ///< the plane is fitted to the NORMAL points beyond this
  double link = 0.0;           ///< EDGE grouping distance
  double compact_len = 0.0;    ///< EDGE groups at most this across are compact
  double spacing = 0.0;        ///< the cloud's spacing (the bead rule's lengths)
  int max_iterations = 1;
  /// Optional: the first pass also writes the height of every tested point over the plane of
  /// the NORMAL points within `radius` (as the heights stage does) into `height[i]`, sets
  /// `have[i] = 1`, and appends to `*unnormal` every NORMAL point a later verdict makes
  /// ABNORMAL (whose neighbours' heights are then stale).
  double* height = nullptr;
  std::uint8_t* have = nullptr;
  std::vector<std::uint32_t>* unnormal = nullptr;
  /// Optional: the first pass writes the rms of each tested point's surroundings plane where
  /// the test gave a verdict (the plane exists, no feature line near); others are left as is.
  double* first_rms = nullptr;
};

/// Height passes: NORMAL and compact-EDGE points farther than the tolerance from the plane of
/// the NORMAL points at distances in (`t.inner`, `t.radius`] (the surroundings, not the point's
/// own bump) become ABNORMAL, unless a feature-line EDGE point is within `t.radius`. Returns the
/// number of passes run.
template <typename T>
int height_passes(const NeighborGrid<T>& grid, const PointsView<T>& points, std::uint8_t* labels,
                  const HeightTest& t, std::vector<JudgeScratch>& scratch, int num_threads);

/// The cloud edge test's settings, resolved (SPEC "Unorganized clouds: edge test").
struct CloudEdgeTest {
  double k = 0.0;        ///< tolerance in sector rms
  double r_edge = 0.0;   ///< sector radius of the narrow scale (the wide one: 1.5 x this)
  double gap = 0.0;      ///< sector members lie at least this far from the point in the tangent plane
  int max_iterations = 1;
  bool hanging = true;   ///< step 5's hanging rule (the wide scale's sectors do without it)
  /// the input's precision, relative (detail::edge_precision of its type): every tolerance is
  /// at least this times P's largest absolute coordinate (SPEC step 3)
  double prec = 0.0;
  /// Not NaN: the median of the candidates' rms given by the caller (the whole cloud's, when
  /// this run sees part of it: PointsDetectHooks); NaN: the median of `*first_rms`.
  double rms_median = kNaN;
};

/// Edge passes after the height passes: candidates are the NORMAL and EDGE points whose
/// `*first_rms` (height_passes' HeightTest::first_rms, NaN: no verdict; freed once the
/// candidates are listed) is NaN or above 1.5 x the median; one becomes ABNORMAL when, at
/// either scale (sectors within r_edge or 1.5 r_edge, each with the frame of its own disk), it
/// stands proud of a clean sector whose opposite is empty or falls away and fits no clean
/// sector that is not past the feature (the crossing rule), or fits none and hangs below one or
/// is a lip at a concave feature beyond one. NORMAL points made ABNORMAL are appended to
/// `*unnormal` (when given). Returns the number of passes run.
template <typename T>
int cloud_edge_passes(const NeighborGrid<T>& grid, const PointsView<T>& points,
                      std::uint8_t* labels, std::vector<double>* first_rms,
                      const CloudEdgeTest& e, std::vector<JudgeScratch>& scratch,
                      int num_threads, std::vector<std::uint32_t>* unnormal);

}  // namespace miem::cloud
