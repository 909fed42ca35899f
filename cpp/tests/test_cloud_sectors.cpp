// The cloud edge test's sector membership (cpp/src/cloud_sectors.hpp): the octant of a tangent
// offset by geometry, and member_octants (eight at a time with AVX-512 where the CPU has it,
// else two with SSE2) equal to the scalar rule on wedge boundaries, signed zeros, subnormals,
// infinities and NaN.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdint>
#include <limits>
#include <random>
#include <vector>

#include "cloud_sectors.hpp"

namespace {

// Offsets of a ball (as cloud_kernels.hpp's Selection).
struct Offsets {
  std::vector<double> wx, wy, wz;
  std::size_t n = 0;
};

using miem::cloud::Frame;
using miem::cloud::kNotMember;
using miem::cloud::member_octants;
using miem::cloud::octant;

TEST(CloudSectors, OctantIsTheWedgeFromE1TowardsE2) {
  // A point on a boundary belongs to the wedge that starts there (SPEC step 3).
  EXPECT_EQ(octant(1.0, 0.0), 0);
  EXPECT_EQ(octant(1.0, 0.4), 0);
  EXPECT_EQ(octant(1.0, 1.0), 1);
  EXPECT_EQ(octant(0.4, 1.0), 1);
  EXPECT_EQ(octant(0.0, 1.0), 2);
  EXPECT_EQ(octant(-0.4, 1.0), 2);
  EXPECT_EQ(octant(-1.0, 1.0), 3);
  EXPECT_EQ(octant(-1.0, 0.4), 3);
  EXPECT_EQ(octant(-1.0, 0.0), 4);
  EXPECT_EQ(octant(-1.0, -0.4), 4);
  EXPECT_EQ(octant(-1.0, -1.0), 5);
  EXPECT_EQ(octant(-0.4, -1.0), 5);
  EXPECT_EQ(octant(0.0, -1.0), 6);
  EXPECT_EQ(octant(0.4, -1.0), 6);
  EXPECT_EQ(octant(1.0, -1.0), 7);
  EXPECT_EQ(octant(1.0, -0.4), 7);
  EXPECT_EQ(octant(1.0, -0.0), 0);  // -0 is 0
}

// The rule member_octants implements, written out with the scalar octant.
std::uint8_t expected(double wx, double wy, double wz, const Frame& f, double gap) {
  const double a = wx * f.e1.x() + wy * f.e1.y() + wz * f.e1.z();
  const double b = wx * f.e2.x() + wy * f.e2.y() + wz * f.e2.z();
  const double rho = std::sqrt(a * a + b * b);
  return rho > 0.0 && rho >= gap ? static_cast<std::uint8_t>(octant(a, b)) : kNotMember;
}

void check(const Offsets& s, const Frame& f, double gap) {
  std::vector<std::uint8_t> oc(s.n, 99);
  member_octants(s.wx.data(), s.wy.data(), s.wz.data(), s.n, f, gap, oc.data());
  for (std::size_t k = 0; k < s.n; ++k) {
    ASSERT_EQ(oc[k], expected(s.wx[k], s.wy[k], s.wz[k], f, gap))
        << "w = (" << s.wx[k] << ", " << s.wy[k] << ", " << s.wz[k] << "), gap " << gap;
  }
}

TEST(CloudSectors, MemberOctantsMatchTheScalarRuleOnSpecialValues) {
  const double inf = std::numeric_limits<double>::infinity();
  const std::vector<double> v = {0.0, -0.0, 1.0, -1.0, 0.5, -0.5, 2.0, -2.0, 1e-310, -1e-310,
                                 3.0, -3.0, inf, -inf, std::nan("")};
  Offsets s;
  for (double x : v) {
    for (double y : v) {
      s.wx.push_back(x);
      s.wy.push_back(y);
      s.wz.push_back(0.0);
    }
  }
  s.wx.push_back(0.25);  // an odd count: the scalar tail too
  s.wy.push_back(0.25);
  s.wz.push_back(0.0);
  s.n = s.wx.size();
  Frame f;
  f.e1 = Eigen::Vector3d(1.0, 0.0, 0.0);
  f.e2 = Eigen::Vector3d(0.0, 1.0, 0.0);
  for (double gap : {0.0, 0.5, 1.0}) check(s, f, gap);
  // Hand-checked members: (1, 1) on the 45-degree boundary is octant 1; (0, 0) is no member.
  std::vector<std::uint8_t> oc(s.n);
  member_octants(s.wx.data(), s.wy.data(), s.wz.data(), s.n, f, 0.5, oc.data());
  EXPECT_EQ(oc[2 * v.size() + 2], 1);  // (1, 1)
  EXPECT_EQ(oc[3 * v.size() + 2], 3);  // (-1, 1)
  EXPECT_EQ(oc[0], kNotMember);        // (0, 0)
  EXPECT_EQ(oc[s.n - 1], kNotMember);  // (0.25, 0.25): inside the gap
}

TEST(CloudSectors, MemberOctantsMatchTheScalarRuleInATurnedFrame) {
  std::mt19937_64 rng(7);
  std::uniform_int_distribution<int> q(-8, 8);  // quarter steps: many exact ties
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  Offsets s;
  for (int k = 0; k < 20001; ++k) {
    s.wx.push_back(q(rng) / 4.0);
    s.wy.push_back(q(rng) / 4.0);
    s.wz.push_back(k % 3 == 0 ? 0.0 : u(rng));
  }
  s.n = s.wx.size();
  Frame f;
  f.e1 = Eigen::Vector3d(0.6, 0.8, 0.0);
  f.e2 = Eigen::Vector3d(-0.8, 0.6, 0.0);
  check(s, f, 0.3);
  f.e1 = Eigen::Vector3d(1.0, 0.0, 0.0);
  f.e2 = Eigen::Vector3d(0.0, 1.0, 0.0);
  check(s, f, 0.25);
}

}  // namespace
