// Exact radius and nearest-neighbour queries on unorganized clouds with a uniform grid: points are
// counting-sorted by a 64-bit cell key (memory linear in N, nothing allocated over the bounding
// box), and a query binary-searches the rows of cells it needs (27 or fewer for r <= cell size).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include <Eigen/Core>

#include "miem/views.hpp"

namespace miem {

/// An inclusive box of cell coordinates [lo, hi] on each axis (empty when any lo > hi).
struct CellBox {
  std::int64_t lo[3] = {0, 0, 0};
  std::int64_t hi[3] = {-1, -1, -1};
  bool empty() const { return lo[0] > hi[0] || lo[1] > hi[1] || lo[2] > hi[2]; }
};

/// Uniform grid over the finite points of a view (non-finite rows are not indexed).
///
/// Cell coordinates are computed in double relative to the cloud's minimum corner, so clouds far
/// from the origin lose nothing. Distances are exact in this sense: a point q is within r of p when
/// `dx*dx + dy*dy + dz*dz <= r*r` with `d = q - p` evaluated in double (float input is widened
/// first); the query visits every cell that could hold such a point (the cell index is a monotone
/// function of each coordinate, and the searched box is widened by a few ulps).
///
/// The grid keeps a reference to the caller's points (index queries read them) and a cell-ordered
/// copy of the finite ones (3 values of T each) for cache-friendly scans.
/// Up to 2^32 - 1 points. When the extent over the requested cell size would overflow the 64-bit
/// cell key, the cell size is enlarged (queries stay exact, `cell_size()` reports the value used).
template <typename T>
class NeighborGrid {
 public:
  /// Build the grid. Throws std::invalid_argument when `cell_size` is not finite and > 0, or the
  /// view is malformed or too large. `num_threads`: 0 = all available (the grid never depends on
  /// it).
  NeighborGrid(const PointsView<T>& points, double cell_size, int num_threads = 0);

  /// The indexed view.
  const PointsView<T>& points() const { return points_; }
  /// Rows in the view (finite or not).
  std::ptrdiff_t size() const { return points_.size; }
  /// Finite points indexed.
  std::ptrdiff_t num_indexed() const { return static_cast<std::ptrdiff_t>(order_.size()); }
  /// Occupied cells.
  std::ptrdiff_t num_cells() const { return static_cast<std::ptrdiff_t>(keys_.size()); }
  /// Cell edge length actually used (>= the requested one).
  double cell_size() const { return cell_; }

  /// Indices of the finite points within distance r of point `index` (the point itself included),
  /// ascending. Empty when point `index` is not finite. Throws std::invalid_argument when
  /// `index` is out of range or r is not finite and >= 0.
  void radius_query(std::ptrdiff_t index, double r, std::vector<std::int64_t>& out) const;

  /// Indices of the finite points within distance r of `q`, ascending. Throws
  /// std::invalid_argument when q or r is not finite or r < 0.
  void radius_query(const Eigen::Vector3d& q, double r, std::vector<std::int64_t>& out) const;

  /// Calls `fn(std::ptrdiff_t index, double sq_dist)` for every finite point within r of `q`,
  /// in a deterministic order (cell key, then index). No allocation; no argument checks.
  template <typename Fn>
  void for_each_in_radius(const Eigen::Vector3d& q, double r, Fn&& fn) const {
    const double r2 = r * r;
    for_each_cell(box_around(q, q, r), [&](std::ptrdiff_t cell) {
      for (std::uint32_t k = starts_[cell]; k < starts_[cell + 1]; ++k) {
        const T* p = sorted_.data() + 3 * static_cast<std::size_t>(k);
        const double dx = static_cast<double>(p[0]) - q.x();
        const double dy = static_cast<double>(p[1]) - q.y();
        const double dz = static_cast<double>(p[2]) - q.z();
        const double d2 = dx * dx + dy * dy + dz * dz;
        if (d2 <= r2) fn(static_cast<std::ptrdiff_t>(order_[k]), d2);
      }
    });
  }

