// Where the time of organized detection goes: each stage of OrganizedDetector::run
// (cpp/src/stages.hpp) timed on its own, in the order run() calls them.
//
// Usage: miem_bench_stages GRID.f64 ROWS COLS THREADS REPEATS [paper|recommended|recommended-no-edge]
//        [fresh-stages]
// GRID.f64 is ROWS x COLS x 3 doubles (numpy tofile). Prints one JSON object: the best time of
// each stage over REPEATS runs (seconds; process CPU time with 1 thread, wall time with more),
// the whole run() ("run": one detector reused, its workspace warm; "run_fresh": a new detector
// and new, uninitialised outputs per call allocated as np.empty allocates them, as miem.detect
// runs; detect_organized's outputs are zeroed vectors besides), the process CPU time of both
// ("run_cpu", "fresh_cpu"), their minor page faults (last repeat) and least system CPU time
// ("run_faults", "fresh_faults", "run_sys", "fresh_sys"), the min_step used (-1: off) and
// checksums of the labels, flags, heights and angles. With "fresh-stages" it adds
// "fresh_stages": each stage timed as in a fresh run (a new workspace and new outputs per
// repeat), with the minor page faults and the system CPU time (getrusage, all threads) of each
// stage and of the release of the buffers ("free"): where a new detector's extra time goes.
// With LD_PRELOAD=libmiem_schedule_probe.so (schedule_probe.cpp) it adds "schedule": per stage
// and run, the CPU work, the critical path (serial CPU + the largest thread's CPU of each parallel
// region), the master's CPU spent entering and leaving regions and the regions, per call:
// work / critical is the speed-up the schedule allows.
#include <dlfcn.h>
#include <sys/mman.h>
#include <sys/resource.h>

#include <algorithm>
#include <chrono>
#include <ctime>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <memory>
#include <new>
#include <string>
#include <vector>

