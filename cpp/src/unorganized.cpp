// MIEM on unorganized clouds. Every per-point result (normal, judgment, height) depends only on
// the point's neighbourhood, gathered from the grid in a fixed order (cell key, then index), so the
// points are independent within a pass (Jacobi) and the output is identical for any thread count.
// Batch passes share one gather among the points of a grid cell; later passes re-judge, one by
// one, only the points within `radius` of a newly removed point.
#include "miem/unorganized.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>

#include "defects.hpp"
#include "miem/neighbor_grid.hpp"
#include "parallel.hpp"

namespace miem {

namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kPi = 3.14159265358979323846;
constexpr double kRadToDeg = 57.29577951308232;
constexpr double kDegToRad = 0.017453292519943295;
constexpr int kMaxDirections = 8;

template <typename T>
void check_view(const PointsView<T>& points) {
  if (points.size < 0 || (points.size > 0 && points.data == nullptr)) {
    throw std::invalid_argument("points: null data");
  }
}

template <typename T>
std::ptrdiff_t count_finite(const PointsView<T>& points, int num_threads) {
  std::ptrdiff_t n = 0;
  const int nt = detail::thread_count(num_threads, points.size);
#pragma omp parallel for schedule(static) num_threads(nt) if (nt > 1) reduction(+ : n)
  for (std::ptrdiff_t i = 0; i < points.size; ++i) n += points[i].allFinite();
  return n;
}

// Candidate points gathered from a box of cells, structure of arrays (absolute coordinates, so
// q - p is computed exactly as a brute-force search would).
struct Gather {
  std::vector<double> x, y, z;
  std::vector<std::uint32_t> id;
  std::size_t n = 0;

  void clear() { n = 0; }
  void push(const Eigen::Vector3d& q, std::uint32_t j) {
    if (n == x.size()) {
      const std::size_t cap = std::max<std::size_t>(64, 2 * n);
      x.resize(cap);
      y.resize(cap);
      z.resize(cap);
      id.resize(cap);
    }
    x[n] = q.x();
    y[n] = q.y();
    z[n] = q.z();
    id[n] = j;
    ++n;
  }
};

// The selected neighbourhood of one point: offsets w = q - p and their squared lengths.
struct Selection {
  std::vector<double> wx, wy, wz, d2;
  std::vector<std::uint32_t> id;
  std::size_t n = 0;

