"""The angle passes with ``min_step`` against the reference on profiler-like grids.

The core searches for the first neighbour at least ``s * min_step`` away in its vectorised row
kernel (to a depth of 16 steps, deeper searches and distances within 1e-12 of the bound go to
the scalar judge), and its later passes re-judge only cells whose verdict read a removed cell.
These grids make both matter: 0.05 along a profile and uneven profile spacing (so searches run
from 1 to beyond 16 steps), quantised z (ties at the bound), dropout runs (gaps), clusters of
spikes (many passes). Labels, flags and iterations must equal the reference's exactly.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

import miem
from miem import reference as ref

sys.path.insert(0, str(Path(__file__).resolve().parent))
from stream_batch import stream_labels  # noqa: E402


def profiler_grid(seed: int, h: int = 36, w: int = 70) -> np.ndarray:
    rng = np.random.default_rng(seed)
    dy = rng.choice([0.1, 0.2, 1.0], h - 1)
    y = np.concatenate([[0.0], np.cumsum(dy)])[:, None] * np.ones((1, w))
    x = np.arange(w)[None, :] * 0.05 * np.ones((h, 1))
    z = 0.1 * y + 0.2 * np.sin(3.0 * x) + rng.normal(0.0, 0.01, (h, w))
    z = np.round(z * 100.0) / 100.0  # quantised: distances tie exactly with s * min_step = 0.05 k
    grid = np.dstack([x, y, z])
    flat = grid.reshape(-1, 3)
    idx = rng.choice(h * w, size=h * w // 12, replace=False)
    flat[idx, 2] += rng.choice([-1.0, 1.0], idx.size) * rng.uniform(0.05, 1.0, idx.size)
    r, c = rng.integers(2, h - 6), rng.integers(5, w - 12)
    grid[r:r + 4, c:c + 8, 2] += 0.5  # a cluster: removed over several passes
    flat[rng.random(h * w) < 0.08] = np.nan
    grid[rng.integers(0, h), 20:26] = np.nan  # a run of dropouts along a profile
    return grid


CASES = [
    # searches 1-8 steps along a profile
    {"scales": (1, 2), "min_step": 0.2, "max_gap": 1},
    # s * min_step = 0.05 k: candidates exactly at the bound (the spec's square root decides)
    {"scales": (1, 2), "min_step": 0.1, "max_gap": 1},
    # beyond the kernel's 16 steps along a profile, and max_reach cutting searches short
    {"scales": (1, 3), "min_step": 1.1, "max_gap": 2, "max_reach": 32},
    {"scales": (2,), "min_step": 0.45, "max_gap": 0, "max_reach": 3},
    {"scales": (2, 3), "min_step": 0.3, "max_gap": 3, "max_reach": 20, "min_directions": 2},
    {"scales": (1,), "min_step": 0.0, "max_gap": 1},
]


def assert_angle_passes_match_reference(grid: np.ndarray, kw: dict,
                                        later_passes: bool = False) -> None:
    """Core (1 and 2 threads) == reference on `grid` in float64 and float32: labels, flags,
    iterations, angles; with `later_passes`, the reference must run at least 2 passes."""
    for dtype in (np.float64, np.float32):
        g = grid.astype(dtype)
        oracle = ref.detect(g, **kw)
        if later_passes:
            assert oracle.iterations >= 2  # later passes run
        for nt in (1, 2):
            core = miem.detect(g, num_threads=nt, **kw)
            np.testing.assert_array_equal(core.labels, oracle.labels)
            np.testing.assert_array_equal(core.flags, oracle.flags)
            assert core.iterations == oracle.iterations
            np.testing.assert_allclose(core.angle, oracle.angle, rtol=0, atol=1e-9,
                                       equal_nan=True)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("case", CASES, ids=lambda c: ",".join(f"{k}={v}" for k, v in c.items()))
def test_min_step_angle_passes_match_reference(seed: int, case: dict) -> None:
    grid = profiler_grid(seed)
    kw = {"preset": "paper", "theta0": 100.0, "max_iterations": 12, **case}
    assert_angle_passes_match_reference(grid, kw, later_passes=True)


def test_min_step_auto_on_a_profiler_grid_matches_reference() -> None:
    """The default preset (min_step 'auto' resolves to a length here) against the reference."""
    grid = profiler_grid(3, h=48, w=90)
    grid[..., 2] = np.round(grid[..., 2] * 1000.0) / 1000.0
    oracle = ref.detect(grid)
    assert oracle.params["min_step"] is not None
    for nt in (1, 2):
        core = miem.detect(grid, num_threads=nt)
        assert core.params["min_step"] == oracle.params["min_step"]
        np.testing.assert_array_equal(core.labels, oracle.labels)
        np.testing.assert_array_equal(core.flags, oracle.flags)
        np.testing.assert_allclose(core.height, oracle.height, rtol=0, atol=1e-7, equal_nan=True)


def smooth_profiler_grid(seed: int, h: int = 30, w: int = 150) -> np.ndarray:
    """Smooth profiles (0.05 apart, 1e-4 noise): along a profile the first steps of a min_step
    search lie surely near, so the core skips them (the path-length bound of row_speeds). Lone
    dropouts and pairs of them fall inside the skipped steps (gaps still counted; a pair ends a
    max_gap 1 search), spikes make the bound loose in their stretch, and flat rows put
    candidates exactly at s * min_step (0.05 k) right after the skipped steps."""
    rng = np.random.default_rng(seed)
    dy = rng.choice([0.1, 0.2, 1.0], h - 1)
    y = np.concatenate([[0.0], np.cumsum(dy)])[:, None] * np.ones((1, w))
    x = np.arange(w)[None, :] * 0.05 * np.ones((h, 1))
    z = 0.1 * y + 0.3 * np.exp(-((x - 3.0) ** 2) / 2.0) + rng.normal(0.0, 1e-4, (h, w))
    z[::5] = 0.1 * y[::5]  # flat rows: exact ties at the bound
    grid = np.dstack([x, y, z])
    flat = grid.reshape(-1, 3)
    idx = rng.choice(h * w, size=12, replace=False)
    flat[idx, 2] += rng.choice([-1.0, 1.0], idx.size) * rng.uniform(0.3, 1.0, idx.size)
    flat[rng.choice(h * w, size=h * w // 40, replace=False)] = np.nan  # lone dropouts
    for r in rng.integers(0, h, 6):  # pairs of dropouts along a profile
        c = rng.integers(0, w - 2)
        grid[r, c:c + 2] = np.nan
    return grid


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("case", [
    {"scales": (1, 2), "min_step": 0.2, "max_gap": 1},
    {"scales": (1, 2), "min_step": 0.15, "max_gap": 1},   # ties at 3 and 6 steps
    {"scales": (1, 3), "min_step": 0.33, "max_gap": 2},
    {"scales": (2,), "min_step": 0.2, "max_gap": 0, "max_reach": 4},
], ids=lambda c: ",".join(f"{k}={v}" for k, v in c.items()))
def test_min_step_skipped_steps_match_reference(seed: int, case: dict) -> None:
    grid = smooth_profiler_grid(seed)
    kw = {"preset": "paper", "theta0": 100.0, "max_iterations": 12, **case}
    assert_angle_passes_match_reference(grid, kw)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("case", [
    {"scales": (1, 2), "min_step": 0.2, "max_gap": 1},
    {"scales": (1, 2), "min_step": 0.15, "max_gap": 1},   # ties at 3 and 6 steps
    {"scales": (1, 3), "min_step": 0.33, "max_gap": 2, "min_directions": 2},
], ids=lambda c: ",".join(f"{k}={v}" for k, v in c.items()))
def test_stream_min_step_skipped_steps_match_reference(seed: int, case: dict) -> None:
    """The stream's pass 1 with min_step (theta0 < 90: each verdict computed directly) skips the
    same surely near steps along a profile; its labels equal the reference's."""
    grid = smooth_profiler_grid(seed)
    kw = {"theta0": 80.0, "max_iterations": 12, **case}
    params = miem.PRESETS["paper"].replace(**kw)
    oracle = ref.detect(grid, preset="paper", **kw)
    assert (oracle.labels == miem.ABNORMAL).sum() > 0
    np.testing.assert_array_equal(stream_labels(grid, params), oracle.labels)
