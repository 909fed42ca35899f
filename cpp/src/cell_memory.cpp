// Memory of the per-cell work buffers (Workspace's CellBytes, miem/organized.hpp): blocks of at
// least one huge page are aligned to it and advised as huge-page candidates, so that a new
// detector touching tens of MB for the first time takes a page fault per 2 MiB instead of per
// 4 KiB (on this kind of machine a 4 KiB fault costs ~3 us: 5,000 of them per call on a 2048^2
// grid). Where the kernel does not do transparent huge pages the advice changes nothing.
#include <cstddef>
#include <new>

#include "miem/organized.hpp"

#if defined(__linux__)
#include <sys/mman.h>
#endif

namespace miem::detail {

namespace {
constexpr std::size_t kHugePage = std::size_t{1} << 21;
}  // namespace

void* allocate_cells(std::size_t bytes) {
  if (bytes < kHugePage) return ::operator new(bytes);
  void* p = ::operator new(bytes, std::align_val_t{kHugePage});
#if defined(__linux__) && defined(MADV_HUGEPAGE)
  (void)madvise(p, bytes, MADV_HUGEPAGE);  // advice only: a refusal leaves 4 KiB pages
#endif
  return p;
}

void free_cells(void* p, std::size_t bytes) noexcept {
  if (bytes < kHugePage) {
    ::operator delete(p);
  } else {
    ::operator delete(p, std::align_val_t{kHugePage});
  }
}

}  // namespace miem::detail
