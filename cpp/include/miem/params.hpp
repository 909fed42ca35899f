// Detection parameters, defined once per scope, each with one check(). The throwing API throws
// the check's message, the no-throw API returns it. Defaults are the recommended preset (the best
// measured configuration, docs/SPEC.md "Parameters"); paper_params() is the paper's method.
// Each type lists its fields once, in visit_fields() (name, unit, help): the Python bindings,
// miem.DetectParams, the command line, `miem config` and miem.dask are generated from it, so a
// new field is its member, its visit_fields() entry (cpp/src/params.cpp fails to compile when a
// member has none), its check, SPEC and README.
#pragma once

#include <cstdint>
#include <optional>
#include <vector>

#include "miem/status.hpp"

namespace miem {

/// Which cells get a local height (METHOD section 6).
enum class HeightMode : std::uint8_t {
  kAll = 0,       ///< every finite cell (running window sums, O(1) per cell)
  kAbnormal = 1,  ///< ABNORMAL cells only (direct window fits); others NaN. Much faster.
};

/// One field of a parameter type as its visit_fields() lists it (static strings).
struct FieldInfo {
  const char* name;  ///< the member's name (and the Python / command-line name of plain fields)
  const char* unit;  ///< "deg", "cells", "length", "k x rms", ...; "" when it has none
  const char* help;  ///< one sentence for users: what it does, its range, what "off" is
};

/// theta0_auto's survey reads 180 - angle below this many degrees as 0: a straight triple's
/// angle is round-off, which differs between implementations (SPEC "theta0='auto'").
inline constexpr double kAutoTheta0Straight = 1e-3;

/// The angle test and its iteration: shared by organized batch detection, the profile stream
/// and unorganized clouds.
struct AngleParams {
  double theta0_deg = 90.0;       ///< degrees: flag a direction when its angle <= theta0 (0..180 open)
  bool theta0_auto = false;       ///< derive theta0 from the scan's own angles (grids only, SPEC.md)
  std::vector<int> scales{1, 2};  ///< neighbour scales (each >= 1): cells, or s * min_step on clouds
  int min_directions = 0;         ///< 0: all available directions; else 1..number of directions
  int max_iterations = 10;        ///< angle passes at most, and height passes at most (>= 1)

  /// theta0 (unless theta0_auto), scales, min_directions >= 0, max_iterations.
  Status check() const noexcept;

  /// Calls v(FieldInfo, &AngleParams::member) for every field, in declaration order.
  template <class V>
  static constexpr void visit_fields(V&& v) {
    v(FieldInfo{"theta0_deg", "deg", "angle threshold in degrees: a direction is flagged when its "
                "angle is at most theta0 (0 < theta0 < 180)"}, &AngleParams::theta0_deg);
    v(FieldInfo{"theta0_auto", "", "derive theta0 from the scan's own angles (grids only)"},
      &AngleParams::theta0_auto);
    v(FieldInfo{"scales", "cells", "neighbour distances: (1, 2) also finds defects two points "
                "wide (on clouds: the s-th point along a direction)"}, &AngleParams::scales);
    v(FieldInfo{"min_directions", "directions", "flagged directions needed for ABNORMAL, 1-4 "
                "(clouds: 1-K); 0: all available directions"}, &AngleParams::min_directions);
    v(FieldInfo{"max_iterations", "passes", "maximum detection passes; each pass removes the "
                "points found and judges the rest again (and at most as many height passes)"},
      &AngleParams::max_iterations);
  }
};

/// Organized grids only (batch and stream): the neighbour search along the grid's four
/// directions, the local height window and the height test.
struct GridParams {
  int max_gap = 1;                ///< cells: unusable cells that may be skipped to find a neighbour
  double min_step = -1.0;         ///< length (scan units): < 0 off; else neighbours >= s * min_step away
  bool min_step_auto = true;      ///< min_step from the grid's spacing and noise (auto_min_step,
                                  ///< SPEC "min_step='auto'"); then min_step must stay < 0
  int max_reach = 32;             ///< cells: extra cells searched for min_step (used only with it)
  int window = 21;                ///< cells: side of the height-plane window (odd >= 3)
  HeightMode height_mode = HeightMode::kAll;  ///< which cells get a height
  double height_abs = 0.0;        ///< length: > 0 height test, |height| above this is ABNORMAL
  double height_k = 4.5;          ///< multiple of the window rms: > 0 height test, |h| > k rms
  int edge_extent = 12;           ///< cells: height test also on EDGE groups this compact
  double edge_k = 4.0;            ///< multiple of the sub-window rms: > 0 edge test (SPEC "Edge test")
  int edge_window = 15;           ///< cells: edge test sub-window side (odd >= 3; half-size / 2)
  double z_resolution = -1.0;     ///< length: the scan's z step; < 0 off; the rms tolerances of
                                  ///< the height and edge tests are at least 1.5 x this
  bool z_resolution_auto = true;  ///< z_resolution measured on the min_step sample rows
                                  ///< (SPEC "z_resolution"); then z_resolution must stay < 0
  double z_noise = -1.0;          ///< length: the scan's z noise sigma; < 0 off; the edge test's
                                  ///< tolerances are at least 2 x this
  bool z_noise_auto = true;       ///< z_noise measured as min_step "auto" measures its sigma
                                  ///< (SPEC "z_noise"); then z_noise must stay < 0

