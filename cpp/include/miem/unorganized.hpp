// MIEM on unorganized clouds ((N, 3) points, no order): point spacing, local planes and normals,
// the K-direction tangent-plane angle test with iteration, local heights and defects.
// The exact rules are in docs/SPEC.md, section "Unorganized clouds".
#pragma once

#include <cstdint>
#include <limits>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "miem/organized.hpp"
#include "miem/params.hpp"
#include "miem/plane.hpp"
#include "miem/views.hpp"

namespace miem {

/// Median over the finite points of the distance to the nearest other finite point (the mean of
/// the two middle values for an even count). Throws std::invalid_argument when there are fewer
/// than 3 finite points or the spacing is 0 (more than half the points are duplicates), and
/// CoordinateRangeError (miem/views.hpp) for a finite coordinate outside SPEC's range.
template <typename T>
double point_spacing(const PointsView<T>& points, int num_threads = 0);

/// What detect_points takes the median of when CloudParams::spacing is not given: for every
/// row that represents its duplicate group (within merge_distance, SPEC "Duplicate points"),
/// the distance to the nearest other distinct point; NaN for the other rows and non-finite ones.
/// `out` has points.size elements. Lets a caller that holds the cloud in parts (miem.dask)
/// find the same spacing. Throws as point_spacing for fewer than 3 finite points.
template <typename T>
void distinct_spacings(const PointsView<T>& points, double merge_distance, double* out,
                       int num_threads = 0);

/// Caller-owned outputs of estimate_normals, each for every row of the input.
struct NormalsOutput {
  double* normals = nullptr;        ///< N x 3 row-major oriented unit normals (NaN when invalid)
  double* rms = nullptr;            ///< RMS distance of the fitted points (NaN when invalid)
  std::int64_t* count = nullptr;    ///< points used (the point itself included; 0 for non-finite)
  std::uint8_t* valid = nullptr;    ///< 1 where a plane was fitted
};

/// Local plane at every finite point: eigen fit of the finite points within `radius`, the point
/// itself included. Fewer than 3 points or degenerate (collinear / equal): NaN normal and rms,
/// valid 0. Any of the output pointers may be null. Throws std::invalid_argument when radius is
/// not finite and > 0, CoordinateRangeError for a finite coordinate outside SPEC's range.
/// Deterministic for any thread count.
template <typename T>
void estimate_normals(const PointsView<T>& points, double radius, const NormalsOutput& out,
                      int num_threads = 0);

/// Caller-owned per-point outputs of detect_points, N values each. `labels` is required; the
/// others may be null.
struct PointsOutput {
  std::uint8_t* labels = nullptr;      ///< Label values
  std::uint8_t* flags = nullptr;       ///< bit k: tangent direction k flagged
  double* angle_deg = nullptr;         ///< smallest angle seen, NaN where none
  double* height = nullptr;            ///< height over the local NORMAL plane, NaN where none
  std::uint8_t* degenerate = nullptr;  ///< 1 where the last judgment met a degenerate neighbourhood
};

/// What a detection run returns besides the per-point buffers.
struct PointsDetectSummary {
  int iterations = 0;
  std::optional<Plane> plane;   ///< the MIEM plane (eigen fit of the non-ABNORMAL points)
  std::vector<Defect> defects;  ///< indices are row indices; ordered by |peak_height| descending
  double spacing = 0.0;         ///< median nearest-neighbour distance
  double radius = 0.0;          ///< the values used
  double min_step = 0.0;
  double link = 0.0;
  double height_radius = 0.0;
  double edge_radius = 0.0;     ///< the edge test's sector radius used (0 when it is off)
  std::ptrdiff_t merged = 0;    ///< rows merged into another (duplicates), labelled like it
  /// Wall-clock and process CPU seconds of each stage, in run order (a profile, for
  /// benchmarks; never part of a result).
  struct Stage {
    std::string name;
    double wall = 0.0, cpu = 0.0;
  };
  std::vector<Stage> stage_seconds;
};

/// Everything, owned.
struct PointsDetectResult {
  std::vector<std::uint8_t> labels, flags, degenerate;
  std::vector<double> angle_deg, height;
  PointsDetectSummary summary;
};

/// Internal hooks of detect_points for a caller that holds the cloud in parts (miem.dask; docs/
/// SPEC.md "Blocks"), not parameters: with the defaults a run is the plain detection. The cloud
/// edge test's candidates compare each point's surroundings rms with a median over the whole
/// cloud (SPEC "Unorganized clouds: edge test" step 1), which a part cannot see: the caller
/// surveys the parts (`edge_rms`), selects the median over them and runs each part with it.
struct PointsDetectHooks {
  /// Not NaN (>= 0, +inf for none): the whole cloud's median of the edge test's candidate rms,
  /// used instead of this run's own median. NaN: this run's own.
  double edge_rms_median = std::numeric_limits<double>::quiet_NaN();
  /// Not null (N values): a survey. The run stops after the height passes and writes, per row,
  /// the first height pass's surroundings rms where it gave a verdict (the values that median is
  /// over; NaN for other rows, rows merged into another and when the height test is off); the
  /// other outputs then hold that intermediate state, the summary has no plane and no defects.
  double* edge_rms = nullptr;
};

/// MIEM on an unorganized cloud, writing into `out`. Non-finite rows are INVALID. Throws
/// std::invalid_argument on bad parameters, fewer than 3 finite points, spacing 0, or a null
/// `out.labels`, and CoordinateRangeError for a finite coordinate outside SPEC's range. Deterministic for any thread count. `hooks`: internal (PointsDetectHooks).
template <typename T>
PointsDetectSummary detect_points(const PointsView<T>& points, const PointsDetectParams& params,
                                  const PointsOutput& out, const PointsDetectHooks& hooks = {});

/// The survey behind PointsDetectHooks::edge_rms (internal, miem.dask): writes to `rms` (N
/// values) per row the first height pass's surroundings rms where it gave a verdict, NaN
/// elsewhere. Runs detect_points up to its height passes only.
template <typename T>
void edge_rms_survey(const PointsView<T>& points, const PointsDetectParams& params, double* rms);

/// One-call unorganized detection with owned outputs.
template <typename T>
PointsDetectResult detect_points(const PointsView<T>& points, const PointsDetectParams& params);

}  // namespace miem
