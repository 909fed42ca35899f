// Building blocks of the clouds' batched and threaded work (cpp/src/radix_sort.hpp,
// parallel.hpp, cloud_kernels.hpp): the neighbour grid's radix sort with threads against
// std::stable_sort, the grid itself (threaded compactions) the same for any thread count, and
// PlaneBatch (a cell's plane fits solved together in vector code) against eigen_sym3 one
// matrix at a time, bit for bit.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <random>
#include <utility>
#include <vector>

#include "cloud_kernels.hpp"
#include "miem/neighbor_grid.hpp"
#include "radix_sort.hpp"

namespace {

bool same_bits(double a, double b) { return std::memcmp(&a, &b, sizeof a) == 0; }

// Keys below max_key with many repeats (stability shows), ids 0 .. n - 1.
std::vector<std::uint64_t> random_keys(std::size_t n, std::uint64_t max_key, std::mt19937_64& rng) {
  std::uniform_int_distribution<std::uint64_t> u(0, max_key);
  std::vector<std::uint64_t> keys(n);
  for (std::size_t i = 0; i < n; ++i) keys[i] = i % 5 == 0 && i > 0 ? keys[i / 2] : u(rng);
  return keys;
}

TEST(RadixSort, ThreadsSortAsStableSort) {
  std::mt19937_64 rng(11);
  // 200,003 keys (shares of unequal length); keys of 17 bits (2 passes), 40 bits (4 passes),
  // and 64 bits; and keys whose lowest 11 bits are all equal (a pass that moves nothing).
  for (const std::uint64_t max_key : {std::uint64_t{(1 << 17) - 1}, (std::uint64_t{1} << 40) - 1,
                                      ~std::uint64_t{0}, std::uint64_t{0}}) {
    const std::size_t n = 200003;
    std::vector<std::uint64_t> keys = max_key == 0 ? std::vector<std::uint64_t>(n)
                                                   : random_keys(n, max_key, rng);
    if (max_key == 0) {  // only bits 11 and up vary
      std::uniform_int_distribution<std::uint64_t> u(0, 999);
      for (auto& k : keys) k = (u(rng) << 11) | 5;
    }
    std::vector<std::pair<std::uint64_t, std::uint32_t>> want(n);
    for (std::size_t i = 0; i < n; ++i) want[i] = {keys[i], static_cast<std::uint32_t>(i)};
    std::stable_sort(want.begin(), want.end(),
                     [](const auto& a, const auto& b) { return a.first < b.first; });
    const std::uint64_t top = *std::max_element(keys.begin(), keys.end());
    for (int nt : {1, 2, 3, 8, 64}) {
      std::vector<std::uint64_t> k = keys, tk(n);
      std::vector<std::uint32_t> id(n), tid(n);
      for (std::size_t i = 0; i < n; ++i) id[i] = static_cast<std::uint32_t>(i);
      const bool in_tmp =
          miem::detail::radix_sort(k.data(), id.data(), tk.data(), tid.data(), n, top, nt);
      const std::vector<std::uint64_t>& gk = in_tmp ? tk : k;
      const std::vector<std::uint32_t>& gi = in_tmp ? tid : id;
      std::size_t bad = 0;
      for (std::size_t i = 0; i < n; ++i) bad += gk[i] != want[i].first || gi[i] != want[i].second;
      EXPECT_EQ(bad, 0u) << "max_key " << max_key << ", " << nt << " threads";
    }
  }
}

TEST(NeighborGrid, SameCellsForAnyThreadCount) {
  // 200,003 points (5 % of rows NaN) on a bumpy sheet: the threaded compactions (finite rows,
  // occupied cells) and sort must give one grid
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(0.0, 40.0);
  const std::ptrdiff_t n = 200003;
  std::vector<double> xyz(3 * n);
  for (std::ptrdiff_t i = 0; i < n; ++i) {
    const double x = u(rng), y = u(rng);
    xyz[3 * i] = i % 20 == 7 ? std::nan("") : x;
    xyz[3 * i + 1] = y;
    xyz[3 * i + 2] = 0.1 * std::sin(x) * std::cos(y);
  }
  const miem::PointsView<double> v{xyz.data(), n, 3, 1};
  const miem::NeighborGrid<double> one(v, 0.25, 1);
  ASSERT_EQ(one.num_indexed(), n - n / 20 - (n % 20 > 7 ? 1 : 0));
  for (int nt : {2, 3, 8}) {
    const miem::NeighborGrid<double> g(v, 0.25, nt);
    ASSERT_EQ(g.num_indexed(), one.num_indexed());
    ASSERT_EQ(g.num_cells(), one.num_cells());
    EXPECT_TRUE(std::equal(g.order(), g.order() + g.num_indexed(), one.order())) << nt;
    std::size_t bad = 0;
    for (std::ptrdiff_t c = 0; c <= g.num_cells(); ++c) bad += g.cell_begin(c) != one.cell_begin(c);
    EXPECT_EQ(bad, 0u) << nt << " threads";
  }
  // every finite row once, ascending within a cell
  std::vector<std::uint32_t> rows(one.order(), one.order() + one.num_indexed());
  for (std::ptrdiff_t c = 0; c < one.num_cells(); ++c) {
    const std::uint32_t* o = one.order();
    EXPECT_TRUE(std::is_sorted(o + one.cell_begin(c), o + one.cell_begin(c + 1)));
  }
  std::sort(rows.begin(), rows.end());
  std::size_t k = 0, bad = 0;
  for (std::ptrdiff_t i = 0; i < n; ++i) {
    if (i % 20 == 7) continue;
    bad += rows[k++] != static_cast<std::uint32_t>(i);
  }
  EXPECT_EQ(bad, 0u);
}

// A symmetric matrix from a random cloud of `n` points: flat, a line, one point, or isotropic.
Eigen::Matrix3d scatter_of(int kind, std::mt19937& rng) {
  std::normal_distribution<double> g(0.0, 1.0);
  Eigen::Matrix3d M = Eigen::Matrix3d::Zero();
  for (int k = 0; k < 40; ++k) {
    Eigen::Vector3d q(g(rng), g(rng), g(rng));
    if (kind == 0) q.z() *= 1e-3;                      // a plane with noise
    if (kind == 1) q = Eigen::Vector3d(q.x(), 0, 0);   // a line
    if (kind == 2) q.setZero();                        // one point
    if (kind == 4) q.y() *= 1e-9, q.z() *= 1e-9;       // nearly a line
    M += q * q.transpose();
  }
  if (kind == 5) M = Eigen::Matrix3d::Identity();     // equal eigenvalues
  return M;
}

TEST(PlaneBatch, SameBitsAsEigenSym3) {
  std::mt19937 rng(5);
  std::vector<Eigen::Matrix3d> ms;
  for (int k = 0; k < 300; ++k) ms.push_back(scatter_of(k % 6, rng));
  for (bool all : {false, true}) {
    miem::cloud::PlaneBatch pb;
    pb.reserve(static_cast<std::ptrdiff_t>(ms.size()));
    for (const auto& M : ms) pb.add(M);
    pb.solve();
    std::size_t bad = 0;
    for (std::size_t i = 0; i < ms.size(); ++i) {
      Eigen::Vector3d w1, w2;
      Eigen::Matrix3d V1 = Eigen::Matrix3d::Zero(), V2 = Eigen::Matrix3d::Zero();
      miem::cloud::eigen_sym3(ms[i], w1, V1, all);
      pb.eig(static_cast<int>(i), w2, V2, all);
      const int cols = all ? 3 : 1;
      bool same = true;
      for (int a = 0; a < 3; ++a) {
        same &= same_bits(w1(a), w2(a));
        for (int c = 0; c < cols; ++c) same &= same_bits(V1(a, c), V2(a, c));
      }
      bad += !same;
    }
    EXPECT_EQ(bad, 0u) << (all ? "with" : "without") << " the other eigenvectors";
  }
}

}  // namespace
