// min_step = "auto" (docs/SPEC.md "min_step='auto'"): over the first kAutoMinStepRows rows from the
// grid's first row with a finite cell, per grid axis (along a profile, across profiles) the
// median distance of finite neighbour pairs and the robust z noise
// 1.4826 median|z[i-1] - 2 z[i] + z[i+1]| / sqrt(6) of finite triples; min_step is
// 4 * max(noise) when that exceeds min(spacing), else off (-1).
//
// The four medians are exact (NumPy's: the middle value, or the mean of the two middle values)
// without a sort of all values. band_medians: a sample of the cells gives a narrow band of
// values around each middle; one pass over the grid counts the values below it and keeps those
// in it, where the middle ranks are selected (select_ranks, as the sample's band edges). When
// the sample rows hold fewer than 65,536 cells, the ranks are selected among all their values
// (direct_medians). When a middle rank falls outside its band, key_medians decides: the values
// are non-negative, so their float32 roundings order like them (rounding is monotone) and the
// float32 bit patterns order like the floats.
// Three passes over the grid, each computing the four quantities at once: histograms of the
// patterns' high 16 bits; in the bin of each middle rank, histograms of the low 16 bits (the
// float32 value of that rank); the doubles that round to that value (few), in which the rank is
// then selected. Distances are selected by their squares (sqrt is monotone: the middle
// distances are the square roots of the middle squares). Rows are split between threads;
// counts add up and the kept values are the same set, so the value is the same for any thread
// count. MinStepSelection (the stream's, which may not allocate and must not make one push pay
// the whole decision) selects the same middle values by radix selection over the doubles'
// 64-bit patterns, 16 bits a round, in steps of a few rows.
#include "auto_min_step.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <type_traits>

#include "miem/organized.hpp"
#include "parallel.hpp"
#include "vector_clones.hpp"