  void reserve(std::size_t cap) {
    if (wx.size() < cap) {
      wx.resize(cap);
      wy.resize(cap);
      wz.resize(cap);
      d2.resize(cap);
      id.resize(cap);
    }
  }
};

// Gather the points of `box` that pass `keep(position in order(), index)`, in cell-key order.
template <typename T, typename Keep>
void gather_box(const NeighborGrid<T>& grid, const CellBox& box, Keep&& keep, Gather& g) {
  g.clear();
  const std::uint32_t* order = grid.order();
  grid.for_each_cell(box, [&](std::ptrdiff_t cell) {
    const std::uint32_t e = grid.cell_begin(cell + 1);
    for (std::uint32_t k = grid.cell_begin(cell); k < e; ++k) {
      const std::uint32_t j = order[k];
      if (keep(k, j)) g.push(grid.sorted_point(k), j);
    }
  });
}

// Select the gathered points within r of p (excluding index `self`, pass -1 to keep it).
// Branchless compaction: every candidate is written, the count advances only for the kept ones.
inline void select(const Gather& g, const Eigen::Vector3d& p, double r2, std::int64_t self,
                   Selection& s) {
  s.reserve(g.n + 1);
  const double* __restrict gx = g.x.data();
  const double* __restrict gy = g.y.data();
  const double* __restrict gz = g.z.data();
  const std::uint32_t* __restrict gid = g.id.data();
  double* __restrict wx = s.wx.data();
  double* __restrict wy = s.wy.data();
  double* __restrict wz = s.wz.data();
  double* __restrict sd2 = s.d2.data();
  std::uint32_t* __restrict sid = s.id.data();
  std::size_t m = 0;
  const double px = p.x(), py = p.y(), pz = p.z();
  const std::size_t n = g.n;
  for (std::size_t k = 0; k < n; ++k) {
    const double dx = gx[k] - px, dy = gy[k] - py, dz = gz[k] - pz;
    const double d2 = dx * dx + dy * dy + dz * dz;
    wx[m] = dx;
    wy[m] = dy;
    wz[m] = dz;
    sd2[m] = d2;
    sid[m] = gid[k];
    m += static_cast<std::size_t>((d2 <= r2) & (static_cast<std::int64_t>(gid[k]) != self));
  }
  s.n = m;
}

// Eigen-decomposition of a symmetric 3 x 3 scatter matrix: eigenvalues ascending, orthonormal
// eigenvectors in the columns of V. The QR iteration, as in fit_plane: the closed form
// (computeDirect) is 2.5x faster but loses up to ~1e-8 of the norm on nearly collinear or
// 3-point neighbourhoods, which would move normals and the degeneracy test.
inline void eigen_sym3(const Eigen::Matrix3d& M, Eigen::Vector3d& w, Eigen::Matrix3d& V) {
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(M, Eigen::ComputeEigenvectors);
  w = es.info() == Eigen::Success ? es.eigenvalues() : Eigen::Vector3d::Constant(kNaN);
  V = es.eigenvectors();
}

// Eigen plane of a selection (section "Plane fit" of SPEC.md), centred two-pass moments of the
// offsets. On success: oriented normal, largest-eigenvalue eigenvector, the centroid offset from p.
struct LocalPlane {
  Eigen::Vector3d normal, major, mean;
  Eigen::Vector3d eigenvalues;
  std::size_t n = 0;
};

inline PlaneStatus fit_selection(const Selection& s, bool want_major, LocalPlane* out) {
  const std::size_t n = s.n;
  if (n < 3) return PlaneStatus::kTooFewPoints;
  double sx = 0, sy = 0, sz = 0;
  for (std::size_t k = 0; k < n; ++k) {
    sx += s.wx[k];
    sy += s.wy[k];
    sz += s.wz[k];
  }
  const double inv = 1.0 / static_cast<double>(n);
  const double mx = sx * inv, my = sy * inv, mz = sz * inv;
  double xx = 0, xy = 0, xz = 0, yy = 0, yz = 0, zz = 0;
  for (std::size_t k = 0; k < n; ++k) {
    const double a = s.wx[k] - mx, b = s.wy[k] - my, c = s.wz[k] - mz;
    xx += a * a;
    xy += a * b;
    xz += a * c;
    yy += b * b;
    yz += b * c;
    zz += c * c;
  }
  Eigen::Matrix3d M;
  M << xx, xy, xz, xy, yy, yz, xz, yz, zz;
  Eigen::Vector3d ev;
  Eigen::Matrix3d V;
  eigen_sym3(M, ev, V);
  if (!(ev(2) > 0.0) || ev(1) <= 1e-12 * ev(2)) return PlaneStatus::kDegenerate;
  out->normal = orient_normal(V.col(0).normalized());
  if (want_major) {
    Eigen::Vector3d e1 = V.col(2).normalized();
    if (!(ev(2) - ev(1) > 1e-6 * ev(2))) {
      // In-plane isotropic neighbourhood (a regular lattice): the eigenvector is arbitrary, so
      // project the coordinate axis least aligned with n onto the tangent plane (SPEC.md).
      const Eigen::Vector3d& nn = out->normal;
      int ax = 0;
      for (int a = 1; a < 3; ++a) {
        if (std::abs(nn(a)) < std::abs(nn(ax))) ax = a;
      }
      Eigen::Vector3d unit = Eigen::Vector3d::Zero();
      unit(ax) = 1.0;
      const Eigen::Vector3d proj = unit - unit.dot(nn) * nn;
      e1 = proj / std::sqrt(proj.dot(proj));
    }
    int big = 0;
    for (int a = 1; a < 3; ++a) {
      if (std::abs(e1(a)) > std::abs(e1(big))) big = a;
    }
    if (e1(big) < 0.0) e1 = -e1;
    out->major = e1;
  }
  out->mean = Eigen::Vector3d(mx, my, mz);
  out->eigenvalues = ev;
  out->n = n;
  return PlaneStatus::kOk;
}

// Per-thread scratch of the judge.
struct JudgeScratch {
  Gather gather;
  Selection sel;
  std::vector<double> best_d2;  // per (direction, side, scale) slot
  std::vector<int> best_m;      // position in `sel` of the slot's neighbour, -1: none
};

// The judgment of SPEC.md "Unorganized clouds" for one point against a fixed usable set.
class PointJudge {
 public:
  PointJudge(const PointsDetectParams& p, double radius, double min_step)
      : r2_(radius * radius),
        min_step_(min_step),
        K_(p.num_directions),
        min_dirs_(p.min_directions),
        scales_(p.scales),
        cos0_(std::cos(p.theta0_deg * kDegToRad)),
        cos_half_(std::cos(kPi / (2.0 * p.num_directions))) {
    for (int k = 0; k < K_; ++k) {
      const double a = static_cast<double>(k) * kPi / static_cast<double>(K_);
      ck_[k] = std::cos(a);
      sk_[k] = std::sin(a);
    }
  }

