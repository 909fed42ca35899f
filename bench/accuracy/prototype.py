"""A prototype of a proposed height-test rule, measured on the same suite (not part of miem).

The core's height test (docs/SPEC.md, "height_tolerance") tests NORMAL cells only and abstains
at every cell with an EDGE cell anywhere in its window. On the suite that leaves most of the
defects the angle test labels EDGE (spatter domes, burr ridges, low spikes and pits, the flat
tops of 3x3 clusters) undetected, and one EDGE cell from noise or from a defect's halo silences
the test for a whole window around it.

Proposed rule (parameter ``edge_extent`` E, in cells): group the EDGE cells into 8-connected
components; a component whose bounding box is at most E cells on its longer side is *compact*
(a defect's halo, a short burr ridge, a spatter dome), a longer one is a *feature line* (crease,
flange, fillet, edge strip). A height pass then tests every NORMAL cell and every compact-EDGE
cell, and abstains only where a feature-line cell lies in the window. Everything else is as in
SPEC (window plane of the NORMAL cells, ``|h| > k rms``, Jacobi passes until none is added).

This module emulates that rule in NumPy on top of ``miem.detect``'s angle passes, so the lead
can see what it would give before changing the core:

    python bench/accuracy/prototype.py      # tune on the tuning split, print the test scores
"""

from __future__ import annotations

import itertools
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))

import miem
from score import Counts, confusion
from suite import Scene, scenes

__all__ = ["GRID", "detect_proposed", "test_prototype", "tune_prototype", "window_planes"]


