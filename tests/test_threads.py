"""The default detector gives the same bits for any thread count (README "Guarantees").

The scene is large enough that every stage runs in parallel (>= 65536 cells, later angle passes
with hundreds of candidates, several height and edge passes), with what splits work unevenly:
dropouts (single cells, a band, a hole), a step edge with a burr on its top, a crease, a sharp
ridge, and many spikes and pits in one half only.
"""

import numpy as np
import pytest

import miem


def busy_scene(seed: int = 3, shape=(330, 372)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = xx * 0.2, yy * 0.3
    z = 0.02 * x - 0.01 * y + 0.2 * np.exp(-((x - 20.0) ** 2 + (y - 40.0) ** 2) / 200.0)
    z = z + np.where(xx >= 250, 1.5, 0.0)  # a step edge (a wall) across the profiles
    z = z + np.where(xx > 120, (xx - 120) * 0.2 * np.tan(np.radians(25)), 0.0)  # a crease
    z = z + np.maximum(0.0, 0.6 - 0.3 * np.abs(xx - 80))  # a sharp ridge: a feature line (EDGE)
    z[100:140, 248:250] += 0.25  # a burr standing on the step's top edge
    z = z + rng.normal(0.0, 0.002, z.shape)
    grid = np.dstack([x, y, z])
    flat = grid.reshape(-1, 3)
    top = np.flatnonzero((yy < h // 2).ravel())  # defects in the upper half only: uneven work
    idx = rng.choice(top, size=700, replace=False)
    flat[idx, 2] += rng.choice([-1.0, 1.0], idx.size) * rng.uniform(0.05, 2.0, idx.size)
    flat[rng.random(h * w) < 0.03] = np.nan
    grid[200:204, :] = np.nan  # a dropout band
    grid[40:52, 300:320] = np.nan  # a hole
    return grid


def _same(a: miem.DetectResult, b: miem.DetectResult, what: str) -> None:
    for name in ("labels", "flags", "angle", "height"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.tobytes() == y.tobytes(), f"{what}: {name} differ"
    assert a.iterations == b.iterations, what
    assert a.params["min_step"] == b.params["min_step"], what
    assert a.plane is not None and b.plane is not None
    assert a.plane.normal.tolist() == b.plane.normal.tolist() and a.plane.d == b.plane.d, what
    assert [(d.indices.tolist(), d.peak_height, d.kind) for d in a.defects] == \
        [(d.indices.tolist(), d.peak_height, d.kind) for d in b.defects], what


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_default_preset_same_bits_for_1_2_3_threads(dtype) -> None:
    grid = busy_scene().astype(dtype)
    one = miem.detect(grid, num_threads=1)
    # the scene exercises what the thread schedule splits: every label, several passes
    labels = one.labels
    assert (labels == miem.ABNORMAL).sum() > 500
    assert (labels == miem.EDGE).sum() > 200
    assert (labels == miem.INVALID).sum() > 3000
    assert one.iterations > 3
    for nt in (2, 3):
        _same(one, miem.detect(grid, num_threads=nt), f"{dtype.__name__}, {nt} threads")
