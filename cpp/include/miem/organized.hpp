// MIEM on organized scans (rows = laser profiles): the four-direction angle test, iteration,
// local heights and defects. The exact rules are in docs/SPEC.md.
#pragma once

#include <cstddef>
#include <cstdint>
#include <limits>
#include <optional>
#include <memory>
#include <new>
#include <string>
#include <utility>
#include <vector>

#include <Eigen/Core>

#include "miem/params.hpp"
#include "miem/plane.hpp"
#include "miem/views.hpp"

namespace miem {

namespace detail {
/// Per-thread buffers of the row kernel (structure-of-arrays copies of a few rows).
struct RowScratch {
  std::vector<double> xyz;
  std::vector<std::int64_t> ok;    ///< 64-bit lanes beside the doubles: no packing in the kernel
  std::vector<std::uint64_t> okbits;  ///< `ok` packed, a bit per padded column (pass1_row.hpp)
  std::vector<double> best;
  std::vector<std::int64_t> bits;  ///< per cell: available / flagged directions, slow, near
  // with min_step (min_step_skip.hpp): a row's speeds, the unusable cells before each padded
  // column, and per chunk of columns the largest speed and the unusable cells it may skip
  std::vector<double> speed, chunk_speed;
  std::vector<std::int64_t> gaps_before, chunk_gaps;
  // batch pass 1: the finiteness of a row of another thread's block (sized with the rows),
  // and the cells this thread's scalar judge decides once every row's finiteness is known
  std::vector<std::uint8_t> fin;
  std::vector<std::int64_t> judge;
  void resize(std::ptrdiff_t rows, std::ptrdiff_t cols) {
    const auto n = static_cast<std::size_t>(cols);
    xyz.resize(static_cast<std::size_t>(rows) * 3 * n);
    ok.resize(static_cast<std::size_t>(rows) * n);
    okbits.resize(static_cast<std::size_t>(rows) * (n / 64 + 2));
    best.resize(2 * n);
    bits.resize(n);
    fin.resize(n);
  }
};

/// Per-thread buffers of the window-plane sweep.
struct FitScratch {
  std::vector<double> buf;
  std::vector<std::uint8_t> flags;
  std::vector<std::ptrdiff_t> tiles;  ///< per tile: wanted cells, last row, end column (thread 0's)
};

/// Memory for the per-cell buffers below (cpp/src/cell_memory.cpp): blocks of 2 MiB or more are
/// 2 MiB-aligned and advised as huge-page candidates (Linux MADV_HUGEPAGE, as NumPy advises its
/// large arrays), so a new detector's first touch of a buffer costs one page fault per 2 MiB, not
/// one per 4 KiB; smaller blocks come from operator new. Freed blocks go back as usual.
void* allocate_cells(std::size_t bytes);
void free_cells(void* p, std::size_t bytes) noexcept;

/// An allocator whose resize() leaves new cells unwritten (default-initialised) in memory from
/// allocate_cells: the per-cell buffers below are first written by the stages' parallel loops, so
/// a new detector's pages are touched by all its threads, not zeroed first by one (miem.detect
/// builds one per call).
template <typename T>
struct CellAllocator : std::allocator<T> {
  template <typename U>
  struct rebind {
    using other = CellAllocator<U>;
  };
  CellAllocator() = default;
  template <typename U>
  CellAllocator(const CellAllocator<U>&) noexcept {}
  T* allocate(std::size_t n) {
    if (n > std::numeric_limits<std::size_t>::max() / sizeof(T)) throw std::bad_array_new_length();
    return static_cast<T*>(allocate_cells(n * sizeof(T)));
  }
  void deallocate(T* p, std::size_t n) noexcept { free_cells(p, n * sizeof(T)); }
  template <typename U>
  void construct(U* p) noexcept {
    ::new (static_cast<void*>(p)) U;
  }
  template <typename U, typename... A>
  void construct(U* p, A&&... a) {
    ::new (static_cast<void*>(p)) U(std::forward<A>(a)...);
  }
};
/// One byte per cell (or a few), not initialised by resize().
using CellBytes = std::vector<std::uint8_t, CellAllocator<std::uint8_t>>;

/// The work buffers of one detector, kept between runs (same-size runs do not allocate).
struct Workspace {
  CellBytes usable;  ///< angle passes: bit 0 usable, bit 1 candidate; bit 2 seen
  CellBytes reach;   ///< angle passes with min_step: 4 per cell, rays read
  CellBytes cls;     ///< window sums: kInPlane (NORMAL) / kLine (feature line)
  CellBytes hmask;   ///< height stages: compact, want, fresh, mark bits
  std::vector<std::int64_t> fresh, candidates, queue;
  std::vector<double> height_scratch, survey;
  std::vector<std::uint64_t> zkeys;  ///< z_resolution "auto": the pooled z values' sort keys
  std::vector<double> edge_sums;     ///< edge test: integral images of the support moments
  CellBytes edge_flags;  ///< edge test: candidates and marks of a pass
  std::vector<RowScratch> rows;      ///< per thread
  std::vector<FitScratch> fits;      ///< per thread
  std::vector<Moments> plane_rows;
};
}  // namespace detail

/// Point labels (uint8 in every output).
enum Label : std::uint8_t {
  kNormal = 0,    ///< on the surface
  kAbnormal = 1,  ///< flagged in every available direction (or isolated): grind / discard
  kEdge = 2,      ///< flagged in some directions only: a designed feature edge; never ground
  kInvalid = 3,   ///< non-finite coordinates (dropout)
};

/// Defect kinds.
enum class DefectKind : std::uint8_t { kProtrusion = 0, kPit = 1, kIsolated = 2 };

/// "protrusion", "pit" or "isolated".
const char* to_string(DefectKind kind) noexcept;

/// One connected group of ABNORMAL cells (8-connected).
struct Defect {
  int id = 0;                                ///< rank by |peak_height| (0 = largest)
  std::vector<std::int64_t> indices;         ///< flat cell indices r * cols + c, ascending
  Eigen::Vector3d centroid = Eigen::Vector3d::Zero();
  Eigen::Vector3d normal = Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN());
  double peak_height = 0.0;                  ///< signed, largest magnitude (NaN if none)
  double mean_height = 0.0;                  ///< NaN if no member has a height
  double extent = 0.0;                       ///< diameter in the tangent plane
  DefectKind kind = DefectKind::kProtrusion;
};

