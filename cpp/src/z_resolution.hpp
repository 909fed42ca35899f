// z_resolution = "auto" (SPEC "z_resolution"): the scan's z step, measured as the smallest
// non-zero z difference of neighbouring finite cells along the profiles of the rows that
// min_step="auto" reads. A scanner (or a file format) that stores z in steps of q puts a flat,
// level surface's cells on one or two levels: a window's rms is then far below q and a cell one
// step off read as a defect. The rms tolerances of the height and edge tests are at least
// kZResolutionFactor x q.
#pragma once

#include <cmath>
#include <cstddef>
#include <limits>

#include "miem/views.hpp"

namespace miem::detail {

/// The rms tolerances' floor in units of z_resolution: a cell one step off its plane (the plane
/// itself a fraction of a step off the level its cells lie on) stays below it.
constexpr double kZResolutionFactor = 1.5;

/// The least tolerance for a z_resolution (< 0: off): kZResolutionFactor x it, else 0.
inline double z_floor(double z_resolution) noexcept {
  return z_resolution > 0.0 ? kZResolutionFactor * z_resolution : 0.0;
}

/// Folds one row of `n` cells (cell c's x, y, z at row[c * cell_stride + {0, 1, 2} *
/// coord_stride]) into the running smallest non-zero |z[c + 1] - z[c]| of finite neighbours `q`
/// (+inf: none yet). The differences are taken in double, so float32 rows give batch's bits.
template <typename T>
double fold_z_steps(const T* row, std::ptrdiff_t n, std::ptrdiff_t cell_stride,
                    std::ptrdiff_t coord_stride, double q) noexcept {
  const auto finite = [&](const T* p) {
    return std::isfinite(static_cast<double>(p[0])) &&
           std::isfinite(static_cast<double>(p[coord_stride])) &&
           std::isfinite(static_cast<double>(p[2 * coord_stride]));
  };
  for (std::ptrdiff_t c = 0; c + 1 < n; ++c) {
    const T* a = row + c * cell_stride;
    const T* b = a + cell_stride;
    if (!finite(a) || !finite(b)) continue;
    const double d = std::abs(static_cast<double>(b[2 * coord_stride]) -
                              static_cast<double>(a[2 * coord_stride]));
    if (d > 0.0 && d < q) q = d;
  }
  return q;
}

}  // namespace miem::detail

// (miem::auto_z_resolution, miem/organized.hpp, folds the rows min_step="auto" reads.)
