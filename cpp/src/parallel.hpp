// Thread-count helpers shared by the core's data-parallel loops (OpenMP when available).
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <vector>

#ifdef MIEM_HAVE_OPENMP
#include <omp.h>
#endif

namespace miem::detail {

/// Largest thread count any loop uses: 4 x the processors OpenMP sees, at most 256. Requests
/// above it are clamped (README "Guarantees"): a loop never starts thousands of OS threads or
/// asks the OpenMP runtime for per-thread memory in proportion to a caller's typo, and since
/// results never depend on the thread count, clamping changes nothing but speed.
inline int max_threads() {
#ifdef MIEM_HAVE_OPENMP
  return std::min(256, 4 * std::max(1, omp_get_num_procs()));
#else
  return 1;
#endif
}

/// Threads to use for `work` items: 1 for small work, else the request (0 = all available),
/// clamped to max_threads().
inline int thread_count(int requested, std::ptrdiff_t work, std::ptrdiff_t min_work = 1 << 16) {
#ifdef MIEM_HAVE_OPENMP
  if (work < min_work) return 1;
  const int n = requested > 0 ? requested : omp_get_max_threads();
  return std::clamp(n, 1, max_threads());
#else
  (void)requested;
  (void)work;
  (void)min_work;
  return 1;
#endif
}

/// Calls f(part, i0, i1) on one contiguous range of [0, n) per thread of nt (part = 0, 1, ... in
/// the ranges' order; boundaries multiples of `align`). For loops whose cells are independent:
/// the result does not depend on nt.
template <typename F>
void parallel_ranges(int nt, std::ptrdiff_t n, std::ptrdiff_t align, F f) {
#ifdef MIEM_HAVE_OPENMP
  if (nt > 1 && n > align) {
    const std::ptrdiff_t blocks = (n + align - 1) / align;
#pragma omp parallel num_threads(nt)
    {
      const std::ptrdiff_t t = omp_get_thread_num(), T = omp_get_num_threads();
      const std::ptrdiff_t i0 = std::min(n, blocks * t / T * align);
      const std::ptrdiff_t i1 = std::min(n, blocks * (t + 1) / T * align);
      if (i0 < i1) f(static_cast<int>(t), i0, i1);
    }
    return;
  }
#endif
  (void)nt;
  (void)align;
  f(0, std::ptrdiff_t{0}, n);
}

/// Calls f(i, thread) for each i of [0, n), items handed out one at a time to nt threads (for
/// items of uneven cost that are independent: which thread runs an item changes nothing).
/// Allocates nothing (the stream's per-profile work uses it).
template <typename F>
void parallel_items(int nt, std::ptrdiff_t n, F f) {
#ifdef MIEM_HAVE_OPENMP
  if (nt > 1 && n > 1) {
    const int team = static_cast<int>(std::min<std::ptrdiff_t>(nt, n));
#pragma omp parallel for schedule(dynamic, 1) num_threads(team)
    for (std::ptrdiff_t i = 0; i < n; ++i) f(i, omp_get_thread_num());
    return;
  }
#endif
  (void)nt;
  for (std::ptrdiff_t i = 0; i < n; ++i) f(i, 0);
}

/// A compaction on nt threads: the positions i of [0, n) with keep(i), in increasing order,
/// each handed to put(c, i) (c: how many kept positions come before i) after size(m) is told
/// how many there are. Each thread counts one range, then puts its kept positions from its
/// offset: the result does not depend on nt. keep is called twice per position.
template <typename Keep, typename Size, typename Put>
void compact_ranges(int nt, std::ptrdiff_t n, Keep keep, Size size, Put put) {
  constexpr int kMax = 256;
  nt = n < (std::ptrdiff_t{1} << 16) ? 1 : std::clamp(nt, 1, kMax);
  std::ptrdiff_t at[kMax + 1] = {};
  auto lo = [n, nt](int t) { return n * t / nt; };
#pragma omp parallel for schedule(static, 1) num_threads(nt) if (nt > 1)
  for (int t = 0; t < nt; ++t) {
    std::ptrdiff_t c = 0;
    for (std::ptrdiff_t i = lo(t), e = lo(t + 1); i < e; ++i) c += keep(i) ? 1 : 0;
    at[t + 1] = c;
  }
  for (int t = 0; t < nt; ++t) at[t + 1] += at[t];
  size(at[nt]);
#pragma omp parallel for schedule(static, 1) num_threads(nt) if (nt > 1)
  for (int t = 0; t < nt; ++t) {
    std::ptrdiff_t c = at[t];
    for (std::ptrdiff_t i = lo(t), e = lo(t + 1); i < e; ++i) {
      if (keep(i)) put(c++, i);
    }
  }
}

/// The indices i of [0, n) with keep(i) (which may also update cell i), in increasing order,
/// into `out` (cleared first): nt threads scan one range each and their lists are joined in
/// order, so `out` does not depend on nt. For the stages' scans for new ABNORMAL cells or a
/// pass's marks, which ran on one thread.
/// The same for ranges of `grain` units that each yield any number of indices: fn(u0, u1, part)
/// appends those of units [u0, u1) to `part`; the parts are joined in order.
template <typename Fn>
void collect_ranges(int nt, std::ptrdiff_t n, std::ptrdiff_t grain, std::vector<std::int64_t>& out,
                    Fn fn) {
  out.clear();
  if (nt <= 1) {
    fn(std::ptrdiff_t{0}, n, out);
    return;
  }
  std::vector<std::vector<std::int64_t>> parts(static_cast<std::size_t>(nt));
  parallel_ranges(nt, n, grain, [&](int t, std::ptrdiff_t u0, std::ptrdiff_t u1) {
    fn(u0, u1, parts[static_cast<std::size_t>(t)]);
  });
  for (const auto& part : parts) out.insert(out.end(), part.begin(), part.end());
}

template <typename Keep>
void collect_indices(int nt, std::ptrdiff_t n, std::vector<std::int64_t>& out, Keep keep) {
  collect_ranges(nt, n, 64, out,
                 [&](std::ptrdiff_t i0, std::ptrdiff_t i1, std::vector<std::int64_t>& part) {
                   // 64 cells at a time: keep() of each into bytes (straight-line code,
                   // vectorised for a simple keep), then the kept ones of the blocks that
                   // have any (the indices are few: most blocks have none)
                   std::uint8_t k[64];
                   for (std::ptrdiff_t b = i0; b < i1; b += 64) {
                     const std::ptrdiff_t m = std::min<std::ptrdiff_t>(64, i1 - b);
                     unsigned any = 0;
                     for (std::ptrdiff_t j = 0; j < m; ++j) {
                       k[j] = keep(b + j) ? 1 : 0;
                       any |= k[j];
                     }
                     if (any == 0) continue;
                     for (std::ptrdiff_t j = 0; j < m; ++j) {
                       if (k[j]) part.push_back(b + j);
                     }
                   }
                 });
}

}  // namespace miem::detail
