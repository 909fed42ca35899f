// Edge test (SPEC "Edge test"). Per pass and per 64 x 128-cell tile: integral images of the
// support (NORMAL) moments over the tile and the r cells around it, relative to the tile's first
// finite cell, then for every candidate 8 one-sided sub-window planes from four corner reads
// each. Cells are judged against the pass's fixed support (Jacobi), so tiles run in parallel
// with identical results for any thread count. The formulas are miem.reference.edge_test's.
#include "edge_test.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "byte_scan.hpp"
#include "edge_quiet.hpp"
#include "edge_verdict.hpp"
#include "judge.hpp"
#include "miem/organized.hpp"
#include "miem/plane.hpp"
#include "parallel.hpp"
#include "plane_math.hpp"
#include "stages.hpp"
#include "vector_clones.hpp"
#include "window_fits.hpp"

namespace miem::detail {

namespace {

constexpr int kM = kEdgeMoments;
constexpr double kRankTol = 1e-12;
constexpr double kLineTol = 1e-6;  // support on a line in (x, y): det <= this * trace^2
constexpr double kRoundOff = 1e-9;  // tolerance floor: times sqrt((l1 + l2) / n), as the height test
// (row_lo, row_hi, col_lo, col_hi) in units: -2 = -r, -1 = -1, 1 = 1, 2 = r.
constexpr int kSides[8][4] = {{-2, 2, -2, -1}, {-2, 2, 1, 2},  {-2, -1, -2, 2}, {1, 2, -2, 2},
                              {-2, -1, -2, -1}, {-2, -1, 1, 2}, {1, 2, -2, -1}, {1, 2, 1, 2}};
constexpr int kOpposite[8] = {1, 0, 3, 2, 7, 6, 5, 4};  // left/right, up/down, diagonals

inline std::ptrdiff_t offset(int code, std::ptrdiff_t r) {
  return code == -2 ? -r : (code == 2 ? r : code);
}

using Side = EdgeSide;

// One side's moments (n and the sums of moment q at mm[q * cap]) to what the planes need:
// nn = max(n, 1), the centroid, the centred scatter (a, b, c, d, e, f as smallest_eigenpairs_long
// reads it: M(0, 0), M(1, 1), M(2, 2), M(0, 1), M(1, 2), M(0, 2)) and whether the side has
// enough support (use). Shared by side_moments and side_lows so that both give the same bits.
inline __attribute__((always_inline)) void side_moment(const double* mm, std::ptrdiff_t cap,
                                                       double n_min, double& nn, double& cx,
                                                       double& cy, double& cz, double* M,
                                                       bool& use) {
  const double n = mm[0];
  nn = n < 1.0 ? 1.0 : n;  // std::max(n, 1.0)
  cx = mm[cap] / nn, cy = mm[2 * cap] / nn, cz = mm[3 * cap] / nn;
  const double a = mm[4 * cap] - nn * cx * cx, b = mm[7 * cap] - nn * cy * cy;
  const double d = mm[5 * cap] - nn * cx * cy;
  // support on a line in (x, y): no plane (SPEC step 3)
  use = (n >= n_min) & (a * b - d * d > kLineTol * ((a + b) * (a + b)));
  M[0] = a, M[1] = b, M[2] = mm[9 * cap] - nn * cz * cz, M[3] = d;
  M[4] = mm[8 * cap] - nn * cy * cz, M[5] = mm[6 * cap] - nn * cx * cz;
}

// Sub-window moments (SoA, moment q at mm + q * cap) to what the planes need (side_moment),
// and whether the side is empty: emptyb its INVALID count when that is at least n_min, else
// 0. Vectorised.
MIEM_CLONES void side_moments(std::ptrdiff_t m, std::ptrdiff_t cap, double n_min,
                              const double* __restrict mm, double* __restrict nnb,
                              double* __restrict ceb, double* __restrict Mb,
                              double* __restrict useb, double* __restrict emptyb) {
#pragma GCC ivdep
  for (std::ptrdiff_t e = 0; e < m; ++e) {
    double nn, cx, cy, cz, M[6];
    bool use;
    side_moment(mm + e, cap, n_min, nn, cx, cy, cz, M, use);
    emptyb[e] = mm[10 * cap + e] >= n_min ? mm[10 * cap + e] : 0.0;
    nnb[e] = nn;
    ceb[e] = cx, ceb[cap + e] = cy, ceb[2 * cap + e] = cz;
    useb[e] = use ? 1.0 : 0.0;
    for (int q = 0; q < 6; ++q) Mb[q * cap + e] = M[q];
  }
}

// A lower bound of each side's rms^2 = l0 / nn without solving, exact in floating point: the
// solver's Newton iteration starts at 0 with the step to det / c1 (q(0) = -det, q'(0) = c1, the
// same expressions as eigen_lane) and then only rises, so its l0 >= fl(det / c1) bit for bit
// (and l0 >= 0); division and sqrt round monotonically. Sides without support get +inf (never
// valid). Straight from the sub-window sums (side_moment), storing nothing else: most cells
// solve one side only, whose moments side_moments gives afterwards. Vectorised.
MIEM_CLONES void side_lows(std::ptrdiff_t m, std::ptrdiff_t cap, double n_min,
                           const double* __restrict mm, double* __restrict lowb) {
#pragma GCC ivdep
  for (std::ptrdiff_t i = 0; i < m; ++i) {
    double nn, cx, cy, cz, M[6];
    bool use;
    side_moment(mm + i, cap, n_min, nn, cx, cy, cz, M, use);
    const double a = M[0], b = M[1], c = M[2], d = M[3], e = M[4], f = M[5];
    const double tr = a + b + c;
    const double c1 = (a * b + b * c + a * c) - (d * d + e * e + f * f);
    const double det = a * b * c + 2.0 * d * e * f - a * e * e - b * f * f - c * d * d;
    const double x1 = (tr > 0.0 && c1 > 0.0 && det > 0.0) ? det / (c1 > 0.0 ? c1 : 1.0) : 0.0;
    // a side that may be exactly flat (l0 <= kEdgeFlatL0 l2 needs x1 <= l0 <= kEdgeFlatL0 tr,
    // as l2 <= tr; twice that for the solver's rounding of l2) may have rms 0: bound 0
    const double low = x1 > 2.0 * kEdgeFlatL0 * tr ? x1 / nn : 0.0;
    lowb[i] = use ? low : std::numeric_limits<double>::infinity();
  }
}

// One side's plane from its eigenpair (l0, l1, l2, unit nv): valid, oriented normal (SPEC "Plane
// fit"), the cell's height h over it, rms and tolerance. Shared by the vector loop and the
// scalar redo so that both give the same bits.
inline __attribute__((always_inline)) void side_plane(
    bool use, bool solved, double l0, double l1, double l2, double nx, double ny, double nz,
    double nn, double cx, double cy, double cz, double px, double py, double pz, double k,
    double floor_p, double& valid, double& h, double& rms, double& tol, double& ox, double& oy,
    double& oz) {
  valid = use & solved & (l2 > 0.0) & !(l1 <= kRankTol * l2) ? 1.0 : 0.0;
  const double sg = orient_sign(nx, ny, nz);
  ox = nx * sg, oy = ny * sg, oz = nz * sg;  // orient_normal
  h = ((px - cx) * ox + (py - cy) * oy) + (pz - cz) * oz;  // dot3(pt - centroid, normal)
  rms = edge_side_rms(l0, l2, nn);
  const double round_off = kRoundOff * std::sqrt((l1 + l2) / nn), kr = k * rms;
  const double floor = round_off < floor_p ? floor_p : round_off;
  tol = kr < floor ? floor : kr;  // std::max(k rms, round-off floor, the cell's floor)
}

// The floor of cell p's tolerance (p as given, not relative to the origin): et.floor, or its
// precision floor et.prec x max(|x|, |y|, |z|) when larger (SPEC "Edge test" step 3).
inline double cell_floor(const Eigen::Vector3d& p, EdgeTol et) {
  const double pf = et.prec * p.cwiseAbs().maxCoeff();
  return pf > et.floor ? pf : et.floor;
}

// side_plane for m sides (SoA; P: the cell of each side, relative to the origin, FL its
// floor, cell_floor). Vectorised.
MIEM_CLONES void side_planes(std::ptrdiff_t m, std::ptrdiff_t cap, double k,
                             const double* __restrict useb, const double* __restrict okb,
                             const double* __restrict Eb, const double* __restrict nnb,
                             const double* __restrict ceb, const double* __restrict P,
                             const double* __restrict FL, double* __restrict validb,
                             double* __restrict F) {
#pragma GCC ivdep
  for (std::ptrdiff_t e = 0; e < m; ++e) {
    side_plane(useb[e] != 0.0, okb[e] != 0.0, Eb[e], Eb[cap + e], Eb[2 * cap + e],
               Eb[3 * cap + e], Eb[4 * cap + e], Eb[5 * cap + e], nnb[e], ceb[e], ceb[cap + e],
               ceb[2 * cap + e], P[e], P[cap + e], P[2 * cap + e], k, FL[e], validb[e], F[e],
               F[cap + e], F[2 * cap + e], F[3 * cap + e], F[4 * cap + e], F[5 * cap + e]);
  }
}

// For each of m cells (side s's bound of cell j at low[s][j]): the side with the smallest
// bound, the first among equal ones (as `if (low[s] < low[best]) best = s` in side order), and
// that bound. Branch-free and vectorised over the cells: which side wins is data-dependent, so
// a branch per side mispredicts.
MIEM_CLONES void best_sides(int m, const double* const* low, std::int64_t* __restrict sb,
                            double* __restrict low1) {
  const double *__restrict l0 = low[0], *__restrict l1 = low[1], *__restrict l2 = low[2];
  const double *__restrict l3 = low[3], *__restrict l4 = low[4], *__restrict l5 = low[5];
  const double *__restrict l6 = low[6], *__restrict l7 = low[7];
#pragma GCC ivdep
  for (int j = 0; j < m; ++j) {
    const double v8[8] = {l0[j], l1[j], l2[j], l3[j], l4[j], l5[j], l6[j], l7[j]};
    double best = v8[0];
    std::int64_t b = 0;
    for (std::int64_t s = 1; s < 8; ++s) {
      const double v = v8[s];
      const bool lt = v < best;
      best = lt ? v : best;
      b = lt ? s : b;
    }
    low1[j] = best, sb[j] = b;
  }
}

// The shortcut's test for m cells (edge_judge_row): the solved side (its plane F, `cap` apart:
// h, rms, tol, normal) is clean, rms <= kEdgeCleanRatio x sqrt(the smallest bound low1) <=
// 2 best, valid, not steep, not empty (an empty side: hanging?), solved without the scalar
// redo, and the cell fits it: fits = 1, else 0. Vectorised.
MIEM_CLONES void fits_clean_side(int m, std::ptrdiff_t cap, const double* __restrict redo,
                                 const double* __restrict valid, const double* __restrict empty,
                                 const double* __restrict low1, const double* __restrict F,
                                 double* __restrict fits) {
#pragma GCC ivdep
  for (int j = 0; j < m; ++j) {
    const bool clean = F[cap + j] <= kEdgeCleanRatio * std::sqrt(low1[j]);
    const bool ok = (redo[j] == 0.0) & (valid[j] != 0.0) & clean & (empty[j] == 0.0) &
                    !(F[5 * cap + j] < kEdgeSteepCos) & !(std::abs(F[j]) > F[2 * cap + j]);
    fits[j] = ok ? 1.0 : 0.0;
  }
}

// Rectangle sums of one side for m consecutive cells, all kM moment planes (`plane` apart in
// the images, `cap` apart in out): out[j] = a[j] - b[j] - c[j] + d[j], the corner formula of the
// general path. Vectorised.
MIEM_CLONES void rect_sums(int m, std::ptrdiff_t plane, std::ptrdiff_t cap, const double* a,
                           const double* b, const double* c, const double* d,
                           double* __restrict out) {
  for (int q = 0; q < kM; ++q) {
    const double *__restrict aq = a + q * plane, *__restrict bq = b + q * plane;
    const double *__restrict cq = c + q * plane, *__restrict dq = d + q * plane;
    double* __restrict oq = out + q * cap;
    for (int j = 0; j < m; ++j) oq[j] = aq[j] - bq[j] - cq[j] + dq[j];
  }
}

// SPEC "Edge test" step 6, fins: is candidate (rr, cc) thin material standing proud of the
// ground (NORMAL or EDGE cells at the start of the pass) on both sides along one of the four
// directions, taller than those two lowest ground cells (within r cells) are apart, at least
// two cells wide at half its height and going on both ways along the perpendicular direction
// (material: any cell with a return, ABNORMAL ones too)? The formulas are
// miem.reference._fins'. Called only for cells that fit no clean side (a fin that fits one
// stays as it is), so flat surface, which the shortcut below settles, never pays for it.
template <typename T>
bool is_fin(const GridView<T>& g, const std::uint8_t* labels, std::ptrdiff_t rr,
            std::ptrdiff_t cc, std::ptrdiff_t r) {
  constexpr int kDirs[4][2] = {{1, 0}, {0, 1}, {1, 1}, {1, -1}};
  const std::ptrdiff_t H = g.rows, W = g.cols;
  const auto zat = [&](std::ptrdiff_t a, std::ptrdiff_t b) {
    return static_cast<double>(g.data[a * g.row_stride + b * g.col_stride + 2 * g.coord_stride]);
  };
  const double zp = zat(rr, cc);
  for (const auto& d : kDirs) {
    double zlow[2];
    std::ptrdiff_t jlow[2] = {0, 0};
    bool any = true;
    for (int side = 0; side < 2 && any; ++side) {
      const std::ptrdiff_t sg = side == 0 ? -1 : 1;
      // Steps 1..jmax stay inside the grid (the ones beyond leave it for good); the scan is
      // branch-free: every in-grid z is read, and only ground cells can take the minimum.
      const std::ptrdiff_t sa = sg * d[0], sb = sg * d[1];
      std::ptrdiff_t jmax = r;
      if (sa != 0) jmax = std::min(jmax, sa > 0 ? H - 1 - rr : rr);
      if (sb != 0) jmax = std::min(jmax, sb > 0 ? W - 1 - cc : cc);
      const std::uint8_t* const lq = labels + rr * W + cc;
      const T* const zq0 = g.data + rr * g.row_stride + cc * g.col_stride + 2 * g.coord_stride;
      const std::ptrdiff_t ls = sa * W + sb, zs = sa * g.row_stride + sb * g.col_stride;
      double zmin = std::numeric_limits<double>::infinity();
      std::ptrdiff_t jl = 0;
      for (std::ptrdiff_t j = 1; j <= jmax; ++j) {  // outward: among equal minima the nearest
        const std::uint8_t lab = lq[j * ls];
        const double zq = static_cast<double>(zq0[j * zs]);
        const bool lt = ((lab == kNormal) | (lab == kEdge)) & (zq < zmin);
        zmin = lt ? zq : zmin;
        jl = lt ? j : jl;
      }
      jlow[side] = sg * jl;
      any = zmin < zp;  // else the height is not positive
      zlow[side] = zmin;
    }
    if (!any) continue;
    const double base = std::max(zlow[0], zlow[1]), height = zp - base;
    const Eigen::Vector3d qa = g(rr + jlow[0] * d[0], cc + jlow[0] * d[1]);
    const Eigen::Vector3d qb = g(rr + jlow[1] * d[0], cc + jlow[1] * d[1]);
    const double dx = qa.x() - qb.x(), dy = qa.y() - qb.y();
    if (!(height > 0.0) || !(height * height > dx * dx + dy * dy)) continue;
    const double half = base + 0.5 * height;
    const auto above = [&](std::ptrdiff_t a, std::ptrdiff_t b) {  // material (not INVALID)
      return a >= 0 && a < H && b >= 0 && b < W && labels[a * W + b] != kInvalid &&
             zat(a, b) > half;
    };
    if (!above(rr - d[0], cc - d[1]) && !above(rr + d[0], cc + d[1])) continue;  // wide
    // long: above half height along the perpendicular direction, both ways within r
    const std::ptrdiff_t er = (d[0] == 0 || d[1] == 0) ? d[1] : d[0];
    const std::ptrdiff_t ec = (d[0] == 0 || d[1] == 0) ? d[0] : -d[1];
    bool along = true;
    for (std::ptrdiff_t sg = -1; sg <= 1 && along; sg += 2) {
      bool up = false;
      for (std::ptrdiff_t j = 1; j <= r && !up; ++j) up = above(rr + sg * j * er, cc + sg * j * ec);
      along = up;
    }
    if (along) return true;
  }
  return false;
}

// SPEC "Edge test" step 6, hanging cells: P (candidate (rr, cc), its 8 sides `sd`, `best` their
// smallest rms; the caller has found that P fits no clean side with a return) lies, below a
// clean side x whose opposite is empty or clean with P above it and falls away, deeper below
// x's plane than the top's last ground cell (NORMAL or EDGE) towards x is away along that plane
// (steeper than 45 degrees) or beyond a step steeper than that on a path of ABNORMAL cells from
// that ground cell, with ground beyond P (within r, away from x) more than kHangShelf times as
// deep again along x's normal; or lies on a ledge below x (on_ledge). The formulas are
// miem.reference._hanging's and _ledges'.
constexpr double kHangShelf = 2.0;
constexpr int kHangDirs[8][2] = {{0, 1},  {0, -1}, {1, 0},  {-1, 0},
                                 {1, 1},  {1, -1}, {-1, 1}, {-1, -1}};  // side -> towards P

// SPEC "Edge test" step 5: is P = (rr, cc) attached to side x (index s)? Along P - j d_s
// (kHangDirs), j = 1..r inside the grid, no kEdgeAttachGap INVALID cells in a row before the
// first cell with a return on x's plane (|u . (q - o - m)| <= t; a sliver of returns beyond a
// dropout band is no material of the side's surface). miem.reference._attached.
constexpr int kEdgeAttachGap = 2;
template <typename T>
bool attached(const GridView<T>& g, const std::uint8_t* labels, std::ptrdiff_t rr,
              std::ptrdiff_t cc, std::ptrdiff_t r, const Eigen::Vector3d& o, const Side& x,
              int s) {
  const std::ptrdiff_t H = g.rows, W = g.cols, dr = kHangDirs[s][0], dc = kHangDirs[s][1];
  int run = 0;
  for (std::ptrdiff_t j = 1; j <= r; ++j) {
    const std::ptrdiff_t a = rr - j * dr, b = cc - j * dc;
    if (a < 0 || a >= H || b < 0 || b >= W) return true;
    if (labels[a * W + b] == kInvalid) {
      if (++run >= kEdgeAttachGap) return false;
      continue;
    }
    run = 0;
    const Eigen::Vector3d q = (g(a, b) - o) - x.centroid;
    if (!(std::abs(dot3(q, x.normal)) > x.tol)) return true;
  }
  return true;
}

// The ground cells (NORMAL or EDGE) x = P + j (dr, dc) from P = (rr, cc), j = 1..r inside the
// grid, in order: visit(x - P) for each while it returns true. miem.reference._ground_line.
template <typename T, typename Visit>
void ground_line(const GridView<T>& g, const std::uint8_t* labels, std::ptrdiff_t rr,
                 std::ptrdiff_t cc, std::ptrdiff_t r, std::ptrdiff_t dr, std::ptrdiff_t dc,
                 Visit&& visit) {
  const std::ptrdiff_t H = g.rows, W = g.cols;
  const Eigen::Vector3d p = g(rr, cc);
  for (std::ptrdiff_t j = 1; j <= r; ++j) {
    const std::ptrdiff_t a = rr + j * dr, b = cc + j * dc;
    if (a < 0 || a >= H || b < 0 || b >= W) break;
    const std::uint8_t l = labels[a * W + b];
    if ((l == kNormal || l == kEdge) && !visit(Eigen::Vector3d(g(a, b) - p))) break;
  }
}

// The ground cells beyond P = (rr, cc) away from side s, in order (a hanging cell's shelf, a
// lip's dip and rise): visit(u . (x - P)) for each. miem.reference._beyond.
template <typename T, typename Visit>
void beyond(const GridView<T>& g, const std::uint8_t* labels, std::ptrdiff_t rr,
            std::ptrdiff_t cc, std::ptrdiff_t r, int s, const Eigen::Vector3d& u, Visit&& visit) {
  ground_line(g, labels, rr, cc, r, kHangDirs[s][0], kHangDirs[s][1],
              [&](const Eigen::Vector3d& v) {
                visit(dot3(v, u));
                return true;
              });
}

// SPEC "Edge test" step 6, ledges: does P = (rr, cc), below clean side x (index s; o the
// origin), lie on a ledge? Along x's direction d the cells level with P (within
// min(kLedgeLevel x depth, tol) along x's normal; 2 to kLedgeCells of them, P included) run
// from a ground cell on x's plane, which steps down onto them by more than their largest step
// plus kLedgeJump x tol, to a ground cell that drops steeper than 45 degrees to more than
// kHangShelf times P's depth below P: material bent out level beyond a wall top, however
// gently it droops (a rounded bend or a chamfer steepens outwards instead). The formulas are
// miem.reference._ledges'.
constexpr double kLedgeLevel = 0.5, kLedgeJump = 1.0;
constexpr std::ptrdiff_t kLedgeCells = 5;  // at most, P included (burrs: 1-4 points wide)
template <typename T>
bool on_ledge(const GridView<T>& g, const std::uint8_t* labels, std::ptrdiff_t rr,
              std::ptrdiff_t cc, std::ptrdiff_t r, const Eigen::Vector3d& o, const Side& x,
              int s) {
  const std::ptrdiff_t H = g.rows, W = g.cols;
  const Eigen::Vector3d p = g(rr, cc);
  const Eigen::Vector3d& u = x.normal;
  const double depth = -x.h, level = std::min(kLedgeLevel * depth, x.tol);
  double widest = 0.0;  // the largest step between consecutive ledge cells
  // From P along sg d while the cells are level with P: the first other cell (`end`, false
  // when it is INVALID, outside or not ground) and the ledge cell before it (`last`).
  const auto walk = [&](std::ptrdiff_t sg, Eigen::Vector3d& end, Eigen::Vector3d& last,
                        std::ptrdiff_t& run) {
    last = p;
    for (std::ptrdiff_t j = 1; j <= r; ++j) {
      const std::ptrdiff_t a = rr + sg * j * kHangDirs[s][0];
      const std::ptrdiff_t b = cc + sg * j * kHangDirs[s][1];
      if (a < 0 || a >= H || b < 0 || b >= W) return false;
      const std::uint8_t l = labels[a * W + b];
      if (l == kInvalid) return false;
      end = g(a, b);
      if (std::abs(dot3(Eigen::Vector3d(end - p), u)) > level) return l == kNormal || l == kEdge;
      widest = std::max(widest, std::abs(dot3(Eigen::Vector3d(end - last), u)));
      last = end;
      ++run;
    }
    return false;
  };
  Eigen::Vector3d top, t_last, low, l_last;
  std::ptrdiff_t run = 0;
  if (!walk(-1, top, t_last, run) || !walk(1, low, l_last, run)) return false;
  if (run < 1 || run + 1 > kLedgeCells) return false;
  if (std::abs(dot3(Eigen::Vector3d((top - o) - x.centroid), u)) > x.tol) return false;
  if (!(dot3(Eigen::Vector3d(top - t_last), u) > widest + kLedgeJump * x.tol)) return false;
  const Eigen::Vector3d w = low - l_last;
  const double fall = -dot3(w, u);
  return fall > 0.0 && fall * fall > dot3(w, w) - fall * fall &&
         dot3(Eigen::Vector3d(low - p), u) < -kHangShelf * depth;
}

template <typename T>
bool is_hanging(const GridView<T>& g, const std::uint8_t* labels, std::ptrdiff_t rr,
                std::ptrdiff_t cc, std::ptrdiff_t r, const Eigen::Vector3d& o,
                const Side (&sd)[8], double best) {
  const auto clean = [&](int s) {
    return edge_clean(sd[s], best);
  };
  const std::ptrdiff_t H = g.rows, W = g.cols;
  const auto label = [&](std::ptrdiff_t a, std::ptrdiff_t b) -> std::uint8_t {
    if (a < 0 || a >= H || b < 0 || b >= W) return kInvalid;
    return labels[a * W + b];
  };
  const Eigen::Vector3d p = g(rr, cc);
  for (int s = 0; s < 8; ++s) {
    const Side& x = sd[s];
    const Side& y = sd[kOpposite[s]];
    if (!clean(s) || !(x.h < -x.tol)) continue;
    if (on_ledge(g, labels, rr, cc, r, o, x, s)) return true;
    if (!(y.empty || (clean(kOpposite[s]) && y.h > y.tol && edge_drops(x, y)))) continue;
    const std::ptrdiff_t dr = kHangDirs[s][0], dc = kHangDirs[s][1];
    const double depth = -x.h;
    bool steep = false;
    // the path towards x: while it runs over ABNORMAL cells (`chain`), a step from one cell to
    // the next towards P that drops steeper than 45 degrees below x's plane (`steep_step`)
    bool chain = true, via = false, steep_step = false;
    Eigen::Vector3d prev = p;
    for (std::ptrdiff_t j = 1; j <= r; ++j) {  // the nearest ground cell towards x
      const std::uint8_t l = label(rr - j * dr, cc - j * dc);
      const bool ground = l == kNormal || l == kEdge;
      if (!ground && l != kAbnormal) {  // INVALID or outside: the path is broken
        chain = false;
        continue;
      }
      const Eigen::Vector3d c = g(rr - j * dr, cc - j * dc);
      if (chain) {
        const Eigen::Vector3d w = prev - c;
        const double along_w = dot3(w, x.normal);
        steep_step = steep_step ||
                     (along_w < 0.0 && along_w * along_w > dot3(w, w) - along_w * along_w);
      }
      if (!ground) {
        prev = c;
        via = true;
        continue;
      }
      const Eigen::Vector3d v = c - p;
      const double along = dot3(v, x.normal);
      steep = depth * depth > dot3(v, v) - along * along || (chain && via && steep_step);
      break;
    }
    if (!steep) continue;
    bool shelf = false;  // ground beyond P, deeper along x's normal
    beyond(g, labels, rr, cc, r, s, x.normal, [&](double d) {
      shelf = shelf || d < -kHangShelf * depth;
    });
    if (shelf) return true;
  }
  return false;
}

// The nearest ground cell x along (dr, dc) from P = (rr, cc) (ground_line), seen along the
// unit normal u: its height s = u . (x - P) and its distance w along u's plane. False when
// there is none. miem.reference._nearest_ground.
template <typename T>
bool nearest_ground(const GridView<T>& g, const std::uint8_t* labels, std::ptrdiff_t rr,
                    std::ptrdiff_t cc, std::ptrdiff_t r, std::ptrdiff_t dr, std::ptrdiff_t dc,
                    const Eigen::Vector3d& u, double& s, double& w) {
  bool found = false;
  ground_line(g, labels, rr, cc, r, dr, dc, [&](const Eigen::Vector3d& v) {
    s = dot3(v, u);
    w = std::sqrt(std::max(dot3(v, v) - s * s, 0.0));
    found = true;
    return false;
  });
  return found;
}

// SPEC "Edge test" step 6, lips at a concave feature: P (candidate (rr, cc), its 8 sides `sd`,
// `best` their smallest rms; the caller has found that P fits no clean side) lies above a clean
// side x, and along the cells P + j d beyond P away from x (j = 1..r, ground cells only: NORMAL
// or EDGE), with D = max(kEdgeLipTol x tol, kEdgeLipDip x h), the surface first dips (a cell
// lower than P along x's normal by more than D; or P itself, above the chord from the nearest
// ground cell towards x to the first one beyond P by more than D, that first one lower than P
// by more than kEdgeLipTol x tol), then rises (the last of these ground cells, after the dip,
// lies above x's plane by more than D): a lip before a concave crease or step, not a fillet (no
// dip), a terrace's edge (its next cells level with P), a bead on a plane or a fin beyond P (no
// lasting rise) nor a profile offset of a few rms. The formulas are miem.reference._lips'.
template <typename T>
bool is_lip(const GridView<T>& g, const std::uint8_t* labels, std::ptrdiff_t rr,
            std::ptrdiff_t cc, std::ptrdiff_t r, const Side (&sd)[8], double best) {
  for (int s = 0; s < 8; ++s) {
    const Side& x = sd[s];
    if (!edge_clean(x, best) || !(x.h > x.tol)) continue;
    const double dip = std::max(kEdgeLipTol * x.tol, kEdgeLipDip * x.h);
    // the dip at P: above the chord from the ground before P (towards x) to the first beyond
    const int dr = kHangDirs[s][0], dc = kHangDirs[s][1];
    double sq = 0.0, wq = 0.0, s1 = 0.0, w1 = 0.0;
    const bool chord = nearest_ground(g, labels, rr, cc, r, -dr, -dc, x.normal, sq, wq) &&
                       nearest_ground(g, labels, rr, cc, r, dr, dc, x.normal, s1, w1) &&
                       s1 < -kEdgeLipTol * x.tol && wq + w1 > 0.0 &&
                       -(sq * w1 + s1 * wq) / (wq + w1) > dip;
    bool dipped = chord, risen = false;  // risen: the last ground cell so far, after a dip, high
    beyond(g, labels, rr, cc, r, s, x.normal, [&](double d) {
      risen = dipped && x.h + d > dip;
      dipped = dipped || d < -dip;
    });
    if (risen) return true;
  }
  return false;
}

// SPEC "Edge test" step 4, smooth curved surface: P's four quadrants (sides 4-7) are valid,
// not empty, not steep, and bend as one quadratic surface z = 1/2 v'Av (v = (x, y) - P)
// would: A from the differences of opposite quadrants' slopes at their centroids (a
// quadrant's plane has the surface's slope at its centroid m: A (m_a - m_b) = g_a - g_b for
// the pairs up-left/down-right and up-right/down-left; A symmetrised), each quadrant's rms^2
// (vertical) at least kCurvedBend times the residual variance such a surface leaves about its
// plane (kCurvedLattice (A11^2 Sxx^2 + A22^2 Syy^2) + A12^2 Sxx Syy, S its cells' (x, y)
// covariance: a lattice of cells, uniform along x and y) and at most kCurvedFit times it plus
// floor^2 (nothing but the bend and noise: no burr run in the quadrant, whose cells would lift
// its rms and tilt its slope), and P lies within max(k sigma, floor) of where the surface puts
// it above every quadrant's plane, 1/2 m'Am - 1/2 tr(AS) (sigma^2: the quadrants' mean rms^2
// less that residual variance, the noise; floor: the cell's tolerance floor). Then P lies on
// a smooth bowl, dome or saddle, where the one-sided planes miss it by several of their rms
// whatever its curvature, and no rule of steps 5-7 applies. The formulas are
// miem.reference._curved's.
constexpr double kCurvedBend = 0.5, kCurvedFit = 1.25, kCurvedLattice = 0.2;
// That test for m cells, from their quadrants' solved planes only (so a cell it settles needs
// no half side solved): quadrant q of cell j at entry q * m + j of the SoA
// arrays (components `cap` apart; F: h, rms, tol, normal as side_planes writes it; Mb, nnb:
// side_moments' centred scatter and count), the cell at P[j], P[cap + j] and its floor FL[j].
// curved[j] = 1 or 0. Branch-free and vectorised: every lane computes every expression (a
// lane that fails an early condition may compute infinities and NaNs, masked at the end) in
// the order of the scalar formula, so the same bits.
MIEM_CLONES void curved_cells(int m, std::ptrdiff_t cap, double k,
                              const double* __restrict validb, const double* __restrict emptyb,
                              const double* __restrict F, const double* __restrict ceb,
                              const double* __restrict Mb, const double* __restrict nnb,
                              const double* __restrict P, const double* __restrict FL,
                              double* __restrict curved) {
#pragma GCC ivdep
  for (int j = 0; j < m; ++j) {
    double g[4][2], mq[4][2], hv[4], r2[4], cv[4][3];
    bool ok = true;
    const double px = P[j], py = P[cap + j], floor = FL[j];
    for (int q = 0; q < 4; ++q) {
      const int e = q * m + j;
      const double uz = F[5 * cap + e];  // > 0 where level: oriented, not steep
      ok = ok & (validb[e] != 0.0) & !(uz < kEdgeSteepCos) & (emptyb[e] == 0.0);
      g[q][0] = -F[3 * cap + e] / uz, g[q][1] = -F[4 * cap + e] / uz;
      mq[q][0] = ceb[e] - px, mq[q][1] = ceb[cap + e] - py;
      hv[q] = F[e] / uz;
      const double rv = F[cap + e] / uz;
      r2[q] = rv * rv;
      const double n = nnb[e];
      cv[q][0] = Mb[e] / n, cv[q][1] = Mb[cap + e] / n, cv[q][2] = Mb[3 * cap + e] / n;
    }
    const double d11 = mq[3][0] - mq[0][0], d21 = mq[3][1] - mq[0][1];
    const double d12 = mq[2][0] - mq[1][0], d22 = mq[2][1] - mq[1][1];
    const double det = d11 * d22 - d12 * d21;
    ok = ok & (std::abs(det) > kLineTol * (d11 * d11 + d12 * d12 + d21 * d21 + d22 * d22));
    const double b11 = g[3][0] - g[0][0], b21 = g[3][1] - g[0][1];
    const double b12 = g[2][0] - g[1][0], b22 = g[2][1] - g[1][1];
    const double a11 = (b11 * d22 - b12 * d21) / det, a22 = (b22 * d11 - b21 * d12) / det;
    const double a12 = 0.5 * ((b12 * d11 - b11 * d12) / det + (b21 * d22 - b22 * d21) / det);
    double worst = 0.0, noise = 0.0;
    for (int q = 0; q < 4; ++q) {
      const double sxx = cv[q][0], syy = cv[q][1], sxy = cv[q][2];
      const double mx = mq[q][0], my = mq[q][1];
      const double at = 0.5 * (a11 * mx * mx + 2.0 * a12 * mx * my + a22 * my * my) -
                        0.5 * (a11 * sxx + 2.0 * a12 * sxy + a22 * syy);
      const double bend = kCurvedLattice * (a11 * a11 * sxx * sxx + a22 * a22 * syy * syy) +
                          a12 * a12 * sxx * syy;
      ok = ok & (r2[q] >= kCurvedBend * bend) & (r2[q] <= kCurvedFit * bend + floor * floor);
      const double miss = std::abs(hv[q] - at), rest = r2[q] - bend;
      worst = worst < miss ? miss : worst;  // std::max(worst, miss)
      noise += rest < 0.0 ? 0.0 : rest;     // std::max(rest, 0.0)
    }
    const double kn = k * std::sqrt(0.25 * noise);
    curved[j] = ok & (worst <= (kn < floor ? floor : kn)) ? 1.0 : 0.0;
  }
}

// SPEC "Edge test" step 6, valleys: P (candidate (rr, cc), its 8 sides `sd`; the caller has
// found that P fits no clean side) lies above two opposite level sides x and y (valid, not
// steep; clean or not: beyond P a side may straddle the crease or hold the burr run's cells)
// by more than kValleyHeight times their tolerances, y's centroid lies above x's plane by
// more than kValleyCentroid times x's tolerance (the surface rises beyond P: a concave
// crease), the scan is sampled regularly up to P on both sides (valley_regular), and
// towards x the raised ground cells (at most kValleyCells, P included) step up from a ground
// cell on x's plane by more than their largest rise, and the rise from P onto the nearest
// ground cell beyond, plus kValleyJump x tol: material raised before a concave crease, where
// the lip rule finds no dip (the far face already rises). A fillet rises ever more steeply (no
// step up from the plane); a profile between two wide gaps on a curved surface extrapolates
// both planes over the gaps; a noise peak on a concave curved surface stands less than
// kValleyHeight tolerances above both planes, or its far side rises too little. The formulas
// are miem.reference._valleys'.
constexpr double kValleyHeight = 1.75, kValleyCentroid = 2.0, kValleyGap = 3.0,
                 kValleyJump = 1.5;
// ... and x's and y's planes meet at more than 4 degrees (normals' dot product below cos 4
// degrees): a crease, not a gently curved surface (noise-free, its tolerances are so small that
// the centroid test alone passed a bead standing on it)
constexpr double kValleyCos = 0.9975640502598242;
constexpr std::ptrdiff_t kValleyCells = 4;

// Regular sampling up to P = (rr, cc) towards side s: P - d and P - 2 d have returns (inside
// the grid, not INVALID; within r >= 2) and the gap from P to the first is at most kValleyGap
// times the gap between the two, measured along x's plane.
template <typename T>
bool valley_regular(const GridView<T>& g, const std::uint8_t* labels, std::ptrdiff_t rr,
                    std::ptrdiff_t cc, std::ptrdiff_t r, const Side& x, int s) {
  if (r < 2) return false;
  const std::ptrdiff_t H = g.rows, W = g.cols, dr = kHangDirs[s][0], dc = kHangDirs[s][1];
  Eigen::Vector3d q[3];
  q[0] = g(rr, cc);
  for (std::ptrdiff_t j = 1; j <= 2; ++j) {
    const std::ptrdiff_t a = rr - j * dr, b = cc - j * dc;
    if (a < 0 || a >= H || b < 0 || b >= W || labels[a * W + b] == kInvalid) return false;
    q[j] = g(a, b);
  }
  const auto along = [&](const Eigen::Vector3d& v) {
    const double h = dot3(v, x.normal);
    return std::sqrt(std::max(dot3(v, v) - h * h, 0.0));
  };
  return along(Eigen::Vector3d(q[1] - q[0])) <= kValleyGap * along(Eigen::Vector3d(q[2] - q[1]));
}

template <typename T>
bool in_valley(const GridView<T>& g, const std::uint8_t* labels, std::ptrdiff_t rr,
               std::ptrdiff_t cc, std::ptrdiff_t r, const Side (&sd)[8]) {
  const auto high = [&](int s) {  // (level, clean or not)
    return edge_level(sd[s]) && sd[s].h > kValleyHeight * sd[s].tol;
  };
  for (int s = 0; s < 8; ++s) {
    const Side& x = sd[s];
    const int o = kOpposite[s];
    const double rise = dot3(x.normal, sd[o].centroid - x.centroid);  // y's centroid over x
    if (!high(s) || !high(o) || !(rise > kValleyCentroid * x.tol) ||
        !(dot3(x.normal, sd[o].normal) < kValleyCos)) {
      continue;
    }
    if (!valley_regular(g, labels, rr, cc, r, x, s) ||
        !valley_regular(g, labels, rr, cc, r, sd[o], o)) {
      continue;
    }
    const std::ptrdiff_t dr = kHangDirs[s][0], dc = kHangDirs[s][1];
    // towards x (within kValleyCells steps): the raised ground cells, then the first on x's
    // plane (the base)
    double prev = x.h, widest = 0.0, jump = 0.0;
    bool based = false;
    ground_line(g, labels, rr, cc, std::min(r, kValleyCells), -dr, -dc,
                [&](const Eigen::Vector3d& v) {
                  const double hv = dot3(v, x.normal) + x.h;
                  if (!(std::abs(hv) > x.tol)) {
                    based = true;
                    jump = prev - hv;
                    return false;
                  }
                  widest = std::max(widest, prev - hv);
                  prev = hv;
                  return true;
                });
    if (!based) continue;
    // ... and beyond P: the rise onto the nearest ground cell
    double s1 = 0.0, w1 = 0.0;
    if (nearest_ground(g, labels, rr, cc, r, dr, dc, x.normal, s1, w1)) {
      widest = std::max(widest, s1);
    }
    if (jump > widest + kValleyJump * x.tol) return true;
  }
  return false;
}

// SPEC "Edge test" step 5, outlines: a side is an outline when at least kOutlineEmpty of the
// cells of its full (unclipped) extent have no return (outline_cells: a half (2 r + 1) r, a
// quadrant r r), and it is empty (at least n_min of them) ...
constexpr double kOutlineEmpty = 0.9;
// ... and P is a lip before it when it lies above the opposite clean side x by more than
// kOutlineHeight x tol, is attached to x, and fits no clean side on x's side of it (x and,
// for a half, its two quadrants, kSameSide): the other sides lie along the outline and hold
// the lip itself. miem.reference._outline_lips.
constexpr double kOutlineHeight = 1.5;
constexpr int kSameSide[8][3] = {{0, 4, 6}, {1, 5, 7}, {2, 4, 5}, {3, 6, 7},
                                 {4, 4, 4}, {5, 5, 5}, {6, 6, 6}, {7, 7, 7}};

inline double outline_cells(int s, std::ptrdiff_t r) {
  return static_cast<double>(s < 4 ? (2 * r + 1) * r : r * r);
}

template <typename Attached>
bool outline_lip(const Side (&sd)[8], double best, Attached attached) {
  const auto fits = [&](int q) { return edge_fits(sd[q], best); };
  for (int s = 0; s < 8; ++s) {
    const Side& x = sd[s];
    if (!edge_clean(x, best) || !(x.h > kOutlineHeight * x.tol) || !sd[kOpposite[s]].outline) {
      continue;
    }
    if (!fits(kSameSide[s][0]) && !fits(kSameSide[s][1]) && !fits(kSameSide[s][2]) &&
        attached(s)) {
      return true;
    }
  }
  return false;
}

// SPEC "Edge test" step 6, crossing a convex feature: P stands proud of clean side x
// (edge_proud_of: h > tol, x's opposite empty or falling away) by more than kCrossingFloor x
// the tolerance floor `floor` too (min_step / 2, 1.5 z_resolution, 2 z_noise: where a
// scanner's resolution, not its noise, sets the tolerance), P is attached to x, and every clean
// side P fits lies past the feature (its centroid more than x's tolerance below x's plane): on
// a convex crease or bend the far face's plane, extended back over P, lies above the near face
// there, so a fit to it does not clear P. Asked of a P that fits (one that fits nothing and
// meets it stands proud). Its heights (tol, kCrossingFloor x floor) bound the shortcut's
// side_reaches. miem.reference._crossings.
constexpr double kCrossingFloor = 2.5;

template <typename Attached>
bool crossing_lip(const Side (&sd)[8], double best, double floor, Attached attached) {
  bool fit[8];
  for (int c = 0; c < 8; ++c) fit[c] = edge_fits(sd[c], best);
  for (int s = 0; s < 8; ++s) {
    const Side& x = sd[s];
    if (!edge_proud_of(x, sd[kOpposite[s]], best) || !(x.h > kCrossingFloor * floor)) continue;
    bool cleared = false;
    for (int c = 0; c < 8 && !cleared; ++c) cleared = fit[c] && !edge_drops(x, sd[c]);
    if (!cleared && attached(s)) return true;
  }
  return false;
}

// For m cells (side s of cell j: its moments at mm8[s] + j, `cap` apart, its rms^2 bound at
// low8[s][j], side_lows; the cell at Pc + j and a unit vector at U + j, `pcap` apart), how
// many of their 8 sides may have P above their plane by more than `lim` x tol, tol >=
// max(edge_k rms, floor), without solving: for unit w, (w . v)^2 <= (w' C w) (v' C^-1 v) with
// C = M / nn, v = P - centroid. With w the plane's normal (smallest eigenvector), w' C w =
// rms^2, so h > lim k rms needs nn v' M^-1 v > (lim k)^2 = lim2 (when rms is not 0: low > 0);
// and w' C w <= u' C u for any unit u, so h > lim floor needs (u' M u) (v' M^-1 v) > (lim
// floor)^2 = flo2 (both less a relative 1e-6 for rounding). A side without support (side_moment,
// the same bits as the planes': never valid) never does. The shortcut's test of a cell that
// fits a clean side for a crossing lip: no side reaching, no lip. Vectorised over the cells.
MIEM_CLONES void side_reaches(int m, std::ptrdiff_t cap, double n_min, double lim2,
                              double flo2, const double* const* mm8, const double* const* low8,
                              const double* __restrict Pc, const double* __restrict U,
                              std::ptrdiff_t pcap, double* __restrict reach) {
  for (int j = 0; j < m; ++j) reach[j] = 0.0;
  for (int s = 0; s < 8; ++s) {
    const double* __restrict mm = mm8[s];
    const double* __restrict low = low8[s];
#pragma GCC ivdep
    for (int j = 0; j < m; ++j) {
      double nn, cx, cy, cz, M[6];
      bool use;
      side_moment(mm + j, cap, n_min, nn, cx, cy, cz, M, use);
      const double a = M[0], b = M[1], c = M[2], d = M[3], f = M[4], g = M[5];
      // v' adj(M) v, adj(M) = det M^-1 by cofactors
      const double A00 = b * c - f * f, A11 = a * c - g * g, A22 = a * b - d * d;
      const double A01 = f * g - d * c, A12 = d * g - a * f, A02 = d * f - b * g;
      const double det = a * A00 + d * A01 + g * A02;
      const double vx = Pc[j] - cx, vy = Pc[pcap + j] - cy, vz = Pc[2 * pcap + j] - cz;
      const double q = vx * vx * A00 + vy * vy * A11 + vz * vz * A22 +
                       2.0 * (vx * vy * A01 + vy * vz * A12 + vx * vz * A02);
      const double ux = U[j], uy = U[pcap + j], uz = U[2 * pcap + j];
      const double uMu = a * ux * ux + b * uy * uy + c * uz * uz +
                         2.0 * (d * ux * uy + f * uy * uz + g * ux * uz);
      const bool bounded = det > 0.0 && ((low[j] > 0.0 && nn * q <= lim2 * det) ||
                                         (flo2 > 0.0 && uMu * q <= flo2 * det));
      reach[j] += use && !bounded ? 1.0 : 0.0;
    }
  }
}

}  // namespace

namespace {

// s[j] += u[j] (v null) or u[j] * v[j], j < n: column sums, vectorised over the columns.
MIEM_CLONES void column_add(std::ptrdiff_t n, double* __restrict s, const double* __restrict u,
                            const double* __restrict v) {
  if (v == nullptr) {
    for (std::ptrdiff_t j = 0; j < n; ++j) s[j] += u[j];
  } else {
    for (std::ptrdiff_t j = 0; j < n; ++j) s[j] += u[j] * v[j];
  }
}

// The terms of n cells loaded by load_rel: a NORMAL cell keeps its coordinates and counts 1 in
// nm; any other cell counts 0, and an INVALID cell 1 in iv. Branch-free: vectorised.
MIEM_CLONES void normal_terms(std::ptrdiff_t n, const std::uint8_t* __restrict lb,
                              double* __restrict px, double* __restrict py, double* __restrict pz,
                              double* __restrict nm, double* __restrict iv) {
  for (std::ptrdiff_t j = 0; j < n; ++j) {
    const bool normal = lb[j] == kNormal;
    px[j] = normal ? px[j] : 0.0;
    py[j] = normal ? py[j] : 0.0;
    pz[j] = normal ? pz[j] : 0.0;
    nm[j] = normal ? 1.0 : 0.0;
    iv[j] = lb[j] == kInvalid ? 1.0 : 0.0;
  }
}

// The running sums along an image row of NQ moments (moment q: out[q * plane + j + 1] =
// out[q * plane + j] + col[q * col_plane + j], j < n), NQ chains side by side, each sum kept
// in a register (the same additions in the same order as one at a time).
template <int NQ>
inline void row_prefix(std::ptrdiff_t n, double* __restrict out, std::ptrdiff_t plane,
                       const double* __restrict col, std::ptrdiff_t col_plane) {
  double run[NQ];
  for (int q = 0; q < NQ; ++q) run[q] = out[q * plane];
  for (std::ptrdiff_t j = 0; j < n; ++j) {
    for (int q = 0; q < NQ; ++q) {
      run[q] += col[q * col_plane + j];
      out[q * plane + j + 1] = run[q];
    }
  }
}

// Adds cell row `row` of g (labels `lab`) over grid columns f0 .. f1 - 1 to the column sums
// (moment q of column f0 + x at col[q * col_plane + x]): per cell n, x, y, z, xx, xy, xz, yy,
// yz, zz of a NORMAL cell relative to the origin o (0 for any other cell) and the INVALID
// count. With `out`, also the image row: moment q at out[q * plane], 0 then x + 1 for column
// f0 + x, the running sum of the column sums along the row (NumPy's order). Blocks of kB
// columns: the cells' terms branch-free, the column sums vectorised over the columns (each
// column's own addition: the same bits), the row prefix in its one serial order.
template <typename T>
void add_row_moments(const GridView<T>& g, std::ptrdiff_t row, const std::uint8_t* lab,
                     std::ptrdiff_t f0, std::ptrdiff_t f1, const Eigen::Vector3d& o,
                     double* __restrict col, std::ptrdiff_t col_plane, double* __restrict out,
                     std::ptrdiff_t plane) {
  constexpr std::ptrdiff_t kB = 64;
  double px[kB], py[kB], pz[kB], nm[kB], iv[kB];
  const double ox = o.x(), oy = o.y(), oz = o.z();
  if (out != nullptr) {
    for (int q = 0; q < kM; ++q) out[q * plane] = 0.0;
  }
  for (std::ptrdiff_t b = f0; b < f1; b += kB) {
    const std::ptrdiff_t n = std::min(kB, f1 - b);
    load_rel(g, row, b, n, ox, oy, oz, px, py, pz);  // vector clones for the common layouts
    normal_terms(n, lab + b, px, py, pz, nm, iv);
    double* const cb = col + (b - f0);
    const auto add = [n](double* s, const double* t) { column_add(n, s, t, nullptr); };
    const auto add2 = [n](double* s, const double* u, const double* v) {
      column_add(n, s, u, v);
    };
    add(cb, nm);
    add(cb + col_plane, px), add(cb + 2 * col_plane, py), add(cb + 3 * col_plane, pz);
    add2(cb + 4 * col_plane, px, px), add2(cb + 5 * col_plane, px, py);
    add2(cb + 6 * col_plane, px, pz), add2(cb + 7 * col_plane, py, py);
    add2(cb + 8 * col_plane, py, pz), add2(cb + 9 * col_plane, pz, pz);
    add(cb + 10 * col_plane, iv);
    if (out == nullptr) continue;
    double* const ob = out + (b - f0);
    row_prefix<4>(n, ob, plane, cb, col_plane);
    row_prefix<4>(n, ob + 4 * plane, plane, cb + 4 * col_plane, col_plane);
    row_prefix<kM - 8>(n, ob + 8 * plane, plane, cb + 8 * col_plane, col_plane);
  }
}

// edge_image_row's column sums only (the image row itself is not written): for the rows above
// every image row a pass reads, whose sums the rows below still need.
template <typename T>
void edge_column_row(const GridView<T>& g, std::ptrdiff_t row, const std::uint8_t* lab,
                     std::ptrdiff_t f0, std::ptrdiff_t f1, const Eigen::Vector3d& o, double* col,
                     std::ptrdiff_t col_plane) {
  add_row_moments(g, row, lab, f0, f1, o, col, col_plane, nullptr, 0);
}

}  // namespace

template <typename T>
void edge_image_row(const GridView<T>& g, std::ptrdiff_t row, const std::uint8_t* lab,
                    std::ptrdiff_t f0, std::ptrdiff_t f1, const Eigen::Vector3d& o, double* col,
                    std::ptrdiff_t col_plane, double* out, std::ptrdiff_t plane) {
  add_row_moments(g, row, lab, f0, f1, o, col, col_plane, out, plane);
}

// SPEC "Edge test" step 7, isolated spikes: NORMAL candidate (rr, cc) of grid row `grow`
// (grid rows 0..H - 1: `rr`), with all 8 neighbours inside the grid, lies more than
// kEdgeSpikeTol x tol off every clean side (edge_spike_side), and the median over its
// neighbours with a return of |u . (q - centroid)| for the cleanest side is below kEdgeSpikeIso
// x |h|, and it is no corner of a raised patch (edge_spike_corner). The formulas are
// miem.reference._spikes'.
template <typename T>
bool is_spike(const GridView<T>& g, const std::uint8_t* labels, std::ptrdiff_t grow,
              std::ptrdiff_t rr, std::ptrdiff_t cc, std::ptrdiff_t H, const Eigen::Vector3d& o,
              const Side (&sd)[8], double best) {
  const std::ptrdiff_t W = g.cols;
  if (labels[grow * W + cc] != kNormal || rr < 1 || rr + 1 >= H || cc < 1 || cc + 1 >= W) {
    return false;
  }
  const int s = edge_spike_side(sd, best);
  if (s < 0) return false;
  const Side& x = sd[s];
  double d[8], res[8];
  int n = 0, t = 0;
  for (std::ptrdiff_t a = -1; a <= 1; ++a) {
    for (std::ptrdiff_t b = -1; b <= 1; ++b) {
      if (a == 0 && b == 0) continue;
      double& sv = res[t++];
      sv = std::numeric_limits<double>::quiet_NaN();
      if (labels[(grow + a) * W + cc + b] == kInvalid) continue;
      const Eigen::Vector3d q = (g(grow + a, cc + b) - o) - x.centroid;
      sv = dot3(q, x.normal);
      const double v = std::abs(sv);
      int i = n++;  // insertion: d[0..n) ascending
      for (; i > 0 && d[i - 1] > v; --i) d[i] = d[i - 1];
      d[i] = v;
    }
  }
  if (n == 0) return false;
  const double median = n % 2 ? d[n / 2] : (d[n / 2 - 1] + d[n / 2]) / 2.0;
  return median < kEdgeSpikeIso * std::abs(x.h) && !edge_spike_corner(res, x.h);
}

template <typename T>
void edge_judge_row(const GridView<T>& g, std::ptrdiff_t grow, std::ptrdiff_t rr,
                    std::ptrdiff_t H, std::ptrdiff_t C0, std::ptrdiff_t C1,
                    const EdgeImages& im, const Eigen::Vector3d& o, std::ptrdiff_t r, EdgeTol et,
                    const std::uint8_t* lab, const std::uint8_t* todo, std::uint8_t* mark,
                    const EdgeBandCache* cache, EdgeJudgment judge) {
  const bool fit_only = judge == EdgeJudgment::kFitsGround;  // step 9: any label, fits only
  const std::ptrdiff_t W = g.cols, f0 = im.f0, plane = im.plane;
  const double n_min = static_cast<double>(edge_n_min(r));
  double outline_at[8];  // a side with this many INVALID cells is an outline (outline_lip)
  for (int s = 0; s < 8; ++s) outline_at[s] = std::max(n_min, kOutlineEmpty * outline_cells(s, r));
  const double* const S = im.data;
  const std::uint8_t* const lrow = lab + grow * W;  // the cell's row
  const auto srow = [&im](std::ptrdiff_t s) { return ((s - im.first) % im.rows) * im.stride; };
  // Candidate cells of the row a chunk at a time: a banded block's candidates all at once (up
  // to kChunk, the block's width), else up to kSub, all as SoA over their 8 sides (entry
  // e = side * m + cell): the sub-window sums (corner reads, vectorised over the cells, or
  // over their span when they are not consecutive, away from the grid border; banded: the
  // bands'), then bounds and the shortcut over the chunk, and for the cells it leaves,
  // kSub at a time, moments, eigenpairs and planes of all 8 sides in vectorised loops; each
  // cell is judged from those.
  constexpr int kChunk = 64, kSub = 16, kCap = 8 * kSub;
  double mm[kM * kCap], Mb[6 * kCap], Eb[6 * kCap], nnb[kCap], ceb[3 * kCap];
  // F: h, rms, tol, oriented normal; P: the cells per side (filled for the full path only),
  // Pc: the cells (relative to the origin, q * kChunk + j)
  double F[6 * kCap], P[3 * kCap], Pc[3 * kChunk];
  double FL[kCap], FLc[kChunk];  // the cells' tolerance floors (cell_floor): per side, per cell
  // flags as doubles (1 or 0): 8-byte lanes throughout, so the vector loops run 8 (or 4) lanes
  // at a time, not 32 (a byte store per lane made GCC pick 32 and run chunks of 16 scalar)
  double okb[kCap], redob[kCap], useb[kCap], emptyb[kCap], validb[kCap];
  double lowb[kCap];
  std::ptrdiff_t cols[kChunk];
  constexpr std::ptrdiff_t kSpan = 48;  // sums of up to kSpan columns for scattered cells
  double spn[kM * kSpan];
  int keep[kChunk];
  // Band blocks (many candidates in a row, away from the grid border): the 8 sides of a cell
  // are 5 rectangles slid along the row (kBandOf): rows -r..r (band 0), -r..-1 (1) and 1..r (2)
  // over r columns, rows -r..-1 (3) and 1..r (4) over 2r + 1 columns; side s of cell c is band
  // kBandOf[s] at position c - b0 (left, x0 = c - r) or c - b0 + r + 1 (right, x0 = c + 1).
  // So the right side of c is the left side of c + r + 1: each rectangle's sums and bound are
  // computed once per block (the same corner reads and formula, so the same bits) and picked
  // out per cell. Moment q of band b at position i: band[(b * kM + q) * kBandPos + i].
  constexpr std::ptrdiff_t kBandPos = kEdgeBandPos, kBandCells = kEdgeBandCells;
  constexpr int kBandOf[8] = {0, 0, 3, 4, 1, 1, 2, 2};
  constexpr bool kRight[8] = {false, true, false, false, false, true, false, true};
  double band[5 * kM * kBandPos], bandlow[5 * kBandPos];
  double* bandp[5];  // band b's sums and bounds: here, or in the caller's cache
  double* lowp[5];
  // With a cache: bands 2 and 4 (rows 1..r below) of row rr are bands 1 and 3 (rows -r..-1
  // above) of row rr + r + 1, the same corner reads of the same images: kept in a ring of r + 2
  // rows (per block of the tile row) and reused there. Slot: tag (row, b0, cells), then bands
  // 2 and 4 as (kM moments + bounds) x kBandPos.
  constexpr std::ptrdiff_t kSlot = kEdgeCacheSlot;
  const std::ptrdiff_t nblk = (C1 - C0 + kBandCells - 1) / kBandCells;
  const bool cached = cache != nullptr && cache->data != nullptr &&
                      cache->slots >= (r + 2) * nblk;
  const auto slot = [&](std::ptrdiff_t row, std::ptrdiff_t blk) {
    const std::ptrdiff_t k = ((row % (r + 2)) + (r + 2)) % (r + 2);
    return cache->data + (k * nblk + blk) * kSlot;
  };
  const bool rows_inside = rr - r >= 0 && rr + r + 1 <= H;
  const std::ptrdiff_t bw = std::min(kBandCells, kBandPos - r - 1);  // a block's columns
  std::ptrdiff_t bend = C0, b0 = 0;  // the block [.., bend); its first band cell b0
  bool banded = false;
  // the block's candidates (bcand[0 .. nb)), the next one to take: ib
  std::ptrdiff_t bcand[kBandCells];
  int nb = 0, ib = 0;
  for (std::ptrdiff_t cc = C0; cc < C1;) {
    if (cc >= bend) {  // a new block: banded when it saves rectangles
      bend = std::min(C1, cc + std::max<std::ptrdiff_t>(bw, 1));
      // A band needs all of its cells' rectangles inside the grid (columns r .. W - r - 1):
      // a block is cut where that span begins or ends, so only the r cells at each border,
      // not a whole block of kBandCells, go through the general path. (Band blocks then start
      // at the same columns in every row: the cache's slots and tags still match.)
      if (rows_inside && bw >= 16) {
        if (cc < r) {
          bend = std::min(bend, r);
        } else if (cc < W - r) {
          bend = std::min(bend, W - r);
        }
      }
      nb = 0, ib = 0;
      for (std::ptrdiff_t c = cc; c < bend; ++c) {  // (branch-free)
        bcand[nb] = c;
        nb += todo[c] & (fit_only | (lrow[c] == kNormal) | (lrow[c] == kEdge));
      }
      banded = false;
      if (rows_inside && bw >= 16) {
        const std::ptrdiff_t n = nb, first = nb ? bcand[0] : -1, last = nb ? bcand[nb - 1] : -1;
        const std::ptrdiff_t w = last - first + 1;
        banded = n > 0 && first - r >= 0 && last + r + 1 <= W && 8 * n > 5 * w + 3 * (r + 1);
        if (banded) {
          b0 = first;
          const std::ptrdiff_t rl[3] = {srow(rr - r), srow(rr), srow(rr + r + 1)};
          const std::ptrdiff_t lines[5][2] = {{rl[0], rl[2]}, {rl[0], rl[1]},
                                              {srow(rr + 1), rl[2]}, {rl[0], rl[1]},
                                              {srow(rr + 1), rl[2]}};
          const std::ptrdiff_t x0 = first - r - f0;
          for (int b = 0; b < 5; ++b) {
            bandp[b] = band + b * kM * kBandPos;
            lowp[b] = bandlow + b * kBandPos;
          }
          bool reuse = false;
          if (cached && bw == kBandCells) {
            const std::ptrdiff_t blk = (cc - C0) / kBandCells;
            double* const nw = slot(rr, blk);
            double* const od = slot(rr - r - 1, blk);  // row rr - r - 1's (if it is there)
            reuse = od[0] == static_cast<double>(rr - r - 1) &&
                    od[1] == static_cast<double>(first) && od[2] >= static_cast<double>(w);
            if (reuse) {
              bandp[1] = od + 8;
              lowp[1] = bandp[1] + kM * kBandPos;
              bandp[3] = lowp[1] + kBandPos;
              lowp[3] = bandp[3] + kM * kBandPos;
            }
            bandp[2] = nw + 8, lowp[2] = bandp[2] + kM * kBandPos;
            bandp[4] = lowp[2] + kBandPos, lowp[4] = bandp[4] + kM * kBandPos;
            nw[0] = static_cast<double>(rr), nw[1] = static_cast<double>(first);
            nw[2] = static_cast<double>(w);
          }
          for (int b = 0; b < 5; ++b) {
            if (reuse && (b == 1 || b == 3)) continue;
            const std::ptrdiff_t top = lines[b][0], bottom = lines[b][1];
            const std::ptrdiff_t x1 = x0 + (b < 3 ? r : 2 * r + 1);
            const int np = static_cast<int>(b < 3 ? w + r + 1 : w);
            rect_sums(np, plane, kBandPos, S + bottom + x1, S + top + x1, S + bottom + x0,
                      S + top + x0, bandp[b]);
            side_lows(np, kBandPos, n_min, bandp[b], lowp[b]);
          }
        }
      }
    }
    int m = 0;
    for (const int lim = banded ? kChunk : kSub; ib < nb && m < lim; ++ib) cols[m++] = bcand[ib];
    cc = ib < nb ? bcand[ib] : bend;
    if (m == 0) continue;
    for (int j = 0; j < m; ++j) {
      const Eigen::Vector3d pa = g(grow, cols[j]), pt = pa - o;
      Pc[j] = pt.x(), Pc[kChunk + j] = pt.y(), Pc[2 * kChunk + j] = pt.z();
      FLc[j] = cell_floor(pa, et);
    }
    // no clipping: all corners inside the images; then the sums of the span cols[0] ..
    // cols[m - 1] are contiguous (run: the cells are the span; else up to kSpan columns summed
    // vectorised and the cells' columns picked out: the same bits as corner reads per cell)
    const std::ptrdiff_t span = cols[m - 1] - cols[0] + 1;
    const bool inside = rr - r >= 0 && rr + r + 1 <= H && cols[0] - r >= 0 &&
                        cols[m - 1] + r + 1 <= W;
    const bool run = inside && span == m, spanned = inside && span <= kSpan;
    // a side's position in its band (banded chunks)
    const auto bpos = [&](int s, std::ptrdiff_t c) { return c - b0 + (kRight[s] ? r + 1 : 0); };
    // banded: sides [s0, s1)' sums of the n cells cs[0 .. n) into mm (side s of cell f: s * n + f)
    const auto band_sides = [&](const std::ptrdiff_t* cs, int n, int s0 = 0, int s1 = 8) {
      for (int s = s0; s < s1; ++s) {
        const double* const bs = bandp[kBandOf[s]];
        for (int f = 0; f < n; ++f) {
          const std::ptrdiff_t i = bpos(s, cs[f]);
          for (int q = 0; q < kM; ++q) mm[q * kCap + s * n + f] = bs[q * kBandPos + i];
        }
      }
    };
    for (int s = 0; s < 8 && !banded; ++s) {
      const std::ptrdiff_t r0 = std::clamp<std::ptrdiff_t>(rr + offset(kSides[s][0], r), 0, H);
      const std::ptrdiff_t r1 =
          std::clamp<std::ptrdiff_t>(rr + offset(kSides[s][1], r) + 1, 0, H);
      const std::ptrdiff_t top = srow(r0), bottom = srow(r1);
      if (run || spanned) {  // no clipping: contiguous corners
        const std::ptrdiff_t x0 = cols[0] + offset(kSides[s][2], r) - f0;
        const std::ptrdiff_t x1 = cols[0] + offset(kSides[s][3], r) + 1 - f0;
        if (run) {
          rect_sums(m, plane, kCap, S + bottom + x1, S + top + x1, S + bottom + x0,
                    S + top + x0, mm + s * m);
          continue;
        }
        rect_sums(static_cast<int>(span), plane, kSpan, S + bottom + x1, S + top + x1,
                  S + bottom + x0, S + top + x0, spn);
        for (int q = 0; q < kM; ++q) {
          for (int j = 0; j < m; ++j) mm[q * kCap + s * m + j] = spn[q * kSpan + cols[j] - cols[0]];
        }
        continue;
      }
      for (int j = 0; j < m; ++j) {
        const std::ptrdiff_t c = cols[j];
        const std::ptrdiff_t x0 =
            std::clamp<std::ptrdiff_t>(c + offset(kSides[s][2], r), 0, W) - f0;
        const std::ptrdiff_t x1 =
            std::clamp<std::ptrdiff_t>(c + offset(kSides[s][3], r) + 1, 0, W) - f0;
        const int e = s * m + j;
        for (int q = 0; q < kM; ++q) {
          const double* Sq = S + q * plane;
          mm[q * kCap + e] = Sq[bottom + x1] - Sq[top + x1] - Sq[bottom + x0] + Sq[top + x0];
        }
      }
    }
    // Shortcut (exact): a cell that fits a clean side cannot become ABNORMAL (step 6), unless
    // it lies before an outline (step 5, outline_lip: those are judged in full).
    // Solve only the side s* with the smallest rms lower bound: when its rms is within
    // kCleanRatio of the smallest bound it is clean whatever the other sides give, and
    // when the cell fits it the verdict is "no" without the other seven solves. The
    // others (and cells without a supported side: no valid side, "no") go on below.
    const double* low8[8];  // side s's bound of cell j at low8[s][j]
    if (banded) {  // straight from the bands: position j of the span cols[0] .. cols[m - 1]
      for (int s = 0; s < 8; ++s) low8[s] = lowp[kBandOf[s]] + bpos(s, cols[0]);
    } else {
      side_lows(8 * m, kCap, n_min, mm, lowb);
      for (int s = 0; s < 8; ++s) low8[s] = lowb + s * m;
    }
    int nf = 0;
    {
      double mm1[kM * kChunk], M1[6 * kChunk], E1[6 * kChunk], nn1[kChunk], ce1[3 * kChunk];
      double F1[6 * kChunk], low1[kChunk];
      double use1[kChunk], empty1[kChunk], ok1[kChunk], redo1[kChunk], valid1[kChunk];
      std::int64_t sb[kChunk];
      if (banded && span != m) {  // the span's positions, then the cells' picked out
        double lows[kChunk];
        std::int64_t sbs[kChunk];
        best_sides(static_cast<int>(span), low8, sbs, lows);
        for (int j = 0; j < m; ++j) {
          sb[j] = sbs[cols[j] - cols[0]];
          low1[j] = lows[cols[j] - cols[0]];
        }
      } else {
        best_sides(m, low8, sb, low1);
      }
      const double* sbase[8];  // side s of cell j: from sbase[s] + cols[j] - cols[0] (banded)
      for (int s = 0; banded && s < 8; ++s) sbase[s] = bandp[kBandOf[s]] + bpos(s, cols[0]);
      for (int j = 0; j < m; ++j) {
        if (banded) {
          const double* const bs = sbase[sb[j]] + (cols[j] - cols[0]);
          for (int q = 0; q < kM; ++q) mm1[q * kChunk + j] = bs[q * kBandPos];
          continue;
        }
        const int e = static_cast<int>(sb[j]) * m + j;
        for (int q = 0; q < kM; ++q) mm1[q * kChunk + j] = mm[q * kCap + e];
      }
      side_moments(m, kChunk, n_min, mm1, nn1, ce1, M1, use1, empty1);
      smallest_eigenpairs_long(m, kChunk, M1, E1, ok1, redo1);
      side_planes(m, kChunk, et.k, use1, ok1, E1, nn1, ce1, Pc, FLc, valid1, F1);
      double fits[kChunk];
      fits_clean_side(m, kChunk, redo1, valid1, empty1, low1, F1, fits);
      // a cell that fits may be a lip across a convex feature (crossing_lip) when one of its
      // sides reaches (side_reaches): those are judged in full below
      double reach[kChunk];  // (read only where fits[j]: not computed when no cell fits)
      int n_fit = 0;
      for (int j = 0; j < m; ++j) n_fit += fits[j] != 0.0;
      if (!fit_only && n_fit > 0) {
        const double lim2 = et.k * et.k * (1.0 - 1e-6);  // h > tol >= k rms
        const double flo2 = kCrossingFloor * et.floor * kCrossingFloor * et.floor * (1.0 - 1e-6);
        const double* const U = F1 + 3 * kChunk;  // the solved side's normal
        const double* mm8[8];
        if (!banded || span == m) {  // the chunk's sides in place: mm (s * m + j) or the bands
          for (int s = 0; s < 8; ++s) {
            mm8[s] = banded ? bandp[kBandOf[s]] + bpos(s, cols[0]) : mm + s * m;
          }
          side_reaches(m, banded ? kBandPos : kCap, n_min, lim2, flo2, mm8, low8, Pc, U, kChunk,
                       reach);
        } else {  // scattered banded cells: the fitting ones' sides gathered, kSub at a time
                  // (into mm: a banded chunk reads its sums from the bands)
          int fit[kChunk], nfit = 0;
          for (int j = 0; j < m; ++j) {
            reach[j] = 0.0;
            fit[nfit] = j;
            nfit += fits[j] != 0.0;
          }
          double lq[kCap], pq[3 * kSub], uq[3 * kSub], rq[kSub];
          std::ptrdiff_t fc[kSub];
          const double* lq8[8];
          for (int f0 = 0; f0 < nfit; f0 += kSub) {
            const int mf = std::min(kSub, nfit - f0);
            for (int f = 0; f < mf; ++f) fc[f] = cols[fit[f0 + f]];
            band_sides(fc, mf);
            for (int s = 0; s < 8; ++s) {
              for (int f = 0; f < mf; ++f) lq[s * mf + f] = lowp[kBandOf[s]][bpos(s, fc[f])];
              mm8[s] = mm + s * mf, lq8[s] = lq + s * mf;
            }
            for (int f = 0; f < mf; ++f) {
              for (int q = 0; q < 3; ++q) {
                pq[q * kSub + f] = Pc[q * kChunk + fit[f0 + f]];
                uq[q * kSub + f] = U[q * kChunk + fit[f0 + f]];
              }
            }
            side_reaches(mf, kCap, n_min, lim2, flo2, mm8, lq8, pq, uq, kSub, rq);
            for (int f = 0; f < mf; ++f) reach[fit[f0 + f]] = rq[f];
          }
        }
      }
      for (int j = 0; j < m; ++j) {
        const std::ptrdiff_t i = cols[j];
        if (!use1[j]) {  // no side with support: none to fit or stand proud of; a fin?
          mark[i] = !fit_only && is_fin(g, lab, grow, cols[j], r) ? 1 : 0;
          continue;
        }
        // before an outline a fit does not settle it (outline_lip): judged in full below
        const auto before_outline = [&] {
          for (int s = 0; s < 8; ++s) {
            const double inv = banded ? bandp[kBandOf[s]][10 * kBandPos + bpos(s, cols[j])]
                                      : mm[10 * kCap + s * m + j];
            if (inv >= outline_at[s]) return true;
          }
          return false;
        };
        if (fits[j] != 0.0 && (fit_only || (reach[j] == 0.0 && !before_outline()))) {
          mark[i] = fit_only ? 1 : 0;
          continue;
        }
        keep[nf] = j;
        cols[nf++] = cols[j];
      }
    }
    // The cells left (cols[0 .. nf), keep: their index in the chunk), kSub at a time: in the
    // loop, m, cols and keep are the sub-chunk's. Their sides' sums to the front of mm: from
    // the bands, or (unbanded: one sub-chunk) entry s * mc + keep[f] moved to s * m + f.
    // The four quadrants (entries 4 m .. 8 m) are solved first: a cell on a smooth curved
    // surface (curved_cells) is settled by them, and only the others solve the four halves.
    const int mc = m;
    const std::ptrdiff_t* const left = cols;
    const int* const left_keep = keep;
    // solve entries [e0, e0 + n) (sums in mm, cells in P, floors in FL): moments, eigenpairs,
    // planes, and the scalar routine where Newton needs more steps
    const auto solve_sides = [&](int e0, int n) {
      side_moments(n, kCap, n_min, mm + e0, nnb + e0, ceb + e0, Mb + e0, useb + e0, emptyb + e0);
      smallest_eigenpairs_long(n, kCap, Mb + e0, Eb + e0, okb + e0, redob + e0);
      side_planes(n, kCap, et.k, useb + e0, okb + e0, Eb + e0, nnb + e0, ceb + e0, P + e0,
                  FL + e0, validb + e0, F + e0);
      for (int e = e0; e < e0 + n; ++e) {
        if (!redob[e] || !useb[e]) continue;
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
                   ceb[kCap + e], ceb[2 * kCap + e], P[e], P[kCap + e], P[2 * kCap + e], et.k,
                   FL[e], validb[e], F[e], F[kCap + e], F[2 * kCap + e], F[3 * kCap + e],
                   F[4 * kCap + e], F[5 * kCap + e]);
      }
    };
    // sides [0, ns) of the n cells idx[0 .. n) of a set of `from` cells moved down in mm, from
    // entry s * from + idx[f] to s * n + f (idx ascending: none is overwritten before it moves)
    const auto move_sums = [&](int ns, int from, const int* idx, int n) {
      for (int s = 0; s < ns; ++s) {
        for (int f = 0; f < n; ++f) {
          const int a = s * from + idx[f], b = s * n + f;
          if (a == b) continue;
          for (int q = 0; q < kM; ++q) mm[q * kCap + b] = mm[q * kCap + a];
        }
      }
    };
    // the cells' points and floors for sides [s0, s1) of n cells, cell f from chunk cell ck[f]
    const auto side_cells = [&](const int* ck, int n, int s0, int s1) {
      for (int s = s0; s < s1; ++s) {
        for (int f = 0; f < n; ++f) {
          for (int q = 0; q < 3; ++q) P[q * kCap + s * n + f] = Pc[q * kChunk + ck[f]];
          FL[s * n + f] = FLc[ck[f]];
        }
      }
    };
    for (int fa = 0; fa < nf; fa += kSub) {
      const int m = std::min(kSub, nf - fa);
      const std::ptrdiff_t* const cols = left + fa;
      const int* const keep = left_keep + fa;
      if (banded) {
        band_sides(cols, m, 4, 8);
      } else if (m != mc) {
        move_sums(8, mc, keep, m);
      }
      side_cells(keep, m, 4, 8);
      solve_sides(4 * m, 4 * m);
      double curved[kSub];
      if (fit_only) {
        std::fill(curved, curved + m, 0.0);
      } else {
        curved_cells(m, kCap, et.k, validb + 4 * m, emptyb + 4 * m, F + 4 * m, ceb + 4 * m,
                     Mb + 4 * m, nnb + 4 * m, P + 4 * m, FL + 4 * m, curved);
      }
      // the others (cell f of mu: sub-chunk cell jj[f]) solve their halves at s * mu + f
      // (unbanded: moved down from s * m + jj[f])
      int jj[kSub], kj[kSub], mu = 0;
      for (int j = 0; j < m; ++j) {
        mark[cols[j]] = 0;
        jj[mu] = j;
        kj[mu] = keep[j];
        mu += curved[j] == 0.0;
      }
      if (mu == 0) continue;
      std::ptrdiff_t cu[kSub];
      for (int f = 0; f < mu; ++f) cu[f] = cols[jj[f]];
      if (banded) {
        band_sides(cu, mu, 0, 4);
      } else if (mu != m) {
        move_sums(4, m, jj, mu);
      }
      side_cells(kj, mu, 0, 4);
      solve_sides(0, 4 * mu);
      for (int f = 0; f < mu; ++f) {
        const int j = jj[f];
        const std::ptrdiff_t i = cols[j];
        Side sd[8];
        double best = std::numeric_limits<double>::infinity();
        for (int s = 0; s < 8; ++s) {
          const int e = s < 4 ? s * mu + f : s * m + j;
          Side& x = sd[s];
          x.empty = emptyb[e] != 0;
          x.outline = emptyb[e] >= outline_at[s];
          x.centroid = Eigen::Vector3d(ceb[e], ceb[kCap + e], ceb[2 * kCap + e]);
          x.valid = validb[e] != 0;
          if (!x.valid) continue;
          x.h = F[e];
          x.rms = F[kCap + e];
          x.tol = F[2 * kCap + e];
          x.normal = Eigen::Vector3d(F[3 * kCap + e], F[4 * kCap + e], F[5 * kCap + e]);
          x.steep = x.normal.z() < kEdgeSteepCos;
          if (!x.steep) best = std::min(best, x.rms);
        }
        // P fits a clean side (`fits`; one with a return: `fits_ground`): then no rule of
        // step 6 or 7 flags it but hanging, which a fit to an empty side does not clear (and
        // step 7 needs every clean side more than 2 tol off), and a lip before an outline
        // (step 5), which a fit along the outline does not clear
        bool fits = false, fits_ground = false;
        for (const Side& x : sd) {
          if (edge_fits(x, best)) {
            fits = true;
            fits_ground = fits_ground || !x.empty;
          }
        }
        if (fit_only) {
          mark[i] = fits_ground ? 1 : 0;
          continue;
        }
        const auto attached_to = [&](int s) {
          return attached(g, lab, grow, cols[j], r, o, sd[s], s);
        };
        bool abnormal = !fits && (edge_proud(sd, best, [](int s) { return kOpposite[s]; },
                                             attached_to) ||
                                  is_fin(g, lab, grow, cols[j], r) ||
                                  is_lip(g, lab, grow, cols[j], r, sd, best) ||
                                  in_valley(g, lab, grow, cols[j], r, sd));
        if (!abnormal && fits) {
          abnormal = outline_lip(sd, best, attached_to) ||
                     crossing_lip(sd, best, et.floor, attached_to);
        }
        if (!abnormal && !fits_ground) {
          abnormal = is_hanging(g, lab, grow, cols[j], r, o, sd, best);
        }
        if (!abnormal && !fits) abnormal = is_spike(g, lab, grow, rr, cols[j], H, o, sd, best);
        mark[i] = abnormal ? 1 : 0;
      }
    }
  }
}

