// Height passes on unorganized clouds (docs/SPEC.md, "Unorganized clouds: floating groups and
// height test"). Jacobi passes: within a pass the NORMAL set and the EDGE groups are fixed; the
// first pass tests every NORMAL and compact-EDGE point (one gather per grid cell), later passes
// only the points within the height radius of a point whose role changed.
#include <algorithm>
#include <cmath>

#include "cloud_stages.hpp"
#include "edge_verdict.hpp"

namespace miem::cloud {

namespace {

// Role of a point in a height pass.
enum Role : std::uint8_t { kRoleNormal = 0, kRoleCompact = 1, kRoleLine = 2, kRoleNone = 3 };

// Roles from the labels: EDGE points grouped by distance <= link, a group is compact when twice
// the largest distance of a member from its centroid is <= compact_len.
template <typename T>
void assign_roles(const NeighborGrid<T>& grid, const PointsView<T>& points,
                  const std::uint8_t* labels, double link, double compact_len,
                  std::vector<std::uint8_t>& role, std::vector<std::int64_t>& queue) {
  const std::ptrdiff_t N = points.size;
  for (std::ptrdiff_t i = 0; i < N; ++i) {
    role[i] = labels[i] == kNormal ? kRoleNormal : labels[i] == kEdge ? 4 : kRoleNone;
  }
  for (std::ptrdiff_t start = 0; start < N; ++start) {
    if (role[start] != 4) continue;
    queue.assign(1, start);
    role[start] = 5;  // grouped, undecided
    for (std::size_t head = 0; head < queue.size(); ++head) {
      grid.for_each_in_radius(points[queue[head]], link, [&](std::ptrdiff_t j, double) {
        if (role[j] == 4) {
          role[j] = 5;
          queue.push_back(j);
        }
      });
    }
    std::sort(queue.begin(), queue.end());
    Eigen::Vector3d sum = Eigen::Vector3d::Zero();
    for (std::int64_t j : queue) sum += points[j];
    const Eigen::Vector3d c = sum / static_cast<double>(queue.size());
    double far2 = 0.0;
    for (std::int64_t j : queue) far2 = std::max(far2, (points[j] - c).squaredNorm());
    const std::uint8_t r = 2.0 * std::sqrt(far2) <= compact_len ? kRoleCompact : kRoleLine;
    for (std::int64_t j : queue) role[j] = r;
  }
}

// The bead rule (SPEC "Unorganized clouds: floating groups and height test", step 3): is p,
// which the test would flag, on a designed bead one point wide across its surroundings? `w`:
// the offsets from p of the usable (NORMAL or EDGE) points q != p within the height radius;
// (u, mean) the surroundings plane (mean: its centroid offset from p), h = u . (p - centroid).
// The run (p and the points q at p's level: |sign(h) u . (q - centroid) - |h|| < |h| / 2) is a
// line one point wide (at least 3 points; the square root of the middle eigenvalue of the
// covariance of their offsets below kBeadWidth spacings) that crosses p's ball (along the
// line's direction it reaches within kBeadMargin spacings of the farthest points both ways),
// and the other points lie on both sides of it (each side at least kBeadSide of them).
inline bool on_bead(const std::vector<Eigen::Vector3d>& w, const LocalPlane& lp,
                    double spacing) {
  const Eigen::Vector3d& u = lp.normal;
  const double h = -u.dot(lp.mean);
  const double level = std::abs(h), band = kBeadLevel * level, sgn = h > 0.0 ? 1.0 : -1.0;
  auto in_run = [&](const Eigen::Vector3d& q) {
    return std::abs(sgn * u.dot(q - lp.mean) - level) < band;
  };
  double n = 1.0;  // p, at offset 0
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  Eigen::Matrix3d sq = Eigen::Matrix3d::Zero();
  for (const Eigen::Vector3d& q : w) {
    if (!in_run(q)) continue;
    n += 1.0;
    sum += q;
    sq += q * q.transpose();
  }
  if (n < 3.0) return false;
  const Eigen::Vector3d c = sum / n;
  const Eigen::Matrix3d C = sq / n - c * c.transpose();
  Eigen::Vector3d ev;
  Eigen::Matrix3d V;
  eigen_sym3(C, ev, V);
  const double width = kBeadWidth * spacing;
  if (!(ev(1) < width * width)) return false;
  Eigen::Vector3d L = V.col(2) - V.col(2).dot(u) * u;
  if (!(L.squaredNorm() > 0.0)) return false;
  L.normalize();
  const Eigen::Vector3d across = u.cross(L);
  double run_lo = 0.0, run_hi = 0.0, all_lo = 0.0, all_hi = 0.0, plus = 0.0, minus = 0.0;
  for (const Eigen::Vector3d& q : w) {
    const double a = L.dot(q);
    all_lo = std::min(all_lo, a);
    all_hi = std::max(all_hi, a);
    if (in_run(q)) {
      run_lo = std::min(run_lo, a);
      run_hi = std::max(run_hi, a);
    } else {
      const double b = across.dot(q - c);
      plus += b > 0.0 ? 1.0 : 0.0;
      minus += b < 0.0 ? 1.0 : 0.0;
    }
  }
  const double margin = kBeadMargin * spacing;
  if (!(run_lo <= all_lo + margin && run_hi >= all_hi - margin)) return false;
  const double side = kBeadSide * (plus + minus);
  return plus + minus > 0.0 && plus >= side && minus >= side;
}

// The usable points' offsets for on_bead: the NORMAL ones within the height radius (ring
// positions s.pos[0..n_ring), inner s.id[0..n_inner), ball_sums'; not p) and the EDGE ones of
// `edges` (compact: a feature-line point near made the test abstain before).
inline bool bead_at(const Gather& g, const Gather& edges, Selection& s, std::size_t n_ring,
                    std::size_t n_inner, const Eigen::Vector3d& p, double r2,
                    const LocalPlane& lp, double spacing) {
  std::vector<Eigen::Vector3d>& w = s.offsets;  // the thread's scratch: no allocation once grown
  w.clear();
  auto at = [&](const Gather& x, std::size_t k) {
    return Eigen::Vector3d(x.x[k] - p.x(), x.y[k] - p.y(), x.z[k] - p.z());
  };
  for (std::size_t q = 0; q < n_inner; ++q) {
    if (s.all_d2[s.id[q]] > 0.0) w.push_back(at(g, s.id[q]));
  }
  for (std::size_t q = 0; q < n_ring; ++q) w.push_back(at(g, s.pos[q]));
  for (std::size_t k = 0; k < edges.n; ++k) {
    const Eigen::Vector3d q = at(edges, k);
    const double d2 = q.squaredNorm();
    if (d2 > 0.0 && d2 <= r2) w.push_back(q);
  }
  return on_bead(w, lp, spacing);
}

// The first part of the height verdict of point p from the NORMAL candidates `g` and the EDGE
// candidates `lines` (feature-line and compact, told apart by `role`) gathered around it: whether
// a feature-line point lies within t.radius (the test abstains), the sums of the NORMAL points
// within t.radius (those beyond t.inner are the surroundings, `around`, not the point's own
// bump) and their planes' scatter matrices added to `pb`: the surroundings' for the verdict, all
// of them for the height (`want_height`). None when the test abstains and no height is wanted:
// then false (`s` holds no selection of p), else true.
inline bool ball_sums_of(const Gather& g, const Gather& lines, const std::uint8_t* role,
                         const Eigen::Vector3d& p, const HeightTest& t, bool want_height,
                         Selection& s, BallSums& b, PlaneBatch& pb) {
  const double r2 = t.radius * t.radius, in2 = t.inner * t.inner;
  const double px = p.x(), py = p.y(), pz = p.z();
  bool line = false;
  for (std::size_t k = 0; k < lines.n; ++k) {
    const double dx = lines.x[k] - px, dy = lines.y[k] - py, dz = lines.z[k] - pz;
    line |= role[lines.id[k]] == kRoleLine && dx * dx + dy * dy + dz * dz <= r2;
  }
  b.line = line;
  b.ball = b.ring = -1;
  if (line && !want_height) return false;
  ball_sums(g, p, r2, in2, s, &b.around, &b.inner);
  if (want_height) {
    const OffsetSums all = b.around.plus(b.inner);
    if (all.n >= 3.0) b.ball = pb.add(sums_scatter(all));
  }
  if (!line && b.around.n >= 3.0) b.ring = pb.add(sums_scatter(b.around));
  return true;
}

// The height verdict of point p from its BallSums `b` (ball_sums_of; the batch `pb` solved):
// with `height`, also the point's height over the plane of the NORMAL points within t.radius
// (the same selection and sums as the heights stage's, height_plane: the same value to the
// bit). Unless `selected` (s holds p's selection), the selection is formed again where a rule
// reads the points themselves (rare: a refit, the bead and isolated-point rules).
inline bool too_far_from(const Gather& g, const Gather& lines, const Eigen::Vector3d& p,
                         const HeightTest& t, Selection& s, const BallSums& b,
                         const PlaneBatch& pb, bool selected, double* height,
                         double* rms_out) {
  const double r2 = t.radius * t.radius, in2 = t.inner * t.inner;
  const double px = p.x(), py = p.y(), pz = p.z();
  const OffsetSums& around = b.around;
  const OffsetSums& inner = b.inner;
  auto select_again = [&] {
    if (selected) return;
    OffsetSums x, y;
    ball_sums(g, p, r2, in2, s, &x, &y);
    selected = true;
  };
  auto plane = [&](int at, const OffsetSums& sums, bool with_inner, LocalPlane* lp) {
    return plane_of(pb, at, sums, lp, [&](auto&& f) {
      select_again();
      ball_offsets(g, p, s, around, inner, with_inner)(f);
    });
  };
  const std::size_t n_ring = static_cast<std::size_t>(around.n);
  const std::size_t m_in = static_cast<std::size_t>(inner.n);
  LocalPlane lp;
  auto flag = [&] {
    select_again();
    return !bead_at(g, lines, s, n_ring, m_in, p, r2, lp, t.spacing);
  };
  if (height != nullptr) {
    *height = plane(b.ball, around.plus(inner), true, &lp) == PlaneStatus::kOk
                  ? -lp.normal.dot(lp.mean)
                  : kNaN;
  }
  if (b.line) return false;
  if (plane(b.ring, around, false, &lp) != PlaneStatus::kOk) return false;
  const double h = std::abs(lp.normal.dot(lp.mean));
  const double n = static_cast<double>(lp.n);
  const Eigen::Vector3d& ev = lp.eigenvalues;
  const double rms = std::sqrt(std::max(ev(0), 0.0) / n);
  if (rms_out != nullptr) *rms_out = detail::edge_side_rms(ev(0), ev(2), n);  // 0: exactly flat
  if (t.abs > 0.0 && h > t.abs) return flag();
  if (!(t.k > 0.0) && !(t.iso_k > 0.0)) return false;
  // The common case first: below every multiple of the rms in use (the isolated-point rule
  // applies with a length tolerance too).
  const double k_lo = !(t.k > 0.0) ? t.iso_k : t.iso_k > 0.0 ? std::min(t.k, t.iso_k) : t.k;
  if (!(h > k_lo * rms)) return false;
  if (!(h > 1e-9 * std::sqrt((ev(1) + ev(2)) / n))) return false;
  if (t.k > 0.0 && h > t.k * rms) return flag();
  if (!(t.iso_k > 0.0 && h > t.iso_k * rms)) return false;
  // The isolated-point rule: the NORMAL points q != p within t.inner (the inner positions
  // ball_sums left in s.id; p itself is the one at distance 0) lie about the surroundings plane
  // as loosely as its rms says: the median of their |heights| is at least kIsolatedMedian rms.
  select_again();
  const double nx = lp.normal.x(), ny = lp.normal.y(), nz = lp.normal.z();
  const double mx = lp.mean.x(), my = lp.mean.y(), mz = lp.mean.z();
  double* __restrict hv = s.wx.data();  // free here: ball_sums does not use it
  std::size_t m = 0;
  for (std::size_t q = 0; q < m_in; ++q) {
    const std::uint32_t k = s.id[q];
    if (!(s.all_d2[k] > 0.0)) continue;
    const double wx = g.x[k] - px, wy = g.y[k] - py, wz = g.z[k] - pz;
    hv[m++] = std::abs(nx * (wx - mx) + ny * (wy - my) + nz * (wz - mz));
  }
  if (m < 3) return false;
  const std::size_t mid = m / 2;
  std::nth_element(hv, hv + mid, hv + m);
  double med = hv[mid];
  if (m % 2 == 0) med = (*std::max_element(hv, hv + mid) + med) / 2.0;
  return med >= kIsolatedMedian * rms && flag();
}

// The height verdict of one point (ball_sums_of, its planes solved, too_far_from).
inline bool too_far(const Gather& g, const Gather& lines, const std::uint8_t* role,
                    const Eigen::Vector3d& p, const HeightTest& t, Selection& s,
                    PlaneBatch& pb, double* height, double* rms_out) {
  BallSums b;
  pb.reserve(2);
  const bool selected = ball_sums_of(g, lines, role, p, t, height != nullptr, s, b, pb);
  pb.solve();
  return too_far_from(g, lines, p, t, s, b, pb, selected, height, rms_out);
}

}  // namespace

template <typename T>
int height_passes(const NeighborGrid<T>& grid, const PointsView<T>& points, std::uint8_t* labels,
                  const HeightTest& t, std::vector<JudgeScratch>& scratch, int num_threads) {
  const std::ptrdiff_t N = points.size;
  const int nt = static_cast<int>(scratch.size());
  std::vector<std::uint8_t> role(static_cast<std::size_t>(N)), prev;
  std::vector<std::uint8_t> mark(static_cast<std::size_t>(N), 0);  // 1: new ABNORMAL
  std::vector<std::int64_t> queue, candidates;
  const std::uint32_t* order = grid.order();
  const std::uint8_t* rl = nullptr;
  // Candidate classes in grid order (sequential reads in the gathers): NORMAL points into the
  // main list, EDGE points (feature-line and compact) aside.
  std::vector<std::uint8_t> class_sorted(static_cast<std::size_t>(grid.num_indexed()));
  const std::uint8_t* cs = class_sorted.data();
  auto class_of = [cs](std::uint32_t k, std::uint32_t) { return cs[k]; };
  auto tested = [](std::uint8_t r) { return r == kRoleNormal || r == kRoleCompact; };
  int passes = 0;
  while (passes < t.max_iterations) {
    assign_roles(grid, points, labels, t.link, t.compact_len, role, queue);
    rl = role.data();
    {
      const std::ptrdiff_t ni = grid.num_indexed();
      const int ntn = detail::thread_count(num_threads, ni);
#pragma omp parallel for schedule(static) num_threads(ntn) if (ntn > 1)
      for (std::ptrdiff_t k = 0; k < ni; ++k) {
        const std::uint8_t r = rl[order[k]];
        class_sorted[k] = r == kRoleNormal                        ? kClassMain
                          : r == kRoleLine || r == kRoleCompact ? kClassAside
                                                                : kClassSkip;
      }
    }
    ++passes;
    if (passes == 1) {
      parallel_cells(grid, nt, [&](std::ptrdiff_t cell, int tid) {
        const std::uint32_t b = grid.cell_begin(cell), e = grid.cell_begin(cell + 1);
        bool any = false;
        for (std::uint32_t k = b; k < e && !any; ++k) any = tested(rl[order[k]]);
        if (!any) return;
        JudgeScratch& js = scratch[tid];
        gather_split(grid, cell_box(grid, cell, t.radius), class_of, js.gather, js.aside);
        // The cell's points in two loops: their sums and planes' matrices, the planes solved
        // together (PlaneBatch: vector code), then their verdicts.
        CellPlanes& cp = js.cell;
        cp.start(e - b, 2);
        if (cp.balls.size() < e - b) cp.balls.resize(e - b);
        for (std::uint32_t k = b; k < e; ++k) {
          if (!tested(rl[order[k]])) continue;
          ball_sums_of(js.gather, js.aside, rl, grid.sorted_point(k), t, t.height != nullptr,
                       js.sel, cp.balls[k - b], cp.batch);
        }
        cp.batch.solve();
        for (std::uint32_t k = b; k < e; ++k) {
          if (k + kPrefetchAhead < e) {  // a later point's outputs (cloud_stages.hpp)
            const std::uint32_t f = order[k + kPrefetchAhead];
            if (t.height != nullptr) __builtin_prefetch(t.height + f, 1);
            if (t.first_rms != nullptr) __builtin_prefetch(t.first_rms + f, 1);
            if (t.have != nullptr) __builtin_prefetch(t.have + f, 1);
            __builtin_prefetch(mark.data() + f, 1);
          }
          const std::uint32_t i = order[k];
          if (!tested(rl[i])) continue;
          double* h = t.height != nullptr ? t.height + i : nullptr;
          double* rms = t.first_rms != nullptr ? t.first_rms + i : nullptr;
          if (too_far_from(js.gather, js.aside, grid.sorted_point(k), t, js.sel,
                           cp.balls[k - b], cp.batch, false, h, rms)) {
            mark[i] = 1;
          }
          if (h != nullptr) t.have[i] = 1;
        }
      });
    } else {
      // Points within the height radius of a point whose role changed.
      candidates.clear();
      std::vector<std::uint8_t>& seen = mark;  // all 0 here
      for (std::ptrdiff_t i = 0; i < N; ++i) {
        if (role[i] == prev[i]) continue;
        grid.for_each_in_radius(points[i], t.radius, [&](std::ptrdiff_t j, double) {
          if (!seen[j] && tested(rl[j])) {
            seen[j] = 2;
            candidates.push_back(j);
          }
        });
      }
      for (std::int64_t j : candidates) seen[j] = 0;
      std::sort(candidates.begin(), candidates.end());
      const std::ptrdiff_t nc = static_cast<std::ptrdiff_t>(candidates.size());
      const int ntc = std::min(nt, detail::thread_count(num_threads, nc, 1024));  // <= scratch
#pragma omp parallel for schedule(dynamic, 64) num_threads(ntc) if (ntc > 1)
      for (std::ptrdiff_t c = 0; c < nc; ++c) {
        const std::int64_t i = candidates[c];
        JudgeScratch& js = scratch[thread_id()];
        const Eigen::Vector3d pi = points[i];
        gather_split(grid, grid.box_around(pi, pi, t.radius), class_of, js.gather, js.aside);
        if (too_far(js.gather, js.aside, rl, pi, t, js.sel, js.cell.batch, nullptr, nullptr)) {
          mark[i] = 1;
        }
      }
    }
    std::ptrdiff_t added = 0;
    for (std::ptrdiff_t i = 0; i < N; ++i) {
      if (mark[i]) {
        if (t.unnormal != nullptr && labels[i] == kNormal) {
          t.unnormal->push_back(static_cast<std::uint32_t>(i));
        }
        labels[i] = kAbnormal;
        mark[i] = 0;
        ++added;
      }
    }
    if (added == 0) break;
    prev = role;
    // Roles are recomputed at the top of the next pass; points whose role changes there (new
    // ABNORMAL points, EDGE groups split or joined) trigger the re-tests.
  }
  return passes;
}

template int height_passes<float>(const NeighborGrid<float>&, const PointsView<float>&,
                                  std::uint8_t*, const HeightTest&, std::vector<JudgeScratch>&,
                                  int);
template int height_passes<double>(const NeighborGrid<double>&, const PointsView<double>&,
                                   std::uint8_t*, const HeightTest&, std::vector<JudgeScratch>&,
                                   int);

}  // namespace miem::cloud