  /// True when the height test is on (height_abs > 0 or height_k > 0).
  bool height_test() const noexcept { return height_abs > 0.0 || height_k > 0.0; }

  /// True when the edge test is on (edge_k > 0).
  bool edge_test() const noexcept { return edge_k > 0.0; }

  /// Every field's range (min_step finite and < 0 with min_step_auto, height_abs / height_k
  /// finite, edge_extent >= 0, edge_k finite >= 0, edge_window odd >= 3, z_resolution and
  /// z_noise finite and < 0 with their _auto, ...).
  Status check() const noexcept;

  /// Calls v(FieldInfo, &GridParams::member) for every field, in declaration order.
  template <class V>
  static constexpr void visit_fields(V&& v) {
    v(FieldInfo{"max_gap", "cells", "missing or removed cells that may be skipped to reach a "
                "neighbour (>= 0)"}, &GridParams::max_gap);
    v(FieldInfo{"min_step", "length", "neighbours at least s * min_step away; < 0: off"},
      &GridParams::min_step);
    v(FieldInfo{"min_step_auto", "", "min_step from the grid's spacing and noise (SPEC "
                "\"min_step='auto'\"); min_step must then be < 0"}, &GridParams::min_step_auto);
    v(FieldInfo{"max_reach", "cells", "with min_step: how many cells beyond scale + max_gap the "
                "neighbour search may go (>= 1)"}, &GridParams::max_reach);
    v(FieldInfo{"window", "cells", "side of the square (odd >= 3) whose NORMAL points give the "
                "local plane for heights and the height test"}, &GridParams::window);
    v(FieldInfo{"height_mode", "", "which cells get a height: all finite cells or ABNORMAL "
                "ones only (faster)"}, &GridParams::height_mode);
    v(FieldInfo{"height_abs", "length", "height test: |height| above this is ABNORMAL; <= 0: "
                "off"}, &GridParams::height_abs);
    v(FieldInfo{"height_k", "k x rms", "height test: |height| above k times the window plane's "
                "rms is ABNORMAL; <= 0: off"}, &GridParams::height_k);
    v(FieldInfo{"edge_extent", "cells", "with the height test: EDGE groups whose bounding box is "
                "at most this long are compact (a defect's halo) and height-tested too; longer "
                "ones are feature lines (>= 0)"}, &GridParams::edge_extent);
    v(FieldInfo{"edge_k", "k x rms", "edge test (SPEC 'Edge test'): a point proud of a feature "
                "line or outline by more than k times its sub-window plane's rms (at least "
                "min_step / 2 with a min_step, 2 z_noise) is ABNORMAL; 0: off"}, &GridParams::edge_k);
    v(FieldInfo{"edge_window", "cells", "with the edge test: side of its one-sided sub-windows "
                "(odd >= 3)"}, &GridParams::edge_window);
    v(FieldInfo{"z_resolution", "length", "the scan's z step (quantisation): the height test's "
                "k x rms and the edge test's tolerances are at least 1.5 times it; < 0: off"},
      &GridParams::z_resolution);
    v(FieldInfo{"z_resolution_auto", "", "z_resolution measured on the grid (SPEC "
                "\"z_resolution\"); z_resolution must then be < 0"},
      &GridParams::z_resolution_auto);
    v(FieldInfo{"z_noise", "length", "the scan's z noise (sigma, profile jitter included): the "
                "edge test's tolerances are at least 2 times it; < 0: off"}, &GridParams::z_noise);
    v(FieldInfo{"z_noise_auto", "", "z_noise measured on the grid as min_step 'auto' measures "
                "it (SPEC \"z_noise\"); z_noise must then be < 0"}, &GridParams::z_noise_auto);
  }
};

/// Unorganized clouds only: the neighbourhood and the K tangent-plane directions.
struct CloudParams {
  std::optional<double> radius;    ///< length: neighbourhood radius (> 0); default 5 * spacing
  int num_directions = 4;          ///< K tangent-plane directions, 2..8 (flags are 8 bits)
  std::optional<double> min_step;  ///< length: shortest tangent offset (>= 0); default 0.5 * spacing
  std::optional<double> link;      ///< length: defect linking distance (> 0); default radius
  HeightMode height_mode = HeightMode::kAll;  ///< which points get a height
  int min_group = 40;              ///< points: 0 off; else >= 3, smaller floating groups ABNORMAL
  double height_abs = 0.0;         ///< length: > 0 height test, |height| above this is ABNORMAL
  double height_k = 7.0;           ///< multiple of the local rms: > 0 height test, |h| > k rms
  double edge_extent = 12.0;       ///< spacings: height test also on EDGE groups this compact
  /// multiple of the surroundings rms: > 0 the height test's isolated-point rule (a point alone
  /// above this, its inner neighbours as loose as the rms says, is ABNORMAL), 0 off
  double isolated_k = 5.0;
  std::optional<double> height_radius;  ///< length: height-plane radius (> 0); default 2 * radius
  double merge_distance = 0.0;     ///< length: points this close (>= 0; 0: equal) are one point
  /// multiple of the sector rms: > 0 edge test (SPEC "Unorganized clouds: edge test"; default 4,
  /// chosen on the tune split of the held-out-style clouds), 0 off
  double edge_k = 4.0;
  /// length: edge-test sector radius (> 0; the test also judges at 1.5 times it); default
  /// height_radius
  std::optional<double> edge_radius;
  /// length: the cloud's point spacing (> 0), the unit of the defaults and of edge_extent;
  /// default: the median nearest-neighbour distance of the distinct points (point_spacing).
  std::optional<double> spacing;