namespace {

// The passes on `g`. Each kTileRows x kTileCols tile of the grid (fixed in grid coordinates, as
// the window fits' tiles) gets its own integral images over the tile and the r cells around it,
// relative to the tile's first finite cell (row-major). So a cell's sums depend on nothing
// beyond its tile and r cells around it (a block of miem.dask that starts on a tile boundary
// gives the same bits), and they stay small: sums cumulated over a whole tall grid lose the
// precision that the smallest eigenvalue needs.
template <typename T>
int run_passes(const GridView<T>& g, std::uint8_t* labels, int window, EdgeTol et,
               int max_iterations, int num_threads, std::vector<double>& scratch,
               CellBytes& flags, const std::uint8_t* lines, const std::uint8_t* planes) {
  constexpr std::ptrdiff_t kTileRows = kEdgeTileRows, kTileCols = kEdgeTileCols;
  const std::ptrdiff_t H = g.rows, W = g.cols, N = H * W, r = window / 2;
  const std::ptrdiff_t ER = std::min(H, kTileRows + 2 * r), EC = std::min(W, kTileCols + 2 * r);
  // integral images as kM planes (one per moment) of ER + 1 rows of L = EC + 1 columns
  const std::ptrdiff_t L = EC + 1, plane = (ER + 1) * L;
  // the band cache of edge_judge_row (ordinary window sizes only: it grows with r)
  const std::ptrdiff_t cache_slots =
      r <= 15 ? (r + 2) * ((kTileCols + kEdgeBandCells - 1) / kEdgeBandCells) : 0;
  // a thread's images + column sums + band cache
  const std::ptrdiff_t per = kM * plane + kM * EC + cache_slots * kEdgeCacheSlot;
  const std::ptrdiff_t tiles_r = (H + kTileRows - 1) / kTileRows;
  const std::ptrdiff_t tiles_c = (W + kTileCols - 1) / kTileCols;
  const int nt = std::max(1, std::min<int>(thread_count(num_threads, N),
                                           static_cast<int>(tiles_r * tiles_c)));
  const std::size_t need = static_cast<std::size_t>(per * nt);
  if (scratch.size() < need) scratch.resize(need);
  if (flags.size() < static_cast<std::size_t>(2 * N)) flags.resize(static_cast<std::size_t>(2 * N));
  std::uint8_t* const todo = flags.data();
  std::uint8_t* const mark = todo + N;
  const int ntn = thread_count(num_threads, N);  // the per-cell scans
  // the tiles with a todo cell (the others are skipped: no scan of their cells), and a pass's
  // such tiles in order; a tile's marks are read only while it has its flag
  std::vector<std::uint8_t> tile_todo(static_cast<std::size_t>(tiles_r * tiles_c), 1);
  // tile t's cells: rows [R0, R1), columns [C0, C1) (clipped at the grid's border)
  struct TileBox {
    std::ptrdiff_t R0, R1, C0, C1;
  };
  const auto tile_box = [&](std::ptrdiff_t t) {
    const std::ptrdiff_t R0 = (t / tiles_c) * kTileRows, C0 = (t % tiles_c) * kTileCols;
    return TileBox{R0, std::min(H, R0 + kTileRows), C0, std::min(W, C0 + kTileCols)};
  };
  // One pass over the tiles with tile_todo: the verdicts (or, for step 9, the fits) of the
  // todo cells into mark.
  const auto judge_tiles = [&](EdgeJudgment judge) {
    const bool any_label = judge == EdgeJudgment::kFitsGround;
#pragma omp parallel for schedule(dynamic, 1) num_threads(nt) if (nt > 1)
    for (std::ptrdiff_t tile = 0; tile < tiles_r * tiles_c; ++tile) {
      if (!tile_todo[static_cast<std::size_t>(tile)]) continue;
#ifdef MIEM_HAVE_OPENMP
      double* const S = scratch.data() + per * omp_get_thread_num();
#else
      double* const S = scratch.data();
#endif
      double* const col = S + kM * plane;  // moment q of column x at col[q * EC + x]
      const EdgeBandCache cache{col + kM * EC, cache_slots};
      const auto [R0, R1, C0, C1] = tile_box(tile);
      // the last row and column with a candidate (after the first pass candidates are the
      // windows around new ABNORMAL cells, often a corner of the tile)
      std::ptrdiff_t rfirst = -1, rlast = -1, clast = -1;
      for (std::ptrdiff_t rr = R0; rr < R1; ++rr) {
        std::fill(mark + rr * W + C0, mark + rr * W + C1, std::uint8_t{0});
        std::ptrdiff_t cc = C1 - 1;  // the row's last candidate (from the end: often C1 - 1)
        for (const std::ptrdiff_t i = rr * W; cc >= C0; --cc) {
          // 8 cells at a time while none is to do (most, after the quiet cells leave pass 1)
          for (std::uint64_t w; cc - 7 >= C0; cc -= 8) {
            std::memcpy(&w, todo + i + cc - 7, 8);
            if (w != 0) break;
          }
          if (cc < C0) break;
          const std::uint8_t l = labels[i + cc];
          if (todo[i + cc] && (any_label || l == kNormal || l == kEdge)) break;
        }
        if (cc < C0) continue;
        if (rfirst < 0) rfirst = rr;
        rlast = rr;
        clast = std::max(clast, cc);
      }
      if (rlast < 0) continue;
      // the tile's origin: its first finite cell (a candidate is finite, so there is one)
      Eigen::Vector3d o = Eigen::Vector3d::Zero();
      for (std::ptrdiff_t i = 0; i < (R1 - R0) * (C1 - C0); ++i) {
        const std::ptrdiff_t rr = R0 + i / (C1 - C0), cc = C0 + i % (C1 - C0);
        if (g.finite(rr, cc)) {
          o = g(rr, cc);
          break;
        }
      }
      // integral images over rows e0..e1, columns f0..f1: running sums down each column, then
      // along each row (NumPy's order); local row s holds the sums over rows e0 .. e0 + s - 1
      // (only up to r past the last candidate row and column: the images there are never read;
      // the sums start at e0, f0 whatever the candidates, so every image value read is the same)
      const std::ptrdiff_t e0 = std::max<std::ptrdiff_t>(0, R0 - r);
      const std::ptrdiff_t e1 = std::min(H, rlast + r + 1);
      const std::ptrdiff_t f0 = std::max<std::ptrdiff_t>(0, C0 - r);
      const std::ptrdiff_t f1 = std::min(W, clast + r + 1);
      const std::ptrdiff_t ew = f1 - f0;
      std::fill(col, col + kM * EC, 0.0);
      for (int q = 0; q < kM; ++q) std::fill(S + q * plane, S + q * plane + ew + 1, 0.0);
      // A pass reads image rows rfirst - r and below only (rectangles of candidate rows from
      // rfirst on, clipped at the grid's border): grid rows before rfirst - r - 1 (whose image
      // rows are the ones before) add to the column sums alone.
      for (std::ptrdiff_t rr = e0; rr < e1; ++rr) {
        if (rr < rfirst - r - 1) {
          edge_column_row(g, rr, labels + rr * W, f0, f1, o, col, EC);
          continue;
        }
        edge_image_row(g, rr, labels + rr * W, f0, f1, o, col, EC, S + (rr - e0 + 1) * L, plane);
      }
      const EdgeImages im{S, plane, L, e0, ER + 1, f0};
      cache.clear();
      for (std::ptrdiff_t rr = rfirst; rr <= rlast; ++rr) {  // (rows without a candidate: none)
        edge_judge_row(g, rr, rr, H, C0, clast + 1, im, o, r, et, labels, todo + rr * W,
                       mark + rr * W, &cache, judge);
      }
    }
  };
  if (lines != nullptr) {  // step 9: ABNORMAL cells beside a feature line that fit a clean side
    std::fill(tile_todo.begin(), tile_todo.end(), std::uint8_t{0});
    std::memset(todo, 0, static_cast<std::size_t>(N));
    std::vector<std::int64_t> back;  // the candidates
    for (std::ptrdiff_t i = 0; i < N; ++i) {
      const void* next = std::memchr(labels + i, kAbnormal, static_cast<std::size_t>(N - i));
      if (next == nullptr) break;  // (ABNORMAL cells are few: memchr skips the rest)
      i = static_cast<const std::uint8_t*>(next) - labels;
      const std::ptrdiff_t rr = i / W, cc = i % W;
      const auto line = [&](std::ptrdiff_t a, std::ptrdiff_t b) {
        return (lines[a * W + b] & kLine) != 0;
      };
      if (!beside_line(line, rr, cc, H, W)) continue;
      todo[i] = 1;
      tile_todo[static_cast<std::size_t>((rr / kTileRows) * tiles_c + cc / kTileCols)] = 1;
      back.push_back(i);
    }
    if (!back.empty()) {
      judge_tiles(EdgeJudgment::kFitsGround);
      for (const std::int64_t i : back) {
        if (mark[i]) labels[i] = kEdge;
      }
    }
    std::fill(tile_todo.begin(), tile_todo.end(), std::uint8_t{1});
  }
  parallel_ranges(ntn, N, 64, [todo, labels](int, std::ptrdiff_t i0, std::ptrdiff_t i1) {
    // (local restrict pointers and no short circuit: vectorised; through the captured
    // pointers every byte store reloaded them)
    std::uint8_t* __restrict td = todo;
    const std::uint8_t* __restrict lb = labels;
    for (std::ptrdiff_t i = i0; i < i1; ++i) {
      td[i] = static_cast<std::uint8_t>((lb[i] == kNormal) | (lb[i] == kEdge));
    }
  });
  // pass 1 leaves out the quiet cells (step 1), each thread its rows' window counts
  if (planes != nullptr) {
    parallel_ranges(ntn, H, 16, [&](int, std::ptrdiff_t x0, std::ptrdiff_t x1) {
      std::vector<std::int32_t> buf(static_cast<std::size_t>(QuietCounts::ints(W, r)));
      const QuietCounts qw = QuietCounts::over(buf.data(), W, r);
      qw.clear();
      for (std::ptrdiff_t a = std::max<std::ptrdiff_t>(0, x0 - r); a < std::min(H, x0 + r); ++a)
        qw.add(labels + a * W, 1);
      for (std::ptrdiff_t x = x0; x < x1; ++x) {
        if (x + r < H) qw.add(labels + (x + r) * W, 1);
        qw.drop(labels + x * W, labels + (x + 1) * W, std::min(r, H - 1 - x), planes + x * W,
                kHQuiet | kHStale, kHQuiet, todo + x * W);
        if (x - r >= 0) qw.add(labels + (x - r) * W, -1);
      }
    });
    // pass 1's tiles: those with a candidate left (the others cost no scan of their cells, in
    // the judgment nor in the collection of its marks)
    parallel_ranges(ntn, tiles_r * tiles_c, 1, [&](int, std::ptrdiff_t t0, std::ptrdiff_t t1) {
      for (std::ptrdiff_t t = t0; t < t1; ++t) {
        const auto [R0, R1, C0, C1] = tile_box(t);
        bool any = false;
        for (std::ptrdiff_t rr = R0; rr < R1 && !any; ++rr) {
          any = next_nonzero(todo + rr * W + C0, 0, C1 - C0) < C1 - C0;
        }
        tile_todo[static_cast<std::size_t>(t)] = any ? 1 : 0;
      }
    });
  }
  std::vector<std::int64_t> added;  // a pass's new ABNORMAL cells
  std::vector<std::int64_t> active;
  int passes = 0;
  for (int it = 0; it < max_iterations; ++it) {
    ++passes;
    judge_tiles(EdgeJudgment::kVerdict);
    // the flagged tiles' rows (unit u: row u % kTileRows of tile active[u / kTileRows]):
    // their todo cleared, their marks made ABNORMAL and collected (per thread, joined in order)
    active.clear();
    for (std::ptrdiff_t t = 0; t < tiles_r * tiles_c; ++t) {
      if (tile_todo[static_cast<std::size_t>(t)]) active.push_back(t);
      tile_todo[static_cast<std::size_t>(t)] = 0;
    }
    const std::ptrdiff_t units = static_cast<std::ptrdiff_t>(active.size()) * kTileRows;
    collect_ranges(ntn, units, kTileRows, added,
                   [&](std::ptrdiff_t u0, std::ptrdiff_t u1, std::vector<std::int64_t>& part) {
      for (std::ptrdiff_t u = u0; u < u1; ++u) {
        const std::ptrdiff_t t = active[static_cast<std::size_t>(u / kTileRows)];
        const TileBox b = tile_box(t);
        const std::ptrdiff_t rr = b.R0 + u % kTileRows, C0 = b.C0, C1 = b.C1;
        if (rr >= b.R1) continue;
        std::fill(todo + rr * W + C0, todo + rr * W + C1, std::uint8_t{0});
        for (std::ptrdiff_t i = rr * W + C0; i < rr * W + C1;) {
          std::uint64_t w8 = 0;  // 8 marks at a time: most are 0
          if (i + 8 <= rr * W + C1) {
            std::memcpy(&w8, mark + i, 8);
            if (w8 == 0) {
              i += 8;
              continue;
            }
          }
          if (mark[i]) {
            labels[i] = kAbnormal;
            part.push_back(i);
          }
          ++i;
        }
      }
    });
    for (const std::int64_t i : added) {
      // only cells with a new ABNORMAL cell in their window can change at the next pass
      const std::ptrdiff_t rr = i / W, cc = i % W;
      const std::ptrdiff_t a0 = std::max<std::ptrdiff_t>(0, rr - r), a1 = std::min(H - 1, rr + r);
      const std::ptrdiff_t b0 = std::max<std::ptrdiff_t>(0, cc - r), b1 = std::min(W - 1, cc + r);
      for (std::ptrdiff_t a = a0; a <= a1; ++a) {
        for (std::ptrdiff_t b = b0; b <= b1; ++b) todo[a * W + b] = 1;
      }
      for (std::ptrdiff_t ta = a0 / kTileRows; ta <= a1 / kTileRows; ++ta) {
        for (std::ptrdiff_t tb = b0 / kTileCols; tb <= b1 / kTileCols; ++tb) {
          tile_todo[static_cast<std::size_t>(ta * tiles_c + tb)] = 1;
        }
      }
    }
    if (added.empty()) break;
  }
  return passes;
}

}  // namespace

