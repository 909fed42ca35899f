// The stream's edge test (docs/SPEC.md "Edge test", "Streaming"): batch detection's own edge
// passes (edge_test.hpp) run on blocks of the ring, one band of rows at a time, with
// enough rows around the band (two tile bands, 128 rows) that its cells come out bit for bit
// as on the whole grid:
//  - below, max_iterations * r rows (r = edge_window / 2): after p passes a cell depends only
//    on the cells within p r, so the false border at the block's end reaches none of the band;
//  - above, whole tile bands back to at least 64 + (max_iterations - 1) r rows: the edge test's
//    sums are per 64 x 128 tile from the grid's first row (integral images over the tile and r
//    rows before it), so the block must start on a tile boundary; its first band then has other
//    sums (no r rows before it) and may differ anywhere, and that reaches (max_iterations - 1) r
//    rows further in the later passes.
// Each band is run once the height-test labels are final through its last row below; its
// removals then go into the labels, and the heights whose window lost a NORMAL cell are
// fitted again at the end (as batch heights() does).
#include <algorithm>
#include <cstring>

#include "edge_test.hpp"
#include "miem/stream.hpp"

namespace miem {

namespace {
constexpr std::uint8_t kEdgeRemoved = 254;  // hs_: removed by the edge test
}  // namespace

template <typename T>
void ProfileStream<T>::init_edges() {
  if (!edge_) return;
  const std::size_t W = static_cast<std::size_t>(width_);
  eold_.assign(static_cast<std::size_t>(ring_) * W, 0);
  eblock_.assign(static_cast<std::size_t>(edge_block_rows()) * W, kInvalid);
  // One run on a block without candidates (all INVALID) sizes the edge test's buffers for
  // every later block.
  const GridView<T> g{xyz_.data(), edge_block_rows(), width_, width_, 1, phys_ * width_};
  detail::edge_passes(g, eblock_.data(), params_.edge_window, params_.edge_k, passes_, 1,
                      escratch_, eflags_);
}

template <typename T>
void ProfileStream<T>::edge_band(std::int64_t band) noexcept {
  const std::ptrdiff_t W = width_;
  const std::int64_t R0 = band * kEdgeBandRows;
  const std::int64_t R1 = std::min<std::int64_t>(pushed_, R0 + kEdgeBandRows);
  const std::int64_t B = std::max<std::int64_t>(0, R0 - etop_);
  const std::int64_t E = std::min<std::int64_t>(pushed_, R1 + ebot_);
  const std::ptrdiff_t n = static_cast<std::ptrdiff_t>(E - B);
  // The edge test reads the labels of the height passes: undo the earlier bands' removals.
  for (std::int64_t rr = B; rr < E; ++rr) {
    const std::uint8_t* lab = labels_.data() + slot(rr) * W;
    const std::uint8_t* eo = eold_.data() + slot(rr) * W;
    std::uint8_t* out = eblock_.data() + (rr - B) * W;
    for (std::ptrdiff_t c = 0; c < W; ++c) out[c] = eo[c] ? static_cast<std::uint8_t>(eo[c] - 1) : lab[c];
  }
  // Rows B .. E - 1 are consecutive in memory (the ring's extension holds a whole block).
  const GridView<T> g{xyz_.data() + slot(B) * W, n, W, W, 1, phys_ * W};
  detail::edge_passes(g, eblock_.data(), params_.edge_window, params_.edge_k, passes_, 1,
                      escratch_, eflags_);
  for (std::int64_t rr = R0; rr < R1; ++rr) {
    std::uint8_t* lab = labels_.data() + slot(rr) * W;
    std::uint8_t* eo = eold_.data() + slot(rr) * W;
    std::uint8_t* hs = hs_.data() + slot(rr) * W;
    const std::uint8_t* got = eblock_.data() + (rr - B) * W;
    for (std::ptrdiff_t c = 0; c < W; ++c) {
      if (got[c] != kAbnormal || lab[c] == kAbnormal) continue;
      const std::uint8_t before = lab[c];
      lab[c] = kAbnormal;
      eo[c] = static_cast<std::uint8_t>(before + 1);
      hs[c] = kEdgeRemoved;  // out of the final window classes
      // a NORMAL cell left the windows around it: their heights are fitted again at the end
      if (before == kNormal) mark_stale(rr, c);
    }
  }
}

#define MIEM_STREAM_EDGES(T)                              \
  template void ProfileStream<T>::init_edges();          \
  template void ProfileStream<T>::edge_band(std::int64_t) noexcept;
MIEM_STREAM_EDGES(float)
MIEM_STREAM_EDGES(double)
#undef MIEM_STREAM_EDGES

}  // namespace miem
