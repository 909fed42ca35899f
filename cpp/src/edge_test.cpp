// Edge test (SPEC "Edge test"). Per pass: integral images of the support (NORMAL) moments, then
// for every candidate 8 one-sided sub-window planes from four corner reads each. Cells are
// judged against the pass's fixed support (Jacobi), so rows run in parallel with identical
// results for any thread count. The arithmetic follows miem.reference.edge_test step by step.
#include "edge_test.hpp"

#include <algorithm>
#include <cmath>
#include <limits>

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "judge.hpp"
#include "miem/organized.hpp"
#include "miem/plane.hpp"
#include "parallel.hpp"
#include "plane_math.hpp"

namespace miem::detail {

namespace {

constexpr int kM = 11;  // n, x, y, z, xx, xy, xz, yy, yz, zz (support), INVALID count
constexpr double kCleanRatio = 2.0;
constexpr double kRankTol = 1e-12;
constexpr double kRoundOff = 1e-9;  // tolerance floor: times sqrt((l1 + l2) / n), as the height test
// (row_lo, row_hi, col_lo, col_hi) in units: -2 = -r, -1 = -1, 1 = 1, 2 = r.
constexpr int kSides[8][4] = {{-2, 2, -2, -1}, {-2, 2, 1, 2},  {-2, -1, -2, 2}, {1, 2, -2, 2},
                              {-2, -1, -2, -1}, {-2, -1, 1, 2}, {1, 2, -2, -1}, {1, 2, 1, 2}};
constexpr int kOpposite[4][2] = {{0, 1}, {2, 3}, {4, 7}, {5, 6}};

inline std::ptrdiff_t offset(int code, std::ptrdiff_t r) {
  return code == -2 ? -r : (code == 2 ? r : code);
}

struct Side {
  bool valid = false, empty = false;
  double h = 0.0, rms = 0.0, tol = 0.0;  // tol: max(k rms, the round-off floor)
  Eigen::Vector3d normal, centroid;
};

#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__linux__)
#define MIEM_EDGE_CLONES __attribute__((target_clones("avx2", "default")))
#else
#define MIEM_EDGE_CLONES
#endif

// Sub-window moments (SoA, moment q at mm + q * cap) to what the planes need: nn = max(n, 1),
// the centroid, the centred scatter (a, b, c, d, e, f as smallest_eigenpairs reads it), whether
// the side has enough support (use) and whether it is empty (INVALID count). Vectorised.
MIEM_EDGE_CLONES void side_moments(std::ptrdiff_t m, std::ptrdiff_t cap, double n_min,
                                   const double* __restrict mm, double* __restrict nnb,
                                   double* __restrict ceb, double* __restrict Mb,
                                   std::uint8_t* __restrict useb,
                                   std::uint8_t* __restrict emptyb) {
#pragma GCC ivdep
  for (std::ptrdiff_t e = 0; e < m; ++e) {
    const double n = mm[e], nn = n < 1.0 ? 1.0 : n;  // std::max(n, 1.0)
    emptyb[e] = mm[10 * cap + e] >= n_min;
    useb[e] = n >= n_min;
    nnb[e] = nn;
    const double cx = mm[cap + e] / nn, cy = mm[2 * cap + e] / nn, cz = mm[3 * cap + e] / nn;
    ceb[e] = cx, ceb[cap + e] = cy, ceb[2 * cap + e] = cz;
    Mb[e] = mm[4 * cap + e] - nn * cx * cx;            // M(0, 0)
    Mb[cap + e] = mm[7 * cap + e] - nn * cy * cy;      // M(1, 1)
    Mb[2 * cap + e] = mm[9 * cap + e] - nn * cz * cz;  // M(2, 2)
    Mb[3 * cap + e] = mm[5 * cap + e] - nn * cx * cy;  // M(0, 1)
    Mb[4 * cap + e] = mm[8 * cap + e] - nn * cy * cz;  // M(1, 2)
    Mb[5 * cap + e] = mm[6 * cap + e] - nn * cx * cz;  // M(0, 2)
  }
}

// One side's plane from its eigenpair (l0, l1, l2, unit nv): valid, oriented normal (SPEC "Plane
// fit"), the cell's height h over it, rms and tolerance. Shared by the vector loop and the
// scalar redo so that both give the same bits.
inline __attribute__((always_inline)) void side_plane(
    bool use, bool solved, double l0, double l1, double l2, double nx, double ny, double nz,
    double nn, double cx, double cy, double cz, double px, double py, double pz, double k,
    std::uint8_t& valid, double& h, double& rms, double& tol, double& ox, double& oy,
    double& oz) {
  valid = use & solved & (l2 > 0.0) & !(l1 <= kRankTol * l2);
  const double sg = nz != 0.0 ? (nz > 0.0 ? 1.0 : -1.0)
                              : (nx != 0.0 ? (nx > 0.0 ? 1.0 : -1.0) : (ny < 0.0 ? -1.0 : 1.0));
  ox = nx * sg, oy = ny * sg, oz = nz * sg;  // orient_normal
  h = ((px - cx) * ox + (py - cy) * oy) + (pz - cz) * oz;  // dot3(pt - centroid, normal)
  rms = std::sqrt((l0 < 0.0 ? 0.0 : l0) / nn);  // std::max(l0, 0.0)
  const double floor = kRoundOff * std::sqrt((l1 + l2) / nn), kr = k * rms;
  tol = kr < floor ? floor : kr;  // std::max(k rms, floor)
}

// side_plane for m sides (SoA; P: the cell of each side, relative to the origin). Vectorised.
MIEM_EDGE_CLONES void side_planes(std::ptrdiff_t m, std::ptrdiff_t cap, double k,
                                  const std::uint8_t* __restrict useb,
                                  const std::uint8_t* __restrict okb,
                                  const double* __restrict Eb, const double* __restrict nnb,
                                  const double* __restrict ceb, const double* __restrict P,
                                  std::uint8_t* __restrict validb, double* __restrict F) {
#pragma GCC ivdep
  for (std::ptrdiff_t e = 0; e < m; ++e) {
    side_plane(useb[e] != 0, okb[e] != 0, Eb[e], Eb[cap + e], Eb[2 * cap + e], Eb[3 * cap + e],
               Eb[4 * cap + e], Eb[5 * cap + e], nnb[e], ceb[e], ceb[cap + e], ceb[2 * cap + e],
               P[e], P[cap + e], P[2 * cap + e], k, validb[e], F[e], F[cap + e], F[2 * cap + e],
               F[3 * cap + e], F[4 * cap + e], F[5 * cap + e]);
  }
}

// The passes on `g` (the grid or its transposed view) from the origin `o`. The integral images
// are kept as a ring of R rows: a band of B judged rows and r + 1 rows either side of it.
template <typename T>
int run_passes(const GridView<T>& g, std::uint8_t* labels, const Eigen::Vector3d& o, int window,
               double k, int max_iterations, int num_threads, std::vector<double>& scratch) {
  const std::ptrdiff_t H = g.rows, W = g.cols, N = H * W, r = window / 2;
  const double n_min = static_cast<double>(std::max<std::ptrdiff_t>(3, (r * r) / 2));
  const std::ptrdiff_t W1 = W + 1;
  const std::ptrdiff_t B = std::max<std::ptrdiff_t>(64, 2 * r + 2);
  const std::ptrdiff_t R = std::min(H + 1, B + 2 * r + 2);
  const std::size_t need = static_cast<std::size_t>(R * W1 * kM + W * kM);
  if (scratch.size() < need) scratch.resize(need);
  double* const S = scratch.data();
  double* const col = S + R * W1 * kM;
  const auto srow = [S, R, W1](std::ptrdiff_t s) { return S + (s % R) * W1 * kM; };
  std::vector<std::uint8_t> todo(static_cast<std::size_t>(N)), mark(static_cast<std::size_t>(N));
  for (std::ptrdiff_t i = 0; i < N; ++i) todo[i] = labels[i] == kNormal || labels[i] == kEdge;
  const int nt = thread_count(num_threads, N);
  int passes = 0;
  for (int it = 0; it < max_iterations; ++it) {
    ++passes;
    // integral images: running sums down each column, then along each row (NumPy's order);
    // S row s (0..H) holds the sums over grid rows < s, computed in order as the bands need them
    std::fill(col, col + W * kM, 0.0);
    std::ptrdiff_t next = 0;
    const auto compute_to = [&](std::ptrdiff_t last) {
      for (; next <= last; ++next) {
        double* out = srow(next);
        std::fill(out, out + (next == 0 ? W1 : 1) * kM, 0.0);
        if (next == 0) continue;
        const std::ptrdiff_t rr = next - 1;
        for (std::ptrdiff_t cc = 0; cc < W; ++cc) {
          const std::uint8_t l = labels[rr * W + cc];
          double t[kM] = {0.0};
          if (l == kNormal) {
            const Eigen::Vector3d p = g(rr, cc) - o;
            t[0] = 1.0;
            t[1] = p.x(), t[2] = p.y(), t[3] = p.z();
            t[4] = p.x() * p.x(), t[5] = p.x() * p.y(), t[6] = p.x() * p.z();
            t[7] = p.y() * p.y(), t[8] = p.y() * p.z(), t[9] = p.z() * p.z();
          }
          t[10] = l == kInvalid ? 1.0 : 0.0;
          double* cs = col + cc * kM;
          const double* left = out + cc * kM;
          double* cur = out + (cc + 1) * kM;
          for (int q = 0; q < kM; ++q) {
            cs[q] += t[q];
            cur[q] = left[q] + cs[q];
          }
        }
      }
    };
    for (std::ptrdiff_t b0 = 0; b0 < H; b0 += B) {
      const std::ptrdiff_t b1 = std::min(H, b0 + B);
      compute_to(std::min(H, b1 + r));  // the band reads S rows max(0, b0 - r) .. b1 + r
#pragma omp parallel for schedule(dynamic, 8) num_threads(nt) if (nt > 1)
      for (std::ptrdiff_t rr = b0; rr < b1; ++rr) {
        // Up to kChunk candidate cells of the row at a time, all as SoA over their 8 sides:
        // the sub-window sums (corner reads), then moments, eigenpairs and planes in vectorised
        // loops; each cell is judged from those.
        constexpr int kChunk = 16, kCap = 8 * kChunk;
        double mm[kM * kCap], Mb[6 * kCap], Eb[6 * kCap], nnb[kCap], ceb[3 * kCap];
        double F[6 * kCap], P[3 * kCap];  // F: h, rms, tol, oriented normal; P: the cells
        std::uint8_t okb[kCap], redob[kCap], useb[kCap], emptyb[kCap], validb[kCap];
        std::ptrdiff_t cols[kChunk];
        for (std::ptrdiff_t cc = 0; cc < W;) {
          int m = 0;
          for (; cc < W && m < kChunk; ++cc) {
            const std::ptrdiff_t i = rr * W + cc;
            mark[i] = 0;
            if (todo[i] && (labels[i] == kNormal || labels[i] == kEdge)) cols[m++] = cc;
          }
          if (m == 0) continue;
          for (int j = 0; j < m; ++j) {
            const std::ptrdiff_t c = cols[j];
            const Eigen::Vector3d pt = g(rr, c) - o;
            for (int s = 0; s < 8; ++s) {
              const int e = j * 8 + s;
              P[e] = pt.x(), P[kCap + e] = pt.y(), P[2 * kCap + e] = pt.z();
              const std::ptrdiff_t r0 =
                  std::clamp<std::ptrdiff_t>(rr + offset(kSides[s][0], r), 0, H);
              const std::ptrdiff_t r1 =
                  std::clamp<std::ptrdiff_t>(rr + offset(kSides[s][1], r) + 1, 0, H);
              const std::ptrdiff_t c0 =
                  std::clamp<std::ptrdiff_t>(c + offset(kSides[s][2], r), 0, W);
              const std::ptrdiff_t c1 =
                  std::clamp<std::ptrdiff_t>(c + offset(kSides[s][3], r) + 1, 0, W);
              const double* top = srow(r0);
              const double* bottom = srow(r1);
              const double* a = bottom + c1 * kM;
              const double* b = top + c1 * kM;
              const double* cq = bottom + c0 * kM;
              const double* d = top + c0 * kM;
              for (int q = 0; q < kM; ++q) mm[q * kCap + e] = a[q] - b[q] - cq[q] + d[q];
            }
          }
          const int ms = 8 * m;
          side_moments(ms, kCap, n_min, mm, nnb, ceb, Mb, useb, emptyb);
          smallest_eigenpairs(ms, kCap, Mb, Eb, okb, redob);
          side_planes(ms, kCap, k, useb, okb, Eb, nnb, ceb, P, validb, F);
          for (int e = 0; e < ms; ++e) {
            if (!redob[e] || !useb[e]) continue;  // Newton needs more steps: the scalar routine
            Eigen::Matrix3d M;
            M(0, 0) = Mb[e];
            M(1, 1) = Mb[kCap + e];
            M(2, 2) = Mb[2 * kCap + e];
            M(0, 1) = M(1, 0) = Mb[3 * kCap + e];
            M(1, 2) = M(2, 1) = Mb[4 * kCap + e];
            M(0, 2) = M(2, 0) = Mb[5 * kCap + e];
            double l0 = 0.0, l1 = 0.0, l2 = 0.0;
            Eigen::Vector3d nv = Eigen::Vector3d::Zero();
            const bool solved = smallest_eigenpair(M, &l0, &l1, &l2, &nv);
            side_plane(true, solved, l0, l1, l2, nv.x(), nv.y(), nv.z(), nnb[e], ceb[e],
                       ceb[kCap + e], ceb[2 * kCap + e], P[e], P[kCap + e], P[2 * kCap + e], k,
                       validb[e], F[e], F[kCap + e], F[2 * kCap + e], F[3 * kCap + e],
                       F[4 * kCap + e], F[5 * kCap + e]);
          }
          for (int j = 0; j < m; ++j) {
            const std::ptrdiff_t i = rr * W + cols[j];
            Side sd[8];
            double best = std::numeric_limits<double>::infinity();
            for (int s = 0; s < 8; ++s) {
              const int e = j * 8 + s;
              Side& x = sd[s];
              x.empty = emptyb[e] != 0;
              x.centroid = Eigen::Vector3d(ceb[e], ceb[kCap + e], ceb[2 * kCap + e]);
              x.valid = validb[e] != 0;
              if (!x.valid) continue;
              x.h = F[e];
              x.rms = F[kCap + e];
              x.tol = F[2 * kCap + e];
              x.normal = Eigen::Vector3d(F[3 * kCap + e], F[4 * kCap + e], F[5 * kCap + e]);
              best = std::min(best, x.rms);
            }
            bool fits = false, proud = false;
            for (int s = 0; s < 8; ++s) {
              const Side& x = sd[s];
              if (x.valid && x.rms <= kCleanRatio * best && !(std::abs(x.h) > x.tol)) fits = true;
            }
            if (fits) continue;
            for (const auto& pair : kOpposite) {
              for (int flip = 0; flip < 2; ++flip) {
                const Side& x = sd[pair[flip]];
                const Side& y = sd[pair[1 - flip]];
                if (!x.valid || !(x.rms <= kCleanRatio * best) || !(x.h > x.tol)) continue;
                const bool falls =
                    y.empty || (y.valid && dot3(x.normal, y.centroid - x.centroid) < -x.tol);
                if (falls) proud = true;
              }
            }
            mark[i] = proud ? 1 : 0;
          }
        }
      }
    }
    std::ptrdiff_t added = 0;
    std::fill(todo.begin(), todo.end(), std::uint8_t{0});
    for (std::ptrdiff_t i = 0; i < N; ++i) {
      if (!mark[i]) continue;
      labels[i] = kAbnormal;
      ++added;
      // only cells with a new ABNORMAL cell in their window can change at the next pass
      const std::ptrdiff_t rr = i / W, cc = i % W;
      for (std::ptrdiff_t a = std::max<std::ptrdiff_t>(0, rr - r); a <= std::min(H - 1, rr + r);
           ++a) {
        for (std::ptrdiff_t b = std::max<std::ptrdiff_t>(0, cc - r); b <= std::min(W - 1, cc + r);
             ++b) {
          todo[a * W + b] = 1;
        }
      }
    }
    if (added == 0) break;
  }
  return passes;
}

}  // namespace

template <typename T>
int edge_passes(const GridView<T>& g, std::uint8_t* labels, int window, double k,
                int max_iterations, int num_threads, std::vector<double>& scratch) {
  const std::ptrdiff_t H = g.rows, W = g.cols, N = H * W;
  // origin: the mean of the support cells at the start (row-major sum), fixed for every pass
  Eigen::Vector3d o = Eigen::Vector3d::Zero();
  std::ptrdiff_t n_support = 0;
  for (std::ptrdiff_t i = 0; i < N; ++i) {
    if (labels[i] == kNormal) {
      o += g(i / W, i % W);
      ++n_support;
    }
  }
  if (n_support > 0) o /= static_cast<double>(n_support);
  if (W <= H) return run_passes(g, labels, o, window, k, max_iterations, num_threads, scratch);
  // wider than tall: on the transposed grid (the ring of integral-image rows then spans the
  // shorter side; the sub-windows are the same set, SPEC step 3)
  const GridView<T> t{g.data, W, H, g.col_stride, g.row_stride, g.coord_stride};
  std::vector<std::uint8_t> lt(static_cast<std::size_t>(N));
  for (std::ptrdiff_t i = 0; i < H; ++i)
    for (std::ptrdiff_t j = 0; j < W; ++j) lt[j * H + i] = labels[i * W + j];
  const int passes = run_passes(t, lt.data(), o, window, k, max_iterations, num_threads, scratch);
  for (std::ptrdiff_t i = 0; i < H; ++i)
    for (std::ptrdiff_t j = 0; j < W; ++j) labels[i * W + j] = lt[j * H + i];
  return passes;
}

template int edge_passes<float>(const GridView<float>&, std::uint8_t*, int, double, int, int,
                                std::vector<double>&);
template int edge_passes<double>(const GridView<double>&, std::uint8_t*, int, double, int, int,
                                 std::vector<double>&);

}  // namespace miem::detail
