// Streaming MIEM for line scanners (METHOD.md section 8): profiles go in one at a time, final
// labels come out a fixed lag later, equal to batch detection on the same rows. Nothing is
// allocated after construction and no call throws after construction.
#pragma once

#include <cstddef>
#include <cstdint>
#include <limits>
#include <optional>
#include <vector>

#include "miem/nothrow.hpp"
#include "miem/organized.hpp"
#include "miem/views.hpp"

namespace miem {

/// One finished profile (row) handed back by ProfileStream::push or ProfileStream::flush.
struct StreamRow {
  std::int64_t index = -1;               ///< row number (0 = first profile pushed); -1: none
  const std::uint8_t* labels = nullptr;  ///< `width` Label values; valid until the next call
                                         ///< of push, flush or reset
  const double* height = nullptr;        ///< `width` heights (docs/SPEC.md "Height"; NaN where
                                         ///< none), valid as long as `labels`
  /// The defects this call made final (docs/SPEC.md "Streaming": 8-connected ABNORMAL groups,
  /// summarised as detect_organized summarises them, reported by the first call that hands
  /// back a row after the group, i.e. once no later profile can change it), in the order of
  /// their first cell; `id` numbers the stream's defects in the order reported. `indices` are
  /// flat r * width + c with r counted from the first profile. Valid as long as `labels`.
  const Defect* defects = nullptr;
  std::size_t n_defects = 0;

  /// True when a row was handed back.
  bool ready() const noexcept { return index >= 0; }
};

namespace detail {
struct WindowFit;  // window_fits.hpp

/// min_step "auto" (docs/SPEC.md "min_step='auto'") decided in resumable steps over rows that
/// arrive one at a time: the streaming detector's form (auto_min_step.cpp), so that no push
/// pays the whole decision. Exact medians by radix selection over the doubles' 64-bit
/// patterns, 16 bits a round: the value batch detection's auto_min_step resolves on the same
/// rows. Round 0 (the high 16 bits) takes each row as it arrives (add_row), close() ends it,
/// rounds 1-3 visit the rows again a few at a time (step). Allocates only in init().
template <typename T>
class MinStepSelection {
 public:
  /// Buffers for rows of `width` adjacent cells, their coordinates `coord_stride` apart.
  void init(std::ptrdiff_t width, std::ptrdiff_t coord_stride);
  /// A new set of rows.
  void reset() noexcept;
  /// Row n - 1 is in (rows[0 .. n) hold rows 0 .. n - 1 and stay valid until done()): round 0
  /// takes the rows whose quantities are complete (those before row n - 2).
  void add_row(const T* const* rows, std::ptrdiff_t n) noexcept;
  /// No more rows: round 0 takes the last ones and ends; the middle ranks are known.
  void close(const T* const* rows) noexcept;
  /// Rounds 1-3: visits at most `budget` rows; true once the value is known.
  bool step(const T* const* rows, std::ptrdiff_t budget) noexcept;
  /// True after close().
  bool closed() const noexcept { return round_ >= 1; }
  /// True once the value is known.
  bool done() const noexcept { return round_ > 3; }
  /// The row visits rounds 1-3 still need (3 per row before close()).
  std::ptrdiff_t visits_left() const noexcept;
  /// The min_step (scan units; -1: off), once done().
  double value() const noexcept { return value_; }
  /// The z noise sigma of the same medians (SPEC "z_noise"; -1: none), once done().
  double noise() const noexcept { return noise_; }

