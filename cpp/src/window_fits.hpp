// Window planes (SPEC "Height"): the eigen plane of the NORMAL cells in the window x window square
// around a cell, for many cells at once. Shared by the height test and the heights.
//
// The grid is cut into tiles (kBand rows x kStrip columns); each tile keeps its moments relative
// to one of its own points (far-from-origin scans lose no precision) as running column sums over
// the window's rows, updated by one row in and one row out per row (O(1) per cell), and box sums
// along the row from their prefix sums. The smallest eigenpair of each wanted cell's scatter is
// solved for a whole row at once in straight-line code (vectorised; AVX-512 or AVX2 clones
// where the CPU has them).
// Tiles are independent and each cell is computed by exactly one tile, so the result does not
// depend on the thread count.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <type_traits>
#include <vector>

#include <Eigen/Core>

#include "judge.hpp"
#include "miem/views.hpp"
#include "parallel.hpp"
#include "plane_math.hpp"
#include "vector_clones.hpp"

namespace miem::detail {

/// What a window plane gives one cell.
struct WindowFit {
  bool ok = false;  ///< a plane exists (>= 3 NORMAL cells, not degenerate)
  double height = 0.0, n = 0.0, l0 = 0.0, l1 = 0.0, l2 = 0.0;
  double edges = 0.0;  ///< feature-line cells in the window (cells of class kLine)
};

/// Cell classes read by the sums: NORMAL cells make the plane, kLine cells are counted.
inline constexpr std::uint8_t kInPlane = 1, kLine = 2;

inline constexpr int kMoments = 11;  // n, x, y, z, xx, xy, xz, yy, yz, zz, line count

/// Smallest eigenpair and height for m cells from their window sums (SoA, `cap` apart:
/// S + k * cap is moment k; Q + k * cap is coordinate k of the cell, relative to the same
/// origin). Writes fits to F (height, l0, l1, l2 at F + k * cap) and ok / redo flags; redo marks
/// the rare cells whose Newton iteration needs more steps (solved again by solve_fits_exact).
/// kExact: fit_from_sums's arithmetic bit for bit (means and the normal by division, Newton
/// until every lane has ended or 64 steps, as smallest_eigenpair), for those cells.
template <bool kExact>
inline __attribute__((always_inline)) void solve_fits_body(std::ptrdiff_t m, std::ptrdiff_t cap,
                                                           const double* __restrict S,
                                                           const double* __restrict Q,
                                                           double* __restrict F,
                                                           std::uint8_t* __restrict ok,
                                                           std::uint8_t* __restrict redo) {
  const double* __restrict s0 = S;
  const double* __restrict s1 = S + cap;
  const double* __restrict s2 = S + 2 * cap;
  const double* __restrict s3 = S + 3 * cap;
  const double* __restrict s4 = S + 4 * cap;
  const double* __restrict s5 = S + 5 * cap;
  const double* __restrict s6 = S + 6 * cap;
  const double* __restrict s7 = S + 7 * cap;
  const double* __restrict s8 = S + 8 * cap;
  const double* __restrict s9 = S + 9 * cap;
  const double* __restrict qx = Q;
  const double* __restrict qy = Q + cap;
  const double* __restrict qz = Q + 2 * cap;
  double* __restrict fh = F;
  double* __restrict f0 = F + cap;
  double* __restrict f1 = F + 2 * cap;
  double* __restrict f2 = F + 3 * cap;
  // Blocks of kB cells: the centred scatters, then the Newton steps for the whole block until
  // every cell has ended (at most 4: the steps of an ended cell change nothing, so the bits are
  // those of 4 fixed steps; flat windows end within 2 or 3), then the rest. The
  // flags are 1.0 / 0.0 doubles in the vector loop and bytes only after it: a byte store next to
  // the doubles makes GCC take 32 or 64 lanes at a time, leaving short rows to scalar code.
  constexpr std::ptrdiff_t kB = 128;
  for (std::ptrdiff_t b0 = 0; b0 < m; b0 += kB) {
    const std::ptrdiff_t nb_ = std::min(kB, m - b0);
    double A[kB], B[kB], C[kB], D[kB], E[kB], Fm[kB], MX[kB], MY[kB], MZ[kB];
    double tr[kB], c1[kB], det[kB], x[kB], live[kB], okd[kB], redod[kB];
    for (std::ptrdiff_t t = 0; t < nb_; ++t) {
      const std::ptrdiff_t i = b0 + t;
      const double n = s0[i];
      const double nn = n > 0.0 ? n : 1.0, inv_n = 1.0 / nn;
      const double mx = kExact ? s1[i] / nn : s1[i] * inv_n;
      const double my = kExact ? s2[i] / nn : s2[i] * inv_n;
      const double mz = kExact ? s3[i] / nn : s3[i] * inv_n;
      MX[t] = mx, MY[t] = my, MZ[t] = mz;
      A[t] = s4[i] - n * mx * mx, D[t] = s5[i] - n * mx * my, Fm[t] = s6[i] - n * mx * mz;
      B[t] = s7[i] - n * my * my, E[t] = s8[i] - n * my * mz, C[t] = s9[i] - n * mz * mz;
      eigen_start(A[t], B[t], C[t], D[t], E[t], Fm[t], tr[t], c1[t], det[t]);
      x[t] = 0.0;
      live[t] = tr[t] > 0.0 ? 1.0 : 0.0;
    }
    for (int it = 0; it < (kExact ? 64 : 4); ++it) {
      std::int64_t any = 0;
      for (std::ptrdiff_t t = 0; t < nb_; ++t) {
        newton_step(x[t], live[t], tr[t], c1[t], det[t]);
        any |= static_cast<std::int64_t>(live[t] != 0.0);
      }
      if (any == 0) break;
    }
    for (std::ptrdiff_t t = 0; t < nb_; ++t) {
      const std::ptrdiff_t i = b0 + t;
      const double n = s0[i], mx = MX[t], my = MY[t], mz = MZ[t];
      double l1, hi, nx, ny, nz, nb;
      eigen_finish(A[t], B[t], C[t], D[t], E[t], Fm[t], tr[t], c1[t], x[t], l1, hi, nx, ny, nz,
                   nb);
      if (kExact) {
        const double len = std::sqrt(nb > 0.0 ? nb : 1.0);
        nx /= len, ny /= len, nz /= len;
      } else {
        const double inv_len = 1.0 / std::sqrt(nb > 0.0 ? nb : 1.0);
        nx *= inv_len, ny *= inv_len, nz *= inv_len;
      }
      const double sg = orient_sign(nx, ny, nz);
      const double h = sg * ((nx * (qx[i] - mx) + ny * (qy[i] - my)) + nz * (qz[i] - mz));
      fh[i] = h;
      f0[i] = x[t];
      f1[i] = l1;
      f2[i] = hi;
      okd[t] = (n >= 3.0) & (tr[t] > 0.0) & (nb > 0.0) & window_plane_exists(x[t], l1, hi)
                   ? 1.0
                   : 0.0;
      redod[t] = (live[t] != 0.0) & (n >= 3.0) ? 1.0 : 0.0;
    }
    for (std::ptrdiff_t t = 0; t < nb_; ++t) {
      ok[b0 + t] = static_cast<std::uint8_t>(okd[t] != 0.0);
      redo[b0 + t] = static_cast<std::uint8_t>(redod[t] != 0.0);
    }
  }
}

MIEM_CLONES inline void solve_fits(std::ptrdiff_t m, std::ptrdiff_t cap, const double* __restrict S,
                                   const double* __restrict Q, double* __restrict F,
                                   std::uint8_t* __restrict ok, std::uint8_t* __restrict redo) {
  solve_fits_body<false>(m, cap, S, Q, F, ok, redo);
}

MIEM_CLONES inline void solve_fits_exact(std::ptrdiff_t m, std::ptrdiff_t cap,
                                         const double* __restrict S, const double* __restrict Q,
                                         double* __restrict F, std::uint8_t* __restrict ok,
                                         std::uint8_t* __restrict redo) {
  solve_fits_body<true>(m, cap, S, Q, F, ok, redo);
}

/// The same fit for one cell with the scalar routine (smallest_eigenpair, Newton until done).
inline WindowFit fit_from_sums(const double* s, const Eigen::Vector3d& q) {
  WindowFit fit;
  const double n = s[0];
  fit.edges = s[10];
  if (!(n >= 3.0)) return fit;
  const Eigen::Vector3d mean(s[1] / n, s[2] / n, s[3] / n);
  Eigen::Matrix3d M;
  M(0, 0) = s[4] - n * mean.x() * mean.x();
  M(0, 1) = M(1, 0) = s[5] - n * mean.x() * mean.y();
  M(0, 2) = M(2, 0) = s[6] - n * mean.x() * mean.z();
  M(1, 1) = s[7] - n * mean.y() * mean.y();
  M(1, 2) = M(2, 1) = s[8] - n * mean.y() * mean.z();
  M(2, 2) = s[9] - n * mean.z() * mean.z();
  Eigen::Vector3d nv;
  if (smallest_eigenpair(M, &fit.l0, &fit.l1, &fit.l2, &nv) &&
      window_plane_exists(fit.l0, fit.l1, fit.l2)) {
    fit.ok = true;
    fit.n = n;
    const Eigen::Vector3d o = orient_normal(nv);
    const Eigen::Vector3d w = q - mean;
    fit.height = (o.x() * w.x() + o.y() * w.y()) + o.z() * w.z();
  }
  return fit;
}

// The 11 column sums as separate restrict parameters: pointers into one array (moment k at
// cs + k * stride) would need run-time overlap checks between every pair, more than the
// vectoriser makes, and the loops would run scalar (GCC 12 does not take local restrict
// pointers derived from one parameter as disjoint).
#define MIEM_SUM_PARAMS                                                                         \
  double *__restrict c0, double *__restrict c1, double *__restrict c2, double *__restrict c3, \
      double *__restrict c4, double *__restrict c5, double *__restrict c6,                    \
      double *__restrict c7, double *__restrict c8, double *__restrict c9,                    \
      double *__restrict c10
#define MIEM_SUM_ARGS(cs, stride)                                                          \
  cs, cs + stride, cs + 2 * stride, cs + 3 * stride, cs + 4 * stride, cs + 5 * stride,     \
      cs + 6 * stride, cs + 7 * stride, cs + 8 * stride, cs + 9 * stride, cs + 10 * stride

// The class bytes of up to kSumChunk cells as 1.0 / 0.0 doubles (w: kInPlane, l: kLine). The
// sums' loops read these, not the bytes: a byte next to the doubles makes GCC take 32 cells at a
// time, and the 11 sums of 32 cells spill to the stack (three instructions in four were moves).
inline constexpr std::ptrdiff_t kSumChunk = 64;
inline __attribute__((always_inline)) void class_weights(const std::uint8_t* __restrict cl,
                                                         std::ptrdiff_t n, double* __restrict w,
                                                         double* __restrict l) {
  for (std::ptrdiff_t j = 0; j < n; ++j) {
    w[j] = (cl[j] & kInPlane) != 0 ? 1.0 : 0.0;
    l[j] = (cl[j] & kLine) != 0 ? 1.0 : 0.0;
  }
}

MIEM_CLONES inline void add_row_sums(const std::uint8_t* __restrict cl, std::ptrdiff_t n,
                                     const double* __restrict px, const double* __restrict py,
                                     const double* __restrict pz, double sign, MIEM_SUM_PARAMS) {
  for (std::ptrdiff_t j0 = 0; j0 < n; j0 += kSumChunk) {
    const std::ptrdiff_t m = std::min(kSumChunk, n - j0);
    double wi[kSumChunk], li[kSumChunk];
    class_weights(cl + j0, m, wi, li);
    for (std::ptrdiff_t t = 0; t < m; ++t) {
      const std::ptrdiff_t j = j0 + t;
      const bool in = wi[t] != 0.0;
      const double w = in ? sign : 0.0, l = li[t] != 0.0 ? sign : 0.0;
      const double qx = px[j], qy = py[j], qz = pz[j];
      const double x = in ? qx : 0.0, y = in ? qy : 0.0, z = in ? qz : 0.0;
      c0[j] += w;
      c1[j] += w * x;
      c2[j] += w * y;
      c3[j] += w * z;
      c4[j] += w * (x * x);
      c5[j] += w * (x * y);
      c6[j] += w * (x * z);
      c7[j] += w * (y * y);
      c8[j] += w * (y * z);
      c9[j] += w * (z * z);
      c10[j] += l;
    }
  }
}

MIEM_CLONES inline void move_row_sums(
    const std::uint8_t* __restrict ca, const double* __restrict ax, const double* __restrict ay,
    const double* __restrict az, const std::uint8_t* __restrict cb, const double* __restrict bx,
    const double* __restrict by, const double* __restrict bz, std::ptrdiff_t n, MIEM_SUM_PARAMS) {
  for (std::ptrdiff_t j0 = 0; j0 < n; j0 += kSumChunk) {
    const std::ptrdiff_t m = std::min(kSumChunk, n - j0);
    double wa[kSumChunk], la[kSumChunk], wb[kSumChunk], lb[kSumChunk];
    class_weights(ca + j0, m, wa, la);
    class_weights(cb + j0, m, wb, lb);
    for (std::ptrdiff_t t = 0; t < m; ++t) {
      const std::ptrdiff_t j = j0 + t;
      const bool ia = wa[t] != 0.0, ib = wb[t] != 0.0;
      const double pxa = ax[j], pya = ay[j], pza = az[j], pxb = bx[j], pyb = by[j], pzb = bz[j];
      const double xa = ia ? pxa : 0.0, ya = ia ? pya : 0.0, za = ia ? pza : 0.0;
      const double xb = ib ? pxb : 0.0, yb = ib ? pyb : 0.0, zb = ib ? pzb : 0.0;
      c0[j] += wa[t] - wb[t];
      c1[j] += xa - xb;
      c2[j] += ya - yb;
      c3[j] += za - zb;
      c4[j] += xa * xa - xb * xb;
      c5[j] += xa * ya - xb * yb;
      c6[j] += xa * za - xb * zb;
      c7[j] += ya * ya - yb * yb;
      c8[j] += ya * za - yb * zb;
      c9[j] += za * za - zb * zb;
      c10[j] += la[t] - lb[t];
    }
  }
}

// Adds sign * (1, x, y, z, xx, xy, xz, yy, yz, zz) of the kInPlane cells and sign * 1 of the
// kLine cells of one row, n cells given as SoA coordinates relative to the tile's origin (px,
// py, pz), to the SoA column sums cs (moment k at cs + k * stride). Branch-free: it vectorises.
inline void add_row_moments(const std::uint8_t* cl, std::ptrdiff_t n, const double* px,
                            const double* py, const double* pz, double sign, double* cs,
                            std::ptrdiff_t stride) {
  add_row_sums(cl, n, px, py, pz, sign, MIEM_SUM_ARGS(cs, stride));
}

// The window slides down one row: adds the moments of row a (class bytes ca, SoA coordinates
// ax, ay, az) and subtracts those of row b, in one pass over the column sums (as two
// add_row_moments calls, but each column sum read and written once).
inline void move_row_moments(const std::uint8_t* ca, const double* ax, const double* ay,
                             const double* az, const std::uint8_t* cb, const double* bx,
                             const double* by, const double* bz, std::ptrdiff_t n, double* cs,
                             std::ptrdiff_t stride) {
  move_row_sums(ca, ax, ay, az, cb, bx, by, bz, n, MIEM_SUM_ARGS(cs, stride));
}
#undef MIEM_SUM_ARGS
#undef MIEM_SUM_PARAMS

// n points stored x, y, z, x, y, z, ... (a dense grid's row) as SoA coordinates relative to
// (ox, oy, oz): load_rel's arithmetic in vector code (the interleaved loads vectorise in the
// AVX2 clones; the generic loop below runs one point at a time).
MIEM_CLONES inline void load_rel_xyz(const double* __restrict p, std::ptrdiff_t n, double ox,
                                     double oy, double oz, double* __restrict x,
                                     double* __restrict y, double* __restrict z) {
  for (std::ptrdiff_t j = 0; j < n; ++j) {
    x[j] = p[3 * j] - ox;
    y[j] = p[3 * j + 1] - oy;
    z[j] = p[3 * j + 2] - oz;
  }
}

// The same for n points stored as three planes, x at p, y at p + yo, z at p + 2 yo (the
// stream's ring).
MIEM_CLONES inline void load_rel_planes(const double* __restrict p, std::ptrdiff_t yo,
                                        std::ptrdiff_t n, double ox, double oy, double oz,
                                        double* __restrict x, double* __restrict y,
                                        double* __restrict z) {
  const double* __restrict py = p + yo;
  const double* __restrict pz = p + 2 * yo;
  for (std::ptrdiff_t j = 0; j < n; ++j) {
    x[j] = p[j] - ox;
    y[j] = py[j] - oy;
    z[j] = pz[j] - oz;
  }
}

// Asks for the cache lines of `bytes` bytes from p on.
inline void prefetch_bytes(const void* p, std::ptrdiff_t bytes) {
  const char* a = static_cast<const char*>(p);
  for (std::ptrdiff_t off = 0; off < bytes; off += 64) __builtin_prefetch(a + off);
}

// Asks for the cells [c0, c1) of a row stored as three planes (x at p, y at p + plane, z at
// p + 2 plane: the stream's ring), a few strips before they are read: the stream reads each
// row strip by strip, rows that left the L2 cache pushes ago, in segments too short for the
// hardware prefetcher to run ahead of.
template <typename T>
inline void prefetch_planes(const T* p, std::ptrdiff_t plane, std::ptrdiff_t c0,
                            std::ptrdiff_t c1) {
  for (int q = 0; q < 3; ++q) {
    prefetch_bytes(p + q * plane + c0, (c1 - c0) * static_cast<std::ptrdiff_t>(sizeof(T)));
  }
}

// Row r, columns [c0, c0 + n), as SoA coordinates relative to (ox, oy, oz).
template <typename T>
void load_rel(const GridView<T>& g, std::ptrdiff_t r, std::ptrdiff_t c0, std::ptrdiff_t n,
              double ox, double oy, double oz, double* __restrict x, double* __restrict y,
              double* __restrict z) {
  const T* base = g.data + r * g.row_stride + c0 * g.col_stride;
  const std::ptrdiff_t ps = g.col_stride, yo = g.coord_stride, zo = 2 * g.coord_stride;
  // The next row's cells are read next: ask for them now (a tile's row segment is about one
  // page, too short for the hardware prefetcher to start on its own). One range when the
  // coordinates interleave within the segment, one per coordinate when they lie in planes (a
  // range from x to z would span the planes between, a whole grid); cell by cell when cells
  // lie a cache line or more apart (column-major grids).
  if (r + 1 < g.rows) {
    constexpr std::ptrdiff_t sz = static_cast<std::ptrdiff_t>(sizeof(T));
    const std::ptrdiff_t span = (n - 1) * ps + 1;  // one coordinate's elements
    const bool one = zo < span;
    for (int q = 0; q < (one ? 1 : 3); ++q) {
      const T* nb = base + g.row_stride + q * yo;
      if (ps * sz <= 64) {
        prefetch_bytes(nb, (one ? span + zo : span) * sz);
      } else {
        for (std::ptrdiff_t j = 0; j < n; ++j) __builtin_prefetch(nb + j * ps);
      }
    }
  }
  if constexpr (std::is_same_v<T, double>) {
    if (ps == 3 && yo == 1) {
      load_rel_xyz(base, n, ox, oy, oz, x, y, z);
      return;
    }
    if (ps == 1) {
      load_rel_planes(base, yo, n, ox, oy, oz, x, y, z);
      return;
    }
  }
  for (std::ptrdiff_t j = 0; j < n; ++j) {
    const T* q = base + j * ps;
    x[j] = static_cast<double>(q[0]) - ox;
    y[j] = static_cast<double>(q[yo]) - oy;
    z[j] = static_cast<double>(q[zo]) - oz;
  }
}

/// S + k * cap + j = the sum of col + k * stride over columns j - half .. j + half, for j in
/// [0, n), as running sums: S[j] = S[j - 1] + (col[j + half] - col[j - half - 1]).
/// The 11 running sums are serial chains, so they run side by side in vector lanes, 4 moments a
/// vector (the last vector's fourth lane repeats moment 10 and is not stored), 4 columns a step:
/// the columns' differences are loaded per moment, transposed to per column, added in turn and
/// transposed back. Each moment's additions are the scalar chain's, in its order: the same bits.
MIEM_CLONES inline void box_sums(const double* __restrict col, std::ptrdiff_t stride,
                                 std::ptrdiff_t half, std::ptrdiff_t n, std::ptrdiff_t cap,
                                 double* __restrict S) {
  typedef double V __attribute__((vector_size(32)));
  typedef long long M __attribute__((vector_size(32)));
  const M lo = {0, 4, 2, 6}, hi = {1, 5, 3, 7}, first = {0, 1, 4, 5}, second = {2, 3, 6, 7};
  auto transpose = [&](V& a, V& b, V& c, V& d) {
    const V u0 = __builtin_shuffle(a, b, lo), u1 = __builtin_shuffle(a, b, hi);
    const V u2 = __builtin_shuffle(c, d, lo), u3 = __builtin_shuffle(c, d, hi);
    a = __builtin_shuffle(u0, u2, first);
    b = __builtin_shuffle(u1, u3, first);
    c = __builtin_shuffle(u0, u2, second);
    d = __builtin_shuffle(u1, u3, second);
  };
  // (vectors by reference: by value they would change the default clone's ABI)
  auto diff = [half](V& v, const double* c, std::ptrdiff_t j) {
    V a, b;
    __builtin_memcpy(&a, c + j + half, sizeof(V));
    __builtin_memcpy(&b, c + j - half - 1, sizeof(V));
    v = a - b;
  };
  auto store = [](double* p, const V& v) { __builtin_memcpy(p, &v, sizeof(V)); };
  if (n <= 0) return;
  for (int k = 0; k < kMoments; ++k) {
    const double* c = col + k * stride;
    double a = 0.0;
    for (std::ptrdiff_t d = -half; d <= half; ++d) a += c[d];
    S[k * cap] = a;
  }
  // The three vectors of moments (0-3, 4-7, 8-10) in one loop: three independent chains of
  // additions side by side (one vector at a time, each step waited for the last addition).
  const double* c[12];
  double* s[12];
  for (int q = 0; q < 12; ++q) {
    const int k = std::min(q, kMoments - 1);
    c[q] = col + k * stride;
    s[q] = S + k * cap;
  }
  V acc[3];
  for (int v = 0; v < 3; ++v) {
    acc[v] = V{s[4 * v][0], s[4 * v + 1][0], s[4 * v + 2][0], s[4 * v + 3][0]};
  }
  std::ptrdiff_t j = 1;
  for (; j + 4 <= n; j += 4) {
    for (int v = 0; v < 3; ++v) {
      const double* const* cv = c + 4 * v;
      double* const* sv = s + 4 * v;
      V d0, d1, d2, d3;
      diff(d0, cv[0], j);
      diff(d1, cv[1], j);
      diff(d2, cv[2], j);
      diff(d3, cv[3], j);
      transpose(d0, d1, d2, d3);  // now d_t = the moments' differences at column j + t
      acc[v] += d0;
      d0 = acc[v];
      acc[v] += d1;
      d1 = acc[v];
      acc[v] += d2;
      d2 = acc[v];
      acc[v] += d3;
      d3 = acc[v];
      transpose(d0, d1, d2, d3);  // back to per moment
      store(sv[0] + j, d0);
      store(sv[1] + j, d1);
      store(sv[2] + j, d2);
      if (v < 2) store(sv[3] + j, d3);
    }
  }
  for (; j < n; ++j) {
    for (int k = 0; k < kMoments; ++k) {
      const double* ck = col + k * stride;
      double* sk = S + k * cap;
      sk[j] = sk[j - 1] + (ck[j + half] - ck[j - half - 1]);
    }
  }
}

/// The cell counts of n window sums (a: NORMAL cells, b: feature-line cells) rounded to whole
/// numbers (sums of +-1, whole already; std::round in vector code).
MIEM_CLONES inline void round_counts(std::ptrdiff_t n, double* __restrict a, double* __restrict b) {
  for (std::ptrdiff_t j = 0; j < n; ++j) {
    a[j] = std::round(a[j]);
    b[j] = std::round(b[j]);
  }
}

/// What row_solve leaves for one row segment: the fit of entry e (e = j, the segment's column,
/// or with `compact` the e-th wanted cell) is okf[e], n = S[e], height, l0, l1, l2 at F + k * cap
/// + e and the feature-line cells at S + 10 * cap + e (redo[e]: solved by solve_fits_exact).
/// Not compact: only the entries [j0, j1) are set, the span of the wanted cells.
struct RowFits {
  const double* S;
  const double* F;
  const std::uint8_t* okf;
  const std::uint8_t* redo;
  std::ptrdiff_t cap;
  bool compact;
  std::ptrdiff_t j0, j1;

