// ProfileStream allocates nothing per profile after construction: global operator new is
// replaced in this test binary by a counting one (its own executable, so that nothing else is
// affected).
#include <gtest/gtest.h>

#include <atomic>
#include <cstdlib>
#include <new>
#include <vector>

#include "miem/stream.hpp"
#include "test_util.hpp"

namespace {
std::atomic<long> g_news{0};

void* counted_alloc(std::size_t n) {
  g_news.fetch_add(1, std::memory_order_relaxed);
  if (void* p = std::malloc(n == 0 ? 1 : n)) return p;
  throw std::bad_alloc();
}
}  // namespace

void* operator new(std::size_t n) { return counted_alloc(n); }
void* operator new[](std::size_t n) { return counted_alloc(n); }
void* operator new(std::size_t n, const std::nothrow_t&) noexcept {
  g_news.fetch_add(1, std::memory_order_relaxed);
  return std::malloc(n == 0 ? 1 : n);
}
void* operator new[](std::size_t n, const std::nothrow_t&) noexcept {
  g_news.fetch_add(1, std::memory_order_relaxed);
  return std::malloc(n == 0 ? 1 : n);
}
void operator delete(void* p) noexcept { std::free(p); }
void operator delete[](void* p) noexcept { std::free(p); }
void operator delete(void* p, std::size_t) noexcept { std::free(p); }
void operator delete[](void* p, std::size_t) noexcept { std::free(p); }

namespace {

template <typename T>
void run_without_allocating(const miem::DetectParams& p, std::ptrdiff_t W = 200) {
  const std::ptrdiff_t H = 600;  // edge passes while pushing (lag 223); W 200: 2 tile columns
  const std::vector<double> g = miem::test::make_scan(H, W, 42);
  const std::vector<T> grid(g.begin(), g.end());
  const std::vector<T> nan_row(static_cast<std::size_t>(W * 3), std::numeric_limits<T>::quiet_NaN());
  miem::ProfileStream<T> s(W, p);
  miem::StreamRow row;
  long emitted = 0, abnormal = 0;
  const long before = g_news.load();
  for (int round = 0; round < 2; ++round) {
    for (std::ptrdiff_t r = 0; r < H; ++r) {
      // Bad profiles on the way must not allocate either.
      if (r == 50) s.push(grid.data(), W - 1, &row);  // rejected
      if (r == 60) {
        s.push(nan_row.data(), W, &row);  // a row of dropouts
        emitted += row.ready();
      }
      s.push(grid.data() + r * W * 3, W, &row);
      if (row.ready()) {
        ++emitted;
        for (std::ptrdiff_t c = 0; c < W; ++c) abnormal += row.labels[c] == miem::kAbnormal;
      }
    }
    while (s.flush(&row)) ++emitted;
    s.reset();
  }
  const long after = g_news.load();
  EXPECT_EQ(after - before, 0) << "operator new calls while streaming";
  EXPECT_EQ(emitted, 2 * (H + 1));
  EXPECT_GT(abnormal, 0);
}

TEST(StreamAlloc, NoAllocationPerProfileDouble) {
  ASSERT_GT(g_news.load(), -1);
  run_without_allocating<double>(miem::stream_default_params());  // the whole default detector
}

TEST(StreamAlloc, NoAllocationOnTwoThreads) {  // a push split among threads (W >= 256)
  miem::DetectParams p = miem::stream_default_params();
  p.num_threads = 2;
  run_without_allocating<double>(p, 300);
}

TEST(StreamAlloc, NoAllocationDefaultFloatAbnormalHeights) {
  miem::DetectParams p = miem::stream_default_params();
  p.height_mode = miem::HeightMode::kAbnormal;
  run_without_allocating<float>(p);
}

TEST(StreamAlloc, NoAllocationPerProfileFloatScales) {
  miem::DetectParams p = miem::paper_params();
  p.scales = {1, 2};
  p.max_gap = 2;
  run_without_allocating<float>(p);
}

TEST(StreamAlloc, NoAllocationWithMinStep) {
  miem::DetectParams p = miem::paper_params();
  p.min_step = 0.2;
  p.max_reach = 4;
  run_without_allocating<double>(p);
}

TEST(StreamAlloc, TheCounterWorks) {
  const long before = g_news.load();
  auto* v = new std::vector<int>(100);
  delete v;
  EXPECT_GE(g_news.load() - before, 2);
}

}  // namespace