def window_planes(
    points: np.ndarray, mask: np.ndarray, window: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eigenvalue plane of the `mask` cells in each ``window x window`` square (border-clipped).

    Returns
    -------
    height : ndarray (H, W)
        Signed distance of each cell from its window's plane.
    rms : ndarray (H, W)
        ``sqrt(l0 / n)`` of that plane.
    ok : ndarray (H, W), bool
        The plane exists (at least 3 cells, not collinear).
    """
    h, w, _ = points.shape
    half = window // 2
    centre = np.nanmean(points[mask], axis=0)
    p = np.where(mask[..., None], points - centre, 0.0)
    terms = [mask.astype(np.float64)] + [p[..., a] for a in range(3)]
    terms += [p[..., a] * p[..., b] for a in range(3) for b in range(a, 3)]
    pad = np.pad(np.stack(terms, -1), ((half + 1, half), (half + 1, half), (0, 0)))
    cs = pad.cumsum(0).cumsum(1)
    win = cs[window:, window:] - cs[:-window, window:] - cs[window:, :-window]
    win = win + cs[:-window, :-window]
    n = win[..., 0]
    nn = np.maximum(n, 1.0)
    mean = win[..., 1:4] / nn[..., None]
    cov = np.empty((h, w, 3, 3))
    i = 4
    for a in range(3):
        for b in range(a, 3):
            cov[..., a, b] = cov[..., b, a] = win[..., i] / nn - mean[..., a] * mean[..., b]
            i += 1
    lam, vec = np.linalg.eigh(cov)
    pc = np.where(np.isfinite(points), points - centre, 0.0)
    height = np.einsum("hwi,hwi->hw", pc - mean, vec[..., :, 0])
    rms = np.sqrt(np.maximum(lam[..., 0], 0.0))
    ok = (n >= 3) & (lam[..., 1] > 1e-12 * lam[..., 2])
    return height, rms, ok


def detect_proposed(
    grid: np.ndarray,
    k: float = 4.0,
    edge_extent: int = 12,
    window: int = 21,
    max_iterations: int = 10,
    **angle: Any,
) -> np.ndarray:
    """ABNORMAL mask with the proposed height test after miem's angle passes.

    Parameters
    ----------
    grid : ndarray (H, W, 3)
        Organized scan.
    k : float
        Height tolerance in local rms (``"<k>rms"``).
    edge_extent : int
        Longest side (cells) of a compact EDGE component.
    window, max_iterations : int
        As for ``miem.detect``.
    **angle
        Angle-test arguments of ``miem.detect`` (``theta0``, ``scales``, ...).

    Returns
    -------
    ndarray (H, W), bool
    """
    lab = miem.detect(grid, window=window, max_iterations=max_iterations, heights="abnormal",
                      height_tolerance=None, edge_tolerance=None, **angle).labels.copy()
    box = np.ones((3, 3), dtype=bool)
    for _ in range(max_iterations):
        normal, edge = lab == miem.NORMAL, lab == miem.EDGE
        comp, n = ndimage.label(edge, structure=box)
        compact = np.zeros(n + 1, dtype=bool)
        for i, sl in enumerate(ndimage.find_objects(comp), start=1):
            compact[i] = max(sl[0].stop - sl[0].start, sl[1].stop - sl[1].start) <= edge_extent
        compact_cells = compact[comp] & edge
        line = edge & ~compact_cells
        near_line = ndimage.maximum_filter(line, size=window, mode="constant", cval=False)
        height, rms, ok = window_planes(grid, normal, window)
        new = (normal | compact_cells) & ~near_line & ok & (np.abs(height) > k * rms)
        if not new.any():
            break
        lab[new] = miem.ABNORMAL
    return lab == miem.ABNORMAL


#: Tuning grid of the prototype (the angle test is miem's; scales (1, 2) as miem's winner).
GRID = [
    {"k": k, "edge_extent": e, "window": w, "theta0": t, "scales": (1, 2)}
    for k, e, w, t in itertools.product((4.0, 4.5), (8, 12, 20), (15, 21), (80.0, 90.0))
]


def tune_prototype(tune: Sequence[Scene]) -> tuple[dict, Counts, bool]:
    """Best setting of :data:`GRID` on the tuning scenes (the benchmark's selection rule)."""
    scored = []
    for i, p in enumerate(GRID):
        tot = Counts.total(confusion(detect_proposed(s.points, **p), s.truth) for s in tune)
        ok = (tot.n_edge == 0 or tot.edge_fa <= 0.001) and tot.normal_fa <= 0.0001
        scored.append((ok, round(tot.f1, 9), -tot.fp, -i, p, tot))
    ok, _, _, _, best, tot = max(scored, key=lambda x: x[:4])
    return best, tot, ok


def test_prototype(test: Sequence[Scene], params: dict) -> dict[str, Counts]:
    """Counts per test scene with the given setting (wall time included)."""
    out = {}
    for s in test:
        t0 = time.perf_counter()
        mask = detect_proposed(s.points, **params)
        out[s.name] = confusion(mask, s.truth, time.perf_counter() - t0)
    return out


def main() -> int:
    """Tune the prototype on the tuning split, print its test-split scores per group."""
    t0 = time.perf_counter()
    best, tot, ok = tune_prototype(list(scenes("tune")))
    print(f"tuning: {len(GRID)} settings, best {best}: F1 {tot.f1:.4f} edge FA "
          f"{100 * tot.edge_fa:.3f} % normal FA {100 * tot.normal_fa:.4f} % (targets met: {ok})")
    test = list(scenes("test"))
    per = test_prototype(test, best)
    groups: dict[str, Counts] = {}
    for s in test:
        groups[s.spec.group] = groups.get(s.spec.group, Counts()) + per[s.name]
    for g, c in groups.items():
        print(f"  test {g:14s} F1 {c.f1:.3f}  P {c.precision:.3f}  R {c.recall:.3f}")
    tot = Counts.total(groups.values())
    print(f"test all: F1 {tot.f1:.4f} P {tot.precision:.4f} R {tot.recall:.4f} edge FA "
          f"{100 * tot.edge_fa:.3f} % normal FA {100 * tot.normal_fa:.4f} %  "
          f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
