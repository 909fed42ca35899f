// miem's organized detection against PCL 1.13 on the same organized cloud, where PCL has the
// job: a depth-camera-like (projective) cloud of a machined surface with burr tips, pits and
// floating dust. PCL: IntegralImageNormalEstimation + OrganizedEdgeFromNormals (edge labels
// from normals), and StatisticalOutlierRemoval with keep-organized. miem reads PCL's point
// memory in place (GridView over pcl::PointXYZ, no copy). One thread each. Prints JSON.
//
//   miem_bench_pcl [--repeats 5] [--quick]
//   miem_bench_pcl --grid GRID.f64 ROWS COLS [--repeats 3]
//
// --grid: PCL's counterparts of the Open3D jobs in bench/bench_speed.py's lead table, on that
// table's scan (float64 x, y, z row-major; dropouts NaN): the finite points as an unorganized
// cloud, one thread: StatisticalOutlierRemoval(20, 2.0), RadiusOutlierRemoval(0.6, 8) and
// NormalEstimation (KNN 20), each with a kd-tree. Prints JSON rows (method, median_ms, points,
// flagged: points removed).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <random>
#include <string>
#include <vector>

#include <pcl/features/integral_image_normal.h>
#include <pcl/features/normal_3d.h>
#include <pcl/features/organized_edge_detection.h>
#include <pcl/filters/radius_outlier_removal.h>
#include <pcl/filters/statistical_outlier_removal.h>
#include <pcl/search/kdtree.h>
#include <pcl/point_cloud.h>
#include <pcl/point_types.h>

#include "miem/organized.hpp"

