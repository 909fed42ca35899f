// Deviation from a reference surface: nearest reference point by ring search in the neighbour
// grid, signed distance along its normal; labels by tolerance and defects as linked groups.
#include "miem/deviation.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

#include "defects.hpp"
#include "parallel.hpp"

namespace miem {

namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kInf = std::numeric_limits<double>::infinity();

}  // namespace

ReferenceSurface::ReferenceSurface(const PointsView<double>& points, const double* normals,
                                   double cell_size, int num_threads) {
  if (!std::isfinite(cell_size) || !(cell_size > 0.0)) {
    throw std::invalid_argument("cell_size: must be finite and > 0, got " +
                                std::to_string(cell_size));
  }
  if (points.size < 0 || (points.size > 0 && (points.data == nullptr || normals == nullptr))) {
    throw std::invalid_argument("reference: null data");
  }
  for (std::ptrdiff_t i = 0; i < points.size; ++i) {
    const Eigen::Vector3d p = points[i];
    const double* n = normals + 3 * i;
    if (!p.allFinite() || !std::isfinite(n[0]) || !std::isfinite(n[1]) || !std::isfinite(n[2])) {
      continue;
    }
    points_.insert(points_.end(), {p.x(), p.y(), p.z()});
    normals_.insert(normals_.end(), {n[0], n[1], n[2]});
    rows_.push_back(static_cast<std::int64_t>(i));
  }
  if (rows_.empty()) {
    throw std::invalid_argument("reference: no point has a finite position and normal");
  }
  for (int a = 0; a < 3; ++a) {
    origin_[a] = kInf;
    for (std::size_t k = 0; k < rows_.size(); ++k) origin_[a] = std::min(origin_[a], points_[3 * k + a]);
  }
  const PointsView<double> view{points_.data(), size(), 3, 1};
  grid_ = std::make_unique<NeighborGrid<double>>(view, cell_size, num_threads);
}

