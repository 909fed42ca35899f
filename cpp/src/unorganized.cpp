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

#include "cloud_kernels.hpp"
#include "cloud_stages.hpp"
#include "finite_bounds.hpp"
#include "duplicates.hpp"
#include "edge_verdict.hpp"
#include "defects.hpp"
#include "miem/neighbor_grid.hpp"
#include "parallel.hpp"

namespace miem {

using namespace cloud;  // NOLINT(google-build-using-namespace): the stage kernels

// ---------------------------------------------------------------------------------------------
// spacing

namespace {

// SPEC "Numbers": throws CoordinateRangeError when a finite coordinate of `points` lies
// outside the coordinate range (one read pass).
template <typename T>
void check_range(const PointsView<T>& points) {
  check_coordinate_range(largest_finite_magnitude(points.data, points.size, 3,
                                                  points.point_stride, points.coord_stride),
                         "points");
}

// Distance from every finite point to its nearest other finite point (NaN for non-finite rows,
// 0 for a duplicate). Throws when a finite coordinate lies outside SPEC's range
// (CoordinateRangeError), there are fewer than 3 finite points or all are one point.
template <typename T>
std::vector<double> nearest_other(const PointsView<T>& points, int num_threads) {
  check_view(points);
  check_range(points);
  const detail::FiniteBounds fb =
      detail::finite_bounds(points, detail::thread_count(num_threads, points.size));
  const std::ptrdiff_t n_finite = fb.count;
  if (n_finite < 3) {
    throw std::invalid_argument("points: need at least 3 finite points, found " +
                                std::to_string(n_finite));
  }
  // A first cell size from the bounding box (a scan is a sheet: ~ area / N per point), refined
  // until the occupied cells hold a few points each. Only speed depends on it, never the result.
  Eigen::Vector3d ext = fb.hi - fb.lo;
  std::sort(ext.data(), ext.data() + 3);  // ascending
  if (!(ext(2) > 0.0)) {
    throw std::invalid_argument(
        "points: all finite points are one point (no spacing, no surface to test)");
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
  return nn;
}

// Median of the finite values of nn (the mean of the two middle values for an even count).
double median_spacing(std::vector<double> nn) {
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
        "points: spacing is 0 (more than half of the finite points are duplicates; "
        "detect_points merges them)");
  }
  return spacing;
}

}  // namespace

template <typename T>
double point_spacing(const PointsView<T>& points, int num_threads) {
  return median_spacing(nearest_other(points, num_threads));
}

