"""SPEC "z_resolution": the rms tolerances of the height and edge tests are at least 1.5 times
the scan's z step, measured (``"auto"``) as the smallest non-zero z difference of finite
neighbours along the profiles of the rows min_step="auto" reads, or between two z values of the
finite cells among the first 65,536 cells of the first 32 of those rows when that is
smaller."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

import miem  # noqa: E402
from miem import _core  # noqa: E402
from miem import reference as ref  # noqa: E402
from auto_lengths import (assert_core_is_reference, assert_dask_resolves,  # noqa: E402
                          assert_given_none_and_bad, assert_stream_measures)

Q = 0.01  # z stored in 0.01 mm steps (a CSV written to two decimals)


def _level_sheet(rows: int = 80, cols: int = 120, seed: int = 1, q: float = Q) -> np.ndarray:
    """A level sheet, 0.05 mm along and 0.1 mm across, noise 0.002 mm (a fifth of the step),
    z rounded to steps of ``q``, 2 % dropouts: its cells lie on z = 0, with a few at +-q."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(cols) * 0.05, np.arange(rows) * 0.1)
    z = np.round(rng.normal(0.0, 0.002, (rows, cols)) / q) * q
    g = np.dstack([x, y, z])
    g[rng.random((rows, cols)) < 0.02] = np.nan
    return g


def test_auto_is_the_step_and_quantised_level_surface_stays_clean() -> None:
    g = _level_sheet()
    z = g[..., 2]
    assert 20 < np.count_nonzero(np.isfinite(z) & (z != 0)) < 200  # cells one step off the level
    res = miem.detect(g)
    assert res.params["z_resolution_auto"]
    assert res.params["z_resolution"] == pytest.approx(Q, abs=1e-12)
    assert not (res.labels == miem.ABNORMAL).any()  # no defect on the sheet
    off = ref.detect(g, z_resolution=None)  # the reference, without the floor
    assert (off.labels == miem.ABNORMAL).sum() > 20  # the cells one step off were "defects"
    for kw in ({}, {"z_resolution": None}):
        assert_core_is_reference(g, **kw)


def test_defects_above_the_step_are_still_found() -> None:
    g = _level_sheet(seed=2)
    spikes = [(20, 30, 0.3), (40, 60, -0.2), (60, 90, 0.05)]  # 30, 20 and 5 steps
    for r, c, dz in spikes:
        g[r, c] = [c * 0.05, r * 0.1, dz]
    res = miem.detect(g)
    truth = np.zeros(g.shape[:2], dtype=bool)
    for r, c, _ in spikes:
        truth[r, c] = True
    np.testing.assert_array_equal(res.labels == miem.ABNORMAL, truth)
    np.testing.assert_array_equal(res.labels, ref.detect(g).labels)


def test_auto_reads_the_min_step_rows_only_and_ignores_unquantised_data() -> None:
    g = _level_sheet(rows=300)
    g[:5] = np.nan  # the sample rows start at the first row with data: rows 5 .. 260
    g[270, 10, 2] = g[270, 11, 2] + 0.001  # a smaller step beyond them is not read
    assert miem.detect(g).params["z_resolution"] == pytest.approx(Q, abs=1e-12)
    assert ref.detect(g).params["z_resolution"] == pytest.approx(Q, abs=1e-12)
    g[100, 10, 2] = g[100, 11, 2] + 0.001  # inside them it is
    assert miem.detect(g).params["z_resolution"] == pytest.approx(0.001, abs=1e-12)
    rng = np.random.default_rng(3)
    smooth = _level_sheet()
    fin = np.isfinite(smooth).all(axis=-1)
    smooth[..., 2] = np.where(fin, rng.normal(0.0, 0.002, fin.shape), np.nan)  # not quantised
    pairs = fin[:, 1:] & fin[:, :-1]
    steps = np.abs(np.diff(smooth[..., 2], axis=1))[pairs]
    levels = np.sort(smooth[:32, :, 2][fin[:32]])  # the first 32 rows' values, pooled
    gaps = levels[1:] - levels[:-1]
    want = min(steps[steps > 0].min(), gaps[gaps > 0].min())
    assert miem.detect(smooth).params["z_resolution"] == want  # a speck far below the noise
    assert want < 1e-5
    flat = np.dstack([*np.meshgrid(np.arange(4.0), np.arange(3.0)), np.zeros((3, 4))])
    assert miem.detect(flat).params["z_resolution"] is None  # no non-zero step at all
    assert _core.auto_z_resolution(flat) == -1.0


