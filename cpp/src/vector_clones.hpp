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

#include <cstdint>
#define MIEM_SELECT_AVX512 1

namespace miem::detail {
/// Whether this CPU runs the hand-written AVX-512 loops (decided once).
inline bool has_avx512() {
  static const bool has =
      __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512vl");
  return has;
}

/// 8 points (x, y, z, x, ...) held in three registers of 8 values each (a, b, c) as x, y, z
/// registers.
__attribute__((target("avx512f"), always_inline)) inline void deinterleave_xyz8(
    __m512d a, __m512d b, __m512d c, __m512d& x, __m512d& y, __m512d& z) {
  // x: a0 a3 a6 b1 b4 b7 | c2 c5; y: a1 a4 a7 b2 b5 | c0 c3 c6; z: a2 a5 b0 b3 b6 | c1 c4 c7
  const __m512i ix = _mm512_setr_epi64(0, 3, 6, 9, 12, 15, 0, 0);
  const __m512i iy = _mm512_setr_epi64(1, 4, 7, 10, 13, 0, 0, 0);
  const __m512i iz = _mm512_setr_epi64(2, 5, 8, 11, 14, 0, 0, 0);
  const __m512i jx = _mm512_setr_epi64(0, 1, 2, 3, 4, 5, 10, 13);
  const __m512i jy = _mm512_setr_epi64(0, 1, 2, 3, 4, 8, 11, 14);
  const __m512i jz = _mm512_setr_epi64(0, 1, 2, 3, 4, 9, 12, 15);
  x = _mm512_permutex2var_pd(_mm512_permutex2var_pd(a, ix, b), jx, c);
  y = _mm512_permutex2var_pd(_mm512_permutex2var_pd(a, iy, b), jy, c);
  z = _mm512_permutex2var_pd(_mm512_permutex2var_pd(a, iz, b), jz, c);
}

/// Points 0 .. 7 of an interleaved array of doubles (24 at q) as x, y, z registers.
__attribute__((target("avx512f"), always_inline)) inline void load_xyz8(const double* q,
                                                                        __m512d& x, __m512d& y,
                                                                        __m512d& z) {
  deinterleave_xyz8(_mm512_loadu_pd(q), _mm512_loadu_pd(q + 8), _mm512_loadu_pd(q + 16), x, y,
                    z);
}

/// Which of 8 points (x, y, z registers) are finite: x - x is 0 for a finite x and NaN for an
/// infinite or NaN one (GridView::finite's test).
__attribute__((target("avx512f"), always_inline)) inline __mmask8 finite8(
    __m512d x, __m512d y, __m512d z) {
  const __m512d t = _mm512_add_pd(_mm512_add_pd(_mm512_sub_pd(x, x), _mm512_sub_pd(y, y)),
                                  _mm512_sub_pd(z, z));
  return _mm512_cmp_pd_mask(t, _mm512_setzero_pd(), _CMP_EQ_OQ);
}

/// 8 bytes at p, one in each 64-bit lane.
__attribute__((target("avx512f"), always_inline)) inline __m512i bytes8(const std::uint8_t* p) {
  return _mm512_maskz_cvtepu8_epi64(0xFF, _mm_loadl_epi64(reinterpret_cast<const __m128i*>(p)));
}

/// 8 bytes at p as a mask: bit i set where byte i is not 0.
__attribute__((target("avx512f"), always_inline)) inline __mmask8 nonzero8(
    const std::uint8_t* p) {
  const __m512i b = bytes8(p);
  return _mm512_test_epi64_mask(b, b);
}
}  // namespace miem::detail
#endif
