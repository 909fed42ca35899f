// Scan-line angles (paper eq. 18-19) and eq. 20 heights on hand-worked geometry.
#include <gtest/gtest.h>

#include <cmath>
#include <stdexcept>
#include <vector>

#include "miem/scan_line.hpp"

namespace {

constexpr double kPi = 3.14159265358979323846;

miem::PointsView<double> view(const std::vector<double>& p) {
  return {p.data(), static_cast<std::ptrdiff_t>(p.size() / 3), 3, 1};
}

std::vector<double> angles(const std::vector<double>& p, int step = 1) {
  std::vector<double> out(p.size() / 3);
  miem::scan_line_angles(view(p), step, out.data());
  return out;
}

TEST(Angles, StraightLineIs180AndEndsAreNaN) {
  const std::vector<double> p = {0, 0, 0, 1, 0, 0, 2, 0, 0, 3, 0, 0};
  const auto a = angles(p);
  EXPECT_TRUE(std::isnan(a[0]));
  EXPECT_NEAR(a[1], 180.0, 1e-9);
  EXPECT_NEAR(a[2], 180.0, 1e-9);
  EXPECT_TRUE(std::isnan(a[3]));
}

TEST(Angles, RightAngleAndSpike) {
  // Corner at (1, 0, 0): 90 degrees.
  const std::vector<double> corner = {0, 0, 0, 1, 0, 0, 1, 1, 0};
  EXPECT_NEAR(angles(corner)[1], 90.0, 1e-12);
  // Spike of height h over spacing 1: theta = 2 atan(1 / h).
  const double h = 3.0;
  const std::vector<double> spike = {0, 0, 0, 1, 0, h, 2, 0, 0};
  EXPECT_NEAR(angles(spike)[1], 2.0 * std::atan(1.0 / h) * 180.0 / kPi, 1e-12);
}

TEST(Angles, StepSkipsPoints) {
  const std::vector<double> p = {0, 0, 0, 1, 0, 9, 2, 0, 1, 3, 0, 9, 4, 0, 0};
  const auto a = angles(p, 2);
  EXPECT_TRUE(std::isnan(a[1]));
  // At index 2, neighbours are indices 0 and 4: spike of height 1 over spacing 2.
  EXPECT_NEAR(a[2], 2.0 * std::atan(2.0 / 1.0) * 180.0 / kPi, 1e-12);
}

TEST(Angles, DropoutsAndDuplicatesGiveNaN) {
  const double nan = std::nan("");
  const std::vector<double> p = {0, 0, 0, 1, 0, 0, nan, 0, 0, 3, 0, 0, 3, 0, 0, 4, 0, 0};
  const auto a = angles(p);
  EXPECT_TRUE(std::isnan(a[1]));  // successor is a dropout
  EXPECT_TRUE(std::isnan(a[2]));  // the point itself
  EXPECT_TRUE(std::isnan(a[3]));  // predecessor is a dropout
  EXPECT_TRUE(std::isnan(a[4]));  // predecessor coincides with the point
}

TEST(Angles, FloatInputIsWidened) {
  const std::vector<float> pf = {0, 0, 0, 1, 0, 0.5f, 2, 0, 0};
  const std::vector<double> pd = {0, 0, 0, 1, 0, 0.5, 2, 0, 0};
  double af[3], ad[3];
  miem::scan_line_angles(miem::PointsView<float>{pf.data(), 3, 3, 1}, 1, af);
  miem::scan_line_angles(view(pd), 1, ad);
  EXPECT_EQ(af[1], ad[1]);
}

TEST(Angles, HeightsFollowEquation20) {
  // D_i = sin(theta_{i-1}) |P_i - P_{i-1}|: the distance of P_i from the line through P_{i-2},
  // P_{i-1}.
  const std::vector<double> p = {0, 0, 0, 1, 0, 0, 2, 0, 0.5, 3, 0, 0};
  std::vector<double> h(4);
  miem::scan_line_heights(view(p), 1, h.data());
  EXPECT_TRUE(std::isnan(h[0]));
  EXPECT_TRUE(std::isnan(h[1]));
  EXPECT_NEAR(h[2], 0.5, 1e-12);
  // P_3 against the line through P_1 and P_2 (direction (1, 0, 0.5)): |(1,0,.5) x (1,0,-.5)| / |.|.
  EXPECT_NEAR(h[3], 1.0 / std::sqrt(1.25), 1e-12);
}

TEST(Angles, BadStepThrows) {
  const std::vector<double> p = {0, 0, 0, 1, 0, 0, 2, 0, 0};
  std::vector<double> out(3);
  EXPECT_THROW(miem::scan_line_angles(view(p), 0, out.data()), std::invalid_argument);
  EXPECT_THROW(miem::scan_line_heights(view(p), -1, out.data()), std::invalid_argument);
}

}  // namespace
