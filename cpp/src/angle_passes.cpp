// Angle passes (docs/SPEC.md "Detection"): finiteness and the coordinate range ("Numbers"),
// pass 1 over every finite cell, the automatic theta0, and the later passes over the cells
// whose rays meet a newly removed cell.
// One judge per cell reads only the usable mask and the grid, so cells are independent within a
// pass (Jacobi): row-parallel, and identical for any thread count.
#include <algorithm>
#include <array>
#include <cmath>
#include <cstring>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <vector>

#include "finite_bits.hpp"
#include "judge.hpp"
#include "pass1_row.hpp"
#include "parallel.hpp"
#include "stages.hpp"
#include "vector_clones.hpp"

namespace miem::detail {

namespace {

// GridView::finite of n cells at p (cells cs apart, coordinates ys apart) as straight-line
// code: us[c] 1 or 0 and, with `lb`, the label NORMAL or INVALID; returns the finite count and
// raises `top` (signed) to the largest finite_abs_bits (SPEC "Numbers": every finite coordinate
// counts, a dropout's too; finite_point: fused here, 2-3 ms of a 345 ms run at 2048^2, where a
// second pass over each row with largest_finite_magnitude measured 4-5 ms).
template <typename T, typename S, typename CS, typename YS>
inline __attribute__((always_inline)) std::ptrdiff_t finite_cells(
    const T* __restrict p, std::ptrdiff_t n, CS cs, YS ys, std::uint8_t* __restrict us,
    std::uint8_t* __restrict lb, S& top) {
  std::ptrdiff_t nf = 0;
  S t = top;
  for (std::ptrdiff_t c = 0; c < n; ++c) {
    const T* q = p + c * cs;
    const bool fin = finite_point(q[0], q[ys], q[2 * ys], t);
    us[c] = fin;
    if (lb != nullptr) lb[c] = fin ? kNormal : kInvalid;
    nf += fin;
  }
  top = t;
  return nf;
}

// finite_cells with labels or without (lb null), the loop without a test per cell.
template <typename T, typename S, typename CS, typename YS>
inline __attribute__((always_inline)) std::ptrdiff_t finite_cells_lb(
    const T* p, std::ptrdiff_t n, CS cs, YS ys, std::uint8_t* us, std::uint8_t* lb,
    S& top) {
  return lb != nullptr ? finite_cells(p, n, cs, ys, us, lb, top)
                       : finite_cells(p, n, cs, ys, us, nullptr, top);
}

// The interleaved layout (x, y, z, x, ...) in vector clones: the constant strides vectorise
// (the baseline build has no 64-bit maximum, and its loop ran one cell at a time).
using K3 = std::integral_constant<std::ptrdiff_t, 3>;
using K1 = std::integral_constant<std::ptrdiff_t, 1>;
MIEM_CLONES std::ptrdiff_t finite_xyz(const double* p, std::ptrdiff_t n, std::uint8_t* us,
                                      std::uint8_t* lb, std::int64_t& top) {
  return finite_cells_lb(p, n, K3{}, K1{}, us, lb, top);
}
MIEM_CLONES std::ptrdiff_t finite_xyz(const float* p, std::ptrdiff_t n, std::uint8_t* us,
                                      std::uint8_t* lb, std::int32_t& top) {
  return finite_cells_lb(p, n, K3{}, K1{}, us, lb, top);
}

#ifdef MIEM_SELECT_AVX512
// The bytes of an 8-bit mask: byte i = bit i (0 or 1).
constexpr std::array<std::uint64_t, 256> kMaskBytes = [] {
  std::array<std::uint64_t, 256> t{};
  for (unsigned m = 0; m < 256; ++m)
    for (unsigned i = 0; i < 8; ++i) t[m] |= static_cast<std::uint64_t>((m >> i) & 1u) << (8 * i);
  return t;
}();

// finite_xyz of doubles in AVX-512, 8 cells (24 coordinates) a step, straight from the
// interleaved coordinates: a coordinate is finite when its magnitude's bits lie below
// infinity's (finite_abs_bits), a cell when its three are (then (x - x) + (y - y) + (z - z)
// == 0); `top` the largest finite pattern (an integer maximum: any order). GCC's clones of
// finite_xyz take 64 cells a step, for the byte stores, and spill. The same bytes, count and
// `top` as finite_cells.
__attribute__((target("avx512f,avx512vl"))) std::ptrdiff_t finite_xyz_avx512(
    const double* p, std::ptrdiff_t n, std::uint8_t* us, std::uint8_t* lb, std::int64_t& top) {
  const __m512i abs_mask = _mm512_set1_epi64(0x7FFFFFFFFFFFFFFFll);
  const __m512i inf = _mm512_set1_epi64(0x7FF0000000000000ll);
  __m512i t = _mm512_set1_epi64(top);
  std::ptrdiff_t nf = 0, c = 0;
  for (; c + 8 <= n; c += 8) {
    const double* q = p + 3 * c;
    std::uint32_t m = 0;  // bit k: coordinate k of the 24 is finite
    for (int v = 0; v < 3; ++v) {
      const __m512i u = _mm512_and_si512(_mm512_loadu_si512(q + 8 * v), abs_mask);
      const __mmask8 f = _mm512_cmplt_epu64_mask(u, inf);
      t = _mm512_mask_max_epi64(t, f, t, u);
      m |= static_cast<std::uint32_t>(f) << (8 * v);
    }
    // cell i finite: bits 3i .. 3i + 2 all set; then bits 0, 3, .., 21 gathered into 0 .. 7
    std::uint32_t x = m & (m >> 1) & (m >> 2) & 0x249249u;
    x = (x | (x >> 2)) & 0xC30C3u;
    x = (x | (x >> 4)) & 0xF00Fu;
    x = (x | (x >> 8)) & 0xFFu;
    const std::uint64_t bytes = kMaskBytes[x];
    std::memcpy(us + c, &bytes, 8);
    if (lb != nullptr) {  // NORMAL (0) where finite, else INVALID (3)
      static_assert(kNormal == 0 && kInvalid == 3, "the label bytes below");
      const std::uint64_t labels = (bytes ^ 0x0101010101010101ull) * kInvalid;
      std::memcpy(lb + c, &labels, 8);
    }
    nf += __builtin_popcount(x);
  }
  alignas(64) std::int64_t lanes[8];
  _mm512_store_si512(lanes, t);
  std::int64_t tt = *std::max_element(lanes, lanes + 8);
  nf += finite_cells_lb(p + 3 * c, n - c, K3{}, K1{}, us + c, lb ? lb + c : nullptr, tt);
  top = tt;
  return nf;
}
#endif

// finite_cells of row r of g: the interleaved layout by finite_xyz, any other strides by the
// same loop (scalar).
template <typename T>
std::ptrdiff_t finite_row(const GridView<T>& g, std::ptrdiff_t r, std::uint8_t* us,
                          std::uint8_t* lb, AbsBits<T>& top) {
  const T* base = g.data + r * g.row_stride;
  const std::ptrdiff_t W = g.cols, cs = g.col_stride, ys = g.coord_stride;
  using S = std::conditional_t<sizeof(T) == 8, std::int64_t, std::int32_t>;
  S t = static_cast<S>(top);
  std::ptrdiff_t nf;
#ifdef MIEM_SELECT_AVX512
  if constexpr (std::is_same_v<T, double>) {
    if (cs == 3 && ys == 1 && has_avx512()) {
      nf = finite_xyz_avx512(base, W, us, lb, t);
      top = static_cast<AbsBits<T>>(t);
      return nf;
    }
  }
#endif
  nf = cs == 3 && ys == 1 ? finite_xyz(base, W, us, lb, t)
                          : finite_cells_lb(base, W, cs, ys, us, lb, t);
  top = static_cast<AbsBits<T>>(t);
  return nf;
}

// Judge rows [r_begin, r_end) of pass 1 with the row kernel (pass1_row.hpp), keeping its ring
// of 2 depth + 1 converted rows (each grid row is converted once; depth = smax + 1, deeper with
// min_step). Each row's finiteness is found as it is loaded (pass 0 fused into pass 1: the
// grid is read once): the block's own rows into `usable` and their labels (NORMAL or INVALID)
// and zero flags, the rows of the blocks around into sc.fin. The cells the kernel cannot
// settle are listed in sc.judge for the scalar judge, which may read any row's finiteness:
// the caller judges them once every block is done. With min_step, `reach` (4 bytes per cell)
// receives the rays read. Returns the block's finite count; raises `top` to its rows' largest
// finite coordinate magnitude (finite_abs_bits).
template <typename T>
std::ptrdiff_t pass1_rows(const GridView<T>& g, std::uint8_t* usable, const DetectParams& p,
                          int depth, std::ptrdiff_t r_begin, std::ptrdiff_t r_end,
                          detail::RowScratch& sc, std::uint8_t* labels, std::uint8_t* flags_out,
                          double* angle_out, std::uint8_t* reach, AbsBits<T>& top) {
  const std::ptrdiff_t H = g.rows, W = g.cols, pad = depth;
  pass1_prepare(sc, W, depth, p.min_step >= 0.0);
  sc.judge.clear();
  const Pass1Ring ring{&sc, H, W, depth};
  std::ptrdiff_t n_finite = 0;
  const auto load = [&](std::ptrdiff_t rr) {
    const bool own = rr >= r_begin && rr < r_end;
    std::uint8_t* us = own ? usable + rr * W : sc.fin.data();
    AbsBits<T> row_top = 0;
    const std::ptrdiff_t nf = finite_row(g, rr, us, own ? labels + rr * W : nullptr, row_top);
    if (own) {
      n_finite += nf;
      top = std::max(top, row_top);
      if (flags_out) std::fill(flags_out + rr * W, flags_out + (rr + 1) * W, std::uint8_t{0});
    }
    const T* base = g.data + rr * g.row_stride;
    pass1_load(ring, rr, base, base + g.coord_stride, base + 2 * g.coord_stride, g.col_stride,
               us);
  };
  for (std::ptrdiff_t rr = std::max<std::ptrdiff_t>(0, r_begin - pad);
       rr < std::min(H, r_begin + pad); ++rr) {
    load(rr);
  }
  for (std::ptrdiff_t r = r_begin; r < r_end; ++r) {
    if (r + pad < H) load(r + pad);
    double* angle_row = angle_out ? angle_out + r * W : nullptr;
    pass1_row(ring, r, p, labels + r * W, flags_out ? flags_out + r * W : nullptr, angle_row,
              reach ? reach + 4 * r * W : nullptr);
    pass1_judge_cells(sc, ring.ok(r), W, r * W, sc.judge);
  }
  return n_finite;
}

}  // namespace

template <typename T>
int angle_passes(const GridView<T>& g, DetectParams& eff, const OrganizedOutput& out,
                 Workspace& ws) {
  const DetectParams& p = eff;
  const std::ptrdiff_t H = g.rows, W = g.cols, N = H * W;
  const int nt = detail::thread_count(p.num_threads, N);
  std::uint8_t* labels = out.labels;
  ws.usable.resize(static_cast<std::size_t>(N));
  std::uint8_t* usable = ws.usable.data();

  const int smax = *std::max_element(p.scales.begin(), p.scales.end());
  const bool has_min_step = p.min_step >= 0.0;
  // The row kernel keeps 2 depth + 2 padded, converted rows per thread (32 bytes per cell
  // each) and a row of 25 bytes per cell (the best pair, the bits, a finiteness byte); depth =
  // smax + 1, with min_step up to kDeep steps so that the search for a neighbour far enough
  // runs in the kernel. On a long thin grid (1 x 10^7) that is gigabytes, so it runs
  // only while its scratch stays within 8 bytes per grid cell (at least 1 MiB), with no more
  // threads than rows (with min_step, at the shallow depth when the deep one does not fit);
  // beyond, the scalar judge (same labels, SPEC) reads the grid in place (README "Guarantees").
  constexpr int kDeep = 16;
  const int ntk = static_cast<int>(std::min<std::ptrdiff_t>(nt, H));
  auto kernel_fits = [&](int depth) {
    const double padded = static_cast<double>(W + 2 * depth);
    const double bytes = ntk * padded * (32.0 * (2 * depth + 2) + 25.0);
    return smax <= 64 && bytes <= std::max(double(1 << 20), 8.0 * static_cast<double>(N));
  };
  int depth = smax + 1;
  if (has_min_step) {
    const std::ptrdiff_t full = std::ptrdiff_t{smax} + p.max_gap + p.max_reach;
    const int deep = static_cast<int>(std::min<std::ptrdiff_t>(full, std::max(kDeep, depth)));
    if (kernel_fits(deep)) depth = deep;
  }
  const bool row_kernel = kernel_fits(depth);
  const std::ptrdiff_t padded = W + 2 * depth;
  if (row_kernel) {
    if (ws.rows.size() < static_cast<std::size_t>(ntk)) ws.rows.resize(ntk);
    for (int t = 0; t < ntk; ++t) ws.rows[t].resize(2 * depth + 2, padded);
  }
  // Pass 0: finiteness (the row kernel finds it as it loads the rows, pass1_rows). (The row
  // kernel writes every cell's angle, NaN where there is none.)
  const bool angle_nan = out.angle_deg != nullptr && !row_kernel;
  std::ptrdiff_t n_finite = 0;
  AbsBits<T> top = 0;  // the largest finite coordinate magnitude (finite_abs_bits)
  if (!row_kernel) {
#pragma omp parallel for schedule(static) num_threads(nt) if (nt > 1) \
    reduction(+ : n_finite) reduction(max : top)
    for (std::ptrdiff_t r = 0; r < H; ++r) {
      n_finite += finite_row(g, r, usable + r * W, labels + r * W, top);
      if (out.flags) std::fill(out.flags + r * W, out.flags + (r + 1) * W, std::uint8_t{0});
      if (angle_nan) std::fill(out.angle_deg + r * W, out.angle_deg + (r + 1) * W, kNaN);
    }
  }
  // SPEC "Numbers" first (the coordinate range), then at least 3 finite points.
  const auto check_grid = [&n_finite, &top] {
    check_coordinate_range(magnitude_of<T>(top), "grid");
    if (n_finite < 3) {
      throw std::invalid_argument("grid: fewer than 3 finite points (found " +
                                  std::to_string(n_finite) + ")");
    }
  };
  if (!row_kernel) check_grid();

  // With min_step: the rays each cell's verdict read (4 bytes per cell), so that a later pass
  // re-judges only the cells whose verdict a removal can change.
  std::uint8_t* reach = nullptr;
  if (has_min_step) {
    ws.reach.resize(4 * static_cast<std::size_t>(N));
    reach = ws.reach.data();
  }
  // Pass 1 over every finite cell (row kernel; the scalar judge for min_step and fallbacks).
  auto pass1 = [&](double* angle_out) {
    const CellJudge<T> judge(g, usable, p);
    if (row_kernel) {
      std::ptrdiff_t nf = 0;
      AbsBits<T> tp = 0;
#pragma omp parallel num_threads(ntk) if (ntk > 1) reduction(+ : nf) reduction(max : tp)
      {
        int tid = 0;
#ifdef MIEM_HAVE_OPENMP
        tid = omp_get_thread_num();
#endif
        // Contiguous row blocks, one per thread: each row is converted once per block.
        const std::ptrdiff_t r0 = H * tid / ntk, r1 = H * (tid + 1) / ntk;
        RowScratch& sc = ws.rows[tid];
        nf += pass1_rows(g, usable, p, depth, r0, r1, sc, labels, out.flags, angle_out, reach,
                         tp);
#pragma omp barrier
        // every row's finiteness is known: the scalar judge for the cells the kernel left
        for (const std::int64_t i : sc.judge) {
          std::uint8_t fl;
          double an;
          labels[i] = judge.judge(i / W, i % W, &fl, &an, reach ? reach + 4 * i : nullptr);
          if (out.flags) out.flags[i] = fl;
          if (angle_out) angle_out[i] = an;
        }
      }
      n_finite = nf;
      top = tp;
      check_grid();
    } else {
#pragma omp parallel for schedule(static) num_threads(nt) if (nt > 1)
      for (std::ptrdiff_t r = 0; r < H; ++r) {
        for (std::ptrdiff_t c = 0; c < W; ++c) {
          const std::ptrdiff_t i = r * W + c;
          if (!usable[i]) continue;
          std::uint8_t fl = 0;
          double an = kNaN;
          labels[i] = judge.judge(r, c, &fl, &an, reach ? reach + 4 * i : nullptr);
          if (out.flags) out.flags[i] = fl;
          if (angle_out) angle_out[i] = an;
        }
      }
    }
  };
  if (p.theta0_auto) {
    // Angle survey (independent of theta0), then theta0 = clip(180 - 6 sigma, 75, 170) with
    // sigma = median(180 - angle) / 0.6745, 180 - angle below kAutoTheta0Straight read as 0.
    double* ang = out.angle_deg;
    if (ang == nullptr) {
      ws.height_scratch.resize(static_cast<std::size_t>(N));
      ang = ws.height_scratch.data();
    }
    eff.theta0_deg = 75.0;
    pass1(ang);
    ws.survey.clear();
    for (std::ptrdiff_t i = 0; i < N; ++i)
      if (usable[i] && std::isfinite(ang[i])) {
        const double dev = 180.0 - ang[i];
        ws.survey.push_back(dev < kAutoTheta0Straight ? 0.0 : dev);
      }
    double theta0 = 75.0;
    if (!ws.survey.empty()) {
      const std::size_t m = ws.survey.size(), mid = m / 2;
      std::nth_element(ws.survey.begin(), ws.survey.begin() + mid, ws.survey.end());
      double med = ws.survey[mid];
      if (m % 2 == 0) med = 0.5 * (med + *std::max_element(ws.survey.begin(), ws.survey.begin() + mid));
      theta0 = std::clamp(180.0 - 6.0 * (med / 0.6745), 75.0, 170.0);
    }
    eff.theta0_deg = theta0;
    for (std::ptrdiff_t i = 0; i < N; ++i)
      if (usable[i]) labels[i] = kNormal;
  }
  pass1(out.angle_deg);

  const CellJudge<T> judge(g, usable, p);  // after theta0 is final
  auto judge_cell = [&](std::ptrdiff_t i) {
    std::uint8_t fl = 0;
    double an = kNaN;
    labels[i] = judge.judge(i / W, i % W, &fl, &an, reach ? reach + 4 * i : nullptr);
    if (out.flags) out.flags[i] = fl;
    if (out.angle_deg) out.angle_deg[i] = an;
  };

  collect_indices(nt, N, ws.fresh, [labels](std::ptrdiff_t i) { return labels[i] == kAbnormal; });
  int iterations = 1;

  // Later passes: only cells whose rays meet a newly removed cell; with min_step, only within
  // the steps their verdict read (`reach`), the other verdicts cannot change.
  const std::ptrdiff_t ray_reach = static_cast<std::ptrdiff_t>(smax) + p.max_gap +
                                   (has_min_step ? p.max_reach : 0);
  while (!ws.fresh.empty() && iterations < p.max_iterations) {
    for (std::int64_t i : ws.fresh) usable[i] = 0;
    ws.candidates.clear();
    for (std::int64_t i : ws.fresh) {
      const std::ptrdiff_t r = i / W, c = i % W;
      for (int k = 0; k < 4; ++k) {
        for (int sgn = -1; sgn <= 1; sgn += 2) {
          for (std::ptrdiff_t step = 1; step <= ray_reach; ++step) {
            const std::ptrdiff_t rr = r + sgn * step * kDirRow[k];
            const std::ptrdiff_t cc = c + sgn * step * kDirCol[k];
            if (rr < 0 || rr >= H || cc < 0 || cc >= W) break;
            const std::ptrdiff_t q = rr * W + cc;
            // usable and not yet a candidate (bit 1 marks those), and reads this far (255:
            // at least that far, so any step)
            const std::ptrdiff_t need = std::min<std::ptrdiff_t>(step, 255);
            if (usable[q] == 1 && (!reach || reach[4 * q + k] >= need)) {
              usable[q] = 3;
              ws.candidates.push_back(q);
            }
          }
        }
      }
    }
    const std::ptrdiff_t nc = static_cast<std::ptrdiff_t>(ws.candidates.size());
    // a verdict costs ~1 us (more with min_step): a few hundred are worth a second thread;
    // candidates cluster around the removed cells, so they are dealt in small chunks
    const int ntc = detail::thread_count(p.num_threads, nc, 256);
#pragma omp parallel for schedule(dynamic, 32) num_threads(ntc) if (ntc > 1)
    for (std::ptrdiff_t j = 0; j < nc; ++j) judge_cell(ws.candidates[j]);
    ws.fresh.clear();
    for (std::int64_t q : ws.candidates) {
      usable[q] = 1;
      if (labels[q] == kAbnormal) ws.fresh.push_back(q);
    }
    ++iterations;
  }

  return iterations;
}

template int angle_passes<float>(const GridView<float>&, DetectParams&, const OrganizedOutput&,
                                 Workspace&);
template int angle_passes<double>(const GridView<double>&, DetectParams&, const OrganizedOutput&,
                                  Workspace&);

}  // namespace miem::detail
