// Deviation from a reference surface: a tilted plane with its exact normal (deviation = signed
// distance), coverage by distance and by lateral offset, ties, float input, thread-count
// independence, labels with the don't-care band, and argument errors.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <stdexcept>
#include <vector>

#include "miem/deviation.hpp"

namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kInf = std::numeric_limits<double>::infinity();

// The plane z = 0.2 x + 5 sampled on a 0.1 grid over [0, 10) x [0, 10), with its unit normal.
struct Plane {
  std::vector<double> pts, nrm;
  double nx, nz;
  Plane() {
    const double len = std::sqrt(0.04 + 1.0);
    nx = -0.2 / len;
    nz = 1.0 / len;
    for (int i = 0; i < 100; ++i) {
      for (int j = 0; j < 100; ++j) {
        const double x = 0.1 * i, y = 0.1 * j;
        pts.insert(pts.end(), {x, y, 0.2 * x + 5.0});
        nrm.insert(nrm.end(), {nx, 0.0, nz});
      }
    }
  }
  miem::PointsView<double> view() const {
    return {pts.data(), static_cast<std::ptrdiff_t>(pts.size() / 3), 3, 1};
  }
};

struct Out {
  std::vector<double> dev, dist;
  std::vector<std::int64_t> nearest;
  std::vector<std::uint8_t> covered;
  explicit Out(std::size_t n) : dev(n), dist(n), nearest(n), covered(n) {}
  miem::DeviationOutput out() {
    return {dev.data(), dist.data(), nearest.data(), covered.data()};
  }
};

TEST(Deviation, SignedDistanceFromATiltedPlane) {
  const Plane plane;
  const miem::ReferenceSurface surf(plane.view(), plane.nrm.data(), 0.2);
  EXPECT_EQ(surf.size(), 10000);
  // Points offset by h along the normal above grid points: deviation h, nearest that point.
  std::vector<double> scan;
  const double hs[] = {0.5, -0.3, 0.0, 1.2};
  for (int k = 0; k < 4; ++k) {
    const double x = 2.0 + k, y = 3.0;
    scan.insert(scan.end(), {x + hs[k] * plane.nx, y, 0.2 * x + 5.0 + hs[k] * plane.nz});
  }
  scan.insert(scan.end(), {5.0, 5.0, 50.0});  // far from everything: not covered
  scan.insert(scan.end(), {kNaN, 0.0, 0.0});  // a dropout: not covered
  Out o(6);
  surf.deviation(miem::PointsView<double>{scan.data(), 6, 3, 1}, 1.0, kInf, o.out());
  for (int k = 0; k < 3; ++k) {
    EXPECT_NEAR(o.dev[k], hs[k], 1e-12);
    EXPECT_NEAR(o.dist[k], std::abs(hs[k]), 1e-12);
    EXPECT_EQ(o.nearest[k], (20 + 10 * k) * 100 + 30);
    EXPECT_EQ(o.covered[k], 1);
  }
  EXPECT_EQ(o.covered[3], 0);  // 1.2 > max_distance 1.0
  EXPECT_TRUE(std::isnan(o.dev[3]));
  EXPECT_EQ(o.nearest[3], -1);
  EXPECT_EQ(o.covered[4], 0);
  EXPECT_EQ(o.covered[5], 0);
  EXPECT_EQ(o.nearest[5], -1);
}

TEST(Deviation, LateralOffsetBeyondTheEdgeIsNotCovered) {
  const Plane plane;
  const miem::ReferenceSurface surf(plane.view(), plane.nrm.data(), 0.2);
  // On the plane's extension, 0.5 beyond its edge x = 9.9: close (0.51), but lateral.
  const double x = 10.4;
  std::vector<double> scan = {x, 5.0, 0.2 * x + 5.0, 5.0, 5.0, 6.0 + 0.05};
  Out o(2);
  surf.deviation(miem::PointsView<double>{scan.data(), 2, 3, 1}, 1.0, 0.3, o.out());
  EXPECT_EQ(o.covered[0], 0);
  EXPECT_EQ(o.nearest[0], 99 * 100 + 50);  // reported although not covered
  EXPECT_EQ(o.covered[1], 1);
}

