"""SPEC "z_resolution": the rms tolerances of the height and edge tests are at least 1.5 times
the scan's z step, measured (``"auto"``) as the smallest non-zero z difference of finite
neighbours along the profiles of the rows min_step="auto" reads."""

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
    want = np.abs(np.diff(smooth[..., 2], axis=1))[pairs]
    want = want[want > 0].min()
    assert miem.detect(smooth).params["z_resolution"] == want  # a speck far below the noise
    assert want < 1e-5
    flat = np.dstack([*np.meshgrid(np.arange(4.0), np.arange(3.0)), np.zeros((3, 4))])
    assert miem.detect(flat).params["z_resolution"] is None  # no non-zero step at all
    assert _core.auto_z_resolution(flat) == -1.0


def test_given_length_none_and_bad_values() -> None:
    assert_given_none_and_bad(_level_sheet(seed=4), "z_resolution")


@pytest.mark.parametrize("min_step", ["auto", None])
def test_stream_measures_it_as_batch(min_step: object) -> None:
    g = _level_sheet(rows=300, seed=5)
    g[150, 40, 2] = 0.2  # a spike, after the sample rows
    want = assert_stream_measures(g, {"min_step": min_step}, "z_resolution")
    assert want.params["z_resolution"] == pytest.approx(Q, abs=1e-12)


def test_dask_resolves_it_on_the_driver() -> None:
    g = _level_sheet(rows=300, seed=6)
    g[:3] = np.nan
    assert_dask_resolves(g, "z_resolution")
