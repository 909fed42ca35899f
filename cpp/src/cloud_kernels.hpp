// Kernels of the unorganized-cloud stages (unorganized.cpp, floating_groups.cpp,
// cloud_height_test.cpp): candidate gathers, selections, local plane fits, the point judge
// and the cell-parallel loop. Internal to the core.
#pragma once

#include <algorithm>
#include <chrono>
#include <ctime>
#include <string>
#include <type_traits>
#include <utility>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <vector>

#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>

#ifdef __SSE2__
#include <emmintrin.h>
#endif

#include "miem/neighbor_grid.hpp"
#include "miem/unorganized.hpp"
#include "parallel.hpp"
#include "plane_math.hpp"
#include "vector_clones.hpp"

namespace miem::cloud {

inline constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
inline constexpr double kInf = std::numeric_limits<double>::infinity();
inline constexpr double kPi = 3.14159265358979323846;
inline constexpr double kRadToDeg = 57.29577951308232;
inline constexpr double kDegToRad = 0.017453292519943295;
inline constexpr int kMaxDirections = 8;

template <typename T>
void check_view(const PointsView<T>& points) {
  if (points.size < 0 || (points.size > 0 && points.data == nullptr)) {
    throw std::invalid_argument("points: null data");
  }
}

// Candidate points gathered from a box of cells, structure of arrays (absolute coordinates, so
// q - p is computed exactly as a brute-force search would).
struct Gather {
  std::vector<double> x, y, z;
  std::vector<std::uint32_t> id;
  std::size_t n = 0;

  void clear() { n = 0; }
  void push(const Eigen::Vector3d& q, std::uint32_t j) {
    if (n == x.size()) {
      const std::size_t cap = std::max<std::size_t>(64, 2 * n);
      x.resize(cap);
      y.resize(cap);
      z.resize(cap);
      id.resize(cap);
    }
    x[n] = q.x();
    y[n] = q.y();
    z[n] = q.z();
    id[n] = j;
    ++n;
  }
};

// The selected neighbourhood of one point: offsets w = q - p and their squared lengths.
struct Selection {
  std::vector<double> wx, wy, wz, d2;
  std::vector<std::uint32_t> id;
  std::size_t n = 0;
  std::vector<double> all_d2;      // select's scratch: every candidate's squared distance
  std::vector<std::uint32_t> pos;  // select's scratch: positions of the kept candidates
  std::vector<Eigen::Vector3d> offsets;  // the height test's bead rule: usable points' offsets