 private:
  void finish() noexcept;
  std::vector<std::uint32_t> hist_;  // round 0: 4 x 2^16 counters; rounds 1-3: 8 x 2^16
  std::vector<std::uint8_t> fin_;    // finite flags of three consecutive rows (a ring)
  std::ptrdiff_t width_ = 0, ks_ = 1, rows_ = 0, next_ = 0;
  int round_ = 0;                    // 0: rows coming in; 1-3: the rounds after; 4: done
  std::size_t count_[4] = {};        // values per quantity
  std::size_t rank_[8] = {};         // per pick (2 per quantity): the rank within its prefix
  std::uint64_t prefix_[8] = {};     // ... the bits found so far
  double value_ = -1.0, noise_ = -1.0;
};
}  // namespace detail

/// The default parameters of a stream: the default preset, DetectParams{} (angle test, height
/// test with compact EDGE groups, edge test, min_step "auto", heights).
DetectParams stream_default_params();

/// The lag L of a stream with these parameters (profiles between pushing a row and getting it
/// back final), with R = max(scales) + max_gap (+ max_reach with min_step, given or "auto"),
/// h = window / 2, P = max_iterations, E = edge_extent + max_gap, r = edge_window / 2:
///     L = P R + E + (P + 1) h   with the height test,   L = P R + h   without;
///     L = max(H + max(2 r, q), h) + (P - 1) r + h   with the edge test, H = P R + E + P h
///         (P R without the height test), q = max(r, h) (0 without the height test): its step
///         9 runs row by row r rows behind the height passes, pass 1 r rows behind it (and q
///         behind the height passes: its quiet cells), each pass r rows behind the one before;
///     L = max(L, 256)   with min_step_auto, z_resolution_auto or z_noise_auto (the rows
///                       they are decided from must be in).
/// Defaults: (10 * 35 + 13 + 10 * 10 + 2 * 7) + 9 * 7 + 10 = 550 (256 with min_step off, 230
/// with z_resolution and z_noise off too).
/// Assumes valid parameters.
long long stream_lag(const DetectParams& params) noexcept;

/// Checks the parameters of a stream without throwing: params.check(), then what a stream does
/// not implement (theta0_auto), width >= 1,
/// max_iterations <= 254 (the per-cell pass counter is one byte) and a lag below 2^20 profiles.
Status check_stream_params(std::ptrdiff_t width, const DetectParams& params) noexcept;

/// Streaming organized detector: rows are laser profiles, pushed as they arrive.
///
/// Labels are exactly those of batch detection (detect_organized, docs/SPEC.md) on the grid of
/// all rows pushed so far, for every input, not only for short defects; heights equal batch
/// heights up to rounding (both are the same window plane, summed in another order). The
/// stages run as a wavefront over a ring of rows (docs/SPEC.md "Streaming"): when row n
/// arrives,
///   - angle pass p runs on row n - p R (R = max(scales) + max_gap, + max_reach with
///     min_step: the rows one judgment reads; each pass widens that by R);
///   - row n - P R is then final for the angle test; its compact EDGE groups are known E rows
///     later (a group is compact when its bounding box is at most E = edge_extent cells, so E
///     rows on either side decide it);
///   - height pass 1 runs on row n - P R - E - h by running window sums (h = window / 2), pass
///     p on row n - P R - E - p h, only on the cells within h of a cell the pass before removed;
///   - the edge test's step 9 runs on row n - H - r (H: the rows after which the height
///     passes' labels are final), edge pass 1 on row n - H - max(2 r, q) (q = max(r, h) with
///     the height test: its quiet cells read the height passes' removals within h; and at
///     most on row n - h, so that the heights its removals make stale are all in), pass p r
///     rows behind pass p - 1, row by row with batch detection's own per-row
///     routines on per-tile integral images kept as rings of 2 r + 2 rows: its verdicts are
///     those of the whole grid bit for bit (docs/SPEC.md "Streaming");
///   - heights are final h rows after the last height pass (and the last edge pass).
///   - with min_step "auto" (SPEC "min_step='auto'": the 256 rows from the first row with a
///     finite cell), the stages wait from that row on until it is decided: each of those
///     rows is counted as it arrives (round 0 of the exact selection, no allocation), rounds
///     1-3 visit the 256 rows again 16 a push (48 pushes at the defaults), then the waiting
///     pushes' stages catch up, at least 3 rows a push, by the push that hands back the first
///     of those rows (docs/SPEC.md "Streaming"): no push carries the whole decision.
/// So row i is final once row i + L has arrived, L = stream_lag(params) (550 profiles with
/// the defaults, 256 with min_step off (230 with z_resolution and z_noise off too), 473 without
/// the edge
/// test; 20 + 10 with preset
/// "paper"). Each cell keeps the
/// pass that removed it (angle, height, edge), so a judgment at pass p sees exactly the cells of pass p - 1 even where rows around it have run
/// pass p already. A lower max_iterations (most scans settle in 2-3 passes) or edge_extent
/// shortens the lag, and equals batch detection with those parameters.
///
/// Memory: the last L + h + 2 rows (about L + 2 h; with the edge test L + 64 + edge_window + 2;
/// 304 more with min_step "auto": 927 rows at the defaults) are kept in a ring, plus
/// max(2 R, 2 h) rows that repeat its first rows (2 r with the edge test if more), so that the
/// rows around any row form one strided GridView; with the edge test also (P + 1)
/// ceil(width / 128) rings of integral images (11 x (2 r + 2) x (129 + 2 r) doubles and the
/// column sums), and pass 1's row-kernel ring (2 d + 2 rows of width + 2 d cells, 32 bytes each;
/// d = 16 with min_step, else the largest scale + 1): about 202 MB (measured: resident growth
/// on construction) for double profiles of 3200 points with the defaults (101 MB with min_step
/// off, 98 MB without the edge test), plus the cells of the open defects (a pool
/// reserved for 16 rows' worth of cells, which grows, once, only for more). Defects come with
/// the rows (StreamRow::defects) once final; flags and angles are not reported. (Batch
/// detection also refuses a grid of fewer than 3 finite points; a stream simply labels what it
/// gets.)
///
/// Speed: without min_step, pass 1 runs a vectorised filter over the whole row (SSE2, or AVX2
/// where the CPU has it) and judges exactly only the few cells that might be flagged. Next to
/// a dropout, with max_gap >= 1 and the smallest scale at most max_gap (the default), the
/// filter takes the cell one step further, as the neighbour search does, and the batch
/// detector's judge takes only the cells with no neighbour within those two steps; otherwise
/// the judge takes every cell next to a dropout, and where more than 0.5 % of the rows around
/// are dropouts the stream runs batch detection's vectorised row kernel instead (neighbour
/// searches across dropouts and to s min_step in SIMD lanes), as it always does with min_step,
/// the judge taking only the searches it cannot finish. A later pass re-judges a cell only when its
/// last verdict read a cell removed at the pass before (with min_step: 4 bytes per kept cell,
/// how far each verdict read along each ray). bench/RESULTS.md has the figures.
///
/// Bad profiles never stop or corrupt the stream: a profile of the wrong width or null data is
/// rejected with a status (nothing is pushed); a profile with no finite point is taken as a row
/// of dropouts (INVALID labels), with StatusCode::kEmptyProfile so the caller knows.
///
/// `T` is the storage type of the coordinates (float or double); every computation is in double.
/// Not thread-safe: one stream per scanner thread (a push may use more threads itself:
/// DetectParams::num_threads).
template <typename T = double>
class ProfileStream {
 public:
  /// A stream of profiles of `width` points. Throws std::invalid_argument with the message of
  /// check_stream_params (a bad or unsupported field, width < 1, max_iterations > 254).
  /// `params.num_threads` (0: all available) splits a push's column work among threads: angle
  /// pass 1's filter or row kernel, an angle pass's judgments of a row, the edge passes' tile
  /// columns and height pass 1's strips (and its column sums); one thread below 256 points per
  /// profile, at most one per 128. The results never depend on it. The threads are OpenMP's
  /// (a team per calling thread, kept between pushes: no allocation).
  /// Use nothrow::make_stream in code built without exceptions.
  explicit ProfileStream(std::ptrdiff_t width, DetectParams params = stream_default_params());

