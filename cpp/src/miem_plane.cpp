// The MIEM plane (docs/SPEC.md "MIEM plane"): the eigenvalue fit of the finite points that are
// not ABNORMAL. Per-row moments, merged in a fixed tree order, so the same for any thread count.
#include "parallel.hpp"
#include "plane_math.hpp"
#include "stages.hpp"

namespace miem::detail {

template <typename T>
std::optional<Plane> miem_plane(const GridView<T>& g, const std::uint8_t* labels,
                                int num_threads, Workspace& ws) {
  const std::ptrdiff_t H = g.rows, W = g.cols;
  const int nt = thread_count(num_threads, H * W);
  // Blocks of whole rows with at least 4096 cells each (one row per block on wide grids): the
  // moments buffer stays small on tall thin grids (10^7 x 1) and the blocks depend on the shape
  // only, so the result is the same for any thread count.
  const std::ptrdiff_t per = std::max<std::ptrdiff_t>(1, (4096 + W - 1) / W);
  const std::ptrdiff_t B = (H + per - 1) / per;
  std::vector<Moments>& rows = ws.plane_rows;
  rows.resize(static_cast<std::size_t>(B));
#pragma omp parallel for schedule(static) num_threads(nt) if (nt > 1)
  for (std::ptrdiff_t b = 0; b < B; ++b) {
    const std::ptrdiff_t r0 = b * per, r1 = std::min(H, r0 + per);
    // nearly every point is kept: the masked form, without a branch per point
    const Moments m = two_pass_moments_masked([&](auto&& f) {
      const std::ptrdiff_t cs = g.col_stride, yo = g.coord_stride, zo = 2 * g.coord_stride;
      for (std::ptrdiff_t r = r0; r < r1; ++r) {
        const std::uint8_t* lab = labels + r * W;
        const T* row = g.data + r * g.row_stride;
        for (std::ptrdiff_t c = 0; c < W; ++c) {
          const T* q = row + c * cs;
          f(static_cast<double>(q[0]), static_cast<double>(q[yo]), static_cast<double>(q[zo]),
            (lab[c] == kNormal) | (lab[c] == kEdge));
        }
      }
    });
    rows[static_cast<std::size_t>(b)] = m;
  }
  for (std::ptrdiff_t width = 1; width < B; width *= 2)
    for (std::ptrdiff_t b = 0; b + width < B; b += 2 * width) rows[b].merge(rows[b + width]);
  Plane plane;
  if (eigen_plane_from_moments(rows[0], &plane) == PlaneStatus::kOk) return plane;
  return std::nullopt;
}

template std::optional<Plane> miem_plane<float>(const GridView<float>&, const std::uint8_t*, int,
                                                Workspace&);
template std::optional<Plane> miem_plane<double>(const GridView<double>&, const std::uint8_t*,
                                                 int, Workspace&);

}  // namespace miem::detail
