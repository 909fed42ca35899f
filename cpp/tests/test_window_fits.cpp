// Window planes of the sweep (cpp/src/window_fits.hpp) against a direct eigen fit of each
// window computed here (Eigen's SelfAdjointEigenSolver on the two-pass scatter): dense and sparse
// requests (the running-sum tiles and the per-cell path), far from the origin, with dropouts and
// feature-line cells, and the same bits for any thread count.
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <vector>

#include <Eigen/Eigenvalues>

#include "window_fits.hpp"

namespace {

struct Scene {
  std::ptrdiff_t H = 150, W = 300;
  std::vector<double> xyz;
  std::vector<std::uint8_t> cls;
};

Scene make_scene(unsigned seed, std::ptrdiff_t H = 150, std::ptrdiff_t W = 300) {
  Scene s;
  s.H = H;
  s.W = W;
  std::mt19937 rng(seed);
  std::normal_distribution<double> noise(0.0, 0.01);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  s.xyz.resize(static_cast<std::size_t>(s.H * s.W * 3));
  s.cls.resize(static_cast<std::size_t>(s.H * s.W));
  for (std::ptrdiff_t r = 0; r < s.H; ++r) {
    for (std::ptrdiff_t c = 0; c < s.W; ++c) {
      const std::ptrdiff_t i = r * s.W + c;
      const double x = 1200.0 + 0.2 * c, y = -300.0 + 0.25 * r;
      const double z = 450.0 + 0.1 * x - 0.05 * y + 0.3 * std::sin(0.05 * c) + noise(rng);
      s.xyz[3 * i] = x;
      s.xyz[3 * i + 1] = y;
      s.xyz[3 * i + 2] = z;
      const double v = u(rng);
      s.cls[i] = v < 0.85 ? miem::detail::kInPlane : (v < 0.9 ? miem::detail::kLine : 0);
      if (v > 0.99) s.xyz[3 * i + 2] = std::numeric_limits<double>::quiet_NaN();  // dropout
      if (v > 0.99) s.cls[i] = 0;
    }
  }
  return s;
}

// The window plane of cell (r, c) from its NORMAL cells, fitted directly.
bool direct(const Scene& s, std::ptrdiff_t r, std::ptrdiff_t c, int half, double* h, double* l0,
            double* edges) {
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  int n = 0;
  *edges = 0.0;
  auto at = [&](std::ptrdiff_t rr, std::ptrdiff_t cc) {
    const double* p = &s.xyz[3 * (rr * s.W + cc)];
    return Eigen::Vector3d(p[0], p[1], p[2]);
  };
  for (std::ptrdiff_t rr = std::max<std::ptrdiff_t>(0, r - half); rr <= std::min(s.H - 1, r + half); ++rr)
    for (std::ptrdiff_t cc = std::max<std::ptrdiff_t>(0, c - half); cc <= std::min(s.W - 1, c + half); ++cc) {
      const std::uint8_t k = s.cls[rr * s.W + cc];
      if (k & miem::detail::kInPlane) {
        sum += at(rr, cc);
        ++n;
      } else if (k & miem::detail::kLine) {
        *edges += 1.0;
      }
    }
  if (n < 3) return false;
  const Eigen::Vector3d mean = sum / n;
  Eigen::Matrix3d M = Eigen::Matrix3d::Zero();
  for (std::ptrdiff_t rr = std::max<std::ptrdiff_t>(0, r - half); rr <= std::min(s.H - 1, r + half); ++rr)
    for (std::ptrdiff_t cc = std::max<std::ptrdiff_t>(0, c - half); cc <= std::min(s.W - 1, c + half); ++cc)
      if (s.cls[rr * s.W + cc] & miem::detail::kInPlane) {
        const Eigen::Vector3d q = at(rr, cc) - mean;
        M += q * q.transpose();
      }
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(M);
  Eigen::Vector3d nv = es.eigenvectors().col(0);
  if (nv.z() < 0) nv = -nv;
  *h = nv.dot(at(r, c) - mean);
  *l0 = es.eigenvalues()(0);
  return true;
}

std::vector<double> sweep(const Scene& s, int window, int threads, std::ptrdiff_t every) {
  const auto g = miem::GridView<double>::dense(s.xyz.data(), s.H, s.W);
  std::vector<double> h(static_cast<std::size_t>(s.H * s.W), -1e300);
  std::vector<miem::detail::FitScratch> scratch;
  miem::detail::window_fits(
      g, s.cls.data(), window, threads, scratch,
      [&](std::ptrdiff_t i) { return i % every == 0 && std::isfinite(s.xyz[3 * i + 2]); },
      [&](std::ptrdiff_t i, const miem::detail::WindowFit& f) {
        h[i] = f.ok ? f.height : std::numeric_limits<double>::quiet_NaN();
      });
  return h;
}

TEST(WindowFits, DenseAndSparseEqualDirectFits) {
  const Scene s = make_scene(7);
  for (std::ptrdiff_t every : {1, 97}) {  // every cell (tile sums), or a few per tile (direct)
    for (int window : {5, 21}) {
      const std::vector<double> h = sweep(s, window, 1, every);
      int checked = 0;
      for (std::ptrdiff_t i = 0; i < s.H * s.W; i += 7) {
        if (i % every != 0 || !std::isfinite(s.xyz[3 * i + 2])) {
          EXPECT_EQ(h[i], -1e300) << "a cell that was not asked for was visited";
          continue;
        }
        double hd, l0, edges;
        const bool ok = direct(s, i / s.W, i % s.W, window / 2, &hd, &l0, &edges);
        ASSERT_EQ(ok, std::isfinite(h[i])) << i;
        if (ok) {
          EXPECT_NEAR(h[i], hd, 1e-9) << "cell " << i << " window " << window;
          ++checked;
        }
      }
      EXPECT_GT(checked, 10);
    }
  }
}

TEST(WindowFits, SameBitsForAnyThreadCount) {
  const Scene s = make_scene(11, 300, 300);  // enough cells for two threads
  const std::vector<double> a = sweep(s, 21, 1, 1), b = sweep(s, 21, 2, 1);
  for (std::size_t i = 0; i < a.size(); ++i) {
    if (std::isnan(a[i])) {
      EXPECT_TRUE(std::isnan(b[i]));
    } else {
      EXPECT_EQ(a[i], b[i]) << i;
    }
  }
}

TEST(WindowFits, VectorisedSolveMatchesScalarRoutine) {
  // Random scatter matrices of flat, curved and isotropic windows: the fixed-step solve either
  // agrees with smallest_eigenpair (run to convergence) or asks for the scalar routine.
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  constexpr std::ptrdiff_t cap = 64;
  std::vector<double> S(miem::detail::kMoments * cap), Q(3 * cap), F(4 * cap);
  std::vector<std::uint8_t> ok(cap), redo(cap);
  int compared = 0;
  for (int round = 0; round < 20; ++round) {
    for (std::ptrdiff_t m = 0; m < cap; ++m) {
      const double flat = std::pow(10.0, -6.0 * (u(rng) + 1.0) / 2.0);  // 1 .. 1e-6
      double s[miem::detail::kMoments] = {0};
      for (int k = 0; k < 40; ++k) {
        const double x = u(rng), y = u(rng), z = flat * u(rng) + 0.1 * x;
        const double v[10] = {1, x, y, z, x * x, x * y, x * z, y * y, y * z, z * z};
        for (int j = 0; j < 10; ++j) s[j] += v[j];
      }
      for (int j = 0; j < miem::detail::kMoments; ++j) S[j * cap + m] = s[j];
      Q[m] = u(rng), Q[cap + m] = u(rng), Q[2 * cap + m] = 0.1 * u(rng);
    }
    miem::detail::solve_fits(cap, cap, S.data(), Q.data(), F.data(), ok.data(), redo.data());
    for (std::ptrdiff_t m = 0; m < cap; ++m) {
      double s[miem::detail::kMoments];
      for (int j = 0; j < miem::detail::kMoments; ++j) s[j] = S[j * cap + m];
      const miem::detail::WindowFit f =
          miem::detail::fit_from_sums(s, Eigen::Vector3d(Q[m], Q[cap + m], Q[2 * cap + m]));
      if (redo[m]) continue;
      ++compared;
      ASSERT_EQ(f.ok, ok[m] != 0);
      EXPECT_NEAR(F[m], f.height, 1e-12);
      EXPECT_NEAR(F[cap + m], f.l0, 1e-12 * (f.l1 + f.l2));
    }
  }
  EXPECT_GT(compared, 20 * cap / 2);  // the fixed steps suffice for most (flat) windows
}

}  // namespace