  /// Points per profile.
  std::ptrdiff_t width() const noexcept { return width_; }
  /// The lag L: push n hands back row n - L (stream_lag(params())).
  int lag() const noexcept { return lag_; }
  /// The reach R of one judgment, in rows (with min_step "auto": as if it were on).
  int reach() const noexcept { return reach_; }
  /// The min_step the stream judges with (scan units; -1: off). With min_step_auto: -1 until
  /// decided (min_step_decided()), then the value batch detection resolves on the rows pushed.
  double min_step() const noexcept { return min_step_; }
  /// False while min_step, z_resolution or z_noise "auto" waits for its rows (SPEC
  /// "min_step='auto'", "z_resolution", "z_noise"), else true.
  bool min_step_decided() const noexcept { return !ms_wait_; }
  /// The z_resolution the height and edge tests use (scan units; -1: off). With
  /// z_resolution_auto: -1 until decided (min_step_decided()), then the value batch detection
  /// resolves on the rows pushed.
  double z_resolution() const noexcept { return jparams_.z_resolution; }
  /// The z_noise in use (SPEC "z_noise"): -1 while "auto" waits for its sample rows, or off.
  double z_noise() const noexcept { return jparams_.z_noise; }
  /// The parameters.
  const DetectParams& params() const noexcept { return params_; }
  /// Profiles accepted since construction or reset.
  std::int64_t rows_pushed() const noexcept { return pushed_; }
  /// Cells edge pass 1 has judged since construction or reset(): the NORMAL and EDGE cells
  /// that are not quiet (docs/SPEC.md "Edge test" step 1). The edge test's work; 0 without it.
  std::int64_t edge_candidates() const noexcept { return ecand_; }
  /// Rows handed back since construction or reset.
  std::int64_t rows_emitted() const noexcept { return emitted_; }
  /// True after flush() until reset().
  bool finished() const noexcept { return finished_; }