  /// radius, num_directions, min_step, link, height_mode, min_group, the height test,
  /// height_radius, merge_distance, spacing, the edge test.
  Status check() const noexcept;

  /// Calls v(FieldInfo, &CloudParams::member) for every field, in declaration order.
  template <class V>
  static constexpr void visit_fields(V&& v) {
    v(FieldInfo{"radius", "length", "neighbourhood radius (> 0); None: 5 x the median point "
                "spacing"}, &CloudParams::radius);
    v(FieldInfo{"num_directions", "directions", "K, the tangent-plane directions tested, 2-8"},
      &CloudParams::num_directions);
    v(FieldInfo{"min_step", "length", "shortest tangent-plane offset of a neighbour (>= 0); "
                "None: 0.5 x the point spacing"}, &CloudParams::min_step);
    v(FieldInfo{"link", "length", "ABNORMAL points this close belong to one defect (> 0); None: "
                "radius"}, &CloudParams::link);
    v(FieldInfo{"height_mode", "", "which points get a height: all finite points or ABNORMAL "
                "ones only (faster)"}, &CloudParams::height_mode);
    v(FieldInfo{"min_group", "points", "0 (off) or >= 3: groups of usable points (linked within "
                "radius) smaller than this are ABNORMAL (floating clusters)"},
      &CloudParams::min_group);
    v(FieldInfo{"height_abs", "length", "height test: |height| above this is ABNORMAL; <= 0: "
                "off"}, &CloudParams::height_abs);
    v(FieldInfo{"height_k", "k x rms", "height test: |height| above k times the local plane's "
                "rms is ABNORMAL; <= 0: off"}, &CloudParams::height_k);
    v(FieldInfo{"edge_extent", "spacings", "with the height test: EDGE groups at most this many "
                "spacings across are compact and height-tested too (>= 0)"},
      &CloudParams::edge_extent);
    v(FieldInfo{"isolated_k", "k x rms", "with the height test: a point alone farther than k "
                "times the rms of its surroundings plane, whose neighbours within radius lie "
                "about that plane as loosely as the rms says (a low spike or pit one point "
                "wide), is ABNORMAL; 0: off"}, &CloudParams::isolated_k);
    v(FieldInfo{"height_radius", "length", "radius of the height planes (> 0); None: 2 x "
                "radius"}, &CloudParams::height_radius);
    v(FieldInfo{"merge_distance", "length", "duplicate points: rows this close (>= 0; 0: equal "
                "coordinates) are one point, detected once and labelled alike"},
      &CloudParams::merge_distance);
    v(FieldInfo{"edge_k", "k x rms", "edge test (SPEC 'Unorganized clouds: edge test'): a point "
                "proud of a feature line or outline by more than k times a one-sided sector's "
                "plane rms is ABNORMAL; 0: off"}, &CloudParams::edge_k);
    v(FieldInfo{"edge_radius", "length", "with the edge test: radius of its sectors (> 0; the "
                "test also judges at 1.5 times it); None: height_radius"},
      &CloudParams::edge_radius);
    v(FieldInfo{"spacing", "length", "the cloud's point spacing (> 0), the unit of the defaults "
                "and of edge_extent; None: the median nearest-neighbour distance"},
      &CloudParams::spacing);
  }
};

/// Parameters of organized detection (OrganizedDetector, detect_organized, ProfileStream).
/// Default-constructed: the recommended preset.
struct DetectParams : AngleParams, GridParams {
  int num_threads = 0;  ///< 0: all available; the labels never depend on it

