// Where the time of organized detection goes: each stage of OrganizedDetector::run
// (cpp/src/stages.hpp) timed on its own, in the order run() calls them.
//
// Usage: miem_bench_stages GRID.f64 ROWS COLS THREADS REPEATS [paper|recommended|recommended-no-edge]
// GRID.f64 is ROWS x COLS x 3 doubles (numpy tofile). Prints one JSON object: the best time of
// each stage over REPEATS runs (seconds; process CPU time with 1 thread, wall time with more),
// the whole run() ("run": one detector reused, its workspace warm; "run_fresh": a new detector
// and new, uninitialised outputs per call, as miem.detect runs; detect_organized's outputs are
// zeroed vectors besides), the
// process CPU time of run() ("run_cpu"), the min_step used (-1: off) and checksums of the labels,
// flags, heights and angles.
// With LD_PRELOAD=libmiem_schedule_probe.so (schedule_probe.cpp) it adds "schedule": per stage
// and run, the CPU work, the critical path (serial CPU + the largest thread's CPU of each parallel
// region), the master's CPU spent entering and leaving regions and the regions, per call:
// work / critical is the speed-up the schedule allows.
#include <dlfcn.h>

#include <algorithm>
#include <chrono>
#include <ctime>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <memory>
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
double process_cpu() {
  timespec ts;
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}
// schedule_probe.cpp's hooks when it is preloaded, else no-ops
using SectionFn = void (*)(const char*);
using ResultFn = long (*)(const char*, double*);
const auto g_section = reinterpret_cast<SectionFn>(dlsym(RTLD_DEFAULT, "miem_probe_section"));
const auto g_result = reinterpret_cast<ResultFn>(dlsym(RTLD_DEFAULT, "miem_probe_result"));
void section(const char* name) {
  if (g_section) g_section(name);
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
  double best_fresh = 1e30, best_run_cpu = 1e30;
  for (int rep = 0; rep < reps; ++rep) {
    double t[kStages + 1];
    miem::DetectParams eff = p;
    section(names[0]);
    t[0] = now();
    if (eff.min_step_auto) {
      eff.min_step = miem::detail::auto_min_step(g, ws.survey, nt);
      eff.min_step_auto = false;
    }
    t[1] = now();
    min_step = eff.min_step;
    section(names[1]);
    miem::detail::angle_passes(g, eff, out, ws);
    t[2] = now();
    section(names[2]);
    const bool ht = eff.height_test();
    if (ht) miem::detail::height_test(g, eff, labels.data(), height.data(), ws);
    t[3] = now();
    section(names[3]);
    if (eff.edge_test())
      miem::detail::edge_passes(g, labels.data(), eff.edge_window, eff.edge_k,
                                eff.max_iterations, nt, ws.edge_sums, ws.edge_flags);
    t[4] = now();
    section(names[4]);
    auto plane = miem::detail::miem_plane(g, labels.data(), nt, ws);
    t[5] = now();
    section(names[5]);
    miem::detail::heights(g, eff, labels.data(), height.data(), ht, ws);
    t[6] = now();
    section(names[6]);
    auto defects =
        miem::detail::organized_defects(g, labels.data(), height.data(), eff.window, ws, nt);
    t[7] = now();
    section(nullptr);
    for (int k = 0; k < kStages; ++k) best[k] = std::min(best[k], t[k + 1] - t[k]);
    (void)plane;
    section("run");
    const double c0 = process_cpu(), t0 = now();
    det.run(g, out);
    best_run = std::min(best_run, now() - t0);
    best_run_cpu = std::min(best_run_cpu, process_cpu() - c0);
    section("run_fresh");
    const double t1 = now();
    {  // as miem.detect runs: a new detector, outputs allocated and not initialised (np.empty)
      miem::OrganizedDetector fresh_det(p);
      std::unique_ptr<std::uint8_t[]> fl(new std::uint8_t[N]), ff(new std::uint8_t[N]);
      std::unique_ptr<double[]> fa(new double[N]), fh(new double[N]);
      fresh_det.run(g, miem::OrganizedOutput{fl.get(), ff.get(), fa.get(), fh.get()});
    }
    best_fresh = std::min(best_fresh, now() - t1);
    section(nullptr);
  }
  // the fresh detector's outputs equal the reused one's
  const miem::DetectResult fresh = miem::detect_organized(g, p);
  const bool fresh_same = fresh.labels == labels && fresh.flags == flags &&
                          std::memcmp(fresh.height.data(), height.data(), N * sizeof(double)) == 0;
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
  if (g_result) {  // per call: regions, serial, work, critical, overhead
    std::printf("\"schedule\": {");
    const char* more[2] = {"run", "run_fresh"};
    for (int k = 0; k < kStages + 2; ++k) {
      const char* name = k < kStages ? names[k] : more[k - kStages];
      double r[5] = {0, 0, 0, 0, 0};
      const double calls = static_cast<double>(std::max(1L, g_result(name, r)));
      std::printf("%s\"%s\": {\"regions\": %.1f, \"serial\": %.6f, \"work\": %.6f, "
                  "\"critical\": %.6f, \"overhead\": %.6f}",
                  k ? ", " : "", name, r[0] / calls, r[1] / calls, r[2] / calls, r[3] / calls,
                  r[4] / calls);
    }
    std::printf("}, ");
  }
  std::printf("\"run\": %.6f, \"run_fresh\": %.6f, \"run_cpu\": %.6f, \"clock\": \"%s\", "
              "\"min_step\": %.17g, \"checksum\": %lld, \"flags_checksum\": %lld, "
              "\"height_bits\": %llu, \"angle_bits\": %llu, \"fresh_same\": %s}\n",
              best_run, best_fresh, best_run_cpu, g_cpu_clock ? "cpu" : "wall", min_step, sum,
              fsum, hsum, asum, fresh_same ? "true" : "false");
  return 0;
}