#include "miem/organized.hpp"
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
// An output array as np.empty allocates it (miem.detect's outputs): malloc, and from 4 MiB on
// MADV_HUGEPAGE from the next 4 KiB page to the end (NumPy's default_malloc, numpy alloc.c).
template <typename T>
struct NumpyEmpty {
  T* p;
  explicit NumpyEmpty(std::size_t n) : p(static_cast<T*>(std::malloc(n * sizeof(T)))) {
    if (p == nullptr) throw std::bad_alloc();
#ifdef MADV_HUGEPAGE
    const std::size_t bytes = n * sizeof(T);
    if (bytes >= (std::size_t{1} << 22)) {
      const std::size_t off = 4096 - reinterpret_cast<std::uintptr_t>(p) % 4096;
      madvise(reinterpret_cast<char*>(p) + off, bytes - off, MADV_HUGEPAGE);
    }
#endif
  }
  NumpyEmpty(const NumpyEmpty&) = delete;
  NumpyEmpty& operator=(const NumpyEmpty&) = delete;
  ~NumpyEmpty() { std::free(p); }
};
// minor page faults and system CPU seconds of the process so far (all threads)
struct Usage {
  long minflt = 0;
  double sys = 0.0;
};
Usage usage() {
  rusage ru;
  getrusage(RUSAGE_SELF, &ru);
  return {ru.ru_minflt, static_cast<double>(ru.ru_stime.tv_sec) + 1e-6 * ru.ru_stime.tv_usec};
}
// The stages of OrganizedDetector::run in its order (organized.cpp) on `out` with workspace
// `ws`; at(k) is called before stage k (k = 0..6) and after the last (k = 7). Returns the
// min_step used (-1: off).
template <typename At>
double run_stages(const miem::GridView<double>& g, const miem::DetectParams& p,
                  const miem::OrganizedOutput& out, miem::detail::Workspace& ws, int nt, At at) {
  miem::DetectParams eff = p;
  at(0);
  miem::detail::resolve_auto_lengths(g, eff, ws.survey, ws.zkeys, nt);
  at(1);
  miem::detail::angle_passes(g, eff, out, ws);
  at(2);
  const bool ht = eff.height_test();
  if (ht) miem::detail::height_test(g, eff, out.labels, out.height, ws);
  at(3);
  if (eff.edge_test()) miem::detail::edge_stage(g, eff, out.labels, ht, ws);
  at(4);
  (void)miem::detail::miem_plane(g, out.labels, nt, ws);
  at(5);
  miem::detail::heights(g, eff, out.labels, out.height, ht, ws);
  at(6);
  (void)miem::detail::organized_defects(g, out.labels, out.height, eff.window, ws, nt);
  at(7);
  return eff.min_step;
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
  const bool fresh_stages = argc > 7 && std::string(argv[7]) == "fresh-stages";
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
  double best_fresh = 1e30, best_run_cpu = 1e30, run_sys = 1e30, fresh_sys = 1e30;
  double best_fresh_cpu = 1e30;
  long run_flt = 0, fresh_flt = 0;  // minor page faults of the last repeat
  for (int rep = 0; rep < reps; ++rep) {
    double t[kStages + 1];
    min_step = run_stages(g, p, out, ws, nt, [&](int k) {
      t[k] = now();
      section(k < kStages ? names[k] : nullptr);
    });
    for (int k = 0; k < kStages; ++k) best[k] = std::min(best[k], t[k + 1] - t[k]);
    section("run");
    const Usage u0 = usage();
    const double c0 = process_cpu(), t0 = now();
    det.run(g, out);
    best_run = std::min(best_run, now() - t0);
    best_run_cpu = std::min(best_run_cpu, process_cpu() - c0);
    const Usage u1 = usage();
    run_flt = u1.minflt - u0.minflt;
    run_sys = std::min(run_sys, u1.sys - u0.sys);
    section("run_fresh");
    const double c1 = process_cpu(), t1 = now();
    {  // as miem.detect runs: a new detector, outputs allocated and not initialised (np.empty)
      miem::OrganizedDetector fresh_det(p);
      NumpyEmpty<std::uint8_t> fl(N), ff(N);
      NumpyEmpty<double> fa(N), fh(N);
      fresh_det.run(g, miem::OrganizedOutput{fl.p, ff.p, fa.p, fh.p});
    }
    best_fresh = std::min(best_fresh, now() - t1);
    best_fresh_cpu = std::min(best_fresh_cpu, process_cpu() - c1);
    const Usage u2 = usage();
    fresh_flt = u2.minflt - u1.minflt;
    fresh_sys = std::min(fresh_sys, u2.sys - u1.sys);
    section(nullptr);
  }
  // Each stage as a fresh run meets it: a new workspace and new, uninitialised outputs.
  constexpr int kFresh = kStages + 1;  // the stages and the release of the buffers
  double fbest[kFresh], fsys[kFresh];
  long fflt[kFresh];
  std::fill(fbest, fbest + kFresh, 1e30);
  std::fill(fsys, fsys + kFresh, 1e30);
  std::fill(fflt, fflt + kFresh, 0L);
  for (int rep = 0; fresh_stages && rep < reps; ++rep) {
    double t[kFresh + 1];
    Usage u[kFresh + 1];
    auto mark = [&](int k) {
      u[k] = usage();
      t[k] = now();
    };
    {
      auto fws = std::make_unique<miem::detail::Workspace>();
      NumpyEmpty<std::uint8_t> fl(N), ff(N);
      NumpyEmpty<double> fa(N), fh(N);
      const miem::OrganizedOutput fo{fl.p, ff.p, fa.p, fh.p};
      (void)run_stages(g, p, fo, *fws, nt, mark);
    }
    mark(8);
    for (int k = 0; k < kFresh; ++k) {
      if (t[k + 1] - t[k] < fbest[k]) fflt[k] = u[k + 1].minflt - u[k].minflt;
      fbest[k] = std::min(fbest[k], t[k + 1] - t[k]);
      fsys[k] = std::min(fsys[k], u[k + 1].sys - u[k].sys);
    }
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
  if (fresh_stages) {  // per stage: best time, its minor faults, least system time
    std::printf("\"fresh_stages\": {");
    for (int k = 0; k < kFresh; ++k)
      std::printf("%s\"%s\": [%.6f, %ld, %.6f]", k ? ", " : "", k < kStages ? names[k] : "free",
                  fbest[k], fflt[k], fsys[k]);
    std::printf("}, ");
  }
  std::printf("\"run\": %.6f, \"run_fresh\": %.6f, \"run_cpu\": %.6f, \"clock\": \"%s\", "
              "\"min_step\": %.17g, \"checksum\": %lld, \"flags_checksum\": %lld, "
              "\"height_bits\": %llu, \"angle_bits\": %llu, \"fresh_same\": %s, "
              "\"fresh_cpu\": %.6f, \"run_faults\": %ld, \"fresh_faults\": %ld, "
              "\"run_sys\": %.6f, \"fresh_sys\": %.6f}\n",
              best_run, best_fresh, best_run_cpu, g_cpu_clock ? "cpu" : "wall", min_step, sum,
              fsum, hsum, asum, fresh_same ? "true" : "false", best_fresh_cpu, run_flt, fresh_flt,
              run_sys, fresh_sys);
  return 0;
}