  /// Pushes one profile (`profile.size` must equal width(); any strides; non-finite points are
  /// dropouts). When it completes a row (every push after the first L does), `*out` describes
  /// that row, else `out->ready()` is false. Never allocates or throws.
  /// Returns kOk; kEmptyProfile (pushed as a row of dropouts); kWrongWidth or kInvalidInput
  /// (rejected: the stream is unchanged; kInvalidInput also for a finite coordinate of
  /// magnitude above kCoordinateMax, SPEC "Numbers"); kFinished after flush().
  Status push(const PointsView<T>& profile, StreamRow* out) noexcept;

  /// Pushes a dense profile: `size` points of x, y, z, contiguous.
  Status push(const T* xyz, std::ptrdiff_t size, StreamRow* out) noexcept {
    return push(PointsView<T>{xyz, size, 3, 1}, out);
  }

  /// Ends the stream and hands back the rows still pending, one per call, oldest first: returns
  /// true and fills `*out` while rows remain, then false. The last rows are judged with the end
  /// of the stream as the grid border, exactly as batch detection does. Never allocates or throws.
  bool flush(StreamRow* out) noexcept;

  /// Starts a new stream (a new part) with the same width and parameters; keeps the memory.
  void reset() noexcept;

 private:
  std::ptrdiff_t slot(std::int64_t row) const noexcept {
    return static_cast<std::ptrdiff_t>(row % ring_);
  }
  void use_min_step(double min_step) noexcept;
  void decide() noexcept;
  void min_step_row(std::int64_t row) noexcept;
  void min_step_finish() noexcept;
  void catch_up(std::int64_t last) noexcept;
  bool stages_behind() const noexcept { return (ms_wait_ && ms_first_ >= 0) || ms_next_ >= 0; }
  void advance(std::int64_t row) noexcept;
  void run_pass(std::int64_t row, int pass) noexcept;
  void pass1_fast(std::int64_t row) noexcept;
  // Ring offset (cells) of the cell `step` cells from (row, column 0) along direction k, on
  // side `sign` (-1 or +1): pass 1's neighbour of column c is at this offset + c.
  std::ptrdiff_t step_offset(std::int64_t row, int k, std::ptrdiff_t step,
                             int sign) const noexcept;
  std::uint8_t exact_label(std::int64_t row, std::ptrdiff_t col, std::uint32_t bits) const noexcept;
  const std::int64_t* pass1_kernel(std::int64_t row) noexcept;
  std::ptrdiff_t pass1_depth(bool min_step) const noexcept;
  void remove(std::int64_t row, std::ptrdiff_t col, int pass) noexcept;
  // The stages after the angle passes (stream_stages.cpp): each advances its own next row up
  // to the last row it may run on (all pushed rows once the stream is flushed).
  void init_stages();
  void reset_stages() noexcept;
  void run_stages(bool to_end) noexcept;
  void angle_final_row(std::int64_t row) noexcept;
  void compact_row(std::int64_t row) noexcept;
  void height_pass1_row(std::int64_t row) noexcept;
  void height_pass_row(std::int64_t row, int pass) noexcept;
  void final_row(std::int64_t row) noexcept;
  void remove_height(std::int64_t row, std::ptrdiff_t col, int pass) noexcept;
  void sums_add_row(int set, std::int64_t in, double sign, std::int64_t out) noexcept;
  std::ptrdiff_t fit_doubles() const noexcept;  // one thread's share of fit_buf_
  std::ptrdiff_t fit_strip_doubles() const noexcept;  // its S, Q and F
  bool final_window_plane(std::int64_t row, std::ptrdiff_t col, Plane* plane) noexcept;
  void mark_stale(std::int64_t row, std::ptrdiff_t col) noexcept;
  GridView<T> row_view(std::int64_t row) const noexcept {
    return GridView<T>{xyz_.data() + slot(row) * width_, 1, width_, width_, 1, phys_ * width_};
  }
  // The edge test (stream_edges.cpp): each pass row by row.
  void init_edges();
  void reset_edges() noexcept;
  void edge_push_row(std::int64_t row) noexcept;
  void run_edges(bool to_end) noexcept;
  void edge_row(std::int64_t row, int pass) noexcept;
  bool restore_candidates(std::int64_t row) noexcept;
  void quiet_candidates(std::int64_t row, const std::uint8_t* win, std::int64_t a0) noexcept;
  bool feature_line(std::int64_t row, std::ptrdiff_t col) const noexcept;
  const double* edge_images(int pass, std::ptrdiff_t tile, std::int64_t band,
                            std::int64_t upto, std::int64_t from, std::uint8_t* labs) noexcept;
  void edge_labels(std::int64_t row, int pass, std::ptrdiff_t c0, std::ptrdiff_t c1,
                   std::uint8_t* out) const noexcept;
  // Defects (stream_defects.cpp).
  void init_defects();
  void reset_defects() noexcept;
  void defect_row(std::int64_t row) noexcept;
  std::int32_t find_slot(std::int32_t s) noexcept;
  std::int32_t merge_slots(std::int32_t a, std::int32_t b) noexcept;
  void report(std::int32_t root) noexcept;
  template <typename Fit>
  void window_fit(std::int64_t row, std::ptrdiff_t col, int pass, Fit fit) noexcept;
  detail::WindowFit window_direct_fit(std::int64_t row, std::ptrdiff_t col,
                                      int pass) const noexcept;
  template <typename Visit>
  void region_fits(std::int64_t row, int pass, Visit visit) noexcept;