  /// Distance from point `index` to the nearest other finite point: 0 for a duplicate, +inf when
  /// there is none, NaN when point `index` is not finite. Throws when `index` is out of range.
  double nearest_distance(std::ptrdiff_t index) const;

  /// `nearest_distance` of every point into `out` (size() values). Parallel over cells.
  void nearest_distances(double* out, int num_threads = 0) const;

  // ---- cell-level access, for batch loops that share one gather among the points of a cell ----

  /// The cells that can hold a point within r of any point of the box [lo, hi] (clamped to the
  /// grid).
  CellBox box_around(const Eigen::Vector3d& lo, const Eigen::Vector3d& hi, double r) const {
    CellBox b;
    for (int a = 0; a < 3; ++a) {
      // Widen by a few ulps of the coordinates so rounding in q - p can never hide a point.
      const double slack = r * 1e-12 + 1e-15 * std::max(std::abs(lo[a]), std::abs(hi[a]));
      b.lo[a] = coord(lo[a] - r - slack, a);
      b.hi[a] = coord(hi[a] + r + slack, a);
    }
    return b;
  }

  /// Calls `fn(std::ptrdiff_t cell)` for every occupied cell in `box`, in ascending key order.
  template <typename Fn>
  void for_each_cell(const CellBox& box, Fn&& fn) const {
    for_each_cell_xyz(box, [&](std::ptrdiff_t cell, std::int64_t, std::int64_t, std::int64_t) {
      fn(cell);
    });
  }

  /// Calls `fn(std::ptrdiff_t cell, ix, iy, iz)` for every occupied cell in `box`, in ascending
  /// key order. Each row of cells (fixed iy, iz) is found by a galloping search from the previous
  /// one, so a 3 x 3 x 3 box costs a few comparisons per row.
  template <typename Fn>
  void for_each_cell_xyz(const CellBox& box, Fn&& fn) const {
    if (box.empty() || keys_.empty()) return;
    const std::uint64_t nx = static_cast<std::uint64_t>(dims_[0]);
    const std::uint64_t ny = static_cast<std::uint64_t>(dims_[1]);
    const std::uint64_t rows = static_cast<std::uint64_t>(box.hi[1] - box.lo[1] + 1) *
                               static_cast<std::uint64_t>(box.hi[2] - box.lo[2] + 1);
    const std::ptrdiff_t ncells = num_cells();
    if (rows > static_cast<std::uint64_t>(ncells) / 8 + 8) {
      // More rows than it pays to search: walk the occupied cells instead.
      for (std::ptrdiff_t c = 0; c < ncells; ++c) {
        std::int64_t xyz[3];
        cell_coords(c, xyz);
        if (xyz[0] >= box.lo[0] && xyz[0] <= box.hi[0] && xyz[1] >= box.lo[1] &&
            xyz[1] <= box.hi[1] && xyz[2] >= box.lo[2] && xyz[2] <= box.hi[2]) {
          fn(c, xyz[0], xyz[1], xyz[2]);
        }
      }
      return;
    }
    const std::uint64_t* const keys = keys_.data();
    const std::ptrdiff_t n = ncells;
    // First row: binary search; later rows: gallop forwards from the last position.
    std::ptrdiff_t pos = -1;
    for (std::int64_t iz = box.lo[2]; iz <= box.hi[2]; ++iz) {
      for (std::int64_t iy = box.lo[1]; iy <= box.hi[1]; ++iy) {
        const std::uint64_t base = nx * (static_cast<std::uint64_t>(iy) +
                                         ny * static_cast<std::uint64_t>(iz));
        const std::uint64_t k0 = base + static_cast<std::uint64_t>(box.lo[0]);
        const std::uint64_t k1 = base + static_cast<std::uint64_t>(box.hi[0]);
        if (pos < 0) {
          pos = std::lower_bound(keys, keys + n, k0) - keys;
        } else if (pos < n && keys[pos] < k0) {
          std::ptrdiff_t step = 1, lo = pos;
          while (pos + step < n && keys[pos + step] < k0) {
            lo = pos + step;
            step *= 2;
          }
          pos = std::lower_bound(keys + lo + 1, keys + std::min(n, pos + step + 1), k0) - keys;
        }
        for (; pos < n && keys[pos] <= k1; ++pos) {
          fn(pos, static_cast<std::int64_t>(keys[pos] - base), iy, iz);
        }
      }
    }
  }

