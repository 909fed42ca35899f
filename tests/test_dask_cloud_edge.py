"""miem.dask.detect_points runs the cloud edge test (on by default, issue 11): its candidates
compare each point's surroundings rms with their median over the whole cloud (SPEC "Unorganized
clouds: edge test" step 1), which the tiles survey first (SPEC "Blocks"). Labels, flags, angles,
heights, `degenerate` and defects equal miem.detect on the whole cloud, with a burred cut
outline crossing the tile borders, under every preset, float32 and float64; each tile's own
median would not give them."""

from __future__ import annotations

import numpy as np
import pytest

import miem

da = pytest.importorskip("dask.array", reason="miem[dask] not installed")
import dask  # noqa: E402

import miem.dask as mdask  # noqa: E402
from miem._unorganized import _cloud_part  # noqa: E402

A = miem.ABNORMAL
STEP = 0.3


def cut_cloud(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A tilted plate (`n` x `n` points STEP apart, x / y jittered) cut along a line at 20
    degrees to the y axis through its middle, with a burr run 2 points wide raised 0.12 mm on
    the cut's last points along the whole line; the plate is rougher (noise 0.02 mm) for y below
    the middle than above it (0.004 mm), so that tiles see different rms; rows shuffled. Returns
    the points and the burr mask."""
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[0:n, 0:n]
    x, y = c.ravel() * STEP, r.ravel() * STEP
    mid = 0.5 * n * STEP
    phi = np.radians(20.0)
    d = (x - mid) * np.cos(phi) + (y - mid) * np.sin(phi)
    keep = d < 0.0
    burr = keep & (d >= -2.0 * STEP)
    noise = np.where(y < mid, 0.02, 0.004)
    z = 0.05 * x + 0.02 * y + rng.normal(0.0, 1.0, x.size) * noise + 0.12 * burr
    pts = np.column_stack([x, y, z])
    pts[:, :2] += rng.uniform(-0.25 * STEP, 0.25 * STEP, (x.size, 2))
    pts, burr = pts[keep], burr[keep]
    order = rng.permutation(len(pts))
    return np.ascontiguousarray(pts[order]), burr[order]


def _defects_equal(got: list, want: list) -> None:
    assert len(got) == len(want)
    for a, b in zip(got, want):
        assert (a.id, a.count, a.kind) == (b.id, b.count, b.kind)
        np.testing.assert_array_equal(a.indices, b.indices)
        for f in ("centroid", "normal", "peak_height", "mean_height", "extent"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)


def _equal(res: "mdask.DaskPointsResult", want: miem.DetectResult) -> None:
    defects, *arrays = res.defects(res.labels, res.flags, res.angle, res.height, res.degenerate)
    for k, a in zip(("labels", "flags", "angle", "height", "degenerate"), arrays):
        np.testing.assert_array_equal(a, getattr(want, k), err_msg=k)
    _defects_equal(defects, want.defects)


def _whole_median(pts: np.ndarray, **kw) -> float:
    """The median of step 1 on the whole cloud, by NumPy from the core's survey."""
    rms = _cloud_part(pts, survey=True, **kw)
    return float(np.median(rms[np.isfinite(rms)]))


def test_plain_default_call_equals_the_whole_cloud() -> None:
    """miem.dask.detect_points(points), no argument: the default preset with its edge test, the
    spacing and the edge test's median found from the tiles."""
    pts, burr = cut_cloud(48)
    want = miem.detect(pts)
    assert want.params["edge_tolerance"] == miem.DetectParams().cloud.edge_tolerance
    assert (want.labels[burr] == A).any()  # the edge test has something to do here
    with dask.config.set(scheduler="sync"):
        res = mdask.detect_points(da.from_array(pts, chunks=(700, 3)))
        _equal(res, want)
    assert res.params["spacing"] == want.params["spacing"]
    assert res.params["edge_rms_median"] == _whole_median(pts)


# Reaches cut down so that a tile sees part of the cloud (halo ~96 spacings, ~23 mm of 48).
SMALL = {"max_iterations": 2}


def _small(preset: str) -> dict:
    kw = dict(SMALL, preset=preset)
    cfg = miem.CLOUD_PRESETS.get(preset, {})
    if cfg.get("min_group"):
        kw["min_group"] = 3
    if cfg.get("height_tolerance") is not None and cfg.get("edge_extent"):
        kw["edge_extent"] = 3
    return kw


CASES = [(p, e) for p in miem.PRESETS for e in ("preset", 4.0)
         if not (e == 4.0 and miem.CLOUD_PRESETS.get(p, {}).get("edge_tolerance") == 4.0)]


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("preset,edge", CASES)
def test_tiles_equal_the_whole_cloud(preset: str, edge, dtype) -> None:
    """Every preset as it is and with the edge test on (the paper's: without the height test,
    so every point is a candidate and no median is needed); 3 x 3 tiles of 16 mm, the burred
    cut crossing their borders."""
    pts, burr = cut_cloud(160, seed=1)
    pts = pts.astype(dtype)
    kw = _small(preset)
    if edge != "preset":
        kw["edge_tolerance"] = edge
    want = miem.detect(pts, **kw)
    on = want.params["edge_tolerance"] is not None
    with dask.config.set(scheduler="sync"):
        res = mdask.detect_points(da.from_array(pts, chunks=(4000, 3)), tile=16.0, **kw)
        _equal(res, want)
    assert res.params["tiles"] == (3, 3)
    assert 16.0 + res.params["halo"] < 47.0  # a tile of the first or last row sees part only
    if not on:
        assert res.params["edge_rms_median"] is None
        return
    lo = pts.astype(np.float64).min(axis=0)
    tile_of = np.floor((pts[:, :2].astype(np.float64) - lo[:2]) / 16.0).astype(int)
    by_edge = (want.labels == A) & (miem.detect(pts, **dict(kw, edge_tolerance=None)).labels
                                    != A)
    assert by_edge.sum() >= 10  # the edge test flags burr points here ...
    assert len({tuple(t) for t in tile_of[by_edge]}) >= 3  # ... in several tiles
    assert np.mean(burr[by_edge]) > 0.9
    if want.params["height_tolerance"] is not None:
        assert res.params["edge_rms_median"] == _whole_median(pts, **kw)
    else:
        assert res.params["edge_rms_median"] is None  # every point is a candidate


def test_each_tiles_own_median_would_differ(monkeypatch) -> None:
    """The test above can fail: with each tile's own median (the rough half's tiles see a
    larger one, the smooth half's a smaller one) the labels differ from the whole cloud's."""
    pts, _ = cut_cloud(160, seed=1)
    kw = _small("recommended")
    want = miem.detect(pts, **kw)
    monkeypatch.setattr(mdask, "_edge_rms_median", lambda *a: float("nan"))  # each its own
    with dask.config.set(scheduler="sync"):
        res = mdask.detect_points(da.from_array(pts, chunks=(4000, 3)), tile=16.0, **kw)
        labels = res.labels.compute()
    assert (labels != want.labels).sum() >= 3, (labels != want.labels).sum()


def test_survey_is_the_first_height_pass_rms() -> None:
    """The survey hook by hand (SPEC "Unorganized clouds: floating groups and height test" step
    2): for NORMAL points with no EDGE point within height_radius after the angle passes, the
    rms of the plane of the NORMAL points at distances in (radius, height_radius]."""
    pts, _ = cut_cloud(40, seed=2)
    pre = miem.detect(pts, height_tolerance=None, edge_tolerance=None)
    r, hr = pre.params["radius"], pre.params["height_radius"]
    rms = _cloud_part(pts, survey=True)
    normal = pre.labels == miem.NORMAL
    edge = pre.labels == miem.EDGE
    checked = 0
    for i in np.random.default_rng(0).choice(len(pts), 300, replace=False):
        dist = np.linalg.norm(pts - pts[i], axis=1)
        if not normal[i] or (edge & (dist <= hr)).any():
            continue
        q = pts[normal & (dist > r) & (dist <= hr)]
        sv = np.linalg.svd(q - q.mean(axis=0), compute_uv=False)
        assert rms[i] == pytest.approx(sv[2] / np.sqrt(len(q)), rel=1e-9), i
        checked += 1
    assert checked >= 50
    # the hook changes nothing when given the cloud's own median; +inf: only points without
    # a verdict are candidates
    own = _cloud_part(pts, edge_rms_median=_whole_median(pts))
    np.testing.assert_array_equal(own.labels, miem.detect(pts).labels)
    none = _cloud_part(pts, edge_rms_median=np.inf)
    assert ((none.labels == A) <= (own.labels == A)).all()
    assert (none.labels != own.labels).any()  # the value given is the one used


def test_duplicates_count_once() -> None:
    """Exact duplicate rows (merged, SPEC "Duplicate points") are surveyed once: the survey
    gives NaN on the rows merged into another and the distinct cloud's rms (to rounding: its
    rows lie in another order) on the others; the tiles still equal the whole cloud."""
    pts, _ = cut_cloud(120, seed=3)
    rng = np.random.default_rng(3)
    copied = rng.choice(len(pts), 2000, replace=False)
    order = rng.permutation(len(pts) + len(copied))
    both = np.concatenate([pts, pts[copied]])[order]
    first = np.zeros(len(both), bool)  # the first row of each coordinate triple represents it
    first[np.unique(both, axis=0, return_index=True)[1]] = True
    rms = _cloud_part(both, survey=True)
    assert np.isnan(rms[~first]).all()
    at = np.argsort(order)  # where each row of pts, then each copy, went
    rep = at[:len(pts)].copy()
    rep[copied] = np.minimum(rep[copied], at[len(pts):])
    np.testing.assert_allclose(rms[rep], _cloud_part(pts, survey=True), rtol=1e-9,
                               equal_nan=True)
    kw = _small("recommended")
    want = miem.detect(both, **kw)
    assert want.params["merged"] == 2000
    with dask.config.set(scheduler="sync"):
        _equal(mdask.detect_points(da.from_array(both, chunks=(3000, 3)), tile=12.0, **kw),
               want)
