// z_resolution = "auto" (SPEC "z_resolution"): the scan's z step, measured as the smallest
// non-zero z difference of neighbouring finite cells along the profiles of the rows that
// min_step="auto" reads, or between two z values of the finite cells pooled from their first
// rows (kZGapRows, kZGapCells) if smaller (on a steep or coarsely sampled surface neighbours
// never share a level, and their smallest difference is the slope's, not the step). A scanner
// (or a file format) that stores z in steps of q puts a flat, level surface's cells on one or
// two levels: a window's rms is then far below q and a cell one step off read as a defect. The
// rms tolerances of the height and edge tests are at least kZResolutionFactor x q.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <limits>
#include <type_traits>
#include <vector>

#include "miem/views.hpp"

namespace miem::detail {

/// The rms tolerances' floor in units of z_resolution: a cell one step off its plane (the plane
/// itself a fraction of a step off the level its cells lie on) stays below it.
constexpr double kZResolutionFactor = 1.5;

/// The least tolerance for a z_resolution (< 0: off): kZResolutionFactor x it, else 0.
inline double z_floor(double z_resolution) noexcept {
  return z_resolution > 0.0 ? kZResolutionFactor * z_resolution : 0.0;
}

/// The cells of the sample whose z values are pooled (SPEC "z_resolution"): the first kZGapCells
/// cells (row by row) of its first kZGapRows rows, few enough that sorting them costs little
/// beside the survey (and its buffer stays small on a grid of one long row).
constexpr std::ptrdiff_t kZGapRows = 32, kZGapCells = 65536;

/// How many cells of sample row k (of `cols` cells) are pooled.
inline std::ptrdiff_t z_gap_cells(std::ptrdiff_t k, std::ptrdiff_t cols) noexcept {
  return k < kZGapRows ? std::max<std::ptrdiff_t>(0, std::min(cols, kZGapCells - k * cols)) : 0;
}

/// Whether the cell at p (x, y, z at p[{0, 1, 2} * coord_stride]) is finite.
template <typename T>
bool finite_cell(const T* p, std::ptrdiff_t coord_stride) noexcept {
  return std::isfinite(static_cast<double>(p[0])) &&
         std::isfinite(static_cast<double>(p[coord_stride])) &&
         std::isfinite(static_cast<double>(p[2 * coord_stride]));
}

/// fold_z_steps of the dense layout of doubles (x, y, z, x, ...): the pairs it does (c, c + 1),
/// c < *done, with AVX-512 where the CPU has it (the same differences, their smallest in any
/// order: the same value); *done = 0 elsewhere.
double fold_z_steps_xyz(const double* row, std::ptrdiff_t n, double q,
                        std::ptrdiff_t* done) noexcept;

/// Folds one row of `n` cells (cell c's x, y, z at row[c * cell_stride + {0, 1, 2} *
/// coord_stride]) into the running smallest non-zero |z[c + 1] - z[c]| of finite neighbours `q`
/// (+inf: none yet). The differences are taken in double, so float32 rows give batch's bits.
template <typename T>
double fold_z_steps(const T* row, std::ptrdiff_t n, std::ptrdiff_t cell_stride,
                    std::ptrdiff_t coord_stride, double q) noexcept {
  const auto finite = [&](const T* p) { return finite_cell(p, coord_stride); };
  std::ptrdiff_t c = 0;
  if constexpr (std::is_same_v<T, double>) {
    if (cell_stride == 3 && coord_stride == 1) q = fold_z_steps_xyz(row, n, q, &c);
  }
  for (; c + 1 < n; ++c) {
    const T* a = row + c * cell_stride;
    const T* b = a + cell_stride;
    if (!finite(a) || !finite(b)) continue;
    const double d = std::abs(static_cast<double>(b[2 * coord_stride]) -
                              static_cast<double>(a[2 * coord_stride]));
    if (d > 0.0 && d < q) q = d;
  }
  return q;
}

/// z_resolution "auto" of `grid` (miem::auto_z_resolution; < 0: none), the pooled z values' keys
/// in `keys` (grown only when a grid needs more).
template <typename T>
double z_resolution(const GridView<T>& grid, std::vector<std::uint64_t>& keys);

/// A finite double as an unsigned key in the same order (-0 just below +0), and back.
inline std::uint64_t z_key(double v) noexcept {
  std::uint64_t b;
  std::memcpy(&b, &v, sizeof b);
  return (b >> 63) ? ~b : b | (std::uint64_t{1} << 63);
}
inline double z_of_key(std::uint64_t k) noexcept {
  const std::uint64_t b = (k >> 63) ? k & ~(std::uint64_t{1} << 63) : ~k;
  double v;
  std::memcpy(&v, &b, sizeof v);
  return v;
}

/// Writes the keys of the z values (as double) of the finite cells of one row (as fold_z_steps)
/// to `out`; returns how many.
template <typename T>
std::ptrdiff_t finite_z_keys(const T* row, std::ptrdiff_t n, std::ptrdiff_t cell_stride,
                             std::ptrdiff_t coord_stride, std::uint64_t* out) noexcept {
  std::ptrdiff_t m = 0;
  for (std::ptrdiff_t c = 0; c < n; ++c) {
    const T* a = row + c * cell_stride;
    if (finite_cell(a, coord_stride)) out[m++] = z_key(static_cast<double>(a[2 * coord_stride]));
  }
  return m;
}

/// Folds the smallest gap between two distinct z values into `q`, from their keys
/// keys[0 .. n - 1]: sorts them (a radix sort; keys[n .. 2 n - 1] its scratch).
double fold_z_gaps(std::uint64_t* keys, std::ptrdiff_t n, double q) noexcept;

}  // namespace miem::detail

// (miem::auto_z_resolution, miem/organized.hpp: both folds over the rows min_step="auto" reads.)
