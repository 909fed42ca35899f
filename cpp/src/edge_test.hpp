// Edge test (SPEC "Edge test"): burrs standing proud of a feature line or an outline, judged
// against planes over one-sided sub-windows. Internal to the organized detector.
#pragma once

#include <cstdint>
#include <vector>

#include "miem/views.hpp"

namespace miem::detail {

/// Runs edge passes on `labels` (H x W, row-major, as left by the height passes): candidate
/// cells become ABNORMAL. `window` odd >= 3 (sub-window half-size window / 2), `k` > 0 the
/// tolerance in rms units, at most `max_iterations` passes. Returns the number of passes run.
/// The result does not depend on `num_threads`. `scratch` and `flags` are reused between calls
/// (grown only when a grid needs more: no allocation for grids no larger than before).
template <typename T>
int edge_passes(const GridView<T>& g, std::uint8_t* labels, int window, double k,
                int max_iterations, int num_threads, std::vector<double>& scratch,
                std::vector<std::uint8_t>& flags);

}  // namespace miem::detail