  /// Position in `order()` of the first point of `cell`; the cell's points end at
  /// `cell_begin(cell + 1)`.
  std::uint32_t cell_begin(std::ptrdiff_t cell) const { return starts_[cell]; }
  /// Point indices sorted by cell key, ascending within a cell (num_indexed() values).
  const std::uint32_t* order() const { return order_.data(); }
  /// The grid's cell-ordered copy of the points: x, y, z of the point at position k of order()
  /// at 3 k, 3 k + 1, 3 k + 2 (num_indexed() points).
  const T* sorted_xyz() const { return sorted_.data(); }
  /// The point at position k of order(), from the grid's cell-ordered copy (contiguous reads).
  Eigen::Vector3d sorted_point(std::uint32_t k) const {
    const T* p = sorted_.data() + 3 * static_cast<std::size_t>(k);
    return {static_cast<double>(p[0]), static_cast<double>(p[1]), static_cast<double>(p[2])};
  }
  /// The key of the cell holding `p` (clamped to the grid): cells, and order(), ascend by it.
  std::uint64_t key_of(const Eigen::Vector3d& p) const {
    const std::uint64_t nx = static_cast<std::uint64_t>(dims_[0]);
    const std::uint64_t ny = static_cast<std::uint64_t>(dims_[1]);
    return static_cast<std::uint64_t>(coord(p.x(), 0)) +
           nx * (static_cast<std::uint64_t>(coord(p.y(), 1)) +
                 ny * static_cast<std::uint64_t>(coord(p.z(), 2)));
  }
  /// The cell coordinates of an occupied cell.
  void cell_coords(std::ptrdiff_t cell, std::int64_t out[3]) const {
    const std::uint64_t nx = static_cast<std::uint64_t>(dims_[0]);
    const std::uint64_t ny = static_cast<std::uint64_t>(dims_[1]);
    const std::uint64_t key = keys_[cell];
    out[0] = static_cast<std::int64_t>(key % nx);
    out[1] = static_cast<std::int64_t>((key / nx) % ny);
    out[2] = static_cast<std::int64_t>(key / nx / ny);
  }

 private:
  // Cell coordinate of x on axis a: floor((x - origin) / cell), clamped to the grid. Monotone in x.
  std::int64_t coord(double x, int a) const {
    const double v = (x - origin_[a]) * inv_cell_;
    if (!(v >= 0.0)) return 0;
    if (v >= static_cast<double>(dims_[a] - 1)) return dims_[a] - 1;
    return static_cast<std::int64_t>(v);
  }

  // Squared nearest distances (to other points) of the points `ids[0..count)`, all in the cell
  // with coordinates `center`, searched ring by ring outwards; `first_pos` is their position in
  // order_ (-1: read them from the view). `best2` is overwritten.
  void nearest_in_cell(const std::int64_t center[3], const std::uint32_t* ids, std::ptrdiff_t count,
                       std::ptrdiff_t first_pos, std::vector<Eigen::Vector3d>& scratch,
                       double* best2) const;

  PointsView<T> points_;
  double cell_ = 0.0, inv_cell_ = 0.0;
  Eigen::Vector3d origin_ = Eigen::Vector3d::Zero();
  std::int64_t dims_[3] = {1, 1, 1};
  std::vector<std::uint64_t> keys_;    // occupied cell keys, ascending
  std::vector<std::uint32_t> starts_;  // num_cells() + 1 offsets into order_
  std::vector<std::uint32_t> order_;   // point indices by (key, index)
  std::vector<T> sorted_;              // the points in order_ order, 3 values each (exact copy)
};

extern template class NeighborGrid<float>;
extern template class NeighborGrid<double>;

}  // namespace miem
