"""Duplicate points in clouds (issue 11, SPEC "Duplicate points"): merged within merge_distance,
labelled like the point they duplicate; only an all-one-point cloud is an error."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import miem
from miem import reference as ref

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"


def sheet(seed: int = 0, n: int = 1200) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, 10.0, (n, 2))
    pts = np.column_stack([xy, 0.05 * xy[:, 0] + rng.normal(0, 0.005, n)])
    pts[rng.choice(n, 5, replace=False), 2] += 1.0  # spikes
    return pts


def with_duplicates(pts: np.ndarray, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """The cloud with 60 % of its rows appended again (half exactly, half moved by <= 1e-4),
    shuffled; returns the points and, per row, the row of the first copy in the result."""
    rng = np.random.default_rng(seed)
    n = len(pts)
    extra = rng.choice(n, int(0.6 * n), replace=False)
    copies = pts[extra].copy()
    copies[: len(extra) // 2] += rng.uniform(-5e-5, 5e-5, (len(extra) // 2, 3))
    allp = np.vstack([pts, copies])
    source = np.concatenate([np.arange(n), extra])  # original row of every row
    order = rng.permutation(len(allp))
    return allp[order], source[order]


def test_duplicates_take_the_labels_of_the_point_they_duplicate() -> None:
    base = sheet()
    pts, source = with_duplicates(base)
    # plain: without merging the near copies count as neighbours; with merge_distance they go
    res = miem.detect_points(pts, merge_distance=1e-3)
    oracle = ref.detect_points(pts, merge_distance=1e-3)
    np.testing.assert_array_equal(res.labels, oracle.labels)
    np.testing.assert_allclose(res.height, oracle.height, atol=1e-9, equal_nan=True)
    assert [d.indices.tolist() for d in res.defects] == [d.indices.tolist()
                                                          for d in oracle.defects]
    assert res.params["merged"] == oracle.params["merged"] == len(pts) - len(base)
    # every copy is labelled like its group's first row, and the first rows are detected as
    # the distinct cloud would be
    first = {}
    for row, s in enumerate(source):
        first.setdefault(int(s), row)
    rep = np.array([first[int(s)] for s in source])
    np.testing.assert_array_equal(res.labels, res.labels[rep])
    distinct = np.array(sorted(first.values()))
    alone = miem.detect_points(pts[distinct])
    np.testing.assert_array_equal(res.labels[distinct], alone.labels)
    assert res.params["spacing"] == alone.params["spacing"]
    # defects list every input row of their points, copies included
    for d in res.defects:
        assert set(d.indices.tolist()) == set(np.flatnonzero(np.isin(rep, d.indices)).tolist())
        assert d.count == d.indices.size
    assert sum(d.count for d in res.defects) == int((res.labels == miem.ABNORMAL).sum())


def test_exact_duplicates_merged_by_default_and_errors() -> None:
    base = sheet(2, 600)
    pts = np.vstack([base, base, base])  # two thirds duplicates: the spacing would be 0
    res = miem.detect_points(pts)
    assert res.params["merged"] == 1200 and res.params["merge_distance"] == 0.0
    np.testing.assert_array_equal(res.labels[600:1200], res.labels[:600])
    np.testing.assert_array_equal(res.labels, ref.detect_points(pts).labels)
    one = np.tile([[1.0, 2.0, 3.0]], (50, 1))
    one[3] = np.nan
    for fn in (miem.detect_points, ref.detect_points):
        with pytest.raises(ValueError, match="one point"):
            fn(one)
        with pytest.raises(ValueError, match="merge_distance"):
            fn(base, merge_distance=-1.0)
        with pytest.raises(ValueError, match="distinct"):
            fn(np.array([[0, 0, 0], [0, 0, 0], [1.0, 0, 0], [1, 0, 0]]))


@pytest.mark.skipif(not (REAL / "room_scan1.pcd").exists(), reason="needs ../shared/data/real")
def test_room_scan_with_half_duplicates_is_detected() -> None:
    from miem import io

    pts = io.read(REAL / "room_scan1.pcd").points
    # its 10,000 returns around the scanner lie within one radius (test_clouds_dense.py)
    with pytest.warns(UserWarning, match="dense for its radius"):
        res = miem.detect(pts)
    uniq = np.unique(pts, axis=0)
    assert res.params["merged"] == len(pts) - len(uniq)
    assert res.params["spacing"] > 0


def test_flattened_grid_keeps_its_grid_with_shape_and_warns_without() -> None:
    from miem import simulate

    scan = simulate.make_scan(shape=(40, 50), surface="tilted", noise=0.01, dropout=0.01,
                              defects={"spike": 3}, seed=2)
    flat = scan.points.reshape(-1, 3)
    grid = miem.detect(scan.points)
    kept = miem.detect(flat, shape=(40, 50))
    np.testing.assert_array_equal(kept.labels, grid.labels)
    assert kept.labels.shape == (40, 50)
    with pytest.warns(UserWarning, match="scan-line order.*shape=.*layout='auto'"):
        miem.detect(flat)
    finite = flat[np.isfinite(flat).all(axis=1)]
    with pytest.warns(UserWarning, match="scan-line order"):
        miem.detect(finite)
    rng = np.random.default_rng(0)
    import warnings

    shuffled = finite[rng.permutation(len(finite))]  # on its scan lines, not in their order
    with pytest.warns(UserWarning, match=r"not in scan-line order \(\d+ y positions.*"
                                         r"layout='auto'"):
        res = miem.detect(shuffled)
    assert res.labels.shape == (len(finite),)  # still the cloud detector
    jittered = shuffled.copy()
    jittered[:, :2] += rng.uniform(-0.1, 0.1, (len(finite), 2))  # a third of the 0.3 step
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        miem.detect(jittered)  # a true cloud: no warning
    for bad in ((40, 51), (40,), (0, 2000), (40.0, 50)):
        with pytest.raises(ValueError, match="shape"):
            miem.detect(flat, shape=bad)
