// Thread-count helpers shared by the core's data-parallel loops (OpenMP when available).
#pragma once

#include <algorithm>
#include <cstddef>

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

}  // namespace miem::detail
