// Non-owning, strided, read-only views of caller memory (NumPy arrays, sensor buffers).
// Nothing is copied: float and double coordinates are widened to double per value.
#pragma once

#include <cstddef>
#include <stdexcept>

#include <Eigen/Core>

namespace miem {

/// N points of 3 coordinates each, anywhere in memory. Strides are counted in elements of T.
template <typename T>
struct PointsView {
  const T* data = nullptr;
  std::ptrdiff_t size = 0;          ///< number of points
  std::ptrdiff_t point_stride = 3;  ///< elements from one point to the next
  std::ptrdiff_t coord_stride = 1;  ///< elements from x to y to z of one point

  /// Point i, widened to double.
  Eigen::Vector3d operator[](std::ptrdiff_t i) const {
    const T* p = data + i * point_stride;
    return {static_cast<double>(p[0]), static_cast<double>(p[coord_stride]),
            static_cast<double>(p[2 * coord_stride])};
  }
};

/// An organized scan: rows x cols cells of 3 coordinates (row = one laser profile).
/// Strides are counted in elements of T.
template <typename T>
struct GridView {
  const T* data = nullptr;
  std::ptrdiff_t rows = 0;
  std::ptrdiff_t cols = 0;
  std::ptrdiff_t row_stride = 0;    ///< elements from (r, c) to (r + 1, c)
  std::ptrdiff_t col_stride = 3;    ///< elements from (r, c) to (r, c + 1)
  std::ptrdiff_t coord_stride = 1;  ///< elements from x to y to z

  /// A dense row-major rows x cols x 3 buffer.
  static GridView dense(const T* data, std::ptrdiff_t rows, std::ptrdiff_t cols) {
    return GridView{data, rows, cols, cols * 3, 3, 1};
  }

  /// Cell (r, c), widened to double.
  Eigen::Vector3d operator()(std::ptrdiff_t r, std::ptrdiff_t c) const {
    const T* p = data + r * row_stride + c * col_stride;
    return {static_cast<double>(p[0]), static_cast<double>(p[coord_stride]),
            static_cast<double>(p[2 * coord_stride])};
  }

  /// True when all three coordinates of cell (r, c) are finite.
  bool finite(std::ptrdiff_t r, std::ptrdiff_t c) const {
    const T* p = data + r * row_stride + c * col_stride;
    // x - x is 0 for finite x and NaN for inf/NaN: one test for all three.
    const T s = (p[0] - p[0]) + (p[coord_stride] - p[coord_stride]) +
                (p[2 * coord_stride] - p[2 * coord_stride]);
    return s == T(0);
  }
};

/// The largest magnitude among the finite values of `rows` x `cols` values of T at `data` (strides
/// in elements), 0 when none is finite: the number SPEC's coordinate range bounds. One read
/// pass, no temporaries.
template <typename T>
double largest_finite_magnitude(const T* data, std::ptrdiff_t rows, std::ptrdiff_t cols,
                                std::ptrdiff_t row_stride, std::ptrdiff_t col_stride);

/// SPEC "Numbers", coordinate range: every finite coordinate has magnitude at most
/// kCoordinateMax, and the largest is 0 or at least kCoordinateMin. Beyond them float64
/// overflows or underflows in the tests' powers of coordinate differences (a grid scaled by
/// 1e300 or 1e-310 would silently lose its spikes).
inline constexpr double kCoordinateMax = 1e18;
inline constexpr double kCoordinateMin = 1e-18;

/// Whether `top`, the largest finite magnitude of some coordinates, lies in that range; with
/// `lower` false only the upper bound counts (one profile of a stream: the lower bound is about
/// the whole scan).
inline bool coordinate_range_ok(double top, bool lower = true) noexcept {
  return !(top > kCoordinateMax) && !(lower && top > 0.0 && top < kCoordinateMin);
}

/// What the detectors throw for coordinates outside that range (OrganizedDetector::run,
/// detect_organized, and detect_points, point_spacing, distinct_spacings, estimate_normals of
/// miem/unorganized.hpp; nothrow::detect and ProfileStream::push return
/// StatusCode::kInvalidInput instead): an std::invalid_argument whose message names the
/// argument and the magnitude found.
class CoordinateRangeError : public std::invalid_argument {
 public:
  CoordinateRangeError(const char* name, double magnitude);
  /// The largest finite magnitude found.
  double magnitude() const noexcept { return magnitude_; }

 private:
  double magnitude_;
};

/// Throws CoordinateRangeError(name, magnitude) unless coordinate_range_ok(magnitude, lower).
/// (Defined in the library: the headers compile with -fno-exceptions.)
void check_coordinate_range(double magnitude, const char* name, bool lower = true);

}  // namespace miem
