// Streaming MIEM: the batch passes (Jacobi, docs/SPEC.md) run as a wavefront over a ring of rows.
// Each cell keeps the pass that removed it, so a judgment at pass p sees exactly the usable set of
// pass p - 1 even when rows above have already run pass p. Pass 1, the bulk of the work, runs a
// vectorised filter over the whole row and judges only the cells it cannot rule out; with
// min_step, batch detection's row kernel (pass1_row.hpp).
#include "miem/stream.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <new>
#include <stdexcept>
#include <string>
#include <type_traits>

#if defined(__x86_64__)
#include <immintrin.h>
#endif

#include "auto_min_step.hpp"
#include "edge_quiet.hpp"
#include "finite_bits.hpp"
#include "z_resolution.hpp"
#include "judge.hpp"
#include "parallel.hpp"
#include "pass1_row.hpp"
#include "vector_clones.hpp"

namespace miem {

namespace {

using detail::kDirCol;
using detail::kDirRow;

constexpr std::uint8_t kAlive = 255;  // finite and never removed

// min_step "auto" spread over the pushes (ProfileStream::min_step_row): rounds 1-3 of the
// selection visit at least kMsChunk rows a push, then the stages catch up at least kMsCatch
// rows a push. The stages then fall at most kMsBacklog rows behind the newest: the
// kAutoMinStepRows rows round 0 takes, then one per push of rounds 1-3.
constexpr std::ptrdiff_t kMsChunk = 16;
constexpr std::int64_t kMsCatch = 3;
constexpr std::ptrdiff_t kMsBacklog =
    detail::kAutoMinStepRows + (3 * detail::kAutoMinStepRows + kMsChunk - 1) / kMsChunk;

// Usable at pass p: finite and not removed before pass p (removed at pass q: state == q).
struct UsableAtPass {
  std::uint8_t pass;
  bool operator()(std::uint8_t state) const { return state >= pass; }
};

// The pass-1 kernel's filter. A cell whose directions are all unflagged is NORMAL whatever is
// available, and with theta0 < 90 a flag needs u.v > 0, which almost no surface cell has. So the
// kernel only marks, per (direction, scale), the cells where u.v > -1e-14 (|ux vx| + |uy vy| +
// |uz vz|): that margin is far above the rounding error of the dot product in any summation
// order, so every cell that could be flagged is marked and then judged exactly.
// Cells [c0, c1) of one row; P, A[i], B[i]: x at [c], y at [c + plane], z at [c + 2 plane];
// A[i][c], B[i][c] are the two neighbours of cell c for (direction, scale) i.
// With `gap` (max_gap >= 1), a neighbour cell at step s that is not usable (its state SA[i][c],
// SB[i][c] is 0) stands aside for the cell one step further, A2[i][c], B2[i][c]: SPEC's search
// ends there when that one is usable (the caller sends the cells where neither is to CellJudge).
template <typename T>
struct KernelArgs {
  const T* P;
  const T* A[32];
  const T* B[32];
  const T* A2[32];
  const T* B2[32];
  const std::uint8_t* SA[32];
  const std::uint8_t* SB[32];
  // the rows the kernel reads (their x planes), for kernel_avx512's prefetch: the row, and a
  // row above and one below per scale (4 pairs a scale: at most 32 / 4 scales)
  const T* rows[1 + 2 * (32 / 4)];
  int n_rows;
  bool gap;
  int n;  // (direction, scale) pairs
  std::ptrdiff_t plane, c0, c1;
  std::uint32_t* bits;  // bit i: (direction, scale) i may be flagged
};

constexpr double kMargin = 1e-14;
constexpr std::uint32_t kBadBit = 1u << 31;  // in bits_: a neighbour is missing

template <typename T>
void kernel_scalar(const KernelArgs<T>& a, std::ptrdiff_t c) {
  const std::ptrdiff_t pl = a.plane;
  for (; c < a.c1; ++c) {
    const double px = a.P[c], py = a.P[pl + c], pz = a.P[2 * pl + c];
    for (int i = 0; i < a.n; ++i) {
      const T* A = a.gap && a.SA[i][c] == 0 ? a.A2[i] : a.A[i];
      const T* B = a.gap && a.SB[i][c] == 0 ? a.B2[i] : a.B[i];
      const double ux = A[c] - px, uy = A[pl + c] - py, uz = A[2 * pl + c] - pz;
      const double vx = B[c] - px, vy = B[pl + c] - py, vz = B[2 * pl + c] - pz;
      const double x = ux * vx, y = uy * vy, z = uz * vz;
      if ((x + y) + z > -kMargin * ((std::fabs(x) + std::fabs(y)) + std::fabs(z))) {
        a.bits[c] |= 1u << i;
      }
    }
  }
}

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#define MIEM_X86_KERNELS 1

// Two cells per step (SSE2 is part of x86-64).
template <typename T>
void kernel_sse2(const KernelArgs<T>& a) {
  auto load2 = [](const T* p) {
    if constexpr (std::is_same_v<T, double>) {
      return _mm_loadu_pd(p);
    } else {
      return _mm_cvtps_pd(_mm_castsi128_ps(_mm_loadl_epi64(reinterpret_cast<const __m128i*>(p))));
    }
  };
  const std::ptrdiff_t pl = a.plane;
  const __m128d margin = _mm_set1_pd(-kMargin);
  const __m128d abs_mask = _mm_castsi128_pd(_mm_set1_epi64x(0x7fffffffffffffffLL));
  std::ptrdiff_t c = a.c0;
  for (; c + 2 <= a.c1; c += 2) {
    const __m128d px = load2(a.P + c), py = load2(a.P + pl + c), pz = load2(a.P + 2 * pl + c);
    for (int i = 0; i < a.n; ++i) {
      const T* A = a.A[i];
      const T* B = a.B[i];
      const __m128d x = _mm_mul_pd(_mm_sub_pd(load2(A + c), px), _mm_sub_pd(load2(B + c), px));
      const __m128d y =
          _mm_mul_pd(_mm_sub_pd(load2(A + pl + c), py), _mm_sub_pd(load2(B + pl + c), py));
      const __m128d z = _mm_mul_pd(_mm_sub_pd(load2(A + 2 * pl + c), pz),
                                   _mm_sub_pd(load2(B + 2 * pl + c), pz));
      const __m128d d = _mm_add_pd(_mm_add_pd(x, y), z);
      const __m128d mag = _mm_add_pd(
          _mm_add_pd(_mm_and_pd(x, abs_mask), _mm_and_pd(y, abs_mask)), _mm_and_pd(z, abs_mask));
      const int m = _mm_movemask_pd(_mm_cmpgt_pd(d, _mm_mul_pd(margin, mag)));
      if (m != 0) {
        if (m & 1) a.bits[c] |= 1u << i;
        if (m & 2) a.bits[c + 1] |= 1u << i;
      }
    }
  }
  kernel_scalar(a, c);
}

// Four cells per step, where the CPU has AVX2 (checked at run time).
__attribute__((target("avx2"))) inline __m256d load4(const double* p) {
  return _mm256_loadu_pd(p);
}
__attribute__((target("avx2"))) inline __m256d load4(const float* p) {
  return _mm256_cvtps_pd(_mm_loadu_ps(p));
}

// All-ones lanes where the state byte is 0 (the cell is not usable), of 4 consecutive cells.
__attribute__((target("avx2"))) inline __m256d missing4(const std::uint8_t* st) {
  std::int32_t w;
  std::memcpy(&w, st, sizeof w);
  const __m128i zero = _mm_cmpeq_epi8(_mm_cvtsi32_si128(w), _mm_setzero_si128());
  return _mm256_castsi256_pd(_mm256_cvtepi8_epi64(zero));
}

// From column c (a.c0 by default).
template <typename T>
__attribute__((target("avx2"))) void kernel_avx2(const KernelArgs<T>& a, std::ptrdiff_t c) {
  const std::ptrdiff_t pl = a.plane;
  const __m256d margin = _mm256_set1_pd(-kMargin);
  const __m256d abs_mask = _mm256_castsi256_pd(_mm256_set1_epi64x(0x7fffffffffffffffLL));
  for (; c + 4 <= a.c1; c += 4) {
    const __m256d px = load4(a.P + c), py = load4(a.P + pl + c), pz = load4(a.P + 2 * pl + c);
    for (int i = 0; i < a.n; ++i) {
      const T* A = a.A[i];
      const T* B = a.B[i];
      __m256d ax = load4(A + c), ay = load4(A + pl + c), az = load4(A + 2 * pl + c);
      __m256d bx = load4(B + c), by = load4(B + pl + c), bz = load4(B + 2 * pl + c);
      if (a.gap) {  // lanes whose step-s cell is not usable: the next one's coordinates
        const __m256d ma = missing4(a.SA[i] + c), mb = missing4(a.SB[i] + c);
        if (_mm256_movemask_pd(ma) != 0) {
          const T* A2 = a.A2[i];
          ax = _mm256_blendv_pd(ax, load4(A2 + c), ma);
          ay = _mm256_blendv_pd(ay, load4(A2 + pl + c), ma);
          az = _mm256_blendv_pd(az, load4(A2 + 2 * pl + c), ma);
        }
        if (_mm256_movemask_pd(mb) != 0) {
          const T* B2 = a.B2[i];
          bx = _mm256_blendv_pd(bx, load4(B2 + c), mb);
          by = _mm256_blendv_pd(by, load4(B2 + pl + c), mb);
          bz = _mm256_blendv_pd(bz, load4(B2 + 2 * pl + c), mb);
        }
      }
      const __m256d x = _mm256_mul_pd(_mm256_sub_pd(ax, px), _mm256_sub_pd(bx, px));
      const __m256d y = _mm256_mul_pd(_mm256_sub_pd(ay, py), _mm256_sub_pd(by, py));
      const __m256d z = _mm256_mul_pd(_mm256_sub_pd(az, pz), _mm256_sub_pd(bz, pz));
      const __m256d d = _mm256_add_pd(_mm256_add_pd(x, y), z);
      const __m256d mag =
          _mm256_add_pd(_mm256_add_pd(_mm256_and_pd(x, abs_mask), _mm256_and_pd(y, abs_mask)),
                        _mm256_and_pd(z, abs_mask));
      const int m =
          _mm256_movemask_pd(_mm256_cmp_pd(d, _mm256_mul_pd(margin, mag), _CMP_GT_OQ));
      if (m != 0) {
        for (int k = 0; k < 4; ++k)
          if (m & (1 << k)) a.bits[c + k] |= 1u << i;
      }
    }
  }
  kernel_scalar(a, c);
}

#ifdef MIEM_SELECT_AVX512
// Eight cells per step, where the CPU has AVX-512 F and VL: kernel_avx2's arithmetic lane by
// lane (so the same marks), the next cell's coordinates loaded only into the lanes that need
// them. It asks for its rows' cells kAhead on as it goes: the rows other than the newest left
// the L2 cache in the pushes since their own pass 1, and the hardware prefetcher does not keep
// up with their streams (x, y, z of each row). Measured (miem_bench_stream, one core, alternated
// builds) against kernel_avx2: the angle test alone 11 % more profiles per second, the default
// preset 2 %, float32 storage 6 %; either change alone gained nothing.
__attribute__((target("avx512f,avx512vl"))) inline __m512d load8(const double* p) {
  return _mm512_loadu_pd(p);
}
__attribute__((target("avx512f,avx512vl"))) inline __m512d load8(const float* p) {
  // (maskz: _mm512_cvtps_pd reads an undefined register, which GCC 12 warns of)
  return _mm512_maskz_cvtps_pd(0xFF, _mm256_loadu_ps(p));
}
__attribute__((target("avx512f,avx512vl"))) inline __m512d load8(__m512d old, __mmask8 k,
                                                                  const double* p) {
  return _mm512_mask_loadu_pd(old, k, p);
}
__attribute__((target("avx512f,avx512vl"))) inline __m512d load8(__m512d old, __mmask8 k,
                                                                  const float* p) {
  return _mm512_mask_cvtps_pd(old, k, _mm256_maskz_loadu_ps(k, p));
}

template <typename T>
__attribute__((target("avx512f,avx512vl"))) void kernel_avx512(const KernelArgs<T>& a) {
  const std::ptrdiff_t pl = a.plane;
  const __m512d margin = _mm512_set1_pd(-kMargin);
  constexpr std::ptrdiff_t kAhead = 96;  // cells: 12 cache lines of doubles
  std::ptrdiff_t c = a.c0;
  for (; c + 8 <= a.c1; c += 8) {
    for (int k = 0; k < a.n_rows; ++k) {
      const T* q = a.rows[k] + std::min(c + kAhead, a.c1 - 1);
      _mm_prefetch(reinterpret_cast<const char*>(q), _MM_HINT_T0);
      _mm_prefetch(reinterpret_cast<const char*>(q + pl), _MM_HINT_T0);
      _mm_prefetch(reinterpret_cast<const char*>(q + 2 * pl), _MM_HINT_T0);
    }
    const __m512d px = load8(a.P + c), py = load8(a.P + pl + c), pz = load8(a.P + 2 * pl + c);
    for (int i = 0; i < a.n; ++i) {
      const T* A = a.A[i];
      const T* B = a.B[i];
      __m512d ax = load8(A + c), ay = load8(A + pl + c), az = load8(A + 2 * pl + c);
      __m512d bx = load8(B + c), by = load8(B + pl + c), bz = load8(B + 2 * pl + c);
      if (a.gap) {  // lanes whose step-s cell is not usable: the next one's coordinates
        const __mmask8 ma = static_cast<__mmask8>(~detail::nonzero8(a.SA[i] + c));
        const __mmask8 mb = static_cast<__mmask8>(~detail::nonzero8(a.SB[i] + c));
        if (ma != 0) {
          const T* A2 = a.A2[i];
          ax = load8(ax, ma, A2 + c), ay = load8(ay, ma, A2 + pl + c);
          az = load8(az, ma, A2 + 2 * pl + c);
        }
        if (mb != 0) {
          const T* B2 = a.B2[i];
          bx = load8(bx, mb, B2 + c), by = load8(by, mb, B2 + pl + c);
          bz = load8(bz, mb, B2 + 2 * pl + c);
        }
      }
      const __m512d x = _mm512_mul_pd(_mm512_sub_pd(ax, px), _mm512_sub_pd(bx, px));
      const __m512d y = _mm512_mul_pd(_mm512_sub_pd(ay, py), _mm512_sub_pd(by, py));
      const __m512d z = _mm512_mul_pd(_mm512_sub_pd(az, pz), _mm512_sub_pd(bz, pz));
      const __m512d d = _mm512_add_pd(_mm512_add_pd(x, y), z);
      const __m512d mag =
          _mm512_add_pd(_mm512_add_pd(_mm512_abs_pd(x), _mm512_abs_pd(y)), _mm512_abs_pd(z));
      unsigned m = _mm512_cmp_pd_mask(d, _mm512_mul_pd(margin, mag), _CMP_GT_OQ);
      for (; m != 0; m &= m - 1) a.bits[c + __builtin_ctz(m)] |= 1u << i;
    }
  }
  kernel_avx2(a, c);
}
#endif

#endif

template <typename T>
void run_kernel(const KernelArgs<T>& a) {
#ifdef MIEM_X86_KERNELS
#ifdef MIEM_SELECT_AVX512
  if (detail::has_avx512()) {
    kernel_avx512(a);
    return;
  }
#endif
  static const bool has_avx2 = __builtin_cpu_supports("avx2");
  if (has_avx2) {
    kernel_avx2(a, a.c0);
  } else if (a.gap) {
    kernel_scalar(a, a.c0);
  } else {
    kernel_sse2(a);
  }
#else
  kernel_scalar(a, a.c0);
#endif
}

}  // namespace

DetectParams stream_default_params() { return DetectParams{}; }

namespace {
// R: the rows one judgment reads (+ max_reach with min_step, given or "auto").
long long stream_reach(const DetectParams& p) {
  return static_cast<long long>(*std::max_element(p.scales.begin(), p.scales.end())) +
         p.max_gap + (p.min_step >= 0.0 || p.min_step_auto ? p.max_reach : 0);
}
}  // namespace

long long stream_lag(const DetectParams& p) noexcept {
  const long long reach = stream_reach(p);
  const long long P = p.max_iterations, h = p.window / 2;
  // rows behind the newest at which the height passes' labels are final
  // (an EDGE group links across max_gap dropouts: its compactness is seen E + max_gap rows on)
  const long long lagh =
      P * reach + (p.height_test() ? p.edge_extent + p.max_gap + P * h : 0);
  long long lag = lagh + h;
  if (p.edge_test()) {
    // step 9 runs r rows behind the height passes, edge pass 1 r rows behind it (and, with the
    // height test, q = max(r, h) rows behind the height passes: its quiet cells' windows),
    // once the rows within h are in (its removals mark the heights there stale); pass p r rows
    // behind pass p - 1
    const long long r = p.edge_window / 2;
    const long long q = p.height_test() ? detail::quiet_half(r, h) : 0;
    lag = std::max(lagh + std::max(2 * r, q), h) + (P - 1) * r + h;
  }
  // min_step, z_resolution or z_noise "auto": nothing runs before the sample rows they read
  // are in
  const bool sample = p.min_step_auto || p.z_resolution_auto || p.z_noise_auto;
  return sample ? std::max<long long>(lag, detail::kAutoMinStepRows) : lag;
}

Status check_stream_params(std::ptrdiff_t width, const DetectParams& p) noexcept {
  const auto bad = [](const char* msg) { return Status{StatusCode::kInvalidParameter, msg}; };
  if (Status st = p.check(); !st.ok()) return st;
  if (p.theta0_auto) {
    return bad("theta0_auto: not implemented by ProfileStream (theta0 'auto' is the median of "
               "the whole scan's angles, which a stream never sees); give theta0 in degrees");
  }
  if (width < 1) return bad("width: must be at least 1 point per profile");
  if (p.max_iterations > 254) return bad("max_iterations: a stream supports at most 254 passes");
  if (stream_reach(p) > (1 << 20)) return bad("scales, max_gap, max_reach: reach too long");
  if (stream_lag(p) + p.window > (1 << 20)) {
    return bad("window, edge_extent, max_iterations: the stream's lag would exceed 2^20 profiles");
  }
  return {};
}

template <typename T>
ProfileStream<T>::ProfileStream(std::ptrdiff_t width, DetectParams params)
    : width_(width), params_(std::move(params)) {
  throw_if_error(check_stream_params(width_, params_));
  max_scale_ = *std::max_element(params_.scales.begin(), params_.scales.end());
  const int min_scale = *std::min_element(params_.scales.begin(), params_.scales.end());
  ms_auto_ = params_.min_step_auto;
  sel_ = ms_auto_ || params_.z_noise_auto;
  sample_ = sel_ || params_.z_resolution_auto;
  ms_wait_ = sample_;
  reach_ = static_cast<int>(stream_reach(params_));
  passes_ = params_.max_iterations;
  alag_ = passes_ * reach_;
  htest_ = params_.height_test();
  edge_ = params_.edge_test();
  half_ = params_.window / 2;
  extent_ = htest_ ? params_.edge_extent : 0;
  link_gap_ = htest_ ? params_.max_gap : 0;
  sums_ = htest_ || params_.height_mode == HeightMode::kAll;
  lag_ = static_cast<int>(stream_lag(params_));
  lagh_ = alag_ + (htest_ ? extent_ + link_gap_ + passes_ * half_ : 0);
  // The longest look-back of a stage at push n: heights read row n - L - h, height pass 1
  // drops row n - L - h - 1 from its sums (without the height test), the EDGE grouping reads
  // row n - A - 2E, the angle passes row n - A - R, the last edge pass builds its images from
  // r rows above the tile (of 64 rows) of a row after n - L + h.
  const long long back = std::max<long long>(
      {static_cast<long long>(lag_) + half_ + 1, static_cast<long long>(alag_) + 2LL * (extent_ + link_gap_),
       static_cast<long long>(alag_) + reach_,
       edge_ ? static_cast<long long>(lag_) + 64 + params_.edge_window : 0LL});
  // min_step "auto": the stages fall behind by at most kMsBacklog rows while it is decided
  ring_ = static_cast<std::ptrdiff_t>(back) + 2 + (sample_ ? kMsBacklog : 0);
  // Any ext_ + 1 consecutive rows form one GridView: a judgment's rows, a window, the rows an
  // edge verdict reads.
  ext_ = std::max<std::ptrdiff_t>(
      {2 * reach_, 2 * half_, edge_ ? 2 * static_cast<std::ptrdiff_t>(params_.edge_window / 2) : 0});
  phys_ = ring_ + ext_;
  const double cells = static_cast<double>(phys_) * static_cast<double>(width_);
  if (cells * 3.0 * sizeof(T) > static_cast<double>(std::numeric_limits<std::ptrdiff_t>::max() / 4)) {
    throw std::invalid_argument("width: profile buffer too large");
  }
  cos0_ = std::cos(params_.theta0_deg * detail::kDegToRad);
  // The kernel needs the scale-s cells to stand for the neighbours (no min_step), some of them
  // inside the isolation reach (so "not isolated" is implied), and one bit per (direction, scale).
  fast_ok_ = min_scale <= 1 + params_.max_gap && params_.scales.size() <= 7;
  // A dropout at step s: the kernel takes the cell at s + 1 (SPEC's search with max_gap >= 1),
  // which keeps "not isolated" implied when the smallest scale's s + 1 is within its reach.
  p1_gap_ = params_.max_gap >= 1 && min_scale <= params_.max_gap;
  fedge_ = max_scale_ + (p1_gap_ ? 1 : 0);
  jparams_ = params_;
  jparams_.min_step_auto = false;
  jparams_.z_resolution_auto = false;  // with "auto": -1 (off) until the sample rows are in
  jparams_.z_noise_auto = false;
  if (max_scale_ <= 64) {
    // pass 1's row kernel: its ring sized for the deepest search it may run (min_step given or
    // "auto"), so that use_min_step, which sets the depth in use, never allocates
    const bool deep = ms_auto_ || params_.min_step >= 0.0;
    p1_depth_ = pass1_depth(deep);
    detail::pass1_prepare(p1_, width_, p1_depth_, deep);
    p1_lab_.assign(static_cast<std::size_t>(width_), kInvalid);
  }
  use_min_step(ms_auto_ ? -1.0 : params_.min_step);

  const std::size_t n2 = static_cast<std::size_t>(phys_ * width_);
  const std::size_t n1 = static_cast<std::size_t>(ring_ * width_);
  xyz_.assign(3 * n2, std::numeric_limits<T>::quiet_NaN());
  state_.assign(n2, 0);
  cand_.assign(n1, 0);
  labels_.assign(n1, kInvalid);
  row_cand_.assign(static_cast<std::size_t>(ring_), 0);
  p1_miss_.assign(static_cast<std::size_t>(ring_), 0);
  level_.assign(static_cast<std::size_t>(ring_), 0);
  bits_.assign(static_cast<std::size_t>(width_), 0);
  judge_cols_.assign(static_cast<std::size_t>(width_), 0);
  judge_out_.assign(static_cast<std::size_t>(width_), 0);
  if (ms_auto_ || params_.min_step >= 0.0) {
    ray_.assign(4 * n1, 0);
  }
  use_ray_ = min_step_ >= 0.0 && !ray_.empty();
  if (sample_) nan_row_.assign(static_cast<std::size_t>(width_), detail::kNaN);
  if (params_.z_resolution_auto) {
    const std::ptrdiff_t pooled = std::min(detail::kZGapRows * width_, detail::kZGapCells);
    zkeys_.assign(static_cast<std::size_t>(2 * pooled), 0);
  }
  if (sel_) {
    ms_rows_.assign(static_cast<std::size_t>(detail::kAutoMinStepRows), nullptr);
    ms_sel_.init(width_, phys_ * width_);
  }
  threads_ = static_cast<int>(std::min<std::ptrdiff_t>(
      (width_ + 127) / 128, detail::thread_count(params_.num_threads, width_, 256)));
  init_stages();
  init_edges();
  init_defects();
}

// The row kernel's depth, as batch detection sizes it: with min_step a search of up to 16 steps
// (or the whole reach, when shorter) in the kernel, the deeper ones by CellJudge; without, the
// largest scale + 1 (a search ends at the scale's cell or, past a dropout, the next).
template <typename T>
std::ptrdiff_t ProfileStream<T>::pass1_depth(bool min_step) const noexcept {
  return min_step ? std::min<std::ptrdiff_t>(reach_, std::max(16, max_scale_ + 1))
                  : max_scale_ + 1;
}

// The min_step the judges use (-1: off): pass 1's vectorised filter needs none, and a removal
// marks the cells within the reach of one judgment with that min_step.
template <typename T>
void ProfileStream<T>::use_min_step(double min_step) noexcept {
  min_step_ = min_step;
  jparams_.min_step = min_step;
  fast_ = fast_ok_ && min_step < 0.0;
  use_ray_ = min_step >= 0.0 && !ray_.empty();
  p1_kernel_ = !p1_lab_.empty() && min_step >= 0.0;
  if (!p1_lab_.empty() && pass1_depth(min_step >= 0.0) != p1_depth_) {
    p1_depth_ = pass1_depth(min_step >= 0.0);
    detail::pass1_prepare(p1_, width_, p1_depth_, min_step >= 0.0);  // within its capacity
    p1_next_ = 0;
  }
  mark_reach_ = max_scale_ + params_.max_gap + (min_step >= 0.0 ? params_.max_reach : 0);
}

// min_step "auto" (SPEC "min_step='auto'", "Streaming") at the push of `row`, from the first
// row with a finite cell on: round 0 of the selection takes the row (the first
// kAutoMinStepRows rows), then rounds 1-3 visit at least kMsChunk rows a push, more when the
// pushes left before the deadline (row ms_first_ + L is the first to hand back a row it
// decides) must also leave the stages' catch-up kMsCatch rows a push. Once decided, the
// stages catch up from ms_first_ (catch_up).
template <typename T>
void ProfileStream<T>::min_step_row(std::int64_t row) noexcept {
  const std::int64_t k = row - ms_first_;
  if (k < detail::kAutoMinStepRows) {
    const T* xyz = xyz_.data() + slot(row) * width_;
    if (params_.z_resolution_auto) {  // SPEC "z_resolution": over the same rows
      zq_ = detail::fold_z_steps(xyz, width_, 1, phys_ * width_, zq_);
      zn_ += detail::finite_z_keys(xyz, detail::z_gap_cells(k, width_), 1, phys_ * width_,
                                   zkeys_.data() + zn_);
    }
    if (!sel_) {  // z_resolution alone: known once its rows are in
      if (k + 1 == detail::kAutoMinStepRows) decide();
      return;
    }
    ms_rows_[static_cast<std::size_t>(k)] = xyz;
    ms_sel_.add_row(ms_rows_.data(), static_cast<std::ptrdiff_t>(k + 1));
    if (k + 1 < detail::kAutoMinStepRows) return;
    ms_sel_.close(ms_rows_.data());
  }
  const std::int64_t deadline = ms_first_ + lag_;
  const std::int64_t reserve = (deadline - ms_first_ + kMsCatch) / kMsCatch;
  const std::int64_t pushes = std::max<std::int64_t>(1, deadline - row + 1 - reserve);
  const std::int64_t visits = ms_sel_.visits_left();
  if (ms_sel_.step(ms_rows_.data(), static_cast<std::ptrdiff_t>(std::max<std::int64_t>(
                                        kMsChunk, (visits + pushes - 1) / pushes)))) {
    decide();
  }
}

// The sample rows decided (the selection done when it runs): min_step and z_noise "auto" from
// the selection, z_resolution "auto" the smallest z step of those rows, in use; the stages
// catch up from ms_first_.
template <typename T>
void ProfileStream<T>::decide() noexcept {
  if (ms_auto_) use_min_step(ms_sel_.value());
  if (params_.z_noise_auto) jparams_.z_noise = ms_sel_.noise();
  if (params_.z_resolution_auto) {  // (one sort, once: the pooled values' smallest gap)
    zq_ = detail::fold_z_gaps(zkeys_.data(), zn_, zq_);
    jparams_.z_resolution = std::isfinite(zq_) ? zq_ : -1.0;
  }
  ms_wait_ = false;
  ms_next_ = ms_first_;
}

// At the flush: min_step "auto" decided on the rows pushed (fewer than it reads when the stream
// is that short), and the stages caught up.
template <typename T>
void ProfileStream<T>::min_step_finish() noexcept {
  if (ms_wait_ && ms_first_ >= 0) {
    if (sel_) {
      if (!ms_sel_.closed()) ms_sel_.close(ms_rows_.data());
      ms_sel_.step(ms_rows_.data(), ms_sel_.visits_left());
    }
    decide();
  }
  if (ms_next_ >= 0) catch_up(pushed_ - 1);
}

// The stages of the pushes that waited for min_step, rows ms_next_ through `last`, push by push
// as they would have run (each sees the rows pushed up to its own).
template <typename T>
void ProfileStream<T>::catch_up(std::int64_t last) noexcept {
  const std::int64_t pushed = pushed_;
  for (; ms_next_ <= last; ++ms_next_) {
    pushed_ = ms_next_ + 1;
    advance(ms_next_);
  }
  pushed_ = pushed;
  if (ms_next_ >= pushed_) ms_next_ = -1;
}

// The stages of push `row`: pass p on row - p R (its rows within R have all run pass p - 1),
// then the stages after the angle passes.
template <typename T>
void ProfileStream<T>::advance(std::int64_t row) noexcept {
  for (int p = 1; p <= passes_; ++p) {
    const std::int64_t j = row - static_cast<std::int64_t>(p) * reach_;
    if (j < 0) break;
    run_pass(j, p);
  }
  run_stages(false);
}

template <typename T>
void ProfileStream<T>::reset() noexcept {
  pushed_ = 0;
  emitted_ = 0;
  finished_ = false;
  ms_first_ = -1;
  ms_next_ = -1;
  ms_wait_ = sample_;
  if (ms_auto_) use_min_step(-1.0);
  if (sel_) ms_sel_.reset();
  if (params_.z_noise_auto) jparams_.z_noise = -1.0;
  zq_ = std::numeric_limits<double>::infinity();
  zn_ = 0;
  if (params_.z_resolution_auto) jparams_.z_resolution = -1.0;
  p1_next_ = 0;
  reset_stages();
  reset_defects();
}

namespace {
// n points (point c's coordinates at p[c * ps], p[c * ps + cs], p[c * ps + 2 cs]) into three
// planes in one pass, with their finite flags (state 255 / label NORMAL, state 0 / label
// INVALID) and `top` raised to their largest finite_abs_bits (SPEC "Numbers"; finite_point).
// Returns the finite count. The dense layout (ps 3, cs 1) in vector clones (AVX2 and AVX-512
// shuffle the interleaved loads).
template <typename T, typename S, typename PS, typename CS>
inline __attribute__((always_inline)) std::ptrdiff_t split_finite_body(
    const T* __restrict p, std::ptrdiff_t n, PS ps, CS cs, T* __restrict x, T* __restrict y,
    T* __restrict z, std::uint8_t* __restrict st, std::uint8_t* __restrict lab, S& top) {
  std::ptrdiff_t nf = 0;
  S t = top;
  for (std::ptrdiff_t c = 0; c < n; ++c) {
    const T a = p[c * ps], b = p[c * ps + cs], d = p[c * ps + 2 * cs];
    x[c] = a;
    y[c] = b;
    z[c] = d;
    const bool fin = detail::finite_point(a, b, d, t);
    st[c] = fin ? kAlive : 0;
    lab[c] = fin ? kNormal : kInvalid;
    nf += fin;
  }
  top = t;
  return nf;
}
using K3 = std::integral_constant<std::ptrdiff_t, 3>;
using K1 = std::integral_constant<std::ptrdiff_t, 1>;
// The dense layout in chunks of kChunk points, each asking first for the row slot's lines
// kAhead points on, to be written: the slot last held the ring's oldest row, long out of the
// cache. Measured (miem_bench_stream, one core, alternated builds): the angle test alone 7 %
// more profiles per second, the default preset 2 %.
template <typename T, typename S>
inline __attribute__((always_inline)) std::ptrdiff_t split_dense_body(
    const T* __restrict p, std::ptrdiff_t n, T* __restrict x, T* __restrict y, T* __restrict z,
    std::uint8_t* __restrict st, std::uint8_t* __restrict lab, S& top) {
  constexpr std::ptrdiff_t kChunk = 64, kAhead = 4 * kChunk, kLine = 64 / sizeof(T);
  std::ptrdiff_t nf = 0;
  for (std::ptrdiff_t c0 = 0; c0 < n; c0 += kChunk) {
    if (c0 + kAhead < n) {
      for (std::ptrdiff_t c = c0 + kAhead; c < std::min(n, c0 + kAhead + kChunk); c += kLine) {
        __builtin_prefetch(x + c, 1);
        __builtin_prefetch(y + c, 1);
        __builtin_prefetch(z + c, 1);
      }
      __builtin_prefetch(st + c0 + kAhead, 1);
      __builtin_prefetch(lab + c0 + kAhead, 1);
    }
    nf += split_finite_body(p + 3 * c0, std::min(kChunk, n - c0), K3{}, K1{}, x + c0, y + c0,
                            z + c0, st + c0, lab + c0, top);
  }
  return nf;
}
MIEM_CLONES std::ptrdiff_t split_dense(const double* p, std::ptrdiff_t n, double* x, double* y,
                                       double* z, std::uint8_t* st, std::uint8_t* lab,
                                       std::int64_t& top) {
  return split_dense_body(p, n, x, y, z, st, lab, top);
}
MIEM_CLONES std::ptrdiff_t split_dense(const float* p, std::ptrdiff_t n, float* x, float* y,
                                       float* z, std::uint8_t* st, std::uint8_t* lab,
                                       std::int32_t& top) {
  return split_dense_body(p, n, x, y, z, st, lab, top);
}
}  // namespace

template <typename T>
Status ProfileStream<T>::push(const PointsView<T>& profile, StreamRow* out) noexcept {
  if (out != nullptr) *out = StreamRow{};
  if (out == nullptr) return {StatusCode::kInvalidInput, "out: must not be null (profile rejected)"};
  if (finished_) {
    return {StatusCode::kFinished, "push: the stream was flushed; call reset() to start anew"};
  }
  if (profile.size != width_) {
    return {StatusCode::kWrongWidth,
            "profile: number of points differs from the stream width (profile rejected)"};
  }
  if (profile.data == nullptr) {
    return {StatusCode::kInvalidInput, "profile: null data (profile rejected)"};
  }
  const std::int64_t row = pushed_;
  const std::ptrdiff_t W = width_, s = slot(row), plane = phys_ * W;
  T* x = xyz_.data() + s * W;
  T* y = x + plane;
  T* z = y + plane;
  std::uint8_t* st = state_.data() + s * W;
  std::uint8_t* lab = labels_.data() + s * W;
  // SPEC "Numbers": a profile with a finite coordinate beyond the range is rejected, the
  // stream as it was. It is copied and checked in one pass into its row's slot, which holds a
  // row older than any stage reads (ring_ = the longest look-back + 2) until the profile is
  // taken (then the ring's ext_ copy and the rows' state follow).
  using S = std::conditional_t<sizeof(T) == 8, std::int64_t, std::int32_t>;
  S bits = 0;
  const std::ptrdiff_t n_finite =
      profile.point_stride == 3 && profile.coord_stride == 1
          ? split_dense(profile.data, W, x, y, z, st, lab, bits)
          : split_finite_body(profile.data, W, profile.point_stride, profile.coord_stride, x, y,
                              z, st, lab, bits);
  if (!coordinate_range_ok(detail::magnitude_of<T>(static_cast<detail::AbsBits<T>>(bits)),
                           false)) {
    return {StatusCode::kInvalidInput,
            "profile: finite coordinates reach a magnitude above 1e18, outside the range the "
            "method computes without overflow; rescale the points (profile rejected)"};
  }
  p1_miss_[static_cast<std::size_t>(s)] = W - n_finite;
  if (s < ext_) {  // the copy after the ring's end (see phys_)
    const std::size_t bytes = static_cast<std::size_t>(W) * sizeof(T);
    std::memcpy(x + ring_ * W, x, bytes);
    std::memcpy(y + ring_ * W, y, bytes);
    std::memcpy(z + ring_ * W, z, bytes);
    std::memcpy(st + ring_ * W, st, static_cast<std::size_t>(W));
  }
  std::memset(cand_.data() + s * W, 0, static_cast<std::size_t>(W));
  row_cand_[s] = 0;
  level_[s] = 0;
  std::memset(hm_.data() + s * W, 0, static_cast<std::size_t>(W));
  std::memset(hs_.data() + s * W, 0xff, static_cast<std::size_t>(W));
  hrow_[s] = 0;
  if (edge_) edge_push_row(row);
  pushed_ = row + 1;
  const std::int64_t done = row - lag_;

  // min_step "auto": from the first row with a finite cell the stages wait until it is decided
  // (before that row every row is empty: no stage result depends on it), then catch up, at
  // least kMsCatch rows a push, all by the push that hands back row ms_first_.
  if (ms_wait_ && ms_first_ < 0 && n_finite > 0) ms_first_ = row;
  if (ms_wait_ && ms_first_ >= 0) min_step_row(row);
  if (ms_next_ >= 0) {
    const std::int64_t deadline = ms_first_ + lag_;
    const std::int64_t left = std::max<std::int64_t>(1, deadline - row + 1);
    catch_up(std::min(row, ms_next_ - 1 + std::max<std::int64_t>(
                                            kMsCatch, (deadline - ms_next_ + left) / left)));
  } else if (!stages_behind()) {
    advance(row);
  }
  if (done >= 0) {
    // while the stages are behind, the row handed back lies before the first finite row
    // (lag >= kAutoMinStepRows): a row of dropouts, INVALID since its push, no height
    defect_row(done);
    out->index = done;
    out->labels = labels_.data() + slot(done) * W;
    out->height = stages_behind() ? nan_row_.data() : height_.data() + slot(done) * W;
    out->defects = done_.data();
    out->n_defects = n_done_;
    emitted_ = done + 1;
  }
  if (n_finite == 0) {
    return {StatusCode::kEmptyProfile,
            "profile: no finite point (pushed as a row of dropouts, labels INVALID)"};
  }
  return {};
}

template <typename T>
bool ProfileStream<T>::flush(StreamRow* out) noexcept {
  if (out == nullptr) return false;
  *out = StreamRow{};
  if (!finished_) {
    finished_ = true;
    min_step_finish();  // min_step "auto" decided (on fewer rows than it reads if so), caught up
    // The end of the stream is now the grid border: finish every pass on the last rows, pass by
    // pass over all of them (each row's neighbours then have run the pass before).
    const std::int64_t first = std::max<std::int64_t>(0, pushed_ - alag_);
    for (int p = 1; p <= passes_; ++p) {
      for (std::int64_t j = first; j < pushed_; ++j) {
        if (level_[slot(j)] == p - 1) run_pass(j, p);
      }
    }
    run_stages(true);  // then every later stage on all the rows left, stage by stage
  }
  if (emitted_ >= pushed_) return false;
  defect_row(emitted_);
  out->index = emitted_;
  out->labels = labels_.data() + slot(emitted_) * width_;
  out->height = height_.data() + slot(emitted_) * width_;
  out->defects = done_.data();
  out->n_defects = n_done_;
  ++emitted_;
  return true;
}

// Removes an ABNORMAL cell at `pass` and marks the cells on its rays for the next pass.
template <typename T>
void ProfileStream<T>::remove(std::int64_t row, std::ptrdiff_t col, int pass) noexcept {
  const std::ptrdiff_t W = width_, s = slot(row);
  labels_[s * W + col] = kAbnormal;
  state_[s * W + col] = static_cast<std::uint8_t>(pass);
  if (s < ext_) state_[(s + ring_) * W + col] = static_cast<std::uint8_t>(pass);
  if (pass >= passes_) return;
  const std::uint8_t bit = static_cast<std::uint8_t>(1u << ((pass + 1) & 1));
  for (int k = 0; k < 4; ++k) {
    for (int sgn = -1; sgn <= 1; sgn += 2) {
      for (std::ptrdiff_t step = 1; step <= mark_reach_; ++step) {
        const std::int64_t rr = row + sgn * step * kDirRow[k];
        const std::ptrdiff_t cc = col + sgn * step * kDirCol[k];
        if (rr < 0 || rr >= pushed_ || cc < 0 || cc >= W) break;
        const std::ptrdiff_t sr = slot(rr);
        // a cell whose verdict (its row has run this pass) read less far along this ray
        // keeps it (batch's later passes do the same)
        if (use_ray_ && level_[sr] >= pass &&
            ray_[4 * (sr * W + cc) + k] < detail::reach_byte(step)) {
          continue;
        }
        cand_[sr * W + cc] |= bit;
        row_cand_[sr] |= bit;
      }
    }
  }
}

template <typename T>
void ProfileStream<T>::run_pass(std::int64_t row, int pass) noexcept {
  const std::ptrdiff_t W = width_;
  // The judge's grid: the rows within R of `row` (all a judgment reads), contiguous in the
  // ring thanks to its extension; clamped to the stream's first and (pushed) last rows, which
  // are then the grid's border, as in batch detection.
  const std::int64_t first = std::max<std::int64_t>(0, row - reach_);
  const std::int64_t last = std::min<std::int64_t>(pushed_ - 1, row + reach_);
  const std::ptrdiff_t s0 = slot(first);
  const GridView<T> grid{xyz_.data() + s0 * W, static_cast<std::ptrdiff_t>(last - first + 1), W,
                         W, 1, phys_ * W};
  const detail::CellJudge<T, UsableAtPass, true> judge(
      grid, state_.data() + s0 * W, jparams_, UsableAtPass{static_cast<std::uint8_t>(pass)});
  const std::ptrdiff_t s = slot(row), r = static_cast<std::ptrdiff_t>(row - first);
  const std::uint8_t* st = state_.data() + s * W;
  std::uint8_t* lab = labels_.data() + s * W;
  std::uint8_t* ray = use_ray_ ? ray_.data() + 4 * s * W : nullptr;
  // A cell's verdict (CellJudge), and the verdict taken: ABNORMAL removes the cell.
  auto verdict = [&](std::ptrdiff_t c) {
    std::uint8_t flags = 0;
    double angle = 0.0;
    return judge.judge(r, c, &flags, &angle, ray ? ray + 4 * c : nullptr);
  };
  auto take = [&](std::ptrdiff_t c, std::uint8_t l) {
    if (l == kAbnormal) {
      remove(row, c, pass);
    } else {
      lab[c] = l;
    }
  };
  auto judge_cell = [&](std::ptrdiff_t c) { take(c, verdict(c)); };
  // The verdicts of the cells judge_cols_[0 .. n) (increasing), on the push's threads, then
  // taken in column order: a pass's judgments read the cells usable at its start (a cell
  // removed at this pass still is: Jacobi), so they do not depend on the removals of the same
  // pass. `keep(c)`: false when the cell keeps its verdict (not judged again).
  constexpr std::ptrdiff_t kJudgeChunk = 16;
  auto judge_cells = [&](std::ptrdiff_t n, auto keep) {
    const std::ptrdiff_t* cols = judge_cols_.data();
    std::uint8_t* out = judge_out_.data();
    constexpr std::uint8_t kKeep = 255;
    const auto verdicts = [&](std::ptrdiff_t chunk, int) {
      const std::ptrdiff_t i1 = std::min(n, (chunk + 1) * kJudgeChunk);
      for (std::ptrdiff_t i = chunk * kJudgeChunk; i < i1; ++i) {
        out[i] = keep(cols[i]) ? verdict(cols[i]) : kKeep;
      }
    };
    detail::parallel_items(n >= 4 * kJudgeChunk ? threads_ : 1,
                           (n + kJudgeChunk - 1) / kJudgeChunk, verdicts);
    for (std::ptrdiff_t i = 0; i < n; ++i) {
      if (out[i] != kKeep) take(cols[i], out[i]);
    }
  };

  // Pass 1 by batch detection's row kernel with min_step; without, by the filter below. Without
  // p1_gap_, the filter leaves every cell with a missing neighbour (about 16 per dropout) to
  // CellJudge: then the row kernel runs where more than 0.5 % of the cells within the largest
  // scale are dropouts. (It took 8 % more of a default push than the filter on a clean scan,
  // and 5-12 % less at 1 % dropouts.)
  bool kernel = p1_kernel_;
  if (pass == 1 && !kernel && fast_ && !p1_gap_ && !p1_lab_.empty()) {
    std::int64_t miss = 0;
    const std::int64_t a = std::max<std::int64_t>(0, row - max_scale_);
    const std::int64_t b = std::min<std::int64_t>(pushed_ - 1, row + max_scale_);
    for (std::int64_t rr = a; rr <= b; ++rr) miss += p1_miss_[static_cast<std::size_t>(slot(rr))];
    kernel = 200 * miss > (b - a + 1) * W;
  }
  if (pass == 1 && kernel) {
    // the row kernel, CellJudge for the cells it cannot settle
    const std::int64_t* ok = pass1_kernel(row);
    std::ptrdiff_t n = 0;
    for (std::ptrdiff_t c = 0; c < W; ++c) {
      if (st[c] == 0) continue;
      if (detail::pass1_needs_judge(p1_, ok, c)) {
        judge_cols_[static_cast<std::size_t>(n++)] = c;
      } else {
        take(c, p1_lab_[static_cast<std::size_t>(c)]);
      }
    }
    judge_cells(n, [](std::ptrdiff_t) { return true; });
  } else if (pass == 1) {
    const bool fast = fast_ && row >= fedge_ && row + fedge_ < pushed_ &&
                      W > 2 * static_cast<std::ptrdiff_t>(fedge_);
    if (!fast) {
      for (std::ptrdiff_t c = 0; c < W; ++c)
        if (st[c] != 0) judge_cell(c);
    } else {
      // The kernel marks the few cells that need more than "NORMAL" (set at push).
      pass1_fast(row);
      const std::ptrdiff_t S = fedge_;
      for (std::ptrdiff_t c = 0; c < S; ++c)
        if (st[c] != 0) judge_cell(c);
      for (std::ptrdiff_t c = W - S; c < W; ++c)
        if (st[c] != 0) judge_cell(c);
      const std::uint32_t* bits = bits_.data();
      for (std::ptrdiff_t c = S; c < W - S; ++c) {
        if ((c - S) % 16 == 0 && c + 16 <= W - S) {  // skip empty stretches 16 cells at a time
          std::uint32_t any = 0;
          for (int k = 0; k < 16; ++k) any |= bits[c + k];
          if (any == 0) {
            c += 15;
            continue;
          }
        }
        const std::uint32_t b = bits[c];
        if (b == 0 || st[c] == 0) continue;
        if (b & kBadBit) {
          judge_cell(c);  // next to a dropout
          continue;
        }
        take(c, exact_label(row, c, b));
      }
    }
  } else {
    const std::uint8_t bit = static_cast<std::uint8_t>(1u << (pass & 1));
    // With min_step: a candidate whose last verdict read no cell removed at pass - 1 (the
    // only cells it read that changed since: an earlier removal within its reach made it a
    // candidate then) keeps its verdict; a verdict costs far more than this look.
    const std::uint8_t* us = state_.data() + s0 * W;
    const std::uint8_t gone = static_cast<std::uint8_t>(pass - 1);
    auto reads_removed = [&](std::ptrdiff_t c) {
      const std::uint8_t* ry = ray + 4 * c;
      for (int k = 0; k < 4; ++k) {
        const std::ptrdiff_t n = ry[k] == 255 ? mark_reach_ : ry[k];
        for (int sgn = -1; sgn <= 1; sgn += 2) {
          const std::ptrdiff_t dr = sgn * kDirRow[k], dc = sgn * kDirCol[k];
          for (std::ptrdiff_t step = 1; step <= n; ++step) {
            const std::ptrdiff_t rr = r + step * dr, cc = c + step * dc;
            if (rr < 0 || rr >= grid.rows || cc < 0 || cc >= W) break;
            if (us[rr * W + cc] == gone) return true;
          }
        }
      }
      return false;
    };
    if (row_cand_[s] & bit) {
      std::uint8_t* cand = cand_.data() + s * W;
      std::ptrdiff_t n = 0;
      for (std::ptrdiff_t c = 0; c < W; ++c) {
        if (!(cand[c] & bit)) continue;
        cand[c] &= static_cast<std::uint8_t>(~bit);
        if (st[c] == kAlive) judge_cols_[static_cast<std::size_t>(n++)] = c;
      }
      judge_cells(n, [&](std::ptrdiff_t c) { return ray == nullptr || reads_removed(c); });
      row_cand_[s] &= static_cast<std::uint8_t>(~bit);
    }
  }
  level_[s] = static_cast<std::uint8_t>(pass);
}

template <typename T>
std::ptrdiff_t ProfileStream<T>::step_offset(std::int64_t row, int k, std::ptrdiff_t step,
                                             int sign) const noexcept {
  return slot(row + sign * kDirRow[k] * step) * width_ + sign * kDirCol[k] * step;
}

namespace {
// bits[c] gets kBadBit where a side has no usable cell at step s nor at s + 1 (states sa, sa2
// and sb, sb2; the same pointers twice without p1_gap_), c in [c0, c1): vector clones.
MIEM_CLONES void mark_missing(std::ptrdiff_t c0, std::ptrdiff_t c1,
                              const std::uint8_t* __restrict sa, const std::uint8_t* __restrict sa2,
                              const std::uint8_t* __restrict sb, const std::uint8_t* __restrict sb2,
                              std::uint32_t* __restrict bits) {
  for (std::ptrdiff_t c = c0; c < c1; ++c) {
    bits[c] |= static_cast<std::uint32_t>(((sa[c] | sa2[c]) == 0) | ((sb[c] | sb2[c]) == 0))
               << 31;
  }
}
}  // namespace

// Pass 1 filter of one row where every neighbour cell exists: marks in bits_ the cells that
// might be flagged in some direction (the kernel) and, with kBadBit, the cells with a missing
// neighbour (next to a dropout; with p1_gap_, missing at steps s and s + 1), which CellJudge
// itself judges. Every other cell is NORMAL.
template <typename T>
void ProfileStream<T>::pass1_fast(std::int64_t row) noexcept {
  const std::ptrdiff_t W = width_, S = fedge_, plane = phys_ * W;
  std::uint32_t* bits = bits_.data();
  const std::size_t n_scales = params_.scales.size();
  KernelArgs<T> args{};
  args.gap = p1_gap_;
  args.P = xyz_.data() + slot(row) * W;
  args.n = 4 * static_cast<int>(n_scales);
  args.plane = plane;
  args.bits = bits;
  // the states of the cells one step further: the step-s ones themselves without p1_gap_ (so
  // "no neighbour within s .. s + 1" is "none at s")
  const std::uint8_t* sa2[32];
  const std::uint8_t* sb2[32];
  for (int k = 0; k < 4; ++k) {
    for (std::size_t si = 0; si < n_scales; ++si) {
      const std::ptrdiff_t sc = params_.scales[si];
      // A[c] = the cell sc steps back along direction k from (row, c), B[c] sc steps on
      const int i = k * static_cast<int>(n_scales) + static_cast<int>(si);
      const std::ptrdiff_t a = step_offset(row, k, sc, -1), b = step_offset(row, k, sc, 1);
      args.A[i] = xyz_.data() + a, args.B[i] = xyz_.data() + b;
      args.SA[i] = state_.data() + a, args.SB[i] = state_.data() + b;
      sa2[i] = args.SA[i], sb2[i] = args.SB[i];
      if (!p1_gap_) continue;
      // the cells one step further (rows and columns within fedge_ of the row)
      const std::ptrdiff_t a2 = step_offset(row, k, sc + 1, -1);
      const std::ptrdiff_t b2 = step_offset(row, k, sc + 1, 1);
      args.A2[i] = xyz_.data() + a2, args.B2[i] = xyz_.data() + b2;
      sa2[i] = state_.data() + a2, sb2[i] = state_.data() + b2;
    }
  }
  // the kernel's rows: `row` and the rows a scale above and below it (its directions' steps)
  args.rows[0] = xyz_.data() + slot(row) * W;
  args.n_rows = 1;
  for (std::size_t si = 0; si < n_scales; ++si) {  // (at most 7 scales: fast_ok_)
    args.rows[args.n_rows++] = xyz_.data() + slot(row - params_.scales[si]) * W;
    args.rows[args.n_rows++] = xyz_.data() + slot(row + params_.scales[si]) * W;
  }
  // The columns S .. W - S - 1 in one contiguous range per thread (each cell's bits its own).
  detail::parallel_ranges(threads_, W - 2 * S, 1, [&](int, std::ptrdiff_t i0, std::ptrdiff_t i1) {
    const std::ptrdiff_t c0 = S + i0, c1 = S + i1;
    std::fill(bits + c0, bits + c1, cos0_ > 0.0 ? 0u : ~kBadBit);  // theta0 >= 90: all exact
    for (int i = 0; i < args.n; ++i) {  // no neighbour within steps s .. s + 1 (p1_gap_)
      mark_missing(c0, c1, args.SA[i], sa2[i], args.SB[i], sb2[i], bits);
    }
    if (cos0_ > 0.0 && c0 < c1) {
      KernelArgs<T> part_args = args;
      part_args.c0 = c0;
      part_args.c1 = c1;
      run_kernel(part_args);
    }
  });
}

// The exact judgment of a cell of a row where every neighbour exists at step s (or, with
// p1_gap_, at s + 1 where the step-s cell is a dropout), computed as
// CellJudge computes it (dot3, the same evaluation order); `b` holds the (direction, scale)
// pairs that the filter could not rule out.
template <typename T>
std::uint8_t ProfileStream<T>::exact_label(std::int64_t row, std::ptrdiff_t c,
                                           std::uint32_t b) const noexcept {
  const std::ptrdiff_t W = width_, plane = phys_ * W;
  const T* X0 = xyz_.data() + slot(row) * W + c;
  const Eigen::Vector3d P(static_cast<double>(X0[0]), static_cast<double>(X0[plane]),
                          static_cast<double>(X0[2 * plane]));
  const std::size_t n_scales = params_.scales.size();
  int avail = 0, flagged = 0;
  for (int k = 0; k < 4; ++k) {
    bool dir_avail = false, dir_flag = false;
    for (std::size_t si = 0; si < n_scales; ++si) {
      const int i = k * static_cast<int>(n_scales) + static_cast<int>(si);
      const std::ptrdiff_t sc = params_.scales[si];
      std::ptrdiff_t oa = step_offset(row, k, sc, -1) + c, ob = step_offset(row, k, sc, 1) + c;
      if (p1_gap_) {  // a step-s cell that is not usable: the next one (pass1_fast)
        if (state_[static_cast<std::size_t>(oa)] == 0) oa = step_offset(row, k, sc + 1, -1) + c;
        if (state_[static_cast<std::size_t>(ob)] == 0) ob = step_offset(row, k, sc + 1, 1) + c;
      }
      const T* a = xyz_.data() + oa;
      const T* bb = xyz_.data() + ob;
      const Eigen::Vector3d u = Eigen::Vector3d(static_cast<double>(a[0]),
                                                static_cast<double>(a[plane]),
                                                static_cast<double>(a[2 * plane])) - P;
      const Eigen::Vector3d v = Eigen::Vector3d(static_cast<double>(bb[0]),
                                                static_cast<double>(bb[plane]),
                                                static_cast<double>(bb[2 * plane])) - P;
      const double uu = detail::dot3(u, u), vv = detail::dot3(v, v);
      if (uu == 0.0 || vv == 0.0) continue;
      dir_avail = true;
      if (!(b & (1u << i))) continue;  // the filter showed cos < cos0
      if (detail::clamped_cos(detail::dot3(u, v), uu, vv) >= cos0_) dir_flag = true;
    }
    avail += dir_avail;
    flagged += dir_flag;
  }
  return detail::direction_label(avail, flagged, params_.min_directions);
}

// Pass 1 of `row` by the row kernel (pass1_row.hpp): the rows within p1_depth_ converted (those
// not yet: pass 1 runs row by row, in order; the rows it skipped were not needed), then the
// kernel's labels of the row in p1_lab_ and, with min_step, the rays each verdict read in ray_.
// The rows beyond the last pushed one are the grid's border, as in run_pass's judge. Returns
// the row's usable lanes (pass1_needs_judge reads them).
template <typename T>
const std::int64_t* ProfileStream<T>::pass1_kernel(std::int64_t row) noexcept {
  const std::ptrdiff_t W = width_, plane = phys_ * W;
  const detail::Pass1Ring ring{&p1_, static_cast<std::ptrdiff_t>(pushed_), W, p1_depth_};
  p1_next_ = std::max<std::int64_t>(p1_next_, row - p1_depth_);
  for (; p1_next_ <= std::min<std::int64_t>(pushed_ - 1, row + p1_depth_); ++p1_next_) {
    const std::ptrdiff_t s = slot(p1_next_);
    const T* x = xyz_.data() + s * W;
    const std::uint8_t* st = state_.data() + s * W;
    detail::pass1_load(ring, static_cast<std::ptrdiff_t>(p1_next_), x, x + plane, x + 2 * plane,
                       1, st);
  }
  detail::pass1_row(ring, static_cast<std::ptrdiff_t>(row), jparams_, p1_lab_.data(), nullptr,
                    nullptr, use_ray_ ? ray_.data() + 4 * slot(row) * W : nullptr, threads_);
  return ring.ok(static_cast<std::ptrdiff_t>(row));
}

namespace nothrow {

template <typename T>
Status make_stream(std::ptrdiff_t width, const DetectParams& params,
                   std::optional<ProfileStream<T>>* out) noexcept {
  if (out == nullptr) return {StatusCode::kInvalidInput, "out: must not be null"};
  const Status st = check_stream_params(width, params);
  if (!st.ok()) return st;
  try {
    out->emplace(width, params);
  } catch (const std::bad_alloc&) {
    return {StatusCode::kOutOfMemory, "make_stream: out of memory for the profile ring"};
  } catch (const std::invalid_argument&) {
    return {StatusCode::kInvalidParameter, "make_stream: parameters out of range"};
  } catch (...) {
    return {StatusCode::kInternal, "make_stream: unexpected exception"};
  }
  return {};
}

template Status make_stream<float>(std::ptrdiff_t, const DetectParams&,
                                   std::optional<ProfileStream<float>>*) noexcept;
template Status make_stream<double>(std::ptrdiff_t, const DetectParams&,
                                    std::optional<ProfileStream<double>>*) noexcept;

}  // namespace nothrow

template class ProfileStream<float>;
template class ProfileStream<double>;

}  // namespace miem
