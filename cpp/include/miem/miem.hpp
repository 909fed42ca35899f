// miem: abnormal-point detection in laser scans (Multidimensional Improved Eigenvalue Method).
#pragma once

#include "miem/neighbor_grid.hpp"
#include "miem/nothrow.hpp"
#include "miem/organized.hpp"
#include "miem/plane.hpp"
#include "miem/scan_line.hpp"
#include "miem/stream.hpp"
#include "miem/targets.hpp"
#include "miem/unorganized.hpp"
#include "miem/views.hpp"

namespace miem {
/// The library version, "MAJOR.MINOR.PATCH".
const char* version() noexcept;

/// The most threads any call uses (4 x the processors, at most 256): every `num_threads`
/// request, and 0 = "all available", is clamped to it. Results never depend on the count.
int max_threads() noexcept;
}  // namespace miem
