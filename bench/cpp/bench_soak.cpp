// Soak benchmark: 10^6 profiles through one miem::ProfileStream, with random dropouts (single
// points, runs, whole missing profiles), burr tips, pits and spatter, and a new part (reset)
// now and then. Per window of profiles it prints the push latency percentiles and the resident
// memory, one JSON object per line (bench/run_soak.py turns them into bench/results_soak.md):
// the latency must not drift and the memory must stay flat.
//
//   miem_bench_soak [--width 1280] [--profiles 1000000] [--window 100000] [--seed 1]
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <random>
#include <string>
#include <vector>

#include <unistd.h>

#include "miem/organized.hpp"
#include "miem/stream.hpp"

namespace {

using Clock = std::chrono::steady_clock;

long rss_kb() {
  long pages = 0, resident = 0;
  if (FILE* f = std::fopen("/proc/self/statm", "r")) {
    if (std::fscanf(f, "%ld %ld", &pages, &resident) != 2) resident = 0;
    std::fclose(f);
  }
  return resident * (sysconf(_SC_PAGESIZE) / 1024);
}

double quantile(std::vector<double>& v, double q) {
  const std::size_t k = std::min(v.size() - 1, static_cast<std::size_t>(q * v.size()));
  std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(k), v.end());
  return v[k];
}

}  // namespace

int main(int argc, char** argv) {
  std::ptrdiff_t W = 1280, n = 1000000, window = 100000;
  unsigned seed = 1;
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string a = argv[i];
    if (a == "--width") W = std::atol(argv[i + 1]);
    else if (a == "--profiles") n = std::atol(argv[i + 1]);
    else if (a == "--window") window = std::atol(argv[i + 1]);
    else if (a == "--seed") seed = static_cast<unsigned>(std::atol(argv[i + 1]));
    else {
      std::fprintf(stderr, "usage: %s [--width N] [--profiles N] [--window N] [--seed N]\n",
                   argv[0]);
      return 2;
    }
  }
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> uni(0.0, 1.0);
  std::normal_distribution<double> noise(0.0, 0.002);
  // A pool of noisy rows of a gently curved sheet; each pushed profile is a pool row with its
  // own dropouts and defects drawn fresh.
  const std::ptrdiff_t pool_rows = 512;
  const double dx = 0.05, dy = 0.1;
  std::vector<double> pool(static_cast<std::size_t>(pool_rows * W));
  for (std::ptrdiff_t r = 0; r < pool_rows; ++r)
    for (std::ptrdiff_t c = 0; c < W; ++c)
      pool[static_cast<std::size_t>(r * W + c)] =
          0.3 * std::sin(c * dx / 9.0) + 0.02 * std::sin(6.2831853 * r / pool_rows) + noise(rng);

  // the stream's default: the recommended detector without the edge test and min_step auto
  const miem::DetectParams params = miem::stream_default_params();
  miem::ProfileStream<double> stream(W, params);
  std::vector<double> profile(static_cast<std::size_t>(W * 3));
  std::vector<double> lat;
  lat.reserve(static_cast<std::size_t>(window));
  miem::StreamRow row;
  long long abnormal = 0, rows_out = 0, bad_status = 0, resets = 0, empty = 0;
  const long rss0 = rss_kb();
  std::ptrdiff_t part_row = 0;
  const auto t_start = Clock::now();
  for (std::ptrdiff_t i = 0; i < n; ++i) {
    // stage the profile (not timed)
    const double* base = &pool[static_cast<std::size_t>((i % pool_rows) * W)];
    for (std::ptrdiff_t c = 0; c < W; ++c) {
      double* p = &profile[static_cast<std::size_t>(c * 3)];
      p[0] = c * dx;
      p[1] = part_row * dy;
      p[2] = base[c];
    }
    const double u = uni(rng);
    if (u < 0.002) {  // a missing profile (all dropouts)
      for (double& v : profile) v = NAN;
      ++empty;
    } else {
      const int drops = static_cast<int>(uni(rng) * uni(rng) * 0.05 * static_cast<double>(W));
      for (int k = 0; k < drops; ++k) profile[static_cast<std::size_t>(rng() % W) * 3 + 2] = NAN;
      if (u < 0.05) {  // a run of dropouts (a shiny patch)
        const std::ptrdiff_t c0 = static_cast<std::ptrdiff_t>(rng() % W);
        const std::ptrdiff_t len = 1 + static_cast<std::ptrdiff_t>(rng() % 64);
        for (std::ptrdiff_t c = c0; c < std::min(W, c0 + len); ++c)
          profile[static_cast<std::size_t>(c * 3)] = NAN;
      }
      const int defects = static_cast<int>(rng() % 4);
      for (int k = 0; k < defects; ++k) {
        const std::size_t c = static_cast<std::size_t>(rng() % W);
        profile[c * 3 + 2] += (uni(rng) < 0.7 ? 1.0 : -1.0) * (0.2 + 2.0 * uni(rng));
      }
    }
    const auto a = Clock::now();
    const miem::Status st = stream.push(profile.data(), W, &row);
    const auto b = Clock::now();
    lat.push_back(std::chrono::duration<double, std::micro>(b - a).count());
    bad_status += !st.ok() && st.code != miem::StatusCode::kEmptyProfile;
    ++part_row;
    if (row.ready()) {
      ++rows_out;
      for (std::ptrdiff_t c = 0; c < W; ++c) abnormal += row.labels[c] == miem::kAbnormal;
    }
    if (uni(rng) < 2e-5) {  // a new part: finish this one, start again
      while (stream.flush(&row)) ++rows_out;
      stream.reset();
      part_row = 0;
      ++resets;
    }
    if (static_cast<std::ptrdiff_t>(lat.size()) == window || i + 1 == n) {
      const double elapsed = std::chrono::duration<double>(Clock::now() - t_start).count();
      double sum = 0;
      for (double v : lat) sum += v;
      const double mean = sum / static_cast<double>(lat.size());
      const double p50 = quantile(lat, 0.5), p99 = quantile(lat, 0.99);
      const double p999 = quantile(lat, 0.999), mx = *std::max_element(lat.begin(), lat.end());
      std::printf("{\"profiles\": %td, \"elapsed_s\": %.2f, \"mean_us\": %.3f, \"p50_us\": %.3f, "
                  "\"p99_us\": %.3f, \"p999_us\": %.3f, \"max_us\": %.1f, \"rss_kb\": %ld, "
                  "\"rss0_kb\": %ld, \"rows_out\": %lld, \"abnormal\": %lld, \"resets\": %lld, "
                  "\"empty\": %lld, \"bad_status\": %lld, \"width\": %td, \"lag\": %d}\n",
                  i + 1, elapsed, mean, p50, p99, p999, mx, rss_kb(), rss0, rows_out, abnormal,
                  resets, empty, bad_status, W, stream.lag());
      std::fflush(stdout);
      lat.clear();
    }
  }
  return bad_status == 0 ? 0 : 1;
}