template <typename T>
void distinct_spacings(const PointsView<T>& points, double merge_distance, double* out,
                       int num_threads) {
  if (!(std::isfinite(merge_distance) && merge_distance >= 0.0)) {
    throw std::invalid_argument("merge_distance: must be finite and >= 0");
  }
  const std::vector<double> nn = nearest_other(points, num_threads);
  const Duplicates dup = find_duplicates(points, nn, merge_distance, num_threads);
  if (dup.merged == 0) {
    std::copy(nn.begin(), nn.end(), out);
    return;
  }
  std::fill(out, out + points.size, kNaN);
  const std::size_t m = dup.distinct.size();
  if (m < 3) return;  // detect_points refuses such a cloud
  std::vector<T> buf(3 * m);
  for (std::size_t k = 0; k < m; ++k) {
    const T* q = points.data + dup.distinct[k] * points.point_stride;
    for (int a = 0; a < 3; ++a) buf[3 * k + a] = q[a * points.coord_stride];
  }
  const PointsView<T> view{buf.data(), static_cast<std::ptrdiff_t>(m), 3, 1};
  const std::vector<double> dn = nearest_other(view, num_threads);
  for (std::size_t k = 0; k < m; ++k) out[dup.distinct[k]] = dn[k];
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
  check_range(points);
  const std::ptrdiff_t n = points.size;
  const int ni = detail::thread_count(num_threads, n);
#pragma omp parallel for schedule(static) num_threads(ni) if (ni > 1)
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
    // The cell's points in two loops: their neighbourhoods' scatters, solved together
    // (PlaneBatch: vector code), then their planes (fit_selection's).
    const std::uint32_t b = grid.cell_begin(cell), e = grid.cell_begin(cell + 1);
    CellPlanes& cp = js.cell;
    cp.start(e - b, 1);
    for (std::uint32_t k = b; k < e; ++k) {
      select(js.gather, grid.sorted_point(k), r2, -1, js.sel);
      cp.add_fit(k - b, js.sel);
    }
    cp.batch.solve();
    for (std::uint32_t k = b; k < e; ++k) {
      const std::uint32_t i = order[k];
      if (out.count) out.count[i] = static_cast<std::int64_t>(cp.n[k - b]);
      LocalPlane lp;
      if (cp.fit(k - b, false, &lp) != PlaneStatus::kOk) continue;
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

namespace {

// Detection on a cloud without duplicates (within merge_distance), its spacing known; `hooks`
// (PointsDetectHooks) with `hooks.edge_rms` already for these points.
template <typename T>
PointsDetectSummary detect_distinct(const PointsView<T>& points, const PointsDetectParams& p,
                                    const PointsOutput& out, double spacing,
                                    const PointsDetectHooks& hooks) {
  const std::ptrdiff_t N = points.size;

  PointsDetectSummary summary;
  summary.spacing = spacing;
  const double radius = p.radius ? *p.radius : 5.0 * summary.spacing;
  const double min_step = p.min_step ? *p.min_step : 0.5 * summary.spacing;
  const double link = p.link ? *p.link : radius;
  summary.radius = radius;
  summary.min_step = min_step;
  summary.link = link;
  const double hr = p.height_radius ? *p.height_radius : 2.0 * radius;
  summary.height_radius = hr;
  const double r2 = hr * hr;  // of the height planes
  if (p.edge_k > 0.0) summary.edge_radius = p.edge_radius ? *p.edge_radius : hr;

  StageClock clock(&summary.stage_seconds);
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

  clock.lap("grid");
  const PointJudge judge(p, radius, min_step);
  const std::uint8_t* st = state.data();
  auto usable = [st](std::uint32_t, std::uint32_t j) { return (st[j] & 1) != 0; };
  auto every = [](std::uint32_t, std::uint32_t) { return true; };
  // Finite neighbours within radius (pass 1), for the floating groups.
  std::vector<std::uint16_t> counts(p.min_group > 0 ? static_cast<std::size_t>(N) : 0);
  // judge(i, flags, angle, degenerate) gives point i's label and the rest: all stored
  auto judge_point = [&](std::uint32_t i, auto&& judge) {
    std::uint8_t fl = 0;
    double an = kNaN;
    bool dg = false;
    labels[i] = judge(&fl, &an, &dg);
    degenerate[i] = dg;
    if (out.flags) out.flags[i] = fl;
    if (out.angle_deg) out.angle_deg[i] = an;
  };

  // Pass 1: every finite point, one gather per cell. The cell's points in runs, each in two
  // loops: their neighbourhoods and plane scatters (the neighbourhoods kept), the planes solved
  // together (PlaneBatch: vector code), then their judgments. A run ends where its kept
  // neighbourhoods reach kKeptOffsets (dense clouds: thousands of points per cell and per ball).
  constexpr std::size_t kKeptOffsets = std::size_t{1} << 16;
  parallel_cells(grid, nt, [&](std::ptrdiff_t cell, int tid) {
    JudgeScratch& js = scratch[tid];
    gather_box(grid, cell_box(grid, cell, radius), every, js.gather);  // all usable in pass 1
    const std::uint32_t e = grid.cell_begin(cell + 1);
    CellPlanes& cp = js.cell;
    for (std::uint32_t b = grid.cell_begin(cell), k1; b < e; b = k1) {
      cp.start(e - b, 1);
      for (k1 = b; k1 < e && cp.saved.kept() < kKeptOffsets; ++k1) {
        judge.select_point(order[k1], grid.sorted_point(k1), js, k1 - b);
        cp.saved.save(js.sel);
      }
      cp.batch.solve();
      for (std::uint32_t k = b; k < k1; ++k) {
        if (k + kPrefetchAhead < k1) {  // a later point's outputs (cloud_stages.hpp)
          const std::uint32_t f = order[k + kPrefetchAhead];
          __builtin_prefetch(labels + f, 1);
          __builtin_prefetch(degenerate + f, 1);
          if (out.flags) __builtin_prefetch(out.flags + f, 1);
          if (out.angle_deg) __builtin_prefetch(out.angle_deg + f, 1);
          if (!counts.empty()) __builtin_prefetch(counts.data() + f, 1);
        }
        cp.saved.restore(k - b, js.sel);
        judge_point(order[k], [&](std::uint8_t* fl, double* an, bool* dg) {
          return judge.judge_selected(k - b, js, fl, an, dg);
        });
        if (!counts.empty()) {
          counts[order[k]] = static_cast<std::uint16_t>(
              std::min<std::size_t>(js.sel.n, kCountSaturated));  // select excluded the point
        }
      }
    }
  });
  std::vector<std::int64_t> fresh, candidates;
  for (std::ptrdiff_t i = 0; i < N; ++i) {
    if (labels[i] == kAbnormal) fresh.push_back(i);
  }
  int iterations = 1;
  clock.lap("angle pass 1");

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
    const int ntc = std::min(nt, detail::thread_count(p.num_threads, nc, 1024));  // <= scratch
#pragma omp parallel for schedule(dynamic, 64) num_threads(ntc) if (ntc > 1)
    for (std::ptrdiff_t c = 0; c < nc; ++c) {
      const std::uint32_t i = static_cast<std::uint32_t>(candidates[c]);
      JudgeScratch& js = scratch[thread_id()];
      const Eigen::Vector3d pi = points[i];
      gather_box(grid, grid.box_around(pi, pi, radius), usable, js.gather);
      judge_point(i, [&](std::uint8_t* fl, double* an, bool* dg) {
        return judge.judge(i, pi, js, fl, an, dg);
      });
    }
    fresh.clear();
    for (std::int64_t j : candidates) {
      state[j] = 1;
      if (labels[j] == kAbnormal) fresh.push_back(j);
    }
    ++iterations;
  }
  for (std::int64_t i : fresh) state[i] = 0;  // (last pass's removals, for consistency)
  clock.lap("angle passes 2+");

  // Floating groups, then the height passes (cloud_stages.hpp).
  for (std::uint32_t i : floating_points(grid, points, labels, counts.data(), radius,
                                            p.min_group, p.num_threads)) {
    labels[i] = kAbnormal;
    state[i] = 0;
  }
  std::vector<std::uint16_t>().swap(counts);
  clock.lap("floating groups");
  std::vector<double> height_scratch;
  double* height = out.height;
  if (height == nullptr) {
    height_scratch.assign(static_cast<std::size_t>(N), kNaN);
    height = height_scratch.data();
  }
  // have[i]: height[i] is final (written by the height test's first pass and still valid).
  std::vector<std::uint8_t> have;
  // The edge test's candidates: the first height pass's surroundings rms (NaN: no verdict).
  const bool survey = hooks.edge_rms != nullptr;  // (miem.dask) stop before the edge test
  std::vector<double> first_rms(p.edge_k > 0.0 || survey ? static_cast<std::size_t>(N) : 0, kNaN);
  if (p.height_abs > 0.0 || p.height_k > 0.0) {
    HeightTest t;
    t.abs = p.height_abs;
    t.k = p.height_k;
    t.iso_k = p.isolated_k;
    t.radius = hr;
    t.inner = radius;
    t.link = link;
    t.compact_len = p.edge_extent * summary.spacing;
    t.spacing = summary.spacing;
    t.max_iterations = p.max_iterations;
    std::vector<std::uint32_t> unnormal;
    if (p.height_mode == HeightMode::kAll) {
      have.assign(static_cast<std::size_t>(N), 0);
      t.height = height;
      t.have = have.data();
      t.unnormal = &unnormal;
    }
    if (!first_rms.empty()) t.first_rms = first_rms.data();
    iterations += height_passes(grid, points, labels, t, scratch, p.num_threads);
    for (std::uint32_t u : unnormal) {  // the NORMAL set within hr of these points changed
      grid.for_each_in_radius(points[u], hr, [&](std::ptrdiff_t j, double) { have[j] = 0; });
    }
    for (std::ptrdiff_t i = 0; i < N; ++i) {
      if (labels[i] == kAbnormal) state[i] &= static_cast<std::uint8_t>(~1u);
    }
  }
  clock.lap("height test");
  if (survey) {
    std::copy(first_rms.begin(), first_rms.end(), hooks.edge_rms);
    summary.iterations = iterations;
    return summary;
  }
  if (p.edge_k > 0.0) {  // the edge test
    CloudEdgeTest et;
    et.k = p.edge_k;
    et.r_edge = summary.edge_radius;
    et.gap = min_step;
    et.max_iterations = p.max_iterations;
    et.rms_median = hooks.edge_rms_median;
    et.prec = detail::edge_precision<T>();
    std::vector<std::uint32_t> unnormal;
    iterations += cloud_edge_passes(grid, points, labels, &first_rms, et, scratch,
                                    p.num_threads, have.empty() ? nullptr : &unnormal);
    for (std::uint32_t u : unnormal) {  // the NORMAL set within hr of these points changed
      grid.for_each_in_radius(points[u], hr, [&](std::ptrdiff_t j, double) { have[j] = 0; });
    }
    for (std::ptrdiff_t i = 0; i < N; ++i) {
      if (labels[i] == kAbnormal) state[i] &= static_cast<std::uint8_t>(~1u);
    }
    clock.lap("edge test");
  }
  summary.iterations = iterations;

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
  clock.lap("MIEM plane");

  // Heights over the plane of the NORMAL points within radius (those not already final).
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
    const std::uint8_t* hv = have.empty() ? nullptr : have.data();
    parallel_cells(grid, nt, [&](std::ptrdiff_t cell, int tid) {
      const std::uint32_t b = grid.cell_begin(cell), e = grid.cell_begin(cell + 1);
      bool any = hv == nullptr;
      for (std::uint32_t k = b; k < e && !any; ++k) any = !hv[order[k]];
      if (!any) return;
      JudgeScratch& js = scratch[tid];
      gather_box(grid, cell_box(grid, cell, hr), normal_pt, js.gather);
      for (std::uint32_t k = b; k < e; ++k) {
        const std::uint32_t i = order[k];
        if (hv != nullptr && hv[i]) continue;
        height[i] = kNaN;
        LocalPlane lp;
        if (height_plane(js.gather, grid.sorted_point(k), r2, radius * radius, js.sel, &lp) == PlaneStatus::kOk) {
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
    const int nta = std::min(nt, detail::thread_count(p.num_threads, na, 1024));  // <= scratch
#pragma omp parallel for schedule(dynamic, 64) num_threads(nta) if (nta > 1)
    for (std::ptrdiff_t a = 0; a < na; ++a) {
      const std::uint32_t i = abn[a];
      JudgeScratch& js = scratch[thread_id()];
      const Eigen::Vector3d pi = points[i];
      gather_box(grid, grid.box_around(pi, pi, hr), normal_pt, js.gather);
      LocalPlane lp;
      if (height_plane(js.gather, pi, r2, radius * radius, js.sel, &lp) == PlaneStatus::kOk) {
        height[i] = -lp.normal.dot(lp.mean);
      }
    }
  }

  clock.lap("heights");
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
      gather_box(grid, grid.box_around(pk, pk, hr), normal_pt, js0.gather);
      LocalPlane lp;
      if (height_plane(js0.gather, pk, r2, radius * radius, js0.sel, &lp) == PlaneStatus::kOk) d.normal = lp.normal;
    }
    detail::finish_defect(d, point_at, touches_surface);
    summary.defects.push_back(std::move(d));
  }
  detail::order_defects(summary.defects);
  clock.lap("defects");
  return summary;
}

}  // namespace

template <typename T>
PointsDetectSummary detect_points(const PointsView<T>& points, const PointsDetectParams& p,
                                  const PointsOutput& out, const PointsDetectHooks& hooks) {
  validate(p);
  check_view(points);
  if (out.labels == nullptr) throw std::invalid_argument("out.labels: must not be null");
  std::vector<PointsDetectSummary::Stage> front;
  StageClock clock(&front);
  std::vector<double> nn = nearest_other(points, p.num_threads);  // >= 3 finite, not one
  clock.lap("spacing");
  Duplicates dup = find_duplicates(points, nn, p.merge_distance, p.num_threads);
  clock.lap("duplicates");
  auto with_front = [&front](PointsDetectSummary s) {
    s.stage_seconds.insert(s.stage_seconds.begin(), front.begin(), front.end());
    return s;
  };
  if (dup.merged == 0) {
    const double spacing = p.spacing ? *p.spacing : median_spacing(std::move(nn));  // frees nn
    std::vector<double>().swap(nn);  // (also when p.spacing is given): peak memory
    dup = Duplicates{};
    return with_front(detect_distinct(points, p, out, spacing, hooks));
  }
  // Detect on the distinct points (the representatives), then label every duplicate like the
  // point it duplicates (SPEC "Duplicate points").
  const std::size_t m = dup.distinct.size();
  if (m < 3) {
    throw std::invalid_argument(
        "points: fewer than 3 distinct points after merging duplicates within merge_distance");
  }
  std::vector<T> buf(3 * m);
  for (std::size_t k = 0; k < m; ++k) {
    const T* q = points.data + dup.distinct[k] * points.point_stride;
    for (int a = 0; a < 3; ++a) buf[3 * k + a] = q[a * points.coord_stride];
  }
  const PointsView<T> view{buf.data(), static_cast<std::ptrdiff_t>(m), 3, 1};
  std::vector<std::uint8_t> labels(m), flags(m), degenerate(m);
  std::vector<double> angle(m), height(m);
  const PointsOutput sub{labels.data(), out.flags ? flags.data() : nullptr,
                         out.angle_deg ? angle.data() : nullptr, height.data(),
                         out.degenerate ? degenerate.data() : nullptr};
  std::vector<double> edge_rms(hooks.edge_rms ? m : 0);
  PointsDetectHooks sub_hooks = hooks;
  if (hooks.edge_rms) sub_hooks.edge_rms = edge_rms.data();
  PointsDetectSummary summary = detect_distinct(
      view, p, sub, p.spacing ? *p.spacing : median_spacing(nearest_other(view, p.num_threads)),
      sub_hooks);
  std::vector<std::int64_t> slot(static_cast<std::size_t>(points.size), -1);
  for (std::size_t k = 0; k < m; ++k) slot[dup.distinct[k]] = static_cast<std::int64_t>(k);
  for (std::ptrdiff_t i = 0; i < points.size; ++i) {
    const std::int64_t r = dup.rep[i];
    const std::int64_t k = r < 0 ? -1 : slot[r];
    out.labels[i] = k < 0 ? static_cast<std::uint8_t>(kInvalid) : labels[k];
    if (out.flags) out.flags[i] = k < 0 ? 0 : flags[k];
    if (out.angle_deg) out.angle_deg[i] = k < 0 ? kNaN : angle[k];
    if (out.height) out.height[i] = k < 0 ? kNaN : height[k];
    if (out.degenerate) out.degenerate[i] = k < 0 ? 0 : degenerate[k];
    if (hooks.edge_rms) hooks.edge_rms[i] = k < 0 || r != i ? kNaN : edge_rms[k];
  }
  // Defect members: every input row, duplicates included (fields from the distinct points).
  std::vector<std::vector<std::int64_t>> copies(m);
  for (std::ptrdiff_t i = 0; i < points.size; ++i) {
    const std::int64_t r = dup.rep[i];
    if (r >= 0 && r != i) copies[slot[r]].push_back(i);
  }
  for (Defect& d : summary.defects) {
    std::vector<std::int64_t> rows;
    for (std::int64_t j : d.indices) {
      rows.push_back(dup.distinct[j]);
      rows.insert(rows.end(), copies[j].begin(), copies[j].end());
    }
    std::sort(rows.begin(), rows.end());
    d.indices = std::move(rows);
  }
  summary.merged = dup.merged;
  return with_front(std::move(summary));
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

template <typename T>
void edge_rms_survey(const PointsView<T>& points, const PointsDetectParams& params, double* rms) {
  if (rms == nullptr) throw std::invalid_argument("rms: must not be null");
  const std::ptrdiff_t n = std::max<std::ptrdiff_t>(0, points.size);
  std::vector<std::uint8_t> labels(static_cast<std::size_t>(n));
  PointsOutput out;
  out.labels = labels.data();
  PointsDetectHooks hooks;
  hooks.edge_rms = rms;
  detect_points(points, params, out, hooks);
}

template double point_spacing<float>(const PointsView<float>&, int);
template void distinct_spacings<float>(const PointsView<float>&, double, double*, int);
template void distinct_spacings<double>(const PointsView<double>&, double, double*, int);
template double point_spacing<double>(const PointsView<double>&, int);
template void estimate_normals<float>(const PointsView<float>&, double, const NormalsOutput&, int);
template void estimate_normals<double>(const PointsView<double>&, double, const NormalsOutput&,
                                       int);
template PointsDetectSummary detect_points<float>(const PointsView<float>&,
                                                  const PointsDetectParams&, const PointsOutput&,
                                                  const PointsDetectHooks&);
template PointsDetectSummary detect_points<double>(const PointsView<double>&,
                                                   const PointsDetectParams&, const PointsOutput&,
                                                   const PointsDetectHooks&);
template void edge_rms_survey<float>(const PointsView<float>&, const PointsDetectParams&,
                                     double*);
template void edge_rms_survey<double>(const PointsView<double>&, const PointsDetectParams&,
                                      double*);
template PointsDetectResult detect_points<float>(const PointsView<float>&,
                                                 const PointsDetectParams&);
template PointsDetectResult detect_points<double>(const PointsView<double>&,
                                                  const PointsDetectParams&);

}  // namespace miem
