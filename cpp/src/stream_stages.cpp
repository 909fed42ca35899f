// The stream's stages after the angle passes (docs/SPEC.md "Streaming"): the compact EDGE groups,
// the height passes and the heights, each run on one row per push at its own lag behind the
// angle passes, with the batch stages' own routines (window_fits.hpp: the row moments, the
// vectorised eigen solve, the direct window fit; stages.hpp: the height test's verdict;
// judge.hpp: the window plane of HeightMode::kAbnormal).
//
// Height pass 1 fits every finite cell of its row from running window sums: column sums over
// the window's rows (one row in, one row out per push), box sums along the row, per strip of
// kStrip columns with the strip's own origin (as the batch tiles), and a new origin every band_
// rows: the next band's sums are built alongside the current ones over the 2h + 1 rows before
// it, so no push does more than one extra row. A removal marks the cells within h for the next
// pass (fitted directly, few cells) and for the heights (their pass-1 height is stale).
#include <algorithm>
#include <cmath>
#include <cstring>

#include "byte_scan.hpp"
#include "edge_groups.hpp"
#include "edge_test.hpp"
#include "miem/stream.hpp"
#include "parallel.hpp"
#include "stages.hpp"
#include "window_fits.hpp"
#include "vector_clones.hpp"

namespace miem {

namespace {

using detail::kInPlane;
using detail::kLine;
using detail::kMoments;

// Bits of hm_ besides kInPlane (NORMAL after the angle passes) and kLine (EDGE of a group that
// is not compact): what add_row_moments reads, so a row of hm_ is its own window classes.
constexpr std::uint8_t kSEdge = 4;       // EDGE after the angle passes
constexpr std::uint8_t kSCompact = 8;    // EDGE of a compact group
constexpr std::uint8_t kSSeen = 16;      // grouped
constexpr std::uint8_t kSWantEven = 32;  // re-fit at the next even / odd height pass
constexpr std::uint8_t kSWantOdd = 64;
constexpr std::uint8_t kSStale = 128;  // a cell within h was removed: the pass-1 height is stale
constexpr std::ptrdiff_t kStrip = 128;
constexpr std::ptrdiff_t kAhead = 2;  // strips a prefetch runs ahead (prefetch_planes)
constexpr std::uint8_t kNever = 255;  // hs_: not removed by the height test

constexpr std::uint8_t want_bit(int pass) { return (pass & 1) ? kSWantOdd : kSWantEven; }

// A cell's class in height pass `pass` (kNever: the final labels) from its bits b and removal
// pass hs: in the plane while NORMAL at the pass's start (Jacobi), else a feature-line count
// when `lines`.
constexpr std::uint8_t pass_class(std::uint8_t b, std::uint8_t hs, int pass, bool lines) {
  return ((b & kInPlane) && hs >= pass) ? kInPlane : ((lines && (b & kLine)) ? kLine : 0);
}

// Height pass 1 on a row span of n cells from row_solve's fits (RowFits, not compact): the
// height of each wanted cell (w[j] != 0; NaN without a plane), with quiet_floor >= 0 kHQuiet
// added to quiet[j] where a NORMAL cell's plane is quiet, and, with `test`, w[j] = 1 where
// the cell is a candidate (NORMAL or compact EDGE, by its bits hm[j]) the verdict
// (height_verdict) finds too far, else 0. Straight-line code (vectorised), as the batch's
// height_row: a cell's verdict and height are those of the one-cell path (RowFits::fit).
MIEM_CLONES void pass1_verdicts(std::ptrdiff_t n, const std::uint8_t* __restrict hm,
                                const double* S, const double* F,
                                const std::uint8_t* __restrict okf, std::ptrdiff_t cap, bool test,
                                double height_abs, double height_k, double z_min,
                                double quiet_floor, double* height,
                                std::uint8_t* __restrict quiet, std::uint8_t* __restrict w) {
  detail::store_heights(n, w, okf, F, height);
  if (!test && quiet_floor < 0.0) return;  // (neither verdict wanted: heights only)
  // Blocks of kB cells: the verdicts (verdict_codes), then the bytes.
  constexpr std::ptrdiff_t kB = 256;
  double code[kB];
  for (std::ptrdiff_t b0 = 0; b0 < n; b0 += kB) {
    const std::ptrdiff_t nb = std::min(kB, n - b0);
    detail::verdict_codes(nb, S + b0, F + b0, cap, height_abs, height_k, z_min, quiet_floor,
                          code);
    if (quiet_floor >= 0.0) {  // quiet marks of the NORMAL cells, before w changes
      for (std::ptrdiff_t t = 0; t < nb; ++t) {
        const std::ptrdiff_t j = b0 + t;
        const int c = okf[j] != 0 ? static_cast<int>(code[t]) : 0;
        // hm[j] & kInPlane (bit 0) as a number, not tested with != 0: GCC 12 does not
        // vectorise a loop with that test of bit 0 (no vector type for it)
        const int mark = ((w[j] != 0) & (c >> 1)) & (hm[j] & kInPlane);
        // (kHStale may be there: a removal above)
        quiet[j] = static_cast<std::uint8_t>(quiet[j] | (mark ? detail::kHQuiet : 0));
      }
    }
    if (!test) continue;
    for (std::ptrdiff_t t = 0; t < nb; ++t) {
      const std::ptrdiff_t j = b0 + t;
      const int c = okf[j] != 0 ? static_cast<int>(code[t]) : 0;
      const int cand = (hm[j] & (kInPlane | kSCompact)) != 0;
      w[j] = static_cast<std::uint8_t>((w[j] != 0) & cand & (c & 1));
    }
  }
}

}  // namespace

// One thread's doubles of fit_buf_: S, Q, F of a strip (fit_strip_doubles), then two rows'
// relative coordinates (sums_add_row's).
template <typename T>
std::ptrdiff_t ProfileStream<T>::fit_strip_doubles() const noexcept {
  return (kMoments + 3 + 4) * std::min(width_, kStrip);
}

template <typename T>
std::ptrdiff_t ProfileStream<T>::fit_doubles() const noexcept {
  return fit_strip_doubles() + 6 * span_;
}

template <typename T>
void ProfileStream<T>::init_stages() {
  const std::ptrdiff_t W = width_, n1 = ring_ * W;
  hm_.assign(static_cast<std::size_t>(n1), 0);
  hs_.assign(static_cast<std::size_t>(n1), kNever);
  hrow_.assign(static_cast<std::size_t>(ring_), 0);
  height_.assign(static_cast<std::size_t>(n1), detail::kNaN);
  next_pass_.assign(static_cast<std::size_t>(passes_) + 1, 0);
  queue_.reserve(static_cast<std::size_t>((2 * (extent_ + link_gap_) + 1) * W));
  const std::ptrdiff_t side = 2 * static_cast<std::ptrdiff_t>(half_) + 1;
  local_.assign(static_cast<std::size_t>(side * side), 0);
  const std::ptrdiff_t cap = std::min(W, kStrip);
  strips_ = (W + kStrip - 1) / kStrip;
  span_ = std::min(W, kStrip + 2 * half_);
  stride_ = span_ + 2 * (half_ + 1);
  band_ = std::max<std::ptrdiff_t>(64, 2 * half_ + 2);
  if (sums_) {
    cs_.assign(static_cast<std::size_t>(2 * strips_ * kMoments * stride_), 0.0);
    origin_.assign(static_cast<std::size_t>(2 * strips_ * 3), 0.0);
    has_origin_.assign(static_cast<std::size_t>(2 * strips_), 0);
    fit_buf_.assign(static_cast<std::size_t>(threads_ * fit_doubles()), 0.0);
    fit_flags_.assign(static_cast<std::size_t>(threads_ * 3 * cap), 0);
    far_row_.assign(static_cast<std::size_t>(W), 0);
  }
  if (htest_ || edge_) {  // region_fits: column sums and classes of a segment and its window
    region_cs_.assign(static_cast<std::size_t>(kMoments * (span_ + 2 * (half_ + 1))), 0.0);
    region_cls_.assign(static_cast<std::size_t>(span_), 0);
    want_row_.assign(static_cast<std::size_t>(W), 0);
  }
  reset_stages();
}

template <typename T>
void ProfileStream<T>::reset_stages() noexcept {
  next_final_ = next_compact_ = next_out_ = 0;
  reset_edges();
  std::fill(next_pass_.begin(), next_pass_.end(), 0);
  std::fill(cs_.begin(), cs_.end(), 0.0);
  std::fill(has_origin_.begin(), has_origin_.end(), 0);
  set_first_[0] = 0;
  set_first_[1] = band_ - half_;
  cur_ = 0;
  sums_next_ = 0;
}

template <typename T>
void ProfileStream<T>::run_stages(bool to_end) noexcept {
  const std::int64_t last = pushed_ - 1;
  auto upto = [&](long long offset) { return to_end ? last : last - offset; };
  const long long A = alag_, E = extent_ + link_gap_, h = half_;
  for (const std::int64_t lim = upto(A); next_final_ <= lim;) angle_final_row(next_final_++);
  if (htest_) {
    for (const std::int64_t lim = upto(A + E); next_compact_ <= lim;) compact_row(next_compact_++);
  }
  if (sums_) {
    std::int64_t& next = next_pass_[1];
    for (const std::int64_t lim = upto(A + E + h); next <= lim;) height_pass1_row(next++);
  }
  if (htest_) {
    for (int p = 2; p <= passes_; ++p) {
      std::int64_t& next = next_pass_[static_cast<std::size_t>(p)];
      for (const std::int64_t lim = upto(A + E + p * h); next <= lim;) height_pass_row(next++, p);
    }
  }
  if (edge_) run_edges(to_end);
  for (const std::int64_t lim = upto(lag_); next_out_ <= lim;) final_row(next_out_++);
}

// The angle labels of `row` are final: keep its classes (NORMAL, EDGE) for the later stages.
template <typename T>
void ProfileStream<T>::angle_final_row(std::int64_t row) noexcept {
  const std::ptrdiff_t W = width_, s = slot(row);
  const std::uint8_t* lab = labels_.data() + s * W;
  std::uint8_t* hm = hm_.data() + s * W;
  for (std::ptrdiff_t c = 0; c < W; ++c) {
    hm[c] |= lab[c] == kNormal ? kInPlane : (lab[c] == kEdge ? kSEdge : 0);
  }
}

// The EDGE groups through `row` (SPEC "height_tolerance": compact when the bounding box's longer
// side is at most E cells). A compact group lies within E - 1 rows of each of its cells, so the
// group of a cell, searched within E rows of it, is either whole (and its box decides) or reaches
// E rows away (not compact). Every cell a search reaches is marked seen, with its verdict.
template <typename T>
void ProfileStream<T>::compact_row(std::int64_t row) noexcept {
  const std::ptrdiff_t W = width_;
  std::uint8_t* hm0 = hm_.data() + slot(row) * W;
  const std::int64_t lo = std::max<std::int64_t>(0, row - extent_ - link_gap_);
  const std::int64_t hi = std::min<std::int64_t>(pushed_ - 1, row + extent_ + link_gap_);
  // The rows lo..hi of the ring, EDGE by kSEdge; a claimed cell is tentatively compact, and a
  // group that meets a cell of a group already found not compact is not compact either.
  struct Cells {
    ProfileStream& s;
    std::int64_t lo, hi;
    bool long_group = false;
    detail::EdgeLink link(std::int64_t r, std::ptrdiff_t c) const {
      if (r < lo || r > hi || c < 0 || c >= s.width_) return detail::EdgeLink::kStop;
      const std::ptrdiff_t i = s.slot(r) * s.width_ + c;
      const std::uint8_t b = s.hm_[static_cast<std::size_t>(i)];
      if (b & kSEdge) return detail::EdgeLink::kEdge;
      // past INVALID cells and cells ABNORMAL after the angle passes (neither NORMAL nor EDGE
      // then: kInPlane unset), as the batch's labels before the height test
      const std::uint8_t l = s.labels_[static_cast<std::size_t>(i)];
      return l == kInvalid || (l == kAbnormal && !(b & kInPlane)) ? detail::EdgeLink::kGap
                                                                   : detail::EdgeLink::kStop;
    }
    bool claim(std::int64_t r, std::ptrdiff_t c) {
      std::uint8_t& b = s.hm_[static_cast<std::size_t>(s.slot(r) * s.width_ + c)];
      if (b & kSSeen) {
        long_group |= !(b & kSCompact);
        return false;
      }
      b = static_cast<std::uint8_t>(b | kSSeen | kSCompact);
      return true;
    }
  };
  constexpr std::uint64_t kBytes = 0x0101010101010101ull;  // one in each byte
  for (std::ptrdiff_t c = 0; extent_ > 0 && c < W; ++c) {
    // 8 cells at a time while none is an EDGE cell not yet grouped (most rows have none):
    // kSSeen moved down onto kSEdge clears the grouped ones
    static_assert(kSSeen == kSEdge << 2, "the shift below moves kSSeen onto kSEdge");
    for (std::uint64_t w; c + 8 <= W; c += 8) {
      std::memcpy(&w, hm0 + c, 8);
      if ((w & kBytes * kSEdge & ~((w & kBytes * kSSeen) >> 2)) != 0) break;
    }
    if (c >= W) break;
    if ((hm0[c] & (kSEdge | kSSeen)) != kSEdge) continue;
    Cells cells{*this, lo, hi};
    const detail::EdgeGroupBox box = detail::walk_edge_group(cells, row, c, W, link_gap_, queue_);
    if (cells.long_group || box.extent() > extent_) {
      for (const std::int64_t i : queue_) {
        hm_[static_cast<std::size_t>(slot(i / W) * W + i % W)] &=
            static_cast<std::uint8_t>(~kSCompact);
      }
    }
  }
  for (std::ptrdiff_t c = 0; c < W; ++c) {  // branch-free: vectorised
    const std::uint8_t b = hm0[c];
    hm0[c] = static_cast<std::uint8_t>(b | ((b & (kSEdge | kSCompact)) == kSEdge ? kLine : 0));
  }
}

// A feature-line EDGE cell (edge test step 9): EDGE of a group that is not compact, or
// without the height test EDGE after the angle passes.
template <typename T>
bool ProfileStream<T>::feature_line(std::int64_t row, std::ptrdiff_t col) const noexcept {
  const std::uint8_t b = hm_[static_cast<std::size_t>(slot(row) * width_ + col)];
  return (b & (htest_ ? kLine : kSEdge)) != 0;
}

// Adds (sign 1) or removes (sign -1) the window classes of row `in` to the column sums of `set`;
// with `out` >= 0, adds row `in` and removes row `out` in one pass (move_row_moments).
template <typename T>
void ProfileStream<T>::sums_add_row(int set, std::int64_t in, double sign,
                                    std::int64_t out) noexcept {
  const std::ptrdiff_t W = width_, pad = half_ + 1, plane = phys_ * W;
  const GridView<T> g{xyz_.data() + slot(in) * W, 1, W, W, 1, plane};
  const std::uint8_t* hm = hm_.data() + slot(in) * W;
  // Strips are independent (each its own column sums and origin): split among the threads,
  // each with its own rows of relative coordinates.
  detail::parallel_items(threads_, strips_, [&](std::ptrdiff_t t, int tid) {
    double* x = fit_buf_.data() + tid * fit_doubles() + fit_strip_doubles();
    double* xo = x + 3 * span_;  // the row leaving
    const std::ptrdiff_t tc0 = t * kStrip, tc1 = std::min(W, tc0 + kStrip);
    const std::ptrdiff_t C0 = std::max<std::ptrdiff_t>(0, tc0 - half_);
    const std::ptrdiff_t C1 = std::min<std::ptrdiff_t>(W, tc1 + half_), nc = C1 - C0;
    const std::size_t k = static_cast<std::size_t>(set * strips_ + t);
    double* o = origin_.data() + 3 * k;
    if (!has_origin_[k] && sign > 0.0) {  // the strip's first NORMAL cell (before it, the
      for (std::ptrdiff_t c = C0; c < C1; ++c) {  // rows added nothing but line counts)
        if (hm[c] & kInPlane) {
          const Eigen::Vector3d p = g(0, c);
          o[0] = p.x(), o[1] = p.y(), o[2] = p.z();
          has_origin_[k] = 1;
          break;
        }
      }
    }
    double* cs = cs_.data() + k * kMoments * stride_ + pad;
    if (t + kAhead < strips_) {  // the rows' cells of the strip kAhead on
      const std::ptrdiff_t a0 = (t + kAhead) * kStrip + half_;
      const std::ptrdiff_t a1 = std::min(W, a0 + kStrip);
      detail::prefetch_planes(g.data, plane, a0, a1);
      if (out >= 0) detail::prefetch_planes(xyz_.data() + slot(out) * W, plane, a0, a1);
    }
    detail::load_rel(g, 0, C0, nc, o[0], o[1], o[2], x, x + span_, x + 2 * span_);
    if (out < 0) {
      detail::add_row_moments(hm + C0, nc, x, x + span_, x + 2 * span_, sign, cs, stride_);
      return;
    }
    const GridView<T> go{xyz_.data() + slot(out) * W, 1, W, W, 1, plane};
    detail::load_rel(go, 0, C0, nc, o[0], o[1], o[2], xo, xo + span_, xo + 2 * span_);
    detail::move_row_moments(hm + C0, x, x + span_, x + 2 * span_,
                             hm_.data() + slot(out) * W + C0, xo, xo + span_, xo + 2 * span_,
                             nc, cs, stride_);
  });
}

// Height pass 1 on `row` (and the heights of HeightMode::kAll): the window plane of every finite
// cell from the running sums.
template <typename T>
void ProfileStream<T>::height_pass1_row(std::int64_t row) noexcept {
  const std::ptrdiff_t W = width_, h = half_, pad = h + 1, plane = phys_ * W;
  // The sums hold rows [row - h, row + h] (clipped): add the rows up to row + h, to the next
  // band's set too from its first row, and drop row - h - 1.
  const std::int64_t band = row / band_;
  if (row == band * band_ && band > 0 && set_first_[cur_] != band * band_ - h) {
    cur_ ^= 1;  // the next band's set, built over the last 2h + 1 rows, takes over
  }
  const int nxt = cur_ ^ 1;
  const std::int64_t next_first = (band + 1) * band_ - h;
  const std::int64_t lim = std::min<std::int64_t>(pushed_ - 1, row + h);
  const bool drop = row - h - 1 >= set_first_[cur_];
  const bool move = drop && sums_next_ == lim;  // the steady state: one row in, one out
  for (; sums_next_ <= lim;) {
    const std::int64_t r = sums_next_++;
    sums_add_row(cur_, r, 1.0, move ? row - h - 1 : -1);
    if (r == next_first) {  // start the next set afresh
      const std::size_t n = static_cast<std::size_t>(strips_ * kMoments * stride_);
      std::fill(cs_.begin() + static_cast<std::ptrdiff_t>(nxt * n),
                cs_.begin() + static_cast<std::ptrdiff_t>((nxt + 1) * n), 0.0);
      std::fill(has_origin_.begin() + nxt * strips_, has_origin_.begin() + (nxt + 1) * strips_, 0);
      set_first_[nxt] = next_first;
    }
    if (r >= next_first) sums_add_row(nxt, r, 1.0, -1);
  }
  if (drop && !move) sums_add_row(cur_, row - h - 1, -1.0, -1);

  const std::ptrdiff_t cap = std::min(W, kStrip), s = slot(row);
  const GridView<T> g{xyz_.data() + s * W, 1, W, W, 1, plane};
  const std::uint8_t* st = state_.data() + s * W;
  const std::uint8_t* hm = hm_.data() + s * W;
  double* height = height_.data() + s * W;
  // the edge test's quiet planes (cleared at push; with the height test only)
  const double quiet_floor = htest_ ? detail::quiet_plane_floor(jparams_) : -1.0;
  std::uint8_t* quiet = quiet_floor >= 0.0 ? eplane_.data() + s * W : nullptr;
  // The strips split among the threads, each with its own scratch; a cell too far goes into
  // far_row_, and the removals (which mark the cells around, in other strips too) follow in
  // column order.
  std::uint8_t* far_row = far_row_.data();
  detail::parallel_items(threads_, strips_, [&](std::ptrdiff_t t, int tid) {
    double* S = fit_buf_.data() + tid * fit_doubles();
    double* Q = S + kMoments * cap;
    double* F = Q + 3 * cap;
    std::uint8_t* okf = fit_flags_.data() + tid * 3 * cap;
    std::uint8_t* redo = okf + cap;
    std::uint8_t* wrow = redo + cap;
    const std::ptrdiff_t tc0 = t * kStrip, tc1 = std::min(W, tc0 + kStrip), n = tc1 - tc0;
    const std::ptrdiff_t C0 = std::max<std::ptrdiff_t>(0, tc0 - h);
    const std::size_t k = static_cast<std::size_t>(cur_ * strips_ + t);
    const double* o = origin_.data() + 3 * k;
    const double* col = cs_.data() + k * kMoments * stride_ + pad + (tc0 - C0);
    std::uint8_t* far = far_row + tc0;
    std::fill(far, far + n, std::uint8_t{0});
    std::ptrdiff_t m = 0;
    {  // branch-free over local restrict pointers: vectorised
      const std::uint8_t* __restrict s0 = st + tc0;
      std::uint8_t* __restrict w = wrow;
      for (std::ptrdiff_t j = 0; j < n; ++j) {
        const std::uint8_t finite = s0[j] != 0;
        w[j] = finite;
        m += finite;
      }
    }
    if (m < n) {  // the dropouts' heights
      for (std::ptrdiff_t j = 0; j < n; ++j)
        if (!wrow[j]) height[tc0 + j] = detail::kNaN;
    }
    if (t + kAhead < strips_) {
      const std::ptrdiff_t a0 = (t + kAhead) * kStrip;
      detail::prefetch_planes(g.data, plane, a0, std::min(W, a0 + kStrip));
    }
    if (m == 0) return;
    detail::load_rel(g, 0, tc0, n, o[0], o[1], o[2], Q, Q + cap, Q + 2 * cap);
    const detail::RowFits rf = detail::row_solve(
        col, stride_, h, n, cap, wrow, m, S, Q, F, okf, redo,
        [&](std::ptrdiff_t j) { return window_direct_fit(row, tc0 + j, 1); });
    if (!rf.compact) {  // the whole span at once: heights, then the verdicts
      const std::ptrdiff_t j0 = rf.j0, j1 = rf.j1;
      // wrow[j] becomes: cell j is wanted and too far
      pass1_verdicts(j1 - j0, hm + tc0 + j0, rf.S + j0, rf.F + j0, rf.okf + j0, rf.cap,
                     htest_, params_.height_abs, params_.height_k,
                     detail::z_floor(jparams_.z_resolution), quiet_floor, height + tc0 + j0,
                     quiet ? quiet + tc0 + j0 : nullptr, wrow + j0);
      if (htest_) std::copy(wrow + j0, wrow + j1, far + j0);
      return;
    }
    std::ptrdiff_t e = 0;
    for (std::ptrdiff_t j = 0; j < n; ++j) {
      if (!wrow[j]) continue;
      const detail::WindowFit f = rf.fit(e++);
      const std::ptrdiff_t c = tc0 + j;
      height[c] = f.ok ? f.height : detail::kNaN;
      far[j] = htest_ && (hm[c] & (kInPlane | kSCompact)) && detail::height_far(f, jparams_);
      if (quiet_floor >= 0.0 && (hm[c] & kInPlane) &&
          detail::quiet_plane(f.ok, f.height, f.n, f.l0, f.l1, f.l2, quiet_floor)) {
        quiet[c] |= detail::kHQuiet;  // (kHStale may be there: a removal above)
      }
    }
  });
  if (!htest_) return;
  for (std::ptrdiff_t c = 0; c < W; ++c) {
    if (far_row[c]) remove_height(row, c, 1);
  }
}

// The window of cell (row, col) with the classes of height pass `pass` (kNever: the final
// labels, for the heights), copied and handed to fit(sub-grid, classes, r, c) as a grid of its
// own (final_window_plane's window_plane reads it as labels).
template <typename T>
template <typename Fit>
void ProfileStream<T>::window_fit(std::int64_t row, std::ptrdiff_t col, int pass,
                                  Fit fit) noexcept {
  const std::ptrdiff_t W = width_, h = half_;
  const std::int64_t r0 = std::max<std::int64_t>(0, row - h);
  const std::int64_t r1 = std::min<std::int64_t>(pushed_ - 1, row + h);
  const std::ptrdiff_t c0 = std::max<std::ptrdiff_t>(0, col - h);
  const std::ptrdiff_t c1 = std::min<std::ptrdiff_t>(W - 1, col + h), nc = c1 - c0 + 1;
  const bool lines = pass != kNever;
  std::uint8_t* loc = local_.data();
  for (std::int64_t rr = r0; rr <= r1; ++rr) {
    const std::uint8_t* hm = hm_.data() + slot(rr) * W;
    const std::uint8_t* hs = hs_.data() + slot(rr) * W;
    for (std::ptrdiff_t cc = c0; cc <= c1; ++cc) {
      *loc++ = pass_class(hm[cc], hs[cc], pass, lines);
    }
  }
  // Rows r0..r1 are consecutive in memory (the ring's extension, see phys_).
  const GridView<T> sub{xyz_.data() + slot(r0) * W + c0, static_cast<std::ptrdiff_t>(r1 - r0 + 1),
                        nc, W, 1, phys_ * W};
  fit(sub, local_.data(), static_cast<std::ptrdiff_t>(row - r0), col - c0);
}

// The window fit of cell (row, col) over the classes of height pass `pass` (kNever: the final
// labels), directly (detail::direct_fit_by): for the few cells of a segment, and for the running
// sums' fits that cancellation spoils (detail::kRefitRatio). Reads the rows in place, so the
// threads of height pass 1 may call it.
template <typename T>
detail::WindowFit ProfileStream<T>::window_direct_fit(std::int64_t row, std::ptrdiff_t col,
                                                      int pass) const noexcept {
  const std::ptrdiff_t W = width_;
  const std::int64_t r0 = std::max<std::int64_t>(0, row - half_);
  const std::int64_t r1 = std::min<std::int64_t>(pushed_ - 1, row + half_);
  const bool lines = pass != kNever;
  const auto class_of = [&](std::ptrdiff_t rr, std::ptrdiff_t cc) -> std::uint8_t {
    const std::ptrdiff_t i = slot(r0 + rr) * W + cc;
    return pass_class(hm_[i], hs_[i], pass, lines);
  };
  // Rows r0..r1 are consecutive in memory (the ring's extension, see phys_).
  const GridView<T> g{xyz_.data() + slot(r0) * W, static_cast<std::ptrdiff_t>(r1 - r0 + 1), W, W,
                      1, phys_ * W};
  return detail::direct_fit_by(g, class_of, static_cast<std::ptrdiff_t>(row - r0), col, half_);
}

// Height pass `pass` >= 2 on `row`: the candidates whose window a removal of the pass before
// changed, fitted directly.
template <typename T>
void ProfileStream<T>::height_pass_row(std::int64_t row, int pass) noexcept {
  const std::ptrdiff_t W = width_, s = slot(row);
  const std::uint8_t bit = want_bit(pass);
  if (!(hrow_[s] & bit)) return;
  hrow_[s] = static_cast<std::uint8_t>(hrow_[s] & ~bit);
  std::uint8_t* hm = hm_.data() + s * W;
  const std::uint8_t* hs = hs_.data() + s * W;
  std::uint8_t* want = want_row_.data();
  for (std::ptrdiff_t c = 0; c < W; ++c) {
    const std::uint8_t b = hm[c];
    want[c] = static_cast<std::uint8_t>(((b & bit) != 0) & (hs[c] == kNever) &
                                        ((b & (kInPlane | kSCompact)) != 0));
    hm[c] = static_cast<std::uint8_t>(b & ~bit);
  }
  // Jacobi: every verdict of the row first (the removals below change later rows' windows only
  // through hs_, which this pass reads as ">= pass"); the edge test's quiet marks by the NORMAL
  // cells' new planes (SPEC "Edge test" step 1: a cell's last plane)
  const double quiet_floor = detail::quiet_plane_floor(jparams_);
  std::uint8_t* ep = eplane_.empty() ? nullptr : eplane_.data() + s * W;
  region_fits(row, pass, [&](std::ptrdiff_t c, const detail::WindowFit& f) {
    if (ep != nullptr && (hm[c] & kInPlane)) {
      const bool q = detail::quiet_plane(f.ok, f.height, f.n, f.l0, f.l1, f.l2, quiet_floor);
      ep[c] = static_cast<std::uint8_t>(q ? ep[c] | detail::kHQuiet : ep[c] & ~detail::kHQuiet);
    }
    if (detail::height_far(f, jparams_)) remove_height(row, c, pass);
  });
}

// A removal by height pass `pass`: the cell becomes ABNORMAL; the cells within h are re-fitted at
// the next pass and their pass-1 heights are stale.
template <typename T>
void ProfileStream<T>::remove_height(std::int64_t row, std::ptrdiff_t col, int pass) noexcept {
  const std::ptrdiff_t W = width_, h = half_, s = slot(row);
  labels_[s * W + col] = kAbnormal;
  hs_[s * W + col] = static_cast<std::uint8_t>(pass);
  const std::uint8_t bits =
      static_cast<std::uint8_t>(kSStale | (pass < passes_ ? want_bit(pass + 1) : 0));
  const std::ptrdiff_t c0 = std::max<std::ptrdiff_t>(0, col - h);
  const std::ptrdiff_t c1 = std::min<std::ptrdiff_t>(W - 1, col + h);
  for (std::int64_t rr = std::max<std::int64_t>(0, row - h);
       rr <= std::min<std::int64_t>(pushed_ - 1, row + h); ++rr) {
    std::uint8_t* hm = hm_.data() + slot(rr) * W;
    for (std::ptrdiff_t cc = c0; cc <= c1; ++cc) hm[cc] |= bits;
    hrow_[slot(rr)] |= bits & (kSWantEven | kSWantOdd);
    if (!eplane_.empty() && pass == passes_) {  // the last pass: no plane there is re-fitted
      std::uint8_t* ep = eplane_.data() + slot(rr) * W;
      for (std::ptrdiff_t cc = c0; cc <= c1; ++cc) ep[cc] |= detail::kHStale;
    }
  }
}

// The heights in the window of cell (row, col) are stale: fitted again when handed back.
template <typename T>
void ProfileStream<T>::mark_stale(std::int64_t row, std::ptrdiff_t col) noexcept {
  const std::ptrdiff_t W = width_, h = half_;
  const std::ptrdiff_t c0 = std::max<std::ptrdiff_t>(0, col - h);
  const std::ptrdiff_t c1 = std::min<std::ptrdiff_t>(W - 1, col + h);
  for (std::int64_t rr = std::max<std::int64_t>(0, row - h);
       rr <= std::min<std::int64_t>(pushed_ - 1, row + h); ++rr) {
    std::uint8_t* hm = hm_.data() + slot(rr) * W;
    for (std::ptrdiff_t cc = c0; cc <= c1; ++cc) hm[cc] |= kSStale;
  }
}

// The heights of `row` over its final window: the pass-1 height where no removal touched the
// window, else a direct fit (HeightMode::kAll); the window plane of each ABNORMAL cell, as
// batch detection computes it (kAbnormal).
template <typename T>
void ProfileStream<T>::final_row(std::int64_t row) noexcept {
  const std::ptrdiff_t W = width_, s = slot(row);
  const std::uint8_t* hm = hm_.data() + s * W;
  const std::uint8_t* lab = labels_.data() + s * W;
  double* height = height_.data() + s * W;
  if (params_.height_mode == HeightMode::kAbnormal) {
    for (std::ptrdiff_t c = 0; c < W; ++c) {
      height[c] = detail::kNaN;
      if (lab[c] != kAbnormal) continue;
      Plane pl;
      if (final_window_plane(row, c, &pl)) height[c] = pl.signed_distance(row_view(row)(0, c));
    }
    return;
  }
  if (!htest_ && !edge_) return;  // the pass-1 heights are final
  std::uint8_t* want = want_row_.data();
  for (std::ptrdiff_t c = 0; c < W; ++c) {  // branch-free: vectorised
    want[c] = static_cast<std::uint8_t>(((hm[c] & kSStale) != 0) & (lab[c] != kInvalid));
  }
  region_fits(row, kNever, [&](std::ptrdiff_t c, const detail::WindowFit& f) {
    height[c] = f.ok ? f.height : detail::kNaN;
  });
}

// The window fits of the cells of `row` marked in want_row_, over the classes of height pass
// `pass` (kNever: the final labels, without feature-line counts), handed to visit(col, fit) in
// ascending col. The wanted cells go in segments of at most kStrip columns: a segment's window
// rows are summed column by column (window_fits.hpp's row moments and row_fits, relative to
// its first wanted cell) when that reads fewer cells than fitting each window directly.
template <typename T>
template <typename Visit>
void ProfileStream<T>::region_fits(std::int64_t row, int pass, Visit visit) noexcept {
  const std::ptrdiff_t W = width_, h = half_, side = 2 * h + 1, plane = phys_ * W;
  const std::ptrdiff_t cap = std::min(W, kStrip), pad = h + 1;
  const std::int64_t r0 = std::max<std::int64_t>(0, row - h);
  const std::int64_t r1 = std::min<std::int64_t>(pushed_ - 1, row + h);
  const bool lines = pass != kNever;
  const std::uint8_t* want = want_row_.data();
  double* S = fit_buf_.data();
  double* Q = S + kMoments * cap;
  double* F = Q + 3 * cap;
  double* x = F + 4 * cap;  // one row's relative coordinates, 3 x span_
  std::uint8_t* okf = fit_flags_.data();
  std::uint8_t* redo = okf + cap;
  std::uint8_t* wrow = redo + cap;
  std::uint8_t* cl = region_cls_.data();
  for (std::ptrdiff_t c = 0; c < W;) {
    c = detail::next_nonzero(want, c, W);  // (most cells of a row are not wanted)
    if (c >= W) break;
    const std::ptrdiff_t ca = c, end = std::min(W, ca + kStrip);
    std::ptrdiff_t cb = ca, m = 0;
    for (std::ptrdiff_t q = ca; q < end; ++q) {
      if (want[q]) cb = q, ++m;
    }
    c = cb + 1;
    const std::ptrdiff_t seg = cb - ca + 1;
    if (m * side <= seg + 2 * h) {  // few cells: each window directly
      for (std::ptrdiff_t q = ca; q <= cb; ++q) {
        if (!want[q]) continue;
        visit(q, window_direct_fit(row, q, pass));
      }
      continue;
    }
    const std::ptrdiff_t C0 = std::max<std::ptrdiff_t>(0, ca - h);
    const std::ptrdiff_t C1 = std::min<std::ptrdiff_t>(W, cb + h + 1), nc = C1 - C0;
    const std::ptrdiff_t stride = nc + 2 * pad;
    double* cs = region_cs_.data();
    std::fill(cs, cs + kMoments * stride, 0.0);
    const GridView<T> g0{xyz_.data() + slot(row) * W, 1, W, W, 1, plane};
    const Eigen::Vector3d o = g0(0, ca);
    for (std::int64_t rr = r0; rr <= r1; ++rr) {
      const std::uint8_t* hm = hm_.data() + slot(rr) * W + C0;
      const std::uint8_t* hs = hs_.data() + slot(rr) * W + C0;
      for (std::ptrdiff_t j = 0; j < nc; ++j) {
        cl[j] = pass_class(hm[j], hs[j], pass, lines);
      }
      const GridView<T> g{xyz_.data() + slot(rr) * W, 1, W, W, 1, plane};
      detail::load_rel(g, 0, C0, nc, o.x(), o.y(), o.z(), x, x + span_, x + 2 * span_);
      detail::add_row_moments(cl, nc, x, x + span_, x + 2 * span_, 1.0, cs + pad, stride);
    }
    for (std::ptrdiff_t j = 0; j < seg; ++j) wrow[j] = want[ca + j];
    detail::load_rel(g0, 0, ca, seg, o.x(), o.y(), o.z(), Q, Q + cap, Q + 2 * cap);
    detail::row_fits(cs + pad + (ca - C0), stride, h, seg, cap, wrow, m, S, Q, F, okf, redo,
                     [&](std::ptrdiff_t j) { return window_direct_fit(row, ca + j, pass); },
                     [&](std::ptrdiff_t j, const detail::WindowFit& f) { visit(ca + j, f); });
  }
}

// The window plane of cell (row, col) over the final labels, as batch detection computes it
// (window_plane: the heights of HeightMode::kAbnormal, the defects' normals). False: none.
template <typename T>
bool ProfileStream<T>::final_window_plane(std::int64_t row, std::ptrdiff_t col,
                                          Plane* plane) noexcept {
  bool ok = false;
  window_fit(row, col, kNever, [&](const GridView<T>& g, const std::uint8_t* cls,
                                   std::ptrdiff_t r, std::ptrdiff_t cc) {
    // window_plane reads labels: NORMAL (0) where the class is kInPlane, else INVALID
    for (std::size_t i = 0; i < local_.size(); ++i) {
      local_[i] = cls[i] == kInPlane ? kNormal : kInvalid;
    }
    ok = detail::window_plane(g, local_.data(), r, cc, half_, plane) == PlaneStatus::kOk;
  });
  return ok;
}

// The members defined here (stream.cpp instantiates the others).
#define MIEM_STREAM_STAGES(T)                                                               \
  template void ProfileStream<T>::init_stages();                                           \
  template void ProfileStream<T>::reset_stages() noexcept;                                 \
  template void ProfileStream<T>::run_stages(bool) noexcept;                               \
  template bool ProfileStream<T>::final_window_plane(std::int64_t, std::ptrdiff_t,          \
                                                     Plane*) noexcept;                       \
  template void ProfileStream<T>::mark_stale(std::int64_t, std::ptrdiff_t) noexcept;         \
  template bool ProfileStream<T>::feature_line(std::int64_t, std::ptrdiff_t) const noexcept;
MIEM_STREAM_STAGES(float)
MIEM_STREAM_STAGES(double)
#undef MIEM_STREAM_STAGES

}  // namespace miem