/// Caller-owned output buffers, each rows * cols, row-major. `labels` is required; the others may
/// be null when not wanted (height is needed for defects and is then kept internally).
struct OrganizedOutput {
  std::uint8_t* labels = nullptr;
  std::uint8_t* flags = nullptr;     ///< bit k: direction k flagged (0 along, 1 across, 2, 3 diag)
  double* angle_deg = nullptr;       ///< smallest angle seen, NaN where none
  double* height = nullptr;          ///< signed height over the local plane, NaN where none
};

/// What a detection run returns besides the per-cell buffers.
struct DetectSummary {
  int iterations = 0;                ///< angle passes plus height passes
  double theta0_deg = 0.0;           ///< the threshold used (differs from params with auto)
  double min_step = -1.0;            ///< the min_step used (< 0: off; from the grid with auto)
  double z_resolution = -1.0;        ///< the z_resolution used (< 0: off; from the grid with auto)
  double z_noise = -1.0;             ///< the z_noise used (< 0: off; from the grid with auto)
  std::optional<Plane> plane;        ///< the MIEM plane (eigen fit of non-ABNORMAL points)
  std::vector<Defect> defects;       ///< ordered by |peak_height| descending
};

/// Everything, owned (convenience for callers that do not manage buffers).
struct DetectResult {
  std::ptrdiff_t rows = 0, cols = 0;
  std::vector<std::uint8_t> labels, flags;
  std::vector<double> angle_deg, height;
  DetectSummary summary;
};

/// Reusable organized detector: keeps its work buffers between runs, so repeated runs on grids of
/// the same size do not allocate except for the defect list.
class OrganizedDetector {
 public:
  /// Throws std::invalid_argument on bad parameters.
  explicit OrganizedDetector(DetectParams params);

  const DetectParams& params() const { return params_; }

  /// Detect on `grid` writing into `out`. Throws std::invalid_argument when the grid is empty,
  /// has fewer than 3 finite points, or `out.labels` is null, and CoordinateRangeError (an
  /// std::invalid_argument, miem/views.hpp) when a finite coordinate lies outside SPEC's range
  /// (found while pass 1 reads the grid: `out` then holds no result).
  template <typename T>
  DetectSummary run(const GridView<T>& grid, const OrganizedOutput& out);

 private:
  DetectParams params_;
  DetectParams eff_;  // params_ with theta0, min_step, z_resolution, z_noise resolved (*_auto)
  detail::Workspace ws_;
};

/// SPEC "min_step='auto'": the min_step that GridParams::min_step_auto gives on `grid` (scan
/// units), or -1 when the grid's unit neighbours are far enough apart (off). Over the 256 rows
/// from the first row with a finite cell, per grid axis, the median distance of finite
/// neighbour pairs and the robust noise 1.4826 median|z[i-1] - 2 z[i] + z[i+1]| / sqrt(6) of
/// finite triples; 4 * max(noise) when that exceeds min(spacing). (ProfileStream decides it
/// itself on the same rows.)
template <typename T>
double auto_min_step(const GridView<T>& grid);

/// SPEC "z_noise": the z_noise that GridParams::z_noise_auto gives on `grid` (scan units): the
/// larger robust sigma of the second differences along and across the profiles of the rows
/// auto_min_step reads (min_step "auto" is 4 times it when that exceeds the spacing); -1 when
/// there is none.
template <typename T>
double auto_z_noise(const GridView<T>& grid);

/// SPEC "z_resolution": the z_resolution that GridParams::z_resolution_auto gives on `grid`
/// (scan units): the smallest non-zero |z difference| of finite neighbours along the profiles
/// (columns c, c + 1) of the rows auto_min_step reads, or between two z values of the finite
/// cells among the first 65,536 cells (row by row) of the first 32 of those rows if smaller; -1
/// when there is none.
template <typename T>
double auto_z_resolution(const GridView<T>& grid);

/// One-call organized detection with owned outputs.
template <typename T>
DetectResult detect_organized(const GridView<T>& grid, const DetectParams& params);

}  // namespace miem