  void reserve(std::size_t cap) {
    if (wx.size() < cap) {
      wx.resize(cap);
      wy.resize(cap);
      wz.resize(cap);
      d2.resize(cap);
      id.resize(cap);
      all_d2.resize(cap);
      pos.resize(cap);
    }
  }
};

#ifdef __SSE2__
// Branch-free compaction of 4 candidates: for a 4-bit mask (bit l: candidate l is kept), the
// kept lanes packed to the front, ascending (lane[mask]), and how many there are (count[mask]).
struct CompactTable {
  alignas(16) std::uint32_t lane[16][4];
  std::uint32_t count[16];
};
constexpr CompactTable make_compact_table() {
  CompactTable t{};
  for (unsigned m = 0; m < 16; ++m) {
    unsigned c = 0;
    for (unsigned l = 0; l < 4; ++l) {
      if (m >> l & 1u) t.lane[m][c++] = l;
    }
    t.count[m] = c;
  }
  return t;
}
inline constexpr CompactTable kCompact = make_compact_table();

// Appends k + (the kept lanes of `mask`) at pos + m (`k`: k in every lane) and returns the new
// m. Writes 4 entries: pos must have room for m + 4 of them.
inline std::size_t compact4(std::uint32_t* pos, std::size_t m, unsigned mask, __m128i k) {
  const __m128i lanes = _mm_load_si128(reinterpret_cast<const __m128i*>(kCompact.lane[mask]));
  _mm_storeu_si128(reinterpret_cast<__m128i*>(pos + m), _mm_add_epi32(lanes, k));
  return m + kCompact.count[mask];
}

// Squared distances from (px, py, pz) of candidates k, k + 1 of g (the scalar formula's
// operations in its order: the same bits).
inline __m128d d2_pair(const double* gx, const double* gy, const double* gz, std::size_t k,
                       __m128d px, __m128d py, __m128d pz) {
  const __m128d dx = _mm_sub_pd(_mm_loadu_pd(gx + k), px);
  const __m128d dy = _mm_sub_pd(_mm_loadu_pd(gy + k), py);
  const __m128d dz = _mm_sub_pd(_mm_loadu_pd(gz + k), pz);
  return _mm_add_pd(_mm_add_pd(_mm_mul_pd(dx, dx), _mm_mul_pd(dy, dy)), _mm_mul_pd(dz, dz));
}

// Squared distances of candidates k .. k + 3 (d2_pair twice), stored at all + k.
struct Four {
  __m128d a, b;
  // bit l: candidate k + l has d2 <= lim
  unsigned within(__m128d lim) const {
    return static_cast<unsigned>(_mm_movemask_pd(_mm_cmple_pd(a, lim))) |
           static_cast<unsigned>(_mm_movemask_pd(_mm_cmple_pd(b, lim))) << 2;
  }
};
inline Four d2_four(const double* gx, const double* gy, const double* gz, std::size_t k,
                    __m128d px, __m128d py, __m128d pz, double* all) {
  const Four f{d2_pair(gx, gy, gz, k, px, py, pz), d2_pair(gx, gy, gz, k + 2, px, py, pz)};
  _mm_storeu_pd(all + k, f.a);
  _mm_storeu_pd(all + k + 2, f.b);
  return f;
}
#endif

#ifdef MIEM_SELECT_AVX512
// One list of select8's kept candidates: their positions and how many there are.
struct Kept {
  std::uint32_t* pos;
  std::size_t m;
};

// The selection loop of select and ball_sums, eight candidates at a time (the last ones
// masked): each candidate's squared distance from (px, py, pz) (d2_pair's operations in its
// order: the same bits) stored at all + k, and the positions of the kept ones (d2 <= r2)
// appended to `out` ascending, by a register compress and a full store (room for 8 entries
// past the last kept one: 8 past the candidates). With `in` (ball_sums): those with
// d2 <= in2 go to `in` instead.
__attribute__((target("avx512f,avx512vl"))) inline void select8(
    const double* gx, const double* gy, const double* gz, std::size_t n, double px, double py,
    double pz, double r2, double in2, double* all, Kept& out, Kept* in) {
  const __m512d vpx = _mm512_set1_pd(px), vpy = _mm512_set1_pd(py), vpz = _mm512_set1_pd(pz);
  const __m512d vr2 = _mm512_set1_pd(r2), vin2 = _mm512_set1_pd(in2);
  const __m256i step = _mm256_set1_epi32(8);
  __m256i vk = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
  const auto keep = [](Kept& to, __mmask8 mask, __m256i k)
                        __attribute__((target("avx512f,avx512vl"))) {
    _mm256_storeu_si256(reinterpret_cast<__m256i*>(to.pos + to.m),
                        _mm256_maskz_compress_epi32(mask, k));
    to.m += static_cast<std::size_t>(__builtin_popcount(mask));
  };
  for (std::size_t k = 0; k < n; k += 8) {
    const __mmask8 live = n - k >= 8 ? 0xFF : static_cast<__mmask8>((1u << (n - k)) - 1u);
    const __m512d dx = _mm512_sub_pd(_mm512_maskz_loadu_pd(live, gx + k), vpx);
    const __m512d dy = _mm512_sub_pd(_mm512_maskz_loadu_pd(live, gy + k), vpy);
    const __m512d dz = _mm512_sub_pd(_mm512_maskz_loadu_pd(live, gz + k), vpz);
    const __m512d d2 = _mm512_add_pd(_mm512_add_pd(_mm512_mul_pd(dx, dx), _mm512_mul_pd(dy, dy)),
                                     _mm512_mul_pd(dz, dz));
    _mm512_mask_storeu_pd(all + k, live, d2);
    const __mmask8 ball = live & _mm512_cmp_pd_mask(d2, vr2, _CMP_LE_OQ);
    if (in == nullptr) {
      keep(out, ball, vk);
    } else {
      const __mmask8 inner = ball & _mm512_cmp_pd_mask(d2, vin2, _CMP_LE_OQ);
      keep(out, ball & static_cast<__mmask8>(~inner), vk);
      keep(*in, inner, vk);
    }
    vk = _mm256_add_epi32(vk, step);
  }
}

// 8 values from q (the lanes of `live`; 0 in the others, nothing read there) as doubles into
// v (float: exactly).
__attribute__((target("avx512f,avx512vl"))) inline void load8(const double* q, __mmask8 live,
                                                              __m512d& v) {
  v = live == 0xFF ? _mm512_loadu_pd(q) : _mm512_maskz_loadu_pd(live, q);
}
__attribute__((target("avx512f,avx512vl"))) inline void load8(const float* q, __mmask8 live,
                                                              __m512d& v) {
  const __m256 f = live == 0xFF ? _mm256_loadu_ps(q) : _mm256_maskz_loadu_ps(live, q);
  v = _mm512_maskz_cvtps_pd(0xFF, f);  // (maskz: GCC 12 warns of the plain form's undefined source)
}

// select_box's loop over positions [b, e) of the grid's cell-ordered copy `xyz` (x, y, z of
// position k at 3 k; float or double, taken as double), eight points at a time: each point's
// offset from (px, py, pz) and squared distance (the scalar loop's operations in its order: the
// same bits), and those within r2 appended to s.wx, wy, wz, d2 and (order[k]) s.id from m on,
// in order, by register compresses and full stores (room for 8 entries past the last kept one).
// Returns the new count.
template <typename T>
__attribute__((target("avx512f,avx512vl"))) inline std::size_t select_run8(
    const T* xyz, const std::uint32_t* order, std::uint32_t b, std::uint32_t e, double px,
    double py, double pz, double r2, Selection& s, std::size_t m) {
  const __m512d vpx = _mm512_set1_pd(px), vpy = _mm512_set1_pd(py), vpz = _mm512_set1_pd(pz);
  const __m512d vr2 = _mm512_set1_pd(r2);
  double* wx = s.wx.data();
  double* wy = s.wy.data();
  double* wz = s.wz.data();
  double* d2o = s.d2.data();
  std::uint32_t* id = s.id.data();
  for (std::uint32_t k = b; k < e; k += 8) {
    const std::uint32_t n = std::min<std::uint32_t>(8, e - k);
    const T* q = xyz + 3 * static_cast<std::size_t>(k);
    // 3 n values (the last block: masked loads, nothing read past them)
    const unsigned t = 3 * n;
    const auto lanes = [](unsigned c) {
      return static_cast<__mmask8>(c >= 8 ? 0xFF : (1u << c) - 1u);
    };
    __m512d v0, v1, v2;
    load8(q, lanes(t), v0);
    load8(q + 8, lanes(t > 8 ? t - 8 : 0), v1);
    load8(q + 16, lanes(t > 16 ? t - 16 : 0), v2);
    __m512d x, y, z;
    detail::deinterleave_xyz8(v0, v1, v2, x, y, z);
    const __m512d dx = _mm512_sub_pd(x, vpx), dy = _mm512_sub_pd(y, vpy);
    const __m512d dz = _mm512_sub_pd(z, vpz);
    const __m512d d2 = _mm512_add_pd(_mm512_add_pd(_mm512_mul_pd(dx, dx), _mm512_mul_pd(dy, dy)),
                                     _mm512_mul_pd(dz, dz));
    const __mmask8 live = static_cast<__mmask8>(n == 8 ? 0xFF : (1u << n) - 1u);
    const __mmask8 keep = live & _mm512_cmp_pd_mask(d2, vr2, _CMP_LE_OQ);
    _mm512_storeu_pd(wx + m, _mm512_maskz_compress_pd(keep, dx));
    _mm512_storeu_pd(wy + m, _mm512_maskz_compress_pd(keep, dy));
    _mm512_storeu_pd(wz + m, _mm512_maskz_compress_pd(keep, dz));
    _mm512_storeu_pd(d2o + m, _mm512_maskz_compress_pd(keep, d2));
    const __m256i ids = _mm256_maskz_loadu_epi32(live, order + k);
    _mm256_storeu_si256(reinterpret_cast<__m256i*>(id + m), _mm256_maskz_compress_epi32(keep, ids));
    m += static_cast<std::size_t>(__builtin_popcount(keep));
  }
  return m;
}
#endif

// Calls f(position in order(), index) for every point of `box`, in cell-key order.
template <typename T, typename F>
void for_each_in_box(const NeighborGrid<T>& grid, const CellBox& box, F&& f) {
  const std::uint32_t* order = grid.order();
  grid.for_each_cell(box, [&](std::ptrdiff_t cell) {
    const std::uint32_t e = grid.cell_begin(cell + 1);
    for (std::uint32_t k = grid.cell_begin(cell); k < e; ++k) f(k, order[k]);
  });
}

// Gather the points of `box` that pass `keep(position in order(), index)`, in cell-key order.
template <typename T, typename Keep>
void gather_box(const NeighborGrid<T>& grid, const CellBox& box, Keep&& keep, Gather& g) {
  g.clear();
  for_each_in_box(grid, box, [&](std::uint32_t k, std::uint32_t j) {
    if (keep(k, j)) g.push(grid.sorted_point(k), j);
  });
}

// Gather the points of `box` by class_of(position in order(), index): kClassMain into `main`,
// kClassAside into `aside`, kClassSkip nowhere (each list in cell-key order).
enum : std::uint8_t { kClassMain = 0, kClassAside = 1, kClassSkip = 2 };
template <typename T, typename ClassOf>
void gather_split(const NeighborGrid<T>& grid, const CellBox& box, ClassOf&& class_of,
                  Gather& main, Gather& aside) {
  main.clear();
  aside.clear();
  for_each_in_box(grid, box, [&](std::uint32_t k, std::uint32_t j) {
    const std::uint8_t c = class_of(k, j);
    if (c == kClassMain) {
      main.push(grid.sorted_point(k), j);
    } else if (c == kClassAside) {
      aside.push(grid.sorted_point(k), j);
    }
  });
}

// Select the gathered points within r of p (excluding index `self`, pass -1 to keep it), in
// gather order. Two loops: every candidate's squared distance and the positions of the kept ones
// (a branch-free compaction, eight at a time with AVX-512 where the CPU has it, else four at a
// time with SSE2), then their offsets.
inline void select(const Gather& g, const Eigen::Vector3d& p, double r2, std::int64_t self,
                   Selection& s) {
  s.reserve(g.n + 8);  // (select8 stores 8 entries at a time)
  const double* __restrict gx = g.x.data();
  const double* __restrict gy = g.y.data();
  const double* __restrict gz = g.z.data();
  const std::uint32_t* __restrict gid = g.id.data();
  double* __restrict all = s.all_d2.data();
  std::uint32_t* __restrict pos = s.pos.data();
  const double px = p.x(), py = p.y(), pz = p.z();
  const std::size_t n = g.n;
  std::size_t m = 0, k = 0;
#ifdef MIEM_SELECT_AVX512
  if (detail::has_avx512()) {
    Kept kept{pos, 0};
    select8(gx, gy, gz, n, px, py, pz, r2, 0.0, all, kept, nullptr);
    m = kept.m, k = n;
  }
#endif
#ifdef __SSE2__
  {
    // Four candidates at a time (two registers), compacted by table.
    const __m128d vpx = _mm_set1_pd(px), vpy = _mm_set1_pd(py), vpz = _mm_set1_pd(pz);
    const __m128d vr2 = _mm_set1_pd(r2);
    __m128i vk = _mm_setzero_si128();  // k in every lane
    const __m128i four = _mm_set1_epi32(4);
    for (; k + 3 < n; k += 4) {
      const Four f = d2_four(gx, gy, gz, k, vpx, vpy, vpz, all);
      m = compact4(pos, m, f.within(vr2), vk);
      vk = _mm_add_epi32(vk, four);
    }
  }
#endif
  for (; k < n; ++k) {
    const double dx = gx[k] - px, dy = gy[k] - py, dz = gz[k] - pz;
    all[k] = dx * dx + dy * dy + dz * dz;
    pos[m] = static_cast<std::uint32_t>(k);
    m += static_cast<std::size_t>(all[k] <= r2);
  }
  if (self >= 0) {  // drop `self` from the kept (at most once: gathered indices are distinct)
    const std::uint32_t me = static_cast<std::uint32_t>(self);
    std::size_t q = 0;
    while (q < m && gid[pos[q]] != me) ++q;
    if (q < m) {
      std::copy(pos + q + 1, pos + m, pos + q);
      --m;
    }
  }
  double* __restrict wx = s.wx.data();
  double* __restrict wy = s.wy.data();
  double* __restrict wz = s.wz.data();
  double* __restrict sd2 = s.d2.data();
  std::uint32_t* __restrict sid = s.id.data();
  for (std::size_t q = 0; q < m; ++q) {
    const std::uint32_t k = pos[q];
    wx[q] = gx[k] - px;
    wy[q] = gy[k] - py;
    wz[q] = gz[k] - pz;
    sd2[q] = all[k];
    sid[q] = gid[k];
  }
  s.n = m;
}

// select(gather_box(box, every), p, r2, -1) without the gather: the points of `box` within r of
// p, straight from the grid's cell-ordered copy, in cell-key order; the same offsets, squared
// distances (the same operations) and order. Fills wx, wy, wz, d2, id. Eight points at a time
// where the CPU has AVX-512 (select_run8).
template <typename T>
void select_box(const NeighborGrid<T>& grid, const CellBox& box, const Eigen::Vector3d& p,
                double r2, Selection& s) {
  const std::uint32_t* order = grid.order();
  const double px = p.x(), py = p.y(), pz = p.z();
  std::size_t m = 0;
  // Positions [b, e) of the grid's copy.
  const auto select_run = [&](std::uint32_t b, std::uint32_t e) {
#ifdef MIEM_SELECT_AVX512
    if (detail::has_avx512()) {
      s.reserve(m + (e - b) + 8);  // (select_run8 stores 8 entries at a time)
      m = select_run8(grid.sorted_xyz(), order, b, e, px, py, pz, r2, s, m);
      return;
    }
#endif
    s.reserve(m + (e - b));
    double* __restrict wx = s.wx.data();
    double* __restrict wy = s.wy.data();
    double* __restrict wz = s.wz.data();
    double* __restrict sd2 = s.d2.data();
    std::uint32_t* __restrict sid = s.id.data();
    for (std::uint32_t k = b; k < e; ++k) {
      const Eigen::Vector3d q = grid.sorted_point(k);
      const double dx = q.x() - px, dy = q.y() - py, dz = q.z() - pz;
      const double d2 = dx * dx + dy * dy + dz * dz;
      wx[m] = dx;
      wy[m] = dy;
      wz[m] = dz;
      sd2[m] = d2;
      sid[m] = order[k];
      m += static_cast<std::size_t>(d2 <= r2);
    }
  };
  // Cells visited one after the other whose indices follow each other hold consecutive
  // positions: each such run in one go (fewer partial blocks of eight).
  std::ptrdiff_t c0 = 0, c1 = 0;  // the run of cells [c0, c1)
  grid.for_each_cell(box, [&](std::ptrdiff_t cell) {
    if (cell != c1) {
      if (c1 > c0) select_run(grid.cell_begin(c0), grid.cell_begin(c1));
      c0 = cell;
    }
    c1 = cell + 1;
  });
  if (c1 > c0) select_run(grid.cell_begin(c0), grid.cell_begin(c1));
  s.n = m;
}

// Eigen-decomposition of a symmetric 3 x 3 scatter matrix: eigenvalues ascending (w), the unit
// eigenvector of the smallest in V.col(0) and, with `all`, those of the other two in V.col(1),
// V.col(2). Without trigonometry where the smallest eigenvalue lies apart from the others by
// more than 1 % of the largest: smallest_eigenpair (Newton on the characteristic cubic, the
// eigenvector from cross products of rows; error ~1e-14 of the norm), then in the plane
// orthogonal to that eigenvector, which M maps to itself, the 2 x 2 problem of the other two
// (their difference without cancellation, so an in-plane isotropic neighbourhood, l1 close to
// l2, costs nothing extra). 3-4x faster than Eigen's closed form (computeDirect). Otherwise
// the QR iteration, as in fit_plane: nearly collinear or 3-point neighbourhoods, where a closed
// form loses up to ~1e-8 of the norm, which would move normals and the degeneracy test.
// eigen_sym3 from smallest_eigenpair's answer for M (`have`: it succeeded, with l0 <= l1 <= l2
// and the unit eigenvector n of l0), as one call or from a batch (PlaneBatch).
inline void eigen_sym3_from(const Eigen::Matrix3d& M, bool have, double l0, double l1, double l2,
                            const Eigen::Vector3d& n, Eigen::Vector3d& w, Eigen::Matrix3d& V,
                            bool all) {
  if (have) {
    const double gap = 1e-2 * std::abs(l2);
    if (std::isfinite(l2) && l1 - l0 > gap && l0 > -gap) {
      V.col(0) = n;
      if (!all) {
        w = Eigen::Vector3d(l0, l1, l2);
        return;
      }
      const Eigen::Vector3d a = n.unitOrthogonal(), b = n.cross(a);
      const Eigen::Vector3d Ma = M * a, Mb = M * b;
      const double maa = a.dot(Ma), mbb = b.dot(Mb), mab = a.dot(Mb);
      const double half = 0.5 * (maa - mbb), mid = 0.5 * (maa + mbb);
      const double r = std::sqrt(half * half + mab * mab);
      // the eigenvector of mid + r: (r + half, mab) or (mab, r - half) in (a, b), the one
      // without cancellation; any unit vector of the plane when both eigenvalues are equal
      const double ca = half >= 0.0 ? r + half : mab, cb = half >= 0.0 ? mab : r - half;
      const double len = std::sqrt(ca * ca + cb * cb);
      const Eigen::Vector3d major = len > 0.0 ? Eigen::Vector3d((ca * a + cb * b) / len) : a;
      w = Eigen::Vector3d(l0, mid - r, mid + r);
      V.col(1) = n.cross(major);
      V.col(2) = major;
      return;
    }
  }
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es;
  es.compute(M, Eigen::ComputeEigenvectors);
  w = es.info() == Eigen::Success ? es.eigenvalues() : Eigen::Vector3d::Constant(kNaN);
  V = es.eigenvectors();
}

inline void eigen_sym3(const Eigen::Matrix3d& M, Eigen::Vector3d& w, Eigen::Matrix3d& V,
                       bool all = true) {
  double l0 = 0.0, l1 = 0.0, l2 = 0.0;
  Eigen::Vector3d n;
  const bool have = detail::smallest_eigenpair(M, &l0, &l1, &l2, &n);
  eigen_sym3_from(M, have, l0, l1, l2, n, w, V, all);
}

// eigen_sym3 of many matrices: their smallest eigenpairs solved
// together in vector code (detail::smallest_eigenpairs_long, smallest_eigenpair's bits), the
// rest per matrix (eig). add() the matrices (at most the capacity reserve() gave since the last
// clear()), solve(), then eig(i) for the i-th added.
class PlaneBatch {
 public:
  void clear() { n_ = 0; }
  void reserve(std::ptrdiff_t m) {  // room for m matrices; clears the batch
    n_ = 0;
    if (m <= cap_) return;
    cap_ = std::max<std::ptrdiff_t>(m, 64);
    M_.resize(static_cast<std::size_t>(6 * cap_));
    out_.resize(static_cast<std::size_t>(6 * cap_));
    ok_.resize(static_cast<std::size_t>(cap_));
    redo_.resize(static_cast<std::size_t>(cap_));
  }
  int add(const Eigen::Matrix3d& M) {
    double* m = M_.data() + n_;
    m[0] = M(0, 0), m[cap_] = M(1, 1), m[2 * cap_] = M(2, 2);
    m[3 * cap_] = M(0, 1), m[4 * cap_] = M(1, 2), m[5 * cap_] = M(0, 2);
    return static_cast<int>(n_++);
  }
  void solve() {
    if (n_ > 0) {
      detail::smallest_eigenpairs_long(n_, cap_, M_.data(), out_.data(), ok_.data(),
                                       redo_.data());
    }
  }
  void eig(int i, Eigen::Vector3d& w, Eigen::Matrix3d& V, bool all = false) const {
    const double* m = M_.data() + i;
    Eigen::Matrix3d M;
    M << m[0], m[3 * cap_], m[5 * cap_], m[3 * cap_], m[cap_], m[4 * cap_], m[5 * cap_],
        m[4 * cap_], m[2 * cap_];
    if (redo_[static_cast<std::size_t>(i)] != 0.0) {  // Newton not ended in the batch's steps
      eigen_sym3(M, w, V, all);
      return;
    }
    const double* o = out_.data() + i;
    eigen_sym3_from(M, ok_[static_cast<std::size_t>(i)] != 0.0, o[0], o[cap_], o[2 * cap_],
                    Eigen::Vector3d(o[3 * cap_], o[4 * cap_], o[5 * cap_]), w, V, all);
  }

