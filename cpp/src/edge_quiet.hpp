// SPEC "Edge test" step 1: the quiet cells, which the edge passes do not judge. A NORMAL cell
// is quiet when its height-window plane is (kHQuiet: quiet_plane at the height test's first
// pass, stages.hpp), every cell within q = max(edge_window, window) / 2 rows and columns lies
// inside the grid and is NORMAL or INVALID, and fewer than n_min of the cells within r =
// edge_window / 2 are INVALID (no sub-window of the edge test is empty). No cell of
// such a window changed during the height passes, so the first pass's plane is the window's
// plane at the start of the edge test. Shared by the batch (edge_test.cpp) and the stream
// (stream_edges.cpp).
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>

#include "miem/organized.hpp"

namespace miem::detail {

/// The window condition: per column, the EDGE or ABNORMAL cells (bad) of the 2 q + 1 rows
/// around a row and the INVALID cells (inv) of the 2 r + 1 rows around it, kept as rows come in
/// and go out (add_bad, add_inv); pinv and pbad (W + 1 each) are scratch for the sums along a
/// row. The caller owns the buffers.
struct QuietCounts {
  std::int32_t* inv;
  std::int32_t* bad;
  std::int32_t* pinv;
  std::int32_t* pbad;
  std::ptrdiff_t W, r, q;
  std::int32_t n_min;

  /// No rows held.
  void clear() const noexcept {
    std::fill(inv, inv + W, 0);
    std::fill(bad, bad + W, 0);
  }
  /// A row of labels in (sign 1) or out (sign -1) of the bad counts, as it was when it came in.
  void add_bad(const std::uint8_t* labels, std::int32_t sign) const noexcept {
    std::int32_t* __restrict nb = bad;
    for (std::ptrdiff_t c = 0; c < W; ++c) {  // (branch-free: vectorised)
      const std::uint8_t l = labels[c];
      nb[c] += sign * static_cast<std::int32_t>((l == kEdge) | (l == kAbnormal));
    }
  }
  /// The same for the INVALID counts.
  void add_inv(const std::uint8_t* labels, std::int32_t sign) const noexcept {
    std::int32_t* __restrict ni = inv;
    for (std::ptrdiff_t c = 0; c < W; ++c) ni[c] += sign * static_cast<std::int32_t>(labels[c] == kInvalid);
  }
  /// The counts held are those around a row inside the grid, `labels` that row's: clears
  /// todo[c] of its quiet cells (`quiet_bit` in planes[c]).
  void drop(const std::uint8_t* labels, const std::uint8_t* planes, std::uint8_t quiet_bit,
            std::uint8_t* todo) const noexcept {
    if (W < 2 * q + 1) return;
    std::int32_t* __restrict si = pinv;
    std::int32_t* __restrict sb = pbad;
    std::int32_t ai = 0, ab = 0;  // (the running sums in registers: no store-to-load chain)
    si[0] = sb[0] = 0;
    for (std::ptrdiff_t c = 0; c < W; ++c) {
      ai += inv[c], ab += bad[c];
      si[c + 1] = ai, sb[c + 1] = ab;
    }
    for (std::ptrdiff_t c = q; c < W - q; ++c) {  // (branch-free: vectorised)
      const std::int32_t ni = si[c + r + 1] - si[c - r], nb = sb[c + q + 1] - sb[c - q];
      const bool quiet = ((planes[c] & quiet_bit) != 0) & (labels[c] == kNormal) & (nb == 0) &
                         (ni < n_min);
      todo[c] = static_cast<std::uint8_t>(todo[c] & !quiet);
    }
  }
};

/// The quiet window's half-size q and n_min for edge half-size r and height half-size h.
inline std::ptrdiff_t quiet_half(std::ptrdiff_t r, std::ptrdiff_t h) { return std::max(r, h); }
inline std::int32_t quiet_n_min(std::ptrdiff_t r) {
  return static_cast<std::int32_t>(std::max<std::ptrdiff_t>(3, (r * r) / 2));
}

}  // namespace miem::detail
