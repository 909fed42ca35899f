// miem: abnormal-point detection in laser scans (Multidimensional Improved Eigenvalue Method).
#pragma once

#include "miem/organized.hpp"
#include "miem/plane.hpp"
#include "miem/scan_line.hpp"
#include "miem/views.hpp"

namespace miem {
/// The library version, "MAJOR.MINOR.PATCH".
const char* version() noexcept;
}  // namespace miem