 private:
  std::vector<double> M_, out_, ok_, redo_;
  std::ptrdiff_t n_ = 0, cap_ = 0;
};

// Eigen plane of a selection (section "Plane fit" of SPEC.md), centred two-pass moments of the
// offsets. On success: oriented normal, largest-eigenvalue eigenvector, the centroid offset from p.
struct LocalPlane {
  Eigen::Vector3d normal, major, mean;
  Eigen::Vector3d eigenvalues;
  std::size_t n = 0;
};

// fit_selection's scatter of the selection's offsets about their mean (two passes; s.n >= 3).
inline Eigen::Matrix3d selection_scatter(const Selection& s, Eigen::Vector3d* mean) {
  const std::size_t n = s.n;
  double sx = 0, sy = 0, sz = 0;
  for (std::size_t k = 0; k < n; ++k) {
    sx += s.wx[k];
    sy += s.wy[k];
    sz += s.wz[k];
  }
  const double inv = 1.0 / static_cast<double>(n);
  const double mx = sx * inv, my = sy * inv, mz = sz * inv;
  double xx = 0, xy = 0, xz = 0, yy = 0, yz = 0, zz = 0;
  for (std::size_t k = 0; k < n; ++k) {
    const double a = s.wx[k] - mx, b = s.wy[k] - my, c = s.wz[k] - mz;
    xx += a * a;
    xy += a * b;
    xz += a * c;
    yy += b * b;
    yz += b * c;
    zz += c * c;
  }
  Eigen::Matrix3d M;
  M << xx, xy, xz, xy, yy, yz, xz, yz, zz;
  *mean = Eigen::Vector3d(mx, my, mz);
  return M;
}

// fit_selection after the eigen_sym3 (ev, V) of its scatter (with the major direction when
// want_major): from a PlaneBatch too.
inline PlaneStatus fit_from(const Eigen::Vector3d& ev, const Eigen::Matrix3d& V,
                            const Eigen::Vector3d& mean, std::size_t n, bool want_major,
                            LocalPlane* out) {
  if (!(ev(2) > 0.0) || ev(1) <= 1e-12 * ev(2)) return PlaneStatus::kDegenerate;
  out->normal = orient_normal(V.col(0).normalized());
  if (want_major) {
    Eigen::Vector3d e1 = V.col(2).normalized();
    if (!(ev(2) - ev(1) > 1e-6 * ev(2))) {
      // In-plane isotropic neighbourhood (a regular lattice): the eigenvector is arbitrary, so
      // project the coordinate axis least aligned with n onto the tangent plane (SPEC.md).
      const Eigen::Vector3d& nn = out->normal;
      int ax = 0;
      for (int a = 1; a < 3; ++a) {
        if (std::abs(nn(a)) < std::abs(nn(ax))) ax = a;
      }
      Eigen::Vector3d unit = Eigen::Vector3d::Zero();
      unit(ax) = 1.0;
      const Eigen::Vector3d proj = unit - unit.dot(nn) * nn;
      e1 = proj / std::sqrt(proj.dot(proj));
    }
    int big = 0;
    for (int a = 1; a < 3; ++a) {
      if (std::abs(e1(a)) > std::abs(e1(big))) big = a;
    }
    if (e1(big) < 0.0) e1 = -e1;
    out->major = e1;
  }
  out->mean = mean;
  out->eigenvalues = ev;
  out->n = n;
  return PlaneStatus::kOk;
}

inline PlaneStatus fit_selection(const Selection& s, bool want_major, LocalPlane* out) {
  if (s.n < 3) return PlaneStatus::kTooFewPoints;
  Eigen::Vector3d mean, ev;
  const Eigen::Matrix3d M = selection_scatter(s, &mean);
  Eigen::Matrix3d V;
  eigen_sym3(M, ev, V, want_major);
  return fit_from(ev, V, mean, s.n, want_major, out);
}

// Raw moments of offsets w = q - p about the query point p (small numbers, so one pass loses
// nothing that matters: the centred scatter is formed once, from sums of size radius^2).
struct OffsetSums {
  double n = 0, x = 0, y = 0, z = 0, xx = 0, xy = 0, xz = 0, yy = 0, yz = 0, zz = 0;
  void add(double dx, double dy, double dz) {
    n += 1.0;
    x += dx;
    y += dy;
    z += dz;
    xx += dx * dx;
    xy += dx * dy;
    xz += dx * dz;
    yy += dy * dy;
    yz += dy * dz;
    zz += dz * dz;
  }
  // The sums of the offsets in *this and in `other` (disjoint sets).
  OffsetSums plus(const OffsetSums& o) const {
    OffsetSums r;
    r.n = n + o.n;
    r.x = x + o.x;
    r.y = y + o.y;
    r.z = z + o.z;
    r.xx = xx + o.xx;
    r.xy = xy + o.xy;
    r.xz = xz + o.xz;
    r.yy = yy + o.yy;
    r.yz = yz + o.yz;
    r.zz = zz + o.zz;
    return r;
  }
  // The sums of the offsets in *this but not in `part` (a subset of them).
  OffsetSums minus(const OffsetSums& part) const {
    OffsetSums r;
    r.n = n - part.n;
    r.x = x - part.x;
    r.y = y - part.y;
    r.z = z - part.z;
    r.xx = xx - part.xx;
    r.xy = xy - part.xy;
    r.xz = xz - part.xz;
    r.yy = yy - part.yy;
    r.yz = yz - part.yz;
    r.zz = zz - part.zz;
    return r;
  }
};

// Selections (wx, wy, wz, d2, id) of several points kept one after the other, to be restored
// into a Selection later (the angle pass judges a cell's points after their planes are solved
// together).
struct SavedSelections {
  std::vector<double> wx, wy, wz, d2;
  std::vector<std::uint32_t> id;
  std::vector<std::size_t> start{0};
  void clear() { start.assign(1, 0); }
  std::size_t kept() const { return start.back(); }  // offsets kept so far
  void save(const Selection& s) {
    const std::size_t b = start.back(), e = b + s.n;
    if (wx.size() < e) {
      const std::size_t cap = std::max<std::size_t>(e, 2 * wx.size());
      wx.resize(cap), wy.resize(cap), wz.resize(cap), d2.resize(cap), id.resize(cap);
    }
    std::copy(s.wx.data(), s.wx.data() + s.n, wx.data() + b);
    std::copy(s.wy.data(), s.wy.data() + s.n, wy.data() + b);
    std::copy(s.wz.data(), s.wz.data() + s.n, wz.data() + b);
    std::copy(s.d2.data(), s.d2.data() + s.n, d2.data() + b);
    std::copy(s.id.data(), s.id.data() + s.n, id.data() + b);
    start.push_back(e);
  }
  // the q-th saved selection into s (q < the number saved)
  void restore(std::size_t q, Selection& s) const {
    const std::size_t b = start[q], n = start[q + 1] - b;
    s.reserve(n + 8);
    std::copy(wx.data() + b, wx.data() + b + n, s.wx.data());
    std::copy(wy.data() + b, wy.data() + b + n, s.wy.data());
    std::copy(wz.data() + b, wz.data() + b + n, s.wz.data());
    std::copy(d2.data() + b, d2.data() + b + n, s.d2.data());
    std::copy(id.data() + b, id.data() + b + n, s.id.data());
    s.n = n;
  }
};

// The height test's sums of one point (cloud_height_test.cpp): the NORMAL points within its
// radius, beyond and within the inner radius; whether a feature-line point is near; its two
// planes' places in a PlaneBatch (-1: none).
struct BallSums {
  OffsetSums around, inner;
  bool line = false;
  int ball = -1, ring = -1;
};

// Moments of the offsets g[pos[q]] - p, q = 0 .. n - 1, in two lanes (the even and the odd q),
// added at the end: two independent chains of additions. The result depends only on the
// sequence of points, never on how it was gathered. With SSE2 the two lanes are the two halves
// of one register (the same operations in the same order: the same bits as the scalar loop).
inline OffsetSums offset_sums(const Gather& g, const std::uint32_t* __restrict pos, std::size_t n,
                              const Eigen::Vector3d& p) {
  const double* __restrict gx = g.x.data();
  const double* __restrict gy = g.y.data();
  const double* __restrict gz = g.z.data();
  const double px = p.x(), py = p.y(), pz = p.z();
  double a[9][2] = {};  // x y z xx xy xz yy yz zz, per lane
  std::size_t q = 0;
#ifdef __SSE2__
  {
    const __m128d vpx = _mm_set1_pd(px), vpy = _mm_set1_pd(py), vpz = _mm_set1_pd(pz);
    __m128d v[9];
    for (__m128d& r : v) r = _mm_setzero_pd();
    for (; q + 1 < n; q += 2) {
      const std::uint32_t k0 = pos[q], k1 = pos[q + 1];  // lane 0: even q, lane 1: odd q
      const __m128d x = _mm_sub_pd(_mm_set_pd(gx[k1], gx[k0]), vpx);
      const __m128d y = _mm_sub_pd(_mm_set_pd(gy[k1], gy[k0]), vpy);
      const __m128d z = _mm_sub_pd(_mm_set_pd(gz[k1], gz[k0]), vpz);
      v[0] = _mm_add_pd(v[0], x);
      v[1] = _mm_add_pd(v[1], y);
      v[2] = _mm_add_pd(v[2], z);
      v[3] = _mm_add_pd(v[3], _mm_mul_pd(x, x));
      v[4] = _mm_add_pd(v[4], _mm_mul_pd(x, y));
      v[5] = _mm_add_pd(v[5], _mm_mul_pd(x, z));
      v[6] = _mm_add_pd(v[6], _mm_mul_pd(y, y));
      v[7] = _mm_add_pd(v[7], _mm_mul_pd(y, z));
      v[8] = _mm_add_pd(v[8], _mm_mul_pd(z, z));
    }
    for (int i = 0; i < 9; ++i) _mm_storeu_pd(a[i], v[i]);
  }
#endif
  auto add = [&](int l, std::uint32_t k) {
    const double x = gx[k] - px, y = gy[k] - py, z = gz[k] - pz;
    a[0][l] += x;
    a[1][l] += y;
    a[2][l] += z;
    a[3][l] += x * x;
    a[4][l] += x * y;
    a[5][l] += x * z;
    a[6][l] += y * y;
    a[7][l] += y * z;
    a[8][l] += z * z;
  };
  for (; q + 1 < n; q += 2) {  // (without SSE2)
    add(0, pos[q]);
    add(1, pos[q + 1]);
  }
  if (q < n) add(0, pos[q]);
  OffsetSums s;
  s.n = static_cast<double>(n);
  s.x = a[0][0] + a[0][1];
  s.y = a[1][0] + a[1][1];
  s.z = a[2][0] + a[2][1];
  s.xx = a[3][0] + a[3][1];
  s.xy = a[4][0] + a[4][1];
  s.xz = a[5][0] + a[5][1];
  s.yy = a[6][0] + a[6][1];
  s.yz = a[7][0] + a[7][1];
  s.zz = a[8][0] + a[8][1];
  return s;
}

// The moments of the gathered points within sqrt(r2) of p, in two parts: those within
// sqrt(in2) (`inner`) and the others (`ring`); in gather order. The ball's are ring + inner.
inline void ball_sums(const Gather& g, const Eigen::Vector3d& p, double r2, double in2,
                      Selection& s, OffsetSums* ring, OffsetSums* inner) {
  s.reserve(g.n + 8);  // (select8 stores 8 entries at a time)
  const double* __restrict gx = g.x.data();
  const double* __restrict gy = g.y.data();
  const double* __restrict gz = g.z.data();
  double* __restrict all = s.all_d2.data();
  std::uint32_t* __restrict out_pos = s.pos.data();  // ring positions
  std::uint32_t* __restrict in_pos = s.id.data();    // inner positions
  const double px = p.x(), py = p.y(), pz = p.z();
  const std::size_t n = g.n;
  // One pass: each candidate's squared distance, then its position appended to the ring or
  // the inner list (branch-free: which one is unpredictable): select8 where the CPU has
  // AVX-512, else four at a time with SSE2.
  std::size_t m_out = 0, m_in = 0, k = 0;
#ifdef MIEM_SELECT_AVX512
  if (detail::has_avx512()) {
    Kept out{out_pos, 0}, in{in_pos, 0};
    select8(gx, gy, gz, n, px, py, pz, r2, in2, all, out, &in);
    m_out = out.m, m_in = in.m, k = n;
  }
#endif
#ifdef __SSE2__
  {
    // Four candidates at a time (two registers), compacted by table.
    const __m128d vpx = _mm_set1_pd(px), vpy = _mm_set1_pd(py), vpz = _mm_set1_pd(pz);
    const __m128d vr2 = _mm_set1_pd(r2), vin2 = _mm_set1_pd(in2);
    __m128i vk = _mm_setzero_si128();  // k in every lane
    const __m128i four = _mm_set1_epi32(4);
    for (; k + 3 < n; k += 4) {
      const Four f = d2_four(gx, gy, gz, k, vpx, vpy, vpz, all);
      const unsigned ball = f.within(vr2), in = ball & f.within(vin2);
      m_out = compact4(out_pos, m_out, ball & ~in, vk);
      m_in = compact4(in_pos, m_in, in, vk);
      vk = _mm_add_epi32(vk, four);
    }
  }
#endif
  for (; k < n; ++k) {
    const double dx = gx[k] - px, dy = gy[k] - py, dz = gz[k] - pz;
    const double d2 = dx * dx + dy * dy + dz * dz;
    all[k] = d2;
    const bool b = d2 <= r2, in = b && d2 <= in2;
    out_pos[m_out] = static_cast<std::uint32_t>(k);
    in_pos[m_in] = static_cast<std::uint32_t>(k);
    m_out += static_cast<std::size_t>(b && !in);
    m_in += static_cast<std::size_t>(in);
  }
  *ring = offset_sums(g, out_pos, m_out, p);
  *inner = offset_sums(g, in_pos, m_in, p);
}

// plane_of's scatter matrix of the offsets summed in `s` (s.n >= 3), centred on their mean.
inline Eigen::Matrix3d sums_scatter(const OffsetSums& s) {
  const double inv = 1.0 / s.n;
  const double mx = s.x * inv, my = s.y * inv, mz = s.z * inv;
  Eigen::Matrix3d M;
  const double xy = s.xy - s.x * my, xz = s.xz - s.x * mz, yz = s.yz - s.y * mz;
  M << s.xx - s.x * mx, xy, xz, xy, s.yy - s.y * my, yz, xz, yz, s.zz - s.z * mz;
  return M;
}

// plane_of after the eigen_sym3 (ev, V) of sums_scatter(s): from a PlaneBatch too.
template <typename Each>
PlaneStatus plane_from(const OffsetSums& s, Eigen::Vector3d ev, Eigen::Matrix3d V,
                       LocalPlane* out, Each&& each) {
  const double inv = 1.0 / s.n;
  const double mx = s.x * inv, my = s.y * inv, mz = s.z * inv;
  if (ev(1) <= detail::kRefitRatio * (s.xx + s.yy + s.zz)) {  // (rare: two more passes)
    eigen_sym3(detail::two_pass_moments(each).scatter, ev, V, false);
  }
  if (!(ev(2) > 0.0) || ev(1) <= 1e-12 * ev(2)) return PlaneStatus::kDegenerate;
  out->normal = orient_normal(V.col(0).normalized());
  out->mean = Eigen::Vector3d(mx, my, mz);
  out->eigenvalues = ev;
  out->n = static_cast<std::size_t>(s.n);
  return PlaneStatus::kOk;
}

// The eigen plane (SPEC "Plane fit") of the offsets summed in `s`: oriented normal, the centroid
// offset from p, eigenvalues and count (no major direction). Where the sums lost the plane to
// cancellation (detail::kRefitRatio: a support nearly on a line, away from p), the scatter is
// formed again about the mean from the offsets themselves (detail::two_pass_moments): `each(f)`
// calls f(w) for every offset w summed in `s`.
template <typename Each>
PlaneStatus plane_of(const OffsetSums& s, LocalPlane* out, Each&& each) {
  if (s.n < 3.0) return PlaneStatus::kTooFewPoints;
  Eigen::Vector3d ev;
  Eigen::Matrix3d V;
  eigen_sym3(sums_scatter(s), ev, V, false);
  return plane_from(s, ev, V, out, std::forward<Each>(each));
}

// plane_of with the eigen_sym3 of sums_scatter(s) taken from the solved batch `pb`, where it was
// added at `at` (-1: not added, fewer than 3 points).
template <typename Each>
PlaneStatus plane_of(const PlaneBatch& pb, int at, const OffsetSums& s, LocalPlane* out,
                     Each&& each) {
  if (at < 0) return PlaneStatus::kTooFewPoints;
  Eigen::Vector3d ev;
  Eigen::Matrix3d V;
  pb.eig(at, ev, V);
  return plane_from(s, ev, V, out, std::forward<Each>(each));
}

// plane_of's visitor of the offsets ball_sums summed into `ring` and (with `inner`) `inner`:
// g[pos] - p for the positions it listed in s.pos and s.id.
inline auto ball_offsets(const Gather& g, const Eigen::Vector3d& p, const Selection& s,
                         const OffsetSums& ring, const OffsetSums& inner, bool with_inner = true) {
  const std::size_t n_ring = static_cast<std::size_t>(ring.n);
  const std::size_t n_in = with_inner ? static_cast<std::size_t>(inner.n) : 0;
  return [&g, &s, p, n_ring, n_in](auto&& f) {
    for (std::size_t q = 0; q < n_ring; ++q) {
      f(Eigen::Vector3d(g.x[s.pos[q]] - p.x(), g.y[s.pos[q]] - p.y(), g.z[s.pos[q]] - p.z()));
    }
    for (std::size_t q = 0; q < n_in; ++q) {
      f(Eigen::Vector3d(g.x[s.id[q]] - p.x(), g.y[s.id[q]] - p.y(), g.z[s.id[q]] - p.z()));
    }
  };
}

// cone_hits for K directions (a constant: the direction loop unrolled, the neighbour loop
// vectorised; each neighbour on its own, so any vector width gives the same bits).
template <int K>
inline __attribute__((always_inline)) void cone_hits_k(
    std::size_t n, const double* __restrict wx, const double* __restrict wy,
    const double* __restrict wz, double nx, double ny, double nz, const double* dx,
    const double* dy, const double* dz, double cos_half, double* __restrict tl,
    std::int64_t* __restrict hits) {
  for (std::size_t m = 0; m < n; ++m) {
    const double wn = (wx[m] * nx + wy[m] * ny) + wz[m] * nz;
    const double tx = wx[m] - wn * nx, ty = wy[m] - wn * ny, tz = wz[m] - wn * nz;
    const double tlen = std::sqrt((tx * tx + ty * ty) + tz * tz);
    const double lim = tlen * cos_half;
    std::int64_t h = 0;
    for (int k = 0; k < K; ++k) {
      const double td = (tx * dx[k] + ty * dy[k]) + tz * dz[k];
      const std::int64_t pos = td >= lim;
      const std::int64_t neg = (pos ^ 1) & static_cast<std::int64_t>(-td >= lim);
      h |= (pos << (2 * k)) | (neg << (2 * k + 1));
    }
    tl[m] = tlen;
    hits[m] = tlen > 0.0 ? h : 0;
  }
}

// Each of n neighbours' (offsets w from the point) tangent-plane length |t|, t = w - (w . nrm)
// nrm, and the (direction, side) cones it falls in, t . (g d_k) >= |t| cos_half, as bits 2k
// (g = +1) and 2k + 1 (g = -1) of hits[m] (none where |t| = 0), for K directions d (SPEC
// "Unorganized clouds"). Branch-free: which cone is unpredictable.
MIEM_CLONES inline void cone_hits(int K, std::size_t n, const double* wx, const double* wy,
                                  const double* wz, double nx, double ny, double nz,
                                  const double* dx, const double* dy, const double* dz,
                                  double cos_half, double* tl, std::int64_t* hits) {
  switch (K) {
    case 2: cone_hits_k<2>(n, wx, wy, wz, nx, ny, nz, dx, dy, dz, cos_half, tl, hits); break;
    case 3: cone_hits_k<3>(n, wx, wy, wz, nx, ny, nz, dx, dy, dz, cos_half, tl, hits); break;
    case 4: cone_hits_k<4>(n, wx, wy, wz, nx, ny, nz, dx, dy, dz, cos_half, tl, hits); break;
    case 5: cone_hits_k<5>(n, wx, wy, wz, nx, ny, nz, dx, dy, dz, cos_half, tl, hits); break;
    case 6: cone_hits_k<6>(n, wx, wy, wz, nx, ny, nz, dx, dy, dz, cos_half, tl, hits); break;
    case 7: cone_hits_k<7>(n, wx, wy, wz, nx, ny, nz, dx, dy, dz, cos_half, tl, hits); break;
    default: cone_hits_k<8>(n, wx, wy, wz, nx, ny, nz, dx, dy, dz, cos_half, tl, hits); break;
  }
}

// The planes of a cell's points, solved together (PlaneBatch: vector code) between a loop that
// forms them and a loop that uses them, and what each point keeps in between (each stage uses
// its part: the angle pass `at`, `mean`, `n` and the selections, the height test `balls`).
struct CellPlanes {
  PlaneBatch batch;
  std::vector<int> at;                 // point q's plane in `batch` (-1: none)
  std::vector<Eigen::Vector3d> mean;   // its neighbours' mean offset (selection_scatter)
  std::vector<std::size_t> n;          // its neighbours
  SavedSelections saved;               // its neighbourhood
  std::vector<BallSums> balls;         // its height-test sums (sized by the height test)
  // For `points` points with up to `per_point` planes each (the per-point vectors only grow:
  // each stage writes the entries it reads).
  void start(std::ptrdiff_t points, int per_point) {
    batch.reserve(per_point * points);
    const auto m = static_cast<std::size_t>(points);
    if (at.size() < m) at.resize(m), mean.resize(m), n.resize(m);
    saved.clear();
  }
  // fit_selection in two halves around batch.solve(): point q's selection `s` (its scatter into
  // the batch; none below 3 neighbours), then its plane.
  void add_fit(std::size_t q, const Selection& s) {
    n[q] = s.n;
    at[q] = s.n < 3 ? -1 : batch.add(selection_scatter(s, &mean[q]));
  }
  PlaneStatus fit(std::size_t q, bool want_major, LocalPlane* out) const {
    if (at[q] < 0) return PlaneStatus::kTooFewPoints;
    Eigen::Vector3d ev;
    Eigen::Matrix3d V;
    batch.eig(at[q], ev, V, want_major);
    return fit_from(ev, V, mean[q], n[q], want_major, out);
  }
};

// Per-thread scratch of the judge.
struct JudgeScratch {
  Gather gather;
  Gather aside;  // a second list of candidates (gather_split)
  Selection sel;
  Selection wide;  // the cloud edge test's wide ball (cloud_edge_test.cpp)
  std::vector<std::uint8_t> members;  // the cloud edge test's octant of each point of a ball
  CellPlanes cell;  // the planes of a cell's points, solved together
  std::vector<std::uint64_t> best_key;  // per (direction, side, scale) slot: bits of its d2
  std::vector<int> best_m;      // position in `sel` of the slot's neighbour, -1: none
  std::vector<double> tlen;     // per selected neighbour: tangent-plane length
  std::vector<std::int64_t> hits;  // per selected neighbour: its (direction, side) cones
};

// The judgment of SPEC.md "Unorganized clouds" for one point against a fixed usable set.
class PointJudge {
 public:
  PointJudge(const PointsDetectParams& p, double radius, double min_step)
      : r2_(radius * radius),
        min_step_(min_step),
        K_(p.num_directions),
        min_dirs_(p.min_directions),
        scales_(p.scales),
        cos0_(std::cos(p.theta0_deg * kDegToRad)),
        cos_half_(std::cos(kPi / (2.0 * p.num_directions))) {
    for (int si : scales_) step_.push_back((2 * si - 1) * min_step_);
    for (int k = 0; k < K_; ++k) {
      const double a = static_cast<double>(k) * kPi / static_cast<double>(K_);
      ck_[k] = std::cos(a);
      sk_[k] = std::sin(a);
    }
  }

