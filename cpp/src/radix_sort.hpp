// Stable LSD radix sort of 64-bit keys, shared by the neighbour grid (cell keys carrying point
// indices) and z_resolution="auto" (the pooled z values' order-preserving keys). Internal.
#pragma once

#include <cstddef>
#include <cstdint>

namespace miem::detail {

/// Sorts keys[0 .. n - 1] ascending, stably, carrying ids[0 .. n - 1] along (ids null: keys
/// only), 11 bits a pass over the bits up to max_key's highest set bit; a pass over a digit the
/// same for every key moves nothing. tmp_keys (and tmp_ids) hold n more: the second buffer.
/// Returns true when the sorted keys (and ids) ended there, false when in keys (ids). n below
/// 2^32. No allocation (48 KB of histograms on the stack; 64 KB more with threads).
/// With nt > 1 threads (at most 8, and 65,536 keys or more), radix_sort_shares.
inline bool radix_sort_shares(std::uint64_t* keys, std::uint32_t* ids, std::uint64_t* tmp_keys,
                              std::uint32_t* tmp_ids, std::size_t n, int passes,
                              int shares) noexcept;

inline bool radix_sort(std::uint64_t* keys, std::uint32_t* ids, std::uint64_t* tmp_keys,
                       std::uint32_t* tmp_ids, std::size_t n, std::uint64_t max_key,
                       int nt = 1) noexcept {
  constexpr int kBits = 11, kMaxPasses = (64 + kBits - 1) / kBits;
  constexpr std::size_t kBuckets = std::size_t{1} << kBits;
  int bits = 0;
  while (bits < 64 && (max_key >> bits) != 0) ++bits;
  const int passes = (bits + kBits - 1) / kBits;
  if (passes == 0 || n < 2) return false;
  if (nt > 1 && n >= 65536) {
    return radix_sort_shares(keys, ids, tmp_keys, tmp_ids, n, passes, nt < 8 ? nt : 8);
  }
  std::uint32_t hist[kMaxPasses][kBuckets] = {};
  for (std::size_t i = 0; i < n; ++i) {
    const std::uint64_t k = keys[i];
    for (int p = 0; p < passes; ++p) ++hist[p][(k >> (p * kBits)) & (kBuckets - 1)];
  }
  std::uint64_t *src = keys, *dst = tmp_keys;
  std::uint32_t *src_ids = ids, *dst_ids = tmp_ids;
  bool in_tmp = false;
  for (int p = 0; p < passes; ++p) {
    std::uint32_t* h = hist[p];
    const int shift = p * kBits;
    if (h[(src[0] >> shift) & (kBuckets - 1)] == n) continue;  // one digit for every key
    std::uint32_t sum = 0;
    for (std::size_t b = 0; b < kBuckets; ++b) {
      const std::uint32_t c = h[b];
      h[b] = sum;
      sum += c;
    }
    for (std::size_t i = 0; i < n; ++i) {
      const std::uint32_t at = h[(src[i] >> shift) & (kBuckets - 1)]++;
      dst[at] = src[i];
      if (ids != nullptr) dst_ids[at] = src_ids[i];
    }
    std::uint64_t* const k = src;
    src = dst, dst = k;
    std::uint32_t* const d = src_ids;
    src_ids = dst_ids, dst_ids = d;
    in_tmp = !in_tmp;
  }
  return in_tmp;
}

/// radix_sort's passes by `shares` threads (2 to 8): in each pass each thread counts the digits
/// of its contiguous share of the keys, then moves the share, its part of every bucket placed
/// after the earlier shares' parts: the same stable order as one thread, so the same result.
inline bool radix_sort_shares(std::uint64_t* keys, std::uint32_t* ids, std::uint64_t* tmp_keys,
                              std::uint32_t* tmp_ids, std::size_t n, int passes,
                              int shares) noexcept {
  constexpr int kBits = 11, kMaxShares = 8;
  constexpr std::size_t kBuckets = std::size_t{1} << kBits;
  std::uint32_t at[kMaxShares][kBuckets];
  const auto ns = static_cast<std::size_t>(shares);
  std::uint64_t *src = keys, *dst = tmp_keys;
  std::uint32_t *src_ids = ids, *dst_ids = tmp_ids;
  bool in_tmp = false;
  for (int p = 0; p < passes; ++p) {
    const int shift = p * kBits;
    auto digit = [shift](std::uint64_t k) { return (k >> shift) & (kBuckets - 1); };
#pragma omp parallel for schedule(static, 1) num_threads(shares)
    for (int t = 0; t < shares; ++t) {
      std::uint32_t* h = at[t];
      for (std::size_t b = 0; b < kBuckets; ++b) h[b] = 0;
      const std::size_t i1 = n * (t + 1) / ns;
      for (std::size_t i = n * t / ns; i < i1; ++i) ++h[digit(src[i])];
    }
    std::size_t first = 0;  // keys with the first key's digit
    for (std::size_t t = 0; t < ns; ++t) first += at[t][digit(src[0])];
    if (first == n) continue;  // one digit for every key
    std::uint32_t sum = 0;  // bucket by bucket, share by share: where each part starts
    for (std::size_t b = 0; b < kBuckets; ++b) {
      for (std::size_t t = 0; t < ns; ++t) {
        const std::uint32_t c = at[t][b];
        at[t][b] = sum;
        sum += c;
      }
    }
#pragma omp parallel for schedule(static, 1) num_threads(shares)
    for (int t = 0; t < shares; ++t) {
      std::uint32_t* h = at[t];
      const std::size_t i1 = n * (t + 1) / ns;
      for (std::size_t i = n * t / ns; i < i1; ++i) {
        const std::uint32_t to = h[digit(src[i])]++;
        dst[to] = src[i];
        if (ids != nullptr) dst_ids[to] = src_ids[i];
      }
    }
    std::uint64_t* const k = src;
    src = dst, dst = k;
    std::uint32_t* const d = src_ids;
    src_ids = dst_ids, dst_ids = d;
    in_tmp = !in_tmp;
  }
  return in_tmp;
}

}  // namespace miem::detail
