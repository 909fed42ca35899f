// MIEM on organized scans: parameter checks and the detector, which runs the stages of
// docs/SPEC.md in order (stages.hpp; each stage in the file named for it).
#include "miem/organized.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

#include "stages.hpp"

namespace miem {

const char* to_string(DefectKind kind) noexcept {
  switch (kind) {
    case DefectKind::kProtrusion:
      return "protrusion";
    case DefectKind::kPit:
      return "pit";
    case DefectKind::kIsolated:
      return "isolated";
  }
  return "unknown";
}

OrganizedDetector::OrganizedDetector(DetectParams params) : params_(std::move(params)) {
  validate(params_);
}

template <typename T>
DetectSummary OrganizedDetector::run(const GridView<T>& g, const OrganizedOutput& out) {
  if (g.rows < 1 || g.cols < 1 || g.data == nullptr) {
    throw std::invalid_argument("grid: must have at least one row and one column");
  }
  if (out.labels == nullptr) throw std::invalid_argument("out.labels: must not be null");
  eff_ = params_;  // same-size assignment: no allocation after the first run
  // A window wider than the grid covers all of it from every cell, as 2 max(H, W) + 1 does: the
  // same windows, so the scratch the window sizes is bounded by the grid (README "Guarantees").
  const std::ptrdiff_t cover = 2 * std::max(g.rows, g.cols) + 1;
  if (eff_.window > cover) eff_.window = static_cast<int>(cover);
  detail::resolve_auto_lengths(g, eff_, ws_.survey, ws_.zkeys, eff_.num_threads);
  const DetectParams& p = eff_;
  const std::size_t N = static_cast<std::size_t>(g.rows * g.cols);
  std::uint8_t* labels = out.labels;
  double* height = out.height;
  if (height == nullptr) {
    ws_.height_scratch.resize(N);
    height = ws_.height_scratch.data();
  }

  DetectSummary summary;
  summary.iterations = detail::angle_passes(g, eff_, out, ws_);
  summary.theta0_deg = p.theta0_deg;
  summary.min_step = p.min_step;
  summary.z_resolution = p.z_resolution;
  summary.z_noise = p.z_noise;
  const bool height_test = p.height_abs > 0.0 || p.height_k > 0.0;
  if (height_test) {
    const bool keep = p.height_mode == HeightMode::kAll;
    summary.iterations += detail::height_test(g, p, labels, keep ? height : nullptr, ws_);
  }
  if (p.edge_test()) summary.iterations += detail::edge_stage(g, p, labels, height_test, ws_);
  summary.plane = detail::miem_plane(g, labels, p.num_threads, ws_);
  // heights() re-fits the windows the edge test changed and reuses the height test's others
  detail::heights(g, p, labels, height, height_test, ws_);
  summary.defects = detail::organized_defects(g, labels, height, p.window, ws_, p.num_threads);
  return summary;
}

template <typename T>
DetectResult detect_organized(const GridView<T>& grid, const DetectParams& params) {
  OrganizedDetector det(params);
  DetectResult res;
  res.rows = grid.rows;
  res.cols = grid.cols;
  const std::size_t n = static_cast<std::size_t>(std::max<std::ptrdiff_t>(0, grid.rows * grid.cols));
  res.labels.resize(n);
  res.flags.resize(n);
  res.angle_deg.resize(n);
  res.height.resize(n);
  OrganizedOutput out{res.labels.data(), res.flags.data(), res.angle_deg.data(),
                      res.height.data()};
  res.summary = det.run(grid, out);
  return res;
}

template DetectSummary OrganizedDetector::run<float>(const GridView<float>&,
                                                     const OrganizedOutput&);
template DetectSummary OrganizedDetector::run<double>(const GridView<double>&,
                                                      const OrganizedOutput&);
template DetectResult detect_organized<float>(const GridView<float>&, const DetectParams&);
template DetectResult detect_organized<double>(const GridView<double>&, const DetectParams&);

}  // namespace miem
