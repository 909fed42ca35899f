// Heights (docs/SPEC.md "Height"): the signed distance of each point from the eigen plane of the
// NORMAL points in the window x window square around it (clipped at the grid's border), NaN
// where that plane does not exist. HeightMode::kAll: every finite point, by the window sweep
// (window_fits.hpp), reusing what the height test already fitted; kAbnormal: ABNORMAL points
// only, each fitted directly.
#include <algorithm>

#include "byte_scan.hpp"
#include "judge.hpp"
#include "parallel.hpp"
#include "stages.hpp"

namespace miem::detail {

template <typename T>
void heights(const GridView<T>& g, const DetectParams& p, const std::uint8_t* labels,
             double* height, bool reuse, Workspace& ws) {
  const std::ptrdiff_t H = g.rows, W = g.cols, N = H * W;
  const int half = p.window / 2;
  const int nt = thread_count(p.num_threads, N);
  if (p.height_mode == HeightMode::kAbnormal) {
#pragma omp parallel for schedule(static) num_threads(nt) if (nt > 1)
    for (std::ptrdiff_t r = 0; r < H; ++r) {
      for (std::ptrdiff_t c = 0; c < W; ++c) {
        const std::ptrdiff_t i = r * W + c;
        height[i] = kNaN;
        if (labels[i] != kAbnormal) continue;
        Plane pl;
        if (window_plane(g, labels, r, c, half, &pl) == PlaneStatus::kOk) {
          height[i] = pl.signed_distance(g(r, c));
        }
      }
    }
    return;
  }
  ws.cls.resize(static_cast<std::size_t>(N));
  std::uint8_t* cls = ws.cls.data();
  std::uint8_t* hm = reuse ? ws.hmask.data() : nullptr;
  if (hm != nullptr) {
    // ws.cls still holds the window classes the height test's fits used. A later stage (the edge
    // test) may have taken NORMAL cells out of the planes: the heights of every window holding
    // one are stale, the others stay exact.
    collect_indices(nt, N, ws.fresh, [cls, labels](std::ptrdiff_t i) {
      // kInPlane is bit 0: moved to bit 7 and tested there, so that collect_indices vectorises
      // this (GCC 12 does not vectorise a test of bit 0)
      static_assert(kInPlane == 1, "kInPlane is bit 0");
      return (static_cast<std::uint8_t>(cls[i] << 7) != 0) & (labels[i] != kNormal);
    });
    for (const std::int64_t i : ws.fresh) {
      const std::ptrdiff_t r = i / W, c = i % W;
      const std::ptrdiff_t c0 = std::max<std::ptrdiff_t>(0, c - half);
      const std::ptrdiff_t c1 = std::min<std::ptrdiff_t>(W - 1, c + half);
      for (std::ptrdiff_t rr = std::max<std::ptrdiff_t>(0, r - half);
           rr <= std::min<std::ptrdiff_t>(H - 1, r + half); ++rr)
        for (std::ptrdiff_t cc = c0; cc <= c1; ++cc) hm[rr * W + cc] &= ~kHFresh;
    }
  }
  // the window classes (feature lines do not matter here), branch-free: vectorised; NaN at
  // the INVALID cells, found by next_byte (a vectorised search: they are few)
  parallel_ranges(nt, N, 64, [cls, labels, height](int, std::ptrdiff_t i0, std::ptrdiff_t i1) {
    std::uint8_t* __restrict cl = cls;
    const std::uint8_t* __restrict lb = labels;
    for (std::ptrdiff_t i = i0; i < i1; ++i) cl[i] = lb[i] == kNormal ? kInPlane : 0;
    for (std::ptrdiff_t i = next_byte(lb, i0, i1, kInvalid); i < i1;
         i = next_byte(lb, i + 1, i1, kInvalid)) {
      height[i] = kNaN;
    }
  });
  auto visit = [height](std::ptrdiff_t i, const WindowFit& f) {
    height[i] = f.ok ? f.height : kNaN;
  };
  // Branch-free predicates (one per case): window_fits scans every tile's want bytes in vector
  // code, and most tiles have nothing to re-fit when the height test's heights are reused.
  if (hm != nullptr) {
    window_fits(
        g, cls, p.window, p.num_threads, ws.fits,
        [labels, hm](std::ptrdiff_t i) {
          return (labels[i] != kInvalid) & ((hm[i] & kHFresh) == 0);
        },
        visit);
  } else {
    window_fits(g, cls, p.window, p.num_threads, ws.fits,
                [labels](std::ptrdiff_t i) { return labels[i] != kInvalid; }, visit);
  }
}

template void heights<float>(const GridView<float>&, const DetectParams&, const std::uint8_t*,
                             double*, bool, Workspace&);
template void heights<double>(const GridView<double>&, const DetectParams&, const std::uint8_t*,
                              double*, bool, Workspace&);

}  // namespace miem::detail