TEST(Deviation, FloatInputAndThreadsGiveTheSame) {
  const Plane plane;
  const miem::ReferenceSurface surf(plane.view(), plane.nrm.data(), 0.15);
  std::vector<float> scan;
  for (int i = 0; i < 5000; ++i) {
    const float x = 0.002f * static_cast<float>(i), y = 0.0017f * static_cast<float>(i);
    scan.insert(scan.end(), {x, y, 0.2f * x + 5.0f + 0.1f * std::sin(0.01f * i)});
  }
  Out a(5000), b(5000);
  const miem::PointsView<float> v{scan.data(), 5000, 3, 1};
  surf.deviation(v, 0.5, kInf, a.out(), 1);
  surf.deviation(v, 0.5, kInf, b.out(), 2);
  EXPECT_EQ(a.nearest, b.nearest);
  for (int i = 0; i < 5000; ++i) {
    ASSERT_EQ(a.covered[i], 1);
    // Exact normal: deviation is the signed distance of the point from the plane.
    const double z = scan[3 * i + 2], x = scan[3 * i];
    EXPECT_NEAR(a.dev[i], (z - 0.2 * x - 5.0) * plane.nz, 1e-9);
  }
}

TEST(Deviation, LabelsAndDontCareBand) {
  // A row of points 0.1 apart; two bumps: 0.5 (a defect) and 0.25 (inside the band).
  std::vector<double> pts, dev;
  std::vector<std::uint8_t> cov;
  for (int i = 0; i < 100; ++i) {
    pts.insert(pts.end(), {0.1 * i, 0.0, 0.0});
    double d = 0.0;
    if (i >= 10 && i <= 14) d = 0.5 - 0.1 * std::abs(i - 12);
    if (i >= 50 && i <= 52) d = 0.25;
    if (i >= 70 && i <= 71) d = -0.6;
    dev.push_back(d);
    cov.push_back(i == 99 ? 0 : 1);
  }
  std::vector<std::uint8_t> labels(100);
  const miem::DeviationLabelParams params{0.2, 0.1, 0.15};
  const auto defects = miem::label_deviation(miem::PointsView<double>{pts.data(), 100, 3, 1},
                                             dev.data(), cov.data(), nullptr, params,
                                             labels.data());
  ASSERT_EQ(defects.size(), 2u);
  EXPECT_EQ(defects[0].kind, miem::DefectKind::kPit);  // |-0.6| first
  EXPECT_EQ(defects[0].indices, (std::vector<std::int64_t>{70, 71}));
  EXPECT_EQ(defects[1].kind, miem::DefectKind::kProtrusion);
  EXPECT_EQ(defects[1].indices, (std::vector<std::int64_t>{10, 11, 12, 13, 14}));
  EXPECT_DOUBLE_EQ(defects[1].peak_height, 0.5);
  EXPECT_EQ(labels[12], 1);
  EXPECT_EQ(labels[51], 0);  // within the don't-care band
  EXPECT_EQ(labels[70], 2);
  EXPECT_EQ(labels[99], 3);
}

TEST(Deviation, BadArguments) {
  const Plane plane;
  EXPECT_THROW(miem::ReferenceSurface(plane.view(), plane.nrm.data(), 0.0),
               std::invalid_argument);
  std::vector<double> nan_normals(plane.nrm.size(), kNaN);
  EXPECT_THROW(miem::ReferenceSurface(plane.view(), nan_normals.data(), 0.1),
               std::invalid_argument);
  const miem::ReferenceSurface surf(plane.view(), plane.nrm.data(), 0.2);
  std::vector<double> scan = {0, 0, 0};
  Out o(1);
  EXPECT_THROW(surf.deviation(miem::PointsView<double>{scan.data(), 1, 3, 1}, -1.0, kInf,
                              o.out()),
               std::invalid_argument);
  EXPECT_THROW(surf.deviation(miem::PointsView<double>{scan.data(), 1, 3, 1}, 1.0, kNaN,
                              o.out()),
               std::invalid_argument);
  std::vector<std::uint8_t> labels(1), cov(1, 1);
  std::vector<double> dev(1, 0.0);
  EXPECT_THROW(miem::label_deviation(miem::PointsView<double>{scan.data(), 1, 3, 1}, dev.data(),
                                     cov.data(), nullptr, miem::DeviationLabelParams{0.0, 0, 1},
                                     labels.data()),
               std::invalid_argument);
}

}  // namespace