  std::ptrdiff_t width_;
  DetectParams params_;
  int reach_ = 0;   // R
  int passes_ = 0;  // max_iterations
  // Threads of a push's column work (params.num_threads; 1 below 256 points, at most one per
  // 128 columns: an edge-test tile column or a height strip each).
  int threads_ = 1;
  int alag_ = 0;    // A = passes_ * reach_: rows after which the angle labels are final
  int lag_ = 0;     // L (stream_lag)
  int half_ = 0;    // h = window / 2
  int extent_ = 0;  // E = edge_extent with the height test, else 0
  int link_gap_ = 0;  // G = max_gap with the height test (EDGE groups link across G dropouts)
  bool htest_ = false;  // the height test is on
  bool edge_ = false;   // the edge test is on
  int lagh_ = 0;        // rows behind the newest at which the height passes' labels are final
  bool sums_ = false;   // height pass 1 / heights run by running window sums (kAll or the test)
  std::ptrdiff_t ring_ = 0;  // rows kept: the longest look-back + 2
  std::ptrdiff_t ext_ = 0;   // max(2R, 2h, 2r with the edge test)
  std::ptrdiff_t phys_ = 0;  // rows stored: ring_ + ext_, rows in slots [0, ext_) again at the
                             // end, so that any ext_ + 1 consecutive rows form one GridView
  int max_scale_ = 1;
  bool fast_ok_ = false;  // the scales allow pass 1's vectorised kernel (without min_step)
  bool fast_ = false;     // pass 1 may use the vectorised kernel
  bool p1_gap_ = false;   // its neighbour at step s + 1 stands in for a dropout at s
  std::ptrdiff_t fedge_ = 0;  // rows and columns within fedge_ of the border: CellJudge
  // Pass 1 runs batch detection's row kernel (src/pass1_row.hpp) with min_step, and without it
  // next to dropouts, on its own ring of converted rows: each row converted once, when the
  // first row within p1_depth_ of it that runs the kernel is judged (rows are judged in order).
  bool p1_kernel_ = false;          // min_step on and the kernel's ring kept: every row
  std::vector<std::int32_t> p1_miss_;  // ring_ rows: the row's dropouts
  detail::RowScratch p1_;           // the ring (2 p1_depth_ + 2 padded rows)
  std::ptrdiff_t p1_depth_ = 0;     // its depth (steps a search reads in the kernel)
  std::int64_t p1_next_ = 0;        // the next row to convert
  std::vector<std::uint8_t> p1_lab_;  // width_: the kernel's labels of the row
  // width_ each: an angle pass's cells to judge on the push's threads, and their verdicts
  std::vector<std::ptrdiff_t> judge_cols_;
  std::vector<std::uint8_t> judge_out_;
  // min_step "auto" (SPEC "min_step='auto'"): decided once the kAutoMinStepRows rows from the
  // first row with a finite cell are in; the stages wait for it (the rows are kept).
  bool ms_auto_ = false;         // params_.min_step_auto
  bool sel_ = false;             // the selection runs: min_step or z_noise "auto"
  bool sample_ = false;          // min_step, z_resolution or z_noise "auto": the stages wait for
                                 // its rows
  bool ms_wait_ = false;         // not decided yet
  std::int64_t ms_first_ = -1;   // the first row with a finite cell (-1: none yet)
  double min_step_ = -1.0;       // the min_step in use (-1: off)
  int mark_reach_ = 0;           // R of one judgment with that min_step
  DetectParams jparams_;         // params_ with min_step and z_resolution resolved: the judges'
  double zq_ = std::numeric_limits<double>::infinity();  // z_resolution "auto": smallest step
  std::vector<std::uint64_t> zkeys_;  // its pooled z values' keys (the first cells of the
                                      // sample), zn_ of them; as many again: the sort's scratch
  std::ptrdiff_t zn_ = 0;             // (detail::z_gap_cells)
  std::vector<const T*> ms_rows_;       // the rows it reads
  detail::MinStepSelection<T> ms_sel_;  // its selection, a few rows per push
  std::int64_t ms_next_ = -1;           // decided: the next row the stages catch up on (-1:
                                        // caught up, or not decided yet)
  std::vector<double> nan_row_;         // heights of a row handed back while waiting
  double cos0_ = 0.0;