  // Judges point `i` at `p` using the candidates already gathered in `js.gather` (a superset of
  // its usable neighbourhood, in grid order).
  std::uint8_t judge(std::uint32_t i, const Eigen::Vector3d& p, JudgeScratch& js,
                     std::uint8_t* flags, double* angle, bool* degenerate) const {
    js.cell.start(1, 1);
    select_point(i, p, js, 0);
    js.cell.batch.solve();
    return judge_selected(0, js, flags, angle, degenerate);
  }

  // judge's first half: point i's neighbourhood selected into js.sel and its plane fit begun
  // as point q of js.cell (CellPlanes::add_fit).
  void select_point(std::uint32_t i, const Eigen::Vector3d& p, JudgeScratch& js,
                    std::size_t q) const {
    select(js.gather, p, r2_, static_cast<std::int64_t>(i), js.sel);
    js.cell.add_fit(q, js.sel);
  }

  // judge's second half, js.sel holding point q's neighbourhood and js.cell.batch solved.
  std::uint8_t judge_selected(std::size_t q, JudgeScratch& js, std::uint8_t* flags,
                              double* angle, bool* degenerate) const {
    Selection& s = js.sel;
    *flags = 0;
    *angle = kNaN;
    *degenerate = false;
    LocalPlane lp;
    const PlaneStatus st = js.cell.fit(q, true, &lp);
    if (st == PlaneStatus::kTooFewPoints) return kAbnormal;
    if (st != PlaneStatus::kOk) {
      *degenerate = true;
      return kNormal;
    }
    const Eigen::Vector3d n = lp.normal, e1 = lp.major, e2 = n.cross(e1);
    Eigen::Vector3d d[kMaxDirections];
    for (int k = 0; k < K_; ++k) d[k] = ck_[k] * e1 + sk_[k] * e2;
    const int S = static_cast<int>(scales_.size());
    const std::size_t slots = static_cast<std::size_t>(K_) * 2 * S;
    js.best_m.assign(slots, -1);
    const int* __restrict bm = js.best_m.data();
    const double* wx = s.wx.data();
    const double* wy = s.wy.data();
    const double* wz = s.wz.data();
    const double* sd2 = s.d2.data();
    // Each neighbour's tangent-plane length and cones (cone_hits), then per slot the nearest
    // neighbour beyond the scale's step, (2s - 1) * min_step (SPEC "Unorganized clouds").
    js.tlen.resize(s.n);
    js.hits.resize(s.n);
    {
      double dx[kMaxDirections], dy[kMaxDirections], dz[kMaxDirections];
      for (int k = 0; k < K_; ++k) dx[k] = d[k].x(), dy[k] = d[k].y(), dz[k] = d[k].z();
      cone_hits(K_, s.n, wx, wy, wz, n.x(), n.y(), n.z(), dx, dy, dz, cos_half_,
                js.tlen.data(), js.hits.data());
    }
    js.best_key.assign(slots, ~std::uint64_t{0});
    switch (S) {  // the scale count as a constant where it is small: the slot loop unrolled
      case 1: nearest_slots<1>(s, js, S); break;
#ifdef __SSE2__
      case 2: nearest_slots_two(s, js); break;
#else
      case 2: nearest_slots<2>(s, js, S); break;
#endif
      case 3: nearest_slots<3>(s, js, S); break;
      default: nearest_slots<0>(s, js, S); break;
    }
    int avail = 0, flagged = 0;
    std::uint8_t mask = 0;
    double best_cos = -2.0;
    for (int k = 0; k < K_; ++k) {
      bool dir_avail = false, dir_flag = false;
      for (int si = 0; si < S; ++si) {
        const int mp = bm[(k * 2 + 0) * S + si], mm = bm[(k * 2 + 1) * S + si];
        if (mp < 0 || mm < 0) continue;
        const Eigen::Vector3d u(wx[mm], wy[mm], wz[mm]);  // A - P, A on side -1
        const Eigen::Vector3d v(wx[mp], wy[mp], wz[mp]);  // B - P
        const double uu = sd2[mm], vv = sd2[mp];
        if (uu == 0.0 || vv == 0.0) continue;
        const double cs = std::clamp(u.dot(v) / std::sqrt(uu * vv), -1.0, 1.0);
        dir_avail = true;
        if (cs >= cos0_) dir_flag = true;
        if (cs > best_cos) best_cos = cs;
      }
      avail += dir_avail;
      if (dir_flag) {
        ++flagged;
        mask |= static_cast<std::uint8_t>(1u << k);
      }
    }
    *flags = mask;
    *angle = best_cos > -2.0 ? std::acos(best_cos) * kRadToDeg : kNaN;
    const int need = min_dirs_ > 0 ? std::min(avail, min_dirs_) : avail;
    if (avail >= 2 && flagged >= need) return kAbnormal;
    return flagged > 0 ? kEdge : kNormal;
  }

