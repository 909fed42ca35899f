"""The dense-cluster advice of miem.detect / detect_points on clouds: a cloud whose points have
on average far more neighbours within the radius than an even scan (a blob of returns around
a scanner) is slow to detect, and the user is told why. The counts are checked against a k-d
tree (scipy), independently of the estimate."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.spatial import cKDTree

import miem
from miem import _unorganized as mu


def sheet(n: int, seed: int = 0) -> np.ndarray:
    """An even jittered sheet of about n points, 1 apart."""
    side = int(np.sqrt(n))
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:side, 0:side].astype(np.float64)
    pts = np.column_stack([x.ravel(), y.ravel(), np.zeros(side * side)])
    pts[:, :2] += rng.uniform(-0.2, 0.2, (len(pts), 2))
    pts[:, 2] = rng.normal(0.0, 0.01, len(pts))
    return pts[rng.permutation(len(pts))]  # a cloud, not a flattened grid


def with_blob(pts: np.ndarray, n: int, seed: int = 1) -> np.ndarray:
    """`pts` with n points in a 0.5-wide ball 3 above the sheet's middle (a scanner's
    near-range returns), in the middle of the rows."""
    rng = np.random.default_rng(seed)
    centre = np.array([pts[:, 0].mean(), pts[:, 1].mean(), 3.0])
    blob = centre + rng.uniform(-0.25, 0.25, (n, 3))
    half = len(pts) // 2
    return np.concatenate([pts[:half], blob, pts[half:]])


def exact_others(pts: np.ndarray, radius: float) -> np.ndarray:
    """Each finite point's count of other finite points within `radius` (k-d tree)."""
    fin = pts[np.isfinite(pts).all(axis=1)]
    return cKDTree(fin).query_ball_point(fin, radius, return_length=True) - 1


def exact_mean_others(pts: np.ndarray, radius: float) -> float:
    return float(exact_others(pts, radius).mean())


def test_even_cloud_gets_no_advice():
    pts = sheet(20_000)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = miem.detect(pts, num_threads=2)
    radius = res.params["radius"]
    assert exact_mean_others(pts, radius) < 200  # an even sheet: tens per ball
    assert mu._dense_advice(pts, radius, 2) == ""


@pytest.mark.parametrize("entry", ["detect", "detect_points"])
def test_dense_blob_is_advised_with_its_count(entry):
    pts = with_blob(sheet(16_900), 4_000)
    fn = miem.detect if entry == "detect" else miem.detect_points
    with pytest.warns(UserWarning, match="dense for its radius") as rec:
        res = fn(pts, num_threads=2)
    radius = res.params["radius"]
    others = exact_others(pts, radius)
    exact = float(others.mean())
    assert exact > 500  # the blob's 4,000 points see each other
    msg = str(rec[0].message)
    assert f"radius {radius:.4g}" in msg and "smaller radius" in msg
    est = float(msg.split("about ")[1].split(" others")[0].replace(",", ""))
    assert est == pytest.approx(exact, rel=0.15)
    share = np.mean(others > 1000)
    assert share == pytest.approx(4_000 / len(pts), abs=0.02)  # the blob, and only it
    said = float(msg.split("(")[2].split("% of them")[0]) / 100
    assert said == pytest.approx(share, abs=0.03)
    # the advice changes nothing: the same labels without it
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        again = fn(pts, num_threads=1)
    assert np.array_equal(res.labels, again.labels)


def test_small_radius_on_the_same_cloud_is_not_advised():
    # the same blob at a radius that keeps it to a few points per ball: no advice
    pts = with_blob(sheet(16_900), 4_000)
    assert exact_mean_others(pts, 0.05) < 500
    assert mu._dense_advice(pts, 0.05, 2) == ""


def test_small_clouds_and_nan_rows_are_not_advised():
    # below _DENSE_MIN_POINTS rows: never (a clump of a few hundred points is quick anyway)
    clump = np.random.default_rng(3).uniform(0, 0.1, (500, 3))
    assert mu._dense_advice(clump, 1.0, 1) == ""
    # NaN rows (dropouts) take no part in the estimate
    pts = with_blob(sheet(16_900), 4_000)
    pts[::3] = np.nan
    assert mu._dense_advice(pts, 5.0, 2) != ""
    assert mu._dense_advice(np.full((30_000, 3), np.nan), 5.0, 2) == ""


def test_command_line_says_it_in_its_words(tmp_path, capsys):
    import miem.io as mio
    from miem import cli

    pts = with_blob(sheet(16_900), 4_000)
    mio.write(tmp_path / "dense.pcd", pts)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no Python warning reaches the terminal
        rc = cli.main(["detect", str(tmp_path / "dense.pcd"), "--out-dir", str(tmp_path / "o"),
                       "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 0, err
    line = next(x for x in err.splitlines() if "dense for its radius" in x)
    assert line.startswith("miem: warning: dense.pcd: detect: this (20900, 3) cloud")
    assert line.endswith("or pass a smaller --radius")
    assert "UserWarning" not in err


def test_dask_cloud_gets_the_same_advice():
    # miem.dask.detect_points estimates on the same rows, read from the chunks that hold them
    da = pytest.importorskip("dask.array")
    import miem.dask as mdask

    pts = with_blob(sheet(16_900), 4_000)
    with pytest.warns(UserWarning, match="dense for its radius") as whole:
        miem.detect(pts, num_threads=2)
    with pytest.warns(UserWarning, match="dense for its radius") as parts:
        res = mdask.detect_points(da.from_array(pts, chunks=6_000), num_threads=2)
    assert str(parts[0].message) == str(whole[0].message)
    assert parts[0].filename == __file__  # it points at the caller's line
    with pytest.warns(UserWarning, match="dense for its radius") as routed:
        mdask.detect(da.from_array(pts, chunks=6_000), num_threads=2, tile=40.0)
    assert str(routed[0].message) == str(whole[0].message)
    assert routed[0].filename == __file__  # through miem.dask.detect too
    # an even cloud, float32 or float64: no advice
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for dt in (np.float32, np.float64):
            mdask.detect_points(da.from_array(sheet(20_000).astype(dt), chunks=7_000))
    assert res.params["radius"] > 0
