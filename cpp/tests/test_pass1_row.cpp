// Pass 1's row kernel (cpp/src/pass1_row.hpp) on random rows: the packed usable bits a row load
// leaves in the ring are its usable lanes, padding unusable, whatever the layout (dense,
// planes, other strides; double and float); the cells pass1_judge_cells lists are those
// pass1_needs_judge selects, cell by cell.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdint>
#include <random>
#include <vector>

#include "miem/organized.hpp"
#include "miem/params.hpp"
#include "pass1_row.hpp"

namespace {

using miem::detail::Pass1Ring;
using miem::detail::RowScratch;

// Rows of W cells, x, y, z interleaved, some cells NaN (dropouts at `rate`).
template <typename T>
std::vector<T> make_rows(std::ptrdiff_t H, std::ptrdiff_t W, double rate, unsigned seed) {
  std::vector<T> g(static_cast<std::size_t>(H * W * 3));
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  for (std::ptrdiff_t r = 0; r < H; ++r) {
    for (std::ptrdiff_t c = 0; c < W; ++c) {
      T* p = g.data() + (r * W + c) * 3;
      p[0] = static_cast<T>(0.2 * c);
      p[1] = static_cast<T>(0.2 * r);
      p[2] = static_cast<T>(0.01 * u(rng) + (u(rng) < 0.01 ? 1.0 : 0.0));
      if (u(rng) < rate) p[2] = std::numeric_limits<T>::quiet_NaN();
    }
  }
  return g;
}

template <typename T>
std::vector<std::uint8_t> usable_of(const std::vector<T>& g, std::ptrdiff_t r, std::ptrdiff_t W) {
  std::vector<std::uint8_t> us(static_cast<std::size_t>(W));
  for (std::ptrdiff_t c = 0; c < W; ++c) us[c] = std::isfinite(g[(r * W + c) * 3 + 2]) ? 1 : 0;
  return us;
}

// Every padded column's bit equals its lane; the spare word is empty.
void expect_bits_match(const Pass1Ring& ring, std::ptrdiff_t rr) {
  const std::uint64_t* bits = ring.okbits(rr);
  const std::int64_t* ok = ring.ok(rr) - ring.depth;
  for (std::ptrdiff_t k = 0; k < ring.stride(); ++k) {
    const bool bit = (bits[k / 64] >> (k % 64)) & 1;
    ASSERT_EQ(bit, ok[k] != 0) << "row " << rr << " padded column " << k;
  }
  for (std::ptrdiff_t k = ring.stride(); k < ring.bit_words() * 64; ++k)
    ASSERT_EQ((bits[k / 64] >> (k % 64)) & 1, 0u) << "spare bit " << k;
}

template <typename T>
void check_layouts(unsigned seed) {
  const std::ptrdiff_t H = 7, W = 203, depth = 3;  // W not a multiple of 64
  const std::vector<T> g = make_rows<T>(H, W, 0.1, seed);
  // the same rows as three planes (the stream's layout) and as a column-major copy
  std::vector<T> planes(g.size()), colmajor(g.size());
  for (std::ptrdiff_t r = 0; r < H; ++r)
    for (std::ptrdiff_t c = 0; c < W; ++c)
      for (int k = 0; k < 3; ++k) {
        planes[static_cast<std::size_t>(k * H * W + r * W + c)] = g[(r * W + c) * 3 + k];
        colmajor[static_cast<std::size_t>(k * H * W + c * H + r)] = g[(r * W + c) * 3 + k];
      }
  for (int layout = 0; layout < 3; ++layout) {
    RowScratch sc;
    miem::detail::pass1_prepare(sc, W, depth, false);
    const Pass1Ring ring{&sc, H, W, depth};
    for (std::ptrdiff_t rr = 0; rr < H; ++rr) {
      const std::vector<std::uint8_t> us = usable_of(g, rr, W);
      if (layout == 0) {
        const T* p = g.data() + rr * W * 3;
        miem::detail::pass1_load(ring, rr, p, p + 1, p + 2, 3, us.data());
      } else if (layout == 1) {
        const T* p = planes.data() + rr * W;
        miem::detail::pass1_load(ring, rr, p, p + H * W, p + 2 * H * W, 1, us.data());
      } else {
        const T* p = colmajor.data() + rr;
        miem::detail::pass1_load(ring, rr, p, p + H * W, p + 2 * H * W, H, us.data());
      }
      for (std::ptrdiff_t c = 0; c < W; ++c) {
        ASSERT_EQ(ring.ok(rr)[c], us[c]) << "layout " << layout;
        const double want = us[c] ? static_cast<double>(g[(rr * W + c) * 3]) : 0.0;
        ASSERT_EQ(ring.x(rr)[c], want) << "layout " << layout;
      }
      expect_bits_match(ring, rr);
    }
    expect_bits_match(ring, -1);  // the all-unusable row beyond the grid
  }
}

TEST(Pass1Row, PackedUsableBitsFollowTheLanes) {
  check_layouts<double>(1);
  check_layouts<float>(2);
}

TEST(Pass1Row, JudgeCellsAreThoseTheCellTestSelects) {
  const std::ptrdiff_t H = 40, W = 300, depth = 3;
  for (double rate : {0.0, 0.05, 0.3}) {
    const std::vector<double> g = make_rows<double>(H, W, rate, 3);
    miem::DetectParams p;
    p.max_gap = 2;  // two dropouts in a row leave a search to the scalar judge
    p.min_step = -1.0;
    RowScratch sc;
    miem::detail::pass1_prepare(sc, W, depth, false);
    const Pass1Ring ring{&sc, H, W, depth};
    std::vector<std::vector<std::uint8_t>> us(H);
    for (std::ptrdiff_t rr = 0; rr < H; ++rr) us[rr] = usable_of(g, rr, W);
    std::vector<std::uint8_t> labels(static_cast<std::size_t>(W));
    std::size_t listed = 0;
    for (std::ptrdiff_t rr = 0; rr < depth; ++rr)
      miem::detail::pass1_load(ring, rr, g.data() + rr * W * 3, g.data() + rr * W * 3 + 1,
                               g.data() + rr * W * 3 + 2, 3, us[rr].data());
    for (std::ptrdiff_t r = 0; r < H; ++r) {
      if (r + depth < H) {
        const double* q = g.data() + (r + depth) * W * 3;
        miem::detail::pass1_load(ring, r + depth, q, q + 1, q + 2, 3, us[r + depth].data());
      }
      miem::detail::pass1_row(ring, r, p, labels.data(), nullptr, nullptr, nullptr);
      std::vector<std::int64_t> got, want;
      miem::detail::pass1_judge_cells(sc, ring.ok(r), W, r * W, got);
      for (std::ptrdiff_t c = 0; c < W; ++c)
        if (miem::detail::pass1_needs_judge(sc, ring.ok(r), c)) want.push_back(r * W + c);
      ASSERT_EQ(got, want) << "row " << r << " dropouts " << rate;
      listed += got.size();
    }
    if (rate > 0.0) EXPECT_GT(listed, 0u) << rate;  // the test sees cells to list
  }
}

}  // namespace
