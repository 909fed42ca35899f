// Plane fits: known planes, orientation, far-from-origin precision, degenerate input, strided
// views, thread-count independence, and the least-squares baseline.
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <stdexcept>
#include <vector>

#include "miem/plane.hpp"

namespace {

// Points on z = a x + b y + c (+ noise), dense x y z.
std::vector<double> plane_points(int n, double a, double b, double c, double noise,
                                 double offset = 0.0, unsigned seed = 1) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-10.0, 10.0), e(-1.0, 1.0);
  std::vector<double> p;
  for (int i = 0; i < n; ++i) {
    const double x = u(rng), y = u(rng);
    p.insert(p.end(), {x + offset, y + offset, a * x + b * y + c + noise * e(rng) + offset});
  }
  return p;
}

miem::PointsView<double> view(const std::vector<double>& p) {
  return {p.data(), static_cast<std::ptrdiff_t>(p.size() / 3), 3, 1};
}

TEST(Plane, EigenRecoversAnExactPlane) {
  const auto pts = plane_points(200, 0.3, -0.2, 5.0, 0.0);
  const miem::Plane pl = miem::fit_plane_eigen(view(pts));
  const double norm = std::sqrt(0.09 + 0.04 + 1.0);
  EXPECT_NEAR(pl.normal.x(), -0.3 / norm, 1e-12);
  EXPECT_NEAR(pl.normal.y(), 0.2 / norm, 1e-12);
  EXPECT_NEAR(pl.normal.z(), 1.0 / norm, 1e-12);
  EXPECT_NEAR(pl.d, -5.0 / norm, 1e-10);
  EXPECT_NEAR(pl.rms, 0.0, 1e-10);
  EXPECT_EQ(pl.n_points, 200);
  EXPECT_NEAR(pl.signed_distance(Eigen::Vector3d(0, 0, 6.0)), 1.0 / norm, 1e-10);
}

TEST(Plane, NormalIsOriented) {
  // A vertical plane x = 2: n_z == 0, so the first non-zero component (x) is positive.
  std::vector<double> p = {2, 0, 0, 2, 1, 0, 2, 0, 1, 2, 3, 5, 2, -1, 2};
  const miem::Plane pl = miem::fit_plane_eigen(view(p));
  EXPECT_NEAR(pl.normal.x(), 1.0, 1e-12);
  EXPECT_NEAR(pl.d, -2.0, 1e-12);
  EXPECT_EQ(miem::orient_normal(Eigen::Vector3d(0, 0, -1)), Eigen::Vector3d(0, 0, 1));
  EXPECT_EQ(miem::orient_normal(Eigen::Vector3d(0, -1, 0)), Eigen::Vector3d(0, 1, 0));
}

TEST(Plane, FarFromOriginKeepsPrecision) {
  // Robot-base coordinates 1e5 mm away: centred moments keep the fit exact.
  const auto near_pts = plane_points(500, 0.1, 0.05, 0.0, 1e-3, 0.0, 7);
  const auto far_pts = plane_points(500, 0.1, 0.05, 0.0, 1e-3, 1e5, 7);
  const miem::Plane a = miem::fit_plane_eigen(view(near_pts));
  const miem::Plane b = miem::fit_plane_eigen(view(far_pts));
  EXPECT_NEAR((a.normal - b.normal).norm(), 0.0, 1e-9);
  EXPECT_NEAR(a.rms, b.rms, 1e-9);
}

TEST(Plane, RmsIsTheOrthogonalDeviation) {
  // z = +-h alternating on the plane z = 0: every point is h away.
  std::vector<double> p;
  for (int i = 0; i < 10; ++i)
    for (int j = 0; j < 10; ++j) p.insert(p.end(), {double(i), double(j), ((i + j) % 2) ? 0.1 : -0.1});
  const miem::Plane pl = miem::fit_plane_eigen(view(p));
  EXPECT_NEAR(pl.rms, 0.1, 1e-12);
  EXPECT_NEAR(pl.normal.z(), 1.0, 1e-12);
}

