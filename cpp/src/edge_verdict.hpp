// Steps 4-6 of the edge test (docs/SPEC.md "Edge test"), shared by grids (one-sided sub-windows)
// and clouds (tangent-plane sectors, "Unorganized clouds: edge test"): from the planes of a
// point's one-sided neighbourhoods, which are clean, does it stand proud of one, is it an
// isolated spike?
#pragma once

#include <cmath>
#include <limits>

#include <Eigen/Core>

#include "judge.hpp"

namespace miem::detail {

/// A clean side: its rms is at most this times the smallest rms of the valid sides.
constexpr double kEdgeCleanRatio = 2.0;
/// A side whose smallest eigenvalue is at most this times its largest has rms 0 (SPEC "Edge
/// test" step 3, "Unorganized clouds: edge test" step 3): its l0 is round-off (an exactly flat
/// support: a noise-free plane, 3 points), so `best` and *clean* do not compare specks of it.
constexpr double kEdgeFlatL0 = 1e-12;

/// The precision floor (SPEC "Edge test" step 3, "Unorganized clouds: edge test" step 3): every
/// tolerance is at least this many machine epsilons of the input type times P's largest
/// absolute coordinate, so that float32's rounding of a noise-free face is not read as a burr.
constexpr double kEdgePrecision = 4.0;
template <typename T>
constexpr double edge_precision() noexcept {
  return kEdgePrecision * static_cast<double>(std::numeric_limits<T>::epsilon());
}

/// A side's rms from the eigenvalues l0 <= l2 of its n-point support (kEdgeFlatL0).
inline __attribute__((always_inline)) double edge_side_rms(double l0, double l2, double n) {
  return l0 > kEdgeFlatL0 * l2 ? std::sqrt(l0 / n) : 0.0;
}
/// A grid side whose plane is steeper than 70 degrees (oriented normal's z below cos 70) is
/// *steep* (SPEC "Edge test" step 4): never clean; as an opposite side its centroid counts.
constexpr double kEdgeSteepCos = 0.3420201433256687;

/// One one-sided neighbourhood of a point P: its plane (valid), or no return there (empty).
struct EdgeSide {
  bool valid = false, empty = false;
  bool steep = false;  // grids: a plane steeper than 70 degrees (never clean); clouds: unused
  bool outline = false;  // grids: an outline, mostly without returns (step 5); clouds: unused
  double h = 0.0, rms = 0.0, tol = 0.0;  // h = u . (P - centroid); tol = max(k rms, floor)
  Eigen::Vector3d normal, centroid;      // centroid in any frame shared by the sides
};

/// A level side (SPEC "Edge test" step 4): valid and not steep.
inline bool edge_level(const EdgeSide& x) { return x.valid && !x.steep; }

/// A clean side (SPEC "Edge test" step 4): level, rms <= kEdgeCleanRatio x best.
inline bool edge_clean(const EdgeSide& x, double best) {
  return edge_level(x) && x.rms <= kEdgeCleanRatio * best;
}

/// P fits side x (step 4): x is clean and not |h| > tol.
inline bool edge_fits(const EdgeSide& x, double best) {
  return edge_clean(x, best) && !(std::abs(x.h) > x.tol);
}

/// Beyond P the surface falls away below side x's plane: side y's centroid lies more than x's
/// tolerance below it (SPEC "Edge test" steps 5 and 6).
inline bool edge_drops(const EdgeSide& x, const EdgeSide& y) {
  return dot3(x.normal, y.centroid - x.centroid) < -x.tol;
}

/// P stands proud of side x with opposite y, but for `attached` (SPEC "Edge test" step 5): x
/// is clean, P lies above its plane by more than its tolerance, and y is empty or valid and
/// falls away below x's plane (edge_proud; the grid's crossing rule asks it of one side).
inline bool edge_proud_of(const EdgeSide& x, const EdgeSide& y, double best) {
  return edge_clean(x, best) && x.h > x.tol && (y.empty || (y.valid && edge_drops(x, y)));
}

/// SPEC "Edge test" step 5: P stands proud of a clean side whose opposite side
/// (`opposite(s)`) is empty or falls away below its plane, and to which P is attached
/// (`attached(s)`; asked last) (step 6 flags it when it also fits no clean side, which the
/// caller checks). `best`: the smallest rms of the valid sides.
template <int N, typename Opposite, typename Attached>
inline bool edge_proud(const EdgeSide (&sd)[N], double best, Opposite opposite,
                       Attached attached) {
  for (int s = 0; s < N; ++s) {
    if (edge_proud_of(sd[s], sd[opposite(s)], best) && attached(s)) return true;
  }
  return false;
}

/// SPEC "Edge test" step 6 (grids) and "Unorganized clouds: edge test" step 6, lips at a
/// concave feature: beyond P the surface dips below it by more than D = max(kEdgeLipTol x tol,
/// kEdgeLipDip x h) (a profile offset of a few rms is no lip, nor a terrace's edge whose next
/// cells lie level with P). miem.reference._EDGE_LIP_TOL, _EDGE_LIP_DIP.
constexpr double kEdgeLipTol = 2.0, kEdgeLipDip = 0.5;

/// Isolated spike (SPEC "Edge test" step 7): P lies more than this times its tolerance off every
/// clean side (2 x edge_k rms: a cell the shortcut certifies, |h| <= tol on a clean side, never
/// qualifies) ...
constexpr double kEdgeSpikeTol = 2.0;
/// ... and the median distance of its neighbours to the cleanest side's plane is below this
/// times P's (on a fillet or a bend the neighbours lie as far off that plane as P).
constexpr double kEdgeSpikeIso = 0.2;

/// Step 7's first half: the cleanest side (the first with the smallest rms among the valid,
/// non-steep ones) when P lies more than kEdgeSpikeTol x tol off every clean side, else -1.
template <int N>
inline int edge_spike_side(const EdgeSide (&sd)[N], double best) {
  int cleanest = -1;
  for (int s = 0; s < N; ++s) {
    const EdgeSide& x = sd[s];
    if (!edge_clean(x, best)) continue;
    if (!(std::abs(x.h) > kEdgeSpikeTol * x.tol)) return -1;
    if (cleanest < 0 && x.rms == best) cleanest = s;
  }
  return cleanest;
}

/// Step 7's last condition (the corner of a raised patch is no isolated spike): a neighbour
/// is *raised* when its signed distance to the cleanest side's plane lies on P's side beyond
/// this times |h| ...
constexpr double kEdgeSpikeRaised = 0.5;

/// ... and P is a *corner* when a raised neighbour lies in its row (left or right) and one in
/// its column (up or down): a small raised pad or lip, raised in two directions, not a spike.
/// `res`: the signed distances (u . (q - centroid)) of P's 8 neighbours in row-major order
/// (up-left, up, up-right, left, right, down-left, down, down-right), NaN without a return.
inline bool edge_spike_corner(const double (&res)[8], double h) {
  const double s = h > 0.0 ? 1.0 : -1.0, lim = kEdgeSpikeRaised * std::abs(h);
  const auto raised = [&](int i) { return s * res[i] > lim; };
  return (raised(3) || raised(4)) && (raised(1) || raised(6));
}

}  // namespace miem::detail
