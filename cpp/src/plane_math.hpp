// The smallest eigenpair of a 3x3 scatter matrix without trigonometry, for the per-cell window
// planes: Newton on the characteristic polynomial from 0 (monotone from below, since it is
// concave and increasing left of the smallest root), then the largest cross product of two rows
// of M - l0 I. Accurate when l0 is well separated from l1, which a surface patch always is.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>

#include <Eigen/Core>
#include <Eigen/Geometry>  // cross

#include "miem/plane.hpp"
#include "vector_clones.hpp"

namespace miem::detail {

/// A plane that moment sums lose to cancellation: its l1 at most this times the sums' second
/// moments about their origin (s_xx + s_yy + s_zz). Sums of moments relative to a point away
/// from the support (a grid window's: a point of its tile; a cloud's surroundings: the query
/// point) form M = Q - n m m^T, which cancels their leading digits; a support nearly on a line
/// (three cells of one row beside a dropout, three points of one scan line) leaves an l1
/// smaller than that round-off, and its plane tilts by up to 1e-6. Such a plane is fitted again
/// from its support's mean, as the reference fits every plane.
inline constexpr double kRefitRatio = 1e-7;

/// A unit normal component at most this large in magnitude counts as zero when orienting
/// (SPEC "Plane fit"): an exactly vertical plane's n_z comes out of any eigen-solver as a
/// rounding residue of either sign (up to the machine epsilon times l2 / l1, 1e-11 on a window
/// of one noisy row), which must not decide the orientation.
inline constexpr double kOrientTol = 1e-6;

/// The orientation sign of a unit normal (SPEC "Plane fit"): that of n_z, or when
/// |n_z| <= kOrientTol of n_x, or when |n_x| <= kOrientTol too of n_y (+1 when all are zero).
inline double orient_sign(double nx, double ny, double nz) noexcept {
  // (three signs and two selects, no branch: vector loops inline it)
  const double sz = nz > 0.0 ? 1.0 : -1.0, sx = nx > 0.0 ? 1.0 : -1.0;
  const double sy = ny < 0.0 ? -1.0 : 1.0;
  const double sxy = std::abs(nx) > kOrientTol ? sx : sy;
  return std::abs(nz) > kOrientTol ? sz : sxy;
}

/// A unit vector of the null space of M - x I for a symmetric M (an eigenvector of M when x is
/// an eigenvalue well apart from the other two): the largest cross product of two of its rows.
/// Returns false when all three vanish.
inline bool eigenvector_of(const Eigen::Matrix3d& M, double x, Eigen::Vector3d* v) {
  const double a = M(0, 0), b = M(1, 1), c = M(2, 2), d = M(0, 1), e = M(1, 2), f = M(0, 2);
  const Eigen::Vector3d r0(a - x, d, f), r1(d, b - x, e), r2(f, e, c - x);
  const Eigen::Vector3d c01 = r0.cross(r1), c02 = r0.cross(r2), c12 = r1.cross(r2);
  const double n01 = c01.squaredNorm(), n02 = c02.squaredNorm(), n12 = c12.squaredNorm();
  const Eigen::Vector3d& best = n01 >= n02 ? (n01 >= n12 ? c01 : c12) : (n02 >= n12 ? c02 : c12);
  const double nb = std::max(n01, std::max(n02, n12));
  if (!(nb > 0.0)) return false;
  *v = best / std::sqrt(nb);
  return true;
}

/// Eigenvalues l0 <= l1 <= l2 of a symmetric positive semi-definite M and the unit eigenvector
/// of l0 (unoriented). Returns false when M is zero.
inline bool smallest_eigenpair(const Eigen::Matrix3d& M, double* l0, double* l1, double* l2,
                               Eigen::Vector3d* normal) {
  const double a = M(0, 0), b = M(1, 1), c = M(2, 2), d = M(0, 1), e = M(1, 2), f = M(0, 2);
  const double tr = a + b + c;
  if (!(tr > 0.0)) return false;
  const double c1 = (a * b + b * c + a * c) - (d * d + e * e + f * f);
  const double det = a * b * c + 2.0 * d * e * f - a * e * e - b * f * f - c * d * d;
  // q(x) = x^3 - tr x^2 + c1 x - det, q(0) = -det <= 0; Newton from 0 rises to the root.
  double x = 0.0;
  for (int it = 0; it < 64; ++it) {
    const double q = ((x - tr) * x + c1) * x - det;
    const double dq = (3.0 * x - 2.0 * tr) * x + c1;
    if (!(dq > 0.0)) break;
    const double step = q / dq;
    if (!(step < 0.0)) break;  // q >= 0: at (or, by rounding, just past) the root
    x -= step;
    if (-step <= 1e-17 * tr) break;
  }
  const double s = tr - x, p = c1 - x * s;  // l1 + l2, l1 l2
  const double disc = s * s - 4.0 * p;
  const double hi = 0.5 * (s + std::sqrt(disc > 0.0 ? disc : 0.0));
  *l0 = x;
  *l2 = hi;
  *l1 = hi > 0.0 ? p / hi : 0.0;
  return eigenvector_of(M, x, normal);
}

// One Newton step of smallest_eigenpair on the characteristic cubic, masked by `live`.
inline __attribute__((always_inline)) void newton_step(double& x, double& live, double tr,
                                                        double c1, double det) {
  const double q = ((x - tr) * x + c1) * x - det;
  const double dq = (3.0 * x - 2.0 * tr) * x + c1;
  const double step = q / (dq > 0.0 ? dq : 1.0);
  const double go = (dq > 0.0 && step < 0.0) ? live : 0.0;  // (doubles: bools do not vectorise)
  x = go != 0.0 ? x - step : x;
  live = (-step <= 1e-17 * tr) ? 0.0 : go;
}

// smallest_eigenpair's arithmetic for one matrix in straight-line code (vector loops inline it),
// in three parts: eigen_start (the cubic's coefficients), newton_step (masked by `live`: the
// steps of an ended lane change nothing), eigen_finish (l1, l2 and the eigenvector).
// eigen_start: tr, c1, det of q(x) = x^3 - tr x^2 + c1 x - det.
inline __attribute__((always_inline)) void eigen_start(double a, double b, double c, double d,
                                                        double e, double f, double& tr,
                                                        double& c1, double& det) {
  tr = a + b + c;
  c1 = (a * b + b * c + a * c) - (d * d + e * e + f * f);
  det = a * b * c + 2.0 * d * e * f - a * e * e - b * f * f - c * d * d;
}

// eigen_lane after the Newton steps: l1, l2 = hi and the largest cross product.
inline __attribute__((always_inline)) void eigen_finish(double a, double b, double c, double d,
                                                         double e, double f, double tr,
                                                         double c1, double x, double& l1,
                                                         double& hi, double& bx0, double& bx1,
                                                         double& bx2, double& nb) {
  const double s = tr - x, p = c1 - x * s;
  const double disc = s * s - 4.0 * p;
  hi = 0.5 * (s + std::sqrt(disc > 0.0 ? disc : 0.0));
  l1 = hi > 0.0 ? p / hi : 0.0;
  const double ax = a - x, bx = b - x, cx = c - x;
  // Rows r0 = (ax, d, f), r1 = (d, bx, e), r2 = (f, e, cx); their cross products.
  const double u0 = d * e - f * bx, u1 = f * d - ax * e, u2 = ax * bx - d * d;  // r0 x r1
  const double v0 = d * cx - f * e, v1 = f * f - ax * cx, v2 = ax * e - d * f;  // r0 x r2
  const double w0 = bx * cx - e * e, w1 = e * f - d * cx, w2 = d * e - bx * f;  // r1 x r2
  const double n01 = (u0 * u0 + u1 * u1) + u2 * u2;
  const double n02 = (v0 * v0 + v1 * v1) + v2 * v2;
  const double n12 = (w0 * w0 + w1 * w1) + w2 * w2;
  // smallest_eigenpair's choice: n01 >= n02 ? (n01 >= n12 ? c01 : c12) : (n02 >= n12 ? c02 : c12)
  const bool pu = (n01 >= n02) & (n01 >= n12);
  const bool pv = !(n01 >= n02) & (n02 >= n12);
  bx0 = pu ? u0 : (pv ? v0 : w0);
  bx1 = pu ? u1 : (pv ? v1 : w1);
  bx2 = pu ? u2 : (pv ? v2 : w2);
  nb = pu ? n01 : (pv ? n02 : n12);  // the largest of the three
}

/// smallest_eigenpair for m matrices at once (SoA: entries a = M00, b = M11, c = M22, d = M01,
/// e = M12, f = M02, `cap` apart in `M` in that order), in straight-line code that vectorises.
/// Writes l0, l1, l2, nx, ny, nz (`cap` apart in `out`) and ok (smallest_eigenpair's return
/// value). Up to 8 Newton steps, stopping once every lane of a block of 128 has ended (steps
/// of an ended lane change nothing, so the bits are those of smallest_eigenpair's iteration):
/// where a lane has not ended by then, redo is set and the caller runs smallest_eigenpair
/// itself; elsewhere every output equals smallest_eigenpair's bit for bit.
/// the edge test's sub-windows of rough or curved surfaces (l0 nearer l1) rarely end within 4
/// (on the real scan almost never), within 8 nearly always; flat ones end within 3 or 4.
/// ok and redo as 1.0 / 0.0 (doubles: a byte per lane would make the vectoriser take 32 lanes
/// at a time, and the edge test's blocks of 16 would run scalar).
MIEM_CLONES inline void smallest_eigenpairs_long(std::ptrdiff_t m, std::ptrdiff_t cap,
                                                 const double* __restrict M, double* __restrict out,
                                                 double* __restrict ok, double* __restrict redo) {
  constexpr std::ptrdiff_t kB = 128;
  for (std::ptrdiff_t b0 = 0; b0 < m; b0 += kB) {
    const std::ptrdiff_t n = std::min(kB, m - b0);
    const double *__restrict ma = M + b0, *__restrict mb = ma + cap, *__restrict mc = ma + 2 * cap;
    const double *__restrict md = ma + 3 * cap, *__restrict me = ma + 4 * cap;
    const double* __restrict mf = ma + 5 * cap;
    double *__restrict o0 = out + b0, *__restrict o1 = o0 + cap, *__restrict o2 = o0 + 2 * cap;
    double *__restrict o3 = o0 + 3 * cap, *__restrict o4 = o0 + 4 * cap;
    double* __restrict o5 = o0 + 5 * cap;
    double tr[kB], c1[kB], det[kB], x[kB], live[kB];
    for (std::ptrdiff_t i = 0; i < n; ++i) {
      eigen_start(ma[i], mb[i], mc[i], md[i], me[i], mf[i], tr[i], c1[i], det[i]);
      x[i] = 0.0;
      live[i] = tr[i] > 0.0 ? 1.0 : 0.0;
    }
    for (int it = 0; it < 8; ++it) {
      std::int64_t any = 0;
      for (std::ptrdiff_t i = 0; i < n; ++i) {
        newton_step(x[i], live[i], tr[i], c1[i], det[i]);
        any |= static_cast<std::int64_t>(live[i] != 0.0);
      }
      if (any == 0) break;
    }
#pragma GCC ivdep
    for (std::ptrdiff_t i = 0; i < n; ++i) {
      const double a = ma[i], b = mb[i], c = mc[i], d = md[i], e = me[i], f = mf[i];
      double l1, hi, bx0, bx1, bx2, nb;
      eigen_finish(a, b, c, d, e, f, tr[i], c1[i], x[i], l1, hi, bx0, bx1, bx2, nb);
      const double len = std::sqrt(nb > 0.0 ? nb : 1.0);
      o0[i] = x[i];
      o1[i] = l1;
      o2[i] = hi;
      o3[i] = bx0 / len;
      o4[i] = bx1 / len;
      o5[i] = bx2 / len;
      ok[b0 + i] = (tr[i] > 0.0) & (nb > 0.0) ? 1.0 : 0.0;
      redo[b0 + i] = live[i] != 0.0 ? 1.0 : 0.0;
    }
  }
}

/// Moments of the points that each(f) hands to f (f(point) per point, in a fixed order; each is
/// called twice): the sum, then the scatter centred on the mean (two passes over a block that
/// stays in cache). The arithmetic of every block of fit_plane and of the MIEM plane's rows.
template <typename Each>
Moments two_pass_moments(Each each) {
  Moments m;
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  std::int64_t n = 0;
  each([&](const Eigen::Vector3d& q) {
    sum += q;
    ++n;
  });
  if (n == 0) return m;
  m.n = n;
  m.mean = sum / static_cast<double>(n);
  double sxx = 0, sxy = 0, sxz = 0, syy = 0, syz = 0, szz = 0;
  const Eigen::Vector3d mean = m.mean;
  each([&](const Eigen::Vector3d& p) {
    const Eigen::Vector3d q = p - mean;
    sxx += q.x() * q.x();
    sxy += q.x() * q.y();
    sxz += q.x() * q.z();
    syy += q.y() * q.y();
    syz += q.y() * q.z();
    szz += q.z() * q.z();
  });
  m.scatter << sxx, sxy, sxz, sxy, syy, syz, sxz, syz, szz;
  return m;
}

/// two_pass_moments of the points that each(f) hands to f as f(x, y, z, keep) (in a fixed
/// order, twice), counting only those with keep: the same moments, bit for bit, in straight-line
/// code (no branch per point; a point not kept, even one with NaN coordinates, adds +0.0, which
/// leaves a sum begun at +0.0 as it was). For long runs of points of which most are kept.
template <typename Each>
Moments two_pass_moments_masked(Each each) {
  Moments m;
  double sx = 0.0, sy = 0.0, sz = 0.0;
  std::int64_t n = 0;
  each([&](double x, double y, double z, bool keep) {
    sx += keep ? x : 0.0;
    sy += keep ? y : 0.0;
    sz += keep ? z : 0.0;
    n += keep ? 1 : 0;
  });
  if (n == 0) return m;
  m.n = n;
  m.mean = Eigen::Vector3d(sx, sy, sz) / static_cast<double>(n);
  double sxx = 0, sxy = 0, sxz = 0, syy = 0, syz = 0, szz = 0;
  const double mx = m.mean.x(), my = m.mean.y(), mz = m.mean.z();
  each([&](double x, double y, double z, bool keep) {
    const double qx = keep ? x - mx : 0.0, qy = keep ? y - my : 0.0, qz = keep ? z - mz : 0.0;
    sxx += qx * qx;
    sxy += qx * qy;
    sxz += qx * qz;
    syy += qy * qy;
    syz += qy * qz;
    szz += qz * qz;
  });
  m.scatter << sxx, sxy, sxz, sxy, syy, syz, sxz, syz, szz;
  return m;
}

/// two_pass_moments of point(i) for the i in [begin, end) with keep(i).
template <typename Point, typename Keep>
Moments two_pass_moments(std::ptrdiff_t begin, std::ptrdiff_t end, Point point, Keep keep) {
  return two_pass_moments([&](auto&& f) {
    for (std::ptrdiff_t i = begin; i < end; ++i)
      if (keep(i)) f(point(i));
  });
}

}  // namespace miem::detail
