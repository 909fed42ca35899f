// MIEM on organized scans. One judge per cell reads only the usable mask and the grid, so cells
// are independent within a pass (Jacobi): row-parallel, and identical for any thread count.
// Later passes re-judge only the cells whose rays cross a newly removed cell.
#include "miem/organized.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numeric>
#include <stdexcept>
#include <string>

#include <Eigen/Eigenvalues>

#include "angle_math.hpp"
#include "defects.hpp"
#include "judge.hpp"
#include "plane_math.hpp"
#include "parallel.hpp"

namespace miem {

namespace {

using detail::CellJudge;
using detail::kDirCol;
using detail::kDirRow;
using detail::kNaN;
using detail::window_plane;

// The window plane (SPEC "Height") of the NORMAL cells around a cell, from box sums.
struct WindowFit {
  bool ok = false;  // a plane exists (>= 3 cells, not degenerate)
  double height = 0.0, n = 0.0, l0 = 0.0, l1 = 0.0, l2 = 0.0;
  double edges = 0.0;  // feature-line EDGE cells in the window
};

// Calls visit(r, c, fit) for every cell with want(r, c), with the window plane of the NORMAL
// cells around it from box sums of their moments. Tiles keep the sums in tile-local coordinates
// (far-from-origin scans lose no precision); each thread owns its buffer. Cells are independent,
// so the result does not depend on the thread count.
template <typename T, typename Want, typename Visit, typename Line>
void window_fits(const GridView<T>& g, const std::uint8_t* labels, int window, int num_threads,
                 std::vector<double>& scratch, Want want, Visit visit, Line is_line) {
  constexpr std::ptrdiff_t kTile = 64;
  constexpr int kM = 11;  // n, x, y, z, xx, xy, xz, yy, yz, zz (NORMAL cells), EDGE count
  const std::ptrdiff_t H = g.rows, W = g.cols, half = window / 2;
  const std::ptrdiff_t tiles_r = (H + kTile - 1) / kTile, tiles_c = (W + kTile - 1) / kTile;
  const std::ptrdiff_t ntiles = tiles_r * tiles_c;
  const std::ptrdiff_t side = kTile + 2 * half + 1;
  const std::ptrdiff_t per_thread = side * side * kM;
  const int nt = detail::thread_count(num_threads, H * W);
  if (scratch.size() < static_cast<std::size_t>(per_thread * nt)) scratch.resize(per_thread * nt);

#pragma omp parallel for schedule(dynamic, 1) num_threads(nt) if (nt > 1)
  for (std::ptrdiff_t t = 0; t < ntiles; ++t) {
    int tid = 0;
#ifdef MIEM_HAVE_OPENMP
    tid = omp_get_thread_num();
#endif
    double* I = scratch.data() + per_thread * tid;
    const std::ptrdiff_t tr0 = (t / tiles_c) * kTile, tc0 = (t % tiles_c) * kTile;
    const std::ptrdiff_t tr1 = std::min(H, tr0 + kTile), tc1 = std::min(W, tc0 + kTile);
    bool wanted = false;
    for (std::ptrdiff_t r = tr0; r < tr1 && !wanted; ++r)
      for (std::ptrdiff_t c = tc0; c < tc1; ++c)
        if (want(r, c)) {
          wanted = true;
          break;
        }
    if (!wanted) continue;
    const std::ptrdiff_t R0 = std::max<std::ptrdiff_t>(0, tr0 - half);
    const std::ptrdiff_t R1 = std::min(H, tr1 + half);
    const std::ptrdiff_t C0 = std::max<std::ptrdiff_t>(0, tc0 - half);
    const std::ptrdiff_t C1 = std::min(W, tc1 + half);
    const std::ptrdiff_t nr = R1 - R0, nc = C1 - C0, stride = (nc + 1) * kM;
    // Local origin: the first NORMAL cell of the region.
    Eigen::Vector3d origin = Eigen::Vector3d::Zero();
    bool any = false;
    for (std::ptrdiff_t r = R0; r < R1 && !any; ++r)
      for (std::ptrdiff_t c = C0; c < C1; ++c)
        if (labels[r * W + c] == kNormal) {
          origin = g(r, c);
          any = true;
          break;
        }
    if (!any) {
      for (std::ptrdiff_t r = tr0; r < tr1; ++r)
        for (std::ptrdiff_t c = tc0; c < tc1; ++c)
          if (want(r, c)) visit(r, c, WindowFit{});
      continue;
    }
    std::fill(I, I + stride, 0.0);  // row 0 of the integral image
    for (std::ptrdiff_t i = 0; i < nr; ++i) {
      double* row = I + (i + 1) * stride;
      const double* up = I + i * stride;
      double acc[kM] = {0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0};
      std::fill(row, row + kM, 0.0);
      for (std::ptrdiff_t j = 0; j < nc; ++j) {
        const std::ptrdiff_t r = R0 + i, c = C0 + j;
        if (labels[r * W + c] == kNormal) {
          const Eigen::Vector3d q = g(r, c) - origin;
          acc[0] += 1.0;
          acc[1] += q.x();
          acc[2] += q.y();
          acc[3] += q.z();
          acc[4] += q.x() * q.x();
          acc[5] += q.x() * q.y();
          acc[6] += q.x() * q.z();
          acc[7] += q.y() * q.y();
          acc[8] += q.y() * q.z();
          acc[9] += q.z() * q.z();
        } else if (is_line(r * W + c)) {
          acc[10] += 1.0;
        }
        double* dst = row + (j + 1) * kM;
        const double* src = up + (j + 1) * kM;
        for (int m = 0; m < kM; ++m) dst[m] = src[m] + acc[m];
      }
    }
    for (std::ptrdiff_t r = tr0; r < tr1; ++r) {
      for (std::ptrdiff_t c = tc0; c < tc1; ++c) {
        if (!want(r, c)) continue;
        WindowFit fit;
        const std::ptrdiff_t i0 = std::max<std::ptrdiff_t>(0, r - half) - R0;
        const std::ptrdiff_t i1 = std::min(H - 1, r + half) - R0 + 1;
        const std::ptrdiff_t j0 = std::max<std::ptrdiff_t>(0, c - half) - C0;
        const std::ptrdiff_t j1 = std::min(W - 1, c + half) - C0 + 1;
        const double* a = I + i1 * stride + j1 * kM;
        const double* b = I + i0 * stride + j1 * kM;
        const double* d = I + i1 * stride + j0 * kM;
        const double* e = I + i0 * stride + j0 * kM;
        double s[kM];
        for (int m = 0; m < kM; ++m) s[m] = (a[m] - b[m]) - (d[m] - e[m]);
        const double n = std::round(s[0]);
        fit.edges = std::round(s[10]);
        if (n >= 3.0) {
          const Eigen::Vector3d mean(s[1] / n, s[2] / n, s[3] / n);
          Eigen::Matrix3d M;
          M(0, 0) = s[4] - n * mean.x() * mean.x();
          M(0, 1) = M(1, 0) = s[5] - n * mean.x() * mean.y();
          M(0, 2) = M(2, 0) = s[6] - n * mean.x() * mean.z();
          M(1, 1) = s[7] - n * mean.y() * mean.y();
          M(1, 2) = M(2, 1) = s[8] - n * mean.y() * mean.z();
          M(2, 2) = s[9] - n * mean.z() * mean.z();
          Eigen::Vector3d nv;
          if (detail::smallest_eigenpair(M, &fit.l0, &fit.l1, &fit.l2, &nv) && fit.l2 > 0.0 &&
              fit.l1 > 1e-12 * fit.l2) {
            fit.ok = true;
            fit.n = n;
            fit.height = orient_normal(nv).dot(g(r, c) - origin - mean);
          }
        }
        visit(r, c, fit);
      }
    }
  }
}

// Pass 1 row kernel. In the common case (every neighbour candidate at exactly s cells is
// usable) the search of SPEC.md returns that candidate, so whole rows are judged with straight-
// line loops over structure-of-arrays copies of the rows, which the compiler vectorizes (an AVX2
// clone is picked at run time where the CPU has it). Cells that need a gap search or the
// isolation test fall back to the scalar judge.
constexpr int kPop4[16] = {0, 1, 1, 2, 1, 2, 2, 3, 1, 2, 2, 3, 2, 3, 3, 4};

#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__linux__)
#define MIEM_CLONES __attribute__((target_clones("avx2", "default")))
#else
#define MIEM_CLONES
#endif

// One (direction, scale) over columns [c0, c1). The running best cos is kept as the pair
// (uv, prod) = (u.v, |u|^2 |v|^2) and compared through uv |uv| / prod, which orders like
// uv / sqrt(prod): no square root or division per candidate.
MIEM_CLONES void kernel_line(std::ptrdiff_t c0, std::ptrdiff_t c1, const double* __restrict ax,
                             const double* __restrict ay, const double* __restrict az,
                             const double* __restrict bx, const double* __restrict by,
                             const double* __restrict bz, const double* __restrict px,
                             const double* __restrict py, const double* __restrict pz,
                             const std::uint8_t* __restrict oa, const std::uint8_t* __restrict ob,
                             double cos0, double c2, std::uint8_t bit, std::uint8_t is_near,
                             double* __restrict buv, double* __restrict bprod,
                             std::uint8_t* __restrict avail, std::uint8_t* __restrict flag,
                             std::uint8_t* __restrict slow, std::uint8_t* __restrict near) {
  for (std::ptrdiff_t c = c0; c < c1; ++c) {
    const int both = oa[c] & ob[c];
    const double ux = ax[c] - px[c], uy = ay[c] - py[c], uz = az[c] - pz[c];
    const double vx = bx[c] - px[c], vy = by[c] - py[c], vz = bz[c] - pz[c];
    const double uu = (ux * ux + uy * uy) + uz * uz;
    const double vv = (vx * vx + vy * vy) + vz * vz;
    const double uv = (ux * vx + uy * vy) + uz * vz;
    const double prod = uu * vv;
    const int good = both & (uu != 0.0) & (vv != 0.0);
    const int flagged = good & detail::cos_at_least(uv, prod, cos0, c2);
    const double b_uv = buv[c], b_prod = bprod[c];
    const int better = good & (uv * std::fabs(uv) * b_prod > b_uv * std::fabs(b_uv) * prod);
    buv[c] = better ? uv : b_uv;
    bprod[c] = better ? prod : b_prod;
    slow[c] |= static_cast<std::uint8_t>(both ^ 1);
    near[c] |= static_cast<std::uint8_t>(both & is_near);
    avail[c] |= static_cast<std::uint8_t>(good * bit);
    flag[c] |= static_cast<std::uint8_t>(flagged * bit);
  }
}

// Smallest angle (degrees) from the best (uv, prod) pairs of a row; NaN where none.
MIEM_CLONES void angles_line(std::ptrdiff_t n, const double* __restrict buv,
                             const double* __restrict bprod, double* __restrict out) {
  for (std::ptrdiff_t c = 0; c < n; ++c) {
    const bool has = bprod[c] > 0.0;
    double cs = buv[c] / std::sqrt(has ? bprod[c] : 1.0);
    cs = cs < -1.0 ? -1.0 : (cs > 1.0 ? 1.0 : cs);
    const double deg = detail::acos_fast(cs) * detail::kRadToDeg;
    out[c] = has ? deg : detail::kNaN;
  }
}

// Copy row rr of the grid into structure-of-arrays slot buffers.
template <typename T>
void load_row(const GridView<T>& g, const std::uint8_t* usable, std::ptrdiff_t rr, double* x,
              std::uint8_t* ok) {
  const std::ptrdiff_t W = g.cols;
  double* y = x + W;
  double* z = y + W;
  const std::uint8_t* us = usable + rr * W;
  const T* base = g.data + rr * g.row_stride;
  for (std::ptrdiff_t c = 0; c < W; ++c) {
    const T* q = base + c * g.col_stride;
    x[c] = static_cast<double>(q[0]);
    y[c] = static_cast<double>(q[g.coord_stride]);
    z[c] = static_cast<double>(q[2 * g.coord_stride]);
    ok[c] = us[c] & 1;
  }
}

// Judge rows [r_begin, r_end) of pass 1, keeping a ring of 2 smax + 1 SoA rows (each grid row
// is converted once).
template <typename T, typename Judge>
void pass1_rows(const GridView<T>& g, const std::uint8_t* usable, const DetectParams& p,
                int smax, std::ptrdiff_t r_begin, std::ptrdiff_t r_end, detail::RowScratch& sc,
                const Judge& judge, std::uint8_t* labels, std::uint8_t* flags_out,
                double* angle_out) {
  const std::ptrdiff_t H = g.rows, W = g.cols, NR = 2 * smax + 1;
  const double cos0 = std::cos(p.theta0_deg * detail::kDegToRad), c2 = cos0 * cos0;
  auto slot_x = [&](std::ptrdiff_t rr) { return sc.xyz.data() + (rr % NR) * 3 * W; };
  auto slot_ok = [&](std::ptrdiff_t rr) { return sc.ok.data() + (rr % NR) * W; };
  for (std::ptrdiff_t rr = std::max<std::ptrdiff_t>(0, r_begin - smax);
       rr < std::min(H, r_begin + smax); ++rr) {
    load_row(g, usable, rr, slot_x(rr), slot_ok(rr));
  }
  double *buv = sc.best.data(), *bprod = sc.best.data() + W;
  std::uint8_t *avail = sc.avail.data(), *flag = sc.flag.data(), *slow = sc.slow.data(),
               *near = sc.near.data();
  for (std::ptrdiff_t r = r_begin; r < r_end; ++r) {
    if (r + smax < H) load_row(g, usable, r + smax, slot_x(r + smax), slot_ok(r + smax));
    std::fill(buv, buv + W, -2.0);
    std::fill(bprod, bprod + W, 0.0);
    std::fill(avail, avail + W, 0);
    std::fill(flag, flag + W, 0);
    std::fill(slow, slow + W, 0);
    std::fill(near, near + W, 0);
    const double* px = slot_x(r);
    for (int k = 0; k < 4; ++k) {
      const int dr = detail::kDirRow[k], dc = detail::kDirCol[k];
      const std::uint8_t bit = static_cast<std::uint8_t>(1u << k);
      for (int s : p.scales) {
        if (r - s * dr < 0 || r + s * dr >= H) continue;  // a side outside the grid: unavailable
        const std::ptrdiff_t sh = static_cast<std::ptrdiff_t>(s) * dc;  // column shift, side +1
        const std::ptrdiff_t c0 = std::abs(sh), c1 = W - std::abs(sh);
        if (c0 >= c1) continue;
        const double* ax = slot_x(r - s * dr) - sh;
        const double* bx = slot_x(r + s * dr) + sh;
        const std::uint8_t* oa = slot_ok(r - s * dr) - sh;
        const std::uint8_t* ob = slot_ok(r + s * dr) + sh;
        kernel_line(c0, c1, ax, ax + W, ax + 2 * W, bx, bx + W, bx + 2 * W, px, px + W,
                    px + 2 * W, oa, ob, cos0, c2, bit,
                    static_cast<std::uint8_t>(s <= 1 + p.max_gap), buv, bprod, avail, flag,
                    slow, near);
      }
    }
    double* angle_row = angle_out ? angle_out + r * W : nullptr;
    if (angle_row) angles_line(W, buv, bprod, angle_row);
    const std::uint8_t* centre_ok = slot_ok(r);
    for (std::ptrdiff_t c = 0; c < W; ++c) {
      if (!centre_ok[c]) continue;
      const std::ptrdiff_t i = r * W + c;
      if (slow[c] | (near[c] ^ 1)) {
        std::uint8_t fl;
        double an;
        labels[i] = judge.judge(r, c, &fl, &an);
        if (flags_out) flags_out[i] = fl;
        if (angle_row) angle_row[c] = an;
        continue;
      }
      const int a = kPop4[avail[c]], f = kPop4[flag[c]];
      const int need = p.min_directions > 0 ? std::min(a, p.min_directions) : a;
      labels[i] = (a >= 2 && f >= need) ? kAbnormal : (f > 0 ? kEdge : kNormal);
      if (flags_out) flags_out[i] = flag[c];
    }
  }
}

}  // namespace

void validate(const DetectParams& p) {
  if (!p.theta0_auto &&
      (!std::isfinite(p.theta0_deg) || p.theta0_deg <= 0.0 || p.theta0_deg >= 180.0)) {
    throw std::invalid_argument("theta0: must be a finite angle in degrees with 0 < theta0 < 180");
  }
  if (p.scales.empty()) throw std::invalid_argument("scales: must not be empty");
  for (int s : p.scales) {
    if (s < 1) throw std::invalid_argument("scales: every scale must be an integer >= 1");
  }
  if (p.max_gap < 0) throw std::invalid_argument("max_gap: must be an integer >= 0");
  if (std::isnan(p.min_step) || std::isinf(p.min_step)) {
    throw std::invalid_argument("min_step: must be finite (negative = off)");
  }
  if (p.max_reach < 1) throw std::invalid_argument("max_reach: must be an integer >= 1");
  if (p.min_directions < 0 || p.min_directions > 4) {
    throw std::invalid_argument("min_directions: must be 0 (all) or 1..4");
  }
  if (p.max_iterations < 1) throw std::invalid_argument("max_iterations: must be >= 1");
  if (p.window < 3 || p.window % 2 == 0) {
    throw std::invalid_argument("window: must be an odd integer >= 3");
  }
  if (p.num_threads < 0) throw std::invalid_argument("num_threads: must be >= 0");
  if (!std::isfinite(p.height_abs) || !std::isfinite(p.height_k)) {
    throw std::invalid_argument("height_tolerance: must be finite (<= 0 = off)");
  }
  if (p.edge_extent < 0) throw std::invalid_argument("edge_extent: must be an integer >= 0");
}

const char* to_string(DefectKind kind) noexcept {
  switch (kind) {
    case DefectKind::kProtrusion:
      return "protrusion";
    case DefectKind::kPit:
      return "pit";
    case DefectKind::kIsolated:
      return "isolated";
  }
  return "unknown";
}

OrganizedDetector::OrganizedDetector(DetectParams params) : params_(std::move(params)) {
  validate(params_);
}

template <typename T>
DetectSummary OrganizedDetector::run(const GridView<T>& g, const OrganizedOutput& out) {
  if (g.rows < 1 || g.cols < 1 || g.data == nullptr) {
    throw std::invalid_argument("grid: must have at least one row and one column");
  }
  if (out.labels == nullptr) throw std::invalid_argument("out.labels: must not be null");
  eff_ = params_;  // same-size assignment: no allocation after the first run
  const DetectParams& p = eff_;
  const std::ptrdiff_t H = g.rows, W = g.cols, N = H * W;
  const int nt = detail::thread_count(p.num_threads, N);
  std::uint8_t* labels = out.labels;
  usable_.resize(static_cast<std::size_t>(N));
  std::uint8_t* usable = usable_.data();

  // Pass 0: finiteness.
  std::ptrdiff_t n_finite = 0;
#pragma omp parallel for schedule(static) num_threads(nt) if (nt > 1) reduction(+ : n_finite)
  for (std::ptrdiff_t r = 0; r < H; ++r) {
    for (std::ptrdiff_t c = 0; c < W; ++c) {
      const std::ptrdiff_t i = r * W + c;
      const bool fin = g.finite(r, c);
      usable[i] = fin;
      labels[i] = fin ? kNormal : kInvalid;
      n_finite += fin;
      if (out.flags) out.flags[i] = 0;
      if (out.angle_deg) out.angle_deg[i] = kNaN;
    }
  }
  if (n_finite < 3) {
    throw std::invalid_argument("grid: fewer than 3 finite points (found " +
                                std::to_string(n_finite) + ")");
  }

  const int smax = *std::max_element(p.scales.begin(), p.scales.end());
  const bool row_kernel = p.min_step < 0.0 && smax <= 64;
  if (row_kernel) {
    if (row_scratch_.size() < static_cast<std::size_t>(nt)) row_scratch_.resize(nt);
    for (int t = 0; t < nt; ++t) row_scratch_[t].resize(2 * smax + 1, W);
  }
  // Pass 1 over every finite cell (row kernel; the scalar judge for min_step and fallbacks).
  auto pass1 = [&](double* angle_out) {
    const CellJudge<T> judge(g, usable, p);
    if (row_kernel) {
#pragma omp parallel num_threads(nt) if (nt > 1)
      {
        int tid = 0;
#ifdef MIEM_HAVE_OPENMP
        tid = omp_get_thread_num();
#endif
        // Contiguous row blocks, one per thread: each row is converted once per block.
        const std::ptrdiff_t r0 = H * tid / nt, r1 = H * (tid + 1) / nt;
        pass1_rows(g, usable, p, smax, r0, r1, row_scratch_[tid], judge, labels, out.flags,
                   angle_out);
      }
    } else {
#pragma omp parallel for schedule(static) num_threads(nt) if (nt > 1)
      for (std::ptrdiff_t r = 0; r < H; ++r) {
        for (std::ptrdiff_t c = 0; c < W; ++c) {
          const std::ptrdiff_t i = r * W + c;
          if (!usable[i]) continue;
          std::uint8_t fl = 0;
          double an = kNaN;
          labels[i] = judge.judge(r, c, &fl, &an);
          if (out.flags) out.flags[i] = fl;
          if (angle_out) angle_out[i] = an;
        }
      }
    }
  };
  if (p.theta0_auto) {
    // Angle survey (independent of theta0), then theta0 = clip(180 - 6 sigma, 75, 170) with
    // sigma = median(180 - angle) / 0.6745.
    double* ang = out.angle_deg;
    if (ang == nullptr) {
      height_scratch_.resize(static_cast<std::size_t>(N));
      ang = height_scratch_.data();
    }
    eff_.theta0_deg = 75.0;
    pass1(ang);
    survey_.clear();
    for (std::ptrdiff_t i = 0; i < N; ++i)
      if (usable[i] && std::isfinite(ang[i])) survey_.push_back(180.0 - ang[i]);
    double theta0 = 75.0;
    if (!survey_.empty()) {
      const std::size_t m = survey_.size(), mid = m / 2;
      std::nth_element(survey_.begin(), survey_.begin() + mid, survey_.end());
      double med = survey_[mid];
      if (m % 2 == 0) med = 0.5 * (med + *std::max_element(survey_.begin(), survey_.begin() + mid));
      theta0 = std::clamp(180.0 - 6.0 * (med / 0.6745), 75.0, 170.0);
    }
    eff_.theta0_deg = theta0;
    for (std::ptrdiff_t i = 0; i < N; ++i)
      if (usable[i]) labels[i] = kNormal;
  }
  pass1(out.angle_deg);

  const CellJudge<T> judge(g, usable, p);  // after theta0 is final
  auto judge_cell = [&](std::ptrdiff_t i) {
    std::uint8_t fl = 0;
    double an = kNaN;
    labels[i] = judge.judge(i / W, i % W, &fl, &an);
    if (out.flags) out.flags[i] = fl;
    if (out.angle_deg) out.angle_deg[i] = an;
  };

  fresh_.clear();
  for (std::ptrdiff_t i = 0; i < N; ++i)
    if (labels[i] == kAbnormal) fresh_.push_back(i);
  int iterations = 1;

  // Later passes: only cells whose rays meet a newly removed cell.
  const std::ptrdiff_t reach = static_cast<std::ptrdiff_t>(smax) + p.max_gap +
                               (p.min_step >= 0.0 ? p.max_reach : 0);
  while (!fresh_.empty() && iterations < p.max_iterations) {
    for (std::int64_t i : fresh_) usable[i] = 0;
    candidates_.clear();
    for (std::int64_t i : fresh_) {
      const std::ptrdiff_t r = i / W, c = i % W;
      for (int k = 0; k < 4; ++k) {
        for (int sgn = -1; sgn <= 1; sgn += 2) {
          for (std::ptrdiff_t step = 1; step <= reach; ++step) {
            const std::ptrdiff_t rr = r + sgn * step * kDirRow[k];
            const std::ptrdiff_t cc = c + sgn * step * kDirCol[k];
            if (rr < 0 || rr >= H || cc < 0 || cc >= W) break;
            const std::ptrdiff_t q = rr * W + cc;
            if (usable[q] == 1) {  // usable and not yet a candidate (bit 1 marks those)
              usable[q] = 3;
              candidates_.push_back(q);
            }
          }
        }
      }
    }
    const std::ptrdiff_t nc = static_cast<std::ptrdiff_t>(candidates_.size());
    const int ntc = detail::thread_count(p.num_threads, nc, 4096);
#pragma omp parallel for schedule(static) num_threads(ntc) if (ntc > 1)
    for (std::ptrdiff_t j = 0; j < nc; ++j) judge_cell(candidates_[j]);
    fresh_.clear();
    for (std::int64_t q : candidates_) {
      usable[q] = 1;
      if (labels[q] == kAbnormal) fresh_.push_back(q);
    }
    ++iterations;
  }

  // Height passes (SPEC "Beyond the paper"): NORMAL cells, and EDGE cells of compact EDGE
  // groups, too far from their window plane; abstain near feature lines (long EDGE groups).
  if (p.height_abs > 0.0 || p.height_k > 0.0) {
    constexpr std::uint8_t kMark = 8, kCompact = 16, kSeenEdge = 32;
    for (int hp = 0; hp < p.max_iterations; ++hp) {
      // 8-connected EDGE groups; compact when the bounding box's longer side <= edge_extent.
      for (std::ptrdiff_t start = 0; start < N; ++start) {
        if (labels[start] != kEdge || (usable[start] & kSeenEdge)) continue;
        queue_.clear();
        queue_.push_back(start);
        usable[start] |= kSeenEdge;
        std::ptrdiff_t r0 = start / W, r1 = r0, c0 = start % W, c1 = c0;
        for (std::size_t head = 0; head < queue_.size(); ++head) {
          const std::ptrdiff_t i = queue_[head], r = i / W, c = i % W;
          r0 = std::min(r0, r), r1 = std::max(r1, r), c0 = std::min(c0, c), c1 = std::max(c1, c);
          for (std::ptrdiff_t dr = -1; dr <= 1; ++dr) {
            for (std::ptrdiff_t dc = -1; dc <= 1; ++dc) {
              const std::ptrdiff_t rr = r + dr, cc = c + dc;
              if (rr < 0 || rr >= H || cc < 0 || cc >= W) continue;
              const std::ptrdiff_t q = rr * W + cc;
              if (labels[q] == kEdge && !(usable[q] & kSeenEdge)) {
                usable[q] |= kSeenEdge;
                queue_.push_back(q);
              }
            }
          }
        }
        if (std::max(r1 - r0, c1 - c0) + 1 <= p.edge_extent) {
          for (std::int64_t i : queue_) usable[i] |= kCompact;
        }
      }
      window_fits(
          g, labels, p.window, p.num_threads, tile_scratch_,
          [&](std::ptrdiff_t r, std::ptrdiff_t c) {
            const std::ptrdiff_t i = r * W + c;
            return labels[i] == kNormal || (usable[i] & kCompact);
          },
          [&](std::ptrdiff_t r, std::ptrdiff_t c, const WindowFit& f) {
            if (!f.ok || f.edges > 0.0) return;  // designed features nearby: no plane model
            const double ah = std::abs(f.height);
            const double rms = std::sqrt(std::max(f.l0, 0.0) / f.n);
            const bool far = (p.height_abs > 0.0 && ah > p.height_abs) ||
                             (p.height_k > 0.0 && ah > p.height_k * rms &&
                              ah > 1e-9 * std::sqrt((f.l1 + f.l2) / f.n));
            if (far) usable[r * W + c] |= kMark;
          },
          [&](std::ptrdiff_t i) { return labels[i] == kEdge && !(usable[i] & kCompact); });
      ++iterations;
      std::ptrdiff_t added = 0;
      for (std::ptrdiff_t i = 0; i < N; ++i) {
        if (usable[i] & kMark) {
          usable[i] = 0;
          labels[i] = kAbnormal;
          ++added;
        } else {
          usable[i] &= static_cast<std::uint8_t>(~(kCompact | kSeenEdge));
        }
      }
      if (added == 0) break;
    }
  }

  DetectSummary summary;
  summary.iterations = iterations;
  summary.theta0_deg = p.theta0_deg;

  // The MIEM plane: finite, non-ABNORMAL cells; per-row moments merged in a fixed tree order.
  {
    std::vector<Moments> rows(static_cast<std::size_t>(H));
#pragma omp parallel for schedule(static) num_threads(nt) if (nt > 1)
    for (std::ptrdiff_t r = 0; r < H; ++r) {
      Moments m;
      Eigen::Vector3d sum = Eigen::Vector3d::Zero();
      for (std::ptrdiff_t c = 0; c < W; ++c) {
        const std::uint8_t l = labels[r * W + c];
        if (l == kNormal || l == kEdge) {
          sum += g(r, c);
          ++m.n;
        }
      }
      if (m.n > 0) {
        m.mean = sum / static_cast<double>(m.n);
        for (std::ptrdiff_t c = 0; c < W; ++c) {
          const std::uint8_t l = labels[r * W + c];
          if (l == kNormal || l == kEdge) {
            const Eigen::Vector3d q = g(r, c) - m.mean;
            m.scatter.noalias() += q * q.transpose();
          }
        }
      }
      rows[r] = m;
    }
    for (std::ptrdiff_t width = 1; width < H; width *= 2)
      for (std::ptrdiff_t b = 0; b + width < H; b += 2 * width) rows[b].merge(rows[b + width]);
    Plane plane;
    if (eigen_plane_from_moments(rows[0], &plane) == PlaneStatus::kOk) summary.plane = plane;
  }

  // Heights.
  double* height = out.height;
  if (height == nullptr) {
    height_scratch_.resize(static_cast<std::size_t>(N));
    height = height_scratch_.data();
  }
  const int half = p.window / 2;
  if (p.height_mode == HeightMode::kAll) {
    window_fits(
        g, labels, p.window, p.num_threads, tile_scratch_,
        [&](std::ptrdiff_t, std::ptrdiff_t) { return true; },
        [&](std::ptrdiff_t r, std::ptrdiff_t c, const WindowFit& f) {
          height[r * W + c] = (f.ok && labels[r * W + c] != kInvalid) ? f.height : kNaN;
        },
        [](std::ptrdiff_t) { return false; });
  } else {
#pragma omp parallel for schedule(static) num_threads(nt) if (nt > 1)
    for (std::ptrdiff_t r = 0; r < H; ++r) {
      for (std::ptrdiff_t c = 0; c < W; ++c) {
        const std::ptrdiff_t i = r * W + c;
        height[i] = kNaN;
        if (labels[i] != kAbnormal) continue;
        Plane pl;
        if (window_plane(g, labels, r, c, half, &pl) == PlaneStatus::kOk) {
          height[i] = pl.signed_distance(g(r, c));
        }
      }
    }
  }

  // Defects: 8-connected ABNORMAL components, found in row-major order.
  // Bit 2 of usable_ marks visited ABNORMAL cells (ABNORMAL cells are never usable).
  constexpr std::uint8_t kSeen = 4;
  for (std::ptrdiff_t start = 0; start < N; ++start) {
    if (labels[start] != kAbnormal || (usable[start] & kSeen)) continue;
    queue_.clear();
    queue_.push_back(start);
    usable[start] |= kSeen;
    bool touches_surface = false;
    for (std::size_t head = 0; head < queue_.size(); ++head) {
      const std::ptrdiff_t i = queue_[head], r = i / W, c = i % W;
      for (std::ptrdiff_t dr = -1; dr <= 1; ++dr) {
        for (std::ptrdiff_t dc = -1; dc <= 1; ++dc) {
          const std::ptrdiff_t rr = r + dr, cc = c + dc;
          if ((dr == 0 && dc == 0) || rr < 0 || rr >= H || cc < 0 || cc >= W) continue;
          const std::ptrdiff_t q = rr * W + cc;
          const std::uint8_t l = labels[q];
          if (l == kAbnormal) {
            if (!(usable[q] & kSeen)) {
              usable[q] |= kSeen;
              queue_.push_back(q);
            }
          } else if (l != kInvalid) {
            touches_surface = true;
          }
        }
      }
    }
    Defect d;
    d.indices.assign(queue_.begin(), queue_.end());
    std::sort(d.indices.begin(), d.indices.end());
    auto point_at = [&](std::int64_t i) -> Eigen::Vector3d { return g(i / W, i % W); };
    const std::int64_t peak_idx = detail::summarize_defect(d, height, point_at);
    if (peak_idx >= 0) {
      Plane pl;
      if (window_plane(g, labels, peak_idx / W, peak_idx % W, half, &pl) == PlaneStatus::kOk) {
        d.normal = pl.normal;
      }
    }
    detail::finish_defect(d, point_at, touches_surface);
    summary.defects.push_back(std::move(d));
  }
  detail::order_defects(summary.defects);
  return summary;
}

template <typename T>
DetectResult detect_organized(const GridView<T>& grid, const DetectParams& params) {
  OrganizedDetector det(params);
  DetectResult res;
  res.rows = grid.rows;
  res.cols = grid.cols;
  const std::size_t n = static_cast<std::size_t>(std::max<std::ptrdiff_t>(0, grid.rows * grid.cols));
  res.labels.resize(n);
  res.flags.resize(n);
  res.angle_deg.resize(n);
  res.height.resize(n);
  OrganizedOutput out{res.labels.data(), res.flags.data(), res.angle_deg.data(),
                      res.height.data()};
  res.summary = det.run(grid, out);
  return res;
}

template DetectSummary OrganizedDetector::run<float>(const GridView<float>&,
                                                     const OrganizedOutput&);
template DetectSummary OrganizedDetector::run<double>(const GridView<double>&,
                                                      const OrganizedOutput&);
template DetectResult detect_organized<float>(const GridView<float>&, const DetectParams&);
template DetectResult detect_organized<double>(const GridView<double>&, const DetectParams&);

}  // namespace miem
