// min_step = "auto" (SPEC "min_step='auto'"): the neighbour distance a grid needs so that its
// profile noise does not read as feature lines. Internal form with a reusable buffer.
#pragma once

#include <vector>

#include "miem/views.hpp"

namespace miem::detail {

/// The min_step GridParams::min_step_auto resolves to on `g` (scan units), or -1 (off).
/// `scratch` is reused between calls (the few values near the medians). The value does not
/// depend on `num_threads` (0: all available).
template <typename T>
double auto_min_step(const GridView<T>& g, std::vector<double>& scratch, int num_threads = 1);

}  // namespace miem::detail
