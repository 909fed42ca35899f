// Duplicate points (docs/SPEC.md, "Duplicate points"): rows within merge_distance of each other
// (transitively) are one point, represented by the smallest row index. Internal to the core.
#pragma once

#include <cstdint>
#include <vector>

#include "miem/views.hpp"

namespace miem::cloud {

struct Duplicates {
  std::vector<std::int64_t> rep;       ///< per row: its representative row, -1 if not finite
  std::vector<std::int64_t> distinct;  ///< representative rows, ascending
  std::ptrdiff_t merged = 0;           ///< finite rows that are not their own representative
};

/// Groups of rows within `tol` (distance <= tol, 0: equal points) from the nearest-other
/// distances `nn` (NaN for non-finite rows). Only rows with nn <= tol are searched, so a cloud
/// without duplicates costs one pass over nn (and `rep`, `distinct` stay empty).
template <typename T>
Duplicates find_duplicates(const PointsView<T>& points, const std::vector<double>& nn, double tol,
                           int num_threads);

}  // namespace miem::cloud
