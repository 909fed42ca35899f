// The no-throw API: arguments are checked up front (static messages, no allocation), and the
// throwing core is called inside a catch-all so that nothing escapes into -fno-exceptions code.
#include "miem/nothrow.hpp"

#include <cmath>
#include <new>
#include <stdexcept>

namespace miem {

namespace {

Status from_plane_status(PlaneStatus st, bool lstsq) {
  switch (st) {
    case PlaneStatus::kOk:
      return {};
    case PlaneStatus::kTooFewPoints:
      return {StatusCode::kTooFewPoints, "points: fewer than 3 finite points"};
    case PlaneStatus::kDegenerate:
      return {StatusCode::kDegenerate,
              lstsq ? "points: the x, y coordinates are collinear or equal: no z = ax + by + c"
                    : "points: all equal or collinear: no plane"};
  }
  return {StatusCode::kInternal, "points: unknown plane status"};
}

Status from_current_exception() noexcept {
  try {
    throw;
  } catch (const std::bad_alloc&) {
    return {StatusCode::kOutOfMemory, "out of memory"};
  } catch (const std::invalid_argument&) {
    // Every argument was checked before the call: reaching this is a bug.
    return {StatusCode::kInternal, "unexpected invalid_argument after the checks"};
  } catch (...) {
    return {StatusCode::kInternal, "unexpected exception"};
  }
}

template <typename T>
Status fit_plane_impl(const PointsView<T>& points, Plane* out, int num_threads,
                      bool lstsq) noexcept {
  if (out == nullptr) return {StatusCode::kInvalidInput, "out: must not be null"};
  if (points.size < 0 || (points.size > 0 && points.data == nullptr)) {
    return {StatusCode::kInvalidInput, "points: null data"};
  }
  if (num_threads < 0) return {StatusCode::kInvalidParameter, "num_threads: must be >= 0"};
  try {
    const Moments m = compute_moments(points, num_threads);
    return from_plane_status(
        lstsq ? lstsq_plane_from_moments(m, out) : eigen_plane_from_moments(m, out), lstsq);
  } catch (...) {
    return from_current_exception();
  }
}

}  // namespace

const char* to_string(StatusCode code) noexcept {
  switch (code) {
    case StatusCode::kOk:
      return "ok";
    case StatusCode::kInvalidParameter:
      return "invalid parameter";
    case StatusCode::kInvalidInput:
      return "invalid input";
    case StatusCode::kTooFewPoints:
      return "too few points";
    case StatusCode::kDegenerate:
      return "degenerate";
    case StatusCode::kWrongWidth:
      return "wrong width";
    case StatusCode::kEmptyProfile:
      return "empty profile";
    case StatusCode::kFinished:
      return "finished";
    case StatusCode::kOutOfMemory:
      return "out of memory";
    case StatusCode::kInternal:
      return "internal error";
  }
  return "unknown";
}

namespace nothrow {

template <typename T>
Status fit_plane_eigen(const PointsView<T>& points, Plane* out, int num_threads) noexcept {
  return fit_plane_impl(points, out, num_threads, false);
}

template <typename T>
Status fit_plane_lstsq(const PointsView<T>& points, Plane* out, int num_threads) noexcept {
  return fit_plane_impl(points, out, num_threads, true);
}

Status make_detector(const DetectParams& params, std::optional<OrganizedDetector>* out) noexcept {
  if (out == nullptr) return {StatusCode::kInvalidInput, "out: must not be null"};
  const Status st = check_params(params);
  if (!st.ok()) return st;
  try {
    out->emplace(params);
  } catch (...) {
    return from_current_exception();
  }
  return {};
}

template <typename T>
Status detect(OrganizedDetector& detector, const GridView<T>& grid, const OrganizedOutput& out,
              DetectSummary* summary) noexcept {
  if (summary == nullptr) return {StatusCode::kInvalidInput, "summary: must not be null"};
  if (out.labels == nullptr) return {StatusCode::kInvalidInput, "out.labels: must not be null"};
  if (grid.data == nullptr || grid.rows < 1 || grid.cols < 1) {
    return {StatusCode::kInvalidInput, "grid: must have at least one row and one column"};
  }
  // The core throws on fewer than 3 finite points: check first (stops at the third one).
  int n_finite = 0;
  for (std::ptrdiff_t r = 0; r < grid.rows && n_finite < 3; ++r)
    for (std::ptrdiff_t c = 0; c < grid.cols && n_finite < 3; ++c) n_finite += grid.finite(r, c);
  if (n_finite < 3) return {StatusCode::kTooFewPoints, "grid: fewer than 3 finite points"};
  try {
    *summary = detector.run(grid, out);
  } catch (const CoordinateRangeError&) {  // (found in the pass that reads the grid anyway)
    return {StatusCode::kInvalidInput,
            "grid: finite coordinates reach a magnitude above 1e18, or the largest is below "
            "1e-18: outside the range the method computes without overflow; rescale the points"};
  } catch (...) {
    return from_current_exception();
  }
  return {};
}

template Status fit_plane_eigen<float>(const PointsView<float>&, Plane*, int) noexcept;
template Status fit_plane_eigen<double>(const PointsView<double>&, Plane*, int) noexcept;
template Status fit_plane_lstsq<float>(const PointsView<float>&, Plane*, int) noexcept;
template Status fit_plane_lstsq<double>(const PointsView<double>&, Plane*, int) noexcept;
template Status detect<float>(OrganizedDetector&, const GridView<float>&, const OrganizedOutput&,
                              DetectSummary*) noexcept;
template Status detect<double>(OrganizedDetector&, const GridView<double>&,
                               const OrganizedOutput&, DetectSummary*) noexcept;

}  // namespace nothrow
}  // namespace miem
