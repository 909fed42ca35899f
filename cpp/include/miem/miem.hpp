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
}  // namespace miem