template <typename T>
void ReferenceSurface::deviation(const PointsView<T>& scan, double max_distance,
                                 double max_lateral, const DeviationOutput& out,
                                 int num_threads) const {
  if (!std::isfinite(max_distance) || !(max_distance > 0.0)) {
    throw std::invalid_argument("max_distance: must be finite and > 0, got " +
                                std::to_string(max_distance));
  }
  if (!(max_lateral >= 0.0)) {
    throw std::invalid_argument("max_lateral: must be >= 0 (or +inf), got " +
                                std::to_string(max_lateral));
  }
  if (scan.size < 0 || (scan.size > 0 && scan.data == nullptr)) {
    throw std::invalid_argument("scan: null data");
  }
  const double lat2_max = max_lateral * max_lateral;
  const NeighborGrid<double>& grid = *grid_;
  const double cell = grid.cell_size();
  const double max2 = max_distance * max_distance;
  const std::uint32_t* order = grid.order();
  const std::ptrdiff_t n = scan.size;
  const int nt = detail::thread_count(num_threads, n, 2048);
  const double slack = 1e-9 * cell;
  const CellBox full = grid.box_around(Eigen::Vector3d::Zero(), Eigen::Vector3d::Zero(), kInf);
#pragma omp parallel for schedule(dynamic, 256) num_threads(nt) if (nt > 1)
  for (std::ptrdiff_t i = 0; i < n; ++i) {
    const Eigen::Vector3d q = scan[i];
    double best2 = kInf;
    std::int64_t best = -1;  // index into the usable rows
    if (q.allFinite()) {
      // Boxes of growing radius r: every point within r of q lies in box_around(q, q, r). Once
      // a point at distance d is found, the box of radius d holds every point that could beat it.
      CellBox seen;  // cells visited so far (empty at first)
      double r = std::min(cell, max_distance);
      for (;;) {
        const CellBox b = grid.box_around(q, q, r);
        grid.for_each_cell_xyz(b, [&](std::ptrdiff_t c, std::int64_t ix, std::int64_t iy,
                                      std::int64_t iz) {
          if (ix >= seen.lo[0] && ix <= seen.hi[0] && iy >= seen.lo[1] && iy <= seen.hi[1] &&
              iz >= seen.lo[2] && iz <= seen.hi[2]) {
            return;
          }
          // Skip cells that cannot hold a point nearer than the best so far (lower bound from
          // the cell's box, widened by rounding slack).
          const std::int64_t ixyz[3] = {ix, iy, iz};
          double lb2 = 0.0;
          for (int a = 0; a < 3; ++a) {
            const double lo = origin_[a] + static_cast<double>(ixyz[a]) * cell;
            const double g = std::max(lo - q[a], q[a] - (lo + cell)) - slack;
            if (g > 0.0) lb2 += g * g;
          }
          if (lb2 > best2 || lb2 > max2) return;
          const std::uint32_t e = grid.cell_begin(c + 1);
          for (std::uint32_t k = grid.cell_begin(c); k < e; ++k) {
            const Eigen::Vector3d p = grid.sorted_point(k);
            const double dx = q.x() - p.x(), dy = q.y() - p.y(), dz = q.z() - p.z();
            const double d2 = dx * dx + dy * dy + dz * dz;
            const std::int64_t j = order[k];
            if (d2 <= max2 && (d2 < best2 || (d2 == best2 && j < best))) {
              best2 = d2;
              best = j;
            }
          }
        });
        seen = b;
        if (b.lo[0] <= full.lo[0] && b.lo[1] <= full.lo[1] && b.lo[2] <= full.lo[2] &&
            b.hi[0] >= full.hi[0] && b.hi[1] >= full.hi[1] && b.hi[2] >= full.hi[2]) {
          break;  // every cell has been visited
        }
        double next;
        if (best >= 0) {
          next = std::sqrt(best2);
        } else if (r >= max_distance) {
          break;  // nothing within max_distance
        } else {
          next = std::min(2.0 * r, max_distance);
        }
        const CellBox nb = grid.box_around(q, q, next);
        if (nb.lo[0] >= b.lo[0] && nb.lo[1] >= b.lo[1] && nb.lo[2] >= b.lo[2] &&
            nb.hi[0] <= b.hi[0] && nb.hi[1] <= b.hi[1] && nb.hi[2] <= b.hi[2]) {
          if (best >= 0 || r >= max_distance) break;
          r = next;  // no new cells yet: grow further
          continue;
        }
        r = next;
      }
    }
    if (best >= 0) {
      const double* p = points_.data() + 3 * best;
      const double* nn = normals_.data() + 3 * best;
      const double dx = q.x() - p[0], dy = q.y() - p[1], dz = q.z() - p[2];
      const double dev = (dx * nn[0] + dy * nn[1]) + dz * nn[2];
      const double tx = dx - dev * nn[0], ty = dy - dev * nn[1], tz = dz - dev * nn[2];
      const bool over = (tx * tx + ty * ty) + tz * tz <= lat2_max;
      if (out.deviation) out.deviation[i] = over ? dev : kNaN;
      if (out.distance) out.distance[i] = std::sqrt(best2);
      if (out.nearest) out.nearest[i] = rows_[best];
      if (out.covered) out.covered[i] = over ? 1 : 0;
    } else {
      if (out.deviation) out.deviation[i] = kNaN;
      if (out.distance) out.distance[i] = kNaN;
      if (out.nearest) out.nearest[i] = -1;
      if (out.covered) out.covered[i] = 0;
    }
  }
}

void validate(const DeviationLabelParams& p) {
  if (!std::isfinite(p.tolerance) || !(p.tolerance > 0.0)) {
    throw std::invalid_argument("tolerance: must be finite and > 0");
  }
  if (!std::isfinite(p.dont_care) || p.dont_care < 0.0) {
    throw std::invalid_argument("dont_care: must be finite and >= 0");
  }
  if (!std::isfinite(p.link) || !(p.link > 0.0)) {
    throw std::invalid_argument("link: must be finite and > 0");
  }
}

