// The stages of organized detection (docs/SPEC.md), in the order OrganizedDetector::run calls
// them. Each lives in the file named for it:
//   angle_passes.cpp  finiteness, pass 1, theta0 "auto", later passes (pass1_row.cpp: pass
//                     1's row kernel, which ProfileStream runs too with min_step)
//   height_test.cpp   compact EDGE groups and the height passes (beyond the paper)
//   edge_test.cpp     the edge test: step 9, then the edge passes (beyond the paper)
//   miem_plane.cpp    the MIEM plane of the non-ABNORMAL points
//   heights.cpp       the local height of each point over its window plane
//   defects.cpp       8-connected ABNORMAL groups and their summaries
// window_fits.hpp holds the window planes shared by the height test and the heights.
#pragma once

#include <cmath>
#include <cstdint>
#include <optional>
#include <vector>

#include "miem/organized.hpp"
#include "miem/plane.hpp"
#include "auto_min_step.hpp"
#include "edge_verdict.hpp"
#include "miem/views.hpp"
#include "vector_clones.hpp"
#include "window_fits.hpp"
#include "z_resolution.hpp"

namespace miem::detail {

/// min_step, z_noise and z_resolution "auto" resolved on `g` before the stages (SPEC
/// "min_step='auto'", "z_noise", "z_resolution"): eff's lengths set, their _auto flags cleared.
/// `survey` is auto_survey's reusable buffer, `zkeys` z_resolution's, `threads` auto_survey's
/// threads (the values do not depend on them).
template <typename T>
void resolve_auto_lengths(const GridView<T>& g, DetectParams& eff, std::vector<double>& survey,
                          std::vector<std::uint64_t>& zkeys, int threads) {
  if (eff.min_step_auto || eff.z_noise_auto) {  // (one survey gives both)
    const AutoSurvey s = auto_survey(g, survey, threads);
    if (eff.min_step_auto) eff.min_step = s.min_step;
    if (eff.z_noise_auto) eff.z_noise = s.noise;
    eff.min_step_auto = eff.z_noise_auto = false;
  }
  if (eff.z_resolution_auto) {
    eff.z_resolution = z_resolution(g, zkeys);
    eff.z_resolution_auto = false;
  }
}

/// Finiteness and the angle passes. Writes labels (and flags / angles where wanted); leaves
/// ws.usable with bit 0 set on the finite, non-ABNORMAL cells. Resolves eff.theta0_deg when
/// eff.theta0_auto. Returns the number of passes. Throws std::invalid_argument when the grid has
/// fewer than 3 finite points.
template <typename T>
int angle_passes(const GridView<T>& g, DetectParams& eff, const OrganizedOutput& out,
                 Workspace& ws);

/// The height test's verdict on one cell from its window plane (WindowFit's fields): too far
/// from the plane, and the test does not abstain there. SPEC "height_tolerance" step 3: it
/// abstains where a feature-line cell lies in the window (`edges` of them) and the tolerance is
/// absolute (a fixed length cannot allow for the bend the window's plane straddles); in the rms
/// form the straddled bend raises the rms, and the test runs. Branch-free, so that the batch's row loop (height_test.cpp) vectorises with it;
/// the one verdict of the batch and streaming detectors.
inline __attribute__((always_inline)) bool height_verdict(bool ok, double edges, double height,
                                                          double n, double l0, double l1,
                                                          double l2, double height_abs,
                                                          double height_k, double z_min) {
  const double ah = std::abs(height);
  // |h| > k rms and |h| > 1e-6 sqrt((l1 + l2) / n), rms = sqrt(max(l0, 0) / n), squared. The
  // floor lies above the round-off of l0 from window sums (SPEC "height_tolerance"), so that a
  // noise-free surface's verdict is not decided by rounding, which differs between sums formed
  // in another order (the stream, other tiles). In the rms form also |h| > z_min (z_floor: 1.5 x
  // the scan's z step, SPEC "z_resolution"; 0 without one).
  const double h2n = ah * ah * n;
  return ok & !((height_abs > 0.0) & (edges > 0.0)) &
         (((height_abs > 0.0) & (ah > height_abs)) |
          ((height_k > 0.0) & (h2n > height_k * height_k * std::max(l0, 0.0)) &
           (h2n > 1e-12 * (l1 + l2)) & (ah > z_min)));
}

/// SPEC "Edge test" step 1, a quiet cell's plane: its height-window plane (WindowFit's fields,
/// from the height test's first pass) exists and is *smooth*: its rms = sqrt(max(l0, 0) / n) is
/// at most kQuietRough x `floor` (the edge test's tolerance floor, >= 0), or it is flat to
/// round-off (l0 <= kEdgeFlatL0 l2, the edge test's rms of 0: a noise-free plane, whose floor is
/// often 0); and the cell lies within kQuietH rms of it, or within the round-off floor
/// 1e-6 sqrt((l1 + l2) / n) of height_verdict (so that a noise-free surface is not decided by
/// rounding). `floor` < 0: none is quiet (no edge test, or a later height pass). Branch-free.
inline constexpr double kQuietH = 4.0, kQuietRough = 0.75;
inline __attribute__((always_inline)) bool quiet_plane(bool ok, double height, double n,
                                                       double l0, double l1, double l2,
                                                       double floor) {
  const double h2n = height * height * n, l0p = std::max(l0, 0.0);
  return ok & (floor >= 0.0) &
         ((l0p <= kQuietRough * kQuietRough * floor * floor * n) | (l0 <= kEdgeFlatL0 * l2)) &
         ((h2n <= kQuietH * kQuietH * l0p) | (h2n <= 1e-12 * (l1 + l2)));
}

/// The verdicts of n cells from row_solve's fits (RowFits: S and F, moments and fits `cap`
/// apart), without their ok flags (both verdicts are `ok & ...`: the caller ands them): code[j]
/// = 1 where height_verdict finds the cell too far, + 2 where quiet_plane finds its plane quiet
/// (`quiet_floor` < 0: none). A loop of doubles only, vectorised: with the callers' bytes in
/// the same loop GCC took 64 cells a step, eight vectors of each double, and spilled them.
MIEM_CLONES inline void verdict_codes(std::ptrdiff_t n, const double* __restrict S,
                                      const double* __restrict F, std::ptrdiff_t cap,
                                      double height_abs, double height_k, double z_min,
                                      double quiet_floor, double* __restrict code) {
  const double* __restrict fh = F;
  const double* __restrict f0 = F + cap;
  const double* __restrict f1 = F + 2 * cap;
  const double* __restrict f2 = F + 3 * cap;
  const double* __restrict sl = S + 10 * cap;
  for (std::ptrdiff_t j = 0; j < n; ++j) {
    const bool far =
        height_verdict(true, sl[j], fh[j], S[j], f0[j], f1[j], f2[j], height_abs, height_k, z_min);
    const bool quiet = quiet_plane(true, fh[j], S[j], f0[j], f1[j], f2[j], quiet_floor);
    code[j] = (far ? 1.0 : 0.0) + (quiet ? 2.0 : 0.0);
  }
}

/// The heights of the wanted cells (want[j]) of a row segment from row_solve's fits: the fit's
/// height (F) where it has a plane (okf), else NaN. A masked store: reading the old heights
/// to blend them waited for each line of the output.
MIEM_CLONES inline void store_heights(std::ptrdiff_t n, const std::uint8_t* __restrict want,
                                      const std::uint8_t* __restrict okf,
                                      const double* __restrict F, double* __restrict height) {
  for (std::ptrdiff_t j = 0; j < n; ++j) {
    const double h = okf[j] != 0 ? F[j] : kNaN;
    if (want[j] != 0) height[j] = h;
  }
}

/// height_verdict of one WindowFit, with `p`'s z_resolution resolved (not auto).
inline bool height_far(const WindowFit& f, const DetectParams& p) {
  return height_verdict(f.ok, f.edges, f.height, f.n, f.l0, f.l1, f.l2, p.height_abs,
                        p.height_k, z_floor(p.z_resolution));
}

/// Bits of ws.hmask after height_test.
inline constexpr std::uint8_t kHCompact = 1;  ///< EDGE cell of a compact group
inline constexpr std::uint8_t kHWant = 2;     ///< (internal) evaluate at the next pass
inline constexpr std::uint8_t kHFresh = 4;    ///< height[i] holds the final window height
inline constexpr std::uint8_t kHMark = 8;     ///< (internal) too far at this pass
inline constexpr std::uint8_t kHSeen = 16;    ///< (internal) visited by the EDGE grouping
inline constexpr std::uint8_t kHQuiet = 32;   ///< its last plane is quiet (quiet_plane)
/// a cell within window / 2 became ABNORMAL in the last height pass (max_iterations reached
/// with cells added): its plane was not fitted again
inline constexpr std::uint8_t kHStale = 64;

/// Height passes (when p.height_abs > 0 or p.height_k > 0): NORMAL cells and EDGE cells of
/// compact groups too far from their window plane become ABNORMAL, at most p.max_iterations
/// passes; a pass re-fits only the cells whose window changed. When `height` is not null it
/// receives the window height of every fitted cell, and ws.hmask marks with kHFresh the cells
/// whose height is final, with kHQuiet the NORMAL cells whose last plane is quiet (quiet_plane,
/// with the edge test's tolerance floor; none without the edge test) and with kHStale the
/// cells within window / 2 of a cell the last pass made ABNORMAL when max_iterations ended the
/// passes (their planes were not fitted again). Leaves ws.cls with the window classes of the
/// final labels. Returns the number of height passes.
template <typename T>
int height_test(const GridView<T>& g, const DetectParams& p, std::uint8_t* labels,
                double* height, Workspace& ws);

/// SPEC "Edge test", after the height passes: step 9 beside the feature lines (the kLine cells
/// of ws.cls as the height test leaves it when `height_test`, else every EDGE cell), then the
/// edge passes. Returns the number of passes.
template <typename T>
int edge_stage(const GridView<T>& g, const DetectParams& p, std::uint8_t* labels,
               bool height_test, Workspace& ws);

/// The MIEM plane: eigen fit of the finite, non-ABNORMAL cells (row moments merged in a fixed
/// tree order, so the same for any thread count).
template <typename T>
std::optional<Plane> miem_plane(const GridView<T>& g, const std::uint8_t* labels,
                                int num_threads, Workspace& ws);

/// Heights (SPEC "Height"): every finite cell (HeightMode::kAll) or the ABNORMAL ones. With
/// `reuse`, cells marked kHFresh by height_test keep the height it wrote, unless a cell its fits
/// took as NORMAL (ws.cls) has changed label since (the edge test).
template <typename T>
void heights(const GridView<T>& g, const DetectParams& p, const std::uint8_t* labels,
             double* height, bool reuse, Workspace& ws);

/// Defects: 8-connected ABNORMAL components in row-major order of their first cell, summarised
/// and ordered (defects.hpp). Uses bit 2 of ws.usable as the visited mark and ws.fresh.
template <typename T>
std::vector<Defect> organized_defects(const GridView<T>& g, const std::uint8_t* labels,
                                      const double* height, int window, Workspace& ws,
                                      int num_threads = 1);

}  // namespace miem::detail
