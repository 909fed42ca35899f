"""SPEC "z_noise": the edge test's tolerances are at least 2 times the scan's z noise, measured
(``"auto"``) as min_step="auto" measures its sigma; it carries that floor where min_step stays
off (profiles jittered by a few times their noise, 4 sigma below the spacing)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

import miem  # noqa: E402
from miem import reference as ref  # noqa: E402
from auto_lengths import (assert_core_is_reference, assert_dask_resolves,  # noqa: E402
                          assert_given_none_and_bad, assert_stream_measures)


def _jittered_sheet(rows: int = 160, cols: int = 240, seed: int = 1) -> np.ndarray:
    """A tilted level sheet, 0.05 mm along and 0.1 mm across (a fifth of them 0.2 mm, a few
    1 mm), noise 0.002 mm, every profile offset by N(0, 0.01 mm), z in 1 um steps: 4 sigma of
    the jitter (about 0.04 mm) stays below the 0.05 mm spacing, so min_step="auto" is off."""
    rng = np.random.default_rng(seed)
    dy = np.full(rows, 0.1)
    u = rng.random(rows)
    dy[u < 0.2] = 0.2
    dy[u < 0.03] = 1.0
    x, y = np.meshgrid(np.arange(cols) * 0.05, np.cumsum(dy))
    z = 0.1 * x + 0.05 * y + rng.normal(0, 0.002, x.shape) + rng.normal(0, 0.01, (rows, 1))
    return np.dstack([x, y, np.round(z / 0.001) * 0.001])


def _sigma_by_hand(g: np.ndarray) -> float:
    """SPEC "min_step='auto'"'s sigma over the first 256 rows with data: 1.4826 median of
    |z[i-1] - 2 z[i] + z[i+1]| / sqrt(6) along and across, the larger."""
    g = g[np.flatnonzero(np.isfinite(g).all(-1).any(1))[0]:][:256]
    out = []
    for zz in (g[..., 2], g[..., 2].T):
        d = np.abs(zz[:, :-2] - 2 * zz[:, 1:-1] + zz[:, 2:])
        out.append(1.4826 * float(np.median(d[np.isfinite(d)])) / math.sqrt(6.0))
    return max(out)


def test_jittered_profiles_stay_clean_and_core_equals_reference() -> None:
    g = _jittered_sheet()
    res = miem.detect(g)
    assert res.params["min_step"] is None  # "auto" off: 4 sigma below the spacing
    assert res.params["z_noise_auto"]
    assert res.params["z_noise"] == pytest.approx(_sigma_by_hand(g), rel=1e-12)
    assert 0.005 < res.params["z_noise"] < 0.0125  # the jitter's sigma, measured across
    assert not (res.labels == miem.ABNORMAL).any()  # a defect-free sheet
    off = ref.detect(g, z_noise=None)  # the reference without the floor
    assert (off.labels == miem.ABNORMAL).sum() > 20  # offset profiles stood proud
    assert ref.detect(g).params["z_noise"] == res.params["z_noise"]
    for kw in ({}, {"z_noise": None}):
        assert_core_is_reference(g, **kw)


def test_defects_are_still_found_and_min_step_on_gives_the_same_floor() -> None:
    g = _jittered_sheet(seed=2)
    spikes = [(30, 40, 0.3), (80, 120, -0.2), (120, 200, 0.15)]
    truth = np.zeros(g.shape[:2], dtype=bool)
    for r, c, dz in spikes:
        g[r, c, 2] += dz
        truth[r, c] = True
    res = miem.detect(g)
    np.testing.assert_array_equal(res.labels == miem.ABNORMAL, truth)
    np.testing.assert_array_equal(res.labels, ref.detect(g).labels)
    # with min_step "auto" on (jitter 4 times larger), 2 z_noise is its min_step / 2
    big = _jittered_sheet(seed=3)
    big[..., 2] += np.random.default_rng(4).normal(0, 0.03, (big.shape[0], 1))
    on = miem.detect(big)
    assert on.params["min_step"] is not None
    assert on.params["z_noise"] == on.params["min_step"] / 4.0
    np.testing.assert_array_equal(miem.detect(big, z_noise=None).labels, on.labels)


def test_given_length_none_and_bad_values() -> None:
    g = _jittered_sheet(seed=5)
    assert_given_none_and_bad(g, "z_noise")
    assert miem.detect(g, preset="paper", z_noise="auto").params["z_noise"] == miem.detect(
        g).params["z_noise"]
    flat = np.dstack([*np.meshgrid(np.arange(2.0), np.arange(2.0)), np.zeros((2, 2))])
    assert miem.detect(flat).params["z_noise"] is None  # no triple along or across


@pytest.mark.parametrize("kw", [{}, {"min_step": None}, {"min_step": None, "z_resolution": None}])
def test_stream_measures_it_as_batch(kw: dict) -> None:
    g = _jittered_sheet(rows=320, seed=6)
    g[200, 50, 2] += 0.25  # a spike after the sample rows
    assert_stream_measures(g, kw, "z_noise")


def test_dask_resolves_it_from_the_min_step_survey() -> None:
    g = _jittered_sheet(rows=300, seed=7)
    g[:3] = np.nan
    assert_dask_resolves(g, "z_noise")
