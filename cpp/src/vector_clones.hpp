// MIEM_CLONES: the vectorised kernels compiled for x86-64-v4 (AVX-512), AVX2 and the baseline,
// one picked at load time (GCC target clones on x86-64 Linux; elsewhere the plain function).
// Their loops keep each lane's arithmetic to itself, so every clone gives the same bits.
#pragma once

#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__linux__)
#define MIEM_CLONES __attribute__((target_clones("arch=x86-64-v4", "avx2", "default")))
#else
#define MIEM_CLONES
#endif

// MIEM_SELECT_AVX512: hand-written AVX-512 loops (target attributes, intrinsics) are compiled in,
// and run where has_avx512() says the CPU has AVX-512 F and VL; elsewhere their portable forms.
// They keep the portable forms' operations in their order: the same bits either way.
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__)
#include <immintrin.h>
#define MIEM_SELECT_AVX512 1

namespace miem::detail {
/// Whether this CPU runs the hand-written AVX-512 loops (decided once).
inline bool has_avx512() {
  static const bool has =
      __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512vl");
  return has;
}
}  // namespace miem::detail
#endif
