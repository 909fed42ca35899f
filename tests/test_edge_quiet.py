"""Quiet cells of the edge test (SPEC "Edge test" step 1): the reference's rule against a direct
fit of each cell's window, and the core against the reference where the rule decides."""

from __future__ import annotations

import numpy as np

import miem
from miem import reference as ref

R = 3  # a 7 x 7 window: small scenes reach its interior
FLOOR = 0.01


def _scene() -> tuple[np.ndarray, np.ndarray]:
    """A noisy sheet (0.1 mm cells, 2 um noise) with a bend, a low bump, a dropout patch, one
    EDGE and one ABNORMAL cell; the labels set by hand (NORMAL elsewhere)."""
    h, w = 40, 60
    rng = np.random.default_rng(5)
    x, y = np.meshgrid(np.arange(w) * 0.1, np.arange(h) * 0.1)
    z = 0.02 * x + rng.normal(0.0, 0.002, (h, w))
    z += np.where(x > 4.0, 0.5 * (x - 4.0) ** 2, 0.0)  # a bend from column 40 on
    z[20, 10] += 0.012  # a low bump: 6 sigma of the noise
    g = np.stack([x, y, z], axis=-1)
    labels = np.zeros((h, w), dtype=np.uint8)
    g[8:14, 25:31] = np.nan  # 36 dropouts: >= n_min (4 at r = 3) in the windows around it
    labels[8:14, 25:31] = miem.INVALID
    labels[30, 20] = miem.EDGE
    labels[30, 32] = miem.ABNORMAL
    return g, labels


def _direct(g: np.ndarray, labels: np.ndarray, r: int, floor: float) -> tuple:
    """Each NORMAL or EDGE cell: quiet per SPEC step 1 by a plane fitted to its window's cells
    one at a time (np.linalg.eigh of the centred scatter); and how close it is to a threshold."""
    h, w = labels.shape
    n_min = max(3, r * r // 2)
    quiet = np.zeros((h, w), dtype=bool)
    margin = np.full((h, w), np.inf)
    for a in range(h):
        for b in range(w):
            if labels[a, b] not in (miem.NORMAL, miem.EDGE):
                continue
            if a < r or b < r or a + r >= h or b + r >= w:
                continue
            win = labels[a - r:a + r + 1, b - r:b + r + 1]
            if np.any((win == miem.EDGE) | (win == miem.ABNORMAL)):
                continue
            if (win == miem.INVALID).sum() >= n_min:
                continue
            sel = win == miem.NORMAL
            sel[r, r] = False
            q = g[a - r:a + r + 1, b - r:b + r + 1][sel]
            m = q.mean(axis=0)
            ev, vec = np.linalg.eigh((q - m).T @ (q - m))
            rms = np.sqrt(ev[0] / len(q)) if ev[0] > 1e-12 * ev[2] else 0.0
            dist = abs((g[a, b] - m) @ vec[:, 0])
            quiet[a, b] = dist <= 3.0 * rms and rms <= 0.75 * floor
            margin[a, b] = min(abs(dist - 3.0 * rms), abs(rms - 0.75 * floor))
    return quiet, margin


def test_quiet_cells_are_a_direct_window_fit() -> None:
    g, labels = _scene()
    cells = (labels == miem.NORMAL) | (labels == miem.EDGE)
    fin = np.isfinite(g).all(axis=-1)
    origin = g[np.unravel_index(np.argmax(fin), fin.shape)]
    judged = np.zeros_like(cells)
    judged[cells] = ref._edge_candidates(g, labels, cells, R, origin, FLOOR)
    quiet, margin = _direct(g, labels, R, FLOOR)
    sure = margin > 1e-9
    np.testing.assert_array_equal(judged[cells & sure], ~quiet[cells & sure])
    assert (cells & ~sure).sum() < 5
    # by geometry: the flat sheet's interior is mostly quiet; the bump, the bend (its curvature
    # 1 / mm: a 0.7 mm window's plane misses it by more than the floor), the cells around the
    # EDGE, ABNORMAL and dropout cells and the border are judged
    assert quiet[5:35, 4:22].mean() > 0.9
    assert judged[20, 10]
    assert judged[10:30, 45:57].all()
    near = np.zeros_like(cells)
    near[27:34, 17:24] = near[27:34, 29:36] = near[6:16, 23:33] = True  # 4+ dropouts
    assert judged[near & cells].all()
    assert judged[:R].all() and judged[:, -R:].all()


def test_core_judges_what_the_reference_judges() -> None:
    """A low pit on a flat sheet that only step 7 finds (the height test leaves it: under a
    loose tolerance) is not quiet (off its window's plane); nor are a burr on a bend that the
    angle test leaves NORMAL (a rough window). The core and the reference agree on every label,
    and the quiet cells around change nothing."""
    h, w = 60, 70
    rng = np.random.default_rng(11)
    x, y = np.meshgrid(np.arange(w) * 0.1, np.arange(h) * 0.1)
    z = rng.normal(0.0, 0.002, (h, w))
    z[20, 20] -= 0.03  # a low pit
    bend = x > 4.0
    z += np.where(bend, 0.25 * (x - 4.0) ** 2, 0.0)
    z[40:46, 55] += 0.04  # a low burr across the bend
    g = np.stack([x, y, z], axis=-1)
    kw = {"preset": "recommended", "height_tolerance": "12rms"}
    oracle = ref.detect(g, **kw)
    assert oracle.labels[20, 20] == miem.ABNORMAL
    for nt in (1, 2):
        core = miem.detect(g, num_threads=nt, **kw)
        np.testing.assert_array_equal(core.labels, oracle.labels)
    no_edge = ref.detect(g, edge_tolerance=None, **kw)
    assert no_edge.labels[20, 20] != miem.ABNORMAL  # the edge test found it
