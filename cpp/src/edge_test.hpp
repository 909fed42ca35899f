// Edge test (SPEC "Edge test"): burrs standing proud of a feature line or an outline, judged
// against planes over one-sided sub-windows. Internal to the organized detector.
#pragma once

#include <algorithm>
#include <cstdint>
#include <limits>
#include <vector>

#include <Eigen/Core>

#include "miem/organized.hpp"
#include "miem/views.hpp"
#include "z_resolution.hpp"

namespace miem::detail {

/// The edge test's tolerance (SPEC "Edge test", step 3): a sub-window's t = max(k x rms,
/// round-off floor, `floor`, prec x |P|), `floor` the largest of min_step / 2 when a min_step
/// is in use (given, or "auto" resolved to one: twice the z noise it measured), 2 z_noise and
/// z_floor(z_resolution); `prec` the input's precision, relative (edge_precision in
/// edge_verdict.hpp: 4 epsilons of its type) and |P| the cell's largest absolute coordinate as
/// given, so that the rounding of float32 coordinates (a noise-free face: no other floor) is
/// not read as a burr.
struct EdgeTol {
  double k;
  double floor;
  double prec = 0.0;
};

/// The tolerance of `p` (its edge_k; its min_step, z_resolution and z_noise resolved, not
/// "auto": the ones in use, < 0 off) for input of precision `prec` (edge_precision).
inline EdgeTol edge_tol(const DetectParams& p, double prec = 0.0) noexcept {
  return {p.edge_k,
          std::max({p.min_step > 0.0 ? 0.5 * p.min_step : 0.0,
                    p.z_noise > 0.0 ? 2.0 * p.z_noise : 0.0, z_floor(p.z_resolution)}),
          prec};
}

/// The floor the height passes' planes are held to for the quiet cells (SPEC "Edge test"
/// step 1: quiet_plane's `floor`): edge_tol's, with the edge test on; < 0: none is quiet.
inline double quiet_plane_floor(const DetectParams& p) noexcept {
  return p.edge_test() ? edge_tol(p).floor : -1.0;
}

/// A sub-window with at least this many INVALID cells has no return there (*empty*), and a
/// plane needs this much support: SPEC "Edge test" step 3's n_min = max(3, r^2 / 2) for
/// sub-window half-size r (also the quiet cells' bound on INVALID cells, step 1).
inline std::ptrdiff_t edge_n_min(std::ptrdiff_t r) noexcept {
  return std::max<std::ptrdiff_t>(3, (r * r) / 2);
}

/// Runs edge passes on `labels` (H x W, row-major, as left by the height passes): candidate
/// cells become ABNORMAL. `window` odd >= 3 (sub-window half-size window / 2), `et` the
/// tolerance (et.k > 0 in rms units; edge_tol), at most `max_iterations` passes. `lines`
/// (H x W, or null: no step 9): bit kLine at the feature-line EDGE cells, whose ABNORMAL
/// neighbours that fit a clean side with a return become EDGE before pass 1 (SPEC step 9).
/// `planes` (H x W, or null: no cell is quiet): the height test's marks (stages.hpp: kHQuiet
/// where the cell's last height-window plane is quiet, kHStale where that plane is not over the
/// final labels); pass 1 leaves out the quiet cells (SPEC step 1, edge_quiet.hpp).
/// Returns the number of passes run. The result does not depend on `num_threads`. `scratch`
/// and `flags` are reused between calls (grown only when a grid needs more: no allocation for
/// grids no larger than before).
template <typename T>
int edge_passes(const GridView<T>& g, std::uint8_t* labels, int window, EdgeTol et,
                int max_iterations, int num_threads, std::vector<double>& scratch,
                CellBytes& flags, const std::uint8_t* lines = nullptr,
                const std::uint8_t* planes = nullptr);

/// Step 9's candidates: does cell (r, c) of an H x W grid have a feature-line cell (line(a, b)
/// true; the cell itself, ABNORMAL, is none) among its 8 neighbours?
template <typename Line>
bool beside_line(const Line& line, std::int64_t r, std::ptrdiff_t c, std::int64_t H,
                 std::ptrdiff_t W) {
  for (std::int64_t a = std::max<std::int64_t>(0, r - 1); a <= std::min(H - 1, r + 1); ++a) {
    for (std::ptrdiff_t b = std::max<std::ptrdiff_t>(0, c - 1); b <= std::min(W - 1, c + 1); ++b) {
      if (line(a, b)) return true;
    }
  }
  return false;
}

/// What edge_judge_row gives a cell: the pass's verdict (mark 1: it becomes ABNORMAL), or for
/// step 9 whether it fits a clean sub-window that is not empty (mark 1: it does).
enum class EdgeJudgment : std::uint8_t { kVerdict, kFitsGround };

/// The edge test's integral images hold, per cell, these moments: n, x, y, z, xx, xy, xz, yy,
/// yz, zz of the support (NORMAL cells, relative to the tile's origin) and the INVALID count.
constexpr int kEdgeMoments = 11;
/// The tiles of the integral images (rows, columns), fixed in grid coordinates from (0, 0).
/// A tile's images cover its rows and r = window / 2 rows and columns around it; its origin is
/// its first finite cell (row-major).
constexpr std::ptrdiff_t kEdgeTileRows = 64, kEdgeTileCols = 128;

/// A tile's integral images as edge_judge_row reads them: moment q of image row s, column x at
/// data[q * plane + ((s - first) % rows) * stride + x]. Image row s holds the sums over grid
/// rows first .. s - 1 (first = max(0, R0 - r) for the tile from grid row R0), column x those
/// over grid columns f0 .. f0 + x - 1 (f0 = max(0, C0 - r)). `rows` < the image's rows: a ring.
struct EdgeImages {
  const double* data = nullptr;
  std::ptrdiff_t plane = 0, stride = 0, first = 0, rows = 1, f0 = 0;
};

/// Adds cell row `row` of g (labels `lab`, indexed by grid column) over grid columns f0 .. f1 - 1
/// to a tile's column sums (moment q of column f0 + x at col[q * col_plane + x]) and writes the
/// next image row: moment q at out[q * plane], 0 then x + 1 for column f0 + x (out null: the
/// column sums only, for a row above every image row that will be read). o: the origin.
template <typename T>
void edge_image_row(const GridView<T>& g, std::ptrdiff_t row, const std::uint8_t* lab,
                    std::ptrdiff_t f0, std::ptrdiff_t f1, const Eigen::Vector3d& o, double* col,
                    std::ptrdiff_t col_plane, double* out, std::ptrdiff_t plane);

/// Band sums a row's verdicts leave for row + r + 1's (edge_judge_row): `slots` slots of
/// kEdgeCacheSlot doubles at `data`. A caller that gives one gives at least (r + 2) *
/// ceil((C1 - C0) / kEdgeBandCells) slots and clears it (clear()) whenever the images change
/// (another tile or pass); with fewer slots it is not used. Its values are the same bits the
/// verdicts would compute.
constexpr std::ptrdiff_t kEdgeBandPos = 128, kEdgeBandCells = 64;
constexpr std::ptrdiff_t kEdgeCacheSlot = 8 + 2 * (kEdgeMoments + 1) * kEdgeBandPos;
struct EdgeBandCache {
  double* data = nullptr;
  std::ptrdiff_t slots = 0;
  /// Every slot's row tag to NaN, which equals no row: not -1, which is row rr - r - 1 for
  /// rr = r (the first row with bands), whose lookup then matched a stale slot (another tile's
  /// bands) when that slot's first cell was the same.
  void clear() const {
    for (std::ptrdiff_t i = 0; i < slots; ++i) {
      data[i * kEdgeCacheSlot] = std::numeric_limits<double>::quiet_NaN();
    }
  }
};

/// One edge pass's verdicts (SPEC "Edge test") on grid row rr, columns C0 .. C1 - 1 of one
/// tile: each cell c with todo[c] and a NORMAL or EDGE label that is not quiet (step 1) gets
/// mark[c] = 1 when it becomes ABNORMAL, else 0 (other cells untouched: the callers clear mark
/// first); with `judge` kFitsGround, each cell with todo[c]
/// (any label) gets mark[c] = 1 when it fits a clean sub-window that is not empty (step 9).
/// g holds at least the grid rows within r of rr
/// (rows max(0, rr - r) .. min(H, rr + r + 1) - 1: a neighbourhood, or the whole grid), the
/// cell's row being g's row `grow`; `lab` the labels at the start of the pass of g's cells
/// (row-major, g.cols a row: the grid's width); todo and mark are rr's row. H: the grid's rows
/// (its border); `im` the tile's images with the image rows max(0, rr - r) .. min(H, rr + r + 1)
/// present, o its origin, r = window / 2. Batch edge_passes judges every row through this,
/// and so does the stream (with a window of 2 r + 1 rows).
template <typename T>
void edge_judge_row(const GridView<T>& g, std::ptrdiff_t grow, std::ptrdiff_t rr,
                    std::ptrdiff_t H, std::ptrdiff_t C0, std::ptrdiff_t C1,
                    const EdgeImages& im, const Eigen::Vector3d& o, std::ptrdiff_t r, EdgeTol et,
                    const std::uint8_t* lab, const std::uint8_t* todo, std::uint8_t* mark,
                    const EdgeBandCache* cache = nullptr,
                    EdgeJudgment judge = EdgeJudgment::kVerdict);

}  // namespace miem::detail
