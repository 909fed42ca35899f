// z_resolution = "auto" on a grid (z_resolution.hpp, SPEC "z_resolution").
#include "z_resolution.hpp"

#include "auto_min_step.hpp"
#include "miem/organized.hpp"

namespace miem {

template <typename T>
double auto_z_resolution(const GridView<T>& grid) {
  const GridView<T> g = detail::min_step_rows(grid);
  double q = std::numeric_limits<double>::infinity();
  for (std::ptrdiff_t r = 0; r < g.rows; ++r) {
    q = detail::fold_z_steps(g.data + r * g.row_stride, g.cols, g.col_stride, g.coord_stride, q);
  }
  return std::isfinite(q) ? q : -1.0;
}

template double auto_z_resolution<float>(const GridView<float>&);
template double auto_z_resolution<double>(const GridView<double>&);

}  // namespace miem
