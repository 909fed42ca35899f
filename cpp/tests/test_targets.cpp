// Grinding targets from the C++ API a controller uses: detect, then plan_targets; poses checked
// against the scan's construction, the no-throw variant against the throwing one.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdint>
#include <stdexcept>
#include <string>
#include <vector>

#include <Eigen/Geometry>

#include "miem/organized.hpp"
#include "miem/targets.hpp"

namespace {

constexpr double kStep = 0.5;

// Tilted plane z = 0.3 x - 0.2 y + 5 (scan frame), spike of 2 at (20, 24).
std::vector<double> tilted_grid(std::ptrdiff_t rows, std::ptrdiff_t cols) {
  std::vector<double> g(static_cast<std::size_t>(rows * cols * 3));
  for (std::ptrdiff_t r = 0; r < rows; ++r)
    for (std::ptrdiff_t c = 0; c < cols; ++c) {
      double* p = &g[static_cast<std::size_t>((r * cols + c) * 3)];
      p[0] = c * kStep;
      p[1] = r * kStep;
      p[2] = 0.3 * p[0] - 0.2 * p[1] + 5.0 + ((r == 20 && c == 24) ? 2.0 : 0.0);
    }
  return g;
}

Eigen::Matrix4d sensor_pose() {
  Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
  T.topLeftCorner<3, 3>() = (Eigen::AngleAxisd(0.5, Eigen::Vector3d::UnitZ()) *
                             Eigen::AngleAxisd(2.8, Eigen::Vector3d::UnitX()))
                                .toRotationMatrix();
  T.topRightCorner<3, 1>() = Eigen::Vector3d(400.0, -120.0, 650.0);
  return T;
}

struct Scene {
  std::ptrdiff_t rows = 44, cols = 48;
  std::vector<double> grid = tilted_grid(rows, cols);
  miem::DetectResult det;
  std::vector<double> T_rowmajor;
  Scene() {
    const auto view = miem::GridView<double>::dense(grid.data(), rows, cols);
    det = miem::detect_organized(view, miem::DetectParams{});
    const Eigen::Matrix<double, 4, 4, Eigen::RowMajor> T = sensor_pose();
    T_rowmajor.assign(T.data(), T.data() + 16);
  }
  miem::GridView<double> view() const {
    return miem::GridView<double>::dense(grid.data(), rows, cols);
  }
};

TEST(Targets, TiltedPlaneTargetInBaseFrame) {
  const Scene s;
  ASSERT_EQ(s.det.summary.defects.size(), 1u);
  miem::TargetParams p;
  p.standoff = 1.0;
  const miem::TargetPlan plan =
      miem::plan_targets(s.view(), s.det.labels.data(), s.det.height.data(), s.det.summary.defects,
                         {s.T_rowmajor.data(), 1}, p);
  ASSERT_EQ(plan.targets.size(), 1u);
  const miem::Target& t = plan.targets[0];
  const Eigen::Matrix4d T = sensor_pose();
  const Eigen::Matrix3d R = T.topLeftCorner<3, 3>();
  const Eigen::Vector3d spike(24 * kStep, 20 * kStep, 0.3 * 12.0 - 0.2 * 10.0 + 7.0);
  EXPECT_LT((t.point - (R * spike + T.topRightCorner<3, 1>())).norm(), 1e-9);
  const Eigen::Vector3d n = R * Eigen::Vector3d(-0.3, 0.2, 1.0).normalized();
  EXPECT_LT((t.normal - n).norm(), 1e-9);
  EXPECT_LT((t.rotation.col(2) + n).norm(), 1e-9);
  EXPECT_LT((t.position - (t.point + n)).norm(), 1e-9);
  const Eigen::Quaterniond q(t.quaternion(0), t.quaternion(1), t.quaternion(2), t.quaternion(3));
  EXPECT_NEAR(q.norm(), 1.0, 1e-12);
  EXPECT_LT((q.toRotationMatrix() - t.rotation).cwiseAbs().maxCoeff(), 1e-12);
  const Eigen::Vector3d abc = t.abc_deg * (M_PI / 180.0);
  const Eigen::Matrix3d from_abc = (Eigen::AngleAxisd(abc(0), Eigen::Vector3d::UnitZ()) *
                                    Eigen::AngleAxisd(abc(1), Eigen::Vector3d::UnitY()) *
                                    Eigen::AngleAxisd(abc(2), Eigen::Vector3d::UnitX()))
                                       .toRotationMatrix();
  EXPECT_LT((from_abc - t.rotation).cwiseAbs().maxCoeff(), 1e-12);
}

TEST(Targets, NoThrowMatchesAndReportsBadTransforms) {
  const Scene s;
  const miem::TargetParams p;
  miem::TargetPlan plan;
  ASSERT_TRUE(miem::nothrow::plan_targets(s.view(), s.det.labels.data(), s.det.height.data(),
                                          s.det.summary.defects, {s.T_rowmajor.data(), 1}, p,
                                          &plan)
                  .ok());
  const miem::TargetPlan thrown =
      miem::plan_targets(s.view(), s.det.labels.data(), s.det.height.data(), s.det.summary.defects,
                         {s.T_rowmajor.data(), 1}, p);
  ASSERT_EQ(plan.targets.size(), thrown.targets.size());
  EXPECT_EQ(plan.targets[0].position, thrown.targets[0].position);

  std::vector<double> scaled = s.T_rowmajor;
  scaled[0] *= 2.0;
  std::vector<double> nan = s.T_rowmajor;
  nan[5] = std::nan("");
  for (const std::vector<double>* bad : {&scaled, &nan}) {
    const miem::Status st = miem::nothrow::plan_targets(
        s.view(), s.det.labels.data(), s.det.height.data(), s.det.summary.defects,
        {bad->data(), 1}, p, &plan);
    EXPECT_EQ(st.code, miem::StatusCode::kInvalidParameter);
    EXPECT_EQ(std::string(st.message).rfind("T_base_sensor", 0), 0u) << st.message;
    EXPECT_THROW(miem::plan_targets(s.view(), s.det.labels.data(), s.det.height.data(),
                                    s.det.summary.defects, {bad->data(), 1}, p),
                 std::invalid_argument);
  }
  // two transforms for a 44-row grid: neither one nor one per profile
  std::vector<double> two(s.T_rowmajor);
  two.insert(two.end(), s.T_rowmajor.begin(), s.T_rowmajor.end());
  EXPECT_EQ(miem::nothrow::plan_targets(s.view(), s.det.labels.data(), s.det.height.data(),
                                        s.det.summary.defects, {two.data(), 2}, p, &plan)
                .code,
            miem::StatusCode::kInvalidParameter);
  miem::TargetParams bad_p;
  bad_p.tool_radius = -1.0;
  const miem::Status st =
      miem::nothrow::plan_targets(s.view(), s.det.labels.data(), s.det.height.data(),
                                  s.det.summary.defects, {s.T_rowmajor.data(), 1}, bad_p, &plan);
  EXPECT_EQ(st.code, miem::StatusCode::kInvalidParameter);
  EXPECT_EQ(std::string(st.message).rfind("tool_radius", 0), 0u);
  std::vector<miem::Defect> wrong = s.det.summary.defects;
  wrong[0].indices.push_back(s.rows * s.cols);
  EXPECT_EQ(miem::nothrow::plan_targets(s.view(), s.det.labels.data(), s.det.height.data(), wrong,
                                        {s.T_rowmajor.data(), 1}, p, &plan)
                .code,
            miem::StatusCode::kInvalidInput);
}

TEST(Targets, OrderPathUncrossesNearestNeighbour) {
  // From (30, 20): nearest neighbour goes (30,27) (34,34) (22,25) (46,20); 2-opt reverses the
  // first three into the shortest order.
  const std::vector<Eigen::Vector3d> pts = {{22, 25, 0}, {46, 20, 0}, {34, 34, 0}, {30, 27, 0}};
  const std::vector<int> order = miem::order_path(pts, Eigen::Vector3d(30, 20, 0));
  EXPECT_EQ(order, (std::vector<int>{0, 3, 2, 1}));
  EXPECT_TRUE(miem::order_path({}, Eigen::Vector3d(0, 0, 0)).empty());
}

}  // namespace
