// Thread-count helpers shared by the core's data-parallel loops (OpenMP when available).
#pragma once

#include <cstddef>

#ifdef MIEM_HAVE_OPENMP
#include <omp.h>
#endif

namespace miem::detail {

/// Threads to use for `work` items: 1 for small work, else the request (0 = all available).
inline int thread_count(int requested, std::ptrdiff_t work, std::ptrdiff_t min_work = 1 << 16) {
#ifdef MIEM_HAVE_OPENMP
  if (work < min_work) return 1;
  int n = requested > 0 ? requested : omp_get_max_threads();
  return n < 1 ? 1 : n;
#else
  (void)requested;
  (void)work;
  (void)min_work;
  return 1;
#endif
}

}  // namespace miem::detail
