// Streaming benchmark: profiles/s and per-push latency (p50 / p99 / p99.9 / max) of
// miem::ProfileStream on laser profiles of 3200 points, one core. Prints one JSON object per
// scenario (bench/run_cpp.py turns them into bench/results_cpp.md).
//
//   miem_bench_stream [--width 3200] [--profiles 100000] [--edge-profiles 3000] [--quick]
//                     [--only INDEX] [--threads N]
// --threads sets DetectParams::num_threads (default 0: all the cores the process may use, so
// 1 when pinned to one core).
// Scenarios with the edge test push at most --edge-profiles profiles (far slower per profile).
// The profiles are measured in the steady state: after 2 lag + 8 profiles of the same part
// (every stage then runs on each push); the part start's longest push (while min_step "auto"
// is decided, spread over the pushes, and the stages catch up) is reported apart.
// Each push is timed in wall time and in this thread's CPU time (the latter immune to the other
// jobs of a shared machine).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <random>
#include <string>
#include <vector>

#include <time.h>

#include "miem/organized.hpp"
#include "miem/stream.hpp"

namespace {

using Clock = std::chrono::steady_clock;

// CPU time of this thread: on a shared, busy machine this is what one core sustains, whatever
// the scheduler does to the wall clock.
double thread_cpu_s() {
  timespec ts;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

struct Scenario {
  const char* name;
  miem::DetectParams params;
  double dropout_rate;
  bool use_float;
  double jitter = 0.0;  // sd of whole-profile z offsets (mm): turns min_step "auto" on
};

// The stage scenarios' names (bench/run_cpp.py takes each stage's time as the difference of
// consecutive ones).
constexpr const char* kStageNames[] = {
    "stage: angle test only (no height test, no edge test, ABNORMAL heights)",
    "stage: angle test + heights",
    "stage: angle test + heights + height test (the default without the edge test)",
};

// A pool of profiles (rows) of a curved sheet, periodic in rows, with scanner noise (z quantised
// to a micrometre), burr tips, pits, spatter and dropouts; with `jitter`, each profile offset in
// z (a profiler's profile-to-profile jitter, which turns min_step "auto" on).
std::vector<double> make_pool(std::ptrdiff_t rows, std::ptrdiff_t W, double dropout_rate,
                              unsigned seed, double jitter = 0.0) {
  std::mt19937_64 rng(seed), rng_jitter(seed + 1);
  std::normal_distribution<double> jitter_dist(0.0, 1.0);
  std::normal_distribution<double> noise(0.0, 0.002);
  std::uniform_real_distribution<double> uni(0.0, 1.0);
  std::vector<double> g(static_cast<std::size_t>(rows * W * 3));
  const double dx = 0.05, dy = 0.1, xc = 0.5 * W * dx;
  for (std::ptrdiff_t r = 0; r < rows; ++r) {
    const double offset = jitter > 0.0 ? jitter * jitter_dist(rng_jitter) : 0.0;
    for (std::ptrdiff_t c = 0; c < W; ++c) {
      double* p = &g[static_cast<std::size_t>((r * W + c) * 3)];
      const double x = c * dx;
      p[0] = x;
      p[1] = r * dy;
      p[2] = std::round((2.0 * std::exp(-(x - xc) * (x - xc) / 2000.0) +
                         0.05 * std::sin(6.283185307179586 * static_cast<double>(r) /
                                         static_cast<double>(rows)) +
                         noise(rng) + offset) * 1000.0) / 1000.0;
      if (uni(rng) < 0.0002) p[2] += 0.3 + uni(rng);           // burr tips and spatter
      if (uni(rng) < 0.0001) p[2] -= 0.3 + uni(rng);           // pits
      if (uni(rng) < dropout_rate) p[0] = p[1] = p[2] = NAN;   // dropouts
    }
  }
  return g;
}

template <typename T>
void run(const Scenario& sc, std::ptrdiff_t W, std::ptrdiff_t n_profiles, std::ptrdiff_t pool_rows,
         bool first) {
  const std::vector<double> pool_d = make_pool(pool_rows, W, sc.dropout_rate, 7, sc.jitter);
  const std::vector<T> pool(pool_d.begin(), pool_d.end());
  miem::ProfileStream<T> stream(W, sc.params);
  std::vector<T> profile(static_cast<std::size_t>(W * 3));
  // The sensor hands over a freshly written buffer: copy a pool row into it with the running
  // y (the pool's z pattern is periodic in rows, so the scan has no seam), then push.
  auto stage = [&](std::ptrdiff_t r) {
    std::memcpy(profile.data(), pool.data() + (r % pool_rows) * W * 3, profile.size() * sizeof(T));
    const T y = static_cast<T>(0.1 * static_cast<double>(r));
    for (std::ptrdiff_t c = 0; c < W; ++c) profile[static_cast<std::size_t>(c * 3 + 1)] = y;
  };
  miem::StreamRow row;
  // The part's start (not measured below): the first lag pushes run fewer stages (nothing
  // is final yet), and with min_step "auto" the stages wait while it is decided (spread over
  // the pushes) and then catch up; the longest of those pushes' CPU times is reported apart
  // (part_start_cpu_max_us). The
  // measured pushes follow in the same part, every stage running: the steady state.
  const std::ptrdiff_t warm = 2 * static_cast<std::ptrdiff_t>(stream.lag()) + 8;
  double start_max_us = 0.0;
  for (std::ptrdiff_t r = 0; r < warm; ++r) {
    stage(r);
    const double ca = thread_cpu_s();
    stream.push(profile.data(), W, &row);
    start_max_us = std::max(start_max_us, 1e6 * (thread_cpu_s() - ca));
  }

  std::vector<double> lat_us(static_cast<std::size_t>(n_profiles));
  std::vector<double> cpu_us(static_cast<std::size_t>(n_profiles));  // this thread's CPU time
  long long abnormal = 0, edge = 0, statuses = 0;
  const double cpu0 = thread_cpu_s();
  double staging_cpu = 0.0;
  for (std::ptrdiff_t r = 0; r < n_profiles; ++r) {
    stage(warm + r);
    const double ca = thread_cpu_s();
    const auto a = Clock::now();
    statuses += !stream.push(profile.data(), W, &row).ok();
    const auto b = Clock::now();
    cpu_us[static_cast<std::size_t>(r)] = 1e6 * (thread_cpu_s() - ca);
    lat_us[static_cast<std::size_t>(r)] = std::chrono::duration<double, std::micro>(b - a).count();
    if (row.ready()) {
      for (std::ptrdiff_t c = 0; c < W; ++c) {
        abnormal += row.labels[c] == miem::kAbnormal;
        edge += row.labels[c] == miem::kEdge;
      }
    }
  }
  const double cpu_s = thread_cpu_s() - cpu0;
  // CPU time of the staging and counting alone, to take it out of the CPU-time throughput.
  {
    const double c0 = thread_cpu_s();
    long long sink = 0;
    for (std::ptrdiff_t r = 0; r < n_profiles; ++r) {
      stage(warm + r);
      for (std::ptrdiff_t c = 0; c < W; ++c) sink += row.labels[c] == miem::kAbnormal;
      const double ca = thread_cpu_s();
      const auto a = Clock::now();
      const auto b = Clock::now();
      sink += (b - a).count() > 0 || thread_cpu_s() > ca;
    }
    staging_cpu = thread_cpu_s() - c0;
    if (sink == -1) std::printf("%lld", sink);
  }
  while (stream.flush(&row)) {
  }

  std::vector<double> s = lat_us;
  std::sort(s.begin(), s.end());
  auto q = [&](double f) {
    return s[std::min(s.size() - 1, static_cast<std::size_t>(f * static_cast<double>(s.size())))];
  };
  std::vector<double> sc_ = cpu_us;  // per-push CPU time: immune to the other jobs' load
  std::sort(sc_.begin(), sc_.end());
  auto qc = [&](double f) {
    return sc_[std::min(sc_.size() - 1, static_cast<std::size_t>(f * static_cast<double>(sc_.size())))];
  };
  double total_us = 0;
  for (double v : s) total_us += v;
  const double mean = total_us / static_cast<double>(s.size());
  std::printf("%s{\"scenario\": \"%s\", \"dtype\": \"%s\", \"width\": %td, \"profiles\": %td, "
              "\"lag\": %d, \"profiles_per_s\": %.1f, \"profiles_per_cpu_s\": %.1f, "
              "\"mean_us\": %.3f, \"p50_us\": %.3f, \"p99_us\": %.3f, \"p999_us\": %.3f, "
              "\"max_us\": %.3f, \"cpu_p50_us\": %.3f, \"cpu_p99_us\": %.3f, "
              "\"cpu_p999_us\": %.3f, \"cpu_max_us\": %.3f, \"abnormal\": %lld, \"edge\": %lld, "
              "\"bad_status\": %lld, \"min_step\": %.6g, \"part_start_cpu_max_us\": %.3f, "
              "\"threads\": %d}",
              first ? "" : ",\n", sc.name, sizeof(T) == 4 ? "float32" : "float64", W, n_profiles,
              stream.lag(), 1e6 / mean,
              static_cast<double>(n_profiles) / std::max(1e-9, cpu_s - staging_cpu), mean, q(0.5),
              q(0.99), q(0.999), s.back(), qc(0.5), qc(0.99), qc(0.999), sc_.back(), abnormal,
              edge, statuses, stream.min_step(), start_max_us, sc.params.num_threads);
  std::fflush(stdout);
}

}  // namespace

int main(int argc, char** argv) {
  std::ptrdiff_t W = 3200, n = 100000, n_edge = 3000;
  bool quick = false;
  int only = -1, threads = 0;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--width" && i + 1 < argc) W = std::atol(argv[++i]);
    else if (a == "--profiles" && i + 1 < argc) n = std::atol(argv[++i]);
    else if (a == "--edge-profiles" && i + 1 < argc) n_edge = std::atol(argv[++i]);
    else if (a == "--quick") quick = true;
    else if (a == "--only" && i + 1 < argc) only = std::atoi(argv[++i]);
    else if (a == "--threads" && i + 1 < argc) threads = std::atoi(argv[++i]);
    else {
      std::fprintf(stderr,
                   "usage: %s [--width N] [--profiles N] [--edge-profiles N] [--quick] "
                   "[--only INDEX] [--threads N]\n",
                   argv[0]);
      return 2;
    }
  }
  if (quick) n = std::min<std::ptrdiff_t>(n, 5000);
  if (quick) n_edge = std::min<std::ptrdiff_t>(n_edge, 600);
  std::vector<Scenario> scenarios;
  // The stream's default: the default preset (angle test, height test with compact EDGE
  // groups, edge test, min_step "auto", heights, defects).
  const miem::DetectParams p = miem::stream_default_params();
  scenarios.push_back({"default preset, 0.1% dropouts", p, 0.001, false});
  scenarios.push_back({"default preset, 1% dropouts", p, 0.01, false});
  // as many as a real profiler scan (second_source.pcd: 4.6 %)
  scenarios.push_back({"default preset, 5% dropouts", p, 0.05, false});
  scenarios.push_back({"default preset, float32 storage", p, 0.001, true});
  miem::DetectParams pa = p;
  pa.height_mode = miem::HeightMode::kAbnormal;
  scenarios.push_back({"default preset, heights of ABNORMAL points only", pa, 0.001, false});
  // Where the time goes: the angle test alone (no height test, no heights), then with
  // heights, then with the height test; the default adds the edge test.
  miem::DetectParams p0 = p;
  p0.height_k = p0.height_abs = 0.0;
  p0.edge_k = 0.0;
  p0.height_mode = miem::HeightMode::kAbnormal;
  scenarios.push_back({kStageNames[0], p0, 0.001, false});
  miem::DetectParams p1 = p0;
  p1.height_mode = miem::HeightMode::kAll;
  scenarios.push_back({kStageNames[1], p1, 0.001, false});
  miem::DetectParams p2 = p;
  p2.edge_k = 0.0;
  scenarios.push_back({kStageNames[2], p2, 0.001, false});
  miem::DetectParams p3 = miem::paper_params();  // the paper's method
  scenarios.push_back({"paper (theta0 75, scales (1,), heights)", p3, 0.001, false});
  miem::DetectParams p4 = p;
  p4.max_iterations = 3;
  scenarios.push_back({"default preset, max_iterations 3", p4, 0.001, false});
  // min_step "auto" resolves to off on the pool above (its noise is below the point spacing);
  // profiles jittered by 0.02 mm turn it on (about 0.08 mm): pass 1 then computes every
  // cell's verdict (the neighbour searches, no vectorised filter), the later passes re-judge
  // more cells (R = 35), and the decision's rounds find values to select.
  scenarios.push_back({"default preset, min_step on (profiles jittered 0.02 mm)", p, 0.001,
                       false, 0.02});
  const std::ptrdiff_t pool_rows = 1024;
  std::printf("[\n");
  bool first = true;
  for (std::size_t k = 0; k < scenarios.size(); ++k) {
    if (only >= 0 && static_cast<int>(k) != only) continue;
    Scenario sc = scenarios[k];
    sc.params.num_threads = threads;
    const std::ptrdiff_t m = sc.params.edge_test() ? std::min(n, n_edge) : n;
    if (sc.use_float) run<float>(sc, W, m, pool_rows, first);
    else run<double>(sc, W, m, pool_rows, first);
    first = false;
  }
  std::printf("\n]\n");
  return 0;
}
