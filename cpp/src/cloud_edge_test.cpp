// Edge test on unorganized clouds (docs/SPEC.md, "Unorganized clouds: edge test"): the grid edge
// test's one-sided sub-windows become eight 90-degree sectors of a point's disk in its tangent
// plane, at two scales (the edge radius and 1.5 times it). Jacobi passes; the first judges every
// candidate, later ones only the candidates within the wide radius of a point the pass before
// made ABNORMAL.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#ifdef __SSE2__
#include <emmintrin.h>
#endif

#include "cloud_sectors.hpp"
#include "cloud_stages.hpp"
#include "edge_verdict.hpp"

namespace miem::cloud {

namespace {

constexpr int kSectors = 16;  // 8 quarter-disk and 8 half-disk sectors
constexpr double kRmsFloor = 1e-9;      // of the tolerance, as the height test's
constexpr double kSuspect = 1.5;        // candidates: surroundings rms above 1.5 x the median
// The wide scale's sector radius, in edge radii (SPEC step 7; edge pool and tune split)
constexpr double kEdgeWide = 1.5;
constexpr double kEmpty = 0.35;  // empty: fewer returns than 0.35 of a full sector (tune split)
// ... and, as the opposite of a hanging point, below 0.3: a face falling away steeper than 45
// degrees past a convex crease keeps about 0.3-0.35 (SPEC step 5)
constexpr double kHangEmpty = 0.3;
// ... unless its support's plane runs through P steeper than 45 degrees against the opposite
// sector's: |u_a . u_b| below cos 45 degrees (sqrt(0.5) rounded to double; SPEC step 5)
constexpr double kFaceCos = 0.7071067811865476;
// ... and is smooth: its rms at most 3 x the cleanest valid sector's (a plane through material
// hanging level with P and the floor beyond it is not a face)
constexpr double kFaceClean = 3.0;
constexpr double kHangShelf = 2.0;  // hanging: the surface beyond lies > 2x P's depth below
constexpr double kLedgeLevel = 0.5;  // a ledge's material within 0.5 x P's depth of P's level
// Lips at a concave feature (SPEC step 6): the grid's dip (detail::kEdgeLipTol, kEdgeLipDip),
// the opposite sector's support centroid above the plane by more than h / 4 (a bead one
// point wide through P lifts it by about 0.13 h at the default radius) ...
constexpr double kLipRise = 0.25;
// ... along the strip beyond P, which reaches this times the edge radius either side of its
// ray (one spacing at the default radius)
constexpr double kLipStrip = 0.1;
// The bisector of sector o: 45 o + 45 degrees (quarter sectors), 45 (o - 8) + 90 (half
// sectors), from e1 towards e2; (cos, sin) per multiple of 45 degrees (sqrt(0.5) rounded).
constexpr double kR2 = 0.7071067811865476;
constexpr double kTurnCos[8] = {1.0, kR2, 0.0, -kR2, -1.0, -kR2, 0.0, kR2};
constexpr double kTurnSin[8] = {0.0, kR2, 1.0, kR2, 0.0, -kR2, -1.0, -kR2};

// The bit pattern of x >= 0 (-0 read as +0): patterns of such values sort as the values do.
inline std::uint64_t sort_key(double x) {
  std::uint64_t b;
  std::memcpy(&b, &x, sizeof b);
  return b >> 63 ? 0 : b;
}

// The k-th smallest (0-based) of the finite values of v (k < their count), all >= 0: the top 16
// bits of their sort keys, then the next 16, are fixed from histograms, and only the values
// that share those 32 bits are copied (no copy of all N values: peak memory).
double kth_finite(const double* v, std::ptrdiff_t n, std::ptrdiff_t k) {
  std::vector<std::uint32_t> hist(std::size_t{1} << 16);
  std::uint64_t prefix = 0;
  for (int shift : {48, 32}) {
    std::fill(hist.begin(), hist.end(), 0u);
    const std::uint64_t above = shift == 48 ? 0 : (prefix >> (shift + 16));
    for (std::ptrdiff_t i = 0; i < n; ++i) {
      if (!std::isfinite(v[i])) continue;
      const std::uint64_t b = sort_key(v[i]);
      if (shift != 48 && (b >> (shift + 16)) != above) continue;
      ++hist[(b >> shift) & 0xffffu];
    }
    std::size_t d = 0;
    while (k >= static_cast<std::ptrdiff_t>(hist[d])) k -= hist[d++];
    prefix |= static_cast<std::uint64_t>(d) << shift;
  }
  std::vector<double> w;
  for (std::ptrdiff_t i = 0; i < n; ++i) {
    if (std::isfinite(v[i]) && (sort_key(v[i]) >> 32) == (prefix >> 32)) w.push_back(v[i]);
  }
  std::nth_element(w.begin(), w.begin() + k, w.end());
  return w[static_cast<std::size_t>(k)];
}

// NumPy's median of the finite values (>= 0; the mean of the two middle ones for an even
// count); +inf when there is none.
double finite_median(const double* v, std::ptrdiff_t n) {
  std::ptrdiff_t m = 0;
  for (std::ptrdiff_t i = 0; i < n; ++i) m += std::isfinite(v[i]) ? 1 : 0;
  if (m == 0) return kInf;
  const std::ptrdiff_t mid = m / 2;
  double med = kth_finite(v, n, mid);
  if (m % 2 == 0) med = (kth_finite(v, n, mid - 1) + med) / 2.0;
  return med;
}

// The turn of sector s by `by` octants within its width (8 quarter, 8 half sectors).
inline int turned(int s, int by) { return (s / 8) * 8 + (s % 8 + 8 + by) % 8; }

// The index in kTurnCos / kTurnSin of sector s's bisector.
inline int bisector(int s) { return (s % 8 + 1 + s / 8) % 8; }

// What step 4 of SPEC "Unorganized clouds: edge test" says of P from its sectors alone.
enum class SectorVerdict { kFits, kProud, kOther };

// SPEC step 3's numbers of a sector's plane: h = u . (P - centroid) (the plane's mean is the
// centroid's offset from P), rms (0 for an exactly flat support), the tolerance's floor (its
// round-off floor, or P's precision floor `pfloor` when larger) and t = max(k rms, floor).
struct SectorFit {
  double h, rms, floor, tol;
};
inline SectorFit sector_fit(const LocalPlane& lp, double k, double pfloor) {
  const double n = static_cast<double>(lp.n);
  const Eigen::Vector3d& ev = lp.eigenvalues;
  const double rms = detail::edge_side_rms(ev(0), ev(2), n);
  const double floor = std::max(kRmsFloor * std::sqrt((ev(1) + ev(2)) / n), pfloor);
  return {-lp.normal.dot(lp.mean), rms, floor, std::max(k * rms, floor)};
}

// The level rule of SPEC step 4, per sector: bit s set when sector s is valid, its opposite is
// empty and a clean neighbour c of that opposite (the same width, turned by +-45 degrees) lies
// at s's level, |u_s . (m_c - m_s)| <= t_s: that empty opposite is no outline (the scan's
// border emptied it, not the part's). Also handed from the narrow scale to the wide one
// (step 7).
unsigned level_vetoes(const detail::EdgeSide (&sd)[kSectors], double best) {
  const double clean = detail::kEdgeCleanRatio * best;
  unsigned veto = 0;
  for (int s = 0; s < kSectors; ++s) {
    const detail::EdgeSide& x = sd[s];
    const int o = turned(s, 4);
    if (!x.valid || !sd[o].empty) continue;
    for (int by : {-1, 1}) {
      const detail::EdgeSide& c = sd[turned(o, by)];
      if (c.valid && c.rms <= clean &&
          !(std::abs(detail::dot3(x.normal, c.centroid - x.centroid)) > x.tol)) {
        veto |= 1u << s;
      }
    }
  }
  return veto;
}

// SPEC "Unorganized clouds: edge test" step 4 (the grid's steps 4-5, edge_verdict.hpp, plus the
// level, top and crossing rules): P stands proud of a clean sector `a` whose
// opposite (the sector of the same width turned by 180 degrees) falls away below a's plane (the
// centroid of its support, `centred`: at least 3 points, a plane or not: a flange falling away
// steeply leaves its sector too few points to be valid), or is empty while `veto`
// (level_vetoes) does not hold bit a (a bead or ridge on a surface that goes on past P, whose
// opposite sector only the scan's border empties, is not a lip before an outline), and no
// valid sector's centroid lies above P along a's normal (P is the top of what it stands on: a
// point on a fillet or a slope whose rising side the scan's border hides is not a lip), and
// every clean sector P fits lies past the feature (the crossing rule: its centroid below a's
// plane by more than a's tolerance; on a convex crease the far side's plane, extended back,
// runs through a lip on the near side). Centroids are relative to P. P fits a clean sector
// when |h| is within the cleanest sector's tolerance (k best, floored as the sector's own
// `floor`): a clean sector of larger rms (up to 2 best, e.g. one holding part of the burr run
// itself) does not lend P its wider tolerance.
// `*below`: when P fits no clean sector and stands proud of none, bit s set for each clean
// sector s that P lies below with the surface beyond falling away (the hanging rule's first
// condition, step 5; the rest needs the points): its opposite `gone` (fewer returns than
// kHangEmpty of a full sector, and not a face through P) or clean with P above it; `*raised`:
// then bit s set for each clean sector s that P lies above (h > tol) with the surface beyond
// rising (the lips' first condition, step 6): the centroid of the opposite's support (at least
// 3 points, `centred`) lies above s's plane by more than kLipRise x h.
SectorVerdict cloud_edge_verdict(const detail::EdgeSide (&sd)[kSectors],
                                 const bool (&centred)[kSectors], const bool (&gone)[kSectors],
                                 const double (&floor)[kSectors], double best, double k,
                                 unsigned veto, unsigned* below, unsigned* raised) {
  const double clean = detail::kEdgeCleanRatio * best;
  bool fit[kSectors];
  bool any_fit = false;
  for (int s = 0; s < kSectors; ++s) {
    const detail::EdgeSide& x = sd[s];
    fit[s] = x.valid && x.rms <= clean && !(std::abs(x.h) > std::max(k * best, floor[s]));
    any_fit = any_fit || fit[s];
  }
  for (int s = 0; s < kSectors; ++s) {
    const detail::EdgeSide& x = sd[s];
    if (!x.valid || !(x.rms <= clean) || !(x.h > x.tol)) continue;
    const int o = turned(s, 4);
    const detail::EdgeSide& y = sd[o];
    const bool outline = y.empty && !(veto >> s & 1u);
    if (!(outline ||
          (centred[o] && detail::edge_drops(x, y)))) {
      continue;
    }
    bool top = true;
    for (const detail::EdgeSide& z : sd) {
      if (z.valid && detail::dot3(x.normal, z.centroid) > 0.0) top = false;
    }
    if (!top) continue;
    // The crossing rule: a sector P fits clears it only when it is not past the feature (its
    // centroid not below x's plane by more than x's tolerance).
    bool cleared = false;
    for (int c = 0; c < kSectors && !cleared; ++c) {
      cleared = fit[c] && !detail::edge_drops(x, sd[c]);
    }
    if (!cleared) return SectorVerdict::kProud;
  }
  if (any_fit) return SectorVerdict::kFits;
  *below = 0;
  *raised = 0;
  for (int s = 0; s < kSectors; ++s) {
    const detail::EdgeSide& x = sd[s];
    if (!x.valid || !(x.rms <= clean)) continue;
    if (x.h > x.tol) {
      const int o = turned(s, 4);
      if (centred[o] && detail::dot3(x.normal, sd[o].centroid - x.centroid) > kLipRise * x.h) {
        *raised |= 1u << s;
      }
    }
    if (!(x.h < -x.tol)) continue;
    const detail::EdgeSide& y = sd[turned(s, 4)];
    if (gone[turned(s, 4)] ||
        (y.valid && y.rms <= clean && y.h > y.tol && detail::edge_drops(x, y))) {
      *below |= 1u << s;
    }
  }
  return SectorVerdict::kOther;
}

// Calls visit(k, o, wx, wy, wz) for each point k of `ball` (the points within r_edge of P,
// offsets w = q - P: select's) that is a sector member of P (`oct`: member_octants' octant of
// each point for P's frame, kNotMember for the others: not P, at least `gap` from P in the
// tangent plane, SPEC step 3); o its octant. In gather order.
template <typename Visit>
void for_each_member(const Selection& ball, const std::uint8_t* oct, Visit&& visit) {
  for (std::size_t k = 0; k < ball.n; ++k) {
    if (oct[k] != kNotMember) visit(k, oct[k], ball.wx[k], ball.wy[k], ball.wz[k]);
  }
}

// Octant o (0..7) lies in sector s (SPEC step 3: s < 8 holds octants s, s + 1; 8 + s holds
// s .. s + 3, mod 8).
inline bool in_sector(int o, int s) { return (o - s % 8 + 8) % 8 < (s < 8 ? 2 : 4); }

// A sector's member nearest to P (smallest |q - P|, then smallest index) and its offset.
struct Nearest {
  double d = kInf;
  std::uint32_t id = 0;
  Eigen::Vector3d w = Eigen::Vector3d::Zero();
  void offer(double dq, std::uint32_t iq, const Eigen::Vector3d& wq) {
    if (dq < d || (dq == d && iq < id)) d = dq, id = iq, w = wq;
  }
};

// u . (w - m): a member's signed distance from a sector's plane.
inline double off_plane(const detail::EdgeSide& x, const Eigen::Vector3d& w) {
  return detail::dot3(w - x.centroid, x.normal);
}

// SPEC "Unorganized clouds: edge test" step 5 (the grid's hanging rule with sectors): does P
// hang below one of the sectors in `below` (step 4's first condition holds for them)? Steeper
// than 45 degrees: of the sector's support points on its plane (not |u . (q - m)| > t: the
// top's, not material hanging below it) the one nearest to P (smallest |q - P|, then smallest
// index), v = q - P, lies above P more steeply than 45 degrees, u . v > 0 and
// (u . v)^2 > v.v - (u . v)^2; a shelf: the opposite sector is `gone` (the surface beyond has
// fallen out of reach) or holds a ground point (NORMAL or EDGE at the start of the pass) x
// with u . (x - P) < -2 delta (delta = -h, P's depth below the sector's plane). Or, with u . v
// > 0, P extends a ledge already removed: of the sector's ABNORMAL members below its plane
// (u . (y - m) < -t) the one nearest to P (same order) lies nearer than q (y . y < v . v) and
// level with P (|u . y| <= 0.5 delta).
bool hangs(const Selection& ball, const std::uint8_t* oct, const std::uint8_t* labels,
           const detail::EdgeSide (&sd)[kSectors], const bool (&gone)[kSectors],
           unsigned below) {
  // Per candidate sector: its nearest support point on its plane and its nearest ABNORMAL
  // member below its plane (distance, index, offset), and the deepest ground point along its
  // normal in the opposite sector.
  Nearest top[kSectors], ledge[kSectors];
  double low[kSectors];
  std::fill(low, low + kSectors, kInf);
  for_each_member(ball, oct, [&](std::size_t k, int o, double wx, double wy, double wz) {
    const std::uint8_t c = labels[ball.id[k]];
    if (c != kAbnormal && c != kNormal && c != kEdge) return;
    const Eigen::Vector3d w(wx, wy, wz);
    const double d = std::sqrt(detail::dot3(w, w));
    if (c == kAbnormal) {  // a ledge's material: below the sector's plane by more than t
      for (int s = 0; s < kSectors; ++s) {
        if (!(below >> s & 1u) || !in_sector(o, s)) continue;
        if (off_plane(sd[s], w) < -sd[s].tol) ledge[s].offer(d, ball.id[k], w);
      }
      return;
    }
    for (int s = 0; s < kSectors; ++s) {
      if (!(below >> s & 1u) || !in_sector(o, turned(s, 4))) continue;
      low[s] = std::min(low[s], detail::dot3(w, sd[s].normal));
    }
    if (c != kNormal) return;
    for (int s = 0; s < kSectors; ++s) {
      if (!(below >> s & 1u) || !in_sector(o, s)) continue;
      if (!(std::abs(off_plane(sd[s], w)) > sd[s].tol)) top[s].offer(d, ball.id[k], w);
    }
  });
  for (int s = 0; s < kSectors; ++s) {
    if (!(below >> s & 1u) || !(top[s].d < kInf)) continue;
    const detail::EdgeSide& x = sd[s];
    const double delta = -x.h;
    const Eigen::Vector3d& u = x.normal;
    const Eigen::Vector3d& v = top[s].w;
    const double along = detail::dot3(v, u), vv = detail::dot3(v, v);
    if (!(along > 0.0)) continue;
    const bool steep = along * along > vv - along * along;
    // ... or P extends a ledge already removed: its material y nearer than q, level with P
    const Eigen::Vector3d& y = ledge[s].w;
    const bool extends = ledge[s].d < kInf && detail::dot3(y, y) < vv &&
                         std::abs(detail::dot3(y, u)) <= kLedgeLevel * delta;
    if (!steep && !extends) continue;
    if (gone[turned(s, 4)] || low[s] < -kHangShelf * delta) return true;
  }
  return false;
}

// SPEC "Unorganized clouds: edge test" step 6, lips at a concave feature (the grid's rule,
// edge_test.cpp's is_lip, with a strip of the ball for its line of cells): is P a lip beyond one
// of the sectors s in `raised` (clean, P above them, the opposite's support rising: the
// caller's)? The *strip* beyond P away from s: the ground points (NORMAL or EDGE at the start of
// the pass) x whose tangent offset, along g (the bisector of s's opposite) and across it, has
// along > |across| (the quarter disk around g) and |across| <= kLipStrip x r_edge; in order of
// along (the furthest last, then the smallest index). With
// D = max(kEdgeLipTol x tol, kEdgeLipDip x h), a point before the last dips (u . (x - P) < -D)
// and the last lies above s's plane (h + u . (x - P) > tol): the surface beyond falls back
// below P, then rises (a concave crease or a step up), not a fillet (no dip) nor a bead or fin
// beyond P (the last point on the plane).
bool is_lip(const Selection& ball, const std::uint8_t* oct, const std::uint8_t* labels,
            const Frame& f, const CloudEdgeTest& e, const detail::EdgeSide (&sd)[kSectors],
            unsigned raised) {
  // Per sector of `raised`: the strip's last point (its offset along, index, u . (x - P)) and
  // the lowest u . (x - P) of the points before it.
  double low[kSectors], far[kSectors], last[kSectors];
  std::uint32_t lid[kSectors] = {};
  std::fill(low, low + kSectors, kInf);
  std::fill(far, far + kSectors, -kInf);
  std::fill(last, last + kSectors, kInf);
  const double width = kLipStrip * e.r_edge;
  // A point lies in the strip along bisector t only from octant t - 1 or t (along > |across|:
  // within 45 degrees of it); octants t - 2 .. t + 1 are let through (`window`, bit o), so that
  // rounding at the wedges' edges cannot leave one out.
  unsigned window[kSectors] = {}, any = 0;
  for (unsigned left = raised; left != 0; left &= left - 1) {
    const int s = __builtin_ctz(left), t = bisector(turned(s, 4));
    for (int d = -2; d <= 1; ++d) window[s] |= 1u << ((t + d + 8) % 8);
    any |= window[s];
  }
  for_each_member(ball, oct, [&](std::size_t k, int o, double wx, double wy, double wz) {
    if (!(any >> o & 1u)) return;
    const std::uint8_t c = labels[ball.id[k]];
    if (c != kNormal && c != kEdge) return;
    const Eigen::Vector3d w(wx, wy, wz);
    const double a = detail::dot3(w, f.e1), b = detail::dot3(w, f.e2);
    for (unsigned left = raised; left != 0; left &= left - 1) {
      const int s = __builtin_ctz(left);
      if (!(window[s] >> o & 1u)) continue;
      const int t = bisector(turned(s, 4));
      const double along = kTurnCos[t] * a + kTurnSin[t] * b;
      const double across = kTurnCos[t] * b - kTurnSin[t] * a;
      if (!(along > std::abs(across)) || std::abs(across) > width) continue;
      const double d = detail::dot3(w, sd[s].normal);
      if (along > far[s] || (along == far[s] && ball.id[k] < lid[s])) {
        low[s] = std::min(low[s], last[s]);  // the last so far now lies before the last
        far[s] = along;
        lid[s] = ball.id[k];
        last[s] = d;
      } else {
        low[s] = std::min(low[s], d);
      }
    }
  });
  for (int s = 0; s < kSectors; ++s) {
    if (!(raised >> s & 1u)) continue;
    const detail::EdgeSide& x = sd[s];
    const double dip = std::max(detail::kEdgeLipTol * x.tol, detail::kEdgeLipDip * x.h);
    if (low[s] < -dip && x.h + last[s] > x.tol) return true;
  }
  return false;
}

// The verdict on a point P with tangent frame f, from the finite points within r_edge of it
// (`ball`, select's, in gather order): the NORMAL ones (labels: at the start of the pass) are
// the support, the others count as returns only. `*level` (when given): P lies within t of
// every clean sector's plane; `*veto_out` (when given): this scale's level_vetoes; `veto_in`:
// the narrow scale's, at the wide one (SPEC step 7). `scratch`: the points' octants (grown
// when a ball needs more); `planes`: the sectors' planes.
bool cloud_edge_judge(const Selection& ball, const std::uint8_t* labels, const Frame& f,
                      const CloudEdgeTest& e, double pfloor, std::vector<std::uint8_t>& scratch,
                      PlaneBatch& planes, bool* level = nullptr, unsigned veto_in = 0,
                      unsigned* veto_out = nullptr) {
  // Each point's octant (kNotMember: no member), once for every rule below.
  if (scratch.size() < ball.n) scratch.resize(ball.n);
  std::uint8_t* const oct = scratch.data();
  member_octants(ball.wx.data(), ball.wy.data(), ball.wz.data(), ball.n, f, e.gap, oct);
  OffsetSums octs[8];
  double fin[8] = {};
#ifdef __SSE2__
  // OffsetSums::add in pairs of fields, (n, x) (y, z) (xx, xy) (xz, yy) (yz, zz): the same
  // operations on each field in the same order (the same bits).
  __m128d acc[8][5];
  for (auto& a : acc) {
    for (__m128d& r : a) r = _mm_setzero_pd();
  }
  for_each_member(ball, oct, [&](std::size_t k, int o, double wx, double wy, double wz) {
    fin[o] += 1.0;
    if (labels[ball.id[k]] != kNormal) return;
    const __m128d xy = _mm_set_pd(wy, wx), yz = _mm_set_pd(wz, wy);
    __m128d* a = acc[o];
    a[0] = _mm_add_pd(a[0], _mm_set_pd(wx, 1.0));
    a[1] = _mm_add_pd(a[1], yz);
    a[2] = _mm_add_pd(a[2], _mm_mul_pd(_mm_set1_pd(wx), xy));
    a[3] = _mm_add_pd(a[3], _mm_mul_pd(xy, _mm_set_pd(wy, wz)));
    a[4] = _mm_add_pd(a[4], _mm_mul_pd(yz, _mm_set1_pd(wz)));
  });
  for (int o = 0; o < 8; ++o) {
    alignas(16) double v[10];
    for (int q = 0; q < 5; ++q) _mm_store_pd(v + 2 * q, acc[o][q]);
    OffsetSums& t = octs[o];
    t.n = v[0], t.x = v[1], t.y = v[2], t.z = v[3], t.xx = v[4], t.xy = v[5];
    t.xz = v[6], t.yy = v[7], t.yz = v[8], t.zz = v[9];
  }
#else
  for_each_member(ball, oct, [&](std::size_t k, int o, double wx, double wy, double wz) {
    fin[o] += 1.0;
    if (labels[ball.id[k]] == kNormal) octs[o].add(wx, wy, wz);
  });
#endif
  // Sectors 0-7: s holds octants s, s + 1 (mod 8), [45 s, 45 s + 90) degrees from e1 towards
  // e2; sectors 8-15: 8 + s holds octants s .. s + 3, [45 s, 45 s + 180).
  double finite[kSectors];
  OffsetSums sums[kSectors];
  double full[2] = {0.0, 0.0};
  for (int s = 0; s < 8; ++s) {
    finite[s] = fin[s] + fin[(s + 1) % 8];
    sums[s] = octs[s].plus(octs[(s + 1) % 8]);
    finite[8 + s] = finite[s] + fin[(s + 2) % 8] + fin[(s + 3) % 8];
    sums[8 + s] = sums[s].plus(octs[(s + 2) % 8].plus(octs[(s + 3) % 8]));
    full[0] = std::max(full[0], finite[s]);
  }
  for (int s = 8; s < kSectors; ++s) full[1] = std::max(full[1], finite[s]);
  // Sector s's support points again, for plane_of.
  const auto support = [&](int s) {
    return [&, s](auto&& fn) {
      for_each_member(ball, oct, [&](std::size_t k, int o, double wx, double wy, double wz) {
        if (in_sector(o, s) && labels[ball.id[k]] == kNormal) fn(Eigen::Vector3d(wx, wy, wz));
      });
    };
  };
  bool valid[kSectors], empty[kSectors], gone[kSectors];
  double h[kSectors], rms[kSectors], tol[kSectors], floor[kSectors] = {};
  // The sectors' planes solved together (PlaneBatch: eigen_sym3's bits in vector code): each
  // sector with the support a valid one needs, and each gone one with 3 points (its face,
  // below); plane(s, lp) is then plane_of(sums[s], lp, support(s)).
  int at[kSectors];
  planes.reserve(kSectors);
  for (int s = 0; s < kSectors; ++s) {
    const double half = full[s / 8] / 2.0;
    empty[s] = finite[s] < kEmpty * full[s / 8];  // (a steep face keeps about half)
    gone[s] = finite[s] < kHangEmpty * full[s / 8];
    const bool want = sums[s].n >= std::max(3.0, half) || (gone[s] && sums[s].n >= 3.0);
    at[s] = want ? planes.add(sums_scatter(sums[s])) : -1;
  }
  planes.solve();
  const auto plane = [&](int s, LocalPlane* out) {
    return plane_of(planes, at[s], sums[s], out, support(s));
  };
  LocalPlane lp[kSectors];
  double best = kInf;
  for (int s = 0; s < kSectors; ++s) {
    const double half = full[s / 8] / 2.0;
    valid[s] = sums[s].n >= std::max(3.0, half) && plane(s, &lp[s]) == PlaneStatus::kOk;
    if (!valid[s]) continue;
    const SectorFit x = sector_fit(lp[s], e.k, pfloor);
    h[s] = x.h;
    rms[s] = x.rms;
    floor[s] = x.floor;
    tol[s] = x.tol;
    best = std::min(best, rms[s]);
  }
  // A gone sector is in reach after all when its support (a plane: at least 3 points, rms at
  // most kFaceClean x best) runs through P (within its own tolerance) steeper than 45 degrees
  // against the opposite sector's plane: a face falling away past a convex bend, sampled
  // sparsely in 3-D (SPEC step 5). `gone` is only read opposite a clean sector (valid: its
  // plane exists); a gone sector is never valid (fewer than 0.3 of a full sector's returns).
  for (int s = 0; s < kSectors; ++s) {
    const int o = turned(s, 4);
    if (!gone[s] || !valid[o] || sums[s].n < 3.0) continue;
    LocalPlane face;
    if (plane(s, &face) != PlaneStatus::kOk) continue;
    const SectorFit x = sector_fit(face, e.k, pfloor);
    if (x.rms <= kFaceClean * best && !(std::abs(x.h) > x.tol) &&
        std::abs(face.normal.dot(lp[o].normal)) < kFaceCos) {
      gone[s] = false;
    }
  }
  detail::EdgeSide sd[kSectors];  // centroids relative to P (the planes' means)
  bool centred[kSectors];         // a centroid of at least 3 support points (valid or not)
  for (int s = 0; s < kSectors; ++s) {
    sd[s].valid = valid[s];
    sd[s].empty = empty[s];
    centred[s] = sums[s].n >= 3.0;
    if (centred[s] && !valid[s]) {  // as plane_from_sums' mean
      const double inv = 1.0 / sums[s].n;
      sd[s].centroid = Eigen::Vector3d(sums[s].x * inv, sums[s].y * inv, sums[s].z * inv);
    }
    if (!valid[s]) continue;
    sd[s].h = h[s];
    sd[s].rms = rms[s];
    sd[s].tol = tol[s];
    sd[s].normal = lp[s].normal;
    sd[s].centroid = lp[s].mean;
  }
  const unsigned veto = level_vetoes(sd, best);
  if (veto_out != nullptr) *veto_out = veto;
  if (level != nullptr) {  // P within t of every clean sector's plane (step 7)
    *level = true;
    for (const detail::EdgeSide& x : sd) {
      if (x.valid && x.rms <= detail::kEdgeCleanRatio * best && std::abs(x.h) > x.tol) {
        *level = false;
      }
    }
  }
  unsigned below = 0, raised = 0;
  const SectorVerdict v =
      cloud_edge_verdict(sd, centred, gone, floor, best, e.k, veto | veto_in, &below, &raised);
  if (v != SectorVerdict::kOther) return v == SectorVerdict::kProud;
  return (below != 0 && e.hanging && hangs(ball, oct, labels, sd, gone, below)) ||
         (raised != 0 && is_lip(ball, oct, labels, f, e, sd, raised));
}

}  // namespace

template <typename T>
int cloud_edge_passes(const NeighborGrid<T>& grid, const PointsView<T>& points,
                      std::uint8_t* labels, std::vector<double>* first_rms,
                      const CloudEdgeTest& e, std::vector<JudgeScratch>& scratch,
                      int num_threads, std::vector<std::uint32_t>* unnormal) {
  const std::ptrdiff_t N = points.size;
  const int nt = static_cast<int>(scratch.size());
  std::vector<std::uint32_t> cand;  // ascending
  {
    const double* rms = first_rms->data();
    const double med = std::isnan(e.rms_median) ? finite_median(rms, N) : e.rms_median;
    const double thr = kSuspect * med;
    for (std::ptrdiff_t i = 0; i < N; ++i) {
      if ((labels[i] == kNormal || labels[i] == kEdge) &&
          (!std::isfinite(rms[i]) || rms[i] > thr)) {
        cand.push_back(static_cast<std::uint32_t>(i));
      }
    }
    std::vector<double>().swap(*first_rms);  // free N doubles before the frames (peak memory)
  }
  // Two scales (SPEC step 7): the sectors within r_edge and within kEdgeWide x r_edge, each
  // with the frame of its own disk (the plane of the finite points within it, the point
  // included, as the normals; it does not depend on the labels, so it is fitted when first
  // needed). The wide ball is selected only when the wide scale is asked.
  const std::ptrdiff_t nc = static_cast<std::ptrdiff_t>(cand.size());
  const double r_wide = kEdgeWide * e.r_edge;
  const double reach[2] = {e.r_edge, r_wide};
  CloudEdgeTest wide = e;  // the wide scale's sectors (the lips' strip scales with them)
  wide.r_edge = r_wide;
  wide.hanging = false;
  std::vector<Frame> frame(2 * cand.size());  // candidate c, scale s: 2 c + s
  // bit s: scale s has a frame; bit 2 + s: scale s's frame was fitted (or found impossible)
  std::vector<std::uint8_t> framed(cand.size(), 0);
  std::vector<std::uint8_t> verdict(cand.size(), 0);
  // The narrow scale's last verdict on the candidate (it did not flag P, or P would not be
  // judged again): whether P was level (the wide scale not asked) and its level_vetoes; and
  // whether the next judgment may take them as they are (no label within the narrow radius
  // changed since).
  std::vector<std::uint8_t> level_at(cand.size(), 0), narrow_kept(cand.size(), 0);
  std::vector<std::uint16_t> veto_at(cand.size(), 0);
  const double near2 = e.r_edge * e.r_edge * (1.0 + 1e-9);
  // Candidate c's verdict at point p on the labels: ABNORMAL at either scale; the wide one is
  // asked only when the narrow one neither flags P nor finds it level (SPEC step 7).
  auto judge = [&](std::uint32_t c, const Eigen::Vector3d& p, JudgeScratch& js) {
    Selection* ball[2] = {&js.sel, &js.wide};
    bool flag = false, level = false;
    unsigned veto = 0;
    const double pfloor = e.prec * p.cwiseAbs().maxCoeff();  // (P as given)
    int s = 0;
    if (narrow_kept[c]) {  // the narrow verdict as before: not level, its vetoes
      veto = veto_at[c];
      s = 1;
    }
    for (; s < 2 && !flag && !level; ++s) {
      select_box(grid, grid.box_around(p, p, reach[s]), p, reach[s] * reach[s], *ball[s]);
      Frame& f = frame[2 * c + s];
      if (!(framed[c] >> (2 + s) & 1u)) {
        framed[c] |= static_cast<std::uint8_t>(4u << s);
        LocalPlane lp;
        if (fit_selection(*ball[s], true, &lp) == PlaneStatus::kOk) {
          f.e1 = lp.major;
          f.e2 = lp.normal.cross(lp.major);
          framed[c] |= static_cast<std::uint8_t>(1u << s);
        }
      }
      if (framed[c] >> s & 1u) {
        flag = s == 0 ? cloud_edge_judge(js.sel, labels, f, e, pfloor, js.members,
                                         js.cell.batch, &level, 0, &veto)
                      : cloud_edge_judge(js.wide, labels, f, wide, pfloor, js.members,
                                         js.cell.batch, nullptr, veto);
      }
    }
    level_at[c] = level;  // (the narrow scale's: the wide one gives none)
    veto_at[c] = static_cast<std::uint16_t>(veto);
    return flag;
  };
  {
    // Pass 1, with the frames. Visited in the grid's cell order (its cell key), not the
    // input's, which a shuffled cloud scatters: one candidate's gather then touches the cells
    // the last one did. Only the speed depends on the order: each candidate has its own slot.
    std::vector<std::pair<std::uint64_t, std::uint32_t>> by_cell(cand.size());
    for (std::ptrdiff_t c = 0; c < nc; ++c) {
      by_cell[c] = {grid.key_of(points[cand[c]]), static_cast<std::uint32_t>(c)};
    }
    std::sort(by_cell.begin(), by_cell.end());
    const int ntc = std::min(nt, detail::thread_count(num_threads, nc, 256));
#pragma omp parallel for schedule(dynamic, 32) num_threads(ntc) if (ntc > 1)
    for (std::ptrdiff_t q = 0; q < nc; ++q) {
      const std::uint32_t c = by_cell[q].second;
      verdict[c] = judge(c, points[cand[c]], scratch[thread_id()]);
    }
  }
  // Testable: a frame at either scale (a wide frame not yet fitted: the narrow one exists).
  std::vector<std::uint32_t> todo;
  for (std::ptrdiff_t c = 0; c < nc; ++c) {
    if (framed[c] & 3u) todo.push_back(static_cast<std::uint32_t>(c));
  }
  std::vector<std::uint8_t> mark(cand.size(), 0);  // per candidate
  std::vector<std::uint32_t> fresh;
  int passes = 0;
  while (passes < e.max_iterations) {
    ++passes;
    const std::ptrdiff_t nj = static_cast<std::ptrdiff_t>(todo.size());
    if (passes > 1) {  // pass 1's verdicts came with the frames
      const int ntj = std::min(nt, detail::thread_count(num_threads, nj, 256));
#pragma omp parallel for schedule(dynamic, 32) num_threads(ntj) if (ntj > 1)
      for (std::ptrdiff_t j = 0; j < nj; ++j) {
        const std::uint32_t c = todo[j], i = cand[c];
        verdict[c] = (labels[i] == kNormal || labels[i] == kEdge) &&
                     judge(c, points[i], scratch[thread_id()]);
      }
    }
    fresh.clear();
    for (std::uint32_t c : todo) {
      if (!verdict[c]) continue;
      verdict[c] = 0;
      const std::uint32_t i = cand[c];
      if (unnormal != nullptr && labels[i] == kNormal) unnormal->push_back(i);
      labels[i] = kAbnormal;
      fresh.push_back(i);
    }
    if (fresh.empty()) break;
    // Only the candidates with a new ABNORMAL point within the wide radius can change; of
    // those whose narrow scale found P level (the wide one not asked), only the ones with such
    // a point within the narrow radius (their narrow ball's labels changed; its frame is kept);
    // the others without one keep their narrow verdict and ask the wide scale again: mark bit 1
    // within r_wide, bit 2 within r_edge (a relative 1e-9 wider than select_box's test, so that
    // no rounding leaves one out).
    todo.clear();
    for (std::uint32_t u : fresh) {
      grid.for_each_in_radius(points[u], r_wide, [&](std::ptrdiff_t j, double d2) {
        const auto it = std::lower_bound(cand.begin(), cand.end(), static_cast<std::uint32_t>(j));
        if (it == cand.end() || *it != static_cast<std::uint32_t>(j)) return;
        const std::size_t c = static_cast<std::size_t>(it - cand.begin());
        if (!(framed[c] & 3u)) return;
        if (!mark[c]) todo.push_back(static_cast<std::uint32_t>(c));
        mark[c] |= d2 <= near2 ? 3 : 1;
      });
    }
    std::size_t kept = 0;
    for (std::uint32_t c : todo) {
      if ((mark[c] & 2) || !level_at[c]) todo[kept++] = c;
      narrow_kept[c] = !(mark[c] & 2);  // (read only for those judged: not level)
      mark[c] = 0;
    }
    todo.resize(kept);
    std::sort(todo.begin(), todo.end());
  }
  return passes;
}

template int cloud_edge_passes<float>(const NeighborGrid<float>&, const PointsView<float>&,
                                      std::uint8_t*, std::vector<double>*, const CloudEdgeTest&,
                                      std::vector<JudgeScratch>&, int,
                                      std::vector<std::uint32_t>*);
template int cloud_edge_passes<double>(const NeighborGrid<double>&, const PointsView<double>&,
                                       std::uint8_t*, std::vector<double>*, const CloudEdgeTest&,
                                       std::vector<JudgeScratch>&, int,
                                       std::vector<std::uint32_t>*);

}  // namespace miem::cloud