  // The ring's buffers (rows of ring_ or phys_, tens of MB at the default's lag) in memory from
  // detail::allocate_cells (cell_memory.cpp): on huge pages where the kernel offers them, so a
  // push's reads of rows of several ages do not each walk the tables of 4 KiB pages.
  template <typename U>
  using Ring = std::vector<U, detail::CellAllocator<U>>;
  Ring<T> xyz_;                      // 3 planes (x, y, z) of phys_ rows of width_
  Ring<std::uint8_t> state_;         // phys_ rows: 0 dropout, p removed at pass p,
                                     // 255 alive; "usable at pass p" is state >= p
  Ring<std::uint8_t> cand_;          // ring_ rows: bit (p & 1) = re-judge at pass p
  std::vector<std::uint8_t> row_cand_;  // ring_ rows: same bits, "the row has any"
  Ring<std::uint8_t> labels_;           // ring_ rows
  std::vector<std::uint8_t> level_;     // ring_ rows: passes done
  Ring<std::uint8_t> ray_;         // with min_step (given or "auto"), ring_ rows x 4: per cell
                                   // and direction the farthest step its last verdict read
                                   // (CellJudge's reach), so that a removal marks only the
                                   // cells whose verdict it can change
  bool use_ray_ = false;           // min_step on and ray_ kept
  std::vector<std::uint32_t> bits_;  // width_: pass-1 filter, bit per (direction, scale) that
                                     // may be flagged; bit 31: a neighbour is missing
  std::int64_t pushed_ = 0, emitted_ = 0;
  bool finished_ = false;