  // Judges point `i` at `p` using the candidates already gathered in `js.gather` (a superset of
  // its usable neighbourhood, in grid order).
  std::uint8_t judge(std::uint32_t i, const Eigen::Vector3d& p, JudgeScratch& js,
                     std::uint8_t* flags, double* angle, bool* degenerate) const {
    Selection& s = js.sel;
    select(js.gather, p, r2_, static_cast<std::int64_t>(i), s);
    *flags = 0;
    *angle = kNaN;
    *degenerate = false;
    if (s.n < 3) return kAbnormal;
    LocalPlane lp;
    if (fit_selection(s, true, &lp) != PlaneStatus::kOk) {
      *degenerate = true;
      return kNormal;
    }
    const Eigen::Vector3d n = lp.normal, e1 = lp.major, e2 = n.cross(e1);
    Eigen::Vector3d d[kMaxDirections];
    for (int k = 0; k < K_; ++k) d[k] = ck_[k] * e1 + sk_[k] * e2;
    const int S = static_cast<int>(scales_.size());
    const std::size_t slots = static_cast<std::size_t>(K_) * 2 * S;
    js.best_d2.assign(slots, kInf);
    js.best_m.assign(slots, -1);
    double* __restrict bd2 = js.best_d2.data();
    int* __restrict bm = js.best_m.data();
    const double* wx = s.wx.data();
    const double* wy = s.wy.data();
    const double* wz = s.wz.data();
    const double* sd2 = s.d2.data();
    const std::uint32_t* sid = s.id.data();
    double step_len[16];
    const int S_fast = std::min(S, 16);
    for (int si = 0; si < S_fast; ++si) step_len[si] = scales_[si] * min_step_;
    const int n_sel = static_cast<int>(s.n);
    for (int m = 0; m < n_sel; ++m) {
      const Eigen::Vector3d w(wx[m], wy[m], wz[m]);
      const Eigen::Vector3d t = w - w.dot(n) * n;
      const double tlen = std::sqrt(t.dot(t));
      if (!(tlen > 0.0)) continue;
      const double lim = tlen * cos_half_;
      const double d2 = sd2[m];
      for (int k = 0; k < K_; ++k) {
        const double td = t.dot(d[k]);
        int side;
        if (td >= lim) {
          side = 0;  // g = +1
        } else if (-td >= lim) {
          side = 1;  // g = -1
        } else {
          continue;
        }
        int* slot_m = bm + (k * 2 + side) * S;
        double* slot_d2 = bd2 + (k * 2 + side) * S;
        for (int si = 0; si < S; ++si) {
          const double need = si < S_fast ? step_len[si] : scales_[si] * min_step_;
          if (!(tlen >= need)) continue;
          if (d2 < slot_d2[si] || (d2 == slot_d2[si] && sid[m] < sid[slot_m[si]])) {
            slot_d2[si] = d2;
            slot_m[si] = m;
          }
        }
      }
    }
    int avail = 0, flagged = 0;
    std::uint8_t mask = 0;
    double best_cos = -2.0;
    for (int k = 0; k < K_; ++k) {
      bool dir_avail = false, dir_flag = false;
      for (int si = 0; si < S; ++si) {
        const int mp = bm[(k * 2 + 0) * S + si], mm = bm[(k * 2 + 1) * S + si];
        if (mp < 0 || mm < 0) continue;
        const Eigen::Vector3d u(wx[mm], wy[mm], wz[mm]);  // A - P, A on side -1
        const Eigen::Vector3d v(wx[mp], wy[mp], wz[mp]);  // B - P
        const double uu = sd2[mm], vv = sd2[mp];
        if (uu == 0.0 || vv == 0.0) continue;
        const double cs = std::clamp(u.dot(v) / std::sqrt(uu * vv), -1.0, 1.0);
        dir_avail = true;
        if (cs >= cos0_) dir_flag = true;
        if (cs > best_cos) best_cos = cs;
      }
      avail += dir_avail;
      if (dir_flag) {
        ++flagged;
        mask |= static_cast<std::uint8_t>(1u << k);
      }
    }
    *flags = mask;
    *angle = best_cos > -2.0 ? std::acos(best_cos) * kRadToDeg : kNaN;
    const int need = min_dirs_ > 0 ? std::min(avail, min_dirs_) : avail;
    if (avail >= 2 && flagged >= need) return kAbnormal;
    return flagged > 0 ? kEdge : kNormal;
  }

