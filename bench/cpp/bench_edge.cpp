// The edge test alone (cpp/src/stages.hpp edge_stage: step 9 and edge_passes), for profiling
// it (callgrind --toggle-collect='*edge_passes*') and timing it: the stages before it run once
// (or their labels and window classes come from LABELS, written there on the first run), then
// edge_stage REPEATS times.
//
// Usage: miem_bench_edge GRID.f64 ROWS COLS REPEATS [LABELS] [THREADS]
// GRID.f64 is ROWS x COLS x 3 doubles (numpy tofile); the recommended preset. Prints the best
// process CPU time of edge_passes, its passes and a checksum of the labels after it.
#include <algorithm>
#include <cstdio>
#include <ctime>
#include <fstream>
#include <string>
#include <vector>

#include "miem/organized.hpp"
#include "../../cpp/src/stages.hpp"

namespace {
double now() {
  timespec ts;
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}
}  // namespace

int main(int argc, char** argv) {
  if (argc < 5) {
    std::fprintf(stderr, "usage: %s GRID.f64 ROWS COLS REPEATS [LABELS] [THREADS]\n", argv[0]);
    return 2;
  }
  const std::ptrdiff_t H = std::stol(argv[2]), W = std::stol(argv[3]);
  const int reps = std::stoi(argv[4]);
  const std::string cache = argc > 5 ? argv[5] : "";
  const int threads = argc > 6 ? std::stoi(argv[6]) : 1;
  const std::size_t N = static_cast<std::size_t>(H * W);
  std::vector<double> xyz(3 * N);
  {
    std::ifstream f(argv[1], std::ios::binary);
    f.read(reinterpret_cast<char*>(xyz.data()), static_cast<std::streamsize>(xyz.size() * 8));
    if (!f) {
      std::fprintf(stderr, "cannot read %s\n", argv[1]);
      return 1;
    }
  }
  miem::DetectParams p = miem::recommended_params();
  p.num_threads = threads;
  const auto g = miem::GridView<double>::dense(xyz.data(), H, W);
  std::vector<std::uint8_t> labels(N), flags(N);
  std::vector<double> angle(N), height(N);
  const miem::OrganizedOutput out{labels.data(), flags.data(), angle.data(), height.data()};
  miem::detail::Workspace ws;
  bool have = false;
  if (!cache.empty()) {
    std::ifstream f(cache, std::ios::binary);
    if (f) {
      ws.cls.resize(N);
      f.read(reinterpret_cast<char*>(labels.data()), static_cast<std::streamsize>(N));
      f.read(reinterpret_cast<char*>(ws.cls.data()), static_cast<std::streamsize>(N));
      have = static_cast<bool>(f);
    }
  }
  miem::DetectParams eff = p;  // min_step, z_resolution "auto" resolved (stages, floors)
  miem::detail::resolve_auto_lengths(g, eff, ws.survey, ws.zkeys, threads);
  if (!have) {
    miem::detail::angle_passes(g, eff, out, ws);
    if (eff.height_test()) miem::detail::height_test(g, eff, labels.data(), height.data(), ws);
    if (!cache.empty()) {
      std::ofstream f(cache, std::ios::binary);
      f.write(reinterpret_cast<const char*>(labels.data()), static_cast<std::streamsize>(N));
      f.write(reinterpret_cast<const char*>(ws.cls.data()), static_cast<std::streamsize>(N));
    }
  }
  const std::vector<std::uint8_t> before = labels;
  double best = 1e30;
  int passes = 0;
  for (int rep = 0; rep < reps; ++rep) {
    labels = before;
    const double t0 = now();
    passes = miem::detail::edge_stage(g, eff, labels.data(), eff.height_test(), ws);
    best = std::min(best, now() - t0);
  }
  unsigned long long sum = 0, nab0 = 0, nab = 0;
  for (std::size_t i = 0; i < N; ++i) {
    sum = sum * 1000003ull + labels[i];
    nab0 += before[i] == miem::kAbnormal;
    nab += labels[i] == miem::kAbnormal;
  }
  std::printf("edge %.2f ms passes %d checksum %llu abnormal %llu -> %llu\n", best * 1e3, passes,
              sum, nab0, nab);
  return 0;
}
