// Memory of the detector's per-cell buffers (cpp/src/cell_memory.cpp, CellAllocator in
// miem/organized.hpp).
#include <gtest/gtest.h>

#include <cstdint>
#include <vector>

#include "miem/organized.hpp"

namespace {

constexpr std::uintptr_t kHugePage = std::uintptr_t{1} << 21;

TEST(CellMemory, LargeBlocksAreHugePageAligned) {
  for (std::size_t bytes : {kHugePage, kHugePage + 1, 5 * kHugePage + 4096}) {
    void* p = miem::detail::allocate_cells(bytes);
    EXPECT_EQ(reinterpret_cast<std::uintptr_t>(p) % kHugePage, 0u) << bytes;
    static_cast<unsigned char*>(p)[bytes - 1] = 7;  // the whole block is ours
    miem::detail::free_cells(p, bytes);
  }
  void* small = miem::detail::allocate_cells(100);
  EXPECT_NE(small, nullptr);
  miem::detail::free_cells(small, 100);
}

TEST(CellMemory, CellBytesKeepTheirValuesWhenTheyGrow) {
  miem::detail::CellBytes v;
  v.resize(1000);
  for (std::size_t i = 0; i < v.size(); ++i) v[i] = static_cast<std::uint8_t>(i * 7);
  v.resize(3 * kHugePage);  // into an aligned block: the first 1000 bytes move with the buffer
  EXPECT_EQ(reinterpret_cast<std::uintptr_t>(v.data()) % kHugePage, 0u);
  for (std::size_t i = 0; i < 1000; ++i) ASSERT_EQ(v[i], static_cast<std::uint8_t>(i * 7)) << i;
}

}  // namespace
