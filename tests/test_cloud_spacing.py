"""The cloud parameter `spacing` (SPEC "Spacing"): the unit of the defaults, given or measured."""

from __future__ import annotations

import numpy as np
import pytest

import miem
from miem import _core
from miem import reference as ref


def cloud(n: int = 900, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, 12.0, (n, 2))
    pts = np.column_stack([xy, 0.05 * np.sin(xy[:, 0])])
    pts[[5, 400], 2] += 1.0
    return pts


def test_measured_spacing_given_back_changes_nothing() -> None:
    pts = cloud()
    a = miem.detect(pts)
    b = miem.detect(pts, spacing=miem.point_spacing(pts))
    assert a.params["spacing"] == b.params["spacing"] == miem.point_spacing(pts)
    for k in ("labels", "flags", "height"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_given_spacing_sets_the_defaults_as_the_reference(dtype) -> None:
    pts = cloud().astype(dtype)
    s = 0.3  # not the measured spacing (~0.2)
    res = miem.detect(pts, spacing=s)
    assert res.params["radius"] == 5 * s and res.params["min_step"] == 0.5 * s
    assert res.params["spacing"] == s
    want = ref.detect_points(pts, spacing=s)
    np.testing.assert_array_equal(res.labels, want.labels)


def test_distinct_spacings_median_is_the_detection_spacing_with_duplicates() -> None:
    pts = cloud(500)
    pts = np.concatenate([pts, pts[:200] + 1e-4, [[np.nan, 0, 0]]])  # 200 near duplicates
    nn = _core.distinct_spacings(pts, 1e-3, 1)
    assert np.isnan(nn[500:]).all() and np.isfinite(nn[:500]).all()  # one value per group
    res = miem.detect(pts, merge_distance=1e-3)
    assert res.params["merged"] == 200
    assert float(np.median(nn[np.isfinite(nn)])) == res.params["spacing"]
    # without merging: every finite row, as point_spacing
    nn0 = _core.distinct_spacings(pts, 0.0, 1)
    assert float(np.median(nn0[np.isfinite(nn0)])) == miem.point_spacing(pts)


@pytest.mark.parametrize("bad", [0.0, -1.0, np.nan, np.inf])
def test_bad_spacing_is_refused_by_name(bad) -> None:
    with pytest.raises(ValueError, match="spacing"):
        miem.detect(cloud(), spacing=bad)


def test_spacing_is_a_cloud_field_refused_on_grids() -> None:
    yy, xx = np.mgrid[0:20, 0:20] * 0.5
    with pytest.raises(ValueError, match="spacing"):
        miem.detect(np.dstack([xx, yy, 0 * xx]), spacing=0.5)