TEST(Plane, NonFinitePointsAreSkipped) {
  auto p = plane_points(50, 0.2, 0.1, 1.0, 0.0);
  const miem::Plane clean = miem::fit_plane_eigen(view(p));
  p.insert(p.end(), {std::nan(""), 0.0, 0.0, 1.0, INFINITY, 2.0});
  const miem::Plane dirty = miem::fit_plane_eigen(view(p));
  EXPECT_EQ(dirty.n_points, 50);
  EXPECT_NEAR((clean.normal - dirty.normal).norm(), 0.0, 1e-12);
}

TEST(Plane, DegenerateInputThrows) {
  std::vector<double> two = {0, 0, 0, 1, 1, 1};
  EXPECT_THROW(miem::fit_plane_eigen(view(two)), std::invalid_argument);
  std::vector<double> line = {0, 0, 0, 1, 1, 1, 2, 2, 2, 3, 3, 3};
  EXPECT_THROW(miem::fit_plane_eigen(view(line)), std::invalid_argument);
  std::vector<double> same = {1, 2, 3, 1, 2, 3, 1, 2, 3};
  EXPECT_THROW(miem::fit_plane_eigen(view(same)), std::invalid_argument);
  // Least squares cannot fit a plane that contains the z axis direction.
  std::vector<double> wall = {0, 0, 0, 1, 1, 0, 0, 0, 1, 1, 1, 1};
  EXPECT_THROW(miem::fit_plane_lstsq(view(wall)), std::invalid_argument);
  EXPECT_NO_THROW(miem::fit_plane_eigen(view(wall)));
}

TEST(Plane, StridedViewNeedsNoCopy) {
  // Coordinates in three separate planes (structure of arrays), float.
  const auto pts = plane_points(300, -0.4, 0.25, 2.0, 0.01);
  const std::ptrdiff_t n = 300;
  std::vector<float> soa(static_cast<std::size_t>(3 * n));
  std::vector<double> rounded(pts.size());
  for (std::ptrdiff_t i = 0; i < n; ++i)
    for (int k = 0; k < 3; ++k) {
      soa[static_cast<std::size_t>(k * n + i)] = static_cast<float>(pts[i * 3 + k]);
      rounded[static_cast<std::size_t>(i * 3 + k)] = static_cast<float>(pts[i * 3 + k]);
    }
  const miem::PointsView<float> v{soa.data(), n, /*point*/ 1, /*coord*/ n};
  const miem::Plane a = miem::fit_plane_eigen(v);
  const miem::Plane b = miem::fit_plane_eigen(view(rounded));
  EXPECT_NEAR((a.normal - b.normal).norm(), 0.0, 1e-14);
  EXPECT_NEAR(a.d, b.d, 1e-12);
}

TEST(Plane, ThreadCountDoesNotChangeTheResult) {
  const auto pts = plane_points(100000, 0.01, 0.02, 0.0, 0.05, 500.0, 3);
  const miem::Plane a = miem::fit_plane_eigen(view(pts), 1);
  const miem::Plane b = miem::fit_plane_eigen(view(pts), 2);
  EXPECT_EQ(a.normal, b.normal);
  EXPECT_EQ(a.d, b.d);
  EXPECT_EQ(a.rms, b.rms);
}

TEST(Plane, LeastSquaresBaseline) {
  const auto pts = plane_points(100, 0.5, -0.25, 3.0, 0.0);
  const miem::Plane pl = miem::fit_plane_lstsq(view(pts));
  const Eigen::Vector3d want = Eigen::Vector3d(-0.5, 0.25, 1.0).normalized();
  EXPECT_NEAR((pl.normal - want).norm(), 0.0, 1e-12);
  EXPECT_NEAR(pl.rms, 0.0, 1e-10);
  // With one outlier, least squares tilts while the points still lie mostly on the plane.
  auto with_outlier = pts;
  with_outlier.insert(with_outlier.end(), {0.0, 0.0, 50.0});
  const miem::Plane tilted = miem::fit_plane_lstsq(view(with_outlier));
  EXPECT_GT(tilted.rms, 1.0);
}

}  // namespace