  // Height test and heights (stream_stages.cpp).
  Ring<std::uint8_t> hm_;          // ring_ rows: window classes and stage bits (kS* there)
  Ring<std::uint8_t> hs_;          // ring_ rows: height pass that removed the cell, 255 none
  std::vector<std::uint8_t> hrow_; // ring_ rows: want bits of the row (any cell)
  Ring<double> height_;            // ring_ rows
  std::int64_t next_final_ = 0, next_compact_ = 0, next_out_ = 0;
  std::vector<std::int64_t> next_pass_;  // [p]: next row of height pass p (1..passes_)
  std::vector<std::int64_t> queue_;      // EDGE grouping, (2E + 1) * width cells
  std::vector<std::uint8_t> local_;      // one window's classes / labels
  // Running window sums of height pass 1: column strips of kStrip cells, each with its own
  // origin, two sets (the current and the next origin band, kBand rows apart).
  std::ptrdiff_t strips_ = 0, span_ = 0, stride_ = 0, band_ = 0;
  std::vector<double> cs_;      // 2 sets x strips x kMoments x stride_
  std::vector<double> origin_;  // 2 sets x strips x 3
  std::vector<std::uint8_t> has_origin_;  // 2 sets x strips
  std::int64_t set_first_[2] = {0, 0};  // first row added to each set
  int cur_ = 0;                           // the set in use
  std::int64_t sums_next_ = 0;            // next row to add
  std::vector<double> fit_buf_;           // S, Q, F and one row's relative coordinates
  std::vector<std::uint8_t> fit_flags_;   // ok, redo, wanted (one strip each)
  // (fit_buf_ and fit_flags_: one set per thread, sums_add_row's and height_pass1_row's)
  std::vector<std::uint8_t> far_row_;     // height pass 1: the row's cells to remove
  std::vector<std::uint8_t> want_row_;    // region_fits: the cells of a row to fit
  std::vector<double> region_cs_;         // region_fits: a segment's column sums
  std::vector<std::uint8_t> region_cls_;  // region_fits: one row's classes