namespace {

using Clock = std::chrono::steady_clock;
using Cloud = pcl::PointCloud<pcl::PointXYZ>;

struct Scene {
  Cloud::Ptr cloud;
  std::vector<std::pair<int, int>> defects;  // injected (row, col)
};

// A pinhole camera (f = 525 px) 500 mm above a gently curved sheet with 0.05 mm noise; burr
// tips and pits (one pixel, 2-5 mm), floating dust (a point 20-60 mm above the surface), and
// dropouts, as an organized cloud in mm.
Scene make_scene(int W, int H, unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<float> noise(0.0f, 0.05f);
  std::uniform_real_distribution<float> uni(0.0f, 1.0f);
  const float f = 525.0f * static_cast<float>(W) / 640.0f, cx = 0.5f * W, cy = 0.5f * H;
  std::vector<float> depth(static_cast<std::size_t>(W * H));
  for (int v = 0; v < H; ++v)
    for (int u = 0; u < W; ++u) {
      const float x = (u - cx) / f * 500.0f, y = (v - cy) / f * 500.0f;
      depth[static_cast<std::size_t>(v * W + u)] =
          500.0f - 8.0f * std::exp(-(x * x + y * y) / 40000.0f) + 0.01f * x + noise(rng);
    }
  Scene s;
  const int n_defects = W * H / 4000;
  for (int i = 0; i < n_defects; ++i) {
    const int u = 3 + static_cast<int>(uni(rng) * (W - 6)), v = 3 + static_cast<int>(uni(rng) * (H - 6));
    float& d = depth[static_cast<std::size_t>(v * W + u)];
    const float kind = uni(rng);
    if (kind < 0.5f) d -= 2.0f + 3.0f * uni(rng);       // burr tip (towards the camera)
    else if (kind < 0.8f) d += 2.0f + 3.0f * uni(rng);  // pit
    else d -= 20.0f + 40.0f * uni(rng);                 // floating dust
    s.defects.push_back({v, u});
  }
  s.cloud.reset(new Cloud(W, H));
  for (int v = 0; v < H; ++v)
    for (int u = 0; u < W; ++u) {
      pcl::PointXYZ& p = (*s.cloud)(u, v);
      const float z = depth[static_cast<std::size_t>(v * W + u)];
      p.x = (u - cx) / f * z;
      p.y = (v - cy) / f * z;
      p.z = z;
      if (uni(rng) < 0.002f) p.x = p.y = p.z = std::numeric_limits<float>::quiet_NaN();
    }
  s.cloud->is_dense = false;
  return s;
}

// Defects found (a flagged cell within one cell) and flagged cells not near any defect.
struct Score {
  int found = 0, total = 0;
  long extra = 0, flagged = 0;
};

Score score(const std::vector<std::uint8_t>& flagged, int W, int H,
            const std::vector<std::pair<int, int>>& defects) {
  Score sc;
  sc.total = static_cast<int>(defects.size());
  std::vector<std::uint8_t> near(flagged.size(), 0);
  for (auto [v, u] : defects) {
    bool hit = false;
    for (int dv = -1; dv <= 1; ++dv)
      for (int du = -1; du <= 1; ++du) {
        const std::size_t i = static_cast<std::size_t>((v + dv) * W + (u + du));
        near[i] = 1;
        hit = hit || flagged[i];
      }
    sc.found += hit;
  }
  for (std::size_t i = 0; i < flagged.size(); ++i) {
    sc.flagged += flagged[i] != 0;
    sc.extra += flagged[i] && !near[i];
  }
  (void)H;
  return sc;
}

template <typename F>
double median_ms(int repeats, F&& f) {
  std::vector<double> t;
  for (int i = 0; i < repeats; ++i) {
    const auto a = Clock::now();
    f();
    t.push_back(std::chrono::duration<double, std::milli>(Clock::now() - a).count());
  }
  std::sort(t.begin(), t.end());
  return t[t.size() / 2];
}

void print_row(bool first, const char* method, int W, int H, double ms, const Score& s) {
  std::printf("%s{\"method\": \"%s\", \"width\": %d, \"height\": %d, \"points\": %d, "
              "\"median_ms\": %.3f, \"defects_found\": %d, \"defects\": %d, \"flagged\": %ld, "
              "\"flagged_elsewhere\": %ld}",
              first ? "" : ",\n", method, W, H, W * H, ms, s.found, s.total, s.flagged, s.extra);
  std::fflush(stdout);
}

// The --grid mode (see the file comment).
int run_grid(const char* path, long rows, long cols, int repeats) {
  if (rows <= 0 || cols <= 0) {
    std::fprintf(stderr, "--grid: ROWS and COLS must be > 0\n");
    return 2;
  }
  const std::size_t n = static_cast<std::size_t>(rows) * static_cast<std::size_t>(cols);
  std::vector<double> xyz(3 * n);
  FILE* f = std::fopen(path, "rb");
  if (f == nullptr || std::fread(xyz.data(), sizeof(double), xyz.size(), f) != xyz.size()) {
    std::fprintf(stderr, "--grid: cannot read %zu points from %s\n", n, path);
    if (f != nullptr) std::fclose(f);
    return 2;
  }
  std::fclose(f);
  Cloud::Ptr cloud(new Cloud);
  for (std::size_t i = 0; i < n; ++i) {
    const double* p = &xyz[3 * i];
    if (std::isfinite(p[0]) && std::isfinite(p[1]) && std::isfinite(p[2]))
      cloud->push_back(pcl::PointXYZ(static_cast<float>(p[0]), static_cast<float>(p[1]),
                                     static_cast<float>(p[2])));
  }
  const long m = static_cast<long>(cloud->size());
  auto row = [&](bool first, const char* method, double ms, long flagged) {
    std::printf("%s{\"method\": \"%s\", \"median_ms\": %.3f, \"points\": %ld, "
                "\"flagged\": %ld}", first ? "" : ",\n", method, ms, m, flagged);
    std::fflush(stdout);
  };
  // A PCL filter, timed on the cloud; the points it removes are the flagged ones.
  auto filter_row = [&](bool first, const char* method, auto& filter) {
    Cloud kept;
    const double ms = median_ms(repeats, [&] {
      filter.setInputCloud(cloud);
      filter.filter(kept);
    });
    row(first, method, ms, m - static_cast<long>(kept.size()));
  };
  std::printf("[\n");
  pcl::StatisticalOutlierRemoval<pcl::PointXYZ> sor;
  sor.setMeanK(20);
  sor.setStddevMulThresh(2.0);
  filter_row(true, "PCL `StatisticalOutlierRemoval(20, 2.0)` (1 thread)", sor);
  pcl::RadiusOutlierRemoval<pcl::PointXYZ> ror;
  ror.setRadiusSearch(0.6);
  ror.setMinNeighborsInRadius(8);
  filter_row(false, "PCL `RadiusOutlierRemoval(0.6, 8)` (1 thread)", ror);
  {
    pcl::PointCloud<pcl::Normal> normals;
    pcl::NormalEstimation<pcl::PointXYZ, pcl::Normal> ne;
    const double ms = median_ms(repeats, [&] {
      ne.setInputCloud(cloud);
      ne.setSearchMethod(pcl::search::KdTree<pcl::PointXYZ>::Ptr(
          new pcl::search::KdTree<pcl::PointXYZ>));
      ne.setKSearch(20);
      ne.compute(normals);
    });
    row(false, "PCL `NormalEstimation` (KNN 20, 1 thread)", ms, -1);
  }
  std::printf("\n]\n");
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc >= 5 && std::string(argv[1]) == "--grid") {
    const int reps = argc >= 7 && std::string(argv[5]) == "--repeats" ? std::atoi(argv[6]) : 3;
    return run_grid(argv[2], std::atol(argv[3]), std::atol(argv[4]), std::max(1, reps));
  }
  int repeats = 5;
  bool quick = false;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--repeats" && i + 1 < argc) repeats = std::atoi(argv[++i]);
    else if (a == "--quick") quick = true;
    else {
      std::fprintf(stderr, "usage: %s [--repeats N] [--quick] | --grid FILE ROWS COLS "
                   "[--repeats N]\n", argv[0]);
      return 2;
    }
  }
  std::vector<std::pair<int, int>> sizes = {{640, 480}, {1280, 960}};
  if (quick) sizes = {{320, 240}};
  std::printf("[\n");
  bool first = true;
  for (auto [W, H] : sizes) {
    const Scene scene = make_scene(W, H, 3);
    const Cloud::Ptr& cloud = scene.cloud;
    const std::size_t N = static_cast<std::size_t>(W) * static_cast<std::size_t>(H);

    // miem, straight on PCL's memory: x, y, z of a PointXYZ are floats 0..2 of 4.
    const miem::GridView<float> grid{&cloud->points[0].x, H, W, 4 * W, 4, 1};
    // The paper's settings (heights of the ABNORMAL points, of every point) and the default
    // preset ("recommended": theta0 90, scales (1, 2), height test 4.5 rms, edge_extent 12).
    for (int cfg = 0; cfg < 3; ++cfg) {
      miem::DetectParams p = cfg == 2 ? miem::recommended_params() : miem::paper_params();
      p.num_threads = 1;
      p.height_mode = cfg == 0 ? miem::HeightMode::kAbnormal : miem::HeightMode::kAll;
      miem::OrganizedDetector det(p);
      std::vector<std::uint8_t> labels(N);
      miem::DetectSummary summary;
      const double ms = median_ms(repeats, [&] { summary = det.run(grid, {labels.data()}); });
      std::vector<std::uint8_t> flagged(N);
      for (std::size_t i = 0; i < N; ++i) flagged[i] = labels[i] == miem::kAbnormal;
      const char* name[] = {"miem detect, paper preset (heights abnormal)",
                            "miem detect, paper preset (heights all)",
                            "miem detect, default preset (recommended, heights all)"};
      print_row(first, name[cfg], W, H, ms, score(flagged, W, H, scene.defects));
      first = false;
    }

    // PCL: integral-image normals, then edges from normals.
    {
      pcl::PointCloud<pcl::Normal>::Ptr normals(new pcl::PointCloud<pcl::Normal>);
      pcl::PointCloud<pcl::Label> labels;
      std::vector<pcl::PointIndices> label_indices;
      auto run = [&] {
        pcl::IntegralImageNormalEstimation<pcl::PointXYZ, pcl::Normal> ne;
        ne.setNormalEstimationMethod(ne.COVARIANCE_MATRIX);
        ne.setMaxDepthChangeFactor(0.02f);
        ne.setNormalSmoothingSize(10.0f);
        ne.setInputCloud(cloud);
        ne.compute(*normals);
        pcl::OrganizedEdgeFromNormals<pcl::PointXYZ, pcl::Normal, pcl::Label> oed;
        oed.setInputCloud(cloud);
        oed.setInputNormals(normals);
        oed.setDepthDisconThreshold(0.004f);  // relative: 2 mm at 500 mm
        oed.setMaxSearchNeighbors(50);
        oed.setEdgeType(oed.EDGELABEL_OCCLUDING | oed.EDGELABEL_OCCLUDED |
                        oed.EDGELABEL_HIGH_CURVATURE);
        oed.compute(labels, label_indices);
      };
      const double ms = median_ms(repeats, run);
      std::vector<std::uint8_t> flagged(N, 0);
      for (const auto& idx : label_indices)
        for (int i : idx.indices) flagged[static_cast<std::size_t>(i)] = 1;
      print_row(first, "PCL IntegralImageNormalEstimation + OrganizedEdgeFromNormals", W, H, ms,
                score(flagged, W, H, scene.defects));
    }

    // PCL: statistical outlier removal, keeping the cloud organized.
    {
      Cloud filtered;
      pcl::StatisticalOutlierRemoval<pcl::PointXYZ> sor(true);
      auto run = [&] {
        sor.setInputCloud(cloud);
        sor.setMeanK(8);
        sor.setStddevMulThresh(3.0);
        sor.setKeepOrganized(true);
        sor.filter(filtered);
      };
      const double ms = median_ms(std::max(1, repeats / 2), run);
      std::vector<std::uint8_t> flagged(N, 0);
      for (int i : *sor.getRemovedIndices()) flagged[static_cast<std::size_t>(i)] = 1;
      print_row(first, "PCL StatisticalOutlierRemoval (keep organized, k = 8, 3 sigma)", W, H, ms,
                score(flagged, W, H, scene.defects));
    }
  }
  std::printf("\n]\n");
  return 0;
}