template <typename T>
std::vector<Defect> label_deviation(const PointsView<T>& points, const double* deviation,
                                    const std::uint8_t* covered, const double* normals,
                                    const DeviationLabelParams& params, std::uint8_t* labels) {
  validate(params);
  const std::ptrdiff_t n = points.size;
  if (n < 0 || (n > 0 && (points.data == nullptr || deviation == nullptr || covered == nullptr ||
                          labels == nullptr))) {
    throw std::invalid_argument("label_deviation: null data");
  }
  constexpr auto kWithin = static_cast<std::uint8_t>(DeviationLabel::kWithin);
  constexpr auto kNotCovered = static_cast<std::uint8_t>(DeviationLabel::kNotCovered);
  // Out-of-tolerance points (+1 excess, -1 missing), compacted for a small grid.
  std::vector<std::int64_t> cand;
  std::vector<double> cpts;
  for (std::ptrdiff_t i = 0; i < n; ++i) {
    const Eigen::Vector3d p = points[i];
    const double dv = deviation[i];
    if (!covered[i] || !p.allFinite() || !std::isfinite(dv)) {
      labels[i] = kNotCovered;
      continue;
    }
    labels[i] = kWithin;
    if (std::abs(dv) > params.tolerance) {
      cand.push_back(i);
      cpts.insert(cpts.end(), {p.x(), p.y(), p.z()});
    }
  }
  std::vector<Defect> defects;
  if (cand.empty()) return defects;
  const std::ptrdiff_t nc = static_cast<std::ptrdiff_t>(cand.size());
  const PointsView<double> cview{cpts.data(), nc, 3, 1};
  const NeighborGrid<double> grid(cview, params.link, 1);
  std::vector<std::uint8_t> seen(static_cast<std::size_t>(nc), 0);
  std::vector<std::int64_t> queue;
  const double keep = params.tolerance + params.dont_care;
  auto point_at = [&](std::int64_t i) -> Eigen::Vector3d { return points[i]; };
  for (std::ptrdiff_t s = 0; s < nc; ++s) {
    if (seen[s]) continue;
    const bool excess = deviation[cand[s]] > 0.0;
    queue.assign(1, s);
    seen[s] = 1;
    for (std::size_t head = 0; head < queue.size(); ++head) {
      grid.for_each_in_radius(cview[queue[head]], params.link, [&](std::ptrdiff_t j, double) {
        if (!seen[j] && (deviation[cand[j]] > 0.0) == excess) {
          seen[j] = 1;
          queue.push_back(j);
        }
      });
    }
    Defect d;
    d.indices.reserve(queue.size());
    for (std::int64_t k : queue) d.indices.push_back(cand[k]);
    std::sort(d.indices.begin(), d.indices.end());
    const std::int64_t peak = detail::summarize_defect(d, deviation, point_at);
    if (!(std::abs(d.peak_height) > keep)) continue;  // inside the don't-care band
    const auto label = static_cast<std::uint8_t>(excess ? DeviationLabel::kExcess
                                                        : DeviationLabel::kMissing);
    for (std::int64_t i : d.indices) labels[i] = label;
    if (normals != nullptr && peak >= 0) {
      d.normal = Eigen::Vector3d(normals[3 * peak], normals[3 * peak + 1], normals[3 * peak + 2]);
    }
    detail::finish_defect(d, point_at, true);
    defects.push_back(std::move(d));
  }
  detail::order_defects(defects);
  return defects;
}

template void ReferenceSurface::deviation<float>(const PointsView<float>&, double, double,
                                                 const DeviationOutput&, int) const;
template void ReferenceSurface::deviation<double>(const PointsView<double>&, double, double,
                                                  const DeviationOutput&, int) const;
template std::vector<Defect> label_deviation<float>(const PointsView<float>&, const double*,
                                                    const std::uint8_t*, const double*,
                                                    const DeviationLabelParams&, std::uint8_t*);
template std::vector<Defect> label_deviation<double>(const PointsView<double>&, const double*,
                                                     const std::uint8_t*, const double*,
                                                     const DeviationLabelParams&,
                                                     std::uint8_t*);

}  // namespace miem
