// Grinding targets from defects: selection, merging, path order and tool poses in the robot's base
// frame (docs/SPEC.md "Grinding targets"). One implementation for controllers and for Python.
#pragma once

#include <cstdint>
#include <limits>
#include <vector>

#include <Eigen/Core>

#include "miem/nothrow.hpp"
#include "miem/organized.hpp"
#include "miem/views.hpp"

namespace miem {

/// Which point of a defect a target is placed on.
enum class TargetAnchor : std::uint8_t {
  kPeak = 0,      ///< the member of largest |height| (first in index order on ties)
  kCentroid = 1,  ///< the mean of the members (in the base frame)
};

/// Rigid transforms base <- scan, row-major 4x4 doubles, contiguous: either one for the whole
/// scan (count 1) or one per profile (count = grid rows; a robot-swept scanner).
struct TransformsView {
  const double* data = nullptr;
  std::ptrdiff_t count = 0;
};

/// How defects become targets. Lengths are in the scan's units.
struct TargetParams {
  TargetAnchor anchor = TargetAnchor::kPeak;
  bool protrusions = true;        ///< target protrusions (burrs, spatter)
  bool pits = false;              ///< target pits (not ground by default)
  bool isolated = false;          ///< target isolated returns (stray points, dust)
  double min_height = 0.0;        ///< keep defects with |peak_height| >= this
  double min_area = 0.0;          ///< keep defects with area >= this (units^2)
  int min_count = 1;              ///< keep defects with at least this many points
  double tool_radius = 0.0;       ///< merge defects whose anchors are closer than this (0: off)
  double edge_clearance = 0.0;    ///< drop targets closer than this to an EDGE point (0: off)
  double standoff = 0.0;          ///< tool pose = anchor + standoff * normal
  double approach = 20.0;         ///< approach point = pose + approach * normal
  double retract = 20.0;          ///< retract point = pose + retract * normal
  /// Direction from the surface toward the scanner, in the scan frame: normals are flipped to
  /// have a positive component along it.
  Eigen::Vector3d toward_sensor{0.0, 0.0, 1.0};
  /// Tool x reference in the base frame; NaN: the scan direction (the scan frame's y axis, the
  /// direction in which profiles follow each other, rotated into the base frame).
  Eigen::Vector3d x_reference = Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN());
  /// Start of the path in the base frame; NaN: the path starts at the deepest target.
  Eigen::Vector3d start = Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN());
  bool order = true;              ///< nearest neighbour + 2-opt; false: deepest first
  double point_area = 0.0;        ///< > 0: area of one point (clouds); 0: from grid neighbours
  /// Region of interest: a polygon in the scan frame's x-y plane (empty: everywhere). A defect
  /// is inside when its peak point is.
  std::vector<Eigen::Vector2d> roi_polygon;
};

/// Throws std::invalid_argument naming the offending field.
void validate(const TargetParams& params);

/// One grinding target, in the base frame.
struct Target {
  Eigen::Vector3d point = Eigen::Vector3d::Zero();         ///< anchor on the defect
  Eigen::Vector3d point_scan = Eigen::Vector3d::Zero();    ///< the same in scan coordinates
  Eigen::Vector3d normal = Eigen::Vector3d::Zero();        ///< unit surface normal, toward sensor
  Eigen::Matrix3d rotation = Eigen::Matrix3d::Identity();  ///< columns: tool x, y, z = -normal
  Eigen::Vector3d position = Eigen::Vector3d::Zero();      ///< tool pose origin (with stand-off)
  Eigen::Vector3d approach_point = Eigen::Vector3d::Zero();
  Eigen::Vector3d retract_point = Eigen::Vector3d::Zero();
  Eigen::Vector4d quaternion = Eigen::Vector4d(1, 0, 0, 0);  ///< (w, x, y, z) of rotation, w >= 0
  Eigen::Vector3d abc_deg = Eigen::Vector3d::Zero();  ///< KUKA A, B, C: R = Rz(A) Ry(B) Rx(C)
  double depth = 0.0;    ///< peak height of the deepest member defect (signed; NaN if none)
  double area = 0.0;     ///< footprint of the member points in their tangent planes (units^2)
  double volume = 0.0;   ///< sum of |height| * area over members on the peak's side (units^3)
  int count = 0;         ///< member points
  std::int64_t peak_index = -1;   ///< flat index of the deepest defect's peak point
  std::vector<int> defect_ids;    ///< ids of the merged defects, ascending
};

/// Why defects were not targeted (each defect is counted once, at the first rule it fails).
struct TargetRejections {
  int kind = 0;     ///< a kind not selected (pits, isolated by default)
  int height = 0;   ///< |peak_height| < min_height
  int size = 0;     ///< count < min_count or area < min_area
  int roi = 0;      ///< peak outside the region of interest
  int edge = 0;     ///< anchor within edge_clearance of an EDGE point
};

/// The plan: targets in path order.
struct TargetPlan {
  std::vector<Target> targets;
  double path_length = 0.0;  ///< through the anchors in order, from `start` when given
  int defects_in = 0;        ///< defects offered
  int defects_used = 0;      ///< defects that ended in a target
  TargetRejections rejected;
};

/// Plans grinding targets from the defects of an organized detection (or of a cloud viewed as
/// one row, with params.point_area > 0). `labels` and `height` are grid.rows * grid.cols,
/// row-major; `roi_mask` (optional, same size) keeps defects whose peak cell is non-zero.
/// Throws std::invalid_argument for a bad parameter, a transform that is not rigid or not finite
/// ("T_base_sensor: ..."), or a defect index outside the grid.
template <typename T>
TargetPlan plan_targets(const GridView<T>& grid, const std::uint8_t* labels, const double* height,
                        const std::vector<Defect>& defects, const TransformsView& T_base_sensor,
                        const TargetParams& params, const std::uint8_t* roi_mask = nullptr);

/// Checks that every transform is finite, rigid (orthonormal rotation, det +1, within 1e-6) with
/// a last row 0 0 0 1. Returns nullptr when fine, else a static message naming T_base_sensor.
const char* check_transforms(const TransformsView& T_base_sensor, std::ptrdiff_t rows) noexcept;

/// Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix.
Eigen::Vector4d quaternion_from_rotation(const Eigen::Matrix3d& R) noexcept;

/// KUKA A, B, C in degrees (R = Rz(A) Ry(B) Rx(C)); at B = +-90 degrees A is 0.
Eigen::Vector3d abc_from_rotation(const Eigen::Matrix3d& R) noexcept;

/// Orders points into a short open path: nearest neighbour from `start` (NaN: from point 0),
/// then 2-opt until no reversal shortens it. Returns the visiting order.
std::vector<int> order_path(const std::vector<Eigen::Vector3d>& points,
                            const Eigen::Vector3d& start);

namespace nothrow {

/// plan_targets without exceptions: kInvalidParameter (params, transforms), kInvalidInput (null
/// arrays, defect indices outside the grid), kOutOfMemory.
template <typename T>
Status plan_targets(const GridView<T>& grid, const std::uint8_t* labels, const double* height,
                    const std::vector<Defect>& defects, const TransformsView& T_base_sensor,
                    const TargetParams& params, TargetPlan* out,
                    const std::uint8_t* roi_mask = nullptr) noexcept;

}  // namespace nothrow
}  // namespace miem
