// The MIEM plane (docs/SPEC.md "MIEM plane"): the eigenvalue fit of the finite points that are
// not ABNORMAL. Per-row moments, merged in a fixed tree order, so the same for any thread count.
#include <type_traits>

#include "parallel.hpp"
#include "plane_math.hpp"
#include "stages.hpp"
#include "vector_clones.hpp"

namespace miem::detail {

namespace {

// The moments of a dense grid's rows (x, y, z interleaved, rows `rs` values apart) in kLanes
// partial sums per moment: cell c of a row adds to lane c % kLanes, and the lanes are added
// in a fixed order at the end: one running sum per moment is a chain of additions at the
// latency of one per cell (a 2048^2 scan's MIEM plane: 9 ms of the run; in lanes, 6.7).
// Two passes like two_pass_moments_masked: the mean, then the scatter about it (a block's
// rows are in cache for the second).
constexpr int kLanes = 8;

inline bool kept(std::uint8_t l) { return (l == kNormal) | (l == kEdge); }

// The lanes' total in a fixed tree: (0 + 4, 1 + 5, 2 + 6, 3 + 7), then (0 + 2, 1 + 3), then 0 + 1.
inline double fold_lanes(double* v) {
  for (int w = kLanes / 2; w > 0; w /= 2)
    for (int l = 0; l < w; ++l) v[l] += v[l + w];
  return v[0];
}

// One cell's terms added to lane l: of the first pass's sums (count, x, y, z), and of the
// second pass's scatter about the mean m (xx, xy, xz, yy, yz, zz); a cell not kept adds 0.
inline void add_sums(int l, bool k, double x, double y, double z, double* n, double* sx,
                     double* sy, double* sz) {
  n[l] += k ? 1.0 : 0.0;
  sx[l] += k ? x : 0.0;
  sy[l] += k ? y : 0.0;
  sz[l] += k ? z : 0.0;
}
inline void add_scatter(int l, bool k, double x, double y, double z, const Eigen::Vector3d& m,
                        double (*v)[kLanes]) {
  const double qx = k ? x - m.x() : 0.0, qy = k ? y - m.y() : 0.0, qz = k ? z - m.z() : 0.0;
  v[0][l] += qx * qx, v[1][l] += qx * qy, v[2][l] += qx * qz;
  v[3][l] += qy * qy, v[4][l] += qy * qz, v[5][l] += qz * qz;
}

// The moments' count and mean from the first pass's lanes (n: none kept when their total is 0),
// and the scatter from the second pass's.
inline Moments lanes_mean(double* n, double* sx, double* sy, double* sz) {
  Moments m;
  const double cnt = fold_lanes(n);
  if (cnt == 0.0) return m;
  m.n = static_cast<std::int64_t>(cnt);
  m.mean = Eigen::Vector3d(fold_lanes(sx), fold_lanes(sy), fold_lanes(sz)) / cnt;
  return m;
}
inline void lanes_scatter(double (*v)[kLanes], Moments& m) {
  const double xx = fold_lanes(v[0]), xy = fold_lanes(v[1]), xz = fold_lanes(v[2]);
  const double yy = fold_lanes(v[3]), yz = fold_lanes(v[4]), zz = fold_lanes(v[5]);
  m.scatter << xx, xy, xz, xy, yy, yz, xz, yz, zz;
}

template <typename T, typename CS, typename YS>
inline __attribute__((always_inline)) Moments lane_moments(const T* __restrict data,
                                                          std::ptrdiff_t rs, CS cs, YS ys,
                                                          std::ptrdiff_t rows,
                                                          const std::uint8_t* __restrict lab,
                                                          std::ptrdiff_t W) {
  // visit(l, keep, x, y, z) for each cell in order, l its lane
  const auto each = [&](auto&& visit) {
    for (std::ptrdiff_t r = 0; r < rows; ++r) {
      const T* row = data + r * rs;
      const std::uint8_t* lb = lab + r * W;
      for (std::ptrdiff_t c = 0; c < W; ++c) {
        const T* q = row + cs * c;
        visit(static_cast<int>(c % kLanes), kept(lb[c]), static_cast<double>(q[0]),
              static_cast<double>(q[ys]), static_cast<double>(q[2 * ys]));
      }
    }
  };
  double n[kLanes] = {}, sx[kLanes] = {}, sy[kLanes] = {}, sz[kLanes] = {};
  each([&](int l, bool k, double x, double y, double z) { add_sums(l, k, x, y, z, n, sx, sy, sz); });
  Moments m = lanes_mean(n, sx, sy, sz);
  if (m.n == 0) return m;
  double v[6][kLanes] = {};
  each([&](int l, bool k, double x, double y, double z) { add_scatter(l, k, x, y, z, m.mean, v); });
  lanes_scatter(v, m);
  return m;
}

#ifdef MIEM_SELECT_AVX512
// Cells 0 .. 7 at q (interleaved) into x, y, z; returns which are kept (labels lb).
__attribute__((target("avx512f,avx512vl"), always_inline)) inline __mmask8 load8(
    const double* q, const std::uint8_t* lb, __m512d& x, __m512d& y, __m512d& z) {
  load_xyz8(q, x, y, z);
  const __m512i l = bytes8(lb);
  return static_cast<__mmask8>(_mm512_cmpeq_epi64_mask(l, _mm512_set1_epi64(kNormal)) |
                               _mm512_cmpeq_epi64_mask(l, _mm512_set1_epi64(kEdge)));
}

// One pass of lane_moments over the interleaved layout (x, y, z, x, ...) of doubles in AVX-512:
// the lanes in one register per sum, 8 cells a step, a row's last cells (fewer than 8) added
// to lanes 0 .. in order after its earlier ones. kSums 4: the first pass's (count, x, y, z);
// 6: the scatter about m. Writes the lanes' sums to t. The same operations per lane in the
// same order as lane_moments (a cell not kept leaves its lane's sums as they are: adding 0.0
// to a sum that starts at +0.0 changes no bit).
template <int kSums>
__attribute__((target("avx512f,avx512vl"), always_inline)) inline void dense_pass(
    const double* data, std::ptrdiff_t rs, std::ptrdiff_t rows, const std::uint8_t* lab,
    std::ptrdiff_t W, const Eigen::Vector3d& m, double (*t)[kLanes]) {
  static_assert(kLanes == 8, "one register of lanes");
  const std::ptrdiff_t W8 = W / 8 * 8;
  const __m512d one = _mm512_set1_pd(1.0);
  const __m512d vmx = _mm512_set1_pd(m.x()), vmy = _mm512_set1_pd(m.y());
  const __m512d vmz = _mm512_set1_pd(m.z());
  __m512d v[kSums];
  for (__m512d& e : v) e = _mm512_setzero_pd();
  for (std::ptrdiff_t r = 0; r < rows; ++r) {
    const double* row = data + r * rs;
    const std::uint8_t* lb = lab + r * W;
    for (std::ptrdiff_t c0 = 0; c0 < W8; c0 += 8) {
      __m512d x, y, z;
      const __mmask8 k = load8(row + 3 * c0, lb + c0, x, y, z);
      if constexpr (kSums == 4) {
        v[0] = _mm512_mask_add_pd(v[0], k, v[0], one);
        v[1] = _mm512_mask_add_pd(v[1], k, v[1], x);
        v[2] = _mm512_mask_add_pd(v[2], k, v[2], y);
        v[3] = _mm512_mask_add_pd(v[3], k, v[3], z);
      } else {
        const __m512d qx = _mm512_maskz_sub_pd(k, x, vmx), qy = _mm512_maskz_sub_pd(k, y, vmy);
        const __m512d qz = _mm512_maskz_sub_pd(k, z, vmz);
        v[0] = _mm512_add_pd(v[0], _mm512_mul_pd(qx, qx));
        v[1] = _mm512_add_pd(v[1], _mm512_mul_pd(qx, qy));
        v[2] = _mm512_add_pd(v[2], _mm512_mul_pd(qx, qz));
        v[3] = _mm512_add_pd(v[3], _mm512_mul_pd(qy, qy));
        v[4] = _mm512_add_pd(v[4], _mm512_mul_pd(qy, qz));
        v[5] = _mm512_add_pd(v[5], _mm512_mul_pd(qz, qz));
      }
    }
    if (W8 == W) continue;
    for (int e = 0; e < kSums; ++e) _mm512_storeu_pd(t[e], v[e]);
    for (std::ptrdiff_t c = W8; c < W; ++c) {
      const double* q = row + 3 * c;
      const int l = static_cast<int>(c - W8);
      if constexpr (kSums == 4) {
        add_sums(l, kept(lb[c]), q[0], q[1], q[2], t[0], t[1], t[2], t[3]);
      } else {
        add_scatter(l, kept(lb[c]), q[0], q[1], q[2], m, t);
      }
    }
    for (int e = 0; e < kSums; ++e) v[e] = _mm512_loadu_pd(t[e]);
  }
  for (int e = 0; e < kSums; ++e) _mm512_storeu_pd(t[e], v[e]);
}

// lane_moments of the interleaved layout of doubles in AVX-512 (GCC does not vectorise
// lane_moments' lanes over the interleaved loads): its two passes by dense_pass.
__attribute__((target("avx512f,avx512vl"))) Moments dense_moments_avx512(
    const double* data, std::ptrdiff_t rs, std::ptrdiff_t rows, const std::uint8_t* lab,
    std::ptrdiff_t W) {
  double s[4][kLanes];
  dense_pass<4>(data, rs, rows, lab, W, Eigen::Vector3d::Zero(), s);
  Moments m = lanes_mean(s[0], s[1], s[2], s[3]);
  if (m.n == 0) return m;
  double v[6][kLanes];
  dense_pass<6>(data, rs, rows, lab, W, m.mean, v);
  lanes_scatter(v, m);
  return m;
}
#endif

}  // namespace

template <typename T>
std::optional<Plane> miem_plane(const GridView<T>& g, const std::uint8_t* labels,
                                int num_threads, Workspace& ws) {
  const std::ptrdiff_t H = g.rows, W = g.cols;
  const int nt = thread_count(num_threads, H * W);
  // Blocks of whole rows with at least 4096 cells each (one row per block on wide grids): the
  // moments buffer stays small on tall thin grids (10^7 x 1) and the blocks depend on the shape
  // only, so the result is the same for any thread count.
  const std::ptrdiff_t per = std::max<std::ptrdiff_t>(1, (4096 + W - 1) / W);
  const std::ptrdiff_t B = (H + per - 1) / per;
  std::vector<Moments>& rows = ws.plane_rows;
  rows.resize(static_cast<std::size_t>(B));
#ifdef MIEM_SELECT_AVX512
  // the interleaved layout of doubles: the AVX-512 loop where the CPU has it
  const bool avx512 = std::is_same_v<T, double> && g.col_stride == 3 && g.coord_stride == 1 &&
                      has_avx512();
#endif
#pragma omp parallel for schedule(static) num_threads(nt) if (nt > 1)
  for (std::ptrdiff_t b = 0; b < B; ++b) {
    const std::ptrdiff_t r0 = b * per, r1 = std::min(H, r0 + per);
    const T* d = g.data + r0 * g.row_stride;
    const std::uint8_t* lb = labels + r0 * W;
    Moments& m = rows[static_cast<std::size_t>(b)];
#ifdef MIEM_SELECT_AVX512
    if constexpr (std::is_same_v<T, double>) {
      if (avx512) {
        m = dense_moments_avx512(d, g.row_stride, r1 - r0, lb, W);
        continue;
      }
    }
#endif
    m = lane_moments(d, g.row_stride, g.col_stride, g.coord_stride, r1 - r0, lb, W);
  }
  for (std::ptrdiff_t width = 1; width < B; width *= 2)
    for (std::ptrdiff_t b = 0; b + width < B; b += 2 * width) rows[b].merge(rows[b + width]);
  Plane plane;
  if (eigen_plane_from_moments(rows[0], &plane) == PlaneStatus::kOk) return plane;
  return std::nullopt;
}

template std::optional<Plane> miem_plane<float>(const GridView<float>&, const std::uint8_t*, int,
                                                Workspace&);
template std::optional<Plane> miem_plane<double>(const GridView<double>&, const std::uint8_t*,
                                                 int, Workspace&);

}  // namespace miem::detail
