// SPEC "Numbers" (the coordinate range) inside a pass that reads every coordinate anyway: the
// bit pattern of |v| where v is finite, else 0. Non-negative floats order like their patterns,
// so an integer maximum of them (vectorised, unlike a floating-point one that must skip NaN) is
// the largest finite magnitude. Batch pass 1's finiteness pass and the stream's profile copy.
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstring>

namespace miem::detail {

inline std::uint64_t finite_abs_bits(double v) {
  std::uint64_t u;
  std::memcpy(&u, &v, sizeof u);
  u &= 0x7FFFFFFFFFFFFFFFull;
  return u < 0x7FF0000000000000ull ? u : 0;
}
inline std::uint32_t finite_abs_bits(float v) {
  std::uint32_t u;
  std::memcpy(&u, &v, sizeof u);
  u &= 0x7FFFFFFFu;
  return u < 0x7F800000u ? u : 0;
}

// The pattern type of T.
template <typename T>
using AbsBits = decltype(finite_abs_bits(T()));

// One point's test, inlined into the loops that read every point (batch pass 1's finiteness
// pass, the stream's profile copy): whether it is finite (GridView::finite's test) and `t`
// raised to its coordinates' largest finite_abs_bits. S: a signed type as wide as the patterns
// (they lie below 2^63, 2^31), whose maximum AVX2 has for 64-bit lanes (the unsigned one only
// AVX-512).
template <typename T, typename S>
inline __attribute__((always_inline)) bool finite_point(T x, T y, T z, S& t) {
  const S bx = static_cast<S>(finite_abs_bits(x)), by = static_cast<S>(finite_abs_bits(y));
  const S bz = static_cast<S>(finite_abs_bits(z));
  t = std::max(t, std::max(bx, std::max(by, bz)));
  return (x - x) + (y - y) + (z - z) == T(0);
}

// The value of a pattern finite_abs_bits gave, widened to double.
template <typename T>
double magnitude_of(AbsBits<T> u) {
  T v;
  std::memcpy(&v, &u, sizeof v);
  return static_cast<double>(v);
}

}  // namespace miem::detail
