// Pass 1's row kernel (docs/SPEC.md "Detection"), shared by batch detection (angle_passes.cpp)
// and ProfileStream (with min_step): the verdicts of a whole row from structure-of-arrays copies
// of the rows around it, vectorised; the cells it cannot settle go to the scalar judge.
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include "miem/organized.hpp"
#include "miem/params.hpp"

namespace miem::detail {

/// The rows the kernel reads: a ring of 2 depth + 1 converted rows in a RowScratch (slot
/// rr % (2 depth + 1) for row rr), and one all-unusable row (slot 2 depth + 1) that stands for
/// the rows outside [0, H). Each row has `depth` padding columns of unusable cells on each side,
/// so that the grid's border needs no special case. A row is loaded once (pass1_load) before the rows within `depth` of it are judged.
struct Pass1Ring {
  RowScratch* sc = nullptr;
  std::ptrdiff_t H = 0, W = 0, depth = 0;

  std::ptrdiff_t stride() const { return W + 2 * depth; }  // a padded row
  std::ptrdiff_t slot(std::ptrdiff_t rr) const {
    return (rr < 0 || rr >= H) ? 2 * depth + 1 : rr % (2 * depth + 1);
  }
  /// Row rr's x (then y, z, stride() apart), column 0 at index 0.
  double* x(std::ptrdiff_t rr) const { return sc->xyz.data() + slot(rr) * 3 * stride() + depth; }
  /// Row rr's usable lanes (1 or 0).
  std::int64_t* ok(std::ptrdiff_t rr) const { return sc->ok.data() + slot(rr) * stride() + depth; }
  /// Words of a row's packed usable bits: the padded row and one spare word (a 64-bit window
  /// read at any padded column stays inside).
  std::ptrdiff_t bit_words() const { return stride() / 64 + 2; }
  /// Row rr's usable lanes packed: bit k % 64 of word k / 64 for padded column k (column
  /// c - depth), written by pass1_load from ok(rr).
  std::uint64_t* okbits(std::ptrdiff_t rr) const {
    return sc->okbits.data() + slot(rr) * bit_words();
  }
};

/// Sizes `sc` for a ring of W columns and `depth` (min_step: the search's per-row buffers too)
/// and clears it (every cell unusable). Allocates only when it has held less.
void pass1_prepare(RowScratch& sc, std::ptrdiff_t W, std::ptrdiff_t depth, bool min_step);

/// Loads row rr into the ring from coordinate planes (column c at x[c * cs], y[c * cs],
/// z[c * cs]) and its usable bytes (`usable[c]` nonzero: usable): unusable cells read as 0
/// (finite), so no NaN enters the kernel's selects; and packs them (okbits). The
/// layouts of a dense grid (x, y, z interleaved: cs 3) and of the stream's ring (planes: cs 1)
/// run in vector code.
void pass1_load(const Pass1Ring& ring, std::ptrdiff_t rr, const double* x, const double* y,
                const double* z, std::ptrdiff_t cs, const std::uint8_t* usable);
void pass1_load(const Pass1Ring& ring, std::ptrdiff_t rr, const float* x, const float* y,
                const float* z, std::ptrdiff_t cs, const std::uint8_t* usable);

/// Pass 1 on row r (rows r - depth .. r + depth loaded): each usable cell's label (and flags
/// and smallest angle, where given) from the kernel, with min_step (p.min_step >= 0) the rays
/// each verdict read in `reach` (4 bytes per cell: the row's). The cells the kernel cannot
/// settle (pass1_needs_judge) get a label too, which the caller's scalar judge replaces.
/// `num_threads`: the row's blocks of columns split among that many threads (the stream's
/// push; batch runs rows in parallel and each row on one thread). Results do not depend on it.
void pass1_row(const Pass1Ring& ring, std::ptrdiff_t r, const DetectParams& p,
               std::uint8_t* labels, std::uint8_t* flags, double* angle, std::uint8_t* reach,
               int num_threads = 1);

/// Bits of RowScratch::bits per cell: directions available (0-3) and flagged (4-7), a search
/// the kernel cannot finish (slow), a usable cell within the isolation reach (near).
constexpr std::int64_t kPass1FlagShift = 4, kPass1SlowBit = 1 << 8, kPass1NearBit = 1 << 9;

/// Whether the scalar judge decides a cell from its kernel bits `b` and its usable lane `ok`: a
/// usable cell whose search the kernel could not finish, or with no usable cell within the
/// isolation reach. Branch-free (pass1_judge_cells' vectorised test uses it).
inline bool pass1_judge_bits(std::int64_t b, std::int64_t ok) {
  return (ok != 0) & (((b & kPass1SlowBit) != 0) | ((b & kPass1NearBit) == 0));
}

/// pass1_judge_bits of cell c of the row pass1_row judged last (`ok`: that row's ring.ok(r)).
inline bool pass1_needs_judge(const RowScratch& sc, const std::int64_t* ok, std::ptrdiff_t c) {
  return pass1_judge_bits(sc.bits[static_cast<std::size_t>(c)], ok[c]);
}

/// Appends `base + c` to `out` for each of the row's W cells that pass1_needs_judge selects (a
/// vectorised test skips the 64-cell chunks that hold none).
void pass1_judge_cells(const RowScratch& sc, const std::int64_t* ok, std::ptrdiff_t W,
                       std::int64_t base, std::vector<std::int64_t>& out);

}  // namespace miem::detail