 private:
  // Per (direction, side, scale) slot: the nearest (then smallest index) neighbour of the
  // slot's cone beyond the scale's step, into js.best_m (updated with masks: which neighbour
  // is nearer is unpredictable). d2 >= 0, so its bit pattern orders as the value. SC: the
  // scale count S as a constant, 0 when given at run time.
  template <int SC>
  void nearest_slots(const Selection& s, JudgeScratch& js, int S_run) const {
    const int S = SC > 0 ? SC : S_run;
    const double* __restrict tl = js.tlen.data();
    const std::int64_t* __restrict hits = js.hits.data();
    const double* __restrict sd2 = s.d2.data();
    const std::uint32_t* __restrict sid = s.id.data();
    std::uint64_t* __restrict bkey = js.best_key.data();
    int* __restrict bm = js.best_m.data();
    const double* __restrict step = step_.data();
    const int n_sel = static_cast<int>(s.n);
    for (int m = 0; m < n_sel; ++m) {
      unsigned h = static_cast<unsigned>(hits[m]);
      if (h == 0) continue;
      const double tlen = tl[m];
      std::uint64_t key;
      std::memcpy(&key, &sd2[m], sizeof key);
      const std::uint32_t id = sid[m];
      while (h != 0) {
        const int bit = __builtin_ctz(h);
        h &= h - 1;
        const int base = bit * S;  // slot (k, side) = bit: side 0 is g = +1, side 1 is g = -1
        for (int si = 0; si < S; ++si) {
          const int q = base + si;
          // A tie (equal d2) is rare: the index of the slot's neighbour is read only then.
          bool nearer = key < bkey[q];
          if (__builtin_expect(key == bkey[q], 0)) nearer = id < sid[bm[q]];
          const bool better = (tlen >= step[si]) & nearer;
          const std::uint64_t m64 = 0 - static_cast<std::uint64_t>(better);
          const std::uint32_t m32 = static_cast<std::uint32_t>(m64);
          bkey[q] = (key & m64) | (bkey[q] & ~m64);
          bm[q] = static_cast<int>((static_cast<std::uint32_t>(m) & m32) |
                                   (static_cast<std::uint32_t>(bm[q]) & ~m32));
        }
      }
    }
  }

#ifdef __SSE2__
  // nearest_slots for two scales (the default): a slot's two scales are the two halves of a
  // register. The best d2 is compared as a double (+inf: empty) rather than by its bits, the
  // same order for d2 >= 0; ties (equal d2, rare) go to the smaller index as in nearest_slots,
  // and an empty slot takes any neighbour.
  void nearest_slots_two(const Selection& s, JudgeScratch& js) const {
    constexpr int kSlots = kMaxDirections * 2 * 2;
    alignas(16) double bd[kSlots];
    alignas(16) std::int64_t bi[kSlots];
    const int slots = K_ * 2 * 2;
    for (int q = 0; q < slots; ++q) {
      bd[q] = kInf;
      bi[q] = -1;
    }
    const double* __restrict tl = js.tlen.data();
    const std::int64_t* __restrict hits = js.hits.data();
    const double* __restrict sd2 = s.d2.data();
    const std::uint32_t* __restrict sid = s.id.data();
    const __m128d vstep = _mm_loadu_pd(step_.data());
    const int n_sel = static_cast<int>(s.n);
    for (int m = 0; m < n_sel; ++m) {
      unsigned h = static_cast<unsigned>(hits[m]);
      if (h == 0) continue;
      const __m128d key = _mm_set1_pd(sd2[m]);
      const __m128d far = _mm_cmple_pd(vstep, _mm_set1_pd(tl[m]));  // tlen >= step[si]
      const __m128i vm = _mm_set1_epi64x(m);
      while (h != 0) {
        const int q = 2 * __builtin_ctz(h);  // slot (k, side) = bit, scales q and q + 1
        h &= h - 1;
        const __m128d cur = _mm_load_pd(bd + q);
        __m128d nearer = _mm_cmplt_pd(key, cur);
        if (__builtin_expect(_mm_movemask_pd(_mm_cmpeq_pd(key, cur)) != 0, 0)) {
          alignas(16) std::int64_t tie[2];
          for (int l = 0; l < 2; ++l) {
            tie[l] = sd2[m] == bd[q + l] && (bi[q + l] < 0 || sid[m] < sid[bi[q + l]]) ? -1 : 0;
          }
          nearer = _mm_or_pd(nearer, _mm_castsi128_pd(_mm_load_si128(
                                         reinterpret_cast<const __m128i*>(tie))));
        }
        const __m128d better = _mm_and_pd(nearer, far);
        _mm_store_pd(bd + q, _mm_or_pd(_mm_and_pd(better, key), _mm_andnot_pd(better, cur)));
        const __m128i bm = _mm_castpd_si128(better);
        __m128i* slot = reinterpret_cast<__m128i*>(bi + q);
        _mm_store_si128(slot, _mm_or_si128(_mm_and_si128(bm, vm),
                                           _mm_andnot_si128(bm, _mm_load_si128(slot))));
      }
    }
    int* bmo = js.best_m.data();
    for (int q = 0; q < slots; ++q) bmo[q] = static_cast<int>(bi[q]);
  }
#endif

