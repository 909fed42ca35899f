// SPEC "Judgment": a cell's (a point's) label from the directions available (at any scale) and
// the directions flagged at each scale. The one rule every judge of the angle test shares: grids
// (CellJudge, the row kernel's label_line, the stream's exact_label and min_step_label) and
// clouds (PointJudge).
#pragma once

#include <cstdint>

#include "miem/organized.hpp"

namespace miem::detail {

/// The directions that must be flagged at one scale: min(avail, min_directions) (0: all).
template <typename I>
inline I needed_directions(I avail, I min_directions) {
  return min_directions > 0 ? (avail < min_directions ? avail : min_directions) : avail;
}

/// ABNORMAL (1, else 0) from `avail`, the directions available at any scale, and `most`, the
/// most directions flagged at one and the same scale: at least 2 available and at least
/// needed_directions flagged at one scale. Branch-free on integer lanes, so that the row
/// kernel's label loop vectorises it.
template <typename I>
inline I abnormal_verdict(I avail, I most, I min_directions) {
  return static_cast<I>((avail >= 2) & (most >= needed_directions(avail, min_directions)));
}

/// Set bits of a direction mask (at most 8 directions).
inline int direction_count(unsigned mask) {
  int n = 0;
  for (; mask != 0; mask &= mask - 1) ++n;
  return n;
}

/// A cell's verdict over its scales: add() each scale's masks (bit k: direction k available /
/// flagged at that scale). ABNORMAL when abnormal_verdict; else EDGE when a direction is flagged
/// at any scale; else NORMAL. flags(): the directions flagged at any scale.
class ScaleVerdict {
 public:
  explicit ScaleVerdict(int min_directions) : min_directions_(min_directions) {}

  void add(unsigned avail, unsigned flagged) {
    avail_ |= avail;
    flags_ |= flagged;
    const int f = direction_count(flagged);
    most_ = f > most_ ? f : most_;
  }
  std::uint8_t flags() const { return static_cast<std::uint8_t>(flags_); }
  std::uint8_t label() const {
    if (abnormal_verdict(direction_count(avail_), most_, min_directions_)) return kAbnormal;
    return flags_ != 0 ? kEdge : kNormal;
  }

 private:
  int min_directions_;
  unsigned avail_ = 0, flags_ = 0;
  int most_ = 0;  // the most directions flagged at one scale
};

}  // namespace miem::detail
