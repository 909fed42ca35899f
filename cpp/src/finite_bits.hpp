// SPEC "Numbers" (the coordinate range) inside a pass that reads every coordinate anyway: the
// bit pattern of |v| where v is finite, else 0. Non-negative floats order like their patterns,
// so an integer maximum of them (vectorised, unlike a floating-point one that must skip NaN) is
// the largest finite magnitude. Batch pass 1's finiteness pass and the stream's profile copy.
#pragma once

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

// The value of a pattern finite_abs_bits gave, widened to double.
template <typename T>
double magnitude_of(AbsBits<T> u) {
  T v;
  std::memcpy(&v, &u, sizeof v);
  return static_cast<double>(v);
}

}  // namespace miem::detail
