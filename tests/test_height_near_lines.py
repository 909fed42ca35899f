"""The rms height test runs next to feature lines (docs/SPEC.md "height_tolerance" step 3).

With an absolute tolerance the test abstains wherever a feature-line cell lies in the window (a
fixed length cannot allow for the bend the window's plane straddles); in the rms form the
straddled bend raises the rms and the tolerance with it, so the test runs there too: a spike
beside a designed bead or crease is found (the accuracy suite's spike_low misses on creases and
flanges), a clean bend is not."""

from __future__ import annotations

import sys
from pathlib import Path

import miem
import miem.reference as ref
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from stream_batch import assert_stream_equals_batch  # noqa: E402

BEAD_COL, SPIKE, SPIKE_HEIGHT = 20, (30, 25), 0.3


def _bead_with_spike(dtype=np.float64) -> np.ndarray:
    """A 1-sample bead 3 units tall (column 20, a feature line) on a plane with 0.01 noise, unit
    spacing, and a 0.3 spike 5 cells beside it: too low for the angle test (its angle is
    180 - 2 atan(0.3) = 147 degrees > theta0 = 90), 30 noise sigmas off the plane."""
    h, w = 60, 40
    rng = np.random.default_rng(5)
    rows, cols = np.mgrid[0:h, 0:w]
    z = 0.02 * cols + rng.normal(0.0, 0.01, (h, w))
    z[:, BEAD_COL] += 3.0
    z[SPIKE] += SPIKE_HEIGHT
    return np.stack([cols * 1.0, rows * 1.0, z], -1).astype(dtype)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_spike_beside_a_feature_line_is_found_in_the_rms_form(dtype) -> None:
    grid = _bead_with_spike(dtype)
    kw = {"min_step": None, "edge_tolerance": None}  # the height test alone
    core, want = miem.detect(grid, **kw), ref.detect(grid, **kw)
    np.testing.assert_array_equal(core.labels, want.labels)
    bead = np.zeros(grid.shape[:2], bool)
    bead[:, BEAD_COL] = True
    assert (core.labels[bead] == miem.EDGE).all()  # the bead is a feature line ...
    assert core.labels[SPIKE] == miem.ABNORMAL  # ... and the spike 5 cells from it is found
    assert np.count_nonzero(core.labels == miem.ABNORMAL) == 1
    # the angle test alone does not see it
    plain = miem.detect(grid, min_step=None, edge_tolerance=None, height_tolerance=None)
    assert plain.labels[SPIKE] == miem.NORMAL
    # the absolute form abstains next to the bead (0.1 would take the spike anywhere else)
    for run in (miem.detect, ref.detect):
        res = run(grid, height_tolerance=0.1, **kw)
        assert res.labels[SPIKE] == miem.NORMAL
        assert np.count_nonzero(res.labels == miem.ABNORMAL) == 0
    far = grid.copy()
    far[SPIKE[0], SPIKE[1], 2] -= SPIKE_HEIGHT
    far[SPIKE[0], 36, 2] += SPIKE_HEIGHT  # 16 cells from the bead: outside the 21-window
    assert miem.detect(far, height_tolerance=0.1, **kw).labels[SPIKE[0], 36] == miem.ABNORMAL
    # the default preset (edge test and min_step='auto' on) finds it too
    assert miem.detect(grid).labels[SPIKE] == miem.ABNORMAL


@pytest.mark.parametrize("shape", ["fold", "step"])
def test_clean_bend_is_not_flagged_next_to_its_feature_line(shape) -> None:
    # Noise-free, everything constant along the columns: within a window each column contributes
    # the same orthogonal residual e_c on every row, so |h| = |e_center| <= sqrt(sum e_c^2) =
    # sqrt(m) rms with m <= 15 columns: sqrt(15) < 4 and "4rms" can never flag a cell, however
    # the window straddles the feature line (EDGE at theta0 = 150). Both must agree.
    rows, cols = np.mgrid[0:30, 0:40]
    x = cols * 1.0
    z = np.where(x > 18, x - 18.0, 0.0) if shape == "fold" else np.where(x > 18, -2.0, 0.0)
    grid = np.stack([x, rows * 1.0, z], -1)
    kw = {"theta0": 150.0, "window": 15, "height_tolerance": "4rms", "min_step": None,
          "edge_tolerance": None}
    core, want = miem.detect(grid, **kw), ref.detect(grid, **kw)
    np.testing.assert_array_equal(core.labels, want.labels)
    assert (core.labels == miem.EDGE).all(axis=0)[18:20].any()  # a feature line at the bend
    assert not (core.labels == miem.ABNORMAL).any()


@pytest.mark.parametrize("fold_deg", [25.0, 45.0])
def test_noisy_fold_stays_clean_next_to_its_feature_line(fold_deg) -> None:
    # a fold across a plane with 0.01 noise, EDGE along the fold at theta0 = 165 (a feature line; the fold angle is 180 - fold_deg),
    # the rest of the default preset: the NORMAL cells beside it are tested now, none is flagged
    rng = np.random.default_rng(8)
    rows, cols = np.mgrid[0:50, 0:50]
    z = 0.01 * rows + np.tan(np.radians(fold_deg)) * np.maximum(cols - 24.0, 0.0)
    grid = np.stack([cols * 1.0, rows * 1.0, z + rng.normal(0.0, 0.01, rows.shape)], -1)
    core, want = miem.detect(grid, theta0=165.0), ref.detect(grid, theta0=165.0)
    np.testing.assert_array_equal(core.labels, want.labels)
    assert (core.labels[:, 23:26] == miem.EDGE).any(axis=1).mean() > 0.5
    assert not (core.labels == miem.ABNORMAL).any()


def test_stream_equals_batch_beside_the_feature_line() -> None:
    grid = _bead_with_spike()
    want = assert_stream_equals_batch(grid, miem.default_params("stream"))
    assert want.labels[SPIKE] == miem.ABNORMAL
