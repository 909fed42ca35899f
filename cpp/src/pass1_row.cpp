// Pass 1's row kernel (pass1_row.hpp), shared by batch detection and ProfileStream.
#include "pass1_row.hpp"

#include <algorithm>
#include <cmath>
#include <type_traits>
#include <vector>

#include "angle_math.hpp"
#include "judge.hpp"
#include "min_step_skip.hpp"
#include "parallel.hpp"
#include "vector_clones.hpp"

namespace miem::detail {

namespace {

// Pass 1 row kernel. Whole rows are judged with straight-line loops over structure-of-arrays
// copies of the rows, which the compiler vectorizes (AVX-512 and AVX2 clones are picked at run
// time where the CPU has them). Without min_step the neighbour search of SPEC.md ends at its
// first or second cell (the candidate at s cells is usable, or it is not and the one at s + 1
// is: one dropout, the max_gap = 1 default); with min_step it runs step by step for all lanes
// of a block to a depth of up to 16 steps. Rows carry `depth` padding columns of unusable cells
// on each side and rows beyond the grid read an all-unusable row, so the grid's border needs no
// special case.
// Cells whose search goes further (max_gap > 1 with two unusable cells in a row without
// min_step, deeper than the ring with it, a min_step candidate within a relative 1e-12 of the
// bound, no usable cell within the isolation reach) fall back to the scalar judge.
constexpr std::ptrdiff_t kBlock = 256;  // columns per block of the row kernel
// Lanes per min_step search: a chunk runs to its longest search, so wider chunks step more
// lanes that have ended, narrower ones make more calls. On the real scan and the jittered
// stream 64 measured about 2 % faster than 32 and clearly faster than 16; 128 and 256 no
// faster than 64.
constexpr std::ptrdiff_t kChunk = 64;

constexpr std::int64_t kFlagShift = kPass1FlagShift, kSlowBit = kPass1SlowBit,
                       kNearBit = kPass1NearBit;

// The two candidates of one side of one (direction, scale): the cells s and s + 1 steps away
// (x, y, z rows and usable lanes, already shifted so that index c is the candidate of cell c),
// and the first candidates' usable lanes packed (bit `off1 + c` of `bits1` for lane c).
struct Side {
  const double *x1, *y1, *z1, *x2, *y2, *z2;
  const std::int64_t *ok1, *ok2;
  const std::uint64_t *bits1, *bits2;  // (bits2, off2: the second candidates', the same way)
  std::ptrdiff_t off1, off2;
};

// 64 bits of a packed row from bit o on (the row has a spare word beyond its last bit).
inline std::uint64_t bits_at(const std::uint64_t* b, std::ptrdiff_t o) {
  const std::ptrdiff_t k = o >> 6;
  const int sh = static_cast<int>(o & 63);
  return sh == 0 ? b[k] : (b[k] >> sh) | (b[k + 1] << (64 - sh));
}

// The candidate a search returns when it ends at one of the two cells: the first usable one.
// Writes the offset u from the centre, `any` (a usable cell among the two, then u is the
// search's answer) and `slow` (the search would go on: two unusable cells and max_gap > 1).
#define MIEM_PICK(P, c, ux, uy, uz, uu, slow, any)                                          \
  do {                                                                                      \
    const std::int64_t o1 = P##o1[c], o2 = P##o2[c];                                        \
    const double x1 = P##x1[c], y1 = P##y1[c], z1 = P##z1[c];                               \
    const double x2 = P##x2[c], y2 = P##y2[c], z2 = P##z2[c];                               \
    ux = (o1 ? x1 : x2) - px[c];                                                            \
    uy = (o1 ? y1 : y2) - py[c];                                                            \
    uz = (o1 ? z1 : z2) - pz[c];                                                            \
    uu = (ux * ux + uy * uy) + uz * uz;                                                     \
    any = o1 | o2;                                                                          \
    slow = (any ^ 1) & gap2;                                                                \
  } while (0)

// The verdict of one (direction, scale) from the offsets u, v of its two neighbours, folded
// into the cell's running best (uv, prod) and its bits. The running best cos is kept as the
// pair (uv, prod) = (u.v, |u|^2 |v|^2) and compared through uv |uv| / prod, which orders like
// uv / sqrt(prod): no square root or division per candidate.
#define MIEM_FOLD(c, ux, uy, uz, uu, vx, vy, vz, vv, found)                                 \
  const double uv = (ux * vx + uy * vy) + uz * vz;                                          \
  const double prod = uu * vv;                                                              \
  const std::int64_t good = (found) & (uu != 0.0) & (vv != 0.0);                            \
  const std::int64_t flagged = good & detail::cos_at_least(uv, prod, cos0, c2);             \
  const double b_uv = buv[c], b_prod = bprod[c];                                            \
  const std::int64_t better =                                                               \
      good & (uv * std::fabs(uv) * b_prod > b_uv * std::fabs(b_uv) * prod);                 \
  buv[c] = better ? uv : b_uv;                                                              \
  bprod[c] = better ? prod : b_prod

// One (direction, scale) without min_step over columns [0, n). Masks and bits are 64-bit lanes
// like the doubles, so nothing is packed or unpacked. `near_bit`: set kNearBit where a side has
// a usable cell (scale 1: the two candidates are the whole isolation reach of max_gap <= 1).
// Two loops: kernel_first, vectorised, for the lanes whose first candidates on both sides are
// usable (nearly all: it does not read the second candidates), and kernel_rest for the others.
// The lanes whose candidates at s are usable on both sides (then the search ends there: found,
// not slow, a usable cell near); the other lanes are left as they are. kernel_line finds the
// others from the packed usable bits (rest_words): gathering them here, a bit per lane, cost
// more than a quarter of this loop.
constexpr std::ptrdiff_t kRestWords = (kBlock + 63) / 64;
MIEM_CLONES void kernel_first(std::ptrdiff_t n, const Side& A, const Side& B,
                              const double* __restrict px, const double* __restrict py,
                              const double* __restrict pz, double cos0, double c2,
                              std::int64_t bit, std::int64_t near_bit, double* __restrict buv,
                              double* __restrict bprod, std::int64_t* __restrict bits) {
  const double *__restrict ax1 = A.x1, *__restrict ay1 = A.y1, *__restrict az1 = A.z1;
  const double *__restrict bx1 = B.x1, *__restrict by1 = B.y1, *__restrict bz1 = B.z1;
  const std::int64_t *__restrict ao1 = A.ok1, *__restrict bo1 = B.ok1;
  for (std::ptrdiff_t c = 0; c < n; ++c) {
    const std::int64_t both = ao1[c] & bo1[c];
    const double ux = ax1[c] - px[c], uy = ay1[c] - py[c], uz = az1[c] - pz[c];
    const double uu = (ux * ux + uy * uy) + uz * uz;
    const double vx = bx1[c] - px[c], vy = by1[c] - py[c], vz = bz1[c] - pz[c];
    const double vv = (vx * vx + vy * vy) + vz * vz;
    MIEM_FOLD(c, ux, uy, uz, uu, vx, vy, vz, vv, both);
    bits[c] |= -both & ((-good & bit) | (-flagged & (bit << kFlagShift)) | near_bit);
  }
}

// One (direction, scale) of the fused kernel: its sides, its direction's bit and near bit.
struct Pair {
  Side A, B;
  std::int64_t bit, near_bit;
};
constexpr std::size_t kFusedScales = 4;  // scales the fused kernel takes (more: kernel_line)

#ifdef MIEM_SELECT_AVX512
// The running state of 8 lanes in the fused kernel: the cells' coordinates, the best pair
// (b_uv, b_prod) with its key b_key = b_uv |b_uv| (the product MIEM_FOLD compares, kept
// instead of recomputed: the same bits), the bits, and which lanes are in the block.
struct Lanes8 {
  __m512d x, y, z, b_uv, b_prod, b_key;
  __m512i b;
  __mmask8 lanes;
};

// MIEM_FOLD on 8 lanes (found: the lanes with a candidate on both sides): the running best and
// the masks good and flagged. The same operations in the same order (no contraction), so the
// same bits.
struct Fold8 {
  __mmask8 good, flagged;
};
__attribute__((target("avx512f,avx512vl"), always_inline)) inline Fold8 fold8(
    __mmask8 found, __m512d ux, __m512d uy, __m512d uz, __m512d vx, __m512d vy, __m512d vz,
    bool acute, __m512d vc2, Lanes8& g) {
  const __m512d zero = _mm512_setzero_pd();
  const __m512d uu = _mm512_add_pd(
      _mm512_add_pd(_mm512_mul_pd(ux, ux), _mm512_mul_pd(uy, uy)), _mm512_mul_pd(uz, uz));
  const __m512d vv = _mm512_add_pd(
      _mm512_add_pd(_mm512_mul_pd(vx, vx), _mm512_mul_pd(vy, vy)), _mm512_mul_pd(vz, vz));
  const __m512d uv = _mm512_add_pd(
      _mm512_add_pd(_mm512_mul_pd(ux, vx), _mm512_mul_pd(uy, vy)), _mm512_mul_pd(uz, vz));
  const __m512d prod = _mm512_mul_pd(uu, vv);
  const __mmask8 good = found & _mm512_cmp_pd_mask(uu, zero, _CMP_NEQ_UQ) &
                        _mm512_cmp_pd_mask(vv, zero, _CMP_NEQ_UQ);
  // cos_at_least
  const __mmask8 ge0 = _mm512_cmp_pd_mask(uv, zero, _CMP_GE_OQ);
  const __m512d uvuv = _mm512_mul_pd(uv, uv), c2p = _mm512_mul_pd(vc2, prod);
  const __mmask8 cos_ok =
      acute ? static_cast<__mmask8>(ge0 & _mm512_cmp_pd_mask(uvuv, c2p, _CMP_GE_OQ))
            : static_cast<__mmask8>(ge0 | _mm512_cmp_pd_mask(uvuv, c2p, _CMP_LE_OQ));
  // better: uv |uv| b_prod > b_uv |b_uv| prod
  const __m512d key = _mm512_mul_pd(uv, _mm512_abs_pd(uv));
  const __mmask8 better = good & _mm512_cmp_pd_mask(_mm512_mul_pd(key, g.b_prod),
                                                    _mm512_mul_pd(g.b_key, prod), _CMP_GT_OQ);
  g.b_uv = _mm512_mask_mov_pd(g.b_uv, better, uv);
  g.b_prod = _mm512_mask_mov_pd(g.b_prod, better, prod);
  g.b_key = _mm512_mask_mov_pd(g.b_key, better, key);
  return Fold8{good, static_cast<__mmask8>(good & cos_ok)};
}

// MIEM_PICK's offset of one coordinate on 8 lanes (m: those read): the first candidate's where
// it is usable (o1), else the second's, less the cell's q.
__attribute__((target("avx512f,avx512vl"), always_inline)) inline __m512d pick8(
    __mmask8 m, const double* p1, const double* p2, __mmask8 o1, __m512d q) {
  return _mm512_sub_pd(
      _mm512_mask_mov_pd(_mm512_maskz_loadu_pd(m, p2), o1, _mm512_maskz_loadu_pd(m, p1)), q);
}

// One pair (direction, scale) on the 8 lanes from column c of the block: kernel_first's fold
// where both first candidates are usable, MIEM_REST_LANE's elsewhere.
__attribute__((target("avx512f,avx512vl"), always_inline)) inline void pair8(
    const Pair& pr, std::ptrdiff_t c, bool acute, __m512d vc2, std::int64_t gap2, Lanes8& g) {
  const Side& A = pr.A;
  const Side& B = pr.B;
  const __m512i vbit = _mm512_set1_epi64(pr.bit);
  const __m512i vflag = _mm512_set1_epi64(pr.bit << kFlagShift);
  const __m512i vnear = _mm512_set1_epi64(pr.near_bit);
  const __mmask8 oa1 = static_cast<__mmask8>(bits_at(A.bits1, A.off1 + c));
  const __mmask8 ob1 = static_cast<__mmask8>(bits_at(B.bits1, B.off1 + c));
  const __mmask8 both = oa1 & ob1 & g.lanes;
  if (both) {  // kernel_first
    const __m512d ux = _mm512_sub_pd(_mm512_maskz_loadu_pd(both, A.x1 + c), g.x);
    const __m512d uy = _mm512_sub_pd(_mm512_maskz_loadu_pd(both, A.y1 + c), g.y);
    const __m512d uz = _mm512_sub_pd(_mm512_maskz_loadu_pd(both, A.z1 + c), g.z);
    const __m512d vx = _mm512_sub_pd(_mm512_maskz_loadu_pd(both, B.x1 + c), g.x);
    const __m512d vy = _mm512_sub_pd(_mm512_maskz_loadu_pd(both, B.y1 + c), g.y);
    const __m512d vz = _mm512_sub_pd(_mm512_maskz_loadu_pd(both, B.z1 + c), g.z);
    const Fold8 f = fold8(both, ux, uy, uz, vx, vy, vz, acute, vc2, g);
    g.b = _mm512_mask_or_epi64(g.b, f.good, g.b, vbit);
    g.b = _mm512_mask_or_epi64(g.b, f.flagged, g.b, vflag);
    g.b = _mm512_mask_or_epi64(g.b, both, g.b, vnear);
  }
  const __mmask8 rest = g.lanes & ~both;
  if (rest) {  // MIEM_REST_LANE: each side's first usable candidate of the two
    const __mmask8 oa2 = static_cast<__mmask8>(bits_at(A.bits2, A.off2 + c));
    const __mmask8 ob2 = static_cast<__mmask8>(bits_at(B.bits2, B.off2 + c));
    const __m512d ux = pick8(rest, A.x1 + c, A.x2 + c, oa1, g.x);
    const __m512d uy = pick8(rest, A.y1 + c, A.y2 + c, oa1, g.y);
    const __m512d uz = pick8(rest, A.z1 + c, A.z2 + c, oa1, g.z);
    const __m512d vx = pick8(rest, B.x1 + c, B.x2 + c, ob1, g.x);
    const __m512d vy = pick8(rest, B.y1 + c, B.y2 + c, ob1, g.y);
    const __m512d vz = pick8(rest, B.z1 + c, B.z2 + c, ob1, g.z);
    const __mmask8 aa = oa1 | oa2, ab = ob1 | ob2;
    const Fold8 f = fold8(rest & aa & ab, ux, uy, uz, vx, vy, vz, acute, vc2, g);
    const __mmask8 slow = gap2 ? static_cast<__mmask8>(rest & ~(aa & ab)) : 0;
    g.b = _mm512_mask_or_epi64(g.b, f.good, g.b, vbit);
    g.b = _mm512_mask_or_epi64(g.b, f.flagged, g.b, vflag);
    g.b = _mm512_mask_or_epi64(g.b, slow, g.b, _mm512_set1_epi64(kSlowBit));
    g.b = _mm512_mask_or_epi64(g.b, rest & (aa | ab), g.b, vnear);
  }
}

__attribute__((target("avx512f,avx512vl"), always_inline)) inline Lanes8 load8(
    std::ptrdiff_t n, std::ptrdiff_t c, const double* px, const double* py, const double* pz,
    const double* buv, const double* bprod, const std::int64_t* bits) {
  Lanes8 g;
  g.lanes = n - c >= 8 ? 0xFF : (n > c ? static_cast<__mmask8>((1u << (n - c)) - 1) : 0);
  g.x = _mm512_maskz_loadu_pd(g.lanes, px + c);
  g.y = _mm512_maskz_loadu_pd(g.lanes, py + c);
  g.z = _mm512_maskz_loadu_pd(g.lanes, pz + c);
  g.b_uv = _mm512_maskz_loadu_pd(g.lanes, buv + c);
  g.b_prod = _mm512_maskz_loadu_pd(g.lanes, bprod + c);
  g.b_key = _mm512_mul_pd(g.b_uv, _mm512_abs_pd(g.b_uv));
  g.b = _mm512_maskz_loadu_epi64(g.lanes, bits + c);
  return g;
}

__attribute__((target("avx512f,avx512vl"), always_inline)) inline void store8(
    const Lanes8& g, std::ptrdiff_t c, double* buv, double* bprod, std::int64_t* bits) {
  _mm512_mask_storeu_pd(buv + c, g.lanes, g.b_uv);
  _mm512_mask_storeu_pd(bprod + c, g.lanes, g.b_prod);
  _mm512_mask_storeu_epi64(bits + c, g.lanes, g.b);
}

// kernel_line for every (direction, scale) of a block at once, in AVX-512 (pairs[0 .. np) in
// kernel_line's order): each lane's best pair and bits stay in registers across the pairs, and
// its own coordinates are loaded once (kernel_line per pair read and wrote them 8 times: a
// block's rows do not fit in L1, and that traffic set its pace). Per lane and pair, as
// kernel_line: the pair at the first candidates where both are usable (kernel_first), else the
// search's first usable candidate of each side (MIEM_REST_LANE), so each lane folds the same
// pairs in the same order: the same bits. The usable lanes come from the packed bits.
__attribute__((target("avx512f,avx512vl"))) void kernel_fused_avx512(
    std::ptrdiff_t n, const Pair* pairs, int np, const double* px, const double* py,
    const double* pz, double cos0, double c2, std::int64_t gap2, double* buv, double* bprod,
    std::int64_t* bits) {
  const bool acute = cos0 >= 0.0;
  const __m512d vc2 = _mm512_set1_pd(c2);
  for (std::ptrdiff_t c = 0; c < n; c += 8) {
    Lanes8 g0 = load8(n, c, px, py, pz, buv, bprod, bits);
    for (int k = 0; k < np; ++k) pair8(pairs[k], c, acute, vc2, gap2, g0);
    store8(g0, c, buv, bprod, bits);
  }
}
#endif

// Bit c % 64 of rest[c / 64] for each lane c < n whose first candidates are not both usable
// (n <= 64 kRestWords).
inline void rest_words(std::ptrdiff_t n, const Side& A, const Side& B, std::uint64_t* rest) {
  for (std::ptrdiff_t w = 0; w * 64 < n; ++w) {
    const std::ptrdiff_t left = n - w * 64;
    const std::uint64_t lanes = left >= 64 ? ~std::uint64_t{0} : (std::uint64_t{1} << left) - 1;
    rest[w] = ~(bits_at(A.bits1, A.off1 + w * 64) & bits_at(B.bits1, B.off1 + w * 64)) & lanes;
  }
}

// The search of lane c on to the candidates at s + 1 (kernel_rest's lanes; a lane whose
// candidates at s are both usable folds the pair kernel_first folded again, which changes
// nothing: the same pair is not better than itself, and the same bits are set).
#define MIEM_REST_LANE(c)                                                                   \
  do {                                                                                      \
    double ux, uy, uz, uu, vx, vy, vz, vv;                                                  \
    std::int64_t sa, aa, sb, ab;                                                            \
    MIEM_PICK(a, c, ux, uy, uz, uu, sa, aa);                                                \
    MIEM_PICK(b, c, vx, vy, vz, vv, sb, ab);                                                \
    MIEM_FOLD(c, ux, uy, uz, uu, vx, vy, vz, vv, aa & ab);                                  \
    /* 0/1 lanes to masks by negation (an int64 multiply has no AVX2 instruction) */       \
    bits[c] |= (-good & bit) | (-flagged & (bit << kFlagShift)) | (-(sa | sb) & kSlowBit) | \
               (-(aa | ab) & near_bit);                                                     \
  } while (0)

// MIEM_REST_LANE for every lane of [c0, c1), vectorised: a word of kernel_first's `rest`
// with many bits set (scattered dropouts) costs less this way than lane by lane.
MIEM_CLONES void kernel_rest_all(std::ptrdiff_t c0, std::ptrdiff_t c1, const Side& A,
                                 const Side& B, const double* __restrict px,
                                 const double* __restrict py, const double* __restrict pz,
                                 double cos0, double c2, std::int64_t gap2, std::int64_t bit,
                                 std::int64_t near_bit, double* __restrict buv,
                                 double* __restrict bprod, std::int64_t* __restrict bits) {
  const double *__restrict ax1 = A.x1, *__restrict ay1 = A.y1, *__restrict az1 = A.z1;
  const double *__restrict ax2 = A.x2, *__restrict ay2 = A.y2, *__restrict az2 = A.z2;
  const double *__restrict bx1 = B.x1, *__restrict by1 = B.y1, *__restrict bz1 = B.z1;
  const double *__restrict bx2 = B.x2, *__restrict by2 = B.y2, *__restrict bz2 = B.z2;
  const std::int64_t *__restrict ao1 = A.ok1, *__restrict ao2 = A.ok2;
  const std::int64_t *__restrict bo1 = B.ok1, *__restrict bo2 = B.ok2;
  for (std::ptrdiff_t c = c0; c < c1; ++c) MIEM_REST_LANE(c);
}

// Set bits of a `rest` word from which kernel_rest_all takes the whole word: about 1.6 ns a
// lane against 11 ns a lane one at a time (2048^2 scan with random dropouts, one thread). The
// angle passes at 10 % of dropouts 136 -> 117 ms, at 20 % 208 -> 127 ms, the same at 0.5-5 %
// (4 and 16 measured slower at 2-5 % and at 10 %).
constexpr int kRestDense = 10;

// The other lanes (kernel_first's `rest` bits): the search of either side goes on to its
// candidate at s + 1.
void kernel_rest(std::ptrdiff_t n, const Side& A, const Side& B, const double* px,
                 const double* py, const double* pz, double cos0, double c2, std::int64_t gap2,
                 std::int64_t bit, std::int64_t near_bit, double* buv, double* bprod,
                 std::int64_t* bits, const std::uint64_t* rest) {
  const double *ax1 = A.x1, *ay1 = A.y1, *az1 = A.z1, *ax2 = A.x2, *ay2 = A.y2, *az2 = A.z2;
  const double *bx1 = B.x1, *by1 = B.y1, *bz1 = B.z1, *bx2 = B.x2, *by2 = B.y2, *bz2 = B.z2;
  const std::int64_t *ao1 = A.ok1, *ao2 = A.ok2, *bo1 = B.ok1, *bo2 = B.ok2;
  for (std::ptrdiff_t w = 0; w * 64 < n; ++w) {
    if (rest[w] == 0) continue;
    if (__builtin_popcountll(rest[w]) >= kRestDense) {
      kernel_rest_all(w * 64, std::min(n, w * 64 + 64), A, B, px, py, pz, cos0, c2, gap2, bit,
                      near_bit, buv, bprod, bits);
      continue;
    }
    for (std::uint64_t word = rest[w]; word != 0; word &= word - 1) {
      const std::ptrdiff_t c = w * 64 + __builtin_ctzll(word);
      MIEM_REST_LANE(c);
    }
  }
}
#undef MIEM_REST_LANE

inline void kernel_line(std::ptrdiff_t n, const Side& A, const Side& B, const double* px,
                        const double* py, const double* pz, double cos0, double c2,
                        std::int64_t gap2, std::int64_t bit, std::int64_t near_bit, double* buv,
                        double* bprod, std::int64_t* bits) {
  std::uint64_t rest[kRestWords];
  kernel_first(n, A, B, px, py, pz, cos0, c2, bit, near_bit, buv, bprod, bits);
  rest_words(n, A, B, rest);
  kernel_rest(n, A, B, px, py, pz, cos0, c2, gap2, bit, near_bit, buv, bprod, bits, rest);
}
#undef MIEM_PICK

// With min_step, the neighbour search of SPEC.md for one side of one (direction, scale), one
// step at a time for every lane of a block (the lanes that have ended keep their state). State
// per lane, one word: bits 0-2 the outcome (0 searching, 1 found: u = the offset, 2 none, 4
// slow: the scalar judge decides: a candidate within a relative 1e-12 of s * min_step, where
// the spec's square root decides, or a search deeper than the row ring), bits 3-15 the gaps
// met, bits 16- the step where the search ended.
struct SideSearch {
  double ux[kBlock], uy[kBlock], uz[kBlock];
  std::int64_t st[kBlock];
};
constexpr std::int64_t kGapShift = 3, kGapMask = 0x1FFF, kEndShift = 16;

// One step of the search for lanes [c0, c0 + n): the candidates' rows x, y, z, ok (shifted so
// that index c is the candidate of cell c). Far: |q - P|^2 > hi; near: < lo. Returns whether a
// lane searches on.
MIEM_CLONES std::int64_t search_step(std::ptrdiff_t c0, std::ptrdiff_t n,
                                     const double* __restrict x,
                                     const double* __restrict y, const double* __restrict z,
                                     const std::int64_t* __restrict ok,
                                     const double* __restrict px, const double* __restrict py,
                                     const double* __restrict pz, double lo, double hi,
                                     std::int64_t max_gap, std::int64_t step,
                                     SideSearch& __restrict sr) {
  double *__restrict ux = sr.ux, *__restrict uy = sr.uy, *__restrict uz = sr.uz;
  std::int64_t* __restrict st = sr.st;
  const std::int64_t end = step << kEndShift;
  std::int64_t any = 0;
  for (std::ptrdiff_t c = c0; c < c0 + n; ++c) {
    const std::int64_t s0 = st[c];
    const std::int64_t act = ((s0 | (s0 >> 1) | (s0 >> 2)) & 1) ^ 1, o = ok[c];
    const double dx = x[c] - px[c], dy = y[c] - py[c], dz = z[c] - pz[c];
    const double dd = (dx * dx + dy * dy) + dz * dz;
    const std::int64_t miss = act & (o ^ 1);
    const std::int64_t g = ((s0 >> kGapShift) & kGapMask) + miss;
    const std::int64_t far = dd > hi, near = dd < lo;
    const std::int64_t f = act & o & far;
    const std::int64_t none = miss & (g > max_gap);
    const std::int64_t slow = act & o & (far ^ 1) & (near ^ 1);
    const std::int64_t done = f | none | slow;
    const std::int64_t s1 = s0 + (miss << kGapShift) + (f | (none << 1) | (slow << 2)) +
                            (-done & end);
    st[c] = s1;
    ux[c] = f ? dx : ux[c];
    uy[c] = f ? dy : uy[c];
    uz[c] = f ? dz : uz[c];
    any |= act & (done ^ 1);
  }
  return any;
}

// The verdict of one (direction, scale) from the two sides' searches (SideSearch), as
// kernel_line. A side still searching at step `stop` (`open` 4: beyond the ring; 2: the
// spec's last step passed) ends slow / none; a slow side makes the cell slow unless the other
// side has none. ext: raised to the last step each side read. (Bit tests only: 64-bit
// compares do not vectorise everywhere.)
MIEM_CLONES void fold_searches(std::ptrdiff_t n, const SideSearch& A, const SideSearch& B,
                               std::int64_t open, std::int64_t stop, double cos0, double c2,
                               std::int64_t bit, double* __restrict buv,
                               double* __restrict bprod, std::int64_t* __restrict bits,
                               std::int64_t* __restrict ext) {
  const double *__restrict ax = A.ux, *__restrict ay = A.uy, *__restrict az = A.uz;
  const double *__restrict bx = B.ux, *__restrict by = B.uy, *__restrict bz = B.uz;
  const std::int64_t *__restrict ast = A.st, *__restrict bst = B.st;
  for (std::ptrdiff_t c = 0; c < n; ++c) {
    const std::int64_t sa0 = ast[c], sb0 = bst[c];
    const std::int64_t oa = -(((sa0 | (sa0 >> 1) | (sa0 >> 2)) & 1) ^ 1);  // still searching
    const std::int64_t ob = -(((sb0 | (sb0 >> 1) | (sb0 >> 2)) & 1) ^ 1);
    const std::int64_t sa = sa0 | (oa & open), sb = sb0 | (ob & open);
    const std::int64_t ea = (oa & stop) | (~oa & (sa0 >> kEndShift));
    const std::int64_t eb = (ob & stop) | (~ob & (sb0 >> kEndShift));
    const std::int64_t e0 = ext[c], e1 = ea > eb ? ea : eb;
    ext[c] = e0 > e1 ? e0 : e1;
    const double ux = ax[c], uy = ay[c], uz = az[c];
    const double vx = bx[c], vy = by[c], vz = bz[c];
    const double uu = (ux * ux + uy * uy) + uz * uz, vv = (vx * vx + vy * vy) + vz * vz;
    const std::int64_t fa = sa & 1, fb = sb & 1, la = (sa >> 2) & 1, lb = (sb >> 2) & 1;
    const std::int64_t na = (sa >> 1) & 1, nb = (sb >> 1) & 1;
    MIEM_FOLD(c, ux, uy, uz, uu, vx, vy, vz, vv, fa & fb);
    const std::int64_t slow = (la | lb) & ((na | nb) ^ 1);
    bits[c] |= (-good & bit) | (-flagged & (bit << kFlagShift)) | (-slow & kSlowBit);
  }
}
#undef MIEM_FOLD

// kNearBit where a usable cell lies 1 or 2 (with gap2: 1 .. 2) steps away along one of the
// rays (when scale 1 is not among the scales).
MIEM_CLONES void near_line(std::ptrdiff_t n, const std::int64_t* const* __restrict ok,
                           int m, std::int64_t* __restrict bits) {
  for (std::ptrdiff_t c = 0; c < n; ++c) {
    std::int64_t a = 0;
    for (int k = 0; k < m; ++k) a |= ok[k][c];
    bits[c] |= a * kNearBit;
  }
}

// Smallest angle (degrees) from the best (uv, prod) pairs of a row; NaN where none or where the
// cell itself is not usable.
MIEM_CLONES void angles_line(std::ptrdiff_t n, const double* __restrict buv,
                             const double* __restrict bprod, const std::int64_t* __restrict ok,
                             double* __restrict out) {
  for (std::ptrdiff_t c = 0; c < n; ++c) {
    const bool has = (bprod[c] > 0.0) & (ok[c] != 0);
    double cs = buv[c] / std::sqrt(has ? bprod[c] : 1.0);
    cs = cs < -1.0 ? -1.0 : (cs > 1.0 ? 1.0 : cs);
    const double deg = detail::acos_fast(cs) * detail::kRadToDeg;
    out[c] = has ? deg : detail::kNaN;
  }
}

// The labels (and flags) of a row's usable cells (ok[c]) from the kernel's bits: ABNORMAL when at
// least 2 directions are available and at least min(available, min_directions) (0: all) are
// flagged, EDGE when some are, else NORMAL (SPEC "Detection"). Slow cells get a label here too;
// the scalar judge overwrites it.
MIEM_CLONES void label_line(std::ptrdiff_t n, const std::int64_t* __restrict bits,
                            const std::int64_t* __restrict ok, int min_directions,
                            std::uint8_t* __restrict labels, std::uint8_t* __restrict flags) {
  const std::int64_t md = min_directions;
  auto pop4 = [](std::int64_t x) { return (x & 1) + ((x >> 1) & 1) + ((x >> 2) & 1) + ((x >> 3) & 1); };
  for (std::ptrdiff_t c = 0; c < n; ++c) {
    const std::int64_t b = bits[c], flag = (b >> kFlagShift) & 15;
    const std::int64_t a = pop4(b & 15), f = pop4(flag);
    const std::int64_t need = md > 0 ? (a < md ? a : md) : a;
    const std::uint8_t l = (a >= 2) & (f >= need) ? kAbnormal : (f > 0 ? kEdge : kNormal);
    labels[c] = ok[c] ? l : labels[c];
  }
  if (flags == nullptr) return;
  for (std::ptrdiff_t c = 0; c < n; ++c) {
    const std::uint8_t flag = static_cast<std::uint8_t>((bits[c] >> kFlagShift) & 15);
    flags[c] = ok[c] ? flag : flags[c];
  }
}


// Packs n lanes of 0/1 into bits (n / 64 words, then the rest in one more word).
MIEM_CLONES void pack_lanes(std::ptrdiff_t n, const std::int64_t* __restrict ok,
                            std::uint64_t* __restrict out) {
  for (std::ptrdiff_t w = 0; w * 64 < n; ++w) {
    std::uint64_t word = 0;
    const std::ptrdiff_t c1 = std::min(n, w * 64 + 64);
    for (std::ptrdiff_t c = w * 64; c < c1; ++c)
      word |= static_cast<std::uint64_t>(ok[c]) << (c & 63);
    out[w] = word;
  }
}

// pass1_load's copy: n cells, column c's coordinates at x[c * cs], y[c * cs], z[c * cs].
template <typename T, typename CS>
inline __attribute__((always_inline)) void load_lanes(std::ptrdiff_t n, const T* __restrict x,
                                                      const T* __restrict y,
                                                      const T* __restrict z, CS cs,
                                                      const std::uint8_t* __restrict usable,
                                                      double* __restrict ox,
                                                      double* __restrict oy,
                                                      double* __restrict oz,
                                                      std::int64_t* __restrict ok) {
  for (std::ptrdiff_t c = 0; c < n; ++c) {
    const std::int64_t u = usable[c] != 0 ? 1 : 0;
    ox[c] = u ? static_cast<double>(x[c * cs]) : 0.0;
    oy[c] = u ? static_cast<double>(y[c * cs]) : 0.0;
    oz[c] = u ? static_cast<double>(z[c * cs]) : 0.0;
    ok[c] = u;
  }
}

using K3 = std::integral_constant<std::ptrdiff_t, 3>;
using K1 = std::integral_constant<std::ptrdiff_t, 1>;

// The constant strides vectorise (a run-time stride ran one cell at a time).
#define MIEM_LOAD_CLONE(T, CS)                                                               \
  MIEM_CLONES void load_lanes_##T##_##CS(std::ptrdiff_t n, const T* x, const T* y,          \
                                         const T* z, const std::uint8_t* usable, double* ox, \
                                         double* oy, double* oz, std::int64_t* ok) {         \
    load_lanes(n, x, y, z, CS{}, usable, ox, oy, oz, ok);                                    \
  }
MIEM_LOAD_CLONE(double, K3)
MIEM_LOAD_CLONE(double, K1)
MIEM_LOAD_CLONE(float, K3)
MIEM_LOAD_CLONE(float, K1)
#undef MIEM_LOAD_CLONE

#ifdef MIEM_SELECT_AVX512
// load_lanes of the interleaved layout of doubles in AVX-512, 8 cells a step (GCC's clones
// take 64 a step, for the usable bytes, and spill): the same values.
__attribute__((target("avx512f,avx512vl"))) void load_lanes_xyz_avx512(
    std::ptrdiff_t n, const double* p, const std::uint8_t* usable, double* ox, double* oy,
    double* oz, std::int64_t* ok) {
  const __m512i one = _mm512_set1_epi64(1);
  std::ptrdiff_t c = 0;
  for (; c + 8 <= n; c += 8) {
    __m512d x, y, z;
    load_xyz8(p + 3 * c, x, y, z);
    const __mmask8 u = nonzero8(usable + c);
    _mm512_storeu_pd(ox + c, _mm512_maskz_mov_pd(u, x));
    _mm512_storeu_pd(oy + c, _mm512_maskz_mov_pd(u, y));
    _mm512_storeu_pd(oz + c, _mm512_maskz_mov_pd(u, z));
    _mm512_storeu_si512(ok + c, _mm512_maskz_mov_epi64(u, one));
  }
  load_lanes(n - c, p + 3 * c, p + 3 * c + 1, p + 3 * c + 2, K3{}, usable + c, ox + c, oy + c,
             oz + c, ok + c);
}
#endif

// The interleaved layout of doubles: AVX-512 where the CPU has it, else the clones.
void load_lanes_xyz(std::ptrdiff_t n, const double* x, const double* y, const double* z,
                    const std::uint8_t* usable, double* ox, double* oy, double* oz,
                    std::int64_t* ok) {
#ifdef MIEM_SELECT_AVX512
  if (has_avx512()) {
    load_lanes_xyz_avx512(n, x, usable, ox, oy, oz, ok);
    return;
  }
#endif
  load_lanes_double_K3(n, x, y, z, usable, ox, oy, oz, ok);
}

template <typename T, typename Dense, typename Planes>
void load_row(const Pass1Ring& ring, std::ptrdiff_t rr, const T* x, const T* y, const T* z,
              std::ptrdiff_t cs, const std::uint8_t* usable, Dense dense, Planes planes) {
  double* ox = ring.x(rr);
  double* oy = ox + ring.stride();
  double* oz = oy + ring.stride();
  std::int64_t* ok = ring.ok(rr);
  const std::ptrdiff_t W = ring.W;
  if (cs == 3 && y == x + 1 && z == x + 2) {
    dense(W, x, y, z, usable, ox, oy, oz, ok);
  } else if (cs == 1) {
    planes(W, x, y, z, usable, ox, oy, oz, ok);
  } else {
    load_lanes(W, x, y, z, cs, usable, ox, oy, oz, ok);
  }
  pack_lanes(ring.stride(), ok - ring.depth, ring.okbits(rr));
}

// Whether any of n cells needs the scalar judge (pass1_judge_bits).
MIEM_CLONES std::int64_t any_needs_judge(std::ptrdiff_t n, const std::int64_t* __restrict bits,
                                         const std::int64_t* __restrict ok) {
  std::int64_t any = 0;
  for (std::ptrdiff_t c = 0; c < n; ++c) any |= pass1_judge_bits(bits[c], ok[c]);
  return any;
}

}  // namespace

