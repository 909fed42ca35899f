// The stream's defects (docs/SPEC.md "Streaming", "Defects"): the 8-connected ABNORMAL groups of
// the rows handed back, grown row by row (union-find over the groups that touch the last row)
// and reported, summarised as batch detection summarises them (defects.hpp), by the call that
// hands back the first row after a group in which none of its cells lies: no later profile can
// change it then. A group's cells (index, point, height) are kept in a pool, so that rows may
// leave the ring while their group is still open; the window plane's normal at the peak is
// computed when a cell becomes its group's peak (its window's labels are final by then).
#include <algorithm>
#include <cmath>

#include "byte_scan.hpp"
#include "defects.hpp"
#include "judge.hpp"
#include "miem/stream.hpp"

namespace miem {

namespace {
constexpr std::int32_t kNone = -1;
// Pools reserved at construction; they grow (and then keep the memory) only beyond this.
constexpr std::size_t kDoneReserve = 32, kIndicesReserve = 64;
}  // namespace

template <typename T>
void ProfileStream<T>::init_defects() {
  const std::size_t W = static_cast<std::size_t>(width_);
  dprev_.assign(W, kNone);
  dcur_.assign(W, kNone);
  dcols_prev_.reserve(W);
  dcols_cur_.reserve(W);
  slots_.reserve(W + 8);
  slot_free_.reserve(W + 8);
  dead_.reserve(W + 8);
  closed_.reserve(W + 8);
  const std::size_t members = std::max<std::size_t>(4096, 16 * W);
  mem_idx_.reserve(members);
  mem_pt_.reserve(3 * members);
  mem_h_.reserve(members);
  mem_next_.reserve(members);
  order_.reserve(members);
  sorted_pt_.reserve(3 * members);
  sorted_h_.reserve(members);
  done_.resize(kDoneReserve);
  for (Defect& d : done_) d.indices.reserve(kIndicesReserve);
  reset_defects();
}

template <typename T>
void ProfileStream<T>::reset_defects() noexcept {
  std::fill(dprev_.begin(), dprev_.end(), kNone);
  std::fill(dcur_.begin(), dcur_.end(), kNone);
  dcols_prev_.clear();
  dcols_cur_.clear();
  slots_.clear();
  slot_free_.clear();
  dead_.clear();
  closed_.clear();
  mem_idx_.clear();
  mem_pt_.clear();
  mem_h_.clear();
  mem_next_.clear();
  mem_free_ = kNone;
  n_done_ = 0;
  defects_reported_ = 0;
}

template <typename T>
std::int32_t ProfileStream<T>::find_slot(std::int32_t s) noexcept {
  while (slots_[static_cast<std::size_t>(s)].parent != s) {
    DefectSlot& d = slots_[static_cast<std::size_t>(s)];
    d.parent = slots_[static_cast<std::size_t>(d.parent)].parent;  // path halving
    s = d.parent;
  }
  return s;
}

// Merges the groups of roots a and b (a != b) into a; b's slot is freed after the row.
template <typename T>
std::int32_t ProfileStream<T>::merge_slots(std::int32_t a, std::int32_t b) noexcept {
  DefectSlot& x = slots_[static_cast<std::size_t>(a)];
  DefectSlot& y = slots_[static_cast<std::size_t>(b)];
  y.parent = a;
  mem_next_[static_cast<std::size_t>(x.tail)] = y.head;
  x.tail = y.tail;
  x.count += y.count;
  x.touches = x.touches || y.touches;
  x.last_row = std::max(x.last_row, y.last_row);
  // The batch's peak: the largest |height|, the first in index order on ties.
  if (y.peak_idx >= 0 &&
      (x.peak_idx < 0 || std::abs(y.peak_h) > std::abs(x.peak_h) ||
       (std::abs(y.peak_h) == std::abs(x.peak_h) && y.peak_idx < x.peak_idx))) {
    x.peak_idx = y.peak_idx;
    x.peak_h = y.peak_h;
    x.normal = y.normal;
  }
  dead_.push_back(b);
  return a;
}

// Row `row` is final (labels, and heights over final labels; the labels of row + 1 are final
// too): adds its ABNORMAL cells to the groups and reports the groups it ends (all of them when
// it is the stream's last row).
template <typename T>
void ProfileStream<T>::defect_row(std::int64_t row) noexcept {
  const std::ptrdiff_t W = width_, plane = phys_ * W;
  n_done_ = 0;
  std::swap(dprev_, dcur_);
  std::swap(dcols_prev_, dcols_cur_);
  // dcur_ still holds the row before the previous one: back to none where it had a slot. (The
  // lists of columns keep the work per row to its ABNORMAL cells, a few in a 3200-point row.)
  for (const std::int32_t c : dcols_cur_) dcur_[static_cast<std::size_t>(c)] = kNone;
  dcols_cur_.clear();
  const std::uint8_t* lab = labels_.data() + slot(row) * W;
  const std::uint8_t* up = row > 0 ? labels_.data() + slot(row - 1) * W : nullptr;
  const std::uint8_t* down = row + 1 < pushed_ ? labels_.data() + slot(row + 1) * W : nullptr;
  const double* height = height_.data() + slot(row) * W;
  const T* px = xyz_.data() + slot(row) * W;
  auto surface = [](std::uint8_t l) { return l != kAbnormal && l != kInvalid; };
  for (std::ptrdiff_t c = 0; c < W; ++c) {
    c = detail::next_byte(lab, c, W, kAbnormal);  // the next ABNORMAL cell
    if (c >= W) break;
    std::int32_t s = kNone;
    const std::int32_t near[4] = {c > 0 ? dcur_[static_cast<std::size_t>(c - 1)] : kNone,
                                  c > 0 ? dprev_[static_cast<std::size_t>(c - 1)] : kNone,
                                  dprev_[static_cast<std::size_t>(c)],
                                  c + 1 < W ? dprev_[static_cast<std::size_t>(c + 1)] : kNone};
    for (const std::int32_t q : near) {
      if (q == kNone) continue;
      const std::int32_t r = find_slot(q);
      s = s == kNone ? r : (r == s ? s : merge_slots(s, r));
    }
    // the new member
    std::int32_t m;
    if (mem_free_ != kNone) {
      m = mem_free_;
      mem_free_ = mem_next_[static_cast<std::size_t>(m)];
    } else {
      m = static_cast<std::int32_t>(mem_idx_.size());
      mem_idx_.push_back(0);
      mem_pt_.insert(mem_pt_.end(), 3, 0.0);
      mem_h_.push_back(0.0);
      mem_next_.push_back(kNone);
    }
    const std::size_t mi = static_cast<std::size_t>(m);
    const std::int64_t idx = row * W + c;
    mem_idx_[mi] = idx;
    mem_pt_[3 * mi] = static_cast<double>(px[c]);
    mem_pt_[3 * mi + 1] = static_cast<double>(px[c + plane]);
    mem_pt_[3 * mi + 2] = static_cast<double>(px[c + 2 * plane]);
    mem_h_[mi] = height[c];
    mem_next_[mi] = kNone;
    if (s == kNone) {
      if (!slot_free_.empty()) {
        s = slot_free_.back();
        slot_free_.pop_back();
      } else {
        s = static_cast<std::int32_t>(slots_.size());
        slots_.emplace_back();
      }
      DefectSlot& d = slots_[static_cast<std::size_t>(s)];
      d = DefectSlot{};
      d.parent = s;
      d.head = d.tail = m;
    } else {
      DefectSlot& d = slots_[static_cast<std::size_t>(s)];
      mem_next_[static_cast<std::size_t>(d.tail)] = m;
      d.tail = m;
    }
    DefectSlot& d = slots_[static_cast<std::size_t>(s)];
    ++d.count;
    d.last_row = row;
    bool touches = false;  // a finite, non-ABNORMAL cell among the 8 neighbours
    for (std::ptrdiff_t q = std::max<std::ptrdiff_t>(0, c - 1);
         q <= std::min<std::ptrdiff_t>(W - 1, c + 1); ++q) {
      touches = touches || (q != c && surface(lab[q])) || (up != nullptr && surface(up[q])) ||
                (down != nullptr && surface(down[q]));
    }
    d.touches = d.touches || touches;
    // Every member so far has a smaller index: a tie keeps the old peak, as batch does.
    const double h = height[c];
    if (std::isfinite(h) && (d.peak_idx < 0 || std::abs(h) > std::abs(d.peak_h))) {
      d.peak_idx = idx;
      d.peak_h = h;
      Plane pl;
      d.normal = final_window_plane(row, c, &pl) ? pl.normal
                                                 : Eigen::Vector3d::Constant(detail::kNaN);
    }
    dcur_[static_cast<std::size_t>(c)] = s;
    dcols_cur_.push_back(static_cast<std::int32_t>(c));
  }
  // Groups of the row before that no cell of this row continues are final; at the stream's
  // end, every group.
  const bool last = finished_ && row + 1 >= pushed_;
  auto close = [&](std::int32_t q) {
    const std::int32_t r = find_slot(q);
    DefectSlot& d = slots_[static_cast<std::size_t>(r)];
    if (d.closed || (!last && d.last_row == row)) return;
    d.closed = true;
    closed_.push_back(r);
    report(r);
  };
  for (const std::int32_t c : dcols_prev_) close(dprev_[static_cast<std::size_t>(c)]);
  if (last) {
    for (const std::int32_t c : dcols_cur_) close(dcur_[static_cast<std::size_t>(c)]);
  }
  // The slots merged away in this row and the closed ones are referenced only by dprev_ (and,
  // at the end, dcur_), which the next row overwrites: dcur_ keeps roots only, then they go.
  for (const std::int32_t c : dcols_cur_) {
    std::int32_t& q = dcur_[static_cast<std::size_t>(c)];
    q = last ? kNone : find_slot(q);
  }
  if (last) dcols_cur_.clear();
  for (const std::int32_t b : dead_) slot_free_.push_back(b);
  dead_.clear();
  for (const std::int32_t b : closed_) slot_free_.push_back(b);
  closed_.clear();
  // Reported in the order of their first cell.
  std::sort(done_.begin(), done_.begin() + static_cast<std::ptrdiff_t>(n_done_),
            [](const Defect& a, const Defect& b) { return a.indices.front() < b.indices.front(); });
  for (std::size_t k = 0; k < n_done_; ++k) {
    done_[k].id = static_cast<int>(defects_reported_++);
  }
}

// Summarises the closed group of root r into the next entry of done_ and frees its cells.
template <typename T>
void ProfileStream<T>::report(std::int32_t r) noexcept {
  if (n_done_ == done_.size()) {
    done_.emplace_back();  // beyond the reserve (then kept)
    done_.back().indices.reserve(kIndicesReserve);
  }
  Defect& d = done_[n_done_++];
  const DefectSlot& s = slots_[static_cast<std::size_t>(r)];
  order_.clear();
  for (std::int32_t m = s.head; m != kNone; m = mem_next_[static_cast<std::size_t>(m)]) {
    order_.push_back(m);
  }
  std::sort(order_.begin(), order_.end(), [&](std::int32_t a, std::int32_t b) {
    return mem_idx_[static_cast<std::size_t>(a)] < mem_idx_[static_cast<std::size_t>(b)];
  });
  d.indices.clear();
  sorted_pt_.clear();
  sorted_h_.clear();
  for (const std::int32_t m : order_) {
    const std::size_t mi = static_cast<std::size_t>(m);
    d.indices.push_back(mem_idx_[mi]);
    sorted_pt_.insert(sorted_pt_.end(), mem_pt_.begin() + static_cast<std::ptrdiff_t>(3 * mi),
                      mem_pt_.begin() + static_cast<std::ptrdiff_t>(3 * mi + 3));
    sorted_h_.push_back(mem_h_[mi]);
  }
  // The members in index order: position k holds index d.indices[k].
  const auto pos = [&](std::int64_t i) {
    return static_cast<std::size_t>(std::lower_bound(d.indices.begin(), d.indices.end(), i) -
                                    d.indices.begin());
  };
  const auto point_at = [&](std::int64_t i) -> Eigen::Vector3d {
    const std::size_t k = pos(i);
    return Eigen::Vector3d(sorted_pt_[3 * k], sorted_pt_[3 * k + 1], sorted_pt_[3 * k + 2]);
  };
  const auto height_at = [&](std::int64_t i) { return sorted_h_[pos(i)]; };
  d.normal = Eigen::Vector3d::Constant(detail::kNaN);
  const std::int64_t peak = detail::summarize_defect_at(d, height_at, point_at);
  if (peak >= 0 && peak == s.peak_idx) d.normal = s.normal;
  detail::finish_defect(d, point_at, s.touches);
  for (const std::int32_t m : order_) {  // the cells back to the pool
    mem_next_[static_cast<std::size_t>(m)] = mem_free_;
    mem_free_ = m;
  }
}

#define MIEM_STREAM_DEFECTS(T)                                        \
  template void ProfileStream<T>::init_defects();                    \
  template void ProfileStream<T>::reset_defects() noexcept;          \
  template void ProfileStream<T>::defect_row(std::int64_t) noexcept;
MIEM_STREAM_DEFECTS(float)
MIEM_STREAM_DEFECTS(double)
#undef MIEM_STREAM_DEFECTS

}  // namespace miem
