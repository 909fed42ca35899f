// The stream's edge test (docs/SPEC.md "Edge test", "Streaming"), row by row with batch
// detection's own per-row routines (edge_test.hpp: edge_image_row builds a tile's integral
// images one row at a time, edge_judge_row gives a row's verdicts), so its cells come out bit
// for bit as batch edge_passes on the whole grid:
//  - pass p runs on a row once pass p - 1 is final r rows below it (r = edge_window / 2), pass 1
//    once the height passes are final r rows below it and the rows within h = window / 2 are
//    pushed (a removal marks the heights within h stale);
//  - a tile's origin (its first finite cell, row-major) is found as rows are pushed; a pass
//    needs a tile's images only at a candidate, a finite cell, so the origin is known by then;
//  - per pass and tile column, the tile's integral images are kept as a ring of the 2 r + 2 image
//    rows a judgment reads, and built from the tile's first image row (r rows above the tile)
//    when the pass first has a candidate in the tile: the same sums, in the same order, as
//    batch's images over the whole tile;
//  - each cell keeps the pass that removed it (epass_), so a judgment at pass p sees exactly
//    the labels after pass p - 1, and a removal at pass p marks the cells within r for pass
//    p + 1 (batch's todo).
// Removals go into the labels at once; the heights whose window lost a NORMAL cell are fitted
// again at the end (as batch heights() does).
#include <algorithm>
#include <cstring>

#include "edge_quiet.hpp"
#include "edge_test.hpp"
#include "edge_verdict.hpp"
#include "stages.hpp"
#include "miem/stream.hpp"
#include "parallel.hpp"
#include "window_fits.hpp"

