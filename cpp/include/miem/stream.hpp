// Streaming MIEM for line scanners (METHOD.md section 8): profiles go in one at a time, final
// labels come out a fixed lag later, equal to batch detection on the same rows. Nothing is
// allocated after construction and no call throws after construction.
#pragma once

#include <cstddef>
#include <cstdint>
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

  /// True when a row was handed back.
  bool ready() const noexcept { return index >= 0; }
};

/// The default parameters of a stream: the recommended preset (DetectParams{}) without the
/// fields a stream does not implement yet, which it rejects (check_stream_params): theta0_auto,
/// the height test (height_abs, height_k), edge_extent, the edge test (edge_k) and
/// min_step_auto (a stream cannot see the whole scan: give min_step as a length, e.g.
/// auto_min_step() of a first scan). So the stream runs the recommended angle test (theta0 90,
/// scales {1, 2}); batch detect_organized with these parameters gives the same labels.
DetectParams stream_default_params();

/// Checks the parameters of a stream without throwing: params.check(), then what a stream does
/// not implement (theta0_auto, height_abs / height_k > 0, edge_extent > 0, edge_k > 0,
/// min_step_auto), width >= 1 and
/// max_iterations <= 254 (the per-cell pass counter is one byte).
Status check_stream_params(std::ptrdiff_t width, const DetectParams& params) noexcept;

/// Streaming organized detector: rows are laser profiles, pushed as they arrive.
///
/// Labels are exactly those of batch detection (detect_organized, docs/SPEC.md) on the grid of
/// all rows pushed so far, for every input, not only for short defects. A cell's judgment reads
/// the rows within R = max(scales) + max_gap (+ max_reach with min_step) of its own, and each
/// further pass (a removal re-judges the cells whose rays meet it) widens that by R; after
/// max_iterations passes nothing further away can matter. So row i is final once row
/// i + L has arrived, with the lag
///
///     L = max_iterations * R   (defaults: 10 * (1 + 1) = 20 profiles).
///
/// The passes run as a wavefront: when row n arrives, pass p runs on row n - p R, pass 1 on
/// every finite cell, later passes only on the cells whose rays meet a cell removed by the pass
/// before (as the batch detector does). A lower max_iterations shortens the lag (most scans
/// settle in 2-3 passes) and equals batch detection with that max_iterations.
///
/// Memory: the last (max_iterations + 1) * R + 1 rows are kept in a ring (plus 2 R rows that
/// repeat its first rows, so that the 2 R + 1 rows around any row form one strided GridView);
/// about 27 * 3200 * 3 * 8 bytes = 2.1 MB for double profiles of 3200 points with the defaults.
/// Heights, flags, angles and defects are not computed here (a height needs window / 2 more
/// rows of lag): group the ABNORMAL labels downstream, or run OrganizedDetector on the rows of
/// interest. (Batch detection also refuses a grid of fewer than 3 finite points; a stream
/// simply labels what it gets.)
///
/// Speed: pass 1 runs a vectorised filter over the whole row (SSE2, or AVX2 where the CPU has
/// it) and judges exactly only the few cells that might be flagged; cells next to a dropout go
/// through the batch detector's judge. bench/RESULTS.md has the figures.
///
/// Bad profiles never stop or corrupt the stream: a profile of the wrong width or null data is
/// rejected with a status (nothing is pushed); a profile with no finite point is taken as a row
/// of dropouts (INVALID labels), with StatusCode::kEmptyProfile so the caller knows.
///
/// `T` is the storage type of the coordinates (float or double); every computation is in double.
/// Not thread-safe: one stream per scanner thread.
template <typename T = double>
class ProfileStream {
 public:
  /// A stream of profiles of `width` points. Throws std::invalid_argument with the message of
  /// check_stream_params (a bad or unsupported field, width < 1, max_iterations > 254).
  /// `params.window` and `height_mode` only shape heights, which a stream does not report;
  /// `num_threads` is not used (one stream runs on its caller's thread).
  /// Use nothrow::make_stream in code built without exceptions.
  explicit ProfileStream(std::ptrdiff_t width, DetectParams params = stream_default_params());

  /// Points per profile.
  std::ptrdiff_t width() const noexcept { return width_; }
  /// The lag L: push n hands back row n - L.
  int lag() const noexcept { return lag_; }
  /// The reach R of one judgment, in rows.
  int reach() const noexcept { return reach_; }
  /// The parameters.
  const DetectParams& params() const noexcept { return params_; }
  /// Profiles accepted since construction or reset.
  std::int64_t rows_pushed() const noexcept { return pushed_; }
  /// Rows handed back since construction or reset.
  std::int64_t rows_emitted() const noexcept { return emitted_; }
  /// True after flush() until reset().
  bool finished() const noexcept { return finished_; }

  /// Pushes one profile (`profile.size` must equal width(); any strides; non-finite points are
  /// dropouts). When it completes a row (every push after the first L does), `*out` describes
  /// that row, else `out->ready()` is false. Never allocates or throws.
  /// Returns kOk; kEmptyProfile (pushed as a row of dropouts); kWrongWidth or kInvalidInput
  /// (rejected: the stream is unchanged); kFinished after flush().
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
  void run_pass(std::int64_t row, int pass) noexcept;
  void pass1_fast(std::int64_t row) noexcept;
  std::uint8_t exact_label(std::int64_t row, std::ptrdiff_t col, std::uint32_t bits) const noexcept;
  void remove(std::int64_t row, std::ptrdiff_t col, int pass) noexcept;

  std::ptrdiff_t width_;
  DetectParams params_;
  int reach_ = 0;   // R
  int passes_ = 0;  // max_iterations
  int lag_ = 0;     // L = passes_ * reach_
  std::ptrdiff_t ring_ = 0;  // rows kept: L + R + 1
  std::ptrdiff_t phys_ = 0;  // rows stored: ring_ + 2R, rows in slots [0, 2R) again at the end,
                             // so that any 2R + 1 consecutive rows form one strided GridView
  int max_scale_ = 1;
  bool fast_ = false;  // pass 1 may use the vectorised kernel
  double cos0_ = 0.0;

  std::vector<T> xyz_;               // 3 planes (x, y, z) of phys_ rows of width_
  std::vector<std::uint8_t> state_;  // phys_ rows: 0 dropout, p removed at pass p,
                                     // 255 alive; "usable at pass p" is state >= p
  std::vector<std::uint8_t> cand_;   // ring_ rows: bit (p & 1) = re-judge at pass p
  std::vector<std::uint8_t> row_cand_;  // ring_ rows: same bits, "the row has any"
  std::vector<std::uint8_t> labels_;    // ring_ rows
  std::vector<std::uint8_t> level_;     // ring_ rows: passes done
  std::vector<std::uint32_t> bits_;  // width_: pass-1 filter, bit per (direction, scale) that
                                     // may be flagged; bit 31: a neighbour is missing
  std::int64_t pushed_ = 0, emitted_ = 0;
  bool finished_ = false;
};

namespace nothrow {
/// Constructs a ProfileStream in `*out` after checking the arguments; never throws.
template <typename T>
Status make_stream(std::ptrdiff_t width, const DetectParams& params,
                   std::optional<ProfileStream<T>>* out) noexcept;
}  // namespace nothrow

}  // namespace miem