  double r2_, min_step_;
  int K_, min_dirs_;
  const std::vector<int>& scales_;
  std::vector<double> step_;  // per scale s: (2 s - 1) * min_step
  double cos0_, cos_half_;
  double ck_[kMaxDirections] = {}, sk_[kMaxDirections] = {};
};

inline int thread_id() {
#ifdef MIEM_HAVE_OPENMP
  return omp_get_thread_num();
#else
  return 0;
#endif
}

// Runs `fn(cell, thread)` over the cells of `grid` in parallel (dynamic schedule).
template <typename T, typename Fn>
void parallel_cells(const NeighborGrid<T>& grid, int nt, Fn&& fn) {
  const std::ptrdiff_t ncells = grid.num_cells();
#pragma omp parallel for schedule(dynamic, 16) num_threads(nt) if (nt > 1)
  for (std::ptrdiff_t c = 0; c < ncells; ++c) fn(c, thread_id());
}

// The box of cells within r of the points of `cell`.
template <typename T>
CellBox cell_box(const NeighborGrid<T>& grid, std::ptrdiff_t cell, double r) {
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(kInf), hi = Eigen::Vector3d::Constant(-kInf);
  const std::uint32_t e = grid.cell_begin(cell + 1);
  for (std::uint32_t k = grid.cell_begin(cell); k < e; ++k) {
    const Eigen::Vector3d p = grid.sorted_point(k);
    lo = lo.cwiseMin(p);
    hi = hi.cwiseMax(p);
  }
  return grid.box_around(lo, hi, r);
}

// Wall-clock and process CPU laps of the detection stages (PointsDetectSummary::stage_seconds).
class StageClock {
 public:
  using Stage = PointsDetectSummary::Stage;
  explicit StageClock(std::vector<Stage>* out) : out_(out), wall_(wall()), cpu_(cpu()) {}
  void lap(const char* stage) {
    const double w = wall(), c = cpu();
    out_->push_back(Stage{stage, w - wall_, c - cpu_});
    wall_ = w;
    cpu_ = c;
  }

 private:
  static double wall() {
    return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch())
        .count();
  }
  static double cpu() { return static_cast<double>(std::clock()) / CLOCKS_PER_SEC; }
  std::vector<Stage>* out_;
  double wall_, cpu_;
};

// Cell size for a grid used with query radius r.
inline double grid_cell(double r) { return r; }

// Height plane of a point (NORMAL points within sqrt(r2), itself included when NORMAL) from the
// gathered NORMAL candidates, summed as ball_sums with inner radius sqrt(in2) (the height test's
// split, so that its heights are the same to the bit).
inline PlaneStatus height_plane(const Gather& g, const Eigen::Vector3d& p, double r2, double in2,
                                Selection& s, LocalPlane* lp) {
  OffsetSums ring, inner;
  ball_sums(g, p, r2, in2, s, &ring, &inner);
  return plane_of(ring.plus(inner), lp, ball_offsets(g, p, s, ring, inner));
}


}  // namespace miem::cloud
