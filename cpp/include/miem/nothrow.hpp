// No-throw C++ API for controllers built without exceptions: every call returns a Status
// (a code plus a static message naming the argument) instead of throwing. Arguments are checked
// up front; anything that still escapes (std::bad_alloc) is caught and reported.
#pragma once

#include <cstdint>
#include <optional>

#include "miem/organized.hpp"
#include "miem/params.hpp"
#include "miem/plane.hpp"
#include "miem/status.hpp"
#include "miem/views.hpp"

namespace miem {

/// params.check(): the same rules and message as miem::validate, without throwing.
inline Status check_params(const DetectParams& params) noexcept { return params.check(); }

/// No-throw counterparts of the throwing API. The throwing functions stay the reference; these
/// check their arguments first and never let an exception escape.
namespace nothrow {

/// Eigenvalue plane fit of the finite points of `points` into `*out`.
/// kTooFewPoints / kDegenerate as fit_plane_eigen would throw; kInvalidInput for a null view.
template <typename T>
Status fit_plane_eigen(const PointsView<T>& points, Plane* out, int num_threads = 0) noexcept;

/// Least-squares z = a x + b y + c fit, reported as a Plane (see fit_plane_lstsq).
template <typename T>
Status fit_plane_lstsq(const PointsView<T>& points, Plane* out, int num_threads = 0) noexcept;

/// Constructs a detector in `*out` after checking `params`. Construct once, at start-up.
Status make_detector(const DetectParams& params, std::optional<OrganizedDetector>* out) noexcept;

/// Organized detection over a strided view of caller memory (no copy), as
/// OrganizedDetector::run, writing labels (and the optional outputs) into `out` and the
/// iteration count, MIEM plane and defects into `*summary`. kInvalidInput for an empty grid, a
/// null `out.labels` / `summary` or coordinates outside SPEC's range (kCoordinateMax,
/// kCoordinateMin; `out` then holds no result); kTooFewPoints when the grid has fewer than 3
/// finite points.
/// The defect list is the only allocation of a run on a grid of an already-seen size.
template <typename T>
Status detect(OrganizedDetector& detector, const GridView<T>& grid, const OrganizedOutput& out,
              DetectSummary* summary) noexcept;

}  // namespace nothrow
}  // namespace miem
