"""``miem.detect(points, layout=...)``: a cloud on a profiler's scan lines detected as the grid
rebuilt from them, with the result mapped back onto the input's rows. The oracle is the
organized scan the cloud was made from: each row must get its own cell's label, flags, angle
and height from ``miem.detect(grid)``, and each defect the rows of its cells."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import miem
from miem import simulate


def scan_and_cloud(seed: int = 4):
    """A 60 x 80 profiler scan with defects and dropouts, and its finite points as a cloud
    (rows in scan order) with the cell each row came from."""
    scan = simulate.make_scan(shape=(60, 80), surface="tilted", noise=0.01, dropout=0.01,
                              defects={"spike": 4, "cluster": 2, "pit": 2}, seed=seed)
    flat = scan.points.reshape(-1, 3)
    cells = np.flatnonzero(np.isfinite(flat).all(axis=1))
    return scan.points, flat[cells], cells


def expect_rows(points_res, grid_res, cells: np.ndarray) -> None:
    """Every row carries its cell's values; every defect lists the rows of its cells."""
    for name in ("labels", "flags", "angle", "height"):
        want = getattr(grid_res, name).reshape(-1)[cells]
        np.testing.assert_array_equal(getattr(points_res, name), want, err_msg=name)
    row_of = {int(c): r for r, c in enumerate(cells)}
    assert len(points_res.defects) == len(grid_res.defects)
    for got, want in zip(points_res.defects, grid_res.defects):
        rows = sorted(row_of[int(c)] for c in want.indices)
        np.testing.assert_array_equal(got.indices, rows)
        np.testing.assert_array_equal(got.cells, np.asarray(rows)[:, None])
        assert got.count == len(rows) and got.kind == want.kind
        assert got.peak_height == want.peak_height


@pytest.mark.parametrize("order", ["scan", "shuffled"])
def test_rebuilt_grid_gives_each_row_its_cells_result(order):
    grid, pts, cells = scan_and_cloud()
    if order == "shuffled":
        perm = np.random.default_rng(1).permutation(len(pts))
        pts, cells = pts[perm], cells[perm]
    before = pts.copy()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the layout is chosen: no advice
        res = miem.detect(pts, layout="auto", num_threads=2)
    want = miem.detect(grid, num_threads=2)
    assert isinstance(res, miem.PointsDetectResult) and res.labels.shape == (len(pts),)
    assert res.counts()["ABNORMAL"] > 0
    expect_rows(res, want, cells)
    assert res.params["layout"] == "scanlines"
    assert res.params["grid_shape"] == (60, 80)
    assert res.params["scan_order"] == ("file" if order == "scan" else "line")
    assert res.params["line_axis"] == 1  # simulate's profiles are at constant y
    assert res.params["preset"] == want.params["preset"] and res.degenerate is None
    np.testing.assert_array_equal(pts, before)  # the caller's array is not changed
    # "scanlines" rebuilds the same grid; float32 points give the float32 grid's result
    again = miem.detect(pts, layout="scanlines", num_threads=1)
    np.testing.assert_array_equal(again.labels, res.labels)
    single = miem.detect(pts.astype(np.float32), layout="auto")
    expect_rows(single, miem.detect(grid.astype(np.float32)), cells)


def test_rows_off_the_grid_are_invalid_and_parameters_reach_the_grid():
    grid, pts, cells = scan_and_cloud(seed=5)
    holes = pts.copy()
    holes[::97] = np.nan  # dropouts kept as NaN rows: in no cell
    res = miem.detect(holes, layout="auto", preset="paper")
    kept = np.isfinite(holes).all(axis=1)
    assert np.all(res.labels[~kept] == miem.INVALID) and np.isnan(res.height[~kept]).all()
    assert np.all(res.flags[~kept] == 0) and np.isnan(res.angle[~kept]).all()
    # the finite rows are the original grid without those points, detected with the paper's
    # settings
    g = grid.reshape(-1, 3).copy()
    g[cells[~kept]] = np.nan
    want = miem.detect(g.reshape(grid.shape), preset="paper")
    np.testing.assert_array_equal(res.labels[kept], want.labels.reshape(-1)[cells[kept]])
    assert res.params["preset"] == "paper"
    # a cloud-only field has no meaning on the rebuilt grid: refused, naming it
    with pytest.raises(ValueError, match="radius"):
        miem.detect(pts, layout="auto", radius=1.0)


def test_a_true_cloud_takes_the_cloud_detector_or_is_refused():
    rng = np.random.default_rng(2)
    cloud = np.column_stack([rng.uniform(0, 20, 4000), rng.uniform(0, 20, 4000),
                             rng.normal(0, 0.01, 4000)])
    auto = miem.detect(cloud, layout="auto", num_threads=1)
    plain = miem.detect_points(cloud, num_threads=1)
    np.testing.assert_array_equal(auto.labels, plain.labels)
    assert "layout" not in auto.params and auto.degenerate is not None
    with pytest.raises(ValueError, match="layout: 'scanlines'"):
        miem.detect(cloud, layout="scanlines")


def test_layout_cloud_runs_the_cloud_detector_without_advice():
    _, pts, _ = scan_and_cloud()
    with pytest.warns(UserWarning, match="layout='auto'"):
        plain = miem.detect(pts)  # in scan-line order: advised
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = miem.detect(pts, layout="cloud")
    np.testing.assert_array_equal(res.labels, plain.labels)


def test_bad_layouts_are_refused():
    grid, pts, _ = scan_and_cloud()
    for bad in ("grid", "Auto", 1, True):
        with pytest.raises(ValueError, match="layout: expected one of 'auto', 'scanlines', "
                                             "'cloud' or None"):
            miem.detect(pts, layout=bad)
    with pytest.raises(ValueError, match=r"layout: 'auto' is for \(N, 3\) clouds, got an "
                                         r"array of shape \(60, 80, 3\)"):
        miem.detect(grid, layout="auto")
    with pytest.raises(ValueError, match="shape= already gives the grid"):
        miem.detect(grid.reshape(-1, 3), layout="auto", shape=(60, 80))


def test_detect_points_refuses_detects_layout_and_shape():
    """detect_points is the cloud detector: miem.detect's layout= and shape= are a ValueError
    naming the argument and saying where it belongs (not 'unknown detection parameter')."""
    _, pts, _ = scan_and_cloud()
    for kw in ({"layout": "auto"}, {"layout": "cloud"}, {"shape": (60, 80)}):
        name = next(iter(kw))
        with pytest.raises(ValueError, match=rf"^{name}: detect_points does not take it: it "
                                             r"runs the cloud detector; miem.detect\(points, "
                                             r"layout='auto'\) rebuilds"):
            miem.detect_points(pts, **kw)
