// The angle test along one scan line (paper eq. 18-19) and the paper's eq. 20 heights.
#pragma once

#include "miem/views.hpp"

namespace miem {

/// Interior angle (degrees, [0, 180]) at every point of a line, between its neighbours `step`
/// points before and after. NaN at the ends, where any of the three points is non-finite, or where
/// a neighbour coincides with the point. `out_deg` has line.size elements.
/// Throws std::invalid_argument when step < 1.
template <typename T>
void scan_line_angles(const PointsView<T>& line, int step, double* out_deg);

/// Paper eq. 20: D_i = sin(theta_{i-step}) |P_i - P_{i-step}|, the height of P_i over the line
/// through its predecessors. NaN where that angle is NaN or P_i is non-finite.
template <typename T>
void scan_line_heights(const PointsView<T>& line, int step, double* out);

}  // namespace miem