namespace miem {

namespace {
constexpr std::uint8_t kEdgeRemoved = 254;  // hs_: removed by the edge test
constexpr std::ptrdiff_t kTR = detail::kEdgeTileRows, kTC = detail::kEdgeTileCols;
constexpr int kQ = detail::kEdgeMoments;
}  // namespace

template <typename T>
void ProfileStream<T>::init_edges() {
  if (!edge_) return;
  const std::ptrdiff_t W = width_, r = params_.edge_window / 2;
  etiles_ = (W + kTC - 1) / kTC;
  const std::ptrdiff_t EC = std::min(W, kTC + 2 * r);
  ek_ = 2 * r + 2;
  estride_ = EC + 1;
  eper_ = kQ * ek_ * estride_ + kQ * EC;  // image ring + column sums of one (pass, tile column)
  eold_.assign(static_cast<std::size_t>(ring_ * W), 0);
  epass_.assign(static_cast<std::size_t>(ring_ * W), 0);
  etodo_.assign(static_cast<std::size_t>(ring_ * W), 0);
  etodo_row_.assign(static_cast<std::size_t>(ring_), 0);
  if (htest_) {
    eplane_.assign(static_cast<std::size_t>(ring_ * W), 0);
    equiet_.assign(static_cast<std::size_t>(detail::QuietCounts::ints(W, r)), 0);
  }
  // pass 1 has two sets (even and odd bands: the next band's images are built alongside), and
  // step 9 (pass 0 here) one after pass passes_'s
  const std::ptrdiff_t sets = static_cast<std::ptrdiff_t>(passes_) + 2;
  eimg_.assign(static_cast<std::size_t>(sets * etiles_ * eper_), 0.0);
  eimg_band_.assign(static_cast<std::size_t>(sets * etiles_), -1);
  eimg_next_.assign(static_cast<std::size_t>(sets * etiles_), 0);
  enext_.assign(static_cast<std::size_t>(passes_) + 1, 0);
  ebands_ = ring_ / kTR + 3;
  eorg_.assign(static_cast<std::size_t>(ebands_ * etiles_ * 3), 0.0);
  eorg_ok_.assign(static_cast<std::size_t>(ebands_ * etiles_), 0);
  eorg_missing_.assign(static_cast<std::size_t>(ebands_), 0);
  eones_.assign(static_cast<std::size_t>(W), 1);
  // A pass's tile columns are independent (Jacobi: each reads the labels at the start of the
  // pass and writes its own images and verdicts), so they split among the threads.
  elab_img_.assign(static_cast<std::size_t>(threads_ * W), kInvalid);
  etile_list_.assign(static_cast<std::size_t>(etiles_), 0);
  ehot_.assign(static_cast<std::size_t>(etiles_), -1);
  ehot_list_.assign(static_cast<std::size_t>(etiles_), 0);
  elab_row_.assign(static_cast<std::size_t>((2 * r + 1) * W), kInvalid);
  elab1_.assign(static_cast<std::size_t>(2 * (2 * r + 1) * W), kInvalid);
  emark_.assign(static_cast<std::size_t>(W), 0);
  etd_.assign(static_cast<std::size_t>(W), 0);
}

template <typename T>
void ProfileStream<T>::reset_edges() noexcept {
  if (!edge_) return;
  std::fill(eimg_band_.begin(), eimg_band_.end(), -1);
  std::fill(enext_.begin(), enext_.end(), 0);
  eq_first_ = eq_next_ = 0;
  ecand_ = 0;
  elab1_next_ = 0;
  std::fill(ehot_.begin(), ehot_.end(), -1);
}

// At push: the tile origins of the row's band (the first finite cell of each tile, row-major).
template <typename T>
void ProfileStream<T>::edge_push_row(std::int64_t row) noexcept {
  const std::ptrdiff_t W = width_, s = slot(row) * W;
  const std::ptrdiff_t b = static_cast<std::ptrdiff_t>((row / kTR) % ebands_);
  std::uint8_t* ok = eorg_ok_.data() + b * etiles_;
  if (row % kTR == 0) {
    std::fill(ok, ok + etiles_, std::uint8_t{0});
    eorg_missing_[static_cast<std::size_t>(b)] = etiles_;
  }
  std::memset(eold_.data() + s, 0, static_cast<std::size_t>(W));
  std::memset(epass_.data() + s, 0, static_cast<std::size_t>(W));
  std::memset(etodo_.data() + s, 0, static_cast<std::size_t>(W));
  if (htest_) std::memset(eplane_.data() + s, 0, static_cast<std::size_t>(W));
  etodo_row_[static_cast<std::size_t>(slot(row))] = 0;
  if (eorg_missing_[static_cast<std::size_t>(b)] == 0) return;
  const GridView<T> g = row_view(row);
  for (std::ptrdiff_t t = 0; t < etiles_; ++t) {
    if (ok[t]) continue;
    for (std::ptrdiff_t c = t * kTC; c < std::min(W, (t + 1) * kTC); ++c) {
      if (!g.finite(0, c)) continue;
      const Eigen::Vector3d o = g(0, c);
      double* org = eorg_.data() + (b * etiles_ + t) * 3;
      org[0] = o.x(), org[1] = o.y(), org[2] = o.z();
      ok[t] = 1;
      --eorg_missing_[static_cast<std::size_t>(b)];
      break;
    }
  }
}

// The labels edge pass `pass` reads (those after pass - 1) of `row`, columns c0 .. c1 - 1.
template <typename T>
void ProfileStream<T>::edge_labels(std::int64_t row, int pass, std::ptrdiff_t c0,
                                   std::ptrdiff_t c1, std::uint8_t* out) const noexcept {
  const std::ptrdiff_t s = slot(row) * width_;
  const std::uint8_t* __restrict lab = labels_.data() + s;
  const std::uint8_t* __restrict ep = epass_.data() + s;
  const std::uint8_t* __restrict eo = eold_.data() + s;
  std::uint8_t* __restrict o = out;
  const std::uint8_t p = static_cast<std::uint8_t>(pass);
  for (std::ptrdiff_t c = c0; c < c1; ++c) {  // branch-free, so that it vectorises
    const std::uint8_t keep = static_cast<std::uint8_t>(-(ep[c] >= p));  // 0xff: the old label
    const std::uint8_t old = static_cast<std::uint8_t>(eo[c] - 1);
    o[c] = static_cast<std::uint8_t>((lab[c] & ~keep) | (old & keep));
  }
}

// The integral images of edge pass `pass`, tile column t, band `band`, with the image rows through
// `upto` (the sums over the grid rows before it): started at the tile's first image row when
// the set holds another band, then one grid row at a time. Image rows before `from` are never
// read (the set's judgments are of rows from + r on): their grid rows add to the column sums
// only, as batch's rows before its first candidate row (a pass p >= 2, or a tile whose first
// candidate comes late in the band, catches up without the row prefixes). `labs`: a row of
// scratch (the calling thread's).
template <typename T>
const double* ProfileStream<T>::edge_images(int pass, std::ptrdiff_t t, std::int64_t band,
                                            std::int64_t upto, std::int64_t from,
                                            std::uint8_t* labs) noexcept {
  const std::ptrdiff_t W = width_, r = params_.edge_window / 2;
  const std::ptrdiff_t C0 = t * kTC, C1 = std::min(W, C0 + kTC);
  const std::ptrdiff_t f0 = std::max<std::ptrdiff_t>(0, C0 - r), f1 = std::min(W, C1 + r);
  const std::ptrdiff_t EC = f1 - f0, L = estride_, plane = ek_ * L;
  const std::int64_t e0 = std::max<std::int64_t>(0, band * kTR - r);
  const std::ptrdiff_t set = pass == 0 ? passes_ + 1 : (pass == 1 ? (band & 1) : pass);
  const std::ptrdiff_t id = set * etiles_ + t;
  double* img = eimg_.data() + id * eper_;
  double* col = img + kQ * plane;
  const double* org = eorg_.data() + ((band % ebands_) * etiles_ + t) * 3;
  const Eigen::Vector3d o(org[0], org[1], org[2]);
  std::int64_t& next = eimg_next_[static_cast<std::size_t>(id)];
  if (eimg_band_[static_cast<std::size_t>(id)] != band) {  // the tile's first image row
    eimg_band_[static_cast<std::size_t>(id)] = band;
    std::fill(col, col + kQ * EC, 0.0);
    for (int q = 0; q < kQ; ++q) std::fill(img + q * plane, img + q * plane + EC + 1, 0.0);
    next = e0;
  }
  for (; next < upto; ++next) {  // add grid row `next`: image row next + 1
    // a catch-up's next row (a row view of its own: load_rel's next-row prefetch does not see it)
    if (next + 1 < upto) detail::prefetch_planes(row_view(next + 1).data, phys_ * W, f0, f1);
    edge_labels(next, std::max(pass, 1), f0, f1, labs);  // (step 9 changes no image)
    double* const out = next + 1 < from ? nullptr : img + ((next + 1 - e0) % ek_) * L;
    detail::edge_image_row(row_view(next), 0, labs, f0, f1, o, col, EC, out, plane);
  }
  return img;
}

// Edge pass `pass` on `row` (pass 0: step 9, the ABNORMAL cells beside a feature line that
// fit a clean side with a return back to EDGE): tile by tile, the images brought down to the
// row's judgment (started at the tile's first image row when the pass first needs them), the
// verdicts, then the removals.
template <typename T>
void ProfileStream<T>::edge_row(std::int64_t row, int pass) noexcept {
  const std::ptrdiff_t W = width_, s = slot(row), r = params_.edge_window / 2;
  const std::uint8_t bit = static_cast<std::uint8_t>(1u << (pass & 1));
  const std::uint8_t* todo = eones_.data();
  const std::int64_t H = pushed_;
  if (pass > 1) {
    if (!(etodo_row_[static_cast<std::size_t>(s)] & bit)) return;
    const std::uint8_t* et = etodo_.data() + s * W;
    for (std::ptrdiff_t c = 0; c < W; ++c) etd_[static_cast<std::size_t>(c)] = (et[c] & bit) != 0;
    todo = etd_.data();
  } else if (pass == 0) {
    if (!restore_candidates(row)) return;
    todo = etd_.data();
  }
  const std::int64_t band = row / kTR, R0 = band * kTR;
  const std::int64_t e0 = std::max<std::int64_t>(0, R0 - r);
  const std::ptrdiff_t b = static_cast<std::ptrdiff_t>(band % ebands_);
  const std::int64_t upto = std::min<std::int64_t>(H, row + r + 1);  // image rows through upto
  // The rows within r as one grid (the ring repeats its first 2 r rows after its end) and
  // their labels at the start of the pass, which the verdicts read
  const std::int64_t a0 = std::max<std::int64_t>(0, row - r);
  const std::ptrdiff_t grow = static_cast<std::ptrdiff_t>(row - a0);
  const GridView<T> gw{xyz_.data() + slot(a0) * W, static_cast<std::ptrdiff_t>(upto - a0), W, W,
                       1, phys_ * W};
  std::uint8_t* win = elab_row_.data();
  if (pass == 1) {
    // Pass 1 moves down one row a push: each row's labels are read once, when the row enters
    // the window (final then: the height passes and step 9 are done r rows below, and the
    // view leaves out pass 1's own removals), and kept for the next 2 r judgments.
    const std::ptrdiff_t M = 2 * r + 1;
    for (std::int64_t a = std::max(elab1_next_, a0); a < upto; ++a) {
      std::uint8_t* d = elab1_.data() + (a % M) * W;
      edge_labels(a, 1, 0, W, d);
      std::memcpy(d + M * W, d, static_cast<std::size_t>(W));
    }
    elab1_next_ = std::max(elab1_next_, upto);
    win = elab1_.data() + (a0 % M) * W;
  } else {
    // (step 9 reads no label of the window: its candidates are todo's, its verdict the fits)
    for (std::int64_t a = a0; pass > 0 && a < upto; ++a) {
      edge_labels(a, pass, 0, W, win + (a - a0) * W);
    }
  }
  const std::uint8_t* lab = win + grow * W;
  if (pass == 1) {
    if (htest_) {  // (from the labels just read: pass 1's, the rows within r)
      quiet_candidates(row, win, a0);
      todo = etd_.data();
    }
    std::ptrdiff_t n = 0;
    for (std::ptrdiff_t c = 0; c < W; ++c) {
      n += todo[c] & ((lab[c] == kNormal) | (lab[c] == kEdge));
    }
    ecand_ += n;
  }
  std::uint8_t* mark = emark_.data();
  std::ptrdiff_t* tiles = etile_list_.data();
  std::ptrdiff_t n_tiles = 0;  // the tile columns with a candidate
  for (std::ptrdiff_t t = 0; t < etiles_; ++t) {
    const std::ptrdiff_t C0 = t * kTC, C1 = std::min(W, C0 + kTC);
    bool any = false;
    for (std::ptrdiff_t c = C0; c < C1 && !any; ++c) {
      any = todo[c] && (pass == 0 || lab[c] == kNormal || lab[c] == kEdge);
    }
    if (any) tiles[n_tiles++] = t;
    if (any && pass == 1) ehot_[static_cast<std::size_t>(t)] = row;
  }
  // Pass 1 builds the next band's images alongside over the last 2 r rows before it (its first
  // image row is r rows above the band, final once pass 1 is 2 r rows above it), one row per
  // push instead of 2 r + 1 at its first candidate, in the tile columns where it had a
  // candidate within the last r rows (once begun, to the band's start): a region of candidates
  // (the cells near a flagged cell, a feature line, a rough surface) is at least 2 r + 1 rows
  // tall and goes on into the next band. The other tile columns catch up when they first have
  // a candidate, as a tile whose first candidate comes late in a band does: most of them never
  // do, since quiet cells (SPEC "Edge test" step 1) leave few candidates on smooth surface.
  // (Built alongside in every tile column, 14 of every 64 pushes of 3200 points took about half
  // as much CPU time again, and set the stream's p99.) Its origins are known once a finite cell
  // of the tile is in (else the tile has no candidate).
  const std::int64_t R0n = R0 + kTR, e0n = R0n - r;
  const bool next_band = pass == 1 && upto > e0n && R0n < H;
  const std::ptrdiff_t bn = static_cast<std::ptrdiff_t>((band + 1) % ebands_);
  std::ptrdiff_t* const hot = ehot_list_.data();
  std::ptrdiff_t n_hot = 0;
  if (next_band) {
    const std::ptrdiff_t set = (band + 1) & 1;  // pass 1's set of the next band
    for (std::ptrdiff_t t = 0; t < etiles_; ++t) {
      const std::size_t id = static_cast<std::size_t>(set * etiles_ + t);
      const bool begun = eimg_band_[id] == band + 1;
      hot[n_hot] = t;
      n_hot += begun || row - ehot_[static_cast<std::size_t>(t)] <= r;
    }
  }
  // Work item i on thread `tid`: the verdicts of tile column tiles[i] (i < n_tiles), else the
  // next band's images of tile column hot[i - n_tiles].
  // min_step etc. as decided, and the precision of T
  const detail::EdgeTol et = detail::edge_tol(jparams_, detail::edge_precision<T>());
  const auto tile = [&](std::ptrdiff_t i, int tid) {
    std::uint8_t* labs = elab_img_.data() + tid * W;
    if (i >= n_tiles) {
      const std::ptrdiff_t t = hot[i - n_tiles];
      if (eorg_ok_[static_cast<std::size_t>(bn * etiles_ + t)]) {
        edge_images(1, t, band + 1, upto, 0, labs);
      }
      return;
    }
    const std::ptrdiff_t t = tiles[i];
    const std::ptrdiff_t C0 = t * kTC, C1 = std::min(W, C0 + kTC);
    const double* img = edge_images(pass, t, band, upto, a0, labs);  // image rows a0 on
    const std::ptrdiff_t f0 = std::max<std::ptrdiff_t>(0, C0 - r);
    const double* org = eorg_.data() + (b * etiles_ + t) * 3;
    const Eigen::Vector3d o(org[0], org[1], org[2]);
    std::fill(mark + C0, mark + C1, std::uint8_t{0});
    const detail::EdgeImages im{img, ek_ * estride_, estride_, e0, ek_, f0};
    // (no band cache, unlike batch: kept per tile column over a whole row of tiles it is 11 MB
    // at 3200 points, read back r + 1 pushes later from beyond the L2 cache; without it a
    // default push took about 8 % less CPU time, though it runs more instructions)
    detail::edge_judge_row(gw, grow, row, H, C0, C1, im, o, r, et, win, todo, mark, nullptr,
                           pass == 0 ? detail::EdgeJudgment::kFitsGround
                                     : detail::EdgeJudgment::kVerdict);
  };
  const std::ptrdiff_t n_work = n_tiles + n_hot;
  detail::parallel_items(threads_, n_work, tile);
  bool any_mark = false;
  for (std::ptrdiff_t i = 0; i < n_tiles && !any_mark; ++i) {
    const std::ptrdiff_t C0 = tiles[i] * kTC, C1 = std::min(W, C0 + kTC);
    for (std::ptrdiff_t c = C0; c < C1 && !any_mark; ++c) any_mark = mark[c] != 0;
  }
  if (pass > 1) {
    std::uint8_t* et = etodo_.data() + s * W;
    for (std::ptrdiff_t c = 0; c < W; ++c) et[c] &= static_cast<std::uint8_t>(~bit);
    etodo_row_[static_cast<std::size_t>(s)] &= static_cast<std::uint8_t>(~bit);
  }
  if (!any_mark) return;
  if (pass == 0) {  // step 9: back to EDGE (no image, height or later candidate changes)
    std::uint8_t* labs = labels_.data() + s * W;
    for (std::ptrdiff_t c = 0; c < W; ++c) {
      if (todo[c] && mark[c]) labs[c] = kEdge;
    }
    return;
  }
  const std::uint8_t nbit = static_cast<std::uint8_t>(1u << ((pass + 1) & 1));
  const std::int64_t a1 = std::min<std::int64_t>(H - 1, row + r);
  std::uint8_t* labs = labels_.data() + s * W;
  std::uint8_t* eo = eold_.data() + s * W;
  std::uint8_t* ep = epass_.data() + s * W;
  std::uint8_t* hs = hs_.data() + s * W;
  for (std::ptrdiff_t c = 0; c < W; ++c) {
    // mark is only written in tiles with a candidate: read it there only
    if (!(todo[c] && (lab[c] == kNormal || lab[c] == kEdge)) || !mark[c]) continue;
    const std::uint8_t before = labs[c];
    labs[c] = kAbnormal;
    eo[c] = static_cast<std::uint8_t>(before + 1);
    ep[c] = static_cast<std::uint8_t>(pass);
    hs[c] = kEdgeRemoved;  // out of the final window classes
    // a NORMAL cell left the windows around it: their heights are fitted again at the end
    if (before == kNormal) mark_stale(row, c);
    if (pass < passes_) {  // the cells within r are judged again at the next pass
      const std::ptrdiff_t b0 = std::max<std::ptrdiff_t>(0, c - r), b1 = std::min(W - 1, c + r);
      for (std::int64_t a = a0; a <= a1; ++a) {
        std::uint8_t* et = etodo_.data() + slot(a) * W;
        for (std::ptrdiff_t x = b0; x <= b1; ++x) et[x] |= nbit;
        etodo_row_[static_cast<std::size_t>(slot(a))] |= nbit;
      }
    }
  }
}

// Step 9's candidates of `row` into etd_: its ABNORMAL cells with a feature-line EDGE cell
// among their 8 neighbours (the height test's kLine; without it, EDGE after the angle passes).
// Returns whether there is one.
template <typename T>
bool ProfileStream<T>::restore_candidates(std::int64_t row) noexcept {
  const std::ptrdiff_t W = width_;
  const std::uint8_t* lab = labels_.data() + slot(row) * W;
  std::uint8_t* td = etd_.data();
  const auto line = [this](std::int64_t a, std::ptrdiff_t b) { return feature_line(a, b); };
  bool any = false;
  for (std::ptrdiff_t c = 0; c < W; ++c) {
    const bool near = lab[c] == kAbnormal && detail::beside_line(line, row, c, pushed_, W);
    td[c] = near ? 1 : 0;
    any = any || near;
  }
  return any;
}

// Pass 1's candidates of `row` into etd_: every cell but the quiet ones (edge_quiet.hpp), from
// the window counts of the rows within r at the start of pass 1 and the height passes' marks
// (eplane_). `win` holds those labels of rows a0 .. row + r (edge_row's); a row leaves the
// counts as it came in (pass 1 reads its labels after step 9, which is done on rows r ahead of
// pass 1's: a row's step 9 turned its ABNORMAL cells EDGE before the row came in).
template <typename T>
void ProfileStream<T>::quiet_candidates(std::int64_t row, const std::uint8_t* win,
                                        std::int64_t a0) noexcept {
  const std::ptrdiff_t W = width_, r = params_.edge_window / 2;
  std::fill(etd_.begin(), etd_.end(), std::uint8_t{1});
  // the window's rows of the grid, [lo, hi): the rows below are all pushed (called at the end
  // of the stream for the last rows; the grid ends at its last pushed row then)
  const std::int64_t lo = std::max<std::int64_t>(0, row - r);
  const std::int64_t hi = std::min<std::int64_t>(pushed_, row + r + 1);
  const detail::QuietCounts qc = detail::QuietCounts::over(equiet_.data(), W, r);
  const auto at = [&](std::int64_t x) { return win + (x - a0) * W; };  // x in [a0, row + r]
  if (eq_next_ <= lo || eq_first_ > lo) {  // nothing of the window held: afresh
    qc.clear();
    eq_first_ = eq_next_ = lo;
  }
  std::uint8_t* labs = elab_img_.data();  // (a row of scratch: the tiles run after this)
  for (; eq_first_ < lo; ++eq_first_) {  // (above the window: no longer in win)
    edge_labels(eq_first_, 1, 0, W, labs);
    qc.add(labs, -1);
  }
  for (; eq_next_ < hi; ++eq_next_) qc.add(at(eq_next_), 1);
  // (the rows below the row are not judged yet: their labels are as they came in)
  qc.drop(at(row), at(row + 1), hi - row - 1, eplane_.data() + slot(row) * W,
          detail::kHQuiet | detail::kHStale, detail::kHQuiet, etd_.data());
}

// Runs the edge passes as far as their inputs are final (all rows at the end of the stream).
template <typename T>
void ProfileStream<T>::run_edges(bool to_end) noexcept {
  const std::int64_t last = pushed_ - 1, r = params_.edge_window / 2;
  const std::int64_t ready = to_end ? last : last - lagh_;  // height-final through this row
  // step 9 (pass 0): the height passes final r rows below (its sub-windows; the feature lines
  // of the rows beside it are final before)
  for (std::int64_t& y = enext_[0]; y <= last; ++y) {
    if (!to_end && y + r > ready) break;
    edge_row(y, 0);
  }
  for (std::int64_t& y = enext_[1]; y <= last; ++y) {
    if (!to_end) {
      // step 9 done r rows below (the labels a judgment reads); the rows within h pushed (a
      // removal marks their heights stale)
      if (y + r >= enext_[0] || y + half_ > last) break;
      // the quiet test's marks final (the height passes' removals within h: within 2 r above,
      // at the defaults)
      if (htest_ && y + detail::quiet_half(r, half_) > ready) break;
    }
    edge_row(y, 1);
  }
  for (int p = 2; p <= passes_; ++p) {
    const std::int64_t lim = to_end ? last : enext_[static_cast<std::size_t>(p - 1)] - 1 - r;
    for (std::int64_t& y = enext_[static_cast<std::size_t>(p)]; y <= lim; ++y) edge_row(y, p);
  }
}

#define MIEM_STREAM_EDGES(T)                                                                 \
  template void ProfileStream<T>::init_edges();                                             \
  template void ProfileStream<T>::reset_edges() noexcept;                                   \
  template void ProfileStream<T>::edge_push_row(std::int64_t) noexcept;                     \
  template void ProfileStream<T>::run_edges(bool) noexcept;
MIEM_STREAM_EDGES(float)
MIEM_STREAM_EDGES(double)
#undef MIEM_STREAM_EDGES

}  // namespace miem
