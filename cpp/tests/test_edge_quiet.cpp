// The edge test's quiet cells (cpp/src/edge_quiet.hpp, SPEC "Edge test" step 1), as batch and
// stream detection find them row by row with QuietCounts, against the rule counted cell by cell:
// a NORMAL cell whose plane bits say quiet, no EDGE cell of the grid within r rows and columns,
// and each of its four half sub-windows (clipped at the grid border) holding fewer than n_min
// INVALID or ABNORMAL cells.
#include <gtest/gtest.h>

#include <algorithm>
#include <cstdint>
#include <random>
#include <vector>

#include "edge_quiet.hpp"
#include "miem/organized.hpp"
#include "stages.hpp"

namespace {

using miem::detail::kHQuiet;
using miem::detail::kHStale;
using miem::detail::QuietCounts;

struct Cells {
  std::ptrdiff_t H, W;
  std::vector<std::uint8_t> labels, planes;
};

// Labels with scattered dropouts (INVALID) and removed cells (ABNORMAL) at the given rates,
// patches of dropouts, a few EDGE cells; plane bits mostly quiet.
Cells make_cells(std::ptrdiff_t H, std::ptrdiff_t W, double invalid, unsigned seed) {
  Cells s{H, W, std::vector<std::uint8_t>(static_cast<std::size_t>(H * W), miem::kNormal),
          std::vector<std::uint8_t>(static_cast<std::size_t>(H * W), kHQuiet)};
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  for (std::ptrdiff_t i = 0; i < H * W; ++i) {
    const double v = u(rng);
    if (v < invalid) s.labels[i] = miem::kInvalid;
    else if (v < invalid + 0.02) s.labels[i] = miem::kAbnormal;
    else if (v > 0.999) s.labels[i] = miem::kEdge;
    if (u(rng) < 0.05) s.planes[i] = kHQuiet | kHStale;
    if (u(rng) < 0.05) s.planes[i] = 0;
  }
  for (std::ptrdiff_t r = H / 3; r < std::min(H, H / 3 + 5); ++r)  // a patch of 5 x 6 dropouts
    for (std::ptrdiff_t c = W / 2; c < std::min(W, W / 2 + 6); ++c)
      s.labels[r * W + c] = miem::kInvalid;
  return s;
}

// The rule cell by cell: 1 where pass 1 judges the cell (not quiet), as todo starts at 1.
std::vector<std::uint8_t> brute(const Cells& s, std::ptrdiff_t r) {
  const std::ptrdiff_t H = s.H, W = s.W, n_min = miem::detail::edge_n_min(r);
  std::vector<std::uint8_t> todo(static_cast<std::size_t>(H * W), 1);
  auto at = [&](std::ptrdiff_t a, std::ptrdiff_t b) { return s.labels[a * W + b]; };
  auto inside = [&](std::ptrdiff_t a, std::ptrdiff_t b) {
    return a >= 0 && a < H && b >= 0 && b < W;
  };
  auto gone = [&](std::ptrdiff_t a0, std::ptrdiff_t a1, std::ptrdiff_t b0, std::ptrdiff_t b1) {
    std::ptrdiff_t n = 0;  // INVALID or ABNORMAL cells of the grid, rows [a0, a1], cols [b0, b1]
    for (std::ptrdiff_t a = a0; a <= a1; ++a)
      for (std::ptrdiff_t b = b0; b <= b1; ++b)
        n += inside(a, b) && (at(a, b) == miem::kInvalid || at(a, b) == miem::kAbnormal);
    return n;
  };
  for (std::ptrdiff_t x = 0; x < H; ++x) {
    for (std::ptrdiff_t c = 0; c < W; ++c) {
      if (at(x, c) != miem::kNormal || s.planes[x * W + c] != kHQuiet) continue;
      bool edge = false;
      for (std::ptrdiff_t a = x - r; a <= x + r; ++a)
        for (std::ptrdiff_t b = c - r; b <= c + r; ++b)
          edge |= inside(a, b) && at(a, b) == miem::kEdge;
      if (edge) continue;
      const std::ptrdiff_t left = gone(x - r, x + r, c - r, c - 1);
      const std::ptrdiff_t right = gone(x - r, x + r, c + 1, c + r);
      const std::ptrdiff_t up = gone(x - r, x - 1, c - r, c + r);
      const std::ptrdiff_t down = gone(x + 1, x + r, c - r, c + r);
      if (left < n_min && right < n_min && up < n_min && down < n_min) todo[x * W + c] = 0;
    }
  }
  return todo;
}

// The batch's loop (edge_test.cpp): the window counts slide down the rows, from row x0 on
// (a thread's first row).
std::vector<std::uint8_t> by_rows(const Cells& s, std::ptrdiff_t r, std::ptrdiff_t x0 = 0) {
  const std::ptrdiff_t H = s.H, W = s.W;
  std::vector<std::uint8_t> todo(static_cast<std::size_t>(H * W), 1);
  // poisoned scratch: every count drop reads is written first
  std::vector<std::int32_t> buf(static_cast<std::size_t>(QuietCounts::ints(W, r)), 0x3FFFFFFF);
  const QuietCounts qw = QuietCounts::over(buf.data(), W, r);
  const std::uint8_t* labels = s.labels.data();
  qw.clear();
  for (std::ptrdiff_t a = std::max<std::ptrdiff_t>(0, x0 - r); a < std::min(H, x0 + r); ++a)
    qw.add(labels + a * W, 1);
  for (std::ptrdiff_t x = x0; x < H; ++x) {
    if (x + r < H) qw.add(labels + (x + r) * W, 1);
    qw.drop(labels + x * W, labels + (x + 1) * W, std::min(r, H - 1 - x),
            s.planes.data() + x * W, kHQuiet | kHStale, kHQuiet, todo.data() + x * W);
    if (x - r >= 0) qw.add(labels + (x - r) * W, -1);
  }
  return todo;
}

TEST(EdgeQuiet, HalvesCountedRowByRowAsCellByCell) {
  for (const std::ptrdiff_t r : {3, 7}) {
    for (const double invalid : {0.005, 0.06, 0.12, 0.2}) {
      const Cells s = make_cells(70, 90, invalid, static_cast<unsigned>(r * 100 + invalid * 1000));
      const std::vector<std::uint8_t> want = brute(s, r);
      EXPECT_EQ(by_rows(s, r), want) << "r " << r << " invalid " << invalid;
      std::ptrdiff_t quiet = 0, border = 0;
      for (std::ptrdiff_t i = 0; i < s.H * s.W; ++i) {
        const std::ptrdiff_t x = i / s.W, c = i % s.W;
        quiet += want[i] == 0;
        border += want[i] == 0 && (x < r || x >= s.H - r || c < r || c >= s.W - r);
      }
      EXPECT_GT(quiet, 0) << "r " << r << " invalid " << invalid;  // the rule decides somewhere
      if (invalid < 0.1) EXPECT_GT(border, 0) << "r " << r << " invalid " << invalid;
      // a thread's rows from any row on: the same
      const std::vector<std::uint8_t> from = by_rows(s, r, 33);
      EXPECT_TRUE(std::equal(from.begin() + 33 * s.W, from.end(), want.begin() + 33 * s.W));
    }
  }
}

// Grids narrower and shorter than a window (2 r + 1): every cell's window reaches past the
// border; cell by cell as above.
TEST(EdgeQuiet, GridsSmallerThanTheWindow) {
  for (const std::ptrdiff_t r : {3, 7}) {
    for (const auto& hw : {std::pair<std::ptrdiff_t, std::ptrdiff_t>{5, 40}, {40, 5}, {4, 4},
                           {1, 30}, {30, 1}}) {
      const Cells s = make_cells(hw.first, hw.second, 0.01, static_cast<unsigned>(r + hw.first));
      EXPECT_EQ(by_rows(s, r), brute(s, r)) << "r " << r << " " << hw.first << " x " << hw.second;
    }
  }
}

// Cells whose window holds n_min INVALID cells but no half does (the whole-window count alone
// would not make them quiet) and a cell with n_min in one half.
TEST(EdgeQuiet, TheWindowMayHoldNMinWhereNoHalfDoes) {
  const std::ptrdiff_t r = 3, H = 20, W = 20;
  Cells s{H, W, std::vector<std::uint8_t>(H * W, miem::kNormal),
          std::vector<std::uint8_t>(H * W, kHQuiet)};
  for (const auto& d : {std::pair{-2, -2}, {-2, 2}, {2, -2}, {2, 2}})  // around (6, 6)
    s.labels[(6 + d.first) * W + 6 + d.second] = miem::kInvalid;
  for (std::ptrdiff_t a = 11; a < 15; ++a) s.labels[a * W + 16] = miem::kInvalid;  // (13, 13)
  ASSERT_EQ(miem::detail::edge_n_min(r), 4);
  const std::vector<std::uint8_t> got = by_rows(s, r);
  EXPECT_EQ(got[6 * W + 6], 0);    // 4 in its window, 2 in each half: quiet
  EXPECT_EQ(got[13 * W + 13], 1);  // 4 in its right half: judged
  EXPECT_EQ(got, brute(s, r));
}

// prefix_sums2 (AVX-512 where the CPU has it, 16 cells a step, and the serial loop) against
// sums added one by one here: every length up to 70 (whole registers and remainders), values
// of either sign, two arrays at once.
TEST(EdgeQuiet, PrefixSumsAreTheRunningSums) {
  std::uint32_t seed = 7;
  for (std::ptrdiff_t n = 0; n <= 70; ++n) {
    std::vector<std::int32_t> a(static_cast<std::size_t>(n)), b(a.size());
    for (std::size_t i = 0; i < a.size(); ++i) {
      seed = seed * 1664525u + 1013904223u;
      a[i] = static_cast<std::int32_t>(seed >> 20) - 2048;
      b[i] = static_cast<std::int32_t>(seed & 0xFF) - 100;
    }
    std::vector<std::int32_t> wa(static_cast<std::size_t>(n + 1), 0), wb = wa;
    for (std::ptrdiff_t c = 0; c < n; ++c) wa[c + 1] = wa[c] + a[c], wb[c + 1] = wb[c] + b[c];
    std::vector<std::int32_t> ga(static_cast<std::size_t>(n + 1), -1), gb = ga, serial = ga;
    miem::detail::prefix_sums2(a.data(), b.data(), n, ga.data(), gb.data());
    miem::detail::prefix_sums_serial(a.data(), n, serial.data());
    EXPECT_EQ(ga, wa) << "n " << n;
    EXPECT_EQ(gb, wb) << "n " << n;
    EXPECT_EQ(serial, wa) << "n " << n;
  }
}

}  // namespace

