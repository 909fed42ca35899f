// SPEC "Edge test" step 1: the quiet cells, which the edge passes do not judge. A NORMAL cell
// is quiet when every cell of the grid within r = edge_window / 2 rows and columns is NORMAL,
// INVALID or ABNORMAL (no EDGE), each of its four half sub-windows (left, right, up, down:
// step 2; clipped at the grid border, as the sub-windows are) holds fewer than n_min INVALID or
// ABNORMAL cells (no sub-window is empty: a quadrant lies within a half; a removed cell is a
// missing one, like a dropout), and its height-window plane over the labels after the height
// passes (each pass re-fits the cells whose window the pass before changed) is quiet (kHQuiet,
// kHStale clear: quiet_plane and the height passes' marks, stages.hpp; kHStale where the last
// pass changed the window and no pass re-fitted it). Shared by the batch (edge_test.cpp) and
// the stream (stream_edges.cpp).
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>

#include "edge_test.hpp"
#include "miem/organized.hpp"
#include "vector_clones.hpp"

namespace miem::detail {

/// out[0] = 0, out[c + 1] = a[0] + ... + a[c] for c < n, and the same of b into outb
/// (integers: any order of the additions gives the same sums). The serial loop is a chain of
/// one addition per cell; with AVX-512, 16 cells a step (a scan within the register, then the
/// carry), the two arrays' chains side by side.
inline void prefix_sums_serial(const std::int32_t* __restrict a, std::ptrdiff_t n,
                               std::int32_t* __restrict out) noexcept {
  std::int32_t s = 0;
  out[0] = 0;
  for (std::ptrdiff_t c = 0; c < n; ++c) out[c + 1] = s += a[c];
}
#ifdef MIEM_SELECT_AVX512
// One register's scan: lane i += lane i - k for k = 1, 2, 4, 8 (alignr with zeros: the lanes
// shifted up by k), then the carry (all lanes: the previous register's last sum).
__attribute__((target("avx512f"), always_inline)) inline __m512i scan16(__m512i x,
                                                                        __m512i carry) {
  const __m512i zero = _mm512_setzero_si512();
  x = _mm512_add_epi32(x, _mm512_maskz_alignr_epi32(0xFFFF, x, zero, 15));
  x = _mm512_add_epi32(x, _mm512_maskz_alignr_epi32(0xFFFF, x, zero, 14));
  x = _mm512_add_epi32(x, _mm512_maskz_alignr_epi32(0xFFFF, x, zero, 12));
  x = _mm512_add_epi32(x, _mm512_maskz_alignr_epi32(0xFFFF, x, zero, 8));
  return _mm512_add_epi32(x, carry);
}
__attribute__((target("avx512f"))) inline void prefix_sums2_avx512(
    const std::int32_t* __restrict a, const std::int32_t* __restrict b, std::ptrdiff_t n,
    std::int32_t* __restrict outa, std::int32_t* __restrict outb) noexcept {
  const __m512i last = _mm512_set1_epi32(15);
  __m512i ca = _mm512_setzero_si512(), cb = ca;
  outa[0] = outb[0] = 0;
  std::ptrdiff_t c = 0;
  for (; c + 16 <= n; c += 16) {
    const __m512i xa = scan16(_mm512_loadu_si512(a + c), ca);
    const __m512i xb = scan16(_mm512_loadu_si512(b + c), cb);
    _mm512_storeu_si512(outa + c + 1, xa);
    _mm512_storeu_si512(outb + c + 1, xb);
    ca = _mm512_maskz_permutexvar_epi32(0xFFFF, last, xa);
    cb = _mm512_maskz_permutexvar_epi32(0xFFFF, last, xb);
  }
  std::int32_t sa = outa[c], sb = outb[c];
  for (; c < n; ++c) outa[c + 1] = sa += a[c], outb[c + 1] = sb += b[c];
}
#endif
inline void prefix_sums2(const std::int32_t* a, const std::int32_t* b, std::ptrdiff_t n,
                         std::int32_t* outa, std::int32_t* outb) noexcept {
#ifdef MIEM_SELECT_AVX512
  if (has_avx512()) {
    prefix_sums2_avx512(a, b, n, outa, outb);
    return;
  }
#endif
  prefix_sums_serial(a, n, outa);
  prefix_sums_serial(b, n, outb);
}

/// QuietCounts::drop's verdicts along a row, first by the whole window: clears todo[c] of the
/// cells whose window holds fewer than n_min INVALID or ABNORMAL cells (then so does each half)
/// and no EDGE cell, from the prefix sums along the row of those cells of the window's rows
/// (si, sb; padded: si[-r .. -1] = si[0] = 0 and si[W + 1 .. W + r] = si[W], so that a window
/// reaching past either end of the row counts its cells inside). Returns whether a cell is left
/// that only that count keeps from being quiet.
inline bool quiet_window(std::ptrdiff_t W, std::ptrdiff_t r, std::int32_t n_min,
                         const std::int32_t* __restrict si, const std::int32_t* __restrict sb,
                         const std::uint8_t* __restrict labels,
                         const std::uint8_t* __restrict planes, std::uint8_t mask,
                         std::uint8_t want, std::uint8_t* __restrict todo) noexcept {
  int more = 0;
  for (std::ptrdiff_t c = 0; c < W; ++c) {  // (branch-free: vectorised)
    const std::int32_t ni = si[c + r + 1] - si[c - r], nb = sb[c + r + 1] - sb[c - r];
    const bool ok = ((planes[c] & mask) == want) & (labels[c] == kNormal) & (nb == 0);
    todo[c] = static_cast<std::uint8_t>(todo[c] & !(ok & (ni < n_min)));
    more |= ok & (ni >= n_min);
  }
  return more != 0;
}

/// The same by the halves: clears todo[c] of the cells whose four halves each hold fewer than
/// n_min INVALID or ABNORMAL cells, with su and sl the prefix sums of those of the rows above
/// and below within the window (all four padded as in quiet_window). (Restrict parameters: with
/// more than ten pointers GCC does not version the loop for aliasing, and it stays scalar.)
inline void quiet_halves(std::ptrdiff_t W, std::ptrdiff_t r, std::int32_t n_min,
                         const std::int32_t* __restrict si, const std::int32_t* __restrict sb,
                         const std::int32_t* __restrict su, const std::int32_t* __restrict sl,
                         const std::uint8_t* __restrict labels,
                         const std::uint8_t* __restrict planes, std::uint8_t mask,
                         std::uint8_t want, std::uint8_t* __restrict todo) noexcept {
  for (std::ptrdiff_t c = 0; c < W; ++c) {  // (branch-free: vectorised)
    const std::int32_t nb = sb[c + r + 1] - sb[c - r];
    const std::int32_t left = si[c] - si[c - r], right = si[c + r + 1] - si[c + 1];
    const std::int32_t up = su[c + r + 1] - su[c - r], down = sl[c + r + 1] - sl[c - r];
    const bool quiet = ((planes[c] & mask) == want) & (labels[c] == kNormal) & (nb == 0) &
                       (std::max(std::max(left, right), std::max(up, down)) < n_min);
    todo[c] = static_cast<std::uint8_t>(todo[c] & !quiet);
  }
}

/// The window condition over the rows of the grid within r of a row (2 r + 1 of them but
/// within r of the grid's first and last rows): per column, the INVALID or ABNORMAL cells (inv:
/// no support) and the EDGE cells (bad) of the rows held, kept as rows come in and go out; low,
/// pinv, pbad, pup and plow are scratch for drop (W, then W + 1 each with r of padding on
/// either side). The caller owns the buffer (over(): ints(W, r) of them).
struct QuietCounts {
  std::int32_t* inv;
  std::int32_t* bad;
  std::int32_t* low;
  std::int32_t* pinv;
  std::int32_t* pbad;
  std::int32_t* pup;
  std::int32_t* plow;
  std::ptrdiff_t W, r;
  std::int32_t n_min;

