// Stable LSD radix sort of 64-bit keys, shared by the neighbour grid (cell keys carrying point
// indices) and z_resolution="auto" (the pooled z values' order-preserving keys). Internal.
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <utility>

namespace miem::detail {

inline constexpr int kRadixBits = 11;
inline constexpr std::size_t kRadixBuckets = std::size_t{1} << kRadixBits;

// The two buffers of a radix sort: a pass moves the keys (and ids) from src to dst, then the
// buffers swap roles.
struct RadixBuffers {
  std::uint64_t *src, *dst;
  std::uint32_t *src_ids, *dst_ids;  // (null: keys only)
  bool in_tmp = false;               // the keys are in the second buffer

  static std::size_t digit(std::uint64_t k, int shift) {
    return static_cast<std::size_t>((k >> shift) & (kRadixBuckets - 1));
  }
  // keys [b0, b1) of src to their places in dst: h[their digit]++
  void move(std::size_t b0, std::size_t b1, int shift, std::uint32_t* h) const noexcept {
    for (std::size_t i = b0; i < b1; ++i) {
      const std::uint32_t at = h[digit(src[i], shift)]++;
      dst[at] = src[i];
      if (src_ids != nullptr) dst_ids[at] = src_ids[i];
    }
  }
  void flip() noexcept {
    std::swap(src, dst);
    std::swap(src_ids, dst_ids);
    in_tmp = !in_tmp;
  }
};

/// radix_sort's passes by `shares` threads (2 to 8): in each pass each thread counts the digits
/// of its contiguous share of the keys, then moves the share, its part of every bucket placed
/// after the earlier shares' parts: the same stable order as one thread, so the same result.
inline bool radix_sort_shares(RadixBuffers rb, std::size_t n, int passes, int shares) noexcept {
  constexpr int kMaxShares = 8;
  std::uint32_t at[kMaxShares][kRadixBuckets];
  const auto ns = static_cast<std::size_t>(shares);
  auto share = [n, ns](int t) { return n * static_cast<std::size_t>(t) / ns; };
  for (int p = 0; p < passes; ++p) {
    const int shift = p * kRadixBits;
#pragma omp parallel for schedule(static, 1) num_threads(shares)
    for (int t = 0; t < shares; ++t) {
      std::uint32_t* h = at[t];
      std::fill(h, h + kRadixBuckets, 0u);
      const std::size_t i1 = share(t + 1);
      for (std::size_t i = share(t); i < i1; ++i) ++h[RadixBuffers::digit(rb.src[i], shift)];
    }
    std::size_t first = 0;  // keys with the first key's digit
    for (std::size_t t = 0; t < ns; ++t) first += at[t][RadixBuffers::digit(rb.src[0], shift)];
    if (first == n) continue;  // one digit for every key
    std::uint32_t sum = 0;     // bucket by bucket, share by share: where each part starts
    for (std::size_t b = 0; b < kRadixBuckets; ++b) {
      for (std::size_t t = 0; t < ns; ++t) {
        const std::uint32_t c = at[t][b];
        at[t][b] = sum;
        sum += c;
      }
    }
#pragma omp parallel for schedule(static, 1) num_threads(shares)
    for (int t = 0; t < shares; ++t) rb.move(share(t), share(t + 1), shift, at[t]);
    rb.flip();
  }
  return rb.in_tmp;
}

/// Sorts keys[0 .. n - 1] ascending, stably, carrying ids[0 .. n - 1] along (ids null: keys
/// only), 11 bits a pass over the bits up to max_key's highest set bit; a pass over a digit the
/// same for every key moves nothing. tmp_keys (and tmp_ids) hold n more: the second buffer.
/// Returns true when the sorted keys (and ids) ended there, false when in keys (ids). n below
/// 2^32. With nt > 1 threads and 65,536 keys or more: radix_sort_shares on up to 8 of them.
/// No allocation (48 KB of histograms on the stack; with threads 64 KB).
inline bool radix_sort(std::uint64_t* keys, std::uint32_t* ids, std::uint64_t* tmp_keys,
                       std::uint32_t* tmp_ids, std::size_t n, std::uint64_t max_key,
                       int nt = 1) noexcept {
  constexpr int kMaxPasses = (64 + kRadixBits - 1) / kRadixBits;
  int bits = 0;
  while (bits < 64 && (max_key >> bits) != 0) ++bits;
  const int passes = (bits + kRadixBits - 1) / kRadixBits;
  if (passes == 0 || n < 2) return false;
  RadixBuffers rb{keys, tmp_keys, ids, tmp_ids};
  if (nt > 1 && n >= 65536) return radix_sort_shares(rb, n, passes, nt < 8 ? nt : 8);
  // one thread: every pass's histogram from one read of the keys
  std::uint32_t hist[kMaxPasses][kRadixBuckets] = {};
  for (std::size_t i = 0; i < n; ++i) {
    for (int p = 0; p < passes; ++p) ++hist[p][RadixBuffers::digit(keys[i], p * kRadixBits)];
  }
  for (int p = 0; p < passes; ++p) {
    std::uint32_t* h = hist[p];
    const int shift = p * kRadixBits;
    if (h[RadixBuffers::digit(rb.src[0], shift)] == n) continue;  // one digit for every key
    std::uint32_t sum = 0;
    for (std::size_t b = 0; b < kRadixBuckets; ++b) {
      const std::uint32_t c = h[b];
      h[b] = sum;
      sum += c;
    }
    rb.move(0, n, shift, h);
    rb.flip();
  }
  return rb.in_tmp;
}

}  // namespace miem::detail
