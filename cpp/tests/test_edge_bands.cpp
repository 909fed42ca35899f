// The edge test's row verdicts (cpp/src/edge_test.hpp edge_judge_row) do not depend on how a
// row's candidates are grouped: band blocks (with and without the band cache that reuses row
// rr - r - 1's lower bands as row rr's upper ones), chunks and single cells give the same marks.
// Batch and stream detection group a row differently (their C1 differ), so stream == batch
// rests on this. The reference here is one call per candidate cell (todo holds that cell only):
// never banded (one cell saves no rectangles), no cache.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdint>
#include <random>
#include <vector>

#include "edge_test.hpp"
#include "miem/organized.hpp"

namespace {

using miem::detail::EdgeBandCache;
using miem::detail::EdgeImages;
using miem::detail::kEdgeBandCells;
using miem::detail::kEdgeCacheSlot;
using miem::detail::kEdgeMoments;

struct Scene {
  std::ptrdiff_t H, W;
  std::vector<double> xyz;
  std::vector<std::uint8_t> labels;
};

// A crease (a fold along a column) and a cut edge (a step along a row) under noise, with
// burrs on both, drop-outs (INVALID) and a few EDGE and ABNORMAL cells.
Scene make_scene(std::ptrdiff_t H, std::ptrdiff_t W, unsigned seed) {
  Scene s{H, W, std::vector<double>(static_cast<std::size_t>(H * W * 3)),
          std::vector<std::uint8_t>(static_cast<std::size_t>(H * W), miem::kNormal)};
  std::mt19937 rng(seed);
  std::normal_distribution<double> noise(0.0, 0.01);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  const std::ptrdiff_t fold = W / 2, step = (3 * H) / 5;
  for (std::ptrdiff_t r = 0; r < H; ++r) {
    for (std::ptrdiff_t c = 0; c < W; ++c) {
      const std::size_t i = static_cast<std::size_t>(r * W + c);
      double z = 0.4 * static_cast<double>(std::max<std::ptrdiff_t>(0, c - fold)) + noise(rng);
      if (r >= step) z -= 3.0;
      if ((c == fold || r == step - 1) && u(rng) < 0.3) z += 0.4 + 0.4 * u(rng);  // burrs
      s.xyz[3 * i] = 1000.0 + static_cast<double>(c);
      s.xyz[3 * i + 1] = -500.0 + static_cast<double>(r);
      s.xyz[3 * i + 2] = z;
      const double p = u(rng);
      if (p < 0.02) {
        s.xyz[3 * i] = s.xyz[3 * i + 1] = s.xyz[3 * i + 2] = std::nan("");
        s.labels[i] = miem::kInvalid;
      } else if (p < 0.04) {
        s.labels[i] = miem::kEdge;
      } else if (p < 0.05) {
        s.labels[i] = miem::kAbnormal;
      }
    }
  }
  return s;
}

// The grid as one tile (H <= 64 + 2 r rows, W <= 128 + 2 r columns): images over all of it
// from its first finite cell, as edge passes build them.
struct Images {
  std::vector<double> data;
  EdgeImages im;
  Eigen::Vector3d o;
};

Images build_images(const miem::GridView<double>& g, const std::uint8_t* labels) {
  const std::ptrdiff_t H = g.rows, W = g.cols, L = W + 1, plane = (H + 1) * L;
  Images out;
  out.data.assign(static_cast<std::size_t>(kEdgeMoments * plane), 0.0);
  std::vector<double> col(static_cast<std::size_t>(kEdgeMoments * W), 0.0);
  out.o = Eigen::Vector3d::Zero();
  for (std::ptrdiff_t i = 0; i < H * W; ++i) {
    if (g.finite(i / W, i % W)) {
      out.o = g(i / W, i % W);
      break;
    }
  }
  for (std::ptrdiff_t rr = 0; rr < H; ++rr) {
    miem::detail::edge_image_row(g, rr, labels + rr * W, 0, W, out.o, col.data(), W,
                                 out.data.data() + (rr + 1) * L, plane);
  }
  out.im = EdgeImages{out.data.data(), plane, L, 0, H + 1, 0};
  return out;
}

struct Case {
  std::ptrdiff_t H, W, r;
  unsigned seed;
};

class EdgeBands : public ::testing::TestWithParam<Case> {};

TEST_P(EdgeBands, GroupingDoesNotChangeVerdicts) {
  const Case cs = GetParam();
  const Scene s = make_scene(cs.H, cs.W, cs.seed);
  const std::ptrdiff_t H = cs.H, W = cs.W, r = cs.r;
  const miem::detail::EdgeTol k{2.5, 0.0};
  const auto g = miem::GridView<double>::dense(s.xyz.data(), H, W);
  const Images img = build_images(g, s.labels.data());
  const std::vector<std::uint8_t> ones(static_cast<std::size_t>(W), 1);
  const std::ptrdiff_t nblk = (W + kEdgeBandCells - 1) / kEdgeBandCells;
  std::vector<double> slots(static_cast<std::size_t>((r + 2) * nblk * kEdgeCacheSlot));
  const EdgeBandCache cache{slots.data(), (r + 2) * nblk};
  {  // the cache as the previous tile left it (another scene), then cleared, as edge passes do
    const Scene prev = make_scene(H, W, cs.seed + 100);
    const auto gp = miem::GridView<double>::dense(prev.xyz.data(), H, W);
    const Images ip = build_images(gp, prev.labels.data());
    std::vector<std::uint8_t> mk(static_cast<std::size_t>(W));
    cache.clear();
    for (std::ptrdiff_t rr = 0; rr < H; ++rr) {
      miem::detail::edge_judge_row(gp, rr, rr, H, 0, W, ip.im, ip.o, r, k, prev.labels.data(),
                                   ones.data(), mk.data(), &cache);
    }
  }
  cache.clear();
  std::vector<std::uint8_t> cached(static_cast<std::size_t>(W)), plain(cached), last(cached),
      one(cached), todo1(static_cast<std::size_t>(W), 0), sparse(cached), todos(cached);
  // later passes: scattered candidates (todo on 4 cells in 5): banded blocks whose cells are
  // not consecutive (the shortcut picks their bounds out of the span's positions)
  std::mt19937 rng(static_cast<unsigned>(cs.seed) * 7u + 1u);
  int candidates = 0, marked = 0;
  for (std::ptrdiff_t rr = 0; rr < H; ++rr) {
    const std::uint8_t* lrow = s.labels.data() + rr * W;
    std::ptrdiff_t clast = -1;
    for (std::ptrdiff_t c = 0; c < W; ++c) {
      if (lrow[c] == miem::kNormal || lrow[c] == miem::kEdge) clast = c;
    }
    if (clast < 0) continue;
    // the whole row with the cache (batch: C1 = the last candidate + 1), without it (the
    // stream's later passes: C1 = the tile's end)
    miem::detail::edge_judge_row(g, rr, rr, H, 0, clast + 1, img.im, img.o, r, k,
                                 s.labels.data(), ones.data(), cached.data(), &cache);
    miem::detail::edge_judge_row(g, rr, rr, H, 0, W, img.im, img.o, r, k, s.labels.data(),
                                 ones.data(), plain.data(), nullptr);
    for (auto& t : todos) t = rng() % 5 != 0 ? 1 : 0;
    miem::detail::edge_judge_row(g, rr, rr, H, 0, W, img.im, img.o, r, k, s.labels.data(),
                                 todos.data(), sparse.data(), nullptr);
    for (std::ptrdiff_t c = 0; c <= clast; ++c) {
      if (!(lrow[c] == miem::kNormal || lrow[c] == miem::kEdge)) continue;
      ++candidates;
      todo1[static_cast<std::size_t>(c)] = 1;
      miem::detail::edge_judge_row(g, rr, rr, H, 0, W, img.im, img.o, r, k, s.labels.data(),
                                   todo1.data(), one.data(), nullptr);
      todo1[static_cast<std::size_t>(c)] = 0;
      marked += one[static_cast<std::size_t>(c)];
      EXPECT_EQ(cached[static_cast<std::size_t>(c)], one[static_cast<std::size_t>(c)])
          << "cached, row " << rr << " col " << c;
      EXPECT_EQ(plain[static_cast<std::size_t>(c)], one[static_cast<std::size_t>(c)])
          << "uncached, row " << rr << " col " << c;
      if (todos[static_cast<std::size_t>(c)]) {
        EXPECT_EQ(sparse[static_cast<std::size_t>(c)], one[static_cast<std::size_t>(c)])
            << "scattered candidates, row " << rr << " col " << c;
      }
    }
  }
  // not vacuous: the burrs are found, the surface is not
  EXPECT_GT(marked, 0);
  EXPECT_LT(marked, candidates / 4);
}

// Narrow grids (one partial block) and grids of one and two blocks, windows 5 to 11.
INSTANTIATE_TEST_SUITE_P(Layouts, EdgeBands,
                         ::testing::Values(Case{40, 20, 2, 1}, Case{40, 37, 2, 2},
                                           Case{40, 70, 2, 3}, Case{48, 128, 2, 4},
                                           Case{40, 100, 3, 5}, Case{40, 128, 4, 6},
                                           Case{40, 90, 5, 7}, Case{30, 66, 2, 8}));

}  // namespace