template <typename T>
int edge_passes(const GridView<T>& g, std::uint8_t* labels, int window, EdgeTol et,
                int max_iterations, int num_threads, std::vector<double>& scratch,
                CellBytes& flags, const std::uint8_t* lines, const std::uint8_t* planes) {
  return run_passes(g, labels, window, et, max_iterations, num_threads, scratch, flags, lines,
                    planes);
}

template <typename T>
int edge_stage(const GridView<T>& g, const DetectParams& p, std::uint8_t* labels,
               bool height_test, Workspace& ws) {
  const std::size_t N = static_cast<std::size_t>(g.rows * g.cols);
  if (!height_test) {  // step 9's feature lines: every EDGE cell
    ws.cls.resize(N);
    for (std::size_t i = 0; i < N; ++i) ws.cls[i] = labels[i] == kEdge ? kLine : 0;
  }
  // the quiet cells' planes: the height test's first pass (none without it)
  return edge_passes(g, labels, p.edge_window, edge_tol(p, edge_precision<T>()),
                     p.max_iterations, p.num_threads,
                     ws.edge_sums, ws.edge_flags, ws.cls.data(),
                     height_test ? ws.hmask.data() : nullptr);
}

template int edge_stage<float>(const GridView<float>&, const DetectParams&, std::uint8_t*, bool,
                               Workspace&);
