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
        // Up to kChunk candidate cells of the row at a time: their 8 sub-window scatters are
        // solved together (smallest_eigenpairs, vectorised), then each cell is judged.
        constexpr int kChunk = 32, kCap = 8 * kChunk;
        double Mb[6 * kCap], Eb[6 * kCap], nnb[kCap], ceb[3 * kCap];
        std::uint8_t okb[kCap], redob[kCap], useb[kCap], emptyb[kCap];
        std::ptrdiff_t cols[kChunk];
        Side sd[8];
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
            for (int s = 0; s < 8; ++s) {
              const int e = j * 8 + s;
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
              double mm[kM];
              for (int q = 0; q < kM; ++q) mm[q] = a[q] - b[q] - cq[q] + d[q];
              const double n = mm[0], nn = std::max(n, 1.0);
              emptyb[e] = mm[10] >= n_min;
              useb[e] = n >= n_min;
              nnb[e] = nn;
              const double cx = mm[1] / nn, cy = mm[2] / nn, cz = mm[3] / nn;
              ceb[e] = cx, ceb[kCap + e] = cy, ceb[2 * kCap + e] = cz;
              Mb[e] = mm[4] - nn * cx * cx;             // M(0, 0)
              Mb[kCap + e] = mm[7] - nn * cy * cy;      // M(1, 1)
              Mb[2 * kCap + e] = mm[9] - nn * cz * cz;  // M(2, 2)
              Mb[3 * kCap + e] = mm[5] - nn * cx * cy;  // M(0, 1)
              Mb[4 * kCap + e] = mm[8] - nn * cy * cz;  // M(1, 2)
              Mb[5 * kCap + e] = mm[6] - nn * cx * cz;  // M(0, 2)
            }
          }
          smallest_eigenpairs(8 * m, kCap, Mb, Eb, okb, redob);
          for (int j = 0; j < m; ++j) {
            const std::ptrdiff_t i = rr * W + cols[j];
            const Eigen::Vector3d pt = g(rr, cols[j]) - o;
            double best = std::numeric_limits<double>::infinity();
            for (int s = 0; s < 8; ++s) {
              const int e = j * 8 + s;
              Side& x = sd[s];
              x.empty = emptyb[e] != 0;
              x.centroid = Eigen::Vector3d(ceb[e], ceb[kCap + e], ceb[2 * kCap + e]);
              x.valid = false;
              if (!useb[e]) continue;
              double l0 = Eb[e], l1 = Eb[kCap + e], l2 = Eb[2 * kCap + e];
              Eigen::Vector3d nv(Eb[3 * kCap + e], Eb[4 * kCap + e], Eb[5 * kCap + e]);
              bool solved = okb[e] != 0;
              if (redob[e]) {  // Newton needs more steps: the scalar routine, to the end
                Eigen::Matrix3d M;
                M(0, 0) = Mb[e];
                M(1, 1) = Mb[kCap + e];
                M(2, 2) = Mb[2 * kCap + e];
                M(0, 1) = M(1, 0) = Mb[3 * kCap + e];
                M(1, 2) = M(2, 1) = Mb[4 * kCap + e];
                M(0, 2) = M(2, 0) = Mb[5 * kCap + e];
                solved = smallest_eigenpair(M, &l0, &l1, &l2, &nv);
              }
              if (!solved) continue;
              if (!(l2 > 0.0) || l1 <= kRankTol * l2) continue;
              const double nn = nnb[e];
              x.valid = true;
              x.normal = orient_normal(nv);  // SPEC "Plane fit" orientation
              x.h = dot3(pt - x.centroid, x.normal);
              x.rms = std::sqrt(std::max(l0, 0.0) / nn);
              x.tol = std::max(k * x.rms, kRoundOff * std::sqrt((l1 + l2) / nn));
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
