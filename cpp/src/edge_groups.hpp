// The EDGE groups of the height test (docs/SPEC.md "height_tolerance" step 1): two EDGE cells are
// linked when they are 8-neighbours, or 2 .. 1 + gap cells apart along one of the 8 directions
// with only INVALID cells, or cells the angle passes made ABNORMAL, between (a dropout or a defect
// on a feature line does not cut it). One walker for the
// batch grid (height_test.cpp) and the stream's ring of rows (stream_stages.cpp), which differ
// only in how they read a cell and mark it seen.
#pragma once

#include <algorithm>
#include <cstdint>
#include <vector>

namespace miem::detail {

/// What a step of the link search finds at a cell.
enum class EdgeLink : std::uint8_t {
  kEdge,  ///< an EDGE cell: linked
  kGap,   ///< INVALID, or ABNORMAL after the angle passes: the search goes on (up to `gap`)
  kStop,  ///< any other cell, or outside the rows / columns the caller searches
};

/// The bounding box of a group (rows r0..r1, columns c0..c1).
struct EdgeGroupBox {
  std::int64_t r0, r1, c0, c1;
  /// The box's longer side in cells (SPEC: compact when at most edge_extent).
  std::int64_t extent() const { return std::max(r1 - r0, c1 - c0) + 1; }
};

/// Walks the EDGE group of cell (row, col) breadth first. `cells` gives
///   EdgeLink link(std::int64_t r, std::ptrdiff_t c): the cell's kind for the link rule, with
///     kStop outside the searched rows / columns;
///   bool claim(std::int64_t r, std::ptrdiff_t c): marks an EDGE cell seen, true when it was not
///     (called for (row, col) first, and for every linked cell the walk reaches).
/// On return `queue` holds the cells claimed, as r * cols + c. Returns the group's box.
template <typename Cells>
EdgeGroupBox walk_edge_group(Cells& cells, std::int64_t row, std::ptrdiff_t col,
                             std::ptrdiff_t cols, int gap, std::vector<std::int64_t>& queue) {
  queue.clear();
  cells.claim(row, col);
  queue.push_back(row * cols + col);
  EdgeGroupBox box{row, row, col, col};
  for (std::size_t head = 0; head < queue.size(); ++head) {
    const std::int64_t r = queue[head] / cols;
    const std::ptrdiff_t c = static_cast<std::ptrdiff_t>(queue[head] % cols);
    box.r0 = std::min(box.r0, r), box.r1 = std::max(box.r1, r);
    box.c0 = std::min<std::int64_t>(box.c0, c), box.c1 = std::max<std::int64_t>(box.c1, c);
    for (std::int64_t dr = -1; dr <= 1; ++dr) {
      for (std::ptrdiff_t dc = -1; dc <= 1; ++dc) {
        if (dr == 0 && dc == 0) continue;
        // the first cell along (dr, dc) within 1 + gap steps that is EDGE, past kGap cells only
        for (int k = 1; k <= 1 + gap; ++k) {
          const std::int64_t rr = r + k * dr;
          const std::ptrdiff_t cc = c + k * dc;
          const EdgeLink l = cells.link(rr, cc);
          if (l == EdgeLink::kGap) continue;
          if (l == EdgeLink::kEdge && cells.claim(rr, cc)) queue.push_back(rr * cols + cc);
          break;
        }
      }
    }
  }
  return box;
}

}  // namespace miem::detail