void pass1_judge_cells(const RowScratch& sc, const std::int64_t* ok, std::ptrdiff_t W,
                       std::int64_t base, std::vector<std::int64_t>& out) {
  for (std::ptrdiff_t c0 = 0; c0 < W; c0 += 64) {
    const std::ptrdiff_t c1 = std::min(W, c0 + 64);
    if (!any_needs_judge(c1 - c0, sc.bits.data() + c0, ok + c0)) continue;
    for (std::ptrdiff_t c = c0; c < c1; ++c) {
      if (pass1_needs_judge(sc, ok, c)) out.push_back(base + c);
    }
  }
}

void pass1_load(const Pass1Ring& ring, std::ptrdiff_t rr, const double* x, const double* y,
                const double* z, std::ptrdiff_t cs, const std::uint8_t* usable) {
  load_row(ring, rr, x, y, z, cs, usable, load_lanes_xyz, load_lanes_double_K1);
}

void pass1_load(const Pass1Ring& ring, std::ptrdiff_t rr, const float* x, const float* y,
                const float* z, std::ptrdiff_t cs, const std::uint8_t* usable) {
  load_row(ring, rr, x, y, z, cs, usable, load_lanes_float_K3, load_lanes_float_K1);
}

void pass1_prepare(RowScratch& sc, std::ptrdiff_t W, std::ptrdiff_t depth, bool min_step) {
  const std::ptrdiff_t S = W + 2 * depth;
  sc.resize(2 * depth + 2, S);
  std::fill(sc.xyz.begin(), sc.xyz.end(), 0.0);
  std::fill(sc.ok.begin(), sc.ok.end(), 0);
  std::fill(sc.okbits.begin(), sc.okbits.end(), 0);
  if (min_step) {
    // with min_step (min_step_skip.hpp): row_speeds, the unusable cells before each padded
    // column, and per chunk of kChunk columns the largest speed and the unusable cells within
    // `depth` columns of it (the steps a search of the chunk can skip)
    sc.speed.resize(static_cast<std::size_t>(W));
    sc.gaps_before.resize(static_cast<std::size_t>(S + 1));
    sc.gaps_before[0] = 0;
    const std::ptrdiff_t n_chunks = (W + kChunk - 1) / kChunk;
    sc.chunk_speed.resize(static_cast<std::size_t>(n_chunks));
    sc.chunk_gaps.resize(static_cast<std::size_t>(n_chunks));
  }
}

