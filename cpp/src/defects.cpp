// Defects (docs/SPEC.md "Defects"): 8-connected groups of ABNORMAL cells, found in row-major
// order, each summarised (centroid, peak and mean height, the window plane's normal at the peak,
// extent, kind; defects.hpp) and ordered by |peak height|.
#include <algorithm>

#include "defects.hpp"
#include "judge.hpp"
#include "parallel.hpp"
#include "stages.hpp"

namespace miem::detail {

template <typename T>
std::vector<Defect> organized_defects(const GridView<T>& g, const std::uint8_t* labels,
                                      const double* height, int window, Workspace& ws,
                                      int num_threads) {
  const std::ptrdiff_t H = g.rows, W = g.cols, N = H * W;
  const int half = window / 2;
  // Bit 2 of ws.usable marks visited ABNORMAL cells (ABNORMAL cells are never usable).
  constexpr std::uint8_t kSeen = 4;
  std::uint8_t* usable = ws.usable.data();
  std::vector<Defect> defects;
  // the ABNORMAL cells in row-major order (a parallel scan), each group from its first one
  collect_indices(thread_count(num_threads, N), N, ws.fresh,
                  [labels](std::ptrdiff_t i) { return labels[i] == kAbnormal; });
  for (const std::int64_t start : ws.fresh) {
    if (usable[start] & kSeen) continue;
    ws.queue.clear();
    ws.queue.push_back(start);
    usable[start] |= kSeen;
    bool touches_surface = false;
    for (std::size_t head = 0; head < ws.queue.size(); ++head) {
      const std::ptrdiff_t i = ws.queue[head], r = i / W, c = i % W;
      for (std::ptrdiff_t dr = -1; dr <= 1; ++dr) {
        for (std::ptrdiff_t dc = -1; dc <= 1; ++dc) {
          const std::ptrdiff_t rr = r + dr, cc = c + dc;
          if ((dr == 0 && dc == 0) || rr < 0 || rr >= H || cc < 0 || cc >= W) continue;
          const std::ptrdiff_t q = rr * W + cc;
          const std::uint8_t l = labels[q];
          if (l == kAbnormal) {
            if (!(usable[q] & kSeen)) {
              usable[q] |= kSeen;
              ws.queue.push_back(q);
            }
          } else if (l != kInvalid) {
            touches_surface = true;
          }
        }
      }
    }
    Defect d;
    d.indices.assign(ws.queue.begin(), ws.queue.end());
    std::sort(d.indices.begin(), d.indices.end());
    auto point_at = [&](std::int64_t i) -> Eigen::Vector3d { return g(i / W, i % W); };
    const std::int64_t peak_idx = summarize_defect(d, height, point_at);
    if (peak_idx >= 0) {
      Plane pl;
      if (window_plane(g, labels, peak_idx / W, peak_idx % W, half, &pl) == PlaneStatus::kOk) {
        d.normal = pl.normal;
      }
    }
    finish_defect(d, point_at, touches_surface);
    defects.push_back(std::move(d));
  }
  order_defects(defects);
  return defects;
}

template std::vector<Defect> organized_defects<float>(const GridView<float>&, const std::uint8_t*,
                                                      const double*, int, Workspace&, int);
template std::vector<Defect> organized_defects<double>(const GridView<double>&,
                                                       const std::uint8_t*, const double*, int,
                                                       Workspace&, int);

}  // namespace miem::detail
