// Deviation of a scan from a reference surface (a golden sample's points or a CAD model's dense
// sampling, each point with an oriented normal): signed point-to-surface distance, coverage,
// per-point labels (excess / missing / within tolerance / not covered) and defects.
// The exact rules are in docs/SPEC.md, section "Deviation from a reference".
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

#include "miem/neighbor_grid.hpp"
#include "miem/organized.hpp"
#include "miem/views.hpp"

namespace miem {

/// Per-scan-point outputs of ReferenceSurface::deviation, one value per scan row each; any
/// pointer may be null.
struct DeviationOutput {
  double* deviation = nullptr;      ///< n_q . (p - q), NaN where not covered
  double* distance = nullptr;       ///< |p - q|, NaN where there is no q
  std::int64_t* nearest = nullptr;  ///< row of q in the reference, -1 where there is no q
  std::uint8_t* covered = nullptr;  ///< 1 where q exists and p lies over it (lateral offset)
};

/// A reference surface: the rows of `points` whose point and normal are both finite, indexed by
/// a uniform neighbour grid. The normals are used as given (unit length, oriented outwards:
/// excess material is on their positive side).
class ReferenceSurface {
 public:
  /// Copies the usable rows. `normals` is row-major M x 3. Throws std::invalid_argument when
  /// `cell_size` is not finite and > 0 or no row is usable.
  ReferenceSurface(const PointsView<double>& points, const double* normals, double cell_size,
                   int num_threads = 0);
  ReferenceSurface(const ReferenceSurface&) = delete;
  ReferenceSurface& operator=(const ReferenceSurface&) = delete;

  /// Usable reference points.
  std::ptrdiff_t size() const { return static_cast<std::ptrdiff_t>(rows_.size()); }
  /// Grid cell size used.
  double cell_size() const { return grid_->cell_size(); }

  /// For every scan point p: q = the usable reference point nearest to p (Euclidean, ties to the
  /// lowest reference row) among those within `max_distance`. Covered when q exists and the
  /// lateral offset |(p - q) - dev n_q| is at most `max_lateral` (+inf: no limit): a point
  /// beyond the edge of the reference is not covered. Non-finite scan points are not covered.
  /// Throws std::invalid_argument when max_distance is not finite and > 0 or max_lateral is
  /// NaN or < 0. Deterministic for any thread count.
  template <typename T>
  void deviation(const PointsView<T>& scan, double max_distance, double max_lateral,
                 const DeviationOutput& out, int num_threads = 0) const;

 private:
  std::vector<double> points_;        // usable rows, 3 values each
  std::vector<double> normals_;       // their normals, 3 values each
  std::vector<std::int64_t> rows_;    // their rows in the caller's arrays
  double origin_[3] = {0.0, 0.0, 0.0};  // minimum corner: the grid's origin (cell boxes)
  std::unique_ptr<NeighborGrid<double>> grid_;
};

/// Per-point labels of a comparison.
enum class DeviationLabel : std::uint8_t {
  kWithin = 0,      ///< covered, within tolerance (or a marginal group inside the don't-care band)
  kExcess = 1,      ///< material beyond the reference surface (burr, spatter)
  kMissing = 2,     ///< material missing under the reference surface (pit, over-grinding)
  kNotCovered = 3,  ///< no reference surface near the point (or a non-finite point)
};

/// Labelling parameters.
struct DeviationLabelParams {
  double tolerance = 0.2;  ///< |deviation| > tolerance is out of tolerance (> 0)
  double dont_care = 0.0;  ///< a group is a defect only when its peak |deviation| exceeds
                           ///< tolerance + dont_care (>= 0)
  double link = 1.0;       ///< out-of-tolerance points of one sign closer than this (<=) are one
                           ///< group (> 0)
};

/// Throws std::invalid_argument naming the offending parameter.
void validate(const DeviationLabelParams& params);

/// Labels and defects from deviations. `points` (N rows) give positions for grouping and the
/// defects' geometry (any rigid frame: the scan's own, typically); `normals` (N x 3 row-major,
/// may be null) the reference normal at each point's nearest reference point in that frame.
/// Defects: peak_height / mean_height are deviations, normal the normal at the peak, kind
/// protrusion (excess) or pit (missing); ordered by |peak_height| descending.
template <typename T>
std::vector<Defect> label_deviation(const PointsView<T>& points, const double* deviation,
                                    const std::uint8_t* covered, const double* normals,
                                    const DeviationLabelParams& params, std::uint8_t* labels);

}  // namespace miem
