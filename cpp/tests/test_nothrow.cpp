// The no-throw API: the same results as the throwing one, and a status (never an exception) for
// every bad argument.
#include <gtest/gtest.h>

#include <cmath>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include "miem/nothrow.hpp"
#include "miem/organized.hpp"
#include "test_util.hpp"

namespace {

using miem::StatusCode;

// Every parameter that validate() rejects, check_params() rejects too, naming it.
TEST(NoThrow, CheckParamsAgreesWithValidate) {
  struct Bad {
    const char* name;
    void (*edit)(miem::DetectParams&);
  };
  const Bad bad[] = {
      {"theta0", [](miem::DetectParams& p) { p.theta0_deg = 0.0; }},
      {"theta0", [](miem::DetectParams& p) { p.theta0_deg = 180.0; }},
      {"theta0", [](miem::DetectParams& p) { p.theta0_deg = std::nan(""); }},
      {"scales", [](miem::DetectParams& p) { p.scales.clear(); }},
      {"scales", [](miem::DetectParams& p) { p.scales = {1, 0}; }},
      {"max_gap", [](miem::DetectParams& p) { p.max_gap = -1; }},
      {"min_step", [](miem::DetectParams& p) { p.min_step = INFINITY; }},
      {"max_reach", [](miem::DetectParams& p) { p.max_reach = 0; }},
      {"min_directions", [](miem::DetectParams& p) { p.min_directions = 5; }},
      {"max_iterations", [](miem::DetectParams& p) { p.max_iterations = 0; }},
      {"window", [](miem::DetectParams& p) { p.window = 6; }},
      {"window", [](miem::DetectParams& p) { p.window = 1; }},
      {"num_threads", [](miem::DetectParams& p) { p.num_threads = -2; }},
  };
  EXPECT_TRUE(miem::check_params(miem::DetectParams{}).ok());
  for (const Bad& b : bad) {
    miem::DetectParams p;
    b.edit(p);
    const miem::Status st = miem::check_params(p);
    EXPECT_EQ(st.code, StatusCode::kInvalidParameter) << b.name;
    EXPECT_EQ(std::string(st.message).rfind(b.name, 0), 0u) << st.message;
    EXPECT_THROW(miem::validate(p), std::invalid_argument) << b.name;
    std::optional<miem::OrganizedDetector> det;
    EXPECT_EQ(miem::nothrow::make_detector(p, &det).code, StatusCode::kInvalidParameter);
    EXPECT_FALSE(det.has_value());
  }
}

TEST(NoThrow, PlaneFitStatuses) {
  const std::vector<double> good = {0, 0, 0, 1, 0, 0, 0, 1, 0, 1, 1, 0.1};
  miem::Plane pl;
  ASSERT_TRUE(miem::nothrow::fit_plane_eigen(miem::PointsView<double>{good.data(), 4}, &pl).ok());
  const miem::Plane thrown = miem::fit_plane_eigen(miem::PointsView<double>{good.data(), 4});
  EXPECT_EQ(pl.normal, thrown.normal);
  EXPECT_EQ(pl.d, thrown.d);
  ASSERT_TRUE(miem::nothrow::fit_plane_lstsq(miem::PointsView<double>{good.data(), 4}, &pl).ok());

  EXPECT_EQ(miem::nothrow::fit_plane_eigen(miem::PointsView<double>{good.data(), 2}, &pl).code,
            StatusCode::kTooFewPoints);
  const std::vector<float> line = {0, 0, 0, 1, 1, 1, 2, 2, 2};
  EXPECT_EQ(miem::nothrow::fit_plane_eigen(miem::PointsView<float>{line.data(), 3}, &pl).code,
            StatusCode::kDegenerate);
  EXPECT_EQ(miem::nothrow::fit_plane_lstsq(miem::PointsView<float>{line.data(), 3}, &pl).code,
            StatusCode::kDegenerate);
  EXPECT_EQ(miem::nothrow::fit_plane_eigen(miem::PointsView<double>{nullptr, 5}, &pl).code,
            StatusCode::kInvalidInput);
  EXPECT_EQ(miem::nothrow::fit_plane_eigen(miem::PointsView<double>{good.data(), 4}, nullptr).code,
            StatusCode::kInvalidInput);
}

TEST(NoThrow, DetectEqualsThrowingApiAndReportsBadInput) {
  const std::ptrdiff_t H = 40, W = 36;
  const std::vector<double> g = miem::test::make_scan(H, W, 17);
  miem::DetectParams p;
  p.scales = {1, 2};
  std::optional<miem::OrganizedDetector> det;
  ASSERT_TRUE(miem::nothrow::make_detector(p, &det).ok());
  const auto view = miem::GridView<double>::dense(g.data(), H, W);
  std::vector<std::uint8_t> labels(static_cast<std::size_t>(H * W));
  std::vector<double> height(labels.size());
  miem::DetectSummary summary;
  const miem::OrganizedOutput out{labels.data(), nullptr, nullptr, height.data()};
  ASSERT_TRUE(miem::nothrow::detect(*det, view, out, &summary).ok());
  const miem::DetectResult want = miem::detect_organized(view, p);
  EXPECT_EQ(labels, want.labels);
  EXPECT_EQ(summary.iterations, want.summary.iterations);
  ASSERT_EQ(summary.defects.size(), want.summary.defects.size());
  EXPECT_GT(summary.defects.size(), 0u);
  for (std::size_t k = 0; k < summary.defects.size(); ++k)
    EXPECT_EQ(summary.defects[k].indices, want.summary.defects[k].indices);

  EXPECT_EQ(miem::nothrow::detect(*det, view, miem::OrganizedOutput{}, &summary).code,
            StatusCode::kInvalidInput);
  EXPECT_EQ(miem::nothrow::detect(*det, view, out, nullptr).code, StatusCode::kInvalidInput);
  EXPECT_EQ(miem::nothrow::detect(*det, miem::GridView<double>{}, out, &summary).code,
            StatusCode::kInvalidInput);
  const std::vector<float> nan_grid(4 * 4 * 3, std::nanf(""));
  EXPECT_EQ(miem::nothrow::detect(*det, miem::GridView<float>::dense(nan_grid.data(), 4, 4), out,
                                  &summary).code,
            StatusCode::kTooFewPoints);
}

TEST(NoThrow, StatusTexts) {
  EXPECT_STREQ(miem::to_string(StatusCode::kOk), "ok");
  EXPECT_STREQ(miem::to_string(StatusCode::kWrongWidth), "wrong width");
  const miem::Status ok;
  EXPECT_TRUE(ok.ok());
  EXPECT_TRUE(static_cast<bool>(ok));
}

}  // namespace