  /// AngleParams::check, GridParams::check, min_directions <= 4, num_threads >= 0.
  Status check() const noexcept;

  /// The fields of this type itself (the bases list theirs).
  template <class V>
  static constexpr void visit_fields(V&& v) {
    v(FieldInfo{"num_threads", "threads", "0: all available; the labels never depend on it"},
      &DetectParams::num_threads);
  }
};

/// Parameters of unorganized detection (detect_points). Default-constructed: the recommended
/// preset (angle test, floating groups, height test). theta0_auto is not implemented for
/// clouds: check() rejects it.
struct PointsDetectParams : AngleParams, CloudParams {
  int num_threads = 0;  ///< 0: all available; results never depend on it

  /// AngleParams::check, CloudParams::check, min_directions <= num_directions, no theta0_auto.
  Status check() const noexcept;

  /// The fields of this type itself (the bases list theirs).
  template <class V>
  static constexpr void visit_fields(V&& v) {
    v(FieldInfo{"num_threads", "threads", "0: all available; results never depend on it"},
      &PointsDetectParams::num_threads);
  }
};

/// The recommended preset (== DetectParams{}): won the accuracy benchmark (bench/accuracy).
DetectParams recommended_params();

/// The paper's method exactly: theta0 75, scales {1}, no min_step, no height test, edge_extent 0,
/// no edge test.
DetectParams paper_params();

/// The paper's method on clouds: theta0 75, scales {1}, no height test, no floating groups.
PointsDetectParams paper_points_params();

/// Throws std::invalid_argument naming the offending field (the message of params.check()).
void validate(const DetectParams& params);

/// Throws std::invalid_argument naming the offending field (the message of params.check()).
void validate(const PointsDetectParams& params);

}  // namespace miem
