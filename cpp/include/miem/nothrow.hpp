// No-throw C++ API for controllers built without exceptions: every call returns a Status
// (a code plus a static message naming the argument) instead of throwing. Arguments are checked
// up front; anything that still escapes (std::bad_alloc) is caught and reported.
#pragma once

#include <cstdint>
#include <optional>

#include "miem/organized.hpp"
#include "miem/plane.hpp"
#include "miem/views.hpp"

namespace miem {

/// What went wrong, if anything.
enum class StatusCode : std::uint8_t {
  kOk = 0,
  kInvalidParameter = 1,  ///< a DetectParams field (or the stream width) is out of range
  kInvalidInput = 2,      ///< null data or output, an empty view
  kTooFewPoints = 3,      ///< fewer than 3 finite points
  kDegenerate = 4,        ///< points all equal or collinear: no plane
  kWrongWidth = 5,        ///< stream: profile size differs from the stream width (rejected)
  kEmptyProfile = 6,      ///< stream: no finite point (taken as a row of dropouts)
  kFinished = 7,          ///< stream: push after flush; call reset() to start a new stream
  kOutOfMemory = 8,       ///< an allocation failed
  kInternal = 9,          ///< an unexpected exception (a bug: please report it)
};

/// A status: a code and a static, human-readable message (never freed, never allocated).
struct Status {
  StatusCode code = StatusCode::kOk;
  const char* message = "ok";

  /// True for StatusCode::kOk only.
  bool ok() const noexcept { return code == StatusCode::kOk; }
  explicit operator bool() const noexcept { return ok(); }
};

/// "ok", "invalid parameter", ... for a code.
const char* to_string(StatusCode code) noexcept;

/// Checks detection parameters without throwing (the same rules as miem::validate).
Status check_params(const DetectParams& params) noexcept;

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
/// iteration count, MIEM plane and defects into `*summary`. kInvalidInput for an empty grid or a
/// null `out.labels` / `summary`; kTooFewPoints when the grid has fewer than 3 finite points.
/// The defect list is the only allocation of a run on a grid of an already-seen size.
template <typename T>
Status detect(OrganizedDetector& detector, const GridView<T>& grid, const OrganizedOutput& out,
              DetectSummary* summary) noexcept;

}  // namespace nothrow
}  // namespace miem
