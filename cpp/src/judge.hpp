// Private building blocks of organized detection, shared by the batch detector and the
// streaming detector: the per-cell judge (docs/SPEC.md) and the direct window plane fit.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>

#include <Eigen/Core>

#include "miem/organized.hpp"
#include "miem/plane.hpp"
#include "miem/views.hpp"
#include "plane_math.hpp"

namespace miem::detail {

inline constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
inline constexpr double kRadToDeg = 57.29577951308232;
inline constexpr double kDegToRad = 0.017453292519943295;
inline constexpr int kDirRow[4] = {0, 1, 1, 1};
inline constexpr int kDirCol[4] = {1, 0, 1, -1};

/// The batch detector's reading of a usable-mask byte: bit 0 set.
struct UsableBit {
  bool operator()(std::uint8_t b) const { return (b & 1) != 0; }
};

/// (x x' + y y') + z z': one fixed evaluation order shared by every code path.
inline double dot3(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  return (a.x() * b.x() + a.y() * b.y()) + a.z() * b.z();
}

/// The cosine of the angle between u and v from their dot products (uu, vv > 0), clamped to
/// [-1, 1]: the one evaluation every judge of SPEC's angle test uses.
inline double clamped_cos(double uv, double uu, double vv) {
  return std::clamp(uv / std::sqrt(uu * vv), -1.0, 1.0);
}

/// A cell's label from its directions (SPEC "Angle test"): ABNORMAL when at least 2 directions
/// are available and at least min(available, min_directions) (0: all) are flagged, else EDGE
/// when any is flagged, else NORMAL.
inline std::uint8_t direction_label(int avail, int flagged, int min_directions) {
  const int need = min_directions > 0 ? std::min(avail, min_directions) : avail;
  if (avail >= 2 && flagged >= need) return kAbnormal;
  return flagged > 0 ? kEdge : kNormal;
}

/// A search's reach (steps read along a ray) as kept in a byte: capped at 255.
inline std::uint8_t reach_byte(std::ptrdiff_t steps) {
  return static_cast<std::uint8_t>(std::min<std::ptrdiff_t>(steps, 255));
}

/// Judges single cells against a fixed usable mask. `Usable` maps a mask byte to "usable"
/// (the batch detector: bit 0; the streaming detector: "removed at this pass or later").
/// `kLabelsOnly` (streaming): labels and flags exact, angle NaN, and no square root for a
/// direction that cannot be flagged (u.v <= 0 with theta0 < 90).
template <typename T, typename Usable = UsableBit, bool kLabelsOnly = false>
class CellJudge {
 public:
  CellJudge(const GridView<T>& grid, const std::uint8_t* usable, const DetectParams& p,
            Usable is_usable = Usable{})
      : g_(grid),
        usable_(usable),
        is_usable_(is_usable),
        rows_(grid.rows),
        cols_(grid.cols),
        p_(p),
        cos0_(std::cos(p.theta0_deg * kDegToRad)),
        has_min_step_(p.min_step >= 0.0),
        min_step_(p.min_step) {}

  // Writes flags and smallest angle; returns the label of a finite, not yet abnormal cell.
  // With `reach` (4 bytes), also the farthest step along each direction (either side) whose
  // usable bit the verdict read, at least 1 + max_gap (capped at 255): a later pass need
  // re-judge the cell only when a cell that near on one of its rays is removed. Not written for
  // an isolated (ABNORMAL) cell.
  std::uint8_t judge(std::ptrdiff_t r, std::ptrdiff_t c, std::uint8_t* flags, double* angle_deg,
                     std::uint8_t* reach = nullptr) const {
    if (isolated(r, c)) {
      *flags = 0;
      *angle_deg = kNaN;
      return kAbnormal;
    }
    const Eigen::Vector3d P = g_(r, c);
    int avail = 0, flagged = 0;
    std::uint8_t mask = 0;
    double best_cos = -2.0;
    for (int k = 0; k < 4; ++k) {
      bool dir_avail = false, dir_flag = false;
      std::ptrdiff_t ext = 1 + static_cast<std::ptrdiff_t>(p_.max_gap);
      for (int s : p_.scales) {
        Eigen::Vector3d a, b;
        const bool has_a = neighbour(r, c, P, -1, k, s, &a, &ext);
        if (!has_a || !neighbour(r, c, P, +1, k, s, &b, &ext)) continue;
        const Eigen::Vector3d u = a - P, v = b - P;
        const double uu = dot3(u, u), vv = dot3(v, v);
        if (uu == 0.0 || vv == 0.0) continue;
        const double uv = dot3(u, v);
        dir_avail = true;
        if (kLabelsOnly && uv <= 0.0 && cos0_ > 0.0) continue;  // cos <= 0 < cos0
        const double cs = clamped_cos(uv, uu, vv);
        if (cs >= cos0_) dir_flag = true;
        if (cs > best_cos) best_cos = cs;
      }
      if (reach) reach[k] = reach_byte(ext);
      avail += dir_avail;
      if (dir_flag) {
        ++flagged;
        mask |= static_cast<std::uint8_t>(1u << k);
      }
    }
    *flags = mask;
    *angle_deg = (!kLabelsOnly && best_cos > -2.0) ? std::acos(best_cos) * kRadToDeg : kNaN;
    return direction_label(avail, flagged, p_.min_directions);
  }

