// Sector membership for the cloud edge test (docs/SPEC.md "Unorganized clouds: edge test",
// step 3): the octant of a tangent offset, and the octants of a run of a point's ball.
#pragma once

#include <cmath>
#include <cstddef>
#include <cstdint>
#ifdef __SSE2__
#include <emmintrin.h>
#endif

#include <Eigen/Core>

#include "vector_clones.hpp"

namespace miem::cloud {

// The octant of a tangent offset (a, b) != 0 (SPEC step 3): the 45-degree wedge [45 o, 45 o + 45)
// degrees from e1 towards e2 that holds it, by exact comparisons (a point on a boundary belongs
// to the wedge that starts there).
inline int octant(double a, double b) {
  if (b > 0.0 || (b == 0.0 && a > 0.0)) {  // [0, 180)
    if (a > 0.0) return b < a ? 0 : 1;
    return b > -a ? 2 : 3;
  }
  if (a < 0.0) return -b < -a ? 4 : 5;  // [180, 270)
  return a < -b ? 6 : 7;                // [270, 360)
}

// Tangent directions of a candidate.
struct Frame {
  Eigen::Vector3d e1, e2;
};

// Not a sector member (member_octants).
constexpr std::uint8_t kNotMember = 8;

#ifdef __SSE2__
// The octant of a member by table (member_octants' code: bit 0 a > 0, 1 a < 0, 2 b > 0, 3 b == 0,
// 4 b < a, 5 b > -a, 6 a < b, 7 b < -a), kNotMember for the codes of non-members (bit 8).
struct OctantTable {
  std::uint8_t oct[512];
  OctantTable() {
    for (int c = 0; c < 512; ++c) {
      const bool ap = c & 1, an = c >> 1 & 1, bp = c >> 2 & 1, bz = c >> 3 & 1;
      const bool lt = c >> 4 & 1, pn = c >> 5 & 1, gt = c >> 6 & 1, nn = c >> 7 & 1;
      int o;  // octant(a, b), from the same comparisons
      if (bp || (bz && ap)) {
        o = ap ? (lt ? 0 : 1) : (pn ? 2 : 3);
      } else {
        o = an ? (gt ? 4 : 5) : (nn ? 6 : 7);
      }
      oct[c] = c >> 8 ? kNotMember : static_cast<std::uint8_t>(o);
    }
  }
};
inline const OctantTable kOctants;
#endif

#ifdef MIEM_SELECT_AVX512
// member_octants for q in [0, n - n % 8), eight at a time: the same operations in the same
// order as the scalar tail (the same bits); the octant's bits from the comparisons' masks as
// OctantTable reads them from its code. Returns the first q not done.
__attribute__((target("avx512f,avx512vl"))) inline std::size_t member_octants8(
    const double* __restrict X, const double* __restrict Y, const double* __restrict Z,
    std::size_t n, const Frame& f, double gap, std::uint8_t* __restrict oc) {
  const __m512d v1x = _mm512_set1_pd(f.e1.x()), v1y = _mm512_set1_pd(f.e1.y());
  const __m512d v1z = _mm512_set1_pd(f.e1.z()), v2x = _mm512_set1_pd(f.e2.x());
  const __m512d v2y = _mm512_set1_pd(f.e2.y()), v2z = _mm512_set1_pd(f.e2.z());
  const __m512d zero = _mm512_setzero_pd(), vgap = _mm512_set1_pd(gap);
  const __m512i sign = _mm512_set1_epi64(static_cast<long long>(0x8000000000000000ull));
  const __m512i one = _mm512_set1_epi64(1), two = _mm512_set1_epi64(2);
  const __m512i four = _mm512_set1_epi64(4), eight = _mm512_set1_epi64(kNotMember);
  std::size_t q = 0;
  for (; q + 8 <= n; q += 8) {
    const __m512d wx = _mm512_loadu_pd(X + q), wy = _mm512_loadu_pd(Y + q);
    const __m512d wz = _mm512_loadu_pd(Z + q);
    const __m512d a = _mm512_add_pd(_mm512_add_pd(_mm512_mul_pd(wx, v1x), _mm512_mul_pd(wy, v1y)),
                                    _mm512_mul_pd(wz, v1z));
    const __m512d b = _mm512_add_pd(_mm512_add_pd(_mm512_mul_pd(wx, v2x), _mm512_mul_pd(wy, v2y)),
                                    _mm512_mul_pd(wz, v2z));
    const __m512d rho =  // (the maskz forms: GCC 12 warns of the plain ones' undefined source)
        _mm512_maskz_sqrt_pd(0xFF, _mm512_add_pd(_mm512_mul_pd(a, a), _mm512_mul_pd(b, b)));
    const __m512d na = _mm512_castsi512_pd(_mm512_xor_si512(_mm512_castpd_si512(a), sign));  // -a
    const unsigned in = _mm512_cmp_pd_mask(rho, zero, _CMP_GT_OQ) &
                        _mm512_cmp_pd_mask(rho, vgap, _CMP_GE_OQ);
    const unsigned ap = _mm512_cmp_pd_mask(a, zero, _CMP_GT_OQ);
    const unsigned an = _mm512_cmp_pd_mask(a, zero, _CMP_LT_OQ);
    const unsigned bp = _mm512_cmp_pd_mask(b, zero, _CMP_GT_OQ);
    const unsigned bz = _mm512_cmp_pd_mask(b, zero, _CMP_EQ_OQ);
    const unsigned lt = _mm512_cmp_pd_mask(b, a, _CMP_LT_OQ);   // b < a
    const unsigned pn = _mm512_cmp_pd_mask(b, na, _CMP_GT_OQ);  // b > -a
    const unsigned gt = _mm512_cmp_pd_mask(a, b, _CMP_LT_OQ);   // a < b
    const unsigned nn = _mm512_cmp_pd_mask(b, na, _CMP_LT_OQ);  // b < -a
    // octant(): [0, 180) when b > 0 or (b = 0, a > 0): 0, 1 (a > 0), 2, 3; else 4, 5 (a < 0), 6, 7
    const unsigned up = bp | (bz & ap);
    const unsigned bit1 = (up & ~ap) | (~up & ~an);
    const unsigned bit0 = (up & ((ap & ~lt) | (~ap & ~pn))) | (~up & ((an & ~gt) | (~an & ~nn)));
    __m512i o = _mm512_maskz_mov_epi64(static_cast<__mmask8>(bit0), one);
    o = _mm512_mask_add_epi64(o, static_cast<__mmask8>(bit1), o, two);
    o = _mm512_mask_add_epi64(o, static_cast<__mmask8>(~up), o, four);
    o = _mm512_mask_mov_epi64(eight, static_cast<__mmask8>(in), o);
    _mm_storel_epi64(reinterpret_cast<__m128i*>(oc + q), _mm512_maskz_cvtepi64_epi8(0xFF, o));
  }
  return q;
}
#endif

// The octants of n points of a point P's ball (offsets w = q - P in X, Y, Z): oc[q] =
// octant(a, b) of the tangent offset (a, b) = (w . e1, w . e2) when rho = |(a, b)| > 0 and
// rho >= gap (a sector member), else kNotMember. P itself (and any point at P's tangent
// position) has rho = 0: never a member, so P's index needs no test.
inline void member_octants(const double* __restrict X, const double* __restrict Y,
                           const double* __restrict Z, std::size_t n, const Frame& f, double gap,
                           std::uint8_t* __restrict oc) {
  const double e1x = f.e1.x(), e1y = f.e1.y(), e1z = f.e1.z();
  const double e2x = f.e2.x(), e2y = f.e2.y(), e2z = f.e2.z();
  std::size_t q = 0;
#ifdef MIEM_SELECT_AVX512
  if (detail::has_avx512()) q = member_octants8(X, Y, Z, n, f, gap, oc);
#endif
#ifdef __SSE2__
  {
    // Two at a time: the same operations in the same order as the scalar tail (the same bits);
    // the comparisons' results as a code in each lane (a small integer double), then the table.
    const __m128d v1x = _mm_set1_pd(e1x), v1y = _mm_set1_pd(e1y), v1z = _mm_set1_pd(e1z);
    const __m128d v2x = _mm_set1_pd(e2x), v2y = _mm_set1_pd(e2y), v2z = _mm_set1_pd(e2z);
    const __m128d zero = _mm_setzero_pd(), vgap = _mm_set1_pd(gap);
    const __m128d sign = _mm_set1_pd(-0.0);
    auto bit = [](__m128d m, double v) { return _mm_and_pd(m, _mm_set1_pd(v)); };
    for (; q + 1 < n; q += 2) {
      const __m128d wx = _mm_loadu_pd(X + q), wy = _mm_loadu_pd(Y + q), wz = _mm_loadu_pd(Z + q);
      const __m128d a = _mm_add_pd(_mm_add_pd(_mm_mul_pd(wx, v1x), _mm_mul_pd(wy, v1y)),
                                   _mm_mul_pd(wz, v1z));
      const __m128d b = _mm_add_pd(_mm_add_pd(_mm_mul_pd(wx, v2x), _mm_mul_pd(wy, v2y)),
                                   _mm_mul_pd(wz, v2z));
      const __m128d rho = _mm_sqrt_pd(_mm_add_pd(_mm_mul_pd(a, a), _mm_mul_pd(b, b)));
      const __m128d in = _mm_and_pd(_mm_cmpgt_pd(rho, zero), _mm_cmpge_pd(rho, vgap));
      const __m128d na = _mm_xor_pd(a, sign);
      __m128d code = _mm_add_pd(bit(_mm_cmpgt_pd(a, zero), 1.0), bit(_mm_cmplt_pd(a, zero), 2.0));
      code = _mm_add_pd(code, bit(_mm_cmpgt_pd(b, zero), 4.0));
      code = _mm_add_pd(code, bit(_mm_cmpeq_pd(b, zero), 8.0));
      code = _mm_add_pd(code, bit(_mm_cmplt_pd(b, a), 16.0));
      code = _mm_add_pd(code, bit(_mm_cmpgt_pd(b, na), 32.0));
      code = _mm_add_pd(code, bit(_mm_cmplt_pd(a, b), 64.0));
      code = _mm_add_pd(code, bit(_mm_cmplt_pd(b, na), 128.0));
      code = _mm_add_pd(code, _mm_andnot_pd(in, _mm_set1_pd(256.0)));
      const __m128i c = _mm_cvttpd_epi32(code);
      oc[q] = kOctants.oct[_mm_cvtsi128_si32(c)];
      oc[q + 1] = kOctants.oct[_mm_cvtsi128_si32(_mm_shuffle_epi32(c, 1))];
    }
  }
#endif
  for (; q < n; ++q) {
    const double wx = X[q], wy = Y[q], wz = Z[q];
    const double a = wx * e1x + wy * e1y + wz * e1z;
    const double b = wx * e2x + wy * e2y + wz * e2z;
    const double rho = std::sqrt(a * a + b * b);
    oc[q] = rho > 0.0 && rho >= gap ? static_cast<std::uint8_t>(octant(a, b)) : kNotMember;
  }
}

}  // namespace miem::cloud