  WindowFit fit(std::ptrdiff_t e) const {
    WindowFit f;
    f.ok = okf[e] != 0;
    f.n = S[e];
    f.height = F[e];
    f.l0 = F[cap + e];
    f.l1 = F[2 * cap + e];
    f.l2 = F[3 * cap + e];
    if (redo[e] && !f.ok) f.n = f.height = 0.0;  // fit_from_sums leaves them unset
    f.edges = S[10 * cap + e];
    return f;
  }
};

/// Whether the sums of a window with n cells (s0), second moments s4, s7, s9 about the tile's
/// point and l1 lost the plane (refit_cancelled).
inline __attribute__((always_inline)) bool cancelled(double s0, double s4, double s7, double s9,
                                                     double l1) {
  return (s0 >= 3.0) & (l1 <= kRefitRatio * (s4 + s7 + s9));
}

/// Whether any of m entries did (nearly always none): one pass in vector clones (the baseline
/// build has no vector form of a double comparison's flag as an integer: a scalar loop there).
MIEM_CLONES inline bool any_cancelled(std::ptrdiff_t m, const double* __restrict s0,
                                      const double* __restrict s4, const double* __restrict s7,
                                      const double* __restrict s9, const double* __restrict l1) {
  std::int64_t any = 0;
  for (std::ptrdiff_t e = 0; e < m; ++e) any |= cancelled(s0[e], s4[e], s7[e], s9[e], l1[e]);
  return any != 0;
}

/// The solved entries [e0, e1) of row_solve whose sums lost the plane (kRefitRatio in
/// plane_math.hpp; at least 3 cells, whether the sums found a plane or not: cancellation may
/// decide either), fitted again directly as the reference fits them: their fit from refit(j)
/// (j: the segment's column of entry e; compact, the e-th wanted one from j0).
template <typename Refit>
void refit_cancelled(std::ptrdiff_t e0, std::ptrdiff_t e1, bool compact, std::ptrdiff_t j0,
                     const std::uint8_t* wrow, std::ptrdiff_t cap, double* S, double* F,
                     std::uint8_t* okf, std::uint8_t* redo, Refit refit) {
  const double *s0 = S, *s4 = S + 4 * cap, *s7 = S + 7 * cap, *s9 = S + 9 * cap;
  const double* l1 = F + 2 * cap;
  const auto lost = [&](std::ptrdiff_t e) { return cancelled(s0[e], s4[e], s7[e], s9[e], l1[e]); };
  if (!any_cancelled(e1 - e0, s0 + e0, s4 + e0, s7 + e0, s9 + e0, l1 + e0)) return;
  std::ptrdiff_t j = j0 - 1;
  for (std::ptrdiff_t e = e0; e < e1; ++e) {
    if (compact) {
      for (++j; !wrow[j];) ++j;  // the e-th wanted column
    } else {
      j = e;
    }
    if (!lost(e)) continue;
    const WindowFit f = refit(j);
    okf[e] = f.ok ? 1 : 0;
    redo[e] = 0;
    F[e] = f.ok ? f.height : 0.0;
    F[cap + e] = f.l0, F[2 * cap + e] = f.l1, F[3 * cap + e] = f.l2;
  }
}

/// The window fits of the wanted cells of one row segment of `ncols` cells from the column sums
/// of the window's rows: `col` + k * stride + j is moment k of the segment's column j, with
/// `half` + 1 valid (or zero-padded) columns on either side. wrow[j]: fit cell j (m of them);
/// Q (3 x cap, SoA): the cells relative to the sums' origin, overwritten. S (kMoments x cap),
/// F (4 x cap), ok and redo (cap each) are scratch. Calls visit(j, fit) in ascending j.
/// Shared by the batch window sweep below and the stream's running sums. row_solve: the same
/// fits left in the scratch (RowFits) for a caller that reads a whole row at once. refit(j):
/// cell j's window fitted directly, for the cells whose sums lose the plane (refit_cancelled).
template <typename Refit>
RowFits row_solve(const double* col, std::ptrdiff_t stride, std::ptrdiff_t half,
                  std::ptrdiff_t ncols, std::ptrdiff_t cap, const std::uint8_t* wrow,
                  std::ptrdiff_t m, double* S, double* Q, double* F, std::uint8_t* okf,
                  std::uint8_t* redo, Refit refit) {
  // The wanted cells' span [j0, j1): a later height pass wants the cells around a removed one.
  std::ptrdiff_t j0 = 0, j1 = ncols;
  while (j0 < j1 && !wrow[j0]) ++j0;
  while (j1 > j0 && !wrow[j1 - 1]) --j1;
  // Box sums along the row: 11 running sums, one column in and one out per cell. The column
  // differences first (a loop that vectorises), then the running sums over them. Running from
  // column 0 (the same sums whatever the span), up to the span's end.
  box_sums(col, stride, half, j1, cap, S);
  const bool compact = 4 * m < j1 - j0;  // few wanted cells: solve only those
  if (compact) {
    std::ptrdiff_t k2 = 0;
    for (std::ptrdiff_t j = j0; j < j1; ++j) {
      if (!wrow[j]) continue;
      for (int k = 0; k < kMoments; ++k) S[k * cap + k2] = S[k * cap + j];
      for (int k = 0; k < 3; ++k) Q[k * cap + k2] = Q[k * cap + j];
      ++k2;
    }
  }
  // the entries solved: [e0, e1) (each cell's fit is its own lanes' arithmetic: the same bits
  // whichever cells share its block)
  const std::ptrdiff_t e0 = compact ? 0 : j0, e1 = compact ? m : j1, ns = e1 - e0;
  round_counts(ns, S + e0, S + 10 * cap + e0);
  solve_fits(ns, cap, S + e0, Q + e0, F + e0, okf + e0, redo + e0);
  // The cells whose Newton iteration has not ended in 4 steps (rough or strongly anisotropic
  // windows, as a profiler's 0.05 x 1 mm cells make): again in vector code, kRedo at a time,
  // with fit_from_sums's arithmetic (its results bit for bit).
  {
    constexpr std::ptrdiff_t kRedo = 32;
    double S2[kMoments * kRedo], Q2[3 * kRedo], F2[4 * kRedo];
    std::uint8_t ok2[kRedo], redo2[kRedo];
    std::ptrdiff_t idx[kRedo], nr = 0;
    auto flush = [&]() {
      solve_fits_exact(nr, kRedo, S2, Q2, F2, ok2, redo2);
      for (std::ptrdiff_t t = 0; t < nr; ++t) {
        for (int k = 0; k < 4; ++k) F[k * cap + idx[t]] = F2[k * kRedo + t];
        okf[idx[t]] = ok2[t];
      }
      nr = 0;
    };
    std::uint8_t any = 0;  // most rows have none: one vector pass
    for (std::ptrdiff_t e = e0; e < e1; ++e) any |= redo[e];
    for (std::ptrdiff_t e = any ? e0 : e1; e < e1; ++e) {
      if (!redo[e]) continue;
      for (int k = 0; k < kMoments; ++k) S2[k * kRedo + nr] = S[k * cap + e];
      for (int k = 0; k < 3; ++k) Q2[k * kRedo + nr] = Q[k * cap + e];
      idx[nr++] = e;
      if (nr == kRedo) flush();
    }
    if (nr > 0) flush();
  }
  refit_cancelled(e0, e1, compact, j0, wrow, cap, S, F, okf, redo, refit);
  return RowFits{S, F, okf, redo, cap, compact, j0, j1};
}

template <typename Refit, typename Visit>
void row_fits(const double* col, std::ptrdiff_t stride, std::ptrdiff_t half, std::ptrdiff_t ncols,
              std::ptrdiff_t cap, const std::uint8_t* wrow, std::ptrdiff_t m, double* S,
              double* Q, double* F, std::uint8_t* okf, std::uint8_t* redo, Refit refit,
              Visit visit) {
  const RowFits rf =
      row_solve(col, stride, half, ncols, cap, wrow, m, S, Q, F, okf, redo, refit);
  std::ptrdiff_t k2 = 0;
  for (std::ptrdiff_t j = 0; j < ncols; ++j) {
    if (!wrow[j]) continue;
    visit(j, rf.fit(rf.compact ? k2++ : j));
  }
}

/// The window fit of one cell from its window's cells directly, in two passes: the mean of the
/// plane's cells relative to the cell, then their moments about that mean, so no cancellation
/// (as the reference's fit). class_of(rr, cc): the class byte of cell (rr, cc) of g.
template <typename T, typename ClassOf>
WindowFit direct_fit_by(const GridView<T>& g, ClassOf class_of, std::ptrdiff_t r,
                        std::ptrdiff_t c, std::ptrdiff_t half) {
  const std::ptrdiff_t r0 = std::max<std::ptrdiff_t>(0, r - half);
  const std::ptrdiff_t r1 = std::min(g.rows - 1, r + half);
  const std::ptrdiff_t c0 = std::max<std::ptrdiff_t>(0, c - half);
  const std::ptrdiff_t c1 = std::min(g.cols - 1, c + half);
  const Eigen::Vector3d o = g(r, c);
  double s[kMoments] = {0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0};
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  for (std::ptrdiff_t rr = r0; rr <= r1; ++rr) {
    for (std::ptrdiff_t cc = c0; cc <= c1; ++cc) {
      const std::uint8_t k = class_of(rr, cc);
      if (k & kInPlane) {
        s[0] += 1.0;
        sum += g(rr, cc) - o;
      } else if (k & kLine) {
        s[10] += 1.0;
      }
    }
  }
  const Eigen::Vector3d mean = s[0] > 0.0 ? Eigen::Vector3d(sum / s[0]) : sum;
  for (std::ptrdiff_t rr = r0; rr <= r1 && s[0] >= 3.0; ++rr) {
    for (std::ptrdiff_t cc = c0; cc <= c1; ++cc) {
      if (!(class_of(rr, cc) & kInPlane)) continue;
      const Eigen::Vector3d q = g(rr, cc) - o - mean;
      s[4] += q.x() * q.x();
      s[5] += q.x() * q.y();
      s[6] += q.x() * q.z();
      s[7] += q.y() * q.y();
      s[8] += q.y() * q.z();
      s[9] += q.z() * q.z();
    }
  }
  // the moments are about the mean (s[1..3] = 0): the cell lies at -mean from it
  WindowFit f = fit_from_sums(s, -mean);
  f.edges = s[10];
  return f;
}

/// direct_fit_by over a class array `cls` laid out as g (g.cols per row).
template <typename T>
WindowFit direct_fit(const GridView<T>& g, const std::uint8_t* cls, std::ptrdiff_t r,
                     std::ptrdiff_t c, std::ptrdiff_t half) {
  const std::ptrdiff_t W = g.cols;
  return direct_fit_by(
      g, [cls, W](std::ptrdiff_t rr, std::ptrdiff_t cc) { return cls[rr * W + cc]; }, r, c,
      half);
}

/// window_fits (below) with the rows swept by the sums handed over whole: visit_row(i0, ncols,
/// wrow, rf) for the wanted cells i0 + j (wrow[j]) of one row segment, their fits in `rf`
/// (RowFits); visit(i, fit) for the cells fitted one by one (direct fits, no plane).
template <typename T, typename Want, typename Visit, typename VisitRow>
void window_fits_rows(const GridView<T>& g, const std::uint8_t* cls, int window, int num_threads,
                      std::vector<FitScratch>& scratch, Want want, Visit visit,
                      VisitRow visit_row) {
  constexpr std::ptrdiff_t kBand = 64, kStrip = 128, kDirect = 24;
  const std::ptrdiff_t H = g.rows, W = g.cols, half = window / 2;
  const std::ptrdiff_t tiles_r = (H + kBand - 1) / kBand, tiles_c = (W + kStrip - 1) / kStrip;
  const std::ptrdiff_t ntiles = tiles_r * tiles_c;
  const std::ptrdiff_t span = std::min(W, kStrip + 2 * half);  // columns with sums
  const std::ptrdiff_t cap = std::min(W, kStrip);               // cells solved per row
  // Padded column sums (kMoments x (span + window + 1)), fit inputs (kMoments + 3 coordinates)
  // and outputs (4) per tile column, the rows of the window (window + 1 rows x 3 x span).
  const std::size_t need = static_cast<std::size_t>(kMoments * (span + 2 * half + 2) +
                                                    (kMoments + 3 + 4) * cap +
                                                    (2 * half + 2) * 3 * span);
  const int nt = thread_count(num_threads, H * W);
  if (scratch.size() < static_cast<std::size_t>(nt)) scratch.resize(static_cast<std::size_t>(nt));

  // Each tile's wanted cells (how many, its last row with one, the column after its last one),
  // found band by band along whole rows before the tiles run: a tile's own rows are 128-byte
  // pieces a row apart, each a cache miss when read first, and that scan in the tile loop took
  // a quarter of the heights' time.
  std::vector<std::ptrdiff_t>& wanted = scratch[0].tiles;  // 3 per tile
  wanted.resize(static_cast<std::size_t>(3 * ntiles));
#pragma omp parallel for schedule(static) num_threads(nt) if (nt > 1)
  for (std::ptrdiff_t b = 0; b < tiles_r; ++b) {
    const Want want_l = want;  // (a local copy: see the tile loop)
    const std::ptrdiff_t tr0 = b * kBand, tr1 = std::min(H, tr0 + kBand);
    std::ptrdiff_t* wt = wanted.data() + 3 * b * tiles_c;
    for (std::ptrdiff_t k = 0; k < tiles_c; ++k) {
      wt[3 * k] = 0, wt[3 * k + 1] = tr0, wt[3 * k + 2] = k * kStrip;
    }
    for (std::ptrdiff_t r = tr0; r < tr1; ++r) {
      for (std::ptrdiff_t k = 0; k < tiles_c; ++k) {
        const std::ptrdiff_t tc0 = k * kStrip, tc1 = std::min(W, tc0 + kStrip);
        std::ptrdiff_t m = 0;
        for (std::ptrdiff_t c = tc0; c < tc1; ++c) m += want_l(r * W + c) ? 1 : 0;
        if (m == 0) continue;
        wt[3 * k] += m;
        wt[3 * k + 1] = r;
        for (std::ptrdiff_t c = tc1; c > wt[3 * k + 2]; --c)
          if (want_l(r * W + c - 1)) {
            wt[3 * k + 2] = c;
            break;
          }
      }
    }
  }

#pragma omp parallel for schedule(dynamic, 1) num_threads(nt) if (nt > 1)
  for (std::ptrdiff_t t = 0; t < ntiles; ++t) {
    int tid = 0;
#ifdef MIEM_HAVE_OPENMP
    tid = omp_get_thread_num();
#endif
    FitScratch& sc = scratch[static_cast<std::size_t>(tid)];
    if (sc.buf.size() < need) sc.buf.resize(need);
    if (sc.flags.size() < static_cast<std::size_t>(3 * cap)) sc.flags.resize(3 * cap);
    const std::ptrdiff_t tr0 = (t / tiles_c) * kBand, tc0 = (t % tiles_c) * kStrip;
    const std::ptrdiff_t tr1 = std::min(H, tr0 + kBand), tc1 = std::min(W, tc0 + kStrip);
    // A local copy of the predicate: through the caller's closure each byte store to wrow
    // would reload its captures (char stores alias everything), and the loops would not vectorise.
    const Want want_l = want;
    const std::ptrdiff_t* wt = wanted.data() + 3 * t;
    const std::ptrdiff_t n_wanted = wt[0];
    const std::ptrdiff_t last = wt[1];  // the tile's last row with a wanted cell
    const std::ptrdiff_t cend = wt[2];  // after the tile's last column with a wanted cell
    if (n_wanted == 0) continue;
    if (n_wanted <= kDirect) {  // a few cells: their windows directly, cheaper than the sums
      for (std::ptrdiff_t r = tr0; r < tr1; ++r)
        for (std::ptrdiff_t c = tc0; c < tc1; ++c)
          if (want(r * W + c)) visit(r * W + c, direct_fit(g, cls, r, c, half));
      continue;
    }
    const std::ptrdiff_t R0 = std::max<std::ptrdiff_t>(0, tr0 - half);
    const std::ptrdiff_t R1 = std::min(H, tr1 + half);
    const std::ptrdiff_t C0 = std::max<std::ptrdiff_t>(0, tc0 - half);
    const std::ptrdiff_t C1 = std::min(W, tc1 + half);
    // Columns with sums: up to half past the last wanted column (each column's sums are its own;
    // the box sums of a cell read half columns either side).
    const std::ptrdiff_t nc = std::min(C1, cend + half) - C0;
    // Local origin: a NORMAL cell of the region, searched from the tile's middle row.
    Eigen::Vector3d origin = Eigen::Vector3d::Zero();
    bool any = false;
    const std::ptrdiff_t mid = (tr0 + tr1) / 2, nr = R1 - R0;
    for (std::ptrdiff_t k = 0; k < nr && !any; ++k) {
      const std::ptrdiff_t r = R0 + (mid - R0 + k) % nr;
      for (std::ptrdiff_t c = C0; c < C1; ++c)
        if (cls[r * W + c] & kInPlane) {
          origin = g(r, c);
          any = true;
          break;
        }
    }
    if (!any) {  // no NORMAL cell within reach: no plane for any cell of the tile
      for (std::ptrdiff_t r = tr0; r < tr1; ++r)
        for (std::ptrdiff_t c = tc0; c < tc1; ++c)
          if (want(r * W + c)) visit(r * W + c, WindowFit{});
      continue;
    }
    // Column sums, zero-padded by half + 1 columns on both sides (the window's clipping).
    const std::ptrdiff_t pad = half + 1, stride = span + 2 * pad;
    double* cs = sc.buf.data();                 // kMoments x stride
    double* S = cs + kMoments * stride;         // kMoments x cap: window sums per tile column
    double* Q = S + kMoments * cap;             // 3 x cap: the cell, relative to the origin
    double* F = Q + 3 * cap;                    // 4 x cap: fits
    double* ring = F + 4 * cap;  // (window + 1) rows x 3 x span: rows in the window, SoA
    std::uint8_t* okf = sc.flags.data();
    std::uint8_t* redo = okf + cap;
    std::uint8_t* wrow = redo + cap;  // want() of this row's cells
    const double ox = origin.x(), oy = origin.y(), oz = origin.z();
    const std::ptrdiff_t ncols = tc1 - tc0, nring = 2 * half + 2;
    auto ring_row = [&](std::ptrdiff_t rr) { return ring + (rr % nring) * 3 * span; };
    // A row enters the window (loaded once, kept in the ring) or leaves it (read from the ring).
    auto add_row = [&](std::ptrdiff_t rr, double sign) {
      double* x = ring_row(rr);
      if (sign > 0.0) load_rel(g, rr, C0, nc, ox, oy, oz, x, x + span, x + 2 * span);
      add_row_moments(cls + rr * W + C0, nc, x, x + span, x + 2 * span, sign, cs + pad, stride);
    };
    std::fill(cs, cs + kMoments * stride, 0.0);
    for (std::ptrdiff_t rr = std::max<std::ptrdiff_t>(0, tr0 - half);
         rr <= std::min(H - 1, tr0 + half); ++rr)
      add_row(rr, 1.0);
    // Rows after the last wanted one are not swept (a later pass wants a few cells only).
    for (std::ptrdiff_t r = tr0; r <= last; ++r) {
      if (r > tr0) {
        const std::ptrdiff_t ra = r + half, rb = r - half - 1;  // row in, row out
        if (ra < H && rb >= 0) {
          double* a = ring_row(ra);
          const double* b = ring_row(rb);
          load_rel(g, ra, C0, nc, ox, oy, oz, a, a + span, a + 2 * span);
          move_row_moments(cls + ra * W + C0, a, a + span, a + 2 * span, cls + rb * W + C0, b,
                           b + span, b + 2 * span, nc, cs + pad, stride);
        } else if (ra < H) {
          add_row(ra, 1.0);
        } else if (rb >= 0) {
          add_row(rb, -1.0);
        }
      }
      std::ptrdiff_t m = 0;
      {
        std::uint8_t* __restrict wr = wrow;
        const std::ptrdiff_t i0 = r * W + tc0;
        for (std::ptrdiff_t j = 0; j < ncols; ++j) {
          const bool w = want_l(i0 + j);
          wr[j] = w;
          m += w;
        }
      }
      if (m == 0) continue;
      {
        const double* x = ring_row(r) + (tc0 - C0);
        const std::ptrdiff_t nq = cend - tc0;  // no cell after it is wanted
        std::copy(x, x + nq, Q);
        std::copy(x + span, x + span + nq, Q + cap);
        std::copy(x + 2 * span, x + 2 * span + nq, Q + 2 * cap);
      }
      const RowFits rf =
          row_solve(cs + pad + (tc0 - C0), stride, half, ncols, cap, wrow, m, S, Q, F, okf, redo,
                    [&](std::ptrdiff_t j) { return direct_fit(g, cls, r, tc0 + j, half); });
      visit_row(r * W + tc0, ncols, static_cast<const std::uint8_t*>(wrow), rf);
    }
  }
}

/// Calls visit(i, fit) (i = r * cols + c) for every cell with want(i), where cls[i] gives the
/// class of each cell (kInPlane, kLine or 0). A tile without wanted cells costs one scan of its
/// want bytes. `fit.edges` is exact only where fit.ok (a tile without a NORMAL cell reports 0).
/// `scratch` is grown to one buffer per thread (sized by the grid, not the tile).
template <typename T, typename Want, typename Visit>
void window_fits(const GridView<T>& g, const std::uint8_t* cls, int window, int num_threads,
                 std::vector<FitScratch>& scratch, Want want, Visit visit) {
  window_fits_rows(g, cls, window, num_threads, scratch, want, visit,
                   [&](std::ptrdiff_t i0, std::ptrdiff_t ncols, const std::uint8_t* wrow,
                       const RowFits& rf) {
                     std::ptrdiff_t k2 = 0;
                     for (std::ptrdiff_t j = 0; j < ncols; ++j) {
                       if (!wrow[j]) continue;
                       visit(i0 + j, rf.fit(rf.compact ? k2++ : j));
                     }
                   });
}

}  // namespace miem::detail