namespace {

// A noisy level sheet (0.1 mm cells, sigma 0.002 mm, z_noise given: the quiet floor 0.004 mm)
// with one spike the height test's first pass flags; the height test's marks (ws.hmask) after
// `iterations` passes.
std::vector<std::uint8_t> spike_marks(int iterations, std::vector<std::uint8_t>& labels) {
  constexpr std::ptrdiff_t H = 60, W = 60;
  std::vector<double> xyz(static_cast<std::size_t>(3 * H * W));
  std::mt19937 rng(17);
  std::normal_distribution<double> noise(0.0, 0.002);
  for (std::ptrdiff_t r = 0; r < H; ++r)
    for (std::ptrdiff_t c = 0; c < W; ++c) {
      double* q = xyz.data() + 3 * (r * W + c);
      q[0] = 0.1 * c, q[1] = 0.1 * r, q[2] = noise(rng);
    }
  xyz[3 * (30 * W + 30) + 2] += 0.3;  // the spike
  miem::DetectParams p = miem::recommended_params();
  p.max_iterations = iterations;
  p.min_step = -1.0, p.min_step_auto = false;
  p.z_resolution = -1.0, p.z_resolution_auto = false;
  p.z_noise = 0.002, p.z_noise_auto = false;
  p.num_threads = 1;
  labels.assign(static_cast<std::size_t>(H * W), miem::kNormal);  // as the angle test left them
  std::vector<double> height(static_cast<std::size_t>(H * W));
  miem::detail::Workspace ws;
  miem::detail::height_test(miem::GridView<double>::dense(xyz.data(), H, W), p, labels.data(),
                            height.data(), ws);
  return std::vector<std::uint8_t>(ws.hmask.begin(), ws.hmask.end());
}

}  // namespace

