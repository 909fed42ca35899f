// The parameter checks (one per scope) and the presets. Messages are static and start with the
// field's name; the throwing API throws them, the no-throw API returns them.
#include "miem/params.hpp"

#include <cmath>
#include <cstddef>
#include <stdexcept>
#include <utility>

namespace miem {

namespace {
constexpr Status bad(const char* msg) { return Status{StatusCode::kInvalidParameter, msg}; }
constexpr Status kOkStatus{};

// Every member is listed in visit_fields(), checked at compile time: the number of members of
// an aggregate is the most initializers T{...} accepts (each copy-initialized from Any), and
// visit_fields() counts its entries. A member added without its entry fails the build here.
struct Any {
  template <class T>
  constexpr operator T() const noexcept {
    return T{};
  }
};

template <class T, class... A>
constexpr auto braces(int) -> decltype(T{std::declval<A>()...}, true) {
  return true;
}
template <class T, class... A>
constexpr bool braces(...) {
  return false;
}

template <class T, class... A>
constexpr std::size_t member_count() {
  if constexpr (braces<T, A..., Any>(0)) {
    return member_count<T, A..., Any>();
  } else {
    return sizeof...(A);
  }
}

template <class T>
constexpr std::size_t listed_count() {
  std::size_t n = 0;
  T::visit_fields([&n](const FieldInfo&, auto) { ++n; });
  return n;
}

static_assert(member_count<AngleParams>() == listed_count<AngleParams>(),
              "AngleParams: a member is missing from visit_fields()");
static_assert(member_count<GridParams>() == listed_count<GridParams>(),
              "GridParams: a member is missing from visit_fields()");
static_assert(member_count<CloudParams>() == listed_count<CloudParams>(),
              "CloudParams: a member is missing from visit_fields()");
}  // namespace

void throw_if_error(const Status& st) {
  if (!st.ok()) throw std::invalid_argument(st.message);
}

Status AngleParams::check() const noexcept {
  if (!theta0_auto &&
      (!std::isfinite(theta0_deg) || theta0_deg <= 0.0 || theta0_deg >= 180.0)) {
    return bad("theta0: must be a finite angle in degrees with 0 < theta0 < 180");
  }
  if (scales.empty()) return bad("scales: must not be empty");
  for (int s : scales) {
    if (s < 1) return bad("scales: every scale must be an integer >= 1");
  }
  if (min_directions < 0) return bad("min_directions: must be 0 (all) or >= 1");
  if (max_iterations < 1) return bad("max_iterations: must be >= 1");
  return kOkStatus;
}

Status GridParams::check() const noexcept {
  if (max_gap < 0) return bad("max_gap: must be an integer >= 0");
  if (!std::isfinite(min_step)) return bad("min_step: must be finite (negative = off)");
  if (min_step_auto && min_step >= 0.0) {
    return bad("min_step: a length with min_step_auto on; set min_step_auto = false to use it");
  }
  if (max_reach < 1) return bad("max_reach: must be an integer >= 1");
  if (window < 3 || window % 2 == 0) return bad("window: must be an odd integer >= 3");
  if (height_mode != HeightMode::kAll && height_mode != HeightMode::kAbnormal) {
    return bad("height_mode: must be kAll or kAbnormal");
  }
  if (!std::isfinite(height_abs)) return bad("height_abs: must be finite (<= 0 = off)");
  if (!std::isfinite(height_k)) return bad("height_k: must be finite (<= 0 = off)");
  if (edge_extent < 0) return bad("edge_extent: must be an integer >= 0");
  if (!(std::isfinite(edge_k) && edge_k >= 0.0)) {
    return bad("edge_k: must be finite and >= 0 (0 = off)");
  }
  if (edge_window < 3 || edge_window % 2 == 0) {
    return bad("edge_window: must be an odd integer >= 3");
  }
  if (!std::isfinite(z_resolution)) return bad("z_resolution: must be finite (negative = off)");
  if (z_resolution_auto && z_resolution >= 0.0) {
    return bad("z_resolution: a length with z_resolution_auto on; set z_resolution_auto = false "
               "to use it");
  }
  if (!std::isfinite(z_noise)) return bad("z_noise: must be finite (negative = off)");
  if (z_noise_auto && z_noise >= 0.0) {
    return bad("z_noise: a length with z_noise_auto on; set z_noise_auto = false to use it");
  }
  return kOkStatus;
}

Status CloudParams::check() const noexcept {
  if (radius && !(std::isfinite(*radius) && *radius > 0.0)) {
    return bad("radius: must be finite and > 0");
  }
  if (num_directions < 2 || num_directions > 8) {
    return bad("K: the number of directions must be an integer in 2..8");
  }
  if (min_step && !(std::isfinite(*min_step) && *min_step >= 0.0)) {
    return bad("min_step: must be finite and >= 0");
  }
  if (link && !(std::isfinite(*link) && *link > 0.0)) return bad("link: must be finite and > 0");
  if (height_mode != HeightMode::kAll && height_mode != HeightMode::kAbnormal) {
    return bad("height_mode: must be kAll or kAbnormal");
  }
  if (min_group < 0 || (min_group > 0 && min_group < 3)) {
    return bad("min_group: must be 0 (off) or an integer >= 3");
  }
  if (!std::isfinite(height_abs)) return bad("height_abs: must be finite (<= 0 = off)");
  if (!std::isfinite(height_k)) return bad("height_k: must be finite (<= 0 = off)");
  if (!(std::isfinite(edge_extent) && edge_extent >= 0.0)) {
    return bad("edge_extent: must be finite and >= 0");
  }
  if (height_radius && !(std::isfinite(*height_radius) && *height_radius > 0.0)) {
    return bad("height_radius: must be finite and > 0");
  }
  if (!(std::isfinite(merge_distance) && merge_distance >= 0.0)) {
    return bad("merge_distance: must be finite and >= 0");
  }
  if (spacing && !(std::isfinite(*spacing) && *spacing > 0.0)) {
    return bad("spacing: must be finite and > 0");
  }
  if (!(std::isfinite(edge_k) && edge_k >= 0.0)) {
    return bad("edge_k: must be finite and >= 0 (0 = off)");
  }
  if (edge_radius && !(std::isfinite(*edge_radius) && *edge_radius > 0.0)) {
    return bad("edge_radius: must be finite and > 0");
  }
  if (!(std::isfinite(isolated_k) && isolated_k >= 0.0)) {
    return bad("isolated_k: must be finite and >= 0 (0 = off)");
  }
  return kOkStatus;
}

Status DetectParams::check() const noexcept {
  if (Status st = AngleParams::check(); !st.ok()) return st;
  if (Status st = GridParams::check(); !st.ok()) return st;
  if (min_directions > 4) return bad("min_directions: must be 0 (all) or 1..4");
  if (num_threads < 0) return bad("num_threads: must be >= 0");
  return kOkStatus;
}

Status PointsDetectParams::check() const noexcept {
  if (theta0_auto) {
    return bad("theta0_auto: not implemented for unorganized clouds; give theta0 in degrees");
  }
  if (Status st = AngleParams::check(); !st.ok()) return st;
  if (Status st = CloudParams::check(); !st.ok()) return st;
  if (min_directions > num_directions) return bad("min_directions: must be 0 (all) or 1..K");
  if (num_threads < 0) return bad("num_threads: must be >= 0");
  return kOkStatus;
}

DetectParams recommended_params() { return DetectParams{}; }

DetectParams paper_params() {
  DetectParams p;
  p.theta0_deg = 75.0;
  p.scales = {1};
  p.height_abs = 0.0;
  p.height_k = 0.0;
  p.edge_extent = 0;
  p.min_step_auto = false;
  p.edge_k = 0.0;
  p.z_resolution_auto = false;
  p.z_noise_auto = false;
  return p;
}

PointsDetectParams paper_points_params() {
  PointsDetectParams p;
  p.theta0_deg = 75.0;
  p.scales = {1};
  p.min_group = 0;
  p.height_abs = 0.0;
  p.height_k = 0.0;
  p.edge_extent = 0.0;
  p.edge_k = 0.0;
  p.isolated_k = 0.0;
  return p;
}

void validate(const DetectParams& params) { throw_if_error(params.check()); }

void validate(const PointsDetectParams& params) { throw_if_error(params.check()); }

}  // namespace miem
