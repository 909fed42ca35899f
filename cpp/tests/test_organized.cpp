// Organized detection against expectations computed by the NumPy reference (data/*.txt, written
// by data/make_expectations.py): labels and flags exactly, floats within tight tolerances.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdint>
#include <limits>
#include <string>
#include <utility>
#include <vector>

#include <Eigen/Eigenvalues>

#include "miem/organized.hpp"
#include "test_util.hpp"

namespace {

using miem::test::Expectation;

constexpr double kAngleTol = 1e-9;   // degrees (files keep 12 significant digits)
constexpr double kHeightTol = 1e-9;  // grid units

std::string data_path(const std::string& name) {
  return std::string(MIEM_TEST_DATA_DIR) + "/" + name + ".txt";
}

void expect_close_or_nan(double got, double want, double tol, const char* what, std::size_t i) {
  if (std::isnan(want)) {
    EXPECT_TRUE(std::isnan(got)) << what << "[" << i << "]: want NaN, got " << got;
  } else {
    EXPECT_NEAR(got, want, tol) << what << "[" << i << "]";
  }
}

template <typename T>
miem::DetectResult run_case(const Expectation& e, std::vector<T>* storage) {
  storage->assign(e.grid.begin(), e.grid.end());
  return miem::detect_organized(miem::GridView<T>::dense(storage->data(), e.rows, e.cols),
                                e.params);
}

void check_case(const Expectation& e, const miem::DetectResult& res) {
  const std::size_t n = static_cast<std::size_t>(e.rows * e.cols);
  ASSERT_EQ(res.labels.size(), n);
  std::size_t label_mismatch = 0;
  for (std::size_t i = 0; i < n; ++i) {
    if (res.labels[i] != e.labels[i]) {
      ++label_mismatch;
      ADD_FAILURE() << e.name << ": label at (" << i / e.cols << ", " << i % e.cols << ") is "
                    << int(res.labels[i]) << ", reference " << e.labels[i];
    }
    EXPECT_EQ(res.flags[i], e.flags[i]) << e.name << ": flags at " << i;
    expect_close_or_nan(res.angle_deg[i], e.angle[i], kAngleTol, "angle", i);
    expect_close_or_nan(res.height[i], e.height[i], kHeightTol, "height", i);
  }
  EXPECT_EQ(label_mismatch, 0u);
  EXPECT_EQ(res.summary.iterations, e.iterations) << e.name;
  ASSERT_EQ(res.summary.plane.has_value(), e.has_plane) << e.name;
  if (e.has_plane) {
    const miem::Plane& p = *res.summary.plane;
    for (int k = 0; k < 3; ++k) EXPECT_NEAR(p.normal(k), e.normal[k], 1e-12) << e.name;
    EXPECT_NEAR(p.d, e.d, 1e-10) << e.name;
    EXPECT_NEAR(p.rms, e.rms, 1e-10) << e.name;
    EXPECT_EQ(p.n_points, e.n_points) << e.name;
  }
  ASSERT_EQ(res.summary.defects.size(), e.defects.size()) << e.name;
  for (std::size_t k = 0; k < e.defects.size(); ++k) {
    const miem::Defect& d = res.summary.defects[k];
    EXPECT_EQ(std::string(miem::to_string(d.kind)), e.defects[k].kind) << e.name << " defect " << k;
    expect_close_or_nan(d.peak_height, e.defects[k].peak_height, kHeightTol, "peak", k);
    EXPECT_EQ(d.indices, e.defects[k].indices) << e.name << " defect " << k;
    EXPECT_EQ(d.id, static_cast<int>(k));
  }
}

class ReferenceCase : public ::testing::TestWithParam<std::string> {};

TEST_P(ReferenceCase, MatchesNumpyReference) {
  const Expectation e = miem::test::read_expectation(data_path(GetParam()));
  ASSERT_EQ(e.name, GetParam());
  if (e.dtype == "float32") {
    std::vector<float> g;
    check_case(e, run_case(e, &g));
  } else {
    std::vector<double> g;
    check_case(e, run_case(e, &g));
  }
}

INSTANTIATE_TEST_SUITE_P(Expectations, ReferenceCase,
                         ::testing::Values("spikes", "dropouts", "edges", "min_step", "cascade",
                                           "float32"));

// A dense H x W grid's copy with the coordinates in separate planes, each column-major (cell
// (r, c)'s coordinate k at k * H * W + c * H + r): a strided view reads it as the same scan.
std::vector<double> column_major_planes(const std::vector<double>& g, std::ptrdiff_t H,
                                        std::ptrdiff_t W) {
  std::vector<double> soa(g.size());
  for (std::ptrdiff_t r = 0; r < H; ++r)
    for (std::ptrdiff_t c = 0; c < W; ++c)
      for (int k = 0; k < 3; ++k)
        soa[static_cast<std::size_t>(k * H * W + c * H + r)] =
            g[static_cast<std::size_t>((r * W + c) * 3 + k)];
  return soa;
}

// Detection of a dense grid and of the same scan through a strided view of its
// column_major_planes copy.
std::pair<miem::DetectResult, miem::DetectResult> dense_and_strided(
    const std::vector<double>& g, std::ptrdiff_t H, std::ptrdiff_t W, const miem::DetectParams& p) {
  const std::vector<double> soa = column_major_planes(g, H, W);
  return {miem::detect_organized(miem::GridView<double>::dense(g.data(), H, W), p),
          miem::detect_organized(miem::GridView<double>{soa.data(), H, W, 1, H, H * W}, p)};
}

// The same scan through a strided view (columns-major copy, coordinates in separate planes):
// the view reads caller memory as it lies, with identical results.
TEST(Organized, StridedViewEqualsDense) {
  const Expectation e = miem::test::read_expectation(data_path("dropouts"));
  const std::ptrdiff_t H = e.rows, W = e.cols;
  const std::vector<double> soa = column_major_planes(e.grid, H, W);
  const miem::GridView<double> view{soa.data(), H, W, /*row*/ 1, /*col*/ H, /*coord*/ H * W};
  const miem::DetectResult res = miem::detect_organized(view, e.params);
  check_case(e, res);
}

// The MIEM plane of a dense double grid (summed 8 cells a step: AVX-512 where the CPU has it)
// and of the same scan through a strided view (the portable loop) has the same bits, rows of
// 53 cells (not a multiple of 8) with dropouts and defects; and it is the eigen fit of the
// NORMAL and EDGE points computed here in long double.
TEST(Organized, MiemPlaneOfDenseAndStridedGridsIsTheFitOfTheKeptPoints) {
  const std::ptrdiff_t H = 37, W = 53;
  std::vector<double> g(static_cast<std::size_t>(3 * H * W));
  std::uint64_t seed = 12345;
  const auto noise = [&seed] {
    seed = seed * 6364136223846793005ULL + 1442695040888963407ULL;
    return static_cast<double>(seed >> 11) / 9007199254740992.0 - 0.5;
  };
  for (std::ptrdiff_t r = 0; r < H; ++r) {
    for (std::ptrdiff_t c = 0; c < W; ++c) {
      double* q = g.data() + 3 * (r * W + c);
      q[0] = 1000.0 + 0.1 * c, q[1] = -50.0 + 0.1 * r;
      q[2] = 20.0 + 0.03 * c - 0.02 * r + 0.002 * noise();
      if ((r * 7 + c * 3) % 41 == 0) q[2] += 0.5;                         // spikes
      if ((r * 5 + c) % 67 == 0) q[0] = q[1] = q[2] = std::nan("");      // dropouts
    }
  }
  const auto [dense, strided] = dense_and_strided(g, H, W, miem::paper_params());
  ASSERT_EQ(dense.labels, strided.labels);
  ASSERT_TRUE(dense.summary.plane.has_value() && strided.summary.plane.has_value());
  const miem::Plane &a = *dense.summary.plane, &b = *strided.summary.plane;
  for (int k = 0; k < 3; ++k) {
    EXPECT_EQ(a.normal(k), b.normal(k));
    EXPECT_EQ(a.centroid(k), b.centroid(k));
    EXPECT_EQ(a.eigenvalues(k), b.eigenvalues(k));
  }
  EXPECT_EQ(a.d, b.d);
  EXPECT_EQ(a.rms, b.rms);
  // the fit of the kept points, in long double
  long double n = 0, s[3] = {0, 0, 0};
  std::size_t abnormal = 0;
  for (std::ptrdiff_t i = 0; i < H * W; ++i) {
    const std::uint8_t l = dense.labels[static_cast<std::size_t>(i)];
    abnormal += l == miem::kAbnormal;
    if (l != miem::kNormal && l != miem::kEdge) continue;
    n += 1;
    for (int k = 0; k < 3; ++k) s[k] += g[static_cast<std::size_t>(3 * i + k)];
  }
  ASSERT_GT(abnormal, 10u);  // the spikes are out of the fit
  long double sc[3][3] = {};
  for (std::ptrdiff_t i = 0; i < H * W; ++i) {
    const std::uint8_t l = dense.labels[static_cast<std::size_t>(i)];
    if (l != miem::kNormal && l != miem::kEdge) continue;
    long double d[3];
    for (int k = 0; k < 3; ++k) d[k] = g[static_cast<std::size_t>(3 * i + k)] - s[k] / n;
    for (int j = 0; j < 3; ++j)
      for (int k = 0; k < 3; ++k) sc[j][k] += d[j] * d[k];
  }
  Eigen::Matrix3d m;
  for (int j = 0; j < 3; ++j)
    for (int k = 0; k < 3; ++k) m(j, k) = static_cast<double>(sc[j][k]);
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(m);
  EXPECT_EQ(a.n_points, static_cast<std::int64_t>(n));
  for (int k = 0; k < 3; ++k) {
    EXPECT_NEAR(a.centroid(k), static_cast<double>(s[k] / n), 1e-12 * std::abs(a.centroid(k)));
    EXPECT_NEAR(a.eigenvalues(k), es.eigenvalues()(k), 1e-9 * es.eigenvalues()(2));
  }
  EXPECT_NEAR(std::abs(a.normal.dot(es.eigenvectors().col(0))), 1.0, 1e-12);
}

// Pass 1's finiteness (AVX-512 on a dense double grid, 8 cells a step; the portable loop on a
// strided view): a cell is INVALID exactly when one of its coordinates is NaN or infinite, at
// every position of a block of 8 and in a row's last cells (rows of 21: 2 blocks and 5 more).
TEST(Organized, InvalidCellsAreThoseWithANonFiniteCoordinate) {
  const std::ptrdiff_t H = 9, W = 21;
  std::vector<double> g(static_cast<std::size_t>(3 * H * W));
  for (std::ptrdiff_t r = 0; r < H; ++r)
    for (std::ptrdiff_t c = 0; c < W; ++c) {
      double* q = g.data() + 3 * (r * W + c);
      q[0] = 0.5 * c, q[1] = 0.5 * r, q[2] = 0.01 * ((r * 5 + c * 3) % 7);
    }
  const double bad[3] = {std::nan(""), std::numeric_limits<double>::infinity(),
                         -std::numeric_limits<double>::infinity()};
  std::vector<std::uint8_t> want(static_cast<std::size_t>(H * W), 0);
  for (std::ptrdiff_t i = 0; i < H * W; ++i) {
    if ((i * 7) % 5 != 0) continue;  // 1 cell in 5, at every position of the blocks
    g[static_cast<std::size_t>(3 * i + i % 3)] = bad[(i / 3) % 3];
    want[static_cast<std::size_t>(i)] = 1;
  }
  const auto [dense, strided] = dense_and_strided(g, H, W, miem::paper_params());
  for (std::ptrdiff_t i = 0; i < H * W; ++i) {
    EXPECT_EQ(dense.labels[static_cast<std::size_t>(i)] == miem::kInvalid,
              want[static_cast<std::size_t>(i)] == 1) << "cell " << i;
  }
  EXPECT_EQ(dense.labels, strided.labels);
}

TEST(Organized, FloatAndDoubleAgreeOnFloatData) {
  const Expectation e = miem::test::read_expectation(data_path("float32"));
  std::vector<float> gf;
  std::vector<double> gd;
  const miem::DetectResult rf = run_case(e, &gf);
  const miem::DetectResult rd = run_case(e, &gd);
  EXPECT_EQ(rf.labels, rd.labels);
  EXPECT_EQ(rf.flags, rd.flags);
}

TEST(Organized, ReusedDetectorGivesTheSameResult) {
  const Expectation e = miem::test::read_expectation(data_path("cascade"));
  miem::OrganizedDetector det(e.params);
  const auto view = miem::GridView<double>::dense(e.grid.data(), e.rows, e.cols);
  std::vector<std::uint8_t> a(e.grid.size() / 3), b(a.size());
  det.run(view, miem::OrganizedOutput{a.data()});
  det.run(view, miem::OrganizedOutput{b.data()});
  EXPECT_EQ(a, b);
  for (std::size_t i = 0; i < a.size(); ++i) EXPECT_EQ(a[i], e.labels[i]);
}

// The workspace is not cleared between runs (nor zeroed when it grows): a run after another
// grid of the same size, with other dropouts and defects, gives a fresh detector's bits.
TEST(Organized, DetectorReusedAfterAnotherGridGivesFreshBits) {
  for (const char* name : {"edges", "dropouts", "min_step"}) {
    const Expectation e = miem::test::read_expectation(data_path(name));
    std::vector<double> other = e.grid;
    for (std::size_t i = 0; i < other.size() / 3; ++i) {
      if (i % 5 == 0) other[3 * i] = std::nan("");
      if (i % 3 == 0) other[3 * i + 2] += 2.0;
    }
    const auto view = miem::GridView<double>::dense(e.grid.data(), e.rows, e.cols);
    const miem::DetectResult fresh = miem::detect_organized(view, e.params);
    miem::OrganizedDetector det(e.params);
    const std::size_t n = e.grid.size() / 3;
    std::vector<std::uint8_t> labels(n), flags(n);
    std::vector<double> angle(n), height(n);
    const miem::OrganizedOutput out{labels.data(), flags.data(), angle.data(), height.data()};
    det.run(miem::GridView<double>::dense(other.data(), e.rows, e.cols), out);
    det.run(view, out);
    EXPECT_EQ(labels, fresh.labels) << name;
    EXPECT_EQ(flags, fresh.flags) << name;
    for (std::size_t i = 0; i < n; ++i) {
      ASSERT_EQ(std::isnan(height[i]), std::isnan(fresh.height[i])) << name << " " << i;
      if (!std::isnan(height[i])) ASSERT_EQ(height[i], fresh.height[i]) << name << " " << i;
    }
    for (std::size_t i = 0; i < n; ++i) ASSERT_EQ(labels[i], e.labels[i]) << name << " " << i;
  }
}

TEST(Organized, ThrowsOnBadInput) {
  miem::DetectParams p;
  std::vector<double> g(4 * 4 * 3, std::nan(""));
  const auto view = miem::GridView<double>::dense(g.data(), 4, 4);
  EXPECT_THROW(miem::detect_organized(view, p), std::invalid_argument);  // no finite point
  const auto empty = miem::GridView<double>::dense(g.data(), 0, 4);
  EXPECT_THROW(miem::detect_organized(empty, p), std::invalid_argument);
  p.theta0_deg = 180.0;
  EXPECT_THROW(miem::OrganizedDetector{p}, std::invalid_argument);
  p = {};
  p.scales = {};
  EXPECT_THROW(miem::validate(p), std::invalid_argument);
  p = {};
  p.window = 4;
  EXPECT_THROW(miem::validate(p), std::invalid_argument);
}

// SPEC "z_resolution": on a sheet sampled every 0.5 mm and rising 0.15 mm from one cell to the
// next along the profiles, no two neighbours lie one z step apart; two cells of the first rows do
// (pooled): "auto" is the 1 um step, not the slope's difference.
TEST(Organized, AutoZResolutionIsTheStepOnASteepSheet) {
  const std::ptrdiff_t H = 40, W = 30;
  std::vector<double> g(static_cast<std::size_t>(H * W * 3));
  double smallest_step = 1e300;
  for (std::ptrdiff_t r = 0; r < H; ++r) {
    for (std::ptrdiff_t c = 0; c < W; ++c) {
      double* p = &g[static_cast<std::size_t>((r * W + c) * 3)];
      const long wobble = (r * 7 + c * 13) % 11 - 5;  // -5 .. 5 um, no pattern along a profile
      p[0] = 0.5 * c, p[1] = 0.5 * r, p[2] = std::round(150.0 * c + wobble + 3.0 * r) * 0.001;
      if (c > 0) smallest_step = std::min(smallest_step, std::abs(p[2] - p[-1]));
    }
  }
  ASSERT_GT(smallest_step, 0.1);  // what the neighbours alone would say
  const auto view = miem::GridView<double>::dense(g.data(), H, W);
  EXPECT_NEAR(miem::auto_z_resolution(view), 0.001, 1e-12);
  miem::DetectParams p;
  p.z_resolution_auto = true;
  EXPECT_NEAR(miem::detect_organized(view, p).summary.z_resolution, 0.001, 1e-12);
}

// SPEC "Edge test" step 6, ledges: material bent out level 0.08 mm below a wall top (floor 2 mm
// down, 0.1 mm grid), columns 20-22 of rows 4-35, is ABNORMAL with the default detector: its
// cells lie level, the top steps down onto them and beyond them the wall drops 1.9 mm. It droops
// gentler than 45 degrees from the top's last sample (0.08 < 0.1 mm), so only the ledge rule
// sees it. A level band 6 columns wide (wider than a burr) stays clean.
TEST(Organized, LedgeBentOutBelowAWallTopIsAbnormal) {
  const std::ptrdiff_t H = 40, W = 40;
  for (const std::ptrdiff_t width : {3, 6}) {
    std::vector<double> g(static_cast<std::size_t>(H * W * 3));
    for (std::ptrdiff_t r = 0; r < H; ++r) {
      for (std::ptrdiff_t c = 0; c < W; ++c) {
        double* p = &g[static_cast<std::size_t>((r * W + c) * 3)];
        const double wobble = 0.001 * static_cast<double>((r * 7 + c * 13) % 5 - 2);  // +-2 um
        const bool ledge = r >= 4 && r < H - 4 && c >= 20 && c < 20 + width;
        p[0] = 0.1 * static_cast<double>(c), p[1] = 0.1 * static_cast<double>(r);
        p[2] = wobble + (ledge ? -0.08 : (c >= 20 ? -2.0 : 0.0));
      }
    }
    const auto view = miem::GridView<double>::dense(g.data(), H, W);
    const miem::DetectResult res = miem::detect_organized(view, miem::DetectParams{});
    int found = 0, inner = 0, outside = 0;
    for (std::ptrdiff_t r = 0; r < H; ++r) {
      for (std::ptrdiff_t c = 0; c < W; ++c) {
        const bool abnormal = res.labels[static_cast<std::size_t>(r * W + c)] == miem::kAbnormal;
        const bool ledge = r >= 4 && r < H - 4 && c >= 20 && c < 20 + width;
        if (ledge && r >= 11 && r < H - 11) inner += 1, found += abnormal;
        if (!ledge) outside += abnormal;
      }
    }
    EXPECT_EQ(outside, 0) << width;
    if (width == 3) EXPECT_EQ(found, inner);
    else EXPECT_EQ(found, 0);
  }
}

}  // namespace
