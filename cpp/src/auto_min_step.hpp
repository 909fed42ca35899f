// min_step = "auto" (SPEC "min_step='auto'"): the neighbour distance a grid needs so that its
// profile noise does not read as feature lines. Internal form with a reusable buffer.
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include "miem/stream.hpp"  // MinStepSelection (the stream's form)
#include "miem/views.hpp"

namespace miem::detail {

/// What the sample rows give (SPEC "min_step='auto'", "z_noise"): the min_step
/// GridParams::min_step_auto resolves to and the z noise sigma GridParams::z_noise_auto resolves
/// to (scan units; -1: off, or no pair or triple to measure).
struct AutoSurvey {
  double min_step = -1.0;
  double noise = -1.0;
};

/// The survey of `g`'s sample rows. `scratch` is reused between calls (the few values near the
/// medians). The values do not depend on `num_threads` (0: all available).
template <typename T>
AutoSurvey auto_survey(const GridView<T>& g, std::vector<double>& scratch, int num_threads = 1);

/// auto_survey(...).min_step.
template <typename T>
double auto_min_step(const GridView<T>& g, std::vector<double>& scratch, int num_threads = 1) {
  return auto_survey(g, scratch, num_threads).min_step;
}

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
