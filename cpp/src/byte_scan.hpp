// Searches of a row of byte flags for the few cells a stage acts on (most rows have none or a
// handful): the vectorised library search for one value, and a scan of 8 bytes a word for any
// non-zero byte. Internal to the core.
#pragma once

#include <cstdint>
#include <cstring>

namespace miem::detail {

/// The first c in [c, n) with p[c] == v, else n (memchr: a vectorised search).
inline std::ptrdiff_t next_byte(const std::uint8_t* p, std::ptrdiff_t c, std::ptrdiff_t n,
                                std::uint8_t v) {
  if (c >= n) return n;
  const void* q = std::memchr(p + c, v, static_cast<std::size_t>(n - c));
  return q == nullptr ? n : static_cast<const std::uint8_t*>(q) - p;
}

/// The first c in [c, n) with p[c] != 0, else n: 8 bytes at a time over zeros.
inline std::ptrdiff_t next_nonzero(const std::uint8_t* p, std::ptrdiff_t c, std::ptrdiff_t n) {
  for (std::uint64_t w; c + 8 <= n; c += 8) {
    std::memcpy(&w, p + c, 8);
    if (w != 0) break;
  }
  while (c < n && p[c] == 0) ++c;
  return c;
}

}  // namespace miem::detail
