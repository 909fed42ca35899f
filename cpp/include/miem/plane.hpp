// Plane fits: the eigenvalue method (paper eq. 4-17) and the least-squares baseline z = ax + by + c.
#pragma once

#include <cstdint>

#include <Eigen/Core>

#include "miem/views.hpp"

namespace miem {

/// A plane n . p + d = 0 with |n| = 1, oriented so that n_z > 0 (if n_z is zero, that is
/// |n_z| <= 1e-6, the first component that is not zero in that sense is positive).
struct Plane {
  Eigen::Vector3d normal = Eigen::Vector3d::Zero();
  double d = 0.0;
  Eigen::Vector3d centroid = Eigen::Vector3d::Zero();
  double rms = 0.0;            ///< RMS orthogonal distance of the fitted points (paper's "delta")
  std::int64_t n_points = 0;   ///< finite points used
  Eigen::Vector3d eigenvalues = Eigen::Vector3d::Zero();  ///< of the scatter matrix, ascending

  /// Signed distance of p from the plane (positive on the side the normal points to).
  double signed_distance(const Eigen::Vector3d& p) const { return normal.dot(p) + d; }
};

/// Centred first and second moments of a point set, mergeable in a fixed order (Chan et al.),
/// so block-parallel sums give the same result for any thread count.
struct Moments {
  std::int64_t n = 0;
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  Eigen::Matrix3d scatter = Eigen::Matrix3d::Zero();  ///< sum (p - mean)(p - mean)^T

  /// Merge another set of moments into this one.
  void merge(const Moments& other);
};

/// Why a plane could not be fitted.
enum class PlaneStatus : std::uint8_t {
  kOk = 0,
  kTooFewPoints = 1,  ///< fewer than 3 finite points
  kDegenerate = 2,    ///< all points equal or collinear (scatter rank < 2)
};

/// Human-readable text for a status.
const char* to_string(PlaneStatus status) noexcept;

/// Orient a unit normal: n_z > 0, or if |n_z| <= 1e-6 the first component larger than that in
/// magnitude positive (a vertical plane's n_z is a rounding residue of either sign).
Eigen::Vector3d orient_normal(const Eigen::Vector3d& n) noexcept;

/// Eigenvalue plane from moments (SelfAdjointEigenSolver). No-throw.
PlaneStatus eigen_plane_from_moments(const Moments& m, Plane* out) noexcept;

/// Least-squares z = a x + b y + c plane from moments (centred normal equations). No-throw.
PlaneStatus lstsq_plane_from_moments(const Moments& m, Plane* out) noexcept;

/// Moments of the finite points of a view (non-finite points are skipped). Block-parallel over
/// `num_threads` (0 = all available); the result does not depend on the thread count.
template <typename T>
Moments compute_moments(const PointsView<T>& points, int num_threads = 0);

/// Eigenvalue plane fit of the finite points. Throws std::invalid_argument when fewer than 3
/// finite points or when they are degenerate.
template <typename T>
Plane fit_plane_eigen(const PointsView<T>& points, int num_threads = 0);

/// Least-squares z = a x + b y + c fit of the finite points, reported as a Plane. Throws
/// std::invalid_argument when fewer than 3 finite points or when x, y are collinear.
template <typename T>
Plane fit_plane_lstsq(const PointsView<T>& points, int num_threads = 0);

}  // namespace miem
