"""Exact order statistics over a Dask-held scan without gathering it: radix selection on the
bit patterns of non-negative float64 values (they order like the values), 16 bits per round,
histograms summed in a tree on the workers. Used by miem.dask for the whole-scan medians of
min_step="auto"."""

from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np
from dask import delayed

_BINS = 1 << 16


def _hists(values: Sequence[np.ndarray], picks: Sequence[tuple], shift: int) -> np.ndarray:
    """For each pick (quantity q, prefix): the counts of the next 16 bits below `shift` among
    quantity q's patterns whose bits above `shift` equal the prefix."""
    out = np.zeros((len(picks), _BINS), np.int64)
    for s, (q, prefix) in enumerate(picks):
        bits = values[q]
        if shift < 64:
            bits = bits[(bits >> np.uint64(shift)) == np.uint64(prefix)]
        out[s] = np.bincount(((bits >> np.uint64(shift - 16)) & np.uint64(0xFFFF))
                             .astype(np.int64), minlength=_BINS)
    return out


def _block_hists(survey: Callable, args: tuple, picks: list, shift: int) -> np.ndarray:
    return _hists(survey(*args), picks, shift)


def _tree_sum(parts: list) -> Any:
    while len(parts) > 1:
        parts = [delayed(np.add)(parts[i], parts[i + 1]) if i + 1 < len(parts) else parts[i]
                 for i in range(0, len(parts), 2)]
    return parts[0]


def medians(survey: Callable, blocks: list, n_quantities: int, **compute_kwargs: Any) -> list:
    """The NumPy median (middle value, or the mean of the two middle values) of each of
    `n_quantities` non-negative quantities over all blocks; None for a quantity with no value.

    ``survey(*args)`` for each ``args`` in `blocks` returns the quantities' values of that
    block as uint64 bit patterns of non-negative float64; it is recomputed in every round
    (4 rounds: nothing is held in memory between them)."""
    import dask

    # round 1 finds the counts too; each quantity then selects its two middle ranks
    first = dask.compute(_tree_sum([delayed(_block_hists)(survey, a, [(q, 0) for q in
                                                                       range(n_quantities)], 64)
                                    for a in blocks]), **compute_kwargs)[0]
    counts = first.sum(axis=1)
    picks, ranks = [], []
    for q in range(n_quantities):
        m = int(counts[q])
        if m:
            for k in sorted({(m - 1) // 2, m // 2}):
                picks.append([q, 0])
                ranks.append(k)
    state = []  # per pick: (quantity, prefix, remaining rank)
    for s, (q, _) in enumerate(picks):
        cum = np.cumsum(first[q])
        k = ranks[s]
        digit = int(np.searchsorted(cum, k, side="right"))
        state.append([q, digit, k - (int(cum[digit - 1]) if digit else 0)])
    for shift in (48, 32, 16):
        if not state:
            break
        h = dask.compute(_tree_sum([delayed(_block_hists)(survey, a, [(q, p) for q, p, _ in
                                                                     state], shift)
                                    for a in blocks]), **compute_kwargs)[0]
        for s, st in enumerate(state):
            cum = np.cumsum(h[s])
            digit = int(np.searchsorted(cum, st[2], side="right"))
            st[2] -= int(cum[digit - 1]) if digit else 0
            st[1] = (st[1] << 16) | digit
    value = {}
    for s, (q, prefix, _) in enumerate(state):
        value.setdefault(q, []).append(
            float(np.array([prefix], dtype=np.uint64).view(np.float64)[0]))
    out = []
    for q in range(n_quantities):
        v = value.get(q)
        if v is None:
            out.append(None)
        elif len(v) == 1:
            out.append(v[0])
        else:
            out.append((v[0] + v[1]) / 2.0)  # lower middle + upper middle, as np.median
    return out


def min_step_survey(ext: np.ndarray, home: tuple) -> list:
    """The four quantities of min_step="auto" (docs/SPEC.md) for the pairs and triples that
    start at the home cells ``ext[:home[0], :home[1]]`` of a block read with up to two more rows
    and columns: distances of finite neighbour pairs along a profile (columns) and across
    (rows), and |z[i-1] - 2 z[i] + z[i+1]| of finite triples along and across; bit patterns."""
    ext = np.asarray(ext)
    g = ext.astype(np.float64)
    fin = np.isfinite(ext).all(axis=-1)
    h, w = home
    out = []
    for dr, dc in ((0, 1), (1, 0)):
        H1, W1 = min(h, g.shape[0] - dr), min(w, g.shape[1] - dc)
        a, b = (slice(0, H1), slice(0, W1)), (slice(dr, dr + H1), slice(dc, dc + W1))
        ok = fin[a] & fin[b]
        d = g[b][ok] - g[a][ok]
        dist = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])
        H2, W2 = min(h, g.shape[0] - 2 * dr), min(w, g.shape[1] - 2 * dc)
        a = (slice(0, H2), slice(0, W2))
        b = (slice(dr, dr + H2), slice(dc, dc + W2))
        c = (slice(2 * dr, 2 * dr + H2), slice(2 * dc, 2 * dc + W2))
        ok = fin[a] & fin[b] & fin[c]
        z0, z1, z2 = g[a][..., 2][ok], g[b][..., 2][ok], g[c][..., 2][ok]
        noise = np.abs(z0 - 2.0 * z1 + z2)
        out += [np.ascontiguousarray(dist).view(np.uint64),
                np.ascontiguousarray(noise).view(np.uint64)]
    return out


def _spacing_noise(med: list) -> "tuple[float | None, float | None]":
    """min(spacing) and max(sigma) of the medians (distance, noise) along and across; an axis
    without pairs or triples counts not."""
    spacing = noise = None
    for dist, nz in ((med[0], med[1]), (med[2], med[3])):
        if dist is None or nz is None:
            continue
        sigma = 1.4826 * nz / np.sqrt(6.0)
        spacing = dist if spacing is None else min(spacing, dist)
        noise = sigma if noise is None else max(noise, sigma)
    return spacing, noise


def min_step_from_medians(med: list) -> "float | None":
    """min_step="auto" from the medians: ``4 max(sigma)`` when that exceeds ``min(spacing)``,
    else None."""
    spacing, noise = _spacing_noise(med)
    if noise is None:
        return None
    m = 4.0 * noise
    return float(m) if m > spacing else None


def noise_from_medians(med: list) -> "float | None":
    """z_noise="auto" from the medians: ``max(sigma)`` (None without an axis)."""
    return None if (v := _spacing_noise(med)[1]) is None else float(v)
