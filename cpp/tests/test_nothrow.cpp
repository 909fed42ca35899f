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
#include "miem/unorganized.hpp"
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
      // Once kInternal from make_detector (issue 9): the height test and edge_extent.
      {"height_abs", [](miem::DetectParams& p) { p.height_abs = std::nan(""); }},
      {"height_k", [](miem::DetectParams& p) { p.height_k = INFINITY; }},
      {"edge_extent", [](miem::DetectParams& p) { p.edge_extent = -1; }},
      {"height_mode", [](miem::DetectParams& p) { p.height_mode = miem::HeightMode{7}; }},
      // a length while min_step_auto is on would be ignored: refused
      {"min_step", [](miem::DetectParams& p) { p.min_step = 0.2; }},
  };
  EXPECT_TRUE(miem::check_params(miem::DetectParams{}).ok());
  for (const Bad& b : bad) {
    miem::DetectParams p;
    b.edit(p);
    const miem::Status st = miem::check_params(p);
    EXPECT_EQ(st.code, StatusCode::kInvalidParameter) << b.name;
    EXPECT_EQ(std::string(st.message).rfind(b.name, 0), 0u) << st.message;
    EXPECT_THROW(miem::validate(p), std::invalid_argument) << b.name;
    try {
      miem::OrganizedDetector thrown(p);
      ADD_FAILURE() << b.name << " accepted";
    } catch (const std::invalid_argument& e) {
      EXPECT_STREQ(e.what(), st.message);  // the throwing API throws the check's message
    }
    std::optional<miem::OrganizedDetector> det;
    const miem::Status made = miem::nothrow::make_detector(p, &det);
    EXPECT_EQ(made.code, StatusCode::kInvalidParameter) << b.name << ": " << made.message;
    EXPECT_STREQ(made.message, st.message);
    EXPECT_FALSE(det.has_value());
  }
  // theta0 is not read with theta0_auto: both APIs accept it.
  miem::DetectParams p;
  p.theta0_auto = true;
  p.theta0_deg = std::nan("");
  EXPECT_TRUE(miem::check_params(p).ok());
  EXPECT_NO_THROW(miem::validate(p));
}

TEST(ParamTypes, DefaultsAreTheRecommendedPresetAndPaperIsThePaper) {
  const miem::DetectParams d;
  EXPECT_EQ(d.theta0_deg, 90.0);
  EXPECT_FALSE(d.theta0_auto);
  EXPECT_EQ(d.scales, (std::vector<int>{1, 2}));
  EXPECT_EQ(d.max_gap, 1);
  EXPECT_LT(d.min_step, 0.0);
  EXPECT_EQ(d.min_directions, 0);
  EXPECT_EQ(d.max_iterations, 10);
  EXPECT_EQ(d.window, 21);
  EXPECT_EQ(d.height_abs, 0.0);
  EXPECT_EQ(d.height_k, 4.5);
  EXPECT_EQ(d.edge_extent, 12);
  EXPECT_TRUE(d.height_test());
  EXPECT_TRUE(d.min_step_auto);  // min_step = "auto" (SPEC)
  EXPECT_EQ(d.edge_k, 4.0);      // the edge test
  EXPECT_EQ(d.edge_window, 15);
  EXPECT_TRUE(d.edge_test());
  const miem::DetectParams paper = miem::paper_params();
  EXPECT_EQ(paper.theta0_deg, 75.0);
  EXPECT_EQ(paper.scales, (std::vector<int>{1}));
  EXPECT_FALSE(paper.height_test());
  EXPECT_EQ(paper.edge_extent, 0);
  EXPECT_FALSE(paper.min_step_auto);
  EXPECT_FALSE(paper.edge_test());
  EXPECT_EQ(paper.max_gap, 1);
  EXPECT_EQ(paper.window, 21);
  const miem::PointsDetectParams c;
  EXPECT_EQ(c.theta0_deg, d.theta0_deg);
  EXPECT_EQ(c.scales, d.scales);
  EXPECT_EQ(c.num_directions, 4);
}

TEST(ParamTypes, CloudChecksNameTheField) {
  struct Bad {
    const char* name;
    void (*edit)(miem::PointsDetectParams&);
  };
  const Bad bad[] = {
      {"theta0", [](miem::PointsDetectParams& p) { p.theta0_deg = 180.0; }},
      {"theta0_auto", [](miem::PointsDetectParams& p) { p.theta0_auto = true; }},
      {"scales", [](miem::PointsDetectParams& p) { p.scales = {0}; }},
      {"radius", [](miem::PointsDetectParams& p) { p.radius = -1.0; }},
      {"K", [](miem::PointsDetectParams& p) { p.num_directions = 9; }},
      {"min_step", [](miem::PointsDetectParams& p) { p.min_step = -0.5; }},
      {"min_directions", [](miem::PointsDetectParams& p) { p.min_directions = 5; }},
      {"max_iterations", [](miem::PointsDetectParams& p) { p.max_iterations = 0; }},
      {"link", [](miem::PointsDetectParams& p) { p.link = std::nan(""); }},
      {"num_threads", [](miem::PointsDetectParams& p) { p.num_threads = -1; }},
  };
  EXPECT_TRUE(miem::PointsDetectParams{}.check().ok());
  for (const Bad& b : bad) {
    miem::PointsDetectParams p;
    b.edit(p);
    const miem::Status st = p.check();
    EXPECT_EQ(st.code, StatusCode::kInvalidParameter) << b.name;
    EXPECT_EQ(std::string(st.message).rfind(b.name, 0), 0u) << st.message;
    try {
      miem::validate(p);
      ADD_FAILURE() << b.name << " accepted";
    } catch (const std::invalid_argument& e) {
      EXPECT_STREQ(e.what(), st.message);
    }
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
