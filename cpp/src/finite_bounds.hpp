// The box and count of a cloud's finite points on nt threads, shared by the neighbour grid and
// the spacing's first cell size. Internal.
#pragma once

#include <cstddef>
#include <limits>

#include <Eigen/Core>

#include "miem/views.hpp"

namespace miem::detail {

struct FiniteBounds {
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(std::numeric_limits<double>::infinity());
  Eigen::Vector3d hi = Eigen::Vector3d::Constant(-std::numeric_limits<double>::infinity());
  std::ptrdiff_t count = 0;  // finite points
};

/// Per-axis min and max of the finite points (min and max are exact: the same for any thread
/// count) and their count.
template <typename T>
FiniteBounds finite_bounds(const PointsView<T>& points, int nt) {
  FiniteBounds b;
  const std::ptrdiff_t n = points.size;
#pragma omp parallel num_threads(nt) if (nt > 1)
  {
    FiniteBounds t;
#pragma omp for schedule(static) nowait
    for (std::ptrdiff_t i = 0; i < n; ++i) {
      const Eigen::Vector3d p = points[i];
      if (!p.allFinite()) continue;
      t.lo = t.lo.cwiseMin(p);
      t.hi = t.hi.cwiseMax(p);
      ++t.count;
    }
#pragma omp critical(miem_finite_bounds)
    {
      b.lo = b.lo.cwiseMin(t.lo);
      b.hi = b.hi.cwiseMax(t.hi);
      b.count += t.count;
    }
  }
  return b;
}

}  // namespace miem::detail
