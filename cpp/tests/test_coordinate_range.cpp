// SPEC "Numbers", the coordinate range: the scan (largest_finite_magnitude, miem/views.hpp),
// values by hand; the detectors' refusals (CoordinateRangeError, the no-throw statuses).
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <string>
#include <vector>

#include "miem/miem.hpp"

namespace {

TEST(CoordinateRange, LargestFiniteMagnitudeSkipsNonFiniteValues) {
  const double inf = std::numeric_limits<double>::infinity();
  const double nan = std::numeric_limits<double>::quiet_NaN();
  // 2 rows of 5, row stride 8: the values between the rows (-100) are not part of the block
  const std::vector<double> a = {1.0, -inf, nan, -2.5, 0.5, -100, -100, -100,
                                 -0.0, 2.0, inf, -3.25, nan, -100, -100, -100};
  EXPECT_EQ(miem::largest_finite_magnitude(a.data(), 2, 5, 8, 1), 3.25);
  EXPECT_EQ(miem::largest_finite_magnitude(a.data(), 1, 16, 0, 1), 100.0);
  // every other value of the first row: 1, nan, 0.5
  EXPECT_EQ(miem::largest_finite_magnitude(a.data(), 1, 3, 0, 2), 1.0);
  // a reversed column: a[8], a[0] (negative row stride)
  EXPECT_EQ(miem::largest_finite_magnitude(a.data() + 8, 2, 1, -8, 1), 1.0);
  const std::vector<double> none = {nan, inf, -inf, -0.0};
  EXPECT_EQ(miem::largest_finite_magnitude(none.data(), 1, 4, 0, 1), 0.0);
  EXPECT_EQ(miem::largest_finite_magnitude(none.data(), 0, 4, 0, 1), 0.0);
  const std::vector<float> f = {1e-30f, -3e38f, std::numeric_limits<float>::infinity(), 2.0f};
  EXPECT_EQ(miem::largest_finite_magnitude(f.data(), 1, 4, 0, 1), static_cast<double>(3e38f));
  // long rows: the last value (past the vector part), then one inside it (an odd lane), between
  // infinities and NaNs in every lane
  std::vector<double> row(1003, 1.0);
  for (std::size_t i = 0; i < row.size(); i += 5) row[i] = i % 2 ? inf : nan;
  row.back() = -9.0;
  EXPECT_EQ(miem::largest_finite_magnitude(row.data(), 1, 1003, 0, 1), 9.0);
  row[501] = -20.0;
  EXPECT_EQ(miem::largest_finite_magnitude(row.data(), 1, 1003, 0, 1), 20.0);
  std::vector<float> frow(21, -1.0f);
  frow[3] = -std::numeric_limits<float>::infinity();
  frow[13] = -7.5f;
  frow[20] = 5.0f;
  EXPECT_EQ(miem::largest_finite_magnitude(frow.data(), 1, 21, 0, 1), 7.5);
}

// A smooth organized grid (0.2 mm steps, a gentle bump) with a few spikes: values by hand.
std::vector<double> bumpy_grid(std::ptrdiff_t H, std::ptrdiff_t W) {
  std::vector<double> g(static_cast<std::size_t>(H * W * 3));
  for (std::ptrdiff_t r = 0; r < H; ++r) {
    for (std::ptrdiff_t c = 0; c < W; ++c) {
      double* p = g.data() + 3 * (r * W + c);
      p[0] = 0.2 * static_cast<double>(c);
      p[1] = 0.2 * static_cast<double>(r);
      p[2] = 0.01 * std::sin(0.3 * static_cast<double>(c)) + ((r * 7 + c * 3) % 11 == 0 ? 0.002 : 0.0);
    }
  }
  for (std::ptrdiff_t k = 1; k < 6; ++k) g[3 * (k * 7 * W + k * 9) + 2] += 1.5;  // spikes
  return g;
}

// SPEC "Numbers": a finite coordinate beyond 1e18 (a dropout's too), or a largest magnitude
// below 1e-18, is refused by every detector, before any result; the range's ends compute.
TEST(CoordinateRange, DetectorsRefuseCoordinatesOutsideTheRange) {
  const std::ptrdiff_t H = 40, W = 50, N = H * W;
  const std::vector<double> base = bumpy_grid(H, W);
  std::vector<std::uint8_t> labels(N);
  miem::OrganizedOutput out{labels.data()};
  miem::OrganizedDetector det(miem::recommended_params());
  auto run = [&](const std::vector<double>& g) {
    return det.run(miem::GridView<double>{g.data(), H, W, 3 * W, 3, 1}, out);
  };
  auto refused = [&](const std::vector<double>& g, double magnitude) {
    try {
      run(g);
    } catch (const miem::CoordinateRangeError& e) {
      EXPECT_EQ(e.magnitude(), magnitude);
      EXPECT_EQ(std::string(e.what()).rfind("grid: finite coordinates reach a magnitude of", 0),
                0u) << e.what();
      return true;
    }
    return false;
  };
  run(base);
  const std::vector<std::uint8_t> expected = labels;
  std::vector<double> g = base;
  g[3 * (17 * W + 23) + 0] = -1e18;  // a dropout (z NaN) whose x is at the bound: computes
  g[3 * (17 * W + 23) + 2] = std::nan("");
  run(g);
  EXPECT_EQ(labels[17 * W + 23], miem::kInvalid);
  g[3 * (17 * W + 23) + 0] = -std::nextafter(1e18, 2e18);  // just past it: refused
  EXPECT_TRUE(refused(g, std::nextafter(1e18, 2e18)));
  g = base;
  g[3 * N - 1] = 3e19;  // the last value of the grid
  EXPECT_TRUE(refused(g, 3e19));
  // scaled by 2^-70 (largest 9.8 * 2^-70 = 8.3e-21): refused; one value of 1e-18 lifts it
  g = base;
  for (double& v : g) v = std::ldexp(v, -70);
  EXPECT_TRUE(refused(g, std::ldexp(9.8, -70)));
  g[0] = 1e-18;
  EXPECT_NO_THROW(run(g));
  // float32, and the row-by-row pass 0 of a long thin grid (no row kernel)
  std::vector<float> f(base.begin(), base.end());
  f[3 * 5 + 1] = -2e19f;
  EXPECT_THROW(det.run(miem::GridView<float>{f.data(), H, W, 3 * W, 3, 1}, out),
               miem::CoordinateRangeError);
  const std::ptrdiff_t L = 200000;
  std::vector<double> line(3 * L);
  for (std::ptrdiff_t c = 0; c < L; ++c) {
    line[3 * c] = 0.1 * static_cast<double>(c);
    line[3 * c + 2] = 0.001 * static_cast<double>(c % 7);
  }
  std::vector<std::uint8_t> line_labels(L);
  line[3 * (L - 1) + 1] = 1e20;
  EXPECT_THROW(det.run(miem::GridView<double>{line.data(), 1, L, 3 * L, 3, 1},
                       miem::OrganizedOutput{line_labels.data()}),
               miem::CoordinateRangeError);
  // the no-throw API
  g = base;
  g[7] = 1e300;
  miem::DetectSummary summary;
  const miem::Status st =
      miem::nothrow::detect(det, miem::GridView<double>{g.data(), H, W, 3 * W, 3, 1}, out, &summary);
  EXPECT_EQ(st.code, miem::StatusCode::kInvalidInput);
  EXPECT_NE(std::string(st.message).find("rescale"), std::string::npos);
  run(base);
  EXPECT_EQ(labels, expected);  // the refusals left the detector as it was
  // clouds
  miem::PointsDetectParams cp;
  g = base;
  g[3 * 100 + 2] = -5e18;
  EXPECT_THROW(miem::detect_points(miem::PointsView<double>{g.data(), N, 3, 1}, cp),
               miem::CoordinateRangeError);
  EXPECT_THROW(miem::point_spacing(miem::PointsView<double>{g.data(), N, 3, 1}),
               miem::CoordinateRangeError);
  std::vector<std::uint8_t> valid(N);
  EXPECT_THROW(miem::estimate_normals(miem::PointsView<double>{g.data(), N, 3, 1}, 1.0,
                                      miem::NormalsOutput{nullptr, nullptr, nullptr, valid.data()}),
               miem::CoordinateRangeError);
  g[3 * 100 + 2] = -1e18;  // at the bound: computes
  miem::estimate_normals(miem::PointsView<double>{g.data(), N, 3, 1}, 1.0,
                         miem::NormalsOutput{nullptr, nullptr, nullptr, valid.data()});
  EXPECT_EQ(valid[100], 0);  // (its ball holds no other point)
  EXPECT_EQ(valid[101], 1);
}

// A stream refuses a profile beyond the range and is unchanged: its rows are those of a stream
// that never saw it.
TEST(CoordinateRange, StreamRejectsAProfileBeyondTheRange) {
  const std::ptrdiff_t H = 1200, W = 50;  // more rows than the default stream's ring (about 940)
  const std::vector<double> g = bumpy_grid(H, W);
  std::vector<double> bad(g.begin(), g.begin() + 3 * W);
  bad[3 * 10 + 2] = 2e18;
  // the same profile as coordinate planes (x, then y, then z: another layout's copy)
  std::vector<double> bad_planes(3 * W);
  for (std::ptrdiff_t c = 0; c < W; ++c)
    for (int k = 0; k < 3; ++k) bad_planes[k * W + c] = bad[3 * c + k];
  auto push_bad = [&](miem::ProfileStream<double>& s, miem::StreamRow& row) {
    const std::int64_t before = s.rows_pushed();
    using View = miem::PointsView<double>;
    for (const View v : {View{bad.data(), W, 3, 1}, View{bad_planes.data(), W, 1, W}}) {
      const miem::Status st = s.push(v, &row);
      EXPECT_EQ(st.code, miem::StatusCode::kInvalidInput);
      EXPECT_NE(std::string(st.message).find("rescale"), std::string::npos);
      EXPECT_FALSE(row.ready());
      EXPECT_EQ(s.rows_pushed(), before);
    }
  };
  // The bad profile in the middle of the part, or just before the flush (more rows than the
  // stream's ring holds: the slot the profile is copied into before its check holds a pushed
  // row, older than any the stages or the flush read).
  auto rows = [&](bool with_bad, std::ptrdiff_t at = 20) {
    miem::ProfileStream<double> s(W);
    std::vector<std::uint8_t> all;  // labels, then each row's heights' bytes
    miem::StreamRow row;
    auto keep = [&](const miem::StreamRow& r) {
      if (!r.ready()) return;
      all.insert(all.end(), r.labels, r.labels + W);
      const auto* h = reinterpret_cast<const std::uint8_t*>(r.height);
      all.insert(all.end(), h, h + W * sizeof(double));
    };
    for (std::ptrdiff_t r = 0; r < H; ++r) {
      if (with_bad && r == at) push_bad(s, row);
      EXPECT_TRUE(s.push(g.data() + 3 * r * W, W, &row).ok());
      keep(row);
    }
    if (with_bad && at == H) push_bad(s, row);
    while (s.flush(&row)) keep(row);
    return all;
  };
  const std::vector<std::uint8_t> clean = rows(false);
  EXPECT_EQ(clean.size(), static_cast<std::size_t>(H * W) * (1 + sizeof(double)));
  EXPECT_EQ(rows(true), clean);
  EXPECT_EQ(rows(true, H), clean);
}

}  // namespace
