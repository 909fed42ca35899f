// ProfileStream: labels equal batch detection on the same rows (generated scans with cascading
// wedge burrs, dropouts, lost profiles, threshold-grazing angles), for many parameter sets and
// both storage types; and bad profiles handled with a status without corrupting the stream.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <string>
#include <vector>

#include "miem/organized.hpp"
#include "miem/stream.hpp"
#include "test_util.hpp"

namespace {

using miem::StatusCode;

// Streams the rows of a dense grid and returns every emitted row's labels, checking the lag and
// the order on the way.
template <typename T>
std::vector<std::uint8_t> stream_labels(const std::vector<T>& grid, std::ptrdiff_t H,
                                        std::ptrdiff_t W, const miem::DetectParams& p,
                                        std::vector<double>* heights = nullptr,
                                        std::vector<miem::Defect>* defects = nullptr,
                                        double* min_step = nullptr) {
  miem::ProfileStream<T> s(W, p);
  std::vector<std::uint8_t> out(static_cast<std::size_t>(H * W), 99);
  if (heights != nullptr) heights->assign(static_cast<std::size_t>(H * W), -1e300);
  std::int64_t next = 0;
  auto take = [&](const miem::StreamRow& row) {
    EXPECT_EQ(row.index, next);
    if (row.index < 0 || row.index >= H) return;
    std::copy(row.labels, row.labels + W, out.begin() + row.index * W);
    if (heights != nullptr) std::copy(row.height, row.height + W, heights->begin() + row.index * W);
    if (defects != nullptr) defects->insert(defects->end(), row.defects, row.defects + row.n_defects);
    ++next;
  };
  for (std::ptrdiff_t r = 0; r < H; ++r) {
    miem::StreamRow row;
    const miem::Status st = s.push(grid.data() + r * W * 3, W, &row);
    EXPECT_TRUE(st.code == StatusCode::kOk || st.code == StatusCode::kEmptyProfile) << st.message;
    EXPECT_EQ(row.ready(), r >= s.lag()) << "row " << r;
    if (row.ready()) {
      EXPECT_EQ(row.index, r - s.lag());
      take(row);
    }
  }
  miem::StreamRow row;
  while (s.flush(&row)) take(row);
  EXPECT_EQ(next, H);
  EXPECT_FALSE(row.ready());
  if (min_step != nullptr) *min_step = s.min_step();
  return out;
}

// The stream's defects are batch detection's (as a set: the stream numbers them in the order
// reported): the same cells, kind and (up to the heights' rounding) summaries.
void expect_same_defects(std::vector<miem::Defect> got, std::vector<miem::Defect> want) {
  auto by_first = [](const miem::Defect& a, const miem::Defect& b) {
    return a.indices.front() < b.indices.front();
  };
  std::sort(got.begin(), got.end(), by_first);
  std::sort(want.begin(), want.end(), by_first);
  ASSERT_EQ(got.size(), want.size());
  ASSERT_FALSE(want.empty());
  std::vector<int> ids;
  for (const miem::Defect& d : got) ids.push_back(d.id);
  std::sort(ids.begin(), ids.end());
  for (std::size_t k = 0; k < ids.size(); ++k) EXPECT_EQ(ids[k], static_cast<int>(k));
  auto near = [](double a, double b) {
    return std::isnan(b) ? std::isnan(a) : std::abs(a - b) <= 1e-9 * (1.0 + std::abs(b));
  };
  for (std::size_t k = 0; k < got.size(); ++k) {
    const miem::Defect& a = got[k];
    const miem::Defect& b = want[k];
    SCOPED_TRACE("defect at cell " + std::to_string(b.indices.front()));
    EXPECT_EQ(a.indices, b.indices);
    EXPECT_EQ(a.kind, b.kind);
    EXPECT_EQ(a.centroid, b.centroid);  // the same points summed in the same (index) order
    EXPECT_TRUE(near(a.peak_height, b.peak_height)) << a.peak_height << " vs " << b.peak_height;
    EXPECT_TRUE(near(a.mean_height, b.mean_height)) << a.mean_height << " vs " << b.mean_height;
    EXPECT_TRUE(near(a.extent, b.extent)) << a.extent << " vs " << b.extent;
    for (int i = 0; i < 3; ++i) {
      EXPECT_TRUE(near(a.normal[i], b.normal[i])) << a.normal.transpose() << " vs "
                                                  << b.normal.transpose();
    }
  }
}

template <typename T>
void expect_stream_equals_batch(const std::vector<double>& grid_d, std::ptrdiff_t H,
                                std::ptrdiff_t W, const miem::DetectParams& p) {
  const std::vector<T> grid(grid_d.begin(), grid_d.end());
  const miem::DetectResult batch =
      miem::detect_organized(miem::GridView<T>::dense(grid.data(), H, W), p);
  std::vector<double> heights;
  std::vector<miem::Defect> defects;
  double min_step = 0.0;
  const std::vector<std::uint8_t> streamed =
      stream_labels(grid, H, W, p, &heights, &defects, &min_step);
  EXPECT_EQ(min_step, batch.summary.min_step);  // the value batch resolved (min_step "auto": decided)
  expect_same_defects(defects, batch.summary.defects);
  std::size_t bad = 0, bad_height = 0;
  for (std::size_t i = 0; i < streamed.size(); ++i) {
    if (streamed[i] != batch.labels[i] && ++bad <= 10) {
      ADD_FAILURE() << "cell (" << i / W << ", " << i % W << "): stream " << int(streamed[i])
                    << ", batch " << int(batch.labels[i]);
    }
    // Heights: the same window planes summed in another order, equal up to rounding.
    const double a = heights[i], b = batch.height[i];
    const bool same = std::isnan(b) ? std::isnan(a) : std::abs(a - b) <= 1e-9;
    if (!same && ++bad_height <= 10) {
      ADD_FAILURE() << "cell (" << i / W << ", " << i % W << "): stream height " << a
                    << ", batch " << b;
    }
  }
  EXPECT_EQ(bad, 0u) << "of " << streamed.size() << " cells";
  EXPECT_EQ(bad_height, 0u) << "of " << streamed.size() << " cells";
  // The scans must exercise the method: some ABNORMAL cells, and cascades when iterating.
  std::size_t abnormal = 0;
  for (auto l : batch.labels) abnormal += l == miem::kAbnormal;
  EXPECT_GT(abnormal, 0u);
}

struct Named {
  const char* name;
  miem::DetectParams params;
  std::ptrdiff_t rows = 90, cols = 70;
  bool outline = false;  // make_outline_scan: the edge test has work
  bool late_origin = false;  // dropouts over the first rows of some edge-test tiles
  double jitter = 0.0;       // z offset of whole profiles (sd): min_step "auto" turns on
  std::ptrdiff_t lead = 0;   // profiles of dropouts first (the scanner before the part)
};

// make_scan with the last third of every profile missing (the part ends: an outline) and lips
// raised along the outline (burrs on a cut edge, for the edge test), some on the feature line
// of a step across the profiles.
std::vector<double> make_outline_scan(std::ptrdiff_t H, std::ptrdiff_t W, std::uint64_t seed) {
  std::vector<double> g = miem::test::make_scan(H, W, seed);
  auto z = [&](std::ptrdiff_t r, std::ptrdiff_t c) -> double& {
    return g[static_cast<std::size_t>((r * W + c) * 3 + 2)];
  };
  const std::ptrdiff_t end = 2 * W / 3;
  for (std::ptrdiff_t r = 0; r < H; ++r) {
    for (std::ptrdiff_t c = end; c < W; ++c) {
      for (int k = 0; k < 3; ++k) g[static_cast<std::size_t>((r * W + c) * 3 + k)] = NAN;
    }
    if (r >= H / 2) {
      for (std::ptrdiff_t c = 0; c < W / 4; ++c) z(r, c) += 0.6;  // a step: a feature line
    }
  }
  std::uint64_t s = seed * 2654435761u + 1;
  auto next = [&]() { return (s = s * 6364136223846793005u + 1442695040888963407u) >> 33; };
  for (std::ptrdiff_t r0 = 3; r0 + 8 < H; r0 += 17 + static_cast<std::ptrdiff_t>(next() % 23)) {
    const std::ptrdiff_t len = 2 + static_cast<std::ptrdiff_t>(next() % 7);
    const double lift = 0.02 + 0.01 * static_cast<double>(next() % 8);
    const bool on_step = next() % 3 == 0 && r0 > H / 2;
    for (std::ptrdiff_t r = r0; r < r0 + len; ++r) {
      if (on_step) {
        z(r, W / 4 - 1) += lift;
      } else {
        z(r, end - 1) += lift;
        if (next() % 2) z(r, end - 2) += 0.5 * lift;
      }
    }
  }
  return g;
}

std::vector<Named> param_sets() {
  std::vector<Named> v;
  miem::DetectParams p = miem::paper_params();
  v.push_back({"paper", p});
  v.push_back({"stream_default", miem::stream_default_params(), 260, 70});  // lag 223
  p = miem::stream_default_params();
  p.height_mode = miem::HeightMode::kAbnormal;
  v.push_back({"stream_default_abnormal_heights", p, 260, 70});
  p = miem::stream_default_params();
  p.min_step_auto = false;
  p.min_step = 0.3;  // min_step given as a length
  v.push_back({"stream_default_min_step", p, 260, 70});
  // min_step "auto" (the default) on profiles whose jitter turns it on: decided at push 255
  // (the rows before run then), after 300 profiles of dropouts (rows handed back while it
  // waits), at the flush (fewer than 256 rows), with the edge test, and where 256 rows bound
  // the lag.
  const miem::DetectParams d = miem::stream_default_params();
  v.push_back({"default_auto_on", d, 700, 50, false, false, 0.1});
  v.push_back({"default_auto_lead", d, 900, 40, false, false, 0.1, 300});
  v.push_back({"default_auto_short", d, 180, 50, false, false, 0.1, 20});
  v.push_back({"default_auto_outline", d, 700, 60, true, false, 0.1});
  p = miem::paper_params();
  p.min_step_auto = true;
  v.push_back({"paper_auto", p, 420, 50, false, false, 0.1, 3});
  p.max_iterations = 1;
  p.max_reach = 4;  // lag max(1 * (1 + 1 + 4) + 10, 256)
  v.push_back({"paper_auto_short_lag", p, 600, 40, false, false, 0.1, 30});
  p = miem::stream_default_params();
  p.max_iterations = 3;
  p.window = 7;
  p.edge_extent = 4;
  v.push_back({"height_test_short_lag", p, 120, 70});
  p = miem::stream_default_params();
  p.height_k = 0.0;
  p.height_abs = 0.05;
  p.window = 9;
  v.push_back({"height_abs_window9", p, 120, 70});
  // The edge test (the stream's default has it), on scans with outlines and lipped edges.
  v.push_back({"stream_default_outline", miem::stream_default_params(), 420, 60, true});
  p = miem::stream_default_params();
  p.max_iterations = 3;
  p.window = 7;
  p.edge_window = 9;
  p.edge_extent = 4;
  v.push_back({"edge_short_lag_window9", p, 260, 60, true});
  p = miem::stream_default_params();
  p.edge_window = 5;
  p.edge_k = 2.5;
  p.max_iterations = 4;
  v.push_back({"edge_window5_k2p5", p, 300, 60, true});
  p = miem::paper_params();  // the edge test without the height test
  p.edge_k = 3.0;
  p.edge_window = 11;
  v.push_back({"paper_edge", p, 300, 60, true});
  // Several edge-test tiles across (128 columns each, the last one partial and empty), the
  // outline 4 columns into the third tile: sub-windows read the tile's images r columns left.
  v.push_back({"edge_wide_tiles", miem::stream_default_params(), 300, 392, true});
  // A short lag (H + 2 r < h): tiles whose origin (first finite cell) lies deep in their band.
  p.max_iterations = 2;
  p.edge_window = 5;
  v.push_back({"edge_late_origin", p, 330, 300, true, true});

  p = miem::paper_params();
  p.window = 9;
  v.push_back({"paper_window9", p});
  p = miem::paper_params();
  p.scales = {1, 2};
  p.max_gap = 2;
  v.push_back({"scales12_gap2", p});
  p = miem::paper_params();
  p.max_gap = 0;
  v.push_back({"gap0", p});
  p = miem::paper_params();
  p.scales = {2};
  p.max_gap = 0;  // smallest scale beyond the isolation reach: every cell through the judge
  v.push_back({"scale2_gap0", p});
  p = miem::paper_params();
  p.scales = {1, 3};
  p.min_directions = 2;
  v.push_back({"scales13_mindir2", p});
  p = miem::paper_params();
  p.theta0_deg = 100.0;  // cos0 < 0: every available direction takes the exact test
  v.push_back({"theta100", p});
  p = miem::paper_params();
  p.theta0_deg = 30.0;
  p.min_directions = 1;
  v.push_back({"theta30_mindir1", p});
  p = miem::paper_params();
  p.max_iterations = 1;
  v.push_back({"one_pass", p});
  p = miem::paper_params();
  p.max_iterations = 2;
  v.push_back({"two_passes", p});
  p = miem::paper_params();
  p.max_iterations = 3;
  v.push_back({"three_passes", p});
  p = miem::paper_params();
  p.min_step = 0.2;
  p.max_reach = 4;
  v.push_back({"min_step", p, 150, 60});
  return v;
}

class StreamEqualsBatch : public ::testing::TestWithParam<Named> {};

// Profile jitter and leading dropouts (Named::jitter, lead); min_step "auto" must then be on.
void jitter_and_lead(const Named& n, std::uint64_t seed, std::vector<double>& g) {
  if (n.jitter <= 0.0 && n.lead == 0) return;
  std::uint64_t s = seed * 0x9E3779B97F4A7C15u + 7;
  auto uni = [&]() {
    s = s * 6364136223846793005u + 1442695040888963407u;
    return static_cast<double>(s >> 11) * 0x1.0p-53;
  };
  for (std::ptrdiff_t r = 0; r < n.rows; ++r) {
    const double off = n.jitter * 1.7320508075688772 * (2.0 * uni() - 1.0);  // sd n.jitter
    for (std::ptrdiff_t c = 0; c < n.cols; ++c) {
      double* q = &g[static_cast<std::size_t>((r * n.cols + c) * 3)];
      if (r < n.lead) q[0] = q[1] = q[2] = NAN;
      q[2] += off;
    }
  }
  if (n.jitter > 0.0 && n.params.min_step_auto) {
    const auto view = miem::GridView<double>::dense(g.data(), n.rows, n.cols);
    EXPECT_GT(miem::auto_min_step(view), 0.0) << "the jitter must turn min_step on";
  }
}

std::vector<double> scan_for(const Named& n, std::uint64_t seed) {
  if (!n.outline) {
    std::vector<double> g = miem::test::make_scan(n.rows, n.cols, seed);
    jitter_and_lead(n, seed, g);
    return g;
  }
  // The scan must give the edge test work: it changes batch labels.
  std::vector<double> g = make_outline_scan(n.rows, n.cols, seed);
  if (n.late_origin) {  // the first finite cell of a tile 37 rows (or 60) into its band
    auto drop = [&](std::ptrdiff_t r0, std::ptrdiff_t r1, std::ptrdiff_t c0, std::ptrdiff_t c1) {
      for (std::ptrdiff_t r = r0; r < r1; ++r) {
        for (std::ptrdiff_t c = c0; c < std::min(c1, n.cols); ++c) {
          for (int k = 0; k < 3; ++k) g[static_cast<std::size_t>((r * n.cols + c) * 3 + k)] = NAN;
        }
      }
    };
    drop(64, 101, 128, 256);
    drop(192, 252, 0, 128);
  }
  jitter_and_lead(n, seed, g);
  miem::DetectParams off = n.params;
  off.edge_k = 0.0;
  const auto view = miem::GridView<double>::dense(g.data(), n.rows, n.cols);
  EXPECT_NE(miem::detect_organized(view, n.params).labels,
            miem::detect_organized(view, off).labels);
  return g;
}

TEST_P(StreamEqualsBatch, DoubleProfiles) {
  const Named& n = GetParam();
  for (std::uint64_t seed : {1u, 2u, 3u}) {
    SCOPED_TRACE("seed " + std::to_string(seed));
    expect_stream_equals_batch<double>(scan_for(n, seed), n.rows, n.cols, n.params);
  }
}

TEST_P(StreamEqualsBatch, FloatProfiles) {
  const Named& n = GetParam();
  expect_stream_equals_batch<float>(scan_for(n, 11), n.rows, n.cols, n.params);
}

// min_step beyond the point spacing on a fine, noisy scan: the neighbour searches pass over
// near candidates in every direction (pass 1's row kernel, and the later passes' rays), and
// the labels depend on it (min_step off labels otherwise).
TEST(Stream, MinStepBeyondTheSpacingEqualsBatch) {
  miem::test::ScanOptions o;
  o.dx = 0.02;
  o.dy = 0.03;
  o.noise = 0.02;
  miem::DetectParams p = miem::stream_default_params();
  p.min_step_auto = false;
  p.min_step = 0.05;  // 2.5 dx, 1.7 dy
  miem::DetectParams off = p;
  off.min_step = -1.0;
  const std::ptrdiff_t H = 260, W = 70;
  for (std::uint64_t seed : {1u, 2u}) {
    SCOPED_TRACE("seed " + std::to_string(seed));
    const std::vector<double> g = miem::test::make_scan(H, W, seed, o);
    const auto view = miem::GridView<double>::dense(g.data(), H, W);
    EXPECT_NE(miem::detect_organized(view, p).labels, miem::detect_organized(view, off).labels);
    expect_stream_equals_batch<double>(g, H, W, p);
    if (seed == 1) expect_stream_equals_batch<float>(g, H, W, p);
  }
}

INSTANTIATE_TEST_SUITE_P(Params, StreamEqualsBatch, ::testing::ValuesIn(param_sets()),
                         [](const auto& info) { return std::string(info.param.name); });

// L = P R + E + (P + 1) h with the height test, P R + h without; with the edge test
// L = max(H + 2 r, h) + (P - 1) r + h, H = P R + E + P h (P R without the height test): the
// edge test's step 9 runs r rows behind the height passes, edge pass 1 r rows behind it (and h
// rows behind the newest), pass p r rows behind pass p - 1 (docs/SPEC.md "Streaming").
// A push's column work (pass 1's filter by column range or its row kernel by blocks of 256
// columns; the edge passes' tile columns, height pass 1's strips and its column sums, 128
// columns each) is split among num_threads threads: the same labels, heights and defects as
// batch for every count, on outline scans whose removals cross strip boundaries, on scans with
// few dropouts (pass 1 by the filter) and on jittered profiles (min_step on).
TEST(Stream, EveryThreadCountEqualsBatch) {
  const std::ptrdiff_t H = 300, W = 392;  // 4 tile columns, the last one partial
  for (int nt : {1, 2, 3, 5}) {
    SCOPED_TRACE("num_threads " + std::to_string(nt));
    miem::DetectParams p = miem::stream_default_params();
    p.num_threads = nt;
    for (std::uint64_t seed : {1u, 2u}) {
      expect_stream_equals_batch<double>(make_outline_scan(H, W, seed), H, W, p);
      expect_stream_equals_batch<double>(miem::test::make_scan(H, W, seed), H, W, p);
    }
    expect_stream_equals_batch<float>(make_outline_scan(H, W, 3), H, W, p);
    // jittered profiles: min_step "auto" turns on, pass 1 by the row kernel's searches
    const Named jittered{"auto_on", p, H, W, false, false, 0.1};
    expect_stream_equals_batch<double>(scan_for(jittered, 5), H, W, p);
    miem::DetectParams paper = miem::paper_params();
    paper.num_threads = nt;
    expect_stream_equals_batch<double>(miem::test::make_scan(H, W, 4), H, W, paper);
  }
}

TEST(Stream, LagFormula) {
  miem::DetectParams p = miem::paper_params();
  EXPECT_EQ(miem::ProfileStream<>(16, p).lag(), 20 + 10);  // 10 * (1 + 1) + 21 / 2
  p.scales = {1, 2};
  p.max_gap = 2;
  p.max_iterations = 3;
  miem::ProfileStream<float> s(16, p);
  EXPECT_EQ(s.reach(), 4);
  EXPECT_EQ(s.lag(), 12 + 10);
  p = miem::paper_params();
  p.min_step = 0.1;
  p.max_reach = 5;
  EXPECT_EQ(miem::ProfileStream<>(16, p).lag(), 10 * (1 + 1 + 5) + 10);
  // The default: with the edge test (r = 15 / 2) and min_step "auto" (R = 1 + 2 + 32: its
  // value is not known before 256 rows are in; E = edge_extent 12 + max_gap 1: EDGE groups
  // link across a dropout): 463 + 2 * 7 + 9 * 7 + 10.
  EXPECT_EQ(miem::ProfileStream<>(16).lag(), (10 * 35 + 12 + 1 + 10 * 10 + 2 * 7) + 9 * 7 + 10);
  EXPECT_EQ(miem::stream_lag(miem::stream_default_params()), 550);
  p = miem::stream_default_params();
  p.min_step_auto = false;  // min_step off: R = 3, but z_resolution "auto" waits for 256 rows
  EXPECT_EQ(miem::stream_lag(p), 256);
  p.z_resolution_auto = false;  // z_noise "auto" still waits
  EXPECT_EQ(miem::stream_lag(p), 256);
  p.z_noise_auto = false;  // none: no wait
  EXPECT_EQ(miem::stream_lag(p), (10 * 3 + 12 + 1 + 10 * 10 + 2 * 7) + 9 * 7 + 10);
  p.max_iterations = 3;
  p.window = 7;
  p.edge_window = 9;
  EXPECT_EQ(miem::ProfileStream<>(16, p).lag(), (3 * 3 + 12 + 1 + 3 * 3 + 2 * 4) + 2 * 4 + 3);
  p.min_step_auto = true;  // max(L, 256): nothing runs before the 256 rows min_step reads
  EXPECT_EQ(miem::ProfileStream<>(16, p).lag(), 256);
  p.max_reach = 200;
  EXPECT_EQ(miem::ProfileStream<>(16, p).lag(), (3 * 203 + 12 + 1 + 3 * 3 + 2 * 4) + 2 * 4 + 3);
  p.min_step_auto = false;
  miem::DetectParams q = miem::paper_params();  // the edge test without the height test
  q.edge_k = 3.0;
  q.max_iterations = 40;  // H + 2 r = 40 * 2 + 2 * 7
  EXPECT_EQ(miem::ProfileStream<>(16, q).lag(), 94 + 39 * 7 + 10);
  q.max_iterations = 1;
  q.edge_window = 3;  // H + 2 r = 2 + 2 < h = 10: the rows within h of a removal must be in
  EXPECT_EQ(miem::ProfileStream<>(16, q).lag(), 10 + 0 + 10);
  p.edge_k = 0.0;  // the edge test off: P R + E + (P + 1) h
  EXPECT_EQ(miem::ProfileStream<>(16, p).lag(), 3 * 3 + 12 + 1 + 4 * 3);
}

TEST(Stream, ThresholdGrazingAnglesMatchBatch) {
  // A sawtooth along the profiles whose apex angle equals theta0 up to 1e-13 noise: every
  // cell's flag is decided by the last bits of the cosine, so the kernel must round as the
  // judge does.
  const std::ptrdiff_t H = 60, W = 80;
  miem::DetectParams p = miem::paper_params();
  const double cos0 = std::cos(p.theta0_deg * 3.14159265358979323846 / 180.0);
  const double dx = 0.25, a = 0.5 * dx * std::sqrt((1.0 + cos0) / (1.0 - cos0));
  std::vector<double> g(static_cast<std::size_t>(H * W * 3));
  std::uint64_t state = 12345;
  for (std::ptrdiff_t r = 0; r < H; ++r)
    for (std::ptrdiff_t c = 0; c < W; ++c) {
      state = state * 6364136223846793005ull + 1442695040888963407ull;
      const double e = (static_cast<double>(state >> 11) / 9007199254740992.0 - 0.5) * 1e-13;
      double* q = &g[static_cast<std::size_t>((r * W + c) * 3)];
      q[0] = c * dx;
      q[1] = r * 0.3 + 1000.0;  // far from the origin as well
      q[2] = ((c % 2) ? a : -a) * (1.0 + e) + ((r % 7 == 3 && c % 11 == 5) ? 1.0 : 0.0);
    }
  expect_stream_equals_batch<double>(g, H, W, p);
  p.scales = {1, 2};
  expect_stream_equals_batch<double>(g, H, W, p);
}

TEST(Stream, ShortStreamsAndNarrowProfiles) {
  miem::DetectParams p = miem::paper_params();
  for (std::ptrdiff_t W : {1, 2, 3, 5}) {
    for (std::ptrdiff_t H : {3, 7, 25}) {
      SCOPED_TRACE("W " + std::to_string(W) + " H " + std::to_string(H));
      miem::test::ScanOptions o;
      o.dropout_rate = 0.0;
      o.nan_rows = false;
      std::vector<double> g = miem::test::make_scan(H, W, 5, o);
      // A spike in the middle so that something happens.
      g[static_cast<std::size_t>(((H / 2) * W + W / 2) * 3 + 2)] += 3.0;
      const std::vector<std::uint8_t> s = stream_labels(g, H, W, p);
      const auto b = miem::detect_organized(miem::GridView<double>::dense(g.data(), H, W), p);
      EXPECT_EQ(s, b.labels);
    }
  }
}

TEST(Stream, WrongWidthAndNullAreRejectedWithoutHarm) {
  const std::ptrdiff_t H = 50, W = 40;
  const std::vector<double> g = miem::test::make_scan(H, W, 21);
  miem::DetectParams p = miem::paper_params();
  const std::vector<std::uint8_t> clean = stream_labels(g, H, W, p);

  miem::ProfileStream<> s(W, p);
  std::vector<std::uint8_t> out(clean.size(), 99);
  const std::vector<double> longer(static_cast<std::size_t>((W + 3) * 3), 0.0);
  miem::StreamRow row;
  for (std::ptrdiff_t r = 0; r < H; ++r) {
    if (r % 9 == 4) {
      miem::Status st = s.push(longer.data(), W + 3, &row);
      EXPECT_EQ(st.code, StatusCode::kWrongWidth);
      EXPECT_FALSE(st.ok());
      EXPECT_NE(std::string(st.message).find("width"), std::string::npos);
      EXPECT_FALSE(row.ready());
      st = s.push(static_cast<const double*>(nullptr), W, &row);
      EXPECT_EQ(st.code, StatusCode::kInvalidInput);
      EXPECT_EQ(s.push(g.data(), 0, &row).code, StatusCode::kWrongWidth);
      EXPECT_EQ(s.push(g.data(), W, nullptr).code, StatusCode::kInvalidInput);
      EXPECT_EQ(s.rows_pushed(), r);
    }
    const StatusCode code = s.push(g.data() + r * W * 3, W, &row).code;
    ASSERT_TRUE(code == StatusCode::kOk || code == StatusCode::kEmptyProfile);
    if (row.ready()) std::copy(row.labels, row.labels + W, out.begin() + row.index * W);
  }
  while (s.flush(&row)) std::copy(row.labels, row.labels + W, out.begin() + row.index * W);
  EXPECT_EQ(out, clean);
}

TEST(Stream, AllNanProfileIsARowOfDropouts) {
  const std::ptrdiff_t H = 60, W = 50;
  miem::test::ScanOptions o;
  o.nan_rows = false;
  std::vector<double> g = miem::test::make_scan(H, W, 8, o);
  for (std::ptrdiff_t c = 0; c < W; ++c)
    for (int k = 0; k < 3; ++k) g[static_cast<std::size_t>((30 * W + c) * 3 + k)] = std::nan("");
  // Infinities are dropouts too.
  g[static_cast<std::size_t>((12 * W + 7) * 3)] = std::numeric_limits<double>::infinity();
  miem::DetectParams p = miem::paper_params();
  miem::ProfileStream<> s(W, p);
  miem::StreamRow row;
  std::vector<std::uint8_t> out(static_cast<std::size_t>(H * W), 99);
  for (std::ptrdiff_t r = 0; r < H; ++r) {
    const miem::Status st = s.push(g.data() + r * W * 3, W, &row);
    EXPECT_EQ(st.code, r == 30 ? StatusCode::kEmptyProfile : StatusCode::kOk) << r;
    if (row.ready()) std::copy(row.labels, row.labels + W, out.begin() + row.index * W);
  }
  while (s.flush(&row)) std::copy(row.labels, row.labels + W, out.begin() + row.index * W);
  const auto b = miem::detect_organized(miem::GridView<double>::dense(g.data(), H, W), p);
  EXPECT_EQ(out, b.labels);
  for (std::ptrdiff_t c = 0; c < W; ++c) EXPECT_EQ(out[static_cast<std::size_t>(30 * W + c)], miem::kInvalid);
  EXPECT_EQ(out[static_cast<std::size_t>(12 * W + 7)], miem::kInvalid);
}

TEST(Stream, PushAfterFlushAndReset) {
  const std::ptrdiff_t H = 40, W = 30;
  miem::test::ScanOptions o;
  o.nan_rows = false;
  const std::vector<double> g = miem::test::make_scan(H, W, 4, o);
  miem::DetectParams p = miem::paper_params();
  miem::ProfileStream<> s(W, p);
  miem::StreamRow row;
  std::vector<std::uint8_t> first, second;
  for (auto* out : {&first, &second}) {
    for (std::ptrdiff_t r = 0; r < H; ++r) {
      ASSERT_TRUE(s.push(g.data() + r * W * 3, W, &row).ok());
      if (row.ready()) out->insert(out->end(), row.labels, row.labels + W);
    }
    while (s.flush(&row)) out->insert(out->end(), row.labels, row.labels + W);
    EXPECT_TRUE(s.finished());
    EXPECT_FALSE(s.flush(&row));
    EXPECT_EQ(s.push(g.data(), W, &row).code, StatusCode::kFinished);
    EXPECT_EQ(s.rows_pushed(), H);
    EXPECT_EQ(s.rows_emitted(), H);
    s.reset();
    EXPECT_EQ(s.rows_pushed(), 0);
  }
  EXPECT_EQ(first, second);
  EXPECT_EQ(first.size(), static_cast<std::size_t>(H * W));
}

// A stream reset in the middle of a part (edge passes, their images and candidates part way
// through) then run on another part equals batch detection on that part.
TEST(Stream, ResetMidStreamWithTheEdgeTest) {
  // W 150: one thread; W 300 on 2 threads (three tile columns split among them)
  for (const std::ptrdiff_t W : {150, 300}) {
    SCOPED_TRACE("width " + std::to_string(W));
    const std::ptrdiff_t H = 300;
    miem::DetectParams p = miem::stream_default_params();
    p.num_threads = 2;
    const std::vector<double> other = make_outline_scan(H, W, 8), g = make_outline_scan(H, W, 9);
    miem::ProfileStream<> s(W, p);
    miem::StreamRow row;
    auto pushed = [](const miem::Status& st) {
      return st.code == StatusCode::kOk || st.code == StatusCode::kEmptyProfile;  // NaN rows
    };
    for (std::ptrdiff_t r = 0; r < 277; ++r) {
      ASSERT_TRUE(pushed(s.push(other.data() + r * W * 3, W, &row)));
    }
    s.reset();
    std::vector<std::uint8_t> got;
    for (std::ptrdiff_t r = 0; r < H; ++r) {
      ASSERT_TRUE(pushed(s.push(g.data() + r * W * 3, W, &row)));
      if (row.ready()) got.insert(got.end(), row.labels, row.labels + W);
    }
    while (s.flush(&row)) got.insert(got.end(), row.labels, row.labels + W);
    const auto view = miem::GridView<double>::dense(g.data(), H, W);
    miem::DetectParams off = p;
    off.edge_k = 0.0;
    const std::vector<std::uint8_t> want = miem::detect_organized(view, p).labels;
    EXPECT_NE(want, miem::detect_organized(view, off).labels);  // the edge test has work
    EXPECT_EQ(got, want);
  }
}

TEST(Stream, StridedProfilesAreRead) {
  // x y z w records (point stride 4), as some sensor SDKs deliver them.
  const std::ptrdiff_t H = 45, W = 33;
  miem::test::ScanOptions o;
  o.nan_rows = false;
  const std::vector<double> g = miem::test::make_scan(H, W, 9, o);
  std::vector<float> xyzw(static_cast<std::size_t>(H * W * 4), 7.0f);
  std::vector<float> dense(g.begin(), g.end());
  for (std::ptrdiff_t i = 0; i < H * W; ++i)
    for (int k = 0; k < 3; ++k) xyzw[static_cast<std::size_t>(i * 4 + k)] = dense[static_cast<std::size_t>(i * 3 + k)];
  miem::DetectParams p = miem::paper_params();
  miem::ProfileStream<float> s(W, p);
  miem::StreamRow row;
  std::vector<std::uint8_t> out;
  for (std::ptrdiff_t r = 0; r < H; ++r) {
    ASSERT_TRUE(s.push(miem::PointsView<float>{xyzw.data() + r * W * 4, W, 4, 1}, &row).ok());
    if (row.ready()) out.insert(out.end(), row.labels, row.labels + W);
  }
  while (s.flush(&row)) out.insert(out.end(), row.labels, row.labels + W);
  EXPECT_EQ(out, stream_labels(dense, H, W, p));
}

TEST(Stream, BadParametersThrowOrReportStatus) {
  miem::DetectParams p = miem::paper_params();
  EXPECT_THROW(miem::ProfileStream<>(0, p), std::invalid_argument);
  p.max_iterations = 255;
  EXPECT_THROW(miem::ProfileStream<>(10, p), std::invalid_argument);
  std::optional<miem::ProfileStream<double>> s;
  EXPECT_EQ(miem::nothrow::make_stream(10, p, &s).code, StatusCode::kInvalidParameter);
  EXPECT_FALSE(s.has_value());
  p = miem::paper_params();
  p.theta0_deg = -1.0;
  EXPECT_THROW(miem::ProfileStream<float>(10, p), std::invalid_argument);
  const miem::Status st = miem::nothrow::make_stream(10, p, &s);
  EXPECT_EQ(st.code, StatusCode::kInvalidParameter);
  EXPECT_NE(std::string(st.message).find("theta0"), std::string::npos);
  EXPECT_EQ(miem::nothrow::make_stream(0, miem::stream_default_params(), &s).code,
            StatusCode::kInvalidParameter);
  EXPECT_TRUE(miem::nothrow::make_stream(10, miem::stream_default_params(), &s).ok());
  ASSERT_TRUE(s.has_value());
  EXPECT_EQ(s->width(), 10);
}

// A field the stream does not implement yet is rejected, naming it, never ignored.
TEST(Stream, RejectsFieldsItDoesNotHonour) {
  struct Case {
    const char* name;
    void (*edit)(miem::DetectParams&);
  };
  const Case cases[] = {
      {"theta0_auto", [](miem::DetectParams& p) { p.theta0_auto = true; }},
  };
  for (const Case& c : cases) {
    miem::DetectParams p = miem::stream_default_params();
    c.edit(p);
    EXPECT_TRUE(p.check().ok()) << c.name;  // fine for batch detection
    std::optional<miem::ProfileStream<double>> s;
    const miem::Status st = miem::nothrow::make_stream(10, p, &s);
    EXPECT_EQ(st.code, StatusCode::kInvalidParameter) << c.name;
    EXPECT_EQ(std::string(st.message).rfind(c.name, 0), 0u) << st.message;
    EXPECT_FALSE(s.has_value());
    try {
      miem::ProfileStream<float> thrown(10, p);
      ADD_FAILURE() << c.name << " accepted";
    } catch (const std::invalid_argument& e) {
      EXPECT_STREQ(e.what(), st.message);
    }
  }
  // The stream's default is the default preset, height and edge tests and min_step "auto"
  // included.
  std::optional<miem::ProfileStream<double>> s;
  EXPECT_TRUE(miem::nothrow::make_stream(10, miem::stream_default_params(), &s).ok());
  const miem::DetectParams d = miem::stream_default_params();
  const miem::DetectParams r;
  EXPECT_EQ(d.theta0_deg, r.theta0_deg);
  EXPECT_EQ(d.scales, r.scales);
  EXPECT_EQ(d.max_gap, r.max_gap);
  EXPECT_EQ(d.max_iterations, r.max_iterations);
  EXPECT_EQ(d.height_k, r.height_k);
  EXPECT_EQ(d.edge_extent, r.edge_extent);
  EXPECT_EQ(d.window, r.window);
  EXPECT_EQ(d.edge_k, r.edge_k);
  EXPECT_GT(d.edge_k, 0.0);
  EXPECT_EQ(d.edge_window, r.edge_window);
  EXPECT_TRUE(d.min_step_auto);
  EXPECT_EQ(d.min_step_auto, r.min_step_auto);
  EXPECT_EQ(d.max_reach, r.max_reach);
  EXPECT_LT(d.min_step, 0.0);
  EXPECT_EQ(miem::ProfileStream<>(10).params().height_k, r.height_k);
}

}  // namespace

// A defect longer than the ring (a trench along the scan, ABNORMAL with min_directions 3): its
// cells are kept after their rows left the ring, and it is reported once, after its last row.
TEST(StreamDefects, GroupLongerThanTheRing) {
  const std::ptrdiff_t H = 320, W = 60;
  miem::test::ScanOptions o;
  o.nan_rows = false;
  std::vector<double> g = miem::test::make_scan(H, W, 5, o);
  for (std::ptrdiff_t r = 5; r < 300; ++r) g[static_cast<std::size_t>((r * W + 30) * 3 + 2)] -= 1.0;
  for (miem::DetectParams p : {miem::paper_params(), miem::stream_default_params()}) {
    p.min_directions = 3;
    const miem::DetectResult batch = miem::detect_organized(
        miem::GridView<double>::dense(g.data(), H, W), p);
    std::size_t longest = 0;
    for (const miem::Defect& d : batch.summary.defects) longest = std::max(longest, d.indices.size());
    ASSERT_GT(longest, 200u);  // one cell per row: longer than the ring (about lag + 3h rows)
    expect_stream_equals_batch<double>(g, H, W, p);
  }
}