// SPEC "Edge test" step 1: a cell's quiet mark follows its last height-window plane. The cells
// around the spike the first pass removed are fitted again at the second pass, without it: a
// level sheet, their planes quiet (rms about sigma, below 0.75 x the floor of 2 sigma). With one
// pass nothing fits them again: their planes are stale (kHStale), not quiet.
TEST(EdgeQuiet, TheLastPlaneDecidesAroundAHeightRemoval) {
  constexpr std::ptrdiff_t W = 60, h = 10;  // the default window 21
  std::vector<std::uint8_t> labels;
  const std::vector<std::uint8_t> ten = spike_marks(10, labels);
  ASSERT_EQ(labels[30 * W + 30], miem::kAbnormal);
  std::ptrdiff_t around = 0, quiet = 0, stale = 0;
  for (std::ptrdiff_t r = 30 - h; r <= 30 + h; ++r)
    for (std::ptrdiff_t c = 30 - h; c <= 30 + h; ++c) {
      if (r == 30 && c == 30) continue;
      const std::uint8_t b = ten[static_cast<std::size_t>(r * W + c)];
      ++around;
      quiet += (b & (kHQuiet | kHStale)) == kHQuiet;
      stale += (b & kHStale) != 0;
    }
  EXPECT_EQ(stale, 0);
  EXPECT_GT(quiet, around * 95 / 100) << quiet << " of " << around;
  const std::vector<std::uint8_t> one = spike_marks(1, labels);
  ASSERT_EQ(labels[30 * W + 30], miem::kAbnormal);
  for (std::ptrdiff_t r = 30 - h; r <= 30 + h; ++r)
    for (std::ptrdiff_t c = 30 - h; c <= 30 + h; ++c) {
      if (r == 30 && c == 30) continue;
      EXPECT_NE(one[static_cast<std::size_t>(r * W + c)] & kHStale, 0) << r << ", " << c;
    }
  // beyond the window no plane changed: the same marks either way
  EXPECT_EQ(one[5 * W + 5] & (kHQuiet | kHStale), ten[5 * W + 5] & (kHQuiet | kHStale));
}
