// min_step = "auto" (SPEC "min_step='auto'"): the neighbour distance a grid needs so that its
// profile noise does not read as feature lines. Internal form with a reusable buffer.
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include "miem/stream.hpp"  // MinStepSelection (the stream's form)
#include "miem/views.hpp"

namespace miem::detail {

/// The min_step GridParams::min_step_auto resolves to on `g` (scan units), or -1 (off).
/// `scratch` is reused between calls (the few values near the medians). The value does not
/// depend on `num_threads` (0: all available).
template <typename T>
double auto_min_step(const GridView<T>& g, std::vector<double>& scratch, int num_threads = 1);

/// The rows min_step="auto" reads: the first kAutoMinStepRows rows from the first row that has
/// a finite cell (fewer at the grid's end; none when no cell is finite). SPEC "min_step='auto'".
constexpr std::ptrdiff_t kAutoMinStepRows = 256;

/// The first row of `g` with a finite cell (g.rows when none).
template <typename T>
std::ptrdiff_t first_finite_row(const GridView<T>& g);

/// The rows of `g` that min_step="auto" reads (see kAutoMinStepRows).
template <typename T>
GridView<T> min_step_rows(const GridView<T>& g);

}  // namespace miem::detail
