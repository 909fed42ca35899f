// Where the time of organized detection goes: each stage of OrganizedDetector::run
// (cpp/src/stages.hpp) timed on its own, in the order run() calls them.
//
// Usage: miem_bench_stages GRID.f64 ROWS COLS THREADS REPEATS [paper|recommended|recommended-no-edge]
// GRID.f64 is ROWS x COLS x 3 doubles (numpy tofile). Prints one JSON object: the best time of
// each stage over REPEATS runs (seconds; process CPU time with 1 thread, wall time with more),
// the whole run(), the min_step used (-1: off) and checksums of the labels, flags, heights and
// angles.
#include <algorithm>
#include <chrono>
#include <ctime>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <string>
#include <vector>

#include "miem/organized.hpp"
#include "../../cpp/src/auto_min_step.hpp"
#include "../../cpp/src/edge_test.hpp"
#include "../../cpp/src/stages.hpp"

namespace {
// Process CPU time with one thread (a shared machine steals wall time, not CPU time), wall time
// with more.
bool g_cpu_clock = true;
double now() {
  if (g_cpu_clock) {
    timespec ts;
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
    return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
  }
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch())
      .count();
}
}  // namespace

int main(int argc, char** argv) {
  if (argc < 6) {
    std::fprintf(stderr, "usage: %s GRID.f64 ROWS COLS THREADS REPEATS [preset]\n", argv[0]);
    return 2;
  }
  const std::ptrdiff_t H = std::stol(argv[2]), W = std::stol(argv[3]);
  const int nt = std::stoi(argv[4]), reps = std::stoi(argv[5]);
  const std::string preset = argc > 6 ? argv[6] : "recommended";
  g_cpu_clock = nt == 1;
  std::vector<double> xyz(static_cast<std::size_t>(H * W * 3));
  std::ifstream f(argv[1], std::ios::binary);
  f.read(reinterpret_cast<char*>(xyz.data()), static_cast<std::streamsize>(xyz.size() * 8));
  if (!f) {
    std::fprintf(stderr, "cannot read %s\n", argv[1]);
    return 2;
  }
  miem::DetectParams p = preset == "paper" ? miem::paper_params() : miem::recommended_params();
  if (preset == "recommended-no-edge") {  // the default before issue 10: no min_step, no edge test
    p.min_step_auto = false;
    p.edge_k = 0.0;
  }
  p.num_threads = nt;
  const auto g = miem::GridView<double>::dense(xyz.data(), H, W);
  const std::size_t N = static_cast<std::size_t>(H * W);
  std::vector<std::uint8_t> labels(N), flags(N);
  std::vector<double> angle(N), height(N);
  const miem::OrganizedOutput out{labels.data(), flags.data(), angle.data(), height.data()};
  // the stages of OrganizedDetector::run, in its order (organized.cpp)
  constexpr int kStages = 7;
  const char* names[kStages] = {"min_step_auto", "angle_passes", "height_test", "edge_test",
                                "miem_plane",    "heights",      "defects"};
  double best[kStages], best_run = 1e30, min_step = -1.0;
  std::fill(best, best + kStages, 1e30);
  miem::detail::Workspace ws;
  miem::OrganizedDetector det(p);
  for (int rep = 0; rep < reps; ++rep) {
    double t[kStages + 1];
    miem::DetectParams eff = p;
    t[0] = now();
    if (eff.min_step_auto) {
      eff.min_step = miem::detail::auto_min_step(g, ws.survey, nt);
      eff.min_step_auto = false;
    }
    t[1] = now();
    min_step = eff.min_step;
    miem::detail::angle_passes(g, eff, out, ws);
    t[2] = now();
    const bool ht = eff.height_test();
    if (ht) miem::detail::height_test(g, eff, labels.data(), height.data(), ws);
    t[3] = now();
    if (eff.edge_test())
      miem::detail::edge_passes(g, labels.data(), eff.edge_window, eff.edge_k,
                                eff.max_iterations, nt, ws.edge_sums, ws.edge_flags);
    t[4] = now();
    auto plane = miem::detail::miem_plane(g, labels.data(), nt, ws);
    t[5] = now();
    miem::detail::heights(g, eff, labels.data(), height.data(), ht, ws);
    t[6] = now();
    auto defects = miem::detail::organized_defects(g, labels.data(), height.data(), eff.window, ws);
    t[7] = now();
    for (int k = 0; k < kStages; ++k) best[k] = std::min(best[k], t[k + 1] - t[k]);
    (void)plane;
    const double t0 = now();
    det.run(g, out);
    best_run = std::min(best_run, now() - t0);
  }
  long long sum = 0, fsum = 0;
  unsigned long long hsum = 0, asum = 0;  // the heights' and angles' bits
  for (std::size_t i = 0; i < N; ++i) {
    sum += labels[i] * static_cast<long long>(i % 7919);
    fsum += flags[i] * static_cast<long long>(i % 7919);
    unsigned long long bits;
    std::memcpy(&bits, &height[i], sizeof bits);
    hsum = hsum * 1000003ULL + bits;
    std::memcpy(&bits, &angle[i], sizeof bits);
    asum = asum * 1000003ULL + bits;
  }
  std::printf("{\"rows\": %td, \"cols\": %td, \"threads\": %d, \"preset\": \"%s\", ", H, W, nt,
              preset.c_str());
  for (int k = 0; k < kStages; ++k) std::printf("\"%s\": %.6f, ", names[k], best[k]);
  std::printf("\"run\": %.6f, \"clock\": \"%s\", \"min_step\": %.17g, \"checksum\": %lld, "
              "\"flags_checksum\": %lld, \"height_bits\": %llu, \"angle_bits\": %llu}\n",
              best_run, g_cpu_clock ? "cpu" : "wall", min_step, sum, fsum, hsum, asum);
  return 0;
}