 private:
  bool usable(std::ptrdiff_t r, std::ptrdiff_t c) const { return is_usable_(usable_[r * cols_ + c]); }

  bool isolated(std::ptrdiff_t r, std::ptrdiff_t c) const {
    const std::ptrdiff_t reach = 1 + static_cast<std::ptrdiff_t>(p_.max_gap);
    for (int k = 0; k < 4; ++k) {
      for (int sgn = -1; sgn <= 1; sgn += 2) {
        for (std::ptrdiff_t step = 1; step <= reach; ++step) {
          const std::ptrdiff_t rr = r + sgn * step * kDirRow[k], cc = c + sgn * step * kDirCol[k];
          if (rr < 0 || rr >= rows_ || cc < 0 || cc >= cols_) break;
          if (usable(rr, cc)) return false;
        }
      }
    }
    return true;
  }

  // The SPEC neighbour search; raises *ext to the last step whose usable bit it read.
  bool neighbour(std::ptrdiff_t r, std::ptrdiff_t c, const Eigen::Vector3d& P, int sgn, int k,
                 int s, Eigen::Vector3d* out, std::ptrdiff_t* ext) const {
    const std::ptrdiff_t dr = sgn * kDirRow[k], dc = sgn * kDirCol[k];
    const std::ptrdiff_t last = static_cast<std::ptrdiff_t>(s) + p_.max_gap + p_.max_reach;
    const double min_len = has_min_step_ ? s * min_step_ : 0.0;
    int gaps = 0;
    for (std::ptrdiff_t step = s;; ++step) {
      if (has_min_step_ && step > last) return false;
      const std::ptrdiff_t rr = r + step * dr, cc = c + step * dc;
      if (rr < 0 || rr >= rows_ || cc < 0 || cc >= cols_) return false;
      if (step > *ext) *ext = step;
      if (!usable(rr, cc)) {
        if (++gaps > p_.max_gap) return false;
        continue;
      }
      const Eigen::Vector3d q = g_(rr, cc);
      if (!has_min_step_ || (q - P).norm() >= min_len) {
        *out = q;
        return true;
      }
    }
  }

  const GridView<T>& g_;
  const std::uint8_t* usable_;
  Usable is_usable_;
  std::ptrdiff_t rows_, cols_;
  const DetectParams& p_;
  double cos0_;
  bool has_min_step_;
  double min_step_;
};

/// A window plane (SPEC "Height") exists only where its normal is unique: l1 - l0 above this
/// times l2. Equal smallest eigenvalues (a noise-free 3 x 3 window around a pit as deep as the
/// window is wide: l0 = l1) leave any normal in their plane, and an l1 within round-off of
/// the 1e-12 rank limit (three collinear cells) is no rank at all: either way the core's solver
/// and NumPy's pick different planes. Above the Newton solver's accuracy at a double root
/// (about sqrt(eps) = 1.5e-8 of l2), far below any measured surface's l1 - l0.
inline constexpr double kWindowUnique = 1e-6;

/// A window plane exists (SPEC "Height"): l2 > 0, the rank (l1 > 1e-12 l2, SPEC "Plane fit")
/// and a unique normal (kWindowUnique). Branch-free, for the vector loops too.
inline __attribute__((always_inline)) bool window_plane_exists(double l0, double l1,
                                                               double l2) {
  return (l2 > 0.0) & (l1 > 1e-12 * l2) & (l1 - l0 > kWindowUnique * l2);
}

// Eigen fit of the NORMAL cells in the window around (r, c), computed directly (two-pass;
// two_pass_moments_masked: the sums of the NORMAL cells in row-major order without a branch per
// cell, the same bits as adding them one by one).
template <typename T>
PlaneStatus window_plane(const GridView<T>& g, const std::uint8_t* labels, std::ptrdiff_t r,
                         std::ptrdiff_t c, int half, Plane* out) {
  const std::ptrdiff_t r0 = std::max<std::ptrdiff_t>(0, r - half);
  const std::ptrdiff_t r1 = std::min<std::ptrdiff_t>(g.rows - 1, r + half);
  const std::ptrdiff_t c0 = std::max<std::ptrdiff_t>(0, c - half);
  const std::ptrdiff_t c1 = std::min<std::ptrdiff_t>(g.cols - 1, c + half);
  const std::ptrdiff_t cs = g.col_stride, ys = g.coord_stride;
  const Moments m = two_pass_moments_masked([&](auto&& f) {
    for (std::ptrdiff_t rr = r0; rr <= r1; ++rr) {
      const T* row = g.data + rr * g.row_stride;
      const std::uint8_t* lab = labels + rr * g.cols;
      for (std::ptrdiff_t cc = c0; cc <= c1; ++cc) {
        const T* q = row + cc * cs;
        f(static_cast<double>(q[0]), static_cast<double>(q[ys]), static_cast<double>(q[2 * ys]),
          lab[cc] == kNormal);
      }
    }
  });
  if (m.n < 3) return PlaneStatus::kTooFewPoints;
  const PlaneStatus st = eigen_plane_from_moments(m, out);
  if (st != PlaneStatus::kOk) return st;
  const Eigen::Vector3d& ev = out->eigenvalues;
  return window_plane_exists(ev(0), ev(1), ev(2)) ? st : PlaneStatus::kDegenerate;
}

}  // namespace miem::detail
