// z_resolution = "auto" on a grid (z_resolution.hpp, SPEC "z_resolution").
#include "z_resolution.hpp"

#include "auto_min_step.hpp"
#include "miem/organized.hpp"
#include "radix_sort.hpp"
#include "vector_clones.hpp"

#include <algorithm>
#include <cstdint>
#include <vector>

namespace miem {

namespace detail {

#ifdef MIEM_SELECT_AVX512
namespace {
// fold_z_steps_xyz's loop: pairs (c .. c + 7, c + 1 .. c + 8) a step, the smallest difference
// per lane, then over the lanes.
__attribute__((target("avx512f,avx512vl"))) double fold_z_steps_avx512(
    const double* row, std::ptrdiff_t n, double q, std::ptrdiff_t* done) {
  const __m512d zero = _mm512_setzero_pd();
  __m512d vq = _mm512_set1_pd(q);
  std::ptrdiff_t c = 0;
  for (; c + 9 <= n; c += 8) {
    __m512d ax, ay, az, bx, by, bz;
    load_xyz8(row + 3 * c, ax, ay, az);
    load_xyz8(row + 3 * (c + 1), bx, by, bz);
    const __m512d d = _mm512_abs_pd(_mm512_sub_pd(bz, az));
    const __mmask8 take = finite8(ax, ay, az) & finite8(bx, by, bz) &
                          _mm512_cmp_pd_mask(d, zero, _CMP_GT_OQ) &
                          _mm512_cmp_pd_mask(d, vq, _CMP_LT_OQ);
    vq = _mm512_mask_mov_pd(vq, take, d);
  }
  *done = c;
  alignas(64) double lanes[8];
  _mm512_store_pd(lanes, vq);
  return *std::min_element(lanes, lanes + 8);
}
}  // namespace
#endif

double fold_z_steps_xyz(const double* row, std::ptrdiff_t n, double q,
                        std::ptrdiff_t* done) noexcept {
  *done = 0;
#ifdef MIEM_SELECT_AVX512
  if (has_avx512()) return fold_z_steps_avx512(row, n, q, done);
#endif
  return q;
}

double fold_z_gaps(std::uint64_t* keys, std::ptrdiff_t n, double q) noexcept {
  // (a radix sort: std::sort took 3 of the 4.6 ms a 2048-wide grid's measurement cost)
  if (n < 2) return q;
  const std::size_t m = static_cast<std::size_t>(n);
  const std::uint64_t* a =
      radix_sort(keys, nullptr, keys + n, nullptr, m, ~std::uint64_t{0}) ? keys + n : keys;
  double prev = z_of_key(a[0]);
  for (std::ptrdiff_t i = 1; i < n; ++i) {
    const double v = z_of_key(a[i]);
    const double d = v - prev;
    if (d > 0.0 && d < q) q = d;
    prev = v;
  }
  return q;
}

template <typename T>
double z_resolution(const GridView<T>& grid, std::vector<std::uint64_t>& keys) {
  const GridView<T> g = min_step_rows(grid);
  const std::ptrdiff_t pooled = std::min(g.rows * g.cols, kZGapCells);
  if (keys.size() < static_cast<std::size_t>(2 * pooled)) {
    keys.resize(static_cast<std::size_t>(2 * pooled));  // keys, the sort's scratch
  }
  double q = std::numeric_limits<double>::infinity();
  std::ptrdiff_t n = 0;
  for (std::ptrdiff_t r = 0; r < g.rows; ++r) {
    const T* row = g.data + r * g.row_stride;
    q = fold_z_steps(row, g.cols, g.col_stride, g.coord_stride, q);
    n += finite_z_keys(row, z_gap_cells(r, g.cols), g.col_stride, g.coord_stride, keys.data() + n);
  }
  q = fold_z_gaps(keys.data(), n, q);
  return std::isfinite(q) ? q : -1.0;
}

template double z_resolution<float>(const GridView<float>&, std::vector<std::uint64_t>&);
template double z_resolution<double>(const GridView<double>&, std::vector<std::uint64_t>&);

}  // namespace detail

template <typename T>
double auto_z_resolution(const GridView<T>& grid) {
  std::vector<std::uint64_t> keys;
  return detail::z_resolution(grid, keys);
}

template double auto_z_resolution<float>(const GridView<float>&);
template double auto_z_resolution<double>(const GridView<double>&);

}  // namespace miem