 private:
  double r2_, min_step_;
  int K_, min_dirs_;
  const std::vector<int>& scales_;
  double cos0_, cos_half_;
  double ck_[kMaxDirections] = {}, sk_[kMaxDirections] = {};
};

int thread_id() {
#ifdef MIEM_HAVE_OPENMP
  return omp_get_thread_num();
#else
  return 0;
#endif
}

// Runs `fn(cell, thread)` over the cells of `grid` in parallel (dynamic schedule).
template <typename T, typename Fn>
void parallel_cells(const NeighborGrid<T>& grid, int nt, Fn&& fn) {
  const std::ptrdiff_t ncells = grid.num_cells();
#pragma omp parallel for schedule(dynamic, 16) num_threads(nt) if (nt > 1)
  for (std::ptrdiff_t c = 0; c < ncells; ++c) fn(c, thread_id());
}

// The box of cells within r of the points of `cell`.
template <typename T>
CellBox cell_box(const NeighborGrid<T>& grid, std::ptrdiff_t cell, double r) {
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(kInf), hi = Eigen::Vector3d::Constant(-kInf);
  const std::uint32_t e = grid.cell_begin(cell + 1);
  for (std::uint32_t k = grid.cell_begin(cell); k < e; ++k) {
    const Eigen::Vector3d p = grid.sorted_point(k);
    lo = lo.cwiseMin(p);
    hi = hi.cwiseMax(p);
  }
  return grid.box_around(lo, hi, r);
}

// Cell size for a grid used with query radius r.
inline double grid_cell(double r) { return r; }

// Height plane of point `i` (NORMAL points within r, itself included when NORMAL) from the
// gathered NORMAL candidates.
inline PlaneStatus height_plane(const Gather& g, const Eigen::Vector3d& p, double r2, Selection& s,
                                LocalPlane* lp) {
  select(g, p, r2, -1, s);
  return fit_selection(s, false, lp);
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// spacing

template <typename T>
double point_spacing(const PointsView<T>& points, int num_threads) {
  check_view(points);
  const std::ptrdiff_t n_finite = count_finite(points, num_threads);
  if (n_finite < 3) {
    throw std::invalid_argument("points: need at least 3 finite points, found " +
                                std::to_string(n_finite));
  }
  // A first cell size from the bounding box (a scan is a sheet: ~ area / N per point), refined
  // until the occupied cells hold a few points each. Only speed depends on it, never the result.
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(kInf), hi = Eigen::Vector3d::Constant(-kInf);
  for (std::ptrdiff_t i = 0; i < points.size; ++i) {
    const Eigen::Vector3d p = points[i];
    if (!p.allFinite()) continue;
    lo = lo.cwiseMin(p);
    hi = hi.cwiseMax(p);
  }
  Eigen::Vector3d ext = hi - lo;
  std::sort(ext.data(), ext.data() + 3);  // ascending
  if (!(ext(2) > 0.0)) {
    throw std::invalid_argument("points: spacing is 0 (all finite points are identical)");
  }
  const double nf = static_cast<double>(n_finite);
  double cell = ext(1) > 0.0 ? 2.5 * std::sqrt(ext(2) * ext(1) / nf) : 2.5 * ext(2) / nf;
  cell = std::max(cell, ext(2) * 1e-9);
  std::vector<double> nn(static_cast<std::size_t>(points.size));
  for (int attempt = 0;; ++attempt) {
    NeighborGrid<T> grid(points, cell, num_threads);
    const double ratio = nf / static_cast<double>(std::max<std::ptrdiff_t>(1, grid.num_cells()));
    if (attempt < 6 && ratio > 12.0) {
      cell *= std::max(0.125, std::sqrt(3.0 / ratio));
      continue;
    }
    grid.nearest_distances(nn.data(), num_threads);
    break;
  }
  std::size_t m = 0;
  for (double v : nn) {
    if (!std::isnan(v)) nn[m++] = v;
  }
  nn.resize(m);
  const std::size_t mid = m / 2;
  std::nth_element(nn.begin(), nn.begin() + mid, nn.end());
  double spacing = nn[mid];
  if (m % 2 == 0) {
    const double lower = *std::max_element(nn.begin(), nn.begin() + mid);
    spacing = (lower + spacing) / 2.0;
  }
  if (!(spacing > 0.0)) {
    throw std::invalid_argument(
        "points: spacing is 0 (more than half of the finite points are duplicates)");
  }
  return spacing;
}

// ---------------------------------------------------------------------------------------------
// normals

template <typename T>
void estimate_normals(const PointsView<T>& points, double radius, const NormalsOutput& out,
                      int num_threads) {
  check_view(points);
  if (!std::isfinite(radius) || !(radius > 0.0)) {
    throw std::invalid_argument("radius: must be finite and > 0, got " + std::to_string(radius));
  }
  const std::ptrdiff_t n = points.size;
  for (std::ptrdiff_t i = 0; i < n; ++i) {
    if (out.normals) out.normals[3 * i] = out.normals[3 * i + 1] = out.normals[3 * i + 2] = kNaN;
    if (out.rms) out.rms[i] = kNaN;
    if (out.count) out.count[i] = 0;
    if (out.valid) out.valid[i] = 0;
  }
  const NeighborGrid<T> grid(points, grid_cell(radius), num_threads);
  const int nt = detail::thread_count(num_threads, grid.num_indexed(), 4096);
  std::vector<JudgeScratch> scratch(static_cast<std::size_t>(nt));
  const double r2 = radius * radius;
  const std::uint32_t* order = grid.order();
  parallel_cells(grid, nt, [&](std::ptrdiff_t cell, int tid) {
    JudgeScratch& js = scratch[tid];
    auto every = [](std::uint32_t, std::uint32_t) { return true; };
    gather_box(grid, cell_box(grid, cell, radius), every, js.gather);
    const std::uint32_t e = grid.cell_begin(cell + 1);
    for (std::uint32_t k = grid.cell_begin(cell); k < e; ++k) {
      const std::uint32_t i = order[k];
      select(js.gather, grid.sorted_point(k), r2, -1, js.sel);
      if (out.count) out.count[i] = static_cast<std::int64_t>(js.sel.n);
      LocalPlane lp;
      if (fit_selection(js.sel, false, &lp) != PlaneStatus::kOk) continue;
      if (out.normals) {
        out.normals[3 * i] = lp.normal.x();
        out.normals[3 * i + 1] = lp.normal.y();
        out.normals[3 * i + 2] = lp.normal.z();
      }
      if (out.rms) {
        out.rms[i] = std::sqrt(std::max(lp.eigenvalues(0), 0.0) / static_cast<double>(lp.n));
      }
      if (out.valid) out.valid[i] = 1;
    }
  });
}

// ---------------------------------------------------------------------------------------------
// detection

void validate(const PointsDetectParams& p) {
  if (!std::isfinite(p.theta0_deg) || p.theta0_deg <= 0.0 || p.theta0_deg >= 180.0) {
    throw std::invalid_argument("theta0: must be a finite angle in degrees with 0 < theta0 < 180");
  }
  if (p.scales.empty()) throw std::invalid_argument("scales: must not be empty");
  for (int s : p.scales) {
    if (s < 1) throw std::invalid_argument("scales: every scale must be an integer >= 1");
  }
  if (p.radius && (!std::isfinite(*p.radius) || !(*p.radius > 0.0))) {
    throw std::invalid_argument("radius: must be finite and > 0");
  }
  if (p.num_directions < 2 || p.num_directions > kMaxDirections) {
    throw std::invalid_argument("K: the number of directions must be an integer in 2..8");
  }
  if (p.min_step && (!std::isfinite(*p.min_step) || *p.min_step < 0.0)) {
    throw std::invalid_argument("min_step: must be finite and >= 0");
  }
  if (p.min_directions < 0 || p.min_directions > p.num_directions) {
    throw std::invalid_argument("min_directions: must be 0 (all) or 1..K");
  }
  if (p.max_iterations < 1) throw std::invalid_argument("max_iterations: must be >= 1");
  if (p.link && (!std::isfinite(*p.link) || !(*p.link > 0.0))) {
    throw std::invalid_argument("link: must be finite and > 0");
  }
  if (p.height_mode != HeightMode::kAll && p.height_mode != HeightMode::kAbnormal) {
    throw std::invalid_argument("heights: unknown mode");
  }
  if (p.num_threads < 0) throw std::invalid_argument("num_threads: must be >= 0");
}

template <typename T>
PointsDetectSummary detect_points(const PointsView<T>& points, const PointsDetectParams& p,
                                  const PointsOutput& out) {
  validate(p);
  check_view(points);
  if (out.labels == nullptr) throw std::invalid_argument("out.labels: must not be null");
  const std::ptrdiff_t N = points.size;

  PointsDetectSummary summary;
  summary.spacing = point_spacing(points, p.num_threads);  // also checks >= 3 finite points
  const double radius = p.radius ? *p.radius : 5.0 * summary.spacing;
  const double min_step = p.min_step ? *p.min_step : 0.5 * summary.spacing;
  const double link = p.link ? *p.link : radius;
  summary.radius = radius;
  summary.min_step = min_step;
  summary.link = link;
  const double r2 = radius * radius;

  const NeighborGrid<T> grid(points, grid_cell(radius), p.num_threads);
  const int nt = detail::thread_count(p.num_threads, grid.num_indexed(), 4096);
  std::vector<JudgeScratch> scratch(static_cast<std::size_t>(nt));
  const std::uint32_t* order = grid.order();

  std::uint8_t* labels = out.labels;
  // bit 0: usable (finite, not ABNORMAL); bit 1: candidate of this pass; bit 2: defect visited.
  std::vector<std::uint8_t> state(static_cast<std::size_t>(N));
  std::vector<std::uint8_t> degen_scratch;
  std::uint8_t* degenerate = out.degenerate;
  if (degenerate == nullptr) {
    degen_scratch.resize(static_cast<std::size_t>(N));
    degenerate = degen_scratch.data();
  }
  {
    const int ntn = detail::thread_count(p.num_threads, N);
#pragma omp parallel for schedule(static) num_threads(ntn) if (ntn > 1)
    for (std::ptrdiff_t i = 0; i < N; ++i) {
      const bool fin = points[i].allFinite();
      state[i] = fin;
      labels[i] = fin ? kNormal : kInvalid;
      degenerate[i] = 0;
      if (out.flags) out.flags[i] = 0;
      if (out.angle_deg) out.angle_deg[i] = kNaN;
      if (out.height) out.height[i] = kNaN;
    }
  }

  const PointJudge judge(p, radius, min_step);
  const std::uint8_t* st = state.data();
  auto usable = [st](std::uint32_t, std::uint32_t j) { return (st[j] & 1) != 0; };
  auto every = [](std::uint32_t, std::uint32_t) { return true; };
  auto judge_point = [&](std::uint32_t i, const Eigen::Vector3d& pi, JudgeScratch& js) {
    std::uint8_t fl = 0;
    double an = kNaN;
    bool dg = false;
    labels[i] = judge.judge(i, pi, js, &fl, &an, &dg);
    degenerate[i] = dg;
    if (out.flags) out.flags[i] = fl;
    if (out.angle_deg) out.angle_deg[i] = an;
  };

  // Pass 1: every finite point, one gather per cell.
  parallel_cells(grid, nt, [&](std::ptrdiff_t cell, int tid) {
    JudgeScratch& js = scratch[tid];
    gather_box(grid, cell_box(grid, cell, radius), every, js.gather);  // all usable in pass 1
    const std::uint32_t e = grid.cell_begin(cell + 1);
    for (std::uint32_t k = grid.cell_begin(cell); k < e; ++k) {
      judge_point(order[k], grid.sorted_point(k), js);
    }
  });
  std::vector<std::int64_t> fresh, candidates;
  for (std::ptrdiff_t i = 0; i < N; ++i) {
    if (labels[i] == kAbnormal) fresh.push_back(i);
  }
  int iterations = 1;

  // Later passes: only the usable points within radius of a newly removed point.
  while (!fresh.empty() && iterations < p.max_iterations) {
    for (std::int64_t i : fresh) state[i] = 0;
    candidates.clear();
    for (std::int64_t i : fresh) {
      grid.for_each_in_radius(points[i], radius, [&](std::ptrdiff_t j, double) {
        if (state[j] == 1) {
          state[j] = 3;
          candidates.push_back(j);
        }
      });
    }
    std::sort(candidates.begin(), candidates.end());
    const std::ptrdiff_t nc = static_cast<std::ptrdiff_t>(candidates.size());
    const int ntc = detail::thread_count(p.num_threads, nc, 1024);
#pragma omp parallel for schedule(dynamic, 64) num_threads(ntc) if (ntc > 1)
    for (std::ptrdiff_t c = 0; c < nc; ++c) {
      const std::uint32_t i = static_cast<std::uint32_t>(candidates[c]);
      JudgeScratch& js = scratch[thread_id()];
      const Eigen::Vector3d pi = points[i];
      gather_box(grid, grid.box_around(pi, pi, radius), usable, js.gather);
      judge_point(i, pi, js);
    }
    fresh.clear();
    for (std::int64_t j : candidates) {
      state[j] = 1;
      if (labels[j] == kAbnormal) fresh.push_back(j);
    }
    ++iterations;
  }
  summary.iterations = iterations;
  for (std::int64_t i : fresh) state[i] = 0;  // (last pass's removals, for consistency)

  // The MIEM plane: finite non-ABNORMAL points, block moments merged in a fixed tree order.
  {
    constexpr std::ptrdiff_t kBlock = 4096;
    const std::ptrdiff_t nblocks = std::max<std::ptrdiff_t>(1, (N + kBlock - 1) / kBlock);
    std::vector<Moments> blocks(static_cast<std::size_t>(nblocks));
    const int ntb = detail::thread_count(p.num_threads, N);
#pragma omp parallel for schedule(static) num_threads(ntb) if (ntb > 1)
    for (std::ptrdiff_t b = 0; b < nblocks; ++b) {
      const std::ptrdiff_t i0 = b * kBlock, i1 = std::min(N, i0 + kBlock);
      Moments m;
      Eigen::Vector3d sum = Eigen::Vector3d::Zero();
      for (std::ptrdiff_t i = i0; i < i1; ++i) {
        if (labels[i] == kNormal || labels[i] == kEdge) {
          sum += points[i];
          ++m.n;
        }
      }
      if (m.n > 0) {
        m.mean = sum / static_cast<double>(m.n);
        for (std::ptrdiff_t i = i0; i < i1; ++i) {
          if (labels[i] == kNormal || labels[i] == kEdge) {
            const Eigen::Vector3d q = points[i] - m.mean;
            m.scatter.noalias() += q * q.transpose();
          }
        }
      }
      blocks[b] = m;
    }
    for (std::ptrdiff_t width = 1; width < nblocks; width *= 2) {
      for (std::ptrdiff_t b = 0; b + width < nblocks; b += 2 * width) {
        blocks[b].merge(blocks[b + width]);
      }
    }
    Plane plane;
    if (eigen_plane_from_moments(blocks[0], &plane) == PlaneStatus::kOk) summary.plane = plane;
  }

  // Heights over the plane of the NORMAL points within radius.
  std::vector<double> height_scratch;
  double* height = out.height;
  if (height == nullptr) {
    height_scratch.assign(static_cast<std::size_t>(N), kNaN);
    height = height_scratch.data();
  }
  // NORMAL flags in grid order, so that the height gathers read memory sequentially.
  std::vector<std::uint8_t> normal_sorted(static_cast<std::size_t>(grid.num_indexed()));
  {
    const std::ptrdiff_t ni = grid.num_indexed();
    const int ntn = detail::thread_count(p.num_threads, ni);
#pragma omp parallel for schedule(static) num_threads(ntn) if (ntn > 1)
    for (std::ptrdiff_t k = 0; k < ni; ++k) normal_sorted[k] = labels[order[k]] == kNormal;
  }
  const std::uint8_t* ns = normal_sorted.data();
  auto normal_pt = [ns](std::uint32_t k, std::uint32_t) { return ns[k] != 0; };
  if (p.height_mode == HeightMode::kAll) {
    parallel_cells(grid, nt, [&](std::ptrdiff_t cell, int tid) {
      JudgeScratch& js = scratch[tid];
      gather_box(grid, cell_box(grid, cell, radius), normal_pt, js.gather);
      const std::uint32_t e = grid.cell_begin(cell + 1);
      for (std::uint32_t k = grid.cell_begin(cell); k < e; ++k) {
        const std::uint32_t i = order[k];
        LocalPlane lp;
        if (height_plane(js.gather, grid.sorted_point(k), r2, js.sel, &lp) == PlaneStatus::kOk) {
          height[i] = -lp.normal.dot(lp.mean);  // n . (p - centroid), centroid = p + mean
        }
      }
    });
  } else {
    std::vector<std::uint32_t> abn;
    for (std::ptrdiff_t i = 0; i < N; ++i) {
      if (labels[i] == kAbnormal) abn.push_back(static_cast<std::uint32_t>(i));
    }
    const std::ptrdiff_t na = static_cast<std::ptrdiff_t>(abn.size());
    const int nta = detail::thread_count(p.num_threads, na, 1024);
#pragma omp parallel for schedule(dynamic, 64) num_threads(nta) if (nta > 1)
    for (std::ptrdiff_t a = 0; a < na; ++a) {
      const std::uint32_t i = abn[a];
      JudgeScratch& js = scratch[thread_id()];
      const Eigen::Vector3d pi = points[i];
      gather_box(grid, grid.box_around(pi, pi, radius), normal_pt, js.gather);
      LocalPlane lp;
      if (height_plane(js.gather, pi, r2, js.sel, &lp) == PlaneStatus::kOk) {
        height[i] = -lp.normal.dot(lp.mean);
      }
    }
  }

  // Defects: components of ABNORMAL points under distance <= link, found in index order.
  constexpr std::uint8_t kSeen = 4;
  std::vector<std::int64_t> queue;
  JudgeScratch& js0 = scratch[0];
  for (std::ptrdiff_t start = 0; start < N; ++start) {
    if (labels[start] != kAbnormal || (state[start] & kSeen)) continue;
    queue.clear();
    queue.push_back(start);
    state[start] |= kSeen;
    bool touches_surface = false;
    for (std::size_t head = 0; head < queue.size(); ++head) {
      grid.for_each_in_radius(points[queue[head]], link, [&](std::ptrdiff_t j, double) {
        if (labels[j] == kAbnormal) {
          if (!(state[j] & kSeen)) {
            state[j] |= kSeen;
            queue.push_back(j);
          }
        } else {
          touches_surface = true;  // the grid holds finite points only
        }
      });
    }
    Defect d;
    d.indices.assign(queue.begin(), queue.end());
    std::sort(d.indices.begin(), d.indices.end());
    auto point_at = [&](std::int64_t i) -> Eigen::Vector3d { return points[i]; };
    const std::int64_t peak_idx = detail::summarize_defect(d, height, point_at);
    if (peak_idx >= 0) {
      const Eigen::Vector3d pk = points[peak_idx];
      gather_box(grid, grid.box_around(pk, pk, radius), normal_pt, js0.gather);
      LocalPlane lp;
      if (height_plane(js0.gather, pk, r2, js0.sel, &lp) == PlaneStatus::kOk) d.normal = lp.normal;
    }
    detail::finish_defect(d, point_at, touches_surface);
    summary.defects.push_back(std::move(d));
  }
  detail::order_defects(summary.defects);
  return summary;
}

template <typename T>
PointsDetectResult detect_points(const PointsView<T>& points, const PointsDetectParams& params) {
  PointsDetectResult res;
  const std::size_t n = static_cast<std::size_t>(std::max<std::ptrdiff_t>(0, points.size));
  res.labels.resize(n);
  res.flags.resize(n);
  res.degenerate.resize(n);
  res.angle_deg.resize(n);
  res.height.resize(n);
  PointsOutput out{res.labels.data(), res.flags.data(), res.angle_deg.data(), res.height.data(),
                   res.degenerate.data()};
  res.summary = detect_points(points, params, out);
  return res;
}

template double point_spacing<float>(const PointsView<float>&, int);
template double point_spacing<double>(const PointsView<double>&, int);
template void estimate_normals<float>(const PointsView<float>&, double, const NormalsOutput&, int);
template void estimate_normals<double>(const PointsView<double>&, double, const NormalsOutput&,
                                       int);
template PointsDetectSummary detect_points<float>(const PointsView<float>&,
                                                  const PointsDetectParams&, const PointsOutput&);
template PointsDetectSummary detect_points<double>(const PointsView<double>&,
                                                   const PointsDetectParams&, const PointsOutput&);
template PointsDetectResult detect_points<float>(const PointsView<float>&,
                                                 const PointsDetectParams&);
template PointsDetectResult detect_points<double>(const PointsView<double>&,
                                                  const PointsDetectParams&);

}  // namespace miem
