// Floating groups (docs/SPEC.md, "Unorganized clouds: floating groups and height test"): a group
// of usable points farther than `radius` from the rest of the cloud and smaller than `min_group`
// is a floating defect (a tall cluster or ridge whose members only see each other).
#include <algorithm>

#include "cloud_stages.hpp"

namespace miem::cloud {

namespace {

inline bool usable_label(std::uint8_t l) { return l == kNormal || l == kEdge; }

}  // namespace

template <typename T>
std::vector<std::uint32_t> floating_points(const NeighborGrid<T>& grid, const PointsView<T>& points,
                                           const std::uint8_t* labels, std::uint16_t* counts,
                                           double radius, int min_group, int num_threads) {
  std::vector<std::uint32_t> out;
  if (min_group <= 0) return out;
  const std::ptrdiff_t N = points.size;
  // Usable neighbours = finite neighbours - ABNORMAL neighbours (the finite points not usable);
  // ABNORMAL points are few, so subtract theirs from the counts of the points around them.
  for (std::ptrdiff_t a = 0; a < N; ++a) {
    if (labels[a] != kAbnormal) continue;
    grid.for_each_in_radius(points[a], radius, [&](std::ptrdiff_t j, double) {
      if (j != a && counts[j] != kCountSaturated) --counts[j];
    });
  }
  // A member of a group of fewer than min_group points has fewer than min_group - 1 usable
  // neighbours: only such points can start a floating group.
  std::vector<std::uint8_t> sparse(static_cast<std::size_t>(N), 0);
  const int nt = detail::thread_count(num_threads, N);
#pragma omp parallel for schedule(static) num_threads(nt) if (nt > 1)
  for (std::ptrdiff_t i = 0; i < N; ++i) {
    if (!usable_label(labels[i])) continue;
    std::ptrdiff_t count = counts[i];
    if (count == kCountSaturated) {  // recount
      count = 0;
      grid.for_each_in_radius(points[i], radius, [&](std::ptrdiff_t j, double) {
        count += (j != i) && usable_label(labels[j]);
      });
    }
    sparse[i] = count < min_group - 1;
  }
  // 0: undecided, 1: floating, 2: in a group of at least min_group points.
  std::vector<std::uint8_t> decided(static_cast<std::size_t>(N), 0);
  std::vector<std::int64_t> queue;
  const std::size_t limit = static_cast<std::size_t>(min_group);
  for (std::ptrdiff_t start = 0; start < N; ++start) {
    if (!sparse[start] || decided[start]) continue;
    queue.assign(1, start);
    decided[start] = 3;  // on the queue
    bool large = false;  // reached a point of a group already known to be large
    for (std::size_t head = 0; head < queue.size() && queue.size() < limit && !large; ++head) {
      grid.for_each_in_radius(points[queue[head]], radius, [&](std::ptrdiff_t j, double) {
        if (!usable_label(labels[j])) return;
        if (decided[j] == 2) {
          large = true;
        } else if (decided[j] == 0) {
          decided[j] = 3;
          queue.push_back(j);
        }
      });
    }
    // Either the whole group was explored (fewer than min_group: floating), or it has at least
    // min_group points (the queue alone, or through a point already known to be in a large one).
    const std::uint8_t verdict = (queue.size() < limit && !large) ? 1 : 2;
    for (std::int64_t j : queue) decided[j] = verdict;
    if (verdict == 1) {
      for (std::int64_t j : queue) out.push_back(static_cast<std::uint32_t>(j));
    }
  }
  std::sort(out.begin(), out.end());
  return out;
}

template std::vector<std::uint32_t> floating_points<float>(const NeighborGrid<float>&,
                                                           const PointsView<float>&,
                                                           const std::uint8_t*, std::uint16_t*,
                                                           double, int, int);
template std::vector<std::uint32_t> floating_points<double>(const NeighborGrid<double>&,
                                                            const PointsView<double>&,
                                                            const std::uint8_t*, std::uint16_t*,
                                                           double, int, int);

}  // namespace miem::cloud