void pass1_row(const Pass1Ring& ring, std::ptrdiff_t r, const DetectParams& p,
               std::uint8_t* labels, std::uint8_t* flags_out, double* angle_row,
               std::uint8_t* reach, int num_threads) {
  RowScratch& sc = *ring.sc;
  const std::ptrdiff_t W = ring.W, depth = ring.depth, pad = depth, S = ring.stride();
  const double cos0 = std::cos(p.theta0_deg * detail::kDegToRad), c2 = cos0 * cos0;
  const std::int64_t gap2 = p.max_gap > 1;
  const bool deep = p.min_step >= 0.0;
  auto slot_x = [&](std::ptrdiff_t rr) { return ring.x(rr); };
  auto slot_ok = [&](std::ptrdiff_t rr) { return ring.ok(rr); };
  auto slot_bits = [&](std::ptrdiff_t rr) -> const std::uint64_t* { return ring.okbits(rr); };
  const bool has_scale1 = std::find(p.scales.begin(), p.scales.end(), 1) != p.scales.end();
  double *buv = sc.best.data(), *bprod = sc.best.data() + S;
  std::int64_t* bits = sc.bits.data();
  const std::ptrdiff_t n_chunks = (W + kChunk - 1) / kChunk;
  double* speed = sc.speed.data();
  std::int64_t* gaps_before = sc.gaps_before.data();
  double* chunk_speed = sc.chunk_speed.data();
  std::int64_t* chunk_gaps = sc.chunk_gaps.data();
  std::fill(buv, buv + W, -2.0);
  std::fill(bprod, bprod + W, 0.0);
  std::fill(bits, bits + W, 0);
  const double* px = slot_x(r);
  if (deep) {
    const std::int64_t* ok = slot_ok(r);
    row_speeds(W, px, S, [ok](std::ptrdiff_t c) { return ok[c] != 0; }, speed);
    chunk_speeds(speed, W, kChunk, pad, chunk_speed);
    for (std::ptrdiff_t i = 0; i < S; ++i)
      gaps_before[i + 1] = gaps_before[i] + (ok[i - pad] ^ 1);
    for (std::ptrdiff_t ch = 0; ch < n_chunks; ++ch) {
      const std::ptrdiff_t a = ch * kChunk, b = std::min(W, a + kChunk) + 2 * pad;
      chunk_gaps[ch] = gaps_before[b] - gaps_before[a];
    }
  }
#ifdef MIEM_SELECT_AVX512
  const bool fused = !deep && has_avx512() && p.scales.size() <= kFusedScales;
#else
  constexpr bool fused = false;
#endif
  // Blocks of columns, every (direction, scale) per block (kernel_line one pair at a time over
  // the block; the fused kernel all pairs for 8 lanes at a time). The blocks are independent
  // (each writes its own columns): split among num_threads.
  const std::ptrdiff_t n_blocks = (W + kBlock - 1) / kBlock;
  parallel_items(num_threads, n_blocks, [&](std::ptrdiff_t blk, int) {
    const std::ptrdiff_t b0 = blk * kBlock;
    SideSearch sides[2];
    std::int64_t ext[kBlock];
    const std::ptrdiff_t nb = std::min(W, b0 + kBlock) - b0;
    const double *qx = px + b0, *qy = px + S + b0, *qz = px + 2 * S + b0;
    const std::int64_t* near_ok[16];
    int n_near = 0;
    // without min_step, every (direction, scale) in one pass over the block (pairs, in the
    // order of the loops below) where the CPU has AVX-512
    Pair pairs[4 * kFusedScales];
    int n_pairs = 0;
    for (int k = 0; k < 4; ++k) {
      const int dr = detail::kDirRow[k], dc = detail::kDirCol[k];
      const std::int64_t bit = std::int64_t{1} << k;
      // the cells `step` steps away on side sgn, shifted to the block's first column
      auto at_x = [&](int sgn, std::ptrdiff_t step) {
        return slot_x(r + sgn * step * dr) + b0 + sgn * step * dc;
      };
      auto at_ok = [&](int sgn, std::ptrdiff_t step) {
        return slot_ok(r + sgn * step * dr) + b0 + sgn * step * dc;
      };
      if (deep) {
        // SPEC's search step by step to its last step s + max_gap + max_reach, or to the
        // ring's depth (lanes still searching there go to the scalar judge).
        const std::int64_t gap = p.max_gap;
        std::fill(ext, ext + nb, 1 + gap);
        for (int s : p.scales) {
          const double len = s * p.min_step, l2 = len * len;
          const double lo = l2 * (1.0 - 1e-12), hi = l2 * (1.0 + 1e-12);
          const std::ptrdiff_t last = s + gap + p.max_reach;
          const std::ptrdiff_t stop = std::min<std::ptrdiff_t>(last, depth);
          for (int sd = 0; sd < 2; ++sd) {
            const int sgn = sd == 0 ? -1 : 1;
            SideSearch& sr = sides[sd];
            std::fill(sr.st, sr.st + nb, 0);
            std::fill(sr.ux, sr.ux + nb, 0.0);
            std::fill(sr.uy, sr.uy + nb, 0.0);
            std::fill(sr.uz, sr.uz + nb, 0.0);
            // chunks of kChunk lanes: a chunk ends with its own longest search
            for (std::ptrdiff_t c0 = 0; c0 < nb; c0 += kChunk) {
              const std::ptrdiff_t nc = std::min(kChunk, nb - c0);
              std::ptrdiff_t first = s;
              if (k == 0) {
                // along the row: skip the surely near steps (row_speeds), counting their
                // gaps; not when a lane's gaps there end its search
                const std::ptrdiff_t ch = (b0 + c0) / kChunk;
                first = first_read_step(chunk_speed[ch], len, s, stop);
                if (first > s && chunk_gaps[ch] > 0) {
                  const std::int64_t* u = gaps_before + pad + b0;  // u[c]: [.., c)
                  std::int64_t worst = 0;
                  for (std::ptrdiff_t c = c0; c < c0 + nc; ++c) {
                    const std::int64_t gc = sgn > 0 ? u[c + first] - u[c + s]
                                                    : u[c - s + 1] - u[c - first + 1];
                    sr.st[c] = gc << kGapShift;
                    worst = std::max(worst, gc);
                  }
                  if (worst > gap) {
                    std::fill(sr.st + c0, sr.st + c0 + nc, 0);
                    first = s;
                  }
                }
              }
              for (std::ptrdiff_t step = first; step <= stop; ++step) {
                const double* x = at_x(sgn, step);
                if (!search_step(c0, nc, x, x + S, x + 2 * S, at_ok(sgn, step), qx, qy, qz,
                                 lo, hi, gap, step, sr))
                  break;
              }
            }
          }
          fold_searches(nb, sides[0], sides[1], last <= depth ? 2 : 4, stop, cos0, c2, bit,
                        buv + b0, bprod + b0, bits + b0, ext);
        }
        // isolation: a usable cell among steps 1 .. 1 + max_gap (those within the ring; a
        // cell without one goes to the scalar judge)
        const std::ptrdiff_t iso = std::min<std::ptrdiff_t>(1 + gap, depth);
        for (std::ptrdiff_t step = 1; step <= iso; ++step) {
          for (int sgn = -1; sgn <= 1; sgn += 2) {
            near_ok[n_near++] = at_ok(sgn, step);
            if (n_near == 16) {
              near_line(nb, near_ok, n_near, bits + b0);
              n_near = 0;
            }
          }
        }
        std::uint8_t* rc = reach + b0 * 4 + k;
        for (std::ptrdiff_t c = 0; c < nb; ++c)
          rc[4 * c] = static_cast<std::uint8_t>(std::min<std::int64_t>(ext[c], 255));
        continue;
      }
      for (int s : p.scales) {
        const std::ptrdiff_t s2 = p.max_gap > 0 ? s + 1 : s;  // max_gap 0: one candidate
        const double *a1 = at_x(-1, s), *a2 = at_x(-1, s2);
        const double *b1 = at_x(+1, s), *b2 = at_x(+1, s2);
        const Side A{a1, a1 + S, a1 + 2 * S, a2, a2 + S, a2 + 2 * S,
                     at_ok(-1, s), at_ok(-1, s2), slot_bits(r - s * dr), slot_bits(r - s2 * dr),
                     pad + b0 - s * dc, pad + b0 - s2 * dc};
        const Side B{b1, b1 + S, b1 + 2 * S, b2, b2 + S, b2 + 2 * S,
                     at_ok(+1, s), at_ok(+1, s2), slot_bits(r + s * dr), slot_bits(r + s2 * dr),
                     pad + b0 + s * dc, pad + b0 + s2 * dc};
        const std::int64_t near_bit = s == 1 ? kNearBit : 0;
        if (fused) {
          pairs[n_pairs++] = Pair{A, B, bit, near_bit};
        } else {
          kernel_line(nb, A, B, qx, qy, qz, cos0, c2, gap2, bit, near_bit, buv + b0, bprod + b0,
                      bits + b0);
        }
      }
      if (!has_scale1) {
        const std::ptrdiff_t s2 = p.max_gap > 0 ? 2 : 1;
        near_ok[n_near++] = at_ok(-1, 1);
        near_ok[n_near++] = at_ok(-1, s2);
        near_ok[n_near++] = at_ok(+1, 1);
        near_ok[n_near++] = at_ok(+1, s2);
      }
    }
#ifdef MIEM_SELECT_AVX512
    if (fused) {
      kernel_fused_avx512(nb, pairs, n_pairs, qx, qy, qz, cos0, c2, gap2, buv + b0, bprod + b0,
                          bits + b0);
    }
#endif
    if (n_near > 0) near_line(nb, near_ok, n_near, bits + b0);
  });
  const std::int64_t* centre_ok = slot_ok(r);
  if (angle_row) angles_line(W, buv, bprod, centre_ok, angle_row);
  // The kernel's verdicts for the whole row (vector code); the caller's scalar judge replaces
  // those of the cells the kernel could not finish (pass1_needs_judge).
  label_line(W, bits, centre_ok, p.min_directions, labels, flags_out);
}

}  // namespace miem::detail
