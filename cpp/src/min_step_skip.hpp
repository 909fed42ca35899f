// The steps a min_step neighbour search (docs/SPEC.md "Neighbour") may pass over unread along a
// profile, shared by the batch's row kernel and the stream's pass 1.
//
// For each usable cell i of a row, e[i] = |q_n - q_i| / (n - i) with n the next usable cell of the
// row (0 when none; 0 for unusable cells). Along a ray from P = q_c, the usable cells a < b met in
// turn are at most (b - a) max e apart, so the usable cell j steps away lies within j D of P, D the
// largest e the path crosses: with j D <= (1 - 1e-9) s min_step it is surely nearer than the
// search's bound (far below the relative 1e-12 margin of the kernels' "near", so the computed
// squared distance is below it too) and the search only passes it. The search is unchanged: the
// skipped steps are exactly the ones it passes over; their unusable cells still count as gaps.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>

namespace miem::detail {

/// e^2 (above) of the W cells of a row: x, y, z at x[c], x[c + plane], x[c + 2 plane] (T float
/// or double, read as double); usable(c): the cell is usable. (Squared: no square root.)
template <typename T, typename Usable>
void row_speeds(std::ptrdiff_t W, const T* x, std::ptrdiff_t plane, Usable usable, double* e2) {
  const T *y = x + plane, *z = x + 2 * plane;
  std::ptrdiff_t next = -1;
  for (std::ptrdiff_t c = W - 1; c >= 0; --c) {
    e2[c] = 0.0;
    if (!usable(c)) continue;
    if (next >= 0) {
      const double dx = static_cast<double>(x[next]) - static_cast<double>(x[c]);
      const double dy = static_cast<double>(y[next]) - static_cast<double>(y[c]);
      const double dz = static_cast<double>(z[next]) - static_cast<double>(z[c]);
      const double dd = (dx * dx + dy * dy) + dz * dz, n = static_cast<double>(next - c);
      e2[c] = next - c == 1 ? dd : dd / (n * n);
    }
    next = c;
  }
}

/// Per chunk of `chunk` columns, the largest e^2 within `reach` columns of it (D^2 of every
/// search from its cells that reads at most `reach` steps).
inline void chunk_speeds(const double* e2, std::ptrdiff_t W, std::ptrdiff_t chunk,
                         std::ptrdiff_t reach, double* out) {
  for (std::ptrdiff_t a = 0, ch = 0; a < W; a += chunk, ++ch) {
    const std::ptrdiff_t lo = std::max<std::ptrdiff_t>(0, a - reach);
    const std::ptrdiff_t hi = std::min(W, a + chunk + reach);
    double D2 = 0.0;
    for (std::ptrdiff_t i = lo; i < hi; ++i) D2 = std::max(D2, e2[i]);
    out[ch] = D2;
  }
}

/// The first step a search at scale s must read (steps s .. first - 1 are surely near: j D <=
/// (1 - 1e-9) len) given D^2 and len = s min_step; at most `stop`.
inline std::ptrdiff_t first_read_step(double D2, double len, std::ptrdiff_t s,
                                      std::ptrdiff_t stop) {
  const double t = len * (1.0 - 1e-9), t2 = t * t;
  if (!(t > 0.0)) return s;
  std::ptrdiff_t j = stop;  // the last surely near step
  if (D2 > 0.0 && t2 / D2 < static_cast<double>(stop) * static_cast<double>(stop)) {
    j = static_cast<std::ptrdiff_t>(std::sqrt(t2 / D2));
    while (j > 0 && static_cast<double>(j) * static_cast<double>(j) * D2 > t2) --j;
  }
  return std::min(std::max(s, j + 1), stop);
}

}  // namespace miem::detail