namespace miem {
namespace detail {
namespace {

constexpr std::size_t kBins = 1 << 16;
constexpr int kQ = 4;  // along: distance^2, |second difference|; across: the same
// band_medians' smallest sample (fewer cells: direct_medians)
constexpr std::ptrdiff_t kBandCells = std::ptrdiff_t{1} << 16;

// The values of ranks r0 <= r1 among the n >= 1 non-negative values at v (reordered), exactly
// (nth_element's). Beyond a few thousand values, the values of their bins first: the 64-bit
// patterns of non-negative doubles order like the values, so a histogram of the patterns'
// offsets from the smallest (kRankBins bins of equal width) gives the bins of the two ranks and
// their ranks within; those bins' values are moved to the front and nth_element runs on them
// only (a fraction of its time on all of them).
constexpr std::size_t kRankBins = 2048;
std::array<double, 2> select_ranks(double* v, std::size_t n, std::size_t r0, std::size_t r1) {
  std::size_t m = n, below = 0;  // the values selected among, and how many lie below them
  if (n >= 4 * kRankBins) {
    auto bits = [](double x) {
      std::uint64_t u;
      std::memcpy(&u, &x, sizeof u);
      return u;
    };
    double lo = v[0], hi = v[0];
    for (std::size_t i = 1; i < n; ++i) {
      lo = v[i] < lo ? v[i] : lo;
      hi = v[i] > hi ? v[i] : hi;
    }
    const std::uint64_t base = bits(lo), span = bits(hi) - base;
    int shift = 0;
    while ((span >> shift) >= kRankBins) ++shift;
    std::uint32_t h[kRankBins] = {};
    for (std::size_t i = 0; i < n; ++i) ++h[(bits(v[i]) - base) >> shift];
    std::size_t b0 = 0;  // the bins b0 <= b1 of ranks r0 and r1
    while (below + h[b0] <= r0) below += h[b0++];
    std::size_t upto = below + h[b0], b1 = b0;
    while (upto <= r1) upto += h[++b1];
    m = 0;  // their values to the front (a swap per value taken)
    for (std::size_t i = 0; i < n; ++i) {
      const std::uint64_t b = (bits(v[i]) - base) >> shift;
      if (b >= b0 && b <= b1) std::swap(v[m++], v[i]);
    }
  }
  const std::size_t s0 = r0 - below, s1 = r1 - below;
  std::nth_element(v, v + s0, v + m);
  if (s1 == s0) return {v[s0], v[s0]};
  std::nth_element(v + s0 + 1, v + s1, v + m);  // (nothing before s0 + 1 lies above v[s0])
  return {v[s0], v[s1]};
}

inline std::uint32_t key(double v) {  // float32 bit pattern of a non-negative v
  const float f = static_cast<float>(v);
  std::uint32_t u;
  std::memcpy(&u, &f, sizeof u);
  return u;
}

// (g(b) - g(a)).squaredNorm() from cell pointers (coordinates `ks` apart), in its order.
template <typename T>
inline double dist2_of(const T* a, const T* b, std::ptrdiff_t ks) {
  const double dx = static_cast<double>(b[0]) - static_cast<double>(a[0]);
  const double dy = static_cast<double>(b[ks]) - static_cast<double>(a[ks]);
  const double dz = static_cast<double>(b[2 * ks]) - static_cast<double>(a[2 * ks]);
  return dx * dx + dy * dy + dz * dz;
}

// The finite flags of row r of W cells (GridView::finite's test) into its slot of `fin`
// (3 * W bytes: the flags of three consecutive rows as a ring). `rowp(r)` is row r's first
// cell (cells cs apart, coordinates ks apart).
template <typename T, typename RowP>
void finite_flags(RowP&& rowp, std::ptrdiff_t W, std::ptrdiff_t cs, std::ptrdiff_t ks,
                  std::ptrdiff_t r, std::uint8_t* fin) {
  std::uint8_t* out = fin + (r % 3) * W;
  const T* p = rowp(r);
  for (std::ptrdiff_t c = 0; c < W; ++c) {
    const T* q = p + c * cs;
    out[c] = (q[0] - q[0]) + (q[ks] - q[ks]) + (q[2 * ks] - q[2 * ks]) == T(0);
  }
}

// The four quantities of the cells whose first cell is in row r of H rows of W cells:
// f(q, value), with the flags of rows r .. min(r + 2, H - 1) in `fin` (finite_flags).
template <typename T, typename RowP, typename F>
void visit_row(RowP&& rowp, std::ptrdiff_t H, std::ptrdiff_t W, std::ptrdiff_t cs,
               std::ptrdiff_t ks, std::ptrdiff_t r, const std::uint8_t* fin, F&& f) {
  const auto row = [&](std::ptrdiff_t i) { return fin + (i % 3) * W; };
  // squared distances and second differences of z, from cell pointers
  const auto dist2 = [ks](const T* a, const T* b) { return dist2_of(a, b, ks); };
  const auto second = [ks](const T* a, const T* b, const T* c) {
    return std::abs(static_cast<double>(a[2 * ks]) - 2.0 * static_cast<double>(b[2 * ks]) +
                    static_cast<double>(c[2 * ks]));
  };
  const std::uint8_t* f0 = row(r);
  const T* p0 = rowp(r);
  for (std::ptrdiff_t c = 0; c + 1 < W; ++c) {
    if (!(f0[c] & f0[c + 1])) continue;
    const T* a = p0 + c * cs;
    f(0, dist2(a, a + cs));
    if (c + 2 < W && f0[c + 2]) f(1, second(a, a + cs, a + 2 * cs));
  }
  if (r + 1 >= H) return;
  const std::uint8_t* f1 = row(r + 1);
  const std::uint8_t* f2 = r + 2 < H ? row(r + 2) : nullptr;
  const T* p1 = rowp(r + 1);
  const T* p2 = f2 ? rowp(r + 2) : nullptr;
  for (std::ptrdiff_t c = 0; c < W; ++c) {
    if (!(f0[c] & f1[c])) continue;
    const T* a = p0 + c * cs;
    const T* b = p1 + c * cs;
    f(2, dist2(a, b));
    if (f2 && f2[c]) f(3, second(a, b, p2 + c * cs));
  }
}

// The four quantities of the cells whose first cell is in rows [r0, r1) of H rows of W cells
// (visit_row), `fin` the flags' ring.
template <typename T, typename RowP, typename F>
void visit_rows(RowP&& rowp, std::ptrdiff_t H, std::ptrdiff_t W, std::ptrdiff_t cs,
                std::ptrdiff_t ks, std::ptrdiff_t r0, std::ptrdiff_t r1, std::uint8_t* fin,
                F&& f) {
  for (std::ptrdiff_t r = r0; r < std::min(H, r0 + 2); ++r) finite_flags<T>(rowp, W, cs, ks, r, fin);
  for (std::ptrdiff_t r = r0; r < r1; ++r) {
    if (r + 2 < H) finite_flags<T>(rowp, W, cs, ks, r + 2, fin);
    visit_row<T>(rowp, H, W, cs, ks, r, fin, f);
  }
}

template <typename T, typename F>
void visit(const GridView<T>& g, std::ptrdiff_t r0, std::ptrdiff_t r1, std::uint8_t* fin,
           F&& f) {
  const std::ptrdiff_t rs = g.row_stride;
  visit_rows<T>([&g, rs](std::ptrdiff_t r) { return g.data + r * rs; }, g.rows, g.cols,
                g.col_stride, g.coord_stride, r0, r1, fin, std::forward<F>(f));
}

#ifdef MIEM_SELECT_AVX512
// load_soa's loop over the dense layout (x, y, z, x, ...) of doubles, 8 cells a step (the same
// values and flags); returns the cells done (a multiple of 8).
__attribute__((target("avx512f,avx512vl"))) std::ptrdiff_t load_soa_xyz8(
    const double* p, std::ptrdiff_t W, double* __restrict x, double* __restrict y,
    double* __restrict z, double* __restrict f) {
  const __m512d zero = _mm512_setzero_pd(), one = _mm512_set1_pd(1.0);
  std::ptrdiff_t c = 0;
  for (; c + 8 <= W; c += 8) {
    __m512d vx, vy, vz;
    load_xyz8(p + 3 * c, vx, vy, vz);
    _mm512_storeu_pd(x + c, vx);
    _mm512_storeu_pd(y + c, vy);
    _mm512_storeu_pd(z + c, vz);
    _mm512_storeu_pd(f + c, _mm512_mask_blend_pd(finite8(vx, vy, vz), zero, one));
  }
  return c;
}
#endif

// One grid row as structure-of-arrays doubles (x, y, z, finite as 1 / 0), for the band pass.
template <typename T>
void load_soa(const GridView<T>& g, std::ptrdiff_t r, double* __restrict x, double* __restrict y,
              double* __restrict z, double* __restrict f) {
  const std::ptrdiff_t W = g.cols, cs = g.col_stride, ks = g.coord_stride;
  const T* p = g.data + r * g.row_stride;
  std::ptrdiff_t c = 0;
#ifdef MIEM_SELECT_AVX512
  if constexpr (std::is_same_v<T, double>) {
    if (cs == 3 && ks == 1 && has_avx512()) c = load_soa_xyz8(p, W, x, y, z, f);
  }
#endif
  for (; c < W; ++c) {
    const T* q = p + c * cs;
    // x - x is 0 for finite x and NaN for inf/NaN (GridView::finite's test, in T)
    const T t = (q[0] - q[0]) + (q[ks] - q[ks]) + (q[2 * ks] - q[2 * ks]);
    x[c] = static_cast<double>(q[0]);
    y[c] = static_cast<double>(q[ks]);
    z[c] = static_cast<double>(q[2 * ks]);
    f[c] = t == T(0) ? 1.0 : 0.0;
  }
}

// The four quantities of visit() whose first cell is in row 0 (SoA rows 0, 1, 2; row 1 / 2
// null beyond the grid), -1 where a quantity has no value (its cells are not all finite): q0
// (columns 0 .. W-2), q1 (0 .. W-3), q2 and q3 (0 .. W-1). The same expressions as visit().
MIEM_CLONES void row_quantities(std::ptrdiff_t W, const double* __restrict x0,
                                const double* __restrict y0, const double* __restrict z0,
                                const double* __restrict f0, const double* __restrict x1,
                                const double* __restrict y1, const double* __restrict z1,
                                const double* __restrict f1, const double* __restrict z2,
                                const double* __restrict f2, double* __restrict q0,
                                double* __restrict q1, double* __restrict q2,
                                double* __restrict q3) {
  for (std::ptrdiff_t c = 0; c + 1 < W; ++c) {
    const double dx = x0[c + 1] - x0[c], dy = y0[c + 1] - y0[c], dz = z0[c + 1] - z0[c];
    const double v = dx * dx + dy * dy + dz * dz;
    q0[c] = (f0[c] * f0[c + 1]) != 0.0 ? v : -1.0;
  }
  for (std::ptrdiff_t c = 0; c + 2 < W; ++c) {
    const double v = std::fabs(z0[c] - 2.0 * z0[c + 1] + z0[c + 2]);
    q1[c] = (f0[c] * f0[c + 1] * f0[c + 2]) != 0.0 ? v : -1.0;
  }
  if (x1 == nullptr) return;
  for (std::ptrdiff_t c = 0; c < W; ++c) {
    const double dx = x1[c] - x0[c], dy = y1[c] - y0[c], dz = z1[c] - z0[c];
    const double v = dx * dx + dy * dy + dz * dz;
    q2[c] = (f0[c] * f1[c]) != 0.0 ? v : -1.0;
  }
  if (z2 == nullptr) return;
  for (std::ptrdiff_t c = 0; c < W; ++c) {
    const double v = std::fabs(z0[c] - 2.0 * z1[c] + z2[c]);
    q3[c] = (f0[c] * f1[c] * f2[c]) != 0.0 ? v : -1.0;
  }
}

// Over n values (-1: none): how many, how many below a, how many in [a, b].
MIEM_CLONES void tally_band(std::ptrdiff_t n, const double* __restrict v, double a, double b,
                            std::int64_t* __restrict out3) {
  std::int64_t total = 0, below = 0, in = 0;
  for (std::ptrdiff_t c = 0; c < n; ++c) {
    const double x = v[c];
    total += x >= 0.0;
    below += (x >= 0.0) & (x < a);
    in += (x >= a) & (x <= b);
  }
  out3[0] += total;
  out3[1] += below;
  out3[2] += in;
}

// The values of v[0 .. n) in [a, b] stored at out in order (room for 8 past the last one),
// how many there are.
std::ptrdiff_t keep_band_portable(std::ptrdiff_t n, const double* __restrict v, double a,
                                  double b, double* __restrict out) {
  std::ptrdiff_t k = 0;
  for (std::ptrdiff_t c = 0; c < n; ++c) {
    out[k] = v[c];
    k += (v[c] >= a) & (v[c] <= b);
  }
  return k;
}
#ifdef MIEM_SELECT_AVX512
__attribute__((target("avx512f,avx512vl"))) std::ptrdiff_t keep_band_avx512(
    std::ptrdiff_t n, const double* __restrict v, double a, double b, double* __restrict out) {
  const __m512d va = _mm512_set1_pd(a), vb = _mm512_set1_pd(b);
  std::ptrdiff_t k = 0, c = 0;
  for (; c + 8 <= n; c += 8) {
    const __m512d x = _mm512_loadu_pd(v + c);
    const __mmask8 m =
        _mm512_cmp_pd_mask(x, va, _CMP_GE_OQ) & _mm512_cmp_pd_mask(x, vb, _CMP_LE_OQ);
    _mm512_storeu_pd(out + k, _mm512_maskz_compress_pd(m, x));
    k += __builtin_popcount(m);
  }
  return k + keep_band_portable(n - c, v + c, a, b, out + k);
}
#endif
inline std::ptrdiff_t keep_band(std::ptrdiff_t n, const double* v, double a, double b,
                                double* out) {
#ifdef MIEM_SELECT_AVX512
  if (has_avx512()) return keep_band_avx512(n, v, a, b, out);
#endif
  return keep_band_portable(n, v, a, b, out);
}

// A middle rank being selected: quantity q, its rank among q's values, the key bits known.
struct Pick {
  int q = 0;
  std::size_t rank = 0;
  std::uint32_t hi = 0, full = 0;  // the high 16 bits, then the whole float32 pattern
};

using Counts = std::array<std::size_t, kQ>;
using Mids = std::array<std::array<double, 2>, kQ>;  // ranks (n - 1) / 2 and n / 2

// The smallest b with sum(h[0..b]) > rank; rank becomes the rank within bin b.
std::uint32_t bin_of(const std::uint32_t* h, std::size_t& rank) {
  std::size_t b = 0;
  while (h[b] <= rank) rank -= h[b++];
  return static_cast<std::uint32_t>(b);
}

// The middle values of each quantity (Mids) by the key histograms: always exact.
template <typename T>
void key_medians(const GridView<T>& g, int nt, Counts& count, Mids& mids,
                 std::vector<double>& scratch) {
  const std::ptrdiff_t H = g.rows, W = g.cols;
  // per thread: 4 histograms and the finite-flag ring (in 32-bit words)
  const std::size_t ring = static_cast<std::size_t>(3 * W + 3) / 4;
  const std::size_t per = kQ * kBins + ring;
  std::vector<std::uint32_t> work(per * static_cast<std::size_t>(nt));
  count = Counts{};
  std::vector<std::uint32_t> hist(kQ * kBins, 0);
  const auto rows_of = [&](int t) {
    return std::pair<std::ptrdiff_t, std::ptrdiff_t>{H * t / nt, H * (t + 1) / nt};
  };
  const auto ring_of = [&](int t) {
    return reinterpret_cast<std::uint8_t*>(work.data() + per * t + kQ * kBins);
  };
  // pass 1: counts and high-16-bit histograms
#pragma omp parallel for schedule(static, 1) num_threads(nt) if (nt > 1)
  for (int t = 0; t < nt; ++t) {
    std::uint32_t* h = work.data() + per * t;
    std::fill(h, h + kQ * kBins, 0u);
    const auto [r0, r1] = rows_of(t);
    visit(g, r0, r1, ring_of(t), [h](int q, double v) { ++h[q * kBins + (key(v) >> 16)]; });
  }
  for (int t = 0; t < nt; ++t)
    for (std::size_t i = 0; i < kQ * kBins; ++i) hist[i] += work[per * t + i];
  for (int q = 0; q < kQ; ++q)
    for (std::size_t b = 0; b < kBins; ++b) count[q] += hist[q * kBins + b];
  // the middle ranks of each quantity and their high bits
  std::vector<Pick> picks;
  for (int q = 0; q < kQ; ++q) {
    const std::size_t n = count[q];
    if (n == 0) continue;
    for (std::size_t rank : {(n - 1) / 2, n / 2}) {
      if (!picks.empty() && picks.back().q == q && picks.back().rank == rank) continue;
      Pick p;
      p.q = q;
      p.rank = rank;
      p.hi = bin_of(hist.data() + q * kBins, p.rank);
      picks.push_back(p);
    }
  }
  const int np = static_cast<int>(picks.size());
  // pass 2: per pick, the low 16 bits within its bin (the pick's histograms reuse `work`)
  std::vector<std::uint32_t> lo(static_cast<std::size_t>(np) * kBins, 0);
  const std::size_t per2 = static_cast<std::size_t>(np) * kBins + ring;
  work.assign(per2 * static_cast<std::size_t>(nt), 0u);
#pragma omp parallel for schedule(static, 1) num_threads(nt) if (nt > 1)
  for (int t = 0; t < nt; ++t) {
    std::uint32_t* h = work.data() + per2 * t;
    const auto [r0, r1] = rows_of(t);
    visit(g, r0, r1, reinterpret_cast<std::uint8_t*>(h + np * kBins), [&](int q, double v) {
      const std::uint32_t k = key(v);
      for (int s = 0; s < np; ++s)
        if (picks[s].q == q && (k >> 16) == picks[s].hi) ++h[s * kBins + (k & 0xFFFF)];
    });
  }
  for (int t = 0; t < nt; ++t)
    for (std::size_t i = 0; i < static_cast<std::size_t>(np) * kBins; ++i)
      lo[i] += work[per2 * t + i];
  for (int s = 0; s < np; ++s)
    picks[s].full = (picks[s].hi << 16) | bin_of(lo.data() + s * kBins, picks[s].rank);
  // pass 3: the doubles of each pick's float32 value, then the rank among them
  std::vector<std::vector<double>> few(static_cast<std::size_t>(np * nt));
  const std::size_t per3 = ring;
  work.assign(per3 * static_cast<std::size_t>(nt), 0u);
#pragma omp parallel for schedule(static, 1) num_threads(nt) if (nt > 1)
  for (int t = 0; t < nt; ++t) {
    const auto [r0, r1] = rows_of(t);
    visit(g, r0, r1, reinterpret_cast<std::uint8_t*>(work.data() + per3 * t),
          [&](int q, double v) {
            const std::uint32_t k = key(v);
            for (int s = 0; s < np; ++s)
              if (picks[s].q == q && k == picks[s].full) few[s * nt + t].push_back(v);
          });
  }
  for (int s = 0; s < np; ++s) {
    std::vector<double>& v = scratch;
    v.clear();
    for (int t = 0; t < nt; ++t)
      v.insert(v.end(), few[s * nt + t].begin(), few[s * nt + t].end());
    const auto mid = v.begin() + static_cast<std::ptrdiff_t>(picks[s].rank);
    std::nth_element(v.begin(), mid, v.end());
    // the pick of rank (n - 1) / 2 comes first (the only one when n is odd)
    const bool first = s == 0 || picks[s - 1].q != picks[s].q;
    if (first) {
      mids[picks[s].q] = {*mid, *mid};
    } else {
      mids[picks[s].q][1] = *mid;
    }
  }
}

// The middle values from a band around a sample's middle: the sample gives values a <= b with
// the middle ranks between them unless it is far off; one pass counts the values below a and
// keeps those in [a, b] (a few per cent), where the ranks are then selected. False (nothing
// decided) when a middle rank falls outside the band. For at least kBandCells cells (fewer:
// direct_medians, auto_survey decides).
template <typename T>
bool band_medians(const GridView<T>& g, int nt, Counts& count, Mids& mids,
                  std::vector<double>& scratch) {
  const std::ptrdiff_t H = g.rows, W = g.cols;
  // the sample: every k-th cell in row-major order (k prime and not dividing the row length,
  // so the sample walks across all rows and columns: spacings may change from row to row)
  std::ptrdiff_t k = 31;
  while (W % k == 0) k += 2;
  std::array<std::vector<double>, kQ> smp;
  const auto fin = [&g](std::ptrdiff_t r, std::ptrdiff_t c) { return g.finite(r, c); };
  const std::ptrdiff_t rs = g.row_stride, cs = g.col_stride, ks = g.coord_stride;
  const auto z = [&](const T* p) { return static_cast<double>(p[2 * ks]); };
  const auto dist2 = [ks](const T* a, const T* b) { return dist2_of(a, b, ks); };
  for (std::ptrdiff_t i = 0; i < H * W; i += k) {
    const std::ptrdiff_t r = i / W, c = i % W;
    if (!fin(r, c)) continue;
    const T* p = g.data + r * rs + c * cs;
    if (c + 1 < W && fin(r, c + 1)) {
      smp[0].push_back(dist2(p, p + cs));
      if (c + 2 < W && fin(r, c + 2))
        smp[1].push_back(std::abs(z(p) - 2.0 * z(p + cs) + z(p + 2 * cs)));
    }
    if (r + 1 < H && fin(r + 1, c)) {
      smp[2].push_back(dist2(p, p + rs));
      if (r + 2 < H && fin(r + 2, c))
        smp[3].push_back(std::abs(z(p) - 2.0 * z(p + rs) + z(p + 2 * rs)));
    }
  }
  std::array<double, kQ> a{}, b{};
  for (int q = 0; q < kQ; ++q) {
    std::vector<double>& v = smp[q];
    const std::size_t n = v.size();
    if (n < 1000) return false;
    const double d = 4.0 / std::sqrt(static_cast<double>(n));
    const auto i0 = static_cast<std::size_t>(std::max(0.0, std::floor(n * (0.5 - d))));
    const auto i1 = std::min(n - 1, static_cast<std::size_t>(std::ceil(n * (0.5 + d))));
    const std::array<double, 2> ab = select_ranks(v.data(), n, i0, i1);
    a[q] = ab[0];
    b[q] = ab[1];
  }
  std::vector<std::array<std::size_t, 2 * kQ>> tally(static_cast<std::size_t>(nt));
  std::vector<std::array<std::vector<double>, kQ>> in(static_cast<std::size_t>(nt));
  // per thread: a ring of 3 SoA rows (x, y, z, finite) and the 4 quantities of a row
  const std::size_t per = static_cast<std::size_t>(16 * W);
  std::vector<double> rows(per * static_cast<std::size_t>(nt));
#pragma omp parallel for schedule(static, 1) num_threads(nt) if (nt > 1)
  for (int t = 0; t < nt; ++t) {
    std::int64_t c3[kQ][3] = {};  // totals, below a, in [a, b]
    auto& keep = in[t];
    double* base = rows.data() + per * t;
    const auto slot = [&](std::ptrdiff_t r) { return base + (r % 3) * 4 * W; };
    double* qv = base + 12 * W;  // q0 .. q3, W apart
    const std::ptrdiff_t r0 = H * t / nt, r1 = H * (t + 1) / nt;
    for (std::ptrdiff_t r = r0; r < std::min(H, r0 + 2); ++r) {
      double* sl = slot(r);
      load_soa(g, r, sl, sl + W, sl + 2 * W, sl + 3 * W);
    }
    for (std::ptrdiff_t r = r0; r < r1; ++r) {
      if (r + 2 < H) {
        double* sl = slot(r + 2);
        load_soa(g, r + 2, sl, sl + W, sl + 2 * W, sl + 3 * W);
      }
      const double* a0 = slot(r);
      const double* a1 = r + 1 < H ? slot(r + 1) : nullptr;
      const double* a2 = r + 2 < H ? slot(r + 2) : nullptr;
      row_quantities(W, a0, a0 + W, a0 + 2 * W, a0 + 3 * W, a1, a1 ? a1 + W : nullptr,
                     a1 ? a1 + 2 * W : nullptr, a1 ? a1 + 3 * W : nullptr,
                     a2 ? a2 + 2 * W : nullptr, a2 ? a2 + 3 * W : nullptr, qv, qv + W,
                     qv + 2 * W, qv + 3 * W);
      const std::ptrdiff_t n[kQ] = {W - 1, W - 2, a1 ? W : 0, a2 ? W : 0};
      for (int q = 0; q < kQ; ++q) {
        if (n[q] <= 0) continue;
        const double* v = qv + q * W;
        const std::int64_t before = c3[q][2];
        tally_band(n[q], v, a[q], b[q], c3[q]);
        const std::int64_t m = c3[q][2] - before;
        if (m == 0) continue;
        // the values in the band, in column order (keep_band stores 8 at a time)
        std::vector<double>& kq = keep[q];
        const std::size_t k0 = kq.size();
        kq.resize(k0 + static_cast<std::size_t>(m) + 8);
        keep_band(n[q], v, a[q], b[q], kq.data() + k0);
        kq.resize(k0 + static_cast<std::size_t>(m));
      }
    }
    std::array<std::size_t, 2 * kQ> c{};
    for (int q = 0; q < kQ; ++q) {
      c[q] = static_cast<std::size_t>(c3[q][0]);
      c[kQ + q] = static_cast<std::size_t>(c3[q][1]);
    }
    tally[t] = c;
  }
  count = Counts{};
  for (int q = 0; q < kQ; ++q) {
    std::size_t below = 0;
    std::vector<double>& v = scratch;
    v.clear();
    for (int t = 0; t < nt; ++t) {
      count[q] += tally[t][q];
      below += tally[t][kQ + q];
      v.insert(v.end(), in[t][q].begin(), in[t][q].end());
    }
    const std::size_t n = count[q];
    if (n == 0) continue;
    const std::size_t ranks[2] = {(n - 1) / 2, n / 2};
    for (std::size_t rank : ranks)
      if (rank < below || rank - below >= v.size()) return false;
    mids[q] = select_ranks(v.data(), v.size(), ranks[0] - below, ranks[1] - below);
  }
  return true;
}

// The middle values of each quantity by selection among all of them: for a sample too small
// for band_medians (under 65,536 cells), where key_medians' histograms (1 MB, cleared per call,
// and three passes) cost more than the values themselves (a 64 x 64 grid: 2.8 ms of a 3.5 ms
// detection). Exact, as the others.
template <typename T>
void direct_medians(const GridView<T>& g, Counts& count, Mids& mids) {
  std::array<std::vector<double>, kQ> v;
  std::vector<std::uint8_t> fin(static_cast<std::size_t>(3 * g.cols));
  visit(g, 0, g.rows, fin.data(), [&v](int q, double x) { v[q].push_back(x); });
  for (int q = 0; q < kQ; ++q) {
    std::vector<double>& w = v[q];
    count[q] = w.size();
    if (w.empty()) continue;
    mids[q] = select_ranks(w.data(), w.size(), (w.size() - 1) / 2, w.size() / 2);
  }
}

// min_step and the z noise from the four medians' middle values (squared distances, |second
// differences|).
AutoSurvey from_medians(const Counts& count, const Mids& mids) {
  std::array<double, kQ> med{};
  for (int q = 0; q < kQ; ++q) {
    if (count[q] == 0) continue;
    const auto f = [q](double v) { return q % 2 == 0 ? std::sqrt(v) : v; };  // distances: roots
    // np.median: the middle value, or the mean of the two middle values
    med[q] = count[q] % 2 == 1 ? f(mids[q][1]) : (f(mids[q][0]) + f(mids[q][1])) / 2.0;
  }
  double spacing = 0.0, noise = 0.0;
  bool any = false;
  for (int axis = 0; axis < 2; ++axis) {  // 0: along a profile (columns), 1: across (rows)
    if (count[2 * axis] == 0 || count[2 * axis + 1] == 0) continue;
    const double dist = med[2 * axis];
    const double sigma = 1.4826 * med[2 * axis + 1] / std::sqrt(6.0);
    spacing = any ? std::min(spacing, dist) : dist;
    noise = any ? std::max(noise, sigma) : sigma;
    any = true;
  }
  if (!any) return {};
  const double m = 4.0 * noise;
  return {m > spacing ? m : -1.0, noise};
}

inline std::uint64_t bits64(double v) {  // non-negative doubles order like their patterns
  std::uint64_t u;
  std::memcpy(&u, &v, sizeof u);
  return u;
}

}  // namespace

template <typename T>
std::ptrdiff_t first_finite_row(const GridView<T>& g) {
  for (std::ptrdiff_t r = 0; r < g.rows; ++r)
    for (std::ptrdiff_t c = 0; c < g.cols; ++c)
      if (g.finite(r, c)) return r;
  return g.rows;
}

template <typename T>
GridView<T> min_step_rows(const GridView<T>& g) {
  const std::ptrdiff_t f = first_finite_row(g);
  GridView<T> s = g;
  s.data = g.data + f * g.row_stride;
  s.rows = std::min<std::ptrdiff_t>(kAutoMinStepRows, g.rows - f);
  return s;
}

template <typename T>
AutoSurvey auto_survey(const GridView<T>& grid, std::vector<double>& scratch, int num_threads) {
  const GridView<T> g = min_step_rows(grid);
  const std::ptrdiff_t H = g.rows, W = g.cols;
  if (H < 1 || W < 1) return {};
  const int nt = std::max(1, std::min<int>(thread_count(num_threads, H * W),
                                           static_cast<int>(H)));
  Counts count{};
  Mids mids{};
  if (H * W < kBandCells) {
    direct_medians(g, count, mids);
  } else if (!band_medians(g, nt, count, mids, scratch)) {
    key_medians(g, nt, count, mids, scratch);
  }
  return from_medians(count, mids);
}

// The exact medians by radix selection over the doubles' 64-bit patterns, 16 bits a round,
// in resumable steps (stream.hpp MinStepSelection): round 0 counts the high 16 bits of each
// quantity's values as rows come in, then each of rounds 1-3 visits every row again and
// counts, per pick (the two middle ranks of each quantity), the next 16 bits of the values
// whose bits above match the pick's so far. The same histograms whatever the steps.
namespace {
constexpr std::size_t kRadixBins = std::size_t{1} << 16;
}  // namespace

template <typename T>
void MinStepSelection<T>::init(std::ptrdiff_t width, std::ptrdiff_t coord_stride) {
  width_ = width;
  ks_ = coord_stride;
  hist_.assign(2 * kQ * kRadixBins, 0u);
  fin_.assign(static_cast<std::size_t>(3 * width), 0);
  reset();
}

template <typename T>
void MinStepSelection<T>::reset() noexcept {
  std::fill(hist_.begin(), hist_.begin() + static_cast<std::ptrdiff_t>(kQ * kRadixBins), 0u);
  rows_ = next_ = 0;
  round_ = 0;
  value_ = noise_ = -1.0;
}

template <typename T>
void MinStepSelection<T>::add_row(const T* const* rows, std::ptrdiff_t n) noexcept {
  const auto rowp = [rows](std::ptrdiff_t r) { return rows[r]; };
  std::uint32_t* h = hist_.data();
  const auto count = [h](int q, double v) { ++h[q * kRadixBins + (bits64(v) >> 48)]; };
  rows_ = n;
  finite_flags<T>(rowp, width_, std::ptrdiff_t{1}, ks_, n - 1, fin_.data());
  // the quantities of row r read rows r + 1, r + 2: complete once row r + 2 is in
  for (; next_ + 2 < n; ++next_)
    visit_row<T>(rowp, n, width_, std::ptrdiff_t{1}, ks_, next_, fin_.data(), count);
}

template <typename T>
void MinStepSelection<T>::close(const T* const* rows) noexcept {
  const auto rowp = [rows](std::ptrdiff_t r) { return rows[r]; };
  std::uint32_t* h = hist_.data();
  const auto count = [h](int q, double v) { ++h[q * kRadixBins + (bits64(v) >> 48)]; };
  for (; next_ < rows_; ++next_)
    visit_row<T>(rowp, rows_, width_, std::ptrdiff_t{1}, ks_, next_, fin_.data(), count);
  for (int q = 0; q < kQ; ++q) {
    count_[q] = 0;
    for (std::size_t b = 0; b < kRadixBins; ++b) count_[q] += h[q * kRadixBins + b];
  }
  // the picks: ranks (n - 1) / 2 and n / 2 of quantity q are picks 2 q and 2 q + 1 (none
  // when q has no value: its prefix can match no pattern), their prefixes so far
  std::fill(prefix_, prefix_ + 2 * kQ, ~std::uint64_t{0});
  for (int q = 0; q < kQ; ++q) {
    rank_[2 * q] = rank_[2 * q + 1] = 0;
    if (count_[q] == 0) continue;
    for (int k = 0; k < 2; ++k) {
      std::size_t rank = k == 0 ? (count_[q] - 1) / 2 : count_[q] / 2;
      prefix_[2 * q + k] = static_cast<std::uint64_t>(bin_of(h + q * kRadixBins, rank)) << 48;
      rank_[2 * q + k] = rank;
    }
  }
  round_ = 1;
  next_ = 0;
  if (count_[0] + count_[1] + count_[2] + count_[3] == 0) finish();  // nothing to select
}

template <typename T>
bool MinStepSelection<T>::step(const T* const* rows, std::ptrdiff_t budget) noexcept {
  const auto rowp = [rows](std::ptrdiff_t r) { return rows[r]; };
  std::uint32_t* h = hist_.data();
  std::uint8_t* fin = fin_.data();
  const std::ptrdiff_t W = width_, H = rows_;
  while (round_ >= 1 && round_ <= 3 && budget > 0) {
    const int shift = 48 - 16 * round_;  // the bits found this round: [shift, shift + 16)
    const std::uint64_t known = ~std::uint64_t{0} << (shift + 16);
    if (next_ == 0) {
      std::fill(h, h + 2 * kQ * kRadixBins, 0u);
      for (std::ptrdiff_t r = 0; r < std::min<std::ptrdiff_t>(H, 2); ++r)
        finite_flags<T>(rowp, W, std::ptrdiff_t{1}, ks_, r, fin);
    }
    const std::uint64_t* pre = prefix_;
    // few values match a prefix (a branch seldom taken: the histograms, 2 MB, stay untouched)
    const auto count = [&](int q, double v) {
      const std::uint64_t k = bits64(v), top = k & known, digit = (k >> shift) & 0xFFFF;
      if (top == pre[2 * q]) ++h[(2 * q) * kRadixBins + digit];
      if (top == pre[2 * q + 1]) ++h[(2 * q + 1) * kRadixBins + digit];
    };
    for (; next_ < H && budget > 0; ++next_, --budget) {
      if (next_ + 2 < H) finite_flags<T>(rowp, W, std::ptrdiff_t{1}, ks_, next_ + 2, fin);
      visit_row<T>(rowp, H, W, std::ptrdiff_t{1}, ks_, next_, fin, count);
    }
    if (next_ < H) break;
    for (int s = 0; s < 2 * kQ; ++s)
      if (count_[s / 2] > 0)
        prefix_[s] |= static_cast<std::uint64_t>(bin_of(h + s * kRadixBins, rank_[s])) << shift;
    next_ = 0;
    if (++round_ > 3) finish();
  }
  return done();
}

template <typename T>
void MinStepSelection<T>::finish() noexcept {
  Mids mids{};
  Counts count{};
  for (int q = 0; q < kQ; ++q) count[q] = count_[q];
  for (int s = 0; s < 2 * kQ; ++s) {
    if (count[s / 2] == 0) continue;
    double v;
    std::memcpy(&v, &prefix_[s], sizeof v);
    mids[s / 2][s % 2] = v;
  }
  const AutoSurvey v = from_medians(count, mids);  // -1 (off) without values
  value_ = v.min_step;
  noise_ = v.noise;
  round_ = 4;
}

template <typename T>
std::ptrdiff_t MinStepSelection<T>::visits_left() const noexcept {
  if (round_ < 1 || round_ > 3) return round_ > 3 ? 0 : 3 * rows_;
  return (3 - round_) * rows_ + (rows_ - next_);
}

template std::ptrdiff_t first_finite_row<float>(const GridView<float>&);
template std::ptrdiff_t first_finite_row<double>(const GridView<double>&);
template GridView<float> min_step_rows<float>(const GridView<float>&);
template GridView<double> min_step_rows<double>(const GridView<double>&);
template class MinStepSelection<float>;
template class MinStepSelection<double>;
template AutoSurvey auto_survey<float>(const GridView<float>&, std::vector<double>&, int);
template AutoSurvey auto_survey<double>(const GridView<double>&, std::vector<double>&, int);

}  // namespace detail

template <typename T>
double auto_min_step(const GridView<T>& grid) {
  std::vector<double> buf;
  return detail::auto_min_step(grid, buf, 1);
}

template <typename T>
double auto_z_noise(const GridView<T>& grid) {
  std::vector<double> buf;
  return detail::auto_survey(grid, buf, 1).noise;
}

template double auto_min_step<float>(const GridView<float>&);
template double auto_min_step<double>(const GridView<double>&);
template double auto_z_noise<float>(const GridView<float>&);
template double auto_z_noise<double>(const GridView<double>&);

}  // namespace miem