def _steep_sheet(rows: int = 80, cols: int = 60, seed: int = 7) -> np.ndarray:
    """A sheet sampled every 0.5 mm both ways, rising 0.3 mm per mm along the profiles, noise
    0.005 mm, z in 1 um steps: neighbours along a profile differ by 0.15 mm +- the noise, so no
    two share a level or lie one step apart."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(cols) * 0.5, np.arange(rows) * 0.5)
    z = np.round((0.3 * x + rng.normal(0.0, 0.005, (rows, cols))) / 0.001) * 0.001
    return np.dstack([x, y, z])


def test_auto_on_a_steep_coarse_sheet_is_the_step_not_the_slope() -> None:
    g = _steep_sheet()
    steps = np.abs(np.diff(g[..., 2], axis=1))
    assert steps.min() > 0.1  # the neighbours' smallest difference is the slope's
    levels = np.unique(np.round(g[:32, :, 2] / 0.001))  # integer levels of the first 32 rows
    assert (np.diff(levels) == 1).any()  # two of their values lie one step apart
    res = miem.detect(g)
    assert res.params["z_resolution"] == pytest.approx(0.001, abs=1e-12)
    # a spike 0.05 mm (10 sigma) proud: found; with the slope's difference as the step (1.5 x
    # 0.1 mm: the tolerance's floor) it would not be
    g[40, 30, 2] += 0.05
    truth = np.zeros(g.shape[:2], dtype=bool)
    truth[40, 30] = True
    np.testing.assert_array_equal(miem.detect(g).labels == miem.ABNORMAL, truth)
    hidden = ref.detect(g, z_resolution=float(steps.min()))
    assert not (hidden.labels == miem.ABNORMAL).any()
    assert_core_is_reference(g)


@pytest.mark.parametrize("at, want", [(60_000, 0.001), (69_000, 0.2)])
def test_auto_pools_the_first_65536_cells(at: int, want: float) -> None:
    """One profile of 70,000 points rising 0.2 mm from one to the next: the neighbours differ
    by 0.2 mm. A point at `at` lies 1 um above point 5: pooled when among the first 65,536
    cells, not beyond."""
    z = 0.2 * np.arange(70_000)
    z[at] = z[5] + 0.001
    g = np.dstack([np.arange(70_000) * 0.05, np.zeros(70_000), z])
    fin = np.isfinite(g).all(axis=-1)
    assert _core.auto_z_resolution(g) == pytest.approx(want, abs=1e-9)
    assert ref._auto_z_resolution(g, fin) == pytest.approx(want, abs=1e-9)


@pytest.mark.parametrize("cols", [5, 9, 17, 61, 333])
def test_auto_steps_equal_the_reference_to_the_bit(cols: int) -> None:
    """The smallest step along the profiles (the dense float64 layout 8 pairs at a time, with
    a scalar tail; float32 and a strided view by the plain loop) is the reference's to the
    last bit: rows of quantised and unquantised z, dropouts (the pairs they break are left
    out), and the smallest step put in turn at every pair of a row beyond the pooled rows
    (each lane of the 8, the tail)."""
    rng = np.random.default_rng(cols)
    rows = 40
    z = np.cumsum(rng.normal(0.0, 0.3, (rows, cols)), axis=1)
    z[::3] = np.round(z[::3], 3)  # quantised rows: many equal neighbours (no step)
    base = np.dstack(np.broadcast_arrays(np.arange(cols) * 0.05, np.arange(rows)[:, None] * 0.1,
                                         z)).astype(np.float64)
    base[rng.random((rows, cols)) < 0.1] = np.nan
    for at in range(cols - 1):
        g = base.copy()
        g[35, at:at + 2] = [[at * 0.05, 3.5, 5.0], [(at + 1) * 0.05, 3.5, 5.0 + 1e-9]]
        wide = np.full((rows, 2 * cols, 3), np.nan)
        wide[:, ::2] = g  # a strided view of the same cells
        for grid in (g, g.astype(np.float32), wide[:, ::2]):
            want = ref._auto_z_resolution(grid.astype(np.float64),
                                          np.isfinite(grid).all(axis=-1))
            assert want is not None and (want < 2e-9 or grid.dtype == np.float32)
            assert _core.auto_z_resolution(grid) == want, at


def test_given_length_none_and_bad_values() -> None:
    assert_given_none_and_bad(_level_sheet(seed=4), "z_resolution")


@pytest.mark.parametrize("min_step", ["auto", None])
def test_stream_measures_it_as_batch(min_step: object) -> None:
    g = _level_sheet(rows=300, seed=5)
    g[150, 40, 2] = 0.2  # a spike, after the sample rows
    want = assert_stream_measures(g, {"min_step": min_step}, "z_resolution")
    assert want.params["z_resolution"] == pytest.approx(Q, abs=1e-12)


def test_stream_measures_it_as_batch_on_a_steep_sheet() -> None:
    g = _steep_sheet(rows=300, seed=8)
    g[150, 20, 2] += 0.2  # a spike, after the sample rows
    want = assert_stream_measures(g, {}, "z_resolution")
    assert want.params["z_resolution"] == pytest.approx(0.001, abs=1e-12)
    short = _steep_sheet(rows=20, seed=9)  # fewer rows than the 32 pooled: those pushed
    s = miem.ProfileStream(short.shape[1])
    for row in short:
        s.push(row)
    list(s.flush())
    assert s.z_resolution == miem.detect(short).params["z_resolution"]
    assert s.z_resolution == pytest.approx(0.001, abs=1e-12)


@pytest.mark.parametrize("steep", [False, True])
def test_dask_resolves_it_on_the_driver(steep: bool) -> None:
    g = _steep_sheet(rows=300, seed=6) if steep else _level_sheet(rows=300, seed=6)
    g[:3] = np.nan
    assert_dask_resolves(g, "z_resolution")
