// SPEC "Numbers", the coordinate range (miem/views.hpp): largest_finite_magnitude, one read pass
// over caller memory, two (SSE2) lanes of doubles or four of floats at a time along contiguous
// rows; CoordinateRangeError's message.
#include <cmath>
#include <cstddef>
#include <cstdio>
#include <limits>
#include <string>

#include "miem/views.hpp"

#ifdef __SSE2__
#include <emmintrin.h>
#endif

namespace miem {

namespace {

// max(top, |v|) for finite v (|v| < inf is false for inf and NaN)
template <typename T>
inline T take(T top, T v) {
  const T a = std::fabs(v);
  return (a < std::numeric_limits<T>::infinity() && a > top) ? a : top;
}

// The same over a contiguous row, n values.
inline double row_top(const double* p, std::ptrdiff_t n, double top) {
  std::ptrdiff_t c = 0;
#ifdef __SSE2__
  const __m128d sign = _mm_set1_pd(-0.0);
  const __m128d inf = _mm_set1_pd(std::numeric_limits<double>::infinity());
  __m128d t0 = _mm_setzero_pd(), t1 = _mm_setzero_pd();
  for (; c + 4 <= n; c += 4) {  // |v| where it is below inf, else 0; max (no NaN reaches it)
    const __m128d a0 = _mm_andnot_pd(sign, _mm_loadu_pd(p + c));
    const __m128d a1 = _mm_andnot_pd(sign, _mm_loadu_pd(p + c + 2));
    t0 = _mm_max_pd(t0, _mm_and_pd(a0, _mm_cmplt_pd(a0, inf)));
    t1 = _mm_max_pd(t1, _mm_and_pd(a1, _mm_cmplt_pd(a1, inf)));
  }
  double lanes[2];
  _mm_storeu_pd(lanes, _mm_max_pd(t0, t1));
  top = take(take(top, lanes[0]), lanes[1]);
#endif
  for (; c < n; ++c) top = take(top, p[c]);
  return top;
}

inline float row_top(const float* p, std::ptrdiff_t n, float top) {
  std::ptrdiff_t c = 0;
#ifdef __SSE2__
  const __m128 sign = _mm_set1_ps(-0.0f), inf = _mm_set1_ps(std::numeric_limits<float>::infinity());
  __m128 t0 = _mm_setzero_ps(), t1 = _mm_setzero_ps();
  for (; c + 8 <= n; c += 8) {
    const __m128 a0 = _mm_andnot_ps(sign, _mm_loadu_ps(p + c));
    const __m128 a1 = _mm_andnot_ps(sign, _mm_loadu_ps(p + c + 4));
    t0 = _mm_max_ps(t0, _mm_and_ps(a0, _mm_cmplt_ps(a0, inf)));
    t1 = _mm_max_ps(t1, _mm_and_ps(a1, _mm_cmplt_ps(a1, inf)));
  }
  float lanes[4];
  _mm_storeu_ps(lanes, _mm_max_ps(t0, t1));
  for (const float l : lanes) top = take(top, l);
#endif
  for (; c < n; ++c) top = take(top, p[c]);
  return top;
}

// The message (the Python layer raises it too: miem/_api.py _check_range).
std::string range_message(const char* name, double magnitude) {
  char buf[320];
  std::snprintf(buf, sizeof buf,
                "%s: finite coordinates reach a magnitude of %.3g, outside the range the method "
                "computes without overflow (at most %g, largest at least %g); rescale the points",
                name, magnitude, kCoordinateMax, kCoordinateMin);
  return buf;
}

}  // namespace

CoordinateRangeError::CoordinateRangeError(const char* name, double magnitude)
    : std::invalid_argument(range_message(name, magnitude)), magnitude_(magnitude) {}

void check_coordinate_range(double magnitude, const char* name, bool lower) {
  if (!coordinate_range_ok(magnitude, lower)) throw CoordinateRangeError(name, magnitude);
}

template <typename T>
double largest_finite_magnitude(const T* data, std::ptrdiff_t rows, std::ptrdiff_t cols,
                                std::ptrdiff_t row_stride, std::ptrdiff_t col_stride) {
  T top = T(0);
  if (col_stride == 1 && row_stride == cols && rows > 1) {  // one block (an (N, 3) cloud): one row
    cols *= rows;
    rows = 1;
  }
  for (std::ptrdiff_t r = 0; r < rows; ++r) {
    const T* p = data + r * row_stride;
    if (col_stride == 1) {
      top = row_top(p, cols, top);
    } else {
      for (std::ptrdiff_t c = 0; c < cols; ++c) top = take(top, p[c * col_stride]);
    }
  }
  return static_cast<double>(top);
}

template double largest_finite_magnitude<float>(const float*, std::ptrdiff_t, std::ptrdiff_t,
                                                std::ptrdiff_t, std::ptrdiff_t);
template double largest_finite_magnitude<double>(const double*, std::ptrdiff_t, std::ptrdiff_t,
                                                 std::ptrdiff_t, std::ptrdiff_t);

}  // namespace miem