  // Edge test (stream_edges.cpp).
  Ring<std::uint8_t> eold_;          // ring_ rows: 0, or 1 + the label the edge test changed
  Ring<std::uint8_t> epass_;         // ring_ rows: the edge pass that removed the cell, 0 none
  Ring<std::uint8_t> etodo_;         // ring_ rows: bit (p & 1) = judge at edge pass p >= 2
  std::vector<std::uint8_t> etodo_row_;  // ring_ rows: same bits, "the row has any"
  // Pass 1's quiet cells (edge_quiet.hpp): ring_ rows of kHQuiet where height pass 1's plane
  // is quiet and kHStale where a height removal lies within h; the window counts
  // (QuietCounts::over) of the rows [eq_first_, eq_next_) at the start of pass 1.
  Ring<std::uint8_t> eplane_;
  std::vector<std::int32_t> equiet_;
  std::int64_t eq_first_ = 0, eq_next_ = 0;
  std::int64_t ecand_ = 0;  // edge_candidates()
  // Per (set, tile column): a ring of ek_ integral-image rows of edge_test.hpp's layout
  // (kEdgeMoments planes of ek_ rows of estride_) and the column sums; the band it was built
  // for and the next grid row to add. Sets: pass 1 even / odd bands, then pass p >= 2 at p.
  std::ptrdiff_t etiles_ = 0, ek_ = 0, estride_ = 0, eper_ = 0, ebands_ = 0;
  Ring<double> eimg_;
  std::vector<std::int64_t> eimg_band_, eimg_next_;
  std::vector<std::int64_t> enext_;      // [p]: next row of edge pass p (1..passes_; 0: step 9)
  std::vector<double> eorg_;             // per (band mod ebands_, tile column): the origin
  std::vector<std::uint8_t> eorg_ok_;    // ... found
  std::vector<std::ptrdiff_t> eorg_missing_;  // per band slot: tiles without an origin yet
  std::vector<std::uint8_t> eones_, elab_row_, emark_, etd_;  // one row each
  std::vector<std::uint8_t> elab_img_;  // one row per thread (edge_images' labels)
  // Pass 1's labels (edge_labels) of the last 2 r + 1 rows, each row twice (2 r + 1 rows
  // apart, so that a judgment's window is contiguous), and the next row to add: a row's are
  // final when it first enters a pass-1 window.
  std::vector<std::uint8_t> elab1_;
  std::int64_t elab1_next_ = 0;
  std::vector<std::ptrdiff_t> etile_list_;  // a pass's tile columns with a candidate
  // Per tile column: the last row pass 1 had a candidate in it (-1: none), and a list of the
  // tile columns whose next band pass 1 builds alongside (edge_row)
  std::vector<std::int64_t> ehot_;
  std::vector<std::ptrdiff_t> ehot_list_;
  // Defects (stream_defects.cpp): open groups as union-find slots over the cells of the last
  // row handed back; their cells in a pool of singly linked members.
  struct DefectSlot {
    std::int32_t parent = 0, head = -1, tail = -1;
    std::int64_t count = 0, last_row = -1, peak_idx = -1;
    double peak_h = 0.0;
    Eigen::Vector3d normal = Eigen::Vector3d::Zero();  // window-plane normal at the peak
    bool touches = false, closed = false;
  };
  std::vector<std::int32_t> dprev_, dcur_;  // per column: slot of the ABNORMAL cell, or -1
  std::vector<std::int32_t> dcols_prev_, dcols_cur_;  // their columns holding a slot, ascending
  std::vector<DefectSlot> slots_;
  std::vector<std::int32_t> slot_free_, dead_, closed_;
  std::vector<std::int64_t> mem_idx_;
  std::vector<double> mem_pt_, mem_h_;
  std::vector<std::int32_t> mem_next_;
  std::int32_t mem_free_ = -1;
  std::vector<std::int32_t> order_;     // a closing group's members in index order
  std::vector<double> sorted_pt_, sorted_h_;
  std::vector<Defect> done_;            // the defects of this call: done_[0, n_done_)
  std::size_t n_done_ = 0;
  std::int64_t defects_reported_ = 0;
};

namespace nothrow {
/// Constructs a ProfileStream in `*out` after checking the arguments; never throws.
template <typename T>
Status make_stream(std::ptrdiff_t width, const DetectParams& params,
                   std::optional<ProfileStream<T>>* out) noexcept;
}  // namespace nothrow

}  // namespace miem
