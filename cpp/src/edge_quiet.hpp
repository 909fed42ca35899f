// SPEC "Edge test" step 1: the quiet cells, which the edge passes do not judge. A NORMAL cell
// is quiet when every cell within r = edge_window / 2 rows and columns lies inside the grid and
// is NORMAL, INVALID or ABNORMAL (no EDGE), fewer than n_min of them INVALID or ABNORMAL (no
// sub-window is empty or short of support: a removed cell is a missing one, like a dropout), no
// cell within h = window / 2 became ABNORMAL in the height passes (so its height-window plane is
// the one the height test's first pass fitted), and that plane is quiet (kHQuiet, kHStale
// clear: quiet_plane and the height passes' marks, stages.hpp). Shared by the batch
// (edge_test.cpp) and the stream (stream_edges.cpp).
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>

#include "edge_test.hpp"
#include "miem/organized.hpp"

namespace miem::detail {

/// The window condition over the 2 r + 1 rows around a row: per column, the INVALID or ABNORMAL
/// cells (inv: no support) and the EDGE cells (bad) of the rows held, kept as rows come in and go
/// out; pinv and pbad (W + 1 each) are scratch for the sums along a row. The caller owns the
/// buffer (over(): ints(W) of them).
struct QuietCounts {
  std::int32_t* inv;
  std::int32_t* bad;
  std::int32_t* pinv;
  std::int32_t* pbad;
  std::ptrdiff_t W, r;
  std::int32_t n_min;

  /// The ints a buffer for rows of W cells holds.
  static constexpr std::ptrdiff_t ints(std::ptrdiff_t W) { return 4 * W + 2; }
  /// The counts in `buf` (ints(W) of them) for rows of W cells and edge half-size r.
  static QuietCounts over(std::int32_t* buf, std::ptrdiff_t W, std::ptrdiff_t r) {
    return {buf, buf + W, buf + 2 * W, buf + 3 * W + 1, W, r,
            static_cast<std::int32_t>(edge_n_min(r))};
  }

  /// No rows held.
  void clear() const noexcept {
    std::fill(inv, inv + W, 0);
    std::fill(bad, bad + W, 0);
  }
  /// A row of labels in (sign 1) or out (sign -1), as it was when it came in.
  void add(const std::uint8_t* labels, std::int32_t sign) const noexcept {
    std::int32_t* __restrict ni = inv;
    std::int32_t* __restrict nb = bad;
    for (std::ptrdiff_t c = 0; c < W; ++c) {  // (branch-free: vectorised)
      const std::uint8_t l = labels[c];
      ni[c] += sign * static_cast<std::int32_t>((l == kInvalid) | (l == kAbnormal));
      nb[c] += sign * static_cast<std::int32_t>(l == kEdge);
    }
  }
  /// The rows held are the 2 r + 1 rows around a row inside the grid, `labels` that row's:
  /// clears todo[c] of its quiet cells, those whose planes[c] & mask == want (the plane's bits).
  void drop(const std::uint8_t* labels, const std::uint8_t* planes, std::uint8_t mask,
            std::uint8_t want, std::uint8_t* todo) const noexcept {
    if (W < 2 * r + 1) return;
    std::int32_t* __restrict si = pinv;
    std::int32_t* __restrict sb = pbad;
    std::int32_t ai = 0, ab = 0;  // (the running sums in registers: no store-to-load chain)
    si[0] = sb[0] = 0;
    for (std::ptrdiff_t c = 0; c < W; ++c) {
      ai += inv[c], ab += bad[c];
      si[c + 1] = ai, sb[c + 1] = ab;
    }
    for (std::ptrdiff_t c = r; c < W - r; ++c) {  // (branch-free: vectorised)
      const std::int32_t ni = si[c + r + 1] - si[c - r], nb = sb[c + r + 1] - sb[c - r];
      const bool quiet = ((planes[c] & mask) == want) & (labels[c] == kNormal) & (nb == 0) &
                         (ni < n_min);
      todo[c] = static_cast<std::uint8_t>(todo[c] & !quiet);
    }
  }
};

/// The rows a quiet cell's test reads around it (its window, the height passes' marks), for
/// edge half-size r and height half-size h.
inline std::ptrdiff_t quiet_half(std::ptrdiff_t r, std::ptrdiff_t h) { return std::max(r, h); }

}  // namespace miem::detail