  /// The ints a buffer for rows of W cells and edge half-size r holds.
  static constexpr std::ptrdiff_t ints(std::ptrdiff_t W, std::ptrdiff_t r) {
    return 7 * W + 4 + 8 * r;
  }
  /// The counts in `buf` (ints(W, r) of them) for rows of W cells and edge half-size r.
  static QuietCounts over(std::int32_t* buf, std::ptrdiff_t W, std::ptrdiff_t r) {
    const std::ptrdiff_t P = W + 1 + 2 * r;  // a padded prefix array
    std::int32_t* pre = buf + 3 * W + r;
    return {buf, buf + W, buf + 2 * W, pre, pre + P, pre + 2 * P, pre + 3 * P, W, r,
            static_cast<std::int32_t>(edge_n_min(r))};
  }
  /// Pads prefix sums p[0 .. W] for windows past the row's ends (quiet_window).
  void pad(std::int32_t* p) const noexcept {
    for (std::ptrdiff_t k = 1; k <= r; ++k) p[-k] = 0, p[W + k] = p[W];
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
  /// The rows held are the rows of the grid within r of a row, `labels` that row's and `below`
  /// the n_below (<= r) rows of the grid under it (W apart; as they came in): clears todo[c] of
  /// its quiet cells, those whose planes[c] & mask == want (the plane's bits).
  void drop(const std::uint8_t* labels, const std::uint8_t* below, std::ptrdiff_t n_below,
            const std::uint8_t* planes, std::uint8_t mask, std::uint8_t want,
            std::uint8_t* todo) const noexcept {
    std::int32_t* __restrict si = pinv;
    std::int32_t* __restrict sb = pbad;
    prefix_sums2(inv, bad, W, si, sb);
    pad(si);
    pad(sb);
    // the whole window first: nearly every cell's holds fewer than n_min (then so do its
    // halves); only a row with a cell it leaves needs the halves' sums
    if (!quiet_window(W, r, n_min, si, sb, labels, planes, mask, want, todo)) return;
    std::int32_t* __restrict nl = low;  // the rows below
    std::fill(nl, nl + W, 0);
    for (std::ptrdiff_t k = 0; k < n_below; ++k) {
      const std::uint8_t* __restrict lk = below + k * W;
      for (std::ptrdiff_t c = 0; c < W; ++c)  // (branch-free: vectorised)
        nl[c] += static_cast<std::int32_t>((lk[c] == kInvalid) | (lk[c] == kAbnormal));
    }
    std::int32_t* __restrict su = pup;
    std::int32_t* __restrict sl = plow;
    std::int32_t au = 0, al = 0;  // up = all rows - the row - the rows below
    su[0] = sl[0] = 0;
    for (std::ptrdiff_t c = 0; c < W; ++c) {
      const std::uint8_t l = labels[c];
      const std::int32_t own = static_cast<std::int32_t>((l == kInvalid) | (l == kAbnormal));
      au += inv[c] - own - nl[c], al += nl[c];
      su[c + 1] = au, sl[c + 1] = al;
    }
    pad(su);
    pad(sl);
    quiet_halves(W, r, n_min, si, sb, su, sl, labels, planes, mask, want, todo);
  }
};

/// The rows a quiet cell's test reads around it (its window, the height passes' marks), for
/// edge half-size r and height half-size h.
inline std::ptrdiff_t quiet_half(std::ptrdiff_t r, std::ptrdiff_t h) { return std::max(r, h); }

}  // namespace miem::detail
