// The height test (docs/SPEC.md "height_tolerance", beyond the paper): after the angle passes,
// NORMAL cells, and EDGE cells of compact EDGE groups, too far from the plane of the NORMAL cells
// in their window become ABNORMAL; the test abstains where a feature line (a longer EDGE group)
// lies in the window. Passes repeat until none adds a cell (at most max_iterations).
//
// Two facts keep the later passes cheap and leave the result as the spec defines it:
// - The EDGE groups are fixed: a pass only turns NORMAL and compact-EDGE cells ABNORMAL, so a
//   compact group only shrinks (its parts stay compact) and a long group never changes. They are
//   grouped once.
// - A cell's verdict depends only on the labels in its window, so a pass re-fits only the cells
//   within window / 2 of a cell the pass before removed; the others would repeat their verdict.
#include <algorithm>
#include <cmath>
#include <cstring>

#include "edge_groups.hpp"
#include "edge_test.hpp"
#include "parallel.hpp"
#include "stages.hpp"
#include "vector_clones.hpp"

namespace miem::detail {

namespace {

// Marks with kHCompact the EDGE cells of EDGE groups (edge_groups.hpp: linked across at most
// `gap` INVALID or ABNORMAL cells of the labels after the angle passes) whose bounding box's longer side is at most `extent` cells.
void mark_compact_edges(const std::uint8_t* labels, std::ptrdiff_t H, std::ptrdiff_t W,
                        int extent, int gap, std::uint8_t* hm, std::vector<std::int64_t>& queue) {
  struct Cells {
    const std::uint8_t* labels;
    std::uint8_t* hm;
    std::ptrdiff_t H, W;
    EdgeLink link(std::int64_t r, std::ptrdiff_t c) const {
      if (r < 0 || r >= H || c < 0 || c >= W) return EdgeLink::kStop;
      const std::uint8_t l = labels[r * W + c];
      // a dropout, or a defect the angle passes found on the feature line, does not cut it
      if (l == kEdge) return EdgeLink::kEdge;
      return l == kInvalid || l == kAbnormal ? EdgeLink::kGap : EdgeLink::kStop;
    }
    bool claim(std::int64_t r, std::ptrdiff_t c) {
      std::uint8_t& b = hm[r * W + c];
      if (b & kHSeen) return false;
      b |= kHSeen;
      return true;
    }
  } cells{labels, hm, H, W};
  const std::ptrdiff_t N = H * W;
  for (std::ptrdiff_t start = 0; start < N; ++start) {
    // the next EDGE cell (memchr: vectorised search)
    const void* next = std::memchr(labels + start, kEdge, static_cast<std::size_t>(N - start));
    if (next == nullptr) break;
    start = static_cast<const std::uint8_t*>(next) - labels;
    if (hm[start] & kHSeen) continue;
    if (walk_edge_group(cells, start / W, start % W, W, gap, queue).extent() <= extent) {
      for (std::int64_t i : queue) hm[i] |= kHCompact;
    }
  }
}

// The height passes' verdict (height_verdict) on a whole row segment of wanted cells wrow[j]
// from row_solve's fits (RowFits, not compact): kHFresh, kHMark where too far, kHQuiet where
// the plane is quiet (quiet_plane with `quiet_floor`: the first pass; -1 after it) and the
// height when `height` is not null. Straight-line code (vectorised), blocks of kB cells: the
// verdicts (verdict_codes), then the bytes.
MIEM_CLONES void height_row(std::ptrdiff_t n, const std::uint8_t* __restrict wrow,
                            const double* S, const double* F,
                            const std::uint8_t* __restrict okf, std::ptrdiff_t cap,
                            double height_abs, double height_k, double z_min,
                            double quiet_floor, double* height, std::uint8_t* __restrict hm) {
  constexpr std::ptrdiff_t kB = 256;
  double code[kB];
  for (std::ptrdiff_t b0 = 0; b0 < n; b0 += kB) {
    const std::ptrdiff_t nb = std::min(kB, n - b0);
    verdict_codes(nb, S + b0, F + b0, cap, height_abs, height_k, z_min, quiet_floor, code);
    for (std::ptrdiff_t t = 0; t < nb; ++t) {
      const std::ptrdiff_t j = b0 + t;
      const int c = okf[j] != 0 ? static_cast<int>(code[t]) : 0;
      const std::uint8_t b = static_cast<std::uint8_t>((hm[j] & ~kHQuiet) | kHFresh |
                                                       ((c & 1) ? kHMark : 0) |
                                                       ((c & 2) ? kHQuiet : 0));
      hm[j] = wrow[j] != 0 ? b : hm[j];
    }
  }
  if (height != nullptr) store_heights(n, wrow, okf, F, height);
}

}  // namespace

template <typename T>
int height_test(const GridView<T>& g, const DetectParams& p, std::uint8_t* labels,
                double* height, Workspace& ws) {
  const std::ptrdiff_t H = g.rows, W = g.cols, N = H * W;
  const std::ptrdiff_t half = p.window / 2;
  ws.hmask.resize(static_cast<std::size_t>(N));
  ws.cls.resize(static_cast<std::size_t>(N));
  std::uint8_t* hm = ws.hmask.data();
  std::uint8_t* cls = ws.cls.data();
  const int nt = thread_count(p.num_threads, N);
  parallel_ranges(nt, N, 64, [hm](int, std::ptrdiff_t i0, std::ptrdiff_t i1) {
    std::fill(hm + i0, hm + i1, std::uint8_t{0});
  });
  mark_compact_edges(labels, H, W, p.edge_extent, p.max_gap, hm, ws.queue);
  parallel_ranges(nt, N, 64, [labels, hm, cls](int, std::ptrdiff_t i0, std::ptrdiff_t i1) {
    // branch-free over local restrict pointers: vectorised (kHCompact, bit 0, read as a
    // number: GCC 12 does not vectorise a test of bit 0 with != 0)
    const std::uint8_t* __restrict lb = labels;
    std::uint8_t* __restrict h = hm;
    std::uint8_t* __restrict cl = cls;
    for (std::ptrdiff_t i = i0; i < i1; ++i) {
      const std::uint8_t l = lb[i], b = h[i];
      const int normal = l == kNormal, compact = b & kHCompact;  // 1 or 0 each
      cl[i] = static_cast<std::uint8_t>(normal * kInPlane + ((l == kEdge) & (compact ^ 1)) * kLine);
      h[i] = static_cast<std::uint8_t>(b | (normal | compact) * kHWant);  // pass 1 fits them
    }
  });
  int passes = 0;
  std::vector<std::vector<std::int64_t>> parts;  // per thread: new ABNORMAL cells of a pass
  // the edge test's quiet cells (SPEC "Edge test" step 1) by each cell's last plane (a pass
  // re-fits every cell whose window the pass before changed; after the last pass, a cell whose
  // window lost a cell is marked kHStale)
  const double quiet_floor = quiet_plane_floor(p);
  for (int hp = 0; hp < p.max_iterations; ++hp) {
    auto visit = [&](std::ptrdiff_t i, const WindowFit& f) {
      if (height) height[i] = f.ok ? f.height : kNaN;
      std::uint8_t b = static_cast<std::uint8_t>((hm[i] & ~kHQuiet) | kHFresh);
      if (height_far(f, p)) b |= kHMark;
      if (quiet_plane(f.ok, f.height, f.n, f.l0, f.l1, f.l2, quiet_floor)) b |= kHQuiet;
      hm[i] = b;
    };
    window_fits_rows(
        g, cls, p.window, p.num_threads, ws.fits,
        [hm](std::ptrdiff_t i) { return (hm[i] & kHWant) != 0; }, visit,
        [&](std::ptrdiff_t i0, std::ptrdiff_t ncols, const std::uint8_t* wrow, const RowFits& rf) {
          if (!rf.compact) {  // the span of the wanted cells, [j0, j1)
            const std::ptrdiff_t j0 = rf.j0;
            height_row(rf.j1 - j0, wrow + j0, rf.S + j0, rf.F + j0, rf.okf + j0, rf.cap,
                       p.height_abs, p.height_k, z_floor(p.z_resolution), quiet_floor,
                       height ? height + i0 + j0 : nullptr,
                       hm + i0 + j0);
            return;
          }
          std::ptrdiff_t e = 0;
          for (std::ptrdiff_t j = 0; j < ncols; ++j)
            if (wrow[j]) visit(i0 + j, rf.fit(e++));
        });
    ++passes;
    // Apply the pass: clear kHWant, turn the marked cells ABNORMAL. Blocks of 64 cells in
    // straight-line (vectorised) code; the few blocks with a marked cell list it in ws.fresh.
    // One range of whole blocks per thread, its new ABNORMAL cells joined in order.
    constexpr std::ptrdiff_t kSpan = 64;
    parts.resize(static_cast<std::size_t>(std::max(1, nt)));
    parallel_ranges(nt, N, kSpan, [&](int t, std::ptrdiff_t r0, std::ptrdiff_t r1) {
      std::vector<std::int64_t>& part = parts[static_cast<std::size_t>(t)];
      part.clear();
      for (std::ptrdiff_t i0 = r0; i0 < r1; i0 += kSpan) {
        const std::ptrdiff_t i1 = std::min(r1, i0 + kSpan);
        // a local restrict pointer: through the captured hm every byte store would reload it
        std::uint8_t* __restrict h = hm;
        std::uint8_t marked = 0;
        for (std::ptrdiff_t i = i0; i < i1; ++i) {
          const std::uint8_t b = h[i];
          marked |= b;
          h[i] = static_cast<std::uint8_t>(b & ~kHWant);
        }
        if ((marked & kHMark) == 0) continue;
        for (std::ptrdiff_t i = i0; i < i1; ++i) {
          if (!(hm[i] & kHMark)) continue;
          labels[i] = kAbnormal;
          cls[i] = 0;
          hm[i] = 0;
          part.push_back(i);
        }
      }
    });
    ws.fresh.clear();
    for (const auto& part : parts) ws.fresh.insert(ws.fresh.end(), part.begin(), part.end());
    for (auto& part : parts) part.clear();
    if (ws.fresh.empty()) break;
    // The windows that changed: re-fit their candidates at the next pass; heights there are
    // stale until then, and after the last pass their planes too (kHStale: no quiet cell there,
    // edge_quiet.hpp).
    const std::uint8_t stale = hp + 1 == p.max_iterations ? kHStale : 0;
    for (std::int64_t i : ws.fresh) {
      const std::ptrdiff_t r = i / W, c = i % W;
      const std::ptrdiff_t ra = std::max<std::ptrdiff_t>(0, r - half);
      const std::ptrdiff_t rb = std::min(H - 1, r + half);
      const std::ptrdiff_t ca = std::max<std::ptrdiff_t>(0, c - half);
      const std::ptrdiff_t cb = std::min(W - 1, c + half);
      for (std::ptrdiff_t rr = ra; rr <= rb; ++rr) {
        std::uint8_t* __restrict h = hm + rr * W;
        const std::uint8_t* __restrict l = labels + rr * W;
        for (std::ptrdiff_t cc = ca; cc <= cb; ++cc) {  // branch-free: vectorised
          const std::uint8_t b = static_cast<std::uint8_t>((h[cc] & ~kHFresh) | stale);
          const bool want = (l[cc] == kNormal) | ((b & kHCompact) != 0);
          h[cc] = static_cast<std::uint8_t>(b | (want ? kHWant : 0));
        }
      }
    }
  }
  // Cells still marked kHWant (max_iterations reached) have stale heights: kHFresh is clear.
  return passes;
}

template int height_test<float>(const GridView<float>&, const DetectParams&, std::uint8_t*,
                                double*, Workspace&);
template int height_test<double>(const GridView<double>&, const DetectParams&, std::uint8_t*,
                                 double*, Workspace&);

}  // namespace miem::detail