template int edge_stage<double>(const GridView<double>&, const DetectParams&, std::uint8_t*,
                                bool, Workspace&);
template int edge_passes<float>(const GridView<float>&, std::uint8_t*, int, EdgeTol, int, int,
                                std::vector<double>&, CellBytes&, const std::uint8_t*,
                                const std::uint8_t*);
template int edge_passes<double>(const GridView<double>&, std::uint8_t*, int, EdgeTol, int, int,
                                 std::vector<double>&, CellBytes&, const std::uint8_t*,
                                 const std::uint8_t*);

#define MIEM_EDGE_ROWS(T)                                                                     \
  template void edge_image_row<T>(const GridView<T>&, std::ptrdiff_t, const std::uint8_t*,      \
                                  std::ptrdiff_t, std::ptrdiff_t, const Eigen::Vector3d&,       \
                                  double*, std::ptrdiff_t, double*, std::ptrdiff_t);            \
  template void edge_judge_row<T>(const GridView<T>&, std::ptrdiff_t, std::ptrdiff_t,            \
                                  std::ptrdiff_t, std::ptrdiff_t, std::ptrdiff_t,               \
                                  const EdgeImages&, const Eigen::Vector3d&, std::ptrdiff_t,    \
                                  EdgeTol, const std::uint8_t*, const std::uint8_t*,            \
                                  std::uint8_t*, const EdgeBandCache*, EdgeJudgment);
MIEM_EDGE_ROWS(float)
MIEM_EDGE_ROWS(double)
#undef MIEM_EDGE_ROWS

}  // namespace miem::detail
