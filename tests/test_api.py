"""The public API on hand-checked geometry and on bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

import miem


def flat_grid(h=21, w=21, step=0.5, z=None) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w] * step
    zz = np.zeros_like(xx) if z is None else z(xx, yy)
    return np.dstack([xx, yy, zz])


# --- geometry computed by hand ---------------------------------------------------------------


def test_known_plane() -> None:
    rng = np.random.default_rng(0)
    xy = rng.uniform(-5, 5, size=(200, 2))
    z = 0.3 * xy[:, 0] - 0.2 * xy[:, 1] + 5.0
    pts = np.column_stack([xy, z])
    expected = np.array([-0.3, 0.2, 1.0]) / math.sqrt(0.09 + 0.04 + 1.0)
    for method in ("eigen", "lstsq"):
        plane = miem.fit_plane(pts, method)
        np.testing.assert_allclose(plane.normal, expected, atol=1e-12)
        assert plane.d == pytest.approx(-5.0 / math.sqrt(1.13), rel=1e-12)
        assert plane.rms < 1e-7
        assert plane.n_points == 200
        np.testing.assert_allclose(plane.distance(pts), 0.0, atol=1e-9)
        assert plane.distance(np.array([0.0, 0.0, 6.0])) == pytest.approx(1 / math.sqrt(1.13))


def test_rms_of_two_parallel_layers() -> None:
    # points at z = +h and z = -h, symmetric: the plane is z = 0 and every distance is h
    g = flat_grid(10, 10)
    g[..., 2] = np.where((np.indices((10, 10)).sum(axis=0) % 2) == 0, 0.25, -0.25)
    plane = miem.fit_plane(g)
    np.testing.assert_allclose(plane.normal, [0, 0, 1], atol=1e-12)
    assert plane.rms == pytest.approx(0.25, rel=1e-12)
    assert plane.eigenvalues[0] == pytest.approx(100 * 0.25**2, rel=1e-12)


def test_orientation_rule() -> None:
    # the plane x = 2 (normal along x): n_z == 0, so the first non-zero component is positive
    pts = np.array([[2.0, 0, 0], [2.0, 1, 0], [2.0, 0, 1], [2.0, 1, 1]])
    np.testing.assert_allclose(miem.fit_plane(pts).normal, [1, 0, 0], atol=1e-15)
    assert miem.fit_plane(pts).d == pytest.approx(-2.0)
    # a plane tilted down in z: the normal is flipped to n_z > 0
    pts = np.array([[0, 0, 0], [1, 0, -1], [0, 1, 0], [1, 1, -1.0]])
    assert miem.fit_plane(pts).normal[2] > 0


def test_known_angles() -> None:
    d = np.array([0.5, math.sqrt(3) / 2, 0.0])  # unit step at 60 deg
    p3 = np.array([1.0, 1.0, 0.0]) + d
    line = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], p3, p3 + d, p3 + 2 * d])
    ang = miem.scan_line_angles(line)
    assert math.isnan(ang[0]) and math.isnan(ang[-1])
    assert ang[1] == pytest.approx(90.0)  # right angle at (1, 0, 0)
    assert ang[4] == pytest.approx(180.0)  # straight through P3, P4, P5
    # equilateral: u = (0,-1) from P=(1,1), v = (0.5, sqrt3/2) -> angle 150 deg
    assert ang[2] == pytest.approx(150.0)


def test_eq20_height_of_a_step() -> None:
    # straight line along x, then P4 at height 1 over the line through P2, P3
    line = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 1.0], [4, 0, 0]])
    heights = miem.scan_line_heights(line)
    assert heights[3] == pytest.approx(1.0)  # sin(theta_2) * |P3 - P2| = (1/sqrt2) * sqrt2
    assert heights[2] == pytest.approx(0.0, abs=1e-12)  # on the line through P0, P1


def test_low_spike_is_flagged_along_rows_and_columns_only() -> None:
    # h = 0.8 over a 0.5 step on z = 0.2x + 0.1y: along x the angle is
    # acos(((-0.5)(0.5) + (-0.9)(-0.7)) / (|(-0.5,-0.9)| |(0.5,-0.7)|)) = 64.6 deg <= 75, along y
    # 64.0 deg, but on the diagonals (0.707 apart) 84.1 and 80.1 deg: only bits 0 and 1 -> EDGE
    g = flat_grid(z=lambda x, y: 0.2 * x + 0.1 * y + 3.0)
    g[10, 10, 2] += 0.8
    res = miem.detect(g, preset="paper")
    assert res.labels[10, 10] == miem.EDGE
    assert res.flags[10, 10] == 0b0011
    def angle(u, v):
        return math.degrees(math.acos(u @ v / np.linalg.norm(u) / np.linalg.norm(v)))

    along = angle(np.array([-0.5, -0.9]), np.array([0.5, -0.7]))
    across = angle(np.array([-0.5, -0.85]), np.array([0.5, -0.75]))
    assert across < along < 75.0
    expect = across  # the smallest angle seen
    assert res.angle[10, 10] == pytest.approx(expect, abs=1e-9)


@pytest.mark.parametrize("h", [1.5, -1.3, 5.0])
def test_known_spike_height_and_labels(h: float) -> None:
    tilt = flat_grid(z=lambda x, y: 0.2 * x + 0.1 * y + 3.0)
    g = tilt.copy()
    g[10, 10, 2] += h
    res = miem.detect(g)
    expected = np.zeros((21, 21), np.uint8)
    expected[10, 10] = miem.ABNORMAL
    np.testing.assert_array_equal(res.labels, expected)
    assert res.flags[10, 10] == 0b1111
    # vertical offset h over a plane with normal (-0.2, -0.1, 1)/|.|: height = h / |.|
    expect_h = h / math.sqrt(0.04 + 0.01 + 1.0)
    assert res.height[10, 10] == pytest.approx(expect_h, rel=1e-9)
    assert len(res.defects) == 1
    d = res.defects[0]
    assert d.count == 1 and d.cells.tolist() == [[10, 10]]
    assert d.kind == ("protrusion" if h > 0 else "pit")
    assert d.peak_height == pytest.approx(expect_h, rel=1e-9)
    np.testing.assert_allclose(d.normal, np.array([-0.2, -0.1, 1.0]) / math.sqrt(1.05), atol=1e-9)
    # the MIEM plane is the clean plane
    np.testing.assert_allclose(res.plane.normal, d.normal, atol=1e-9)
    assert res.plane.rms < 1e-7
    assert res.plane.n_points == 21 * 21 - 1
    # heights of normal points are 0 on an exact plane
    np.testing.assert_allclose(res.height[expected == 0], 0.0, atol=1e-9)


def test_lone_return_in_a_hole_is_isolated_dust() -> None:
    g = flat_grid()
    g[5:12, 5:12] = np.nan
    g[8, 8] = (4.0, 4.0, 0.0)
    res = miem.detect(g)
    assert res.labels[8, 8] == miem.ABNORMAL
    assert (res.labels[5:12, 5:12] == miem.INVALID).sum() == 48
    assert [d.kind for d in res.defects] == ["isolated"]


def test_crease_is_edge_not_abnormal() -> None:
    # two planes meeting at 120 deg along column 10: the crease is flagged across the profile
    g = flat_grid(z=lambda x, y: np.abs(x - 5.0) * math.tan(math.radians(60)))
    res = miem.detect(g, theta0=130.0)
    assert (res.labels[:, 10] == miem.EDGE)[1:-1].all()
    assert not (res.labels == miem.ABNORMAL).any()


def test_two_cell_burr_needs_scale_two() -> None:
    g = flat_grid()
    g[10, 10:12, 2] += 2.0
    g[11, 10:12, 2] += 2.0
    paper = miem.detect(g, preset="paper")  # the paper's scale misses the 2x2 burr
    assert not paper.abnormal[10:12, 10:12].all()
    assert miem.detect(g).abnormal[10:12, 10:12].all()  # the default has scales (1, 2)
    multi = miem.detect(g, preset="paper", scales=(1, 2))
    assert multi.abnormal[10:12, 10:12].all()
    assert multi.abnormal.sum() == 4
    assert multi.defects[0].count == 4
    assert multi.defects[0].peak_height == pytest.approx(2.0, rel=1e-9)


def test_coordinate_offset_gives_the_same_labels() -> None:
    rng = np.random.default_rng(3)
    g = flat_grid(40, 40, z=lambda x, y: 0.05 * x * y / 20)
    g[..., 2] += rng.normal(0, 0.01, g.shape[:2])
    g.reshape(-1, 3)[rng.integers(0, 1600, 12), 2] += 1.5
    base = miem.detect(g)
    far = miem.detect(g + np.array([1e5, 1e5, 1e5]))
    np.testing.assert_array_equal(base.labels, far.labels)
    np.testing.assert_array_equal(base.flags, far.flags)
    np.testing.assert_allclose(base.height, far.height, atol=1e-8, equal_nan=True)


def test_noncontiguous_readonly_and_float32_inputs_are_read_in_place() -> None:
    rng = np.random.default_rng(4)
    g = flat_grid(30, 30)
    g[..., 2] = rng.normal(0, 0.01, (30, 30))
    g[12, 7, 2] = 2.0
    big = np.zeros((60, 30, 4))
    big[::2, :, :3] = g
    view = big[::2, :, :3]  # strided in rows and coordinates
    assert not view.flags.c_contiguous
    ro = g.copy()
    ro.setflags(write=False)
    fortran = np.asfortranarray(g)
    ref = miem.detect(g)
    for arr in (view, ro, fortran, g[::-1][::-1], g.astype(np.float32)):
        np.testing.assert_array_equal(miem.detect(arr).labels, ref.labels)
    # a column-major grid is detected on a C-order copy: the same heights and defects, and
    # the caller's array keeps its values and its order
    res = miem.detect(fortran)
    np.testing.assert_array_equal(res.height, ref.height)
    assert [d.indices.tolist() for d in res.defects] == [d.indices.tolist() for d in ref.defects]
    assert fortran.flags.f_contiguous and np.array_equal(fortran, g, equal_nan=True)
    # integer grids are accepted (converted)
    ints = np.dstack(np.mgrid[0:8, 0:8] + [np.zeros((8, 8), int)])
    ints = np.dstack([ints[..., 1], ints[..., 0], np.zeros((8, 8), int)])
    assert (miem.detect(ints).labels == miem.NORMAL).all()


def test_caller_arrays_are_not_modified() -> None:
    g = flat_grid()
    g[3, 4] = np.nan
    g[10, 10, 2] = 4.0
    before = g.copy()
    miem.detect(g, scales=(1, 2), min_step=0.4)
    miem.fit_plane(g)
    miem.scan_line_angles(g[10])
    np.testing.assert_array_equal(g, before)


def test_labels_enum() -> None:
    assert (miem.NORMAL, miem.ABNORMAL, miem.EDGE, miem.INVALID) == (0, 1, 2, 3)
    assert miem.Label(2) is miem.EDGE
    res = miem.detect(flat_grid())
    assert res.labels.dtype == np.uint8 and res.flags.dtype == np.uint8
    assert res.angle.dtype == np.float64 and res.height.dtype == np.float64
    assert res.labels.shape == res.angle.shape == (21, 21)


# --- bad input -------------------------------------------------------------------------------

GOOD = flat_grid(8, 8)


@pytest.mark.parametrize(
    "grid, match",
    [
        (np.zeros((8, 8)), "shape"),
        (np.zeros((8, 8, 2)), "shape"),
        (np.zeros((2, 8, 8, 3)), "shape"),
        (np.zeros((0, 5, 3)), "at least 3"),
        (np.zeros((1, 2, 3)), "at least 3"),
        (np.full((6, 6, 3), np.nan), "fewer than 3 finite"),
        (np.array([["a", "b", "c"]] * 4, dtype=object).reshape(2, 2, 3), "dtype"),
        (np.ones((4, 4, 3), dtype=complex), "dtype"),
        (np.ones((4, 4, 3), dtype=bool), "dtype"),
        ("not an array", "dtype|shape"),
    ],
)
def test_detect_rejects_bad_grids(grid, match) -> None:
    with pytest.raises(ValueError, match=match):
        miem.detect(grid)


def test_all_nan_but_two_points_is_rejected() -> None:
    g = np.full((5, 5, 3), np.nan)
    g[1, 1] = (0, 0, 0)
    g[3, 3] = (1, 1, 0)
    with pytest.raises(ValueError, match="fewer than 3 finite"):
        miem.detect(g)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"theta0": 0.0}, "theta0"),
        ({"theta0": 180.0}, "theta0"),
        ({"theta0": -5}, "theta0"),
        ({"theta0": float("nan")}, "theta0"),
        ({"theta0": float("inf")}, "theta0"),
        ({"theta0": "75"}, "theta0"),
        ({"scales": ()}, "scales"),
        ({"scales": (0,)}, "scales"),
        ({"scales": (1, -2)}, "scales"),
        ({"scales": (1.5,)}, "scales"),
        ({"scales": (True,)}, "scales"),
        ({"max_gap": -1}, "max_gap"),
        ({"max_gap": 1.0}, "max_gap"),
        ({"min_step": -0.1}, "min_step"),
        ({"min_step": float("nan")}, "min_step"),
        ({"min_directions": 0}, "min_directions"),
        ({"min_directions": 5}, "min_directions"),
        ({"max_iterations": 0}, "max_iterations"),
        ({"window": 4}, "window"),
        ({"window": 1}, "window"),
        ({"max_reach": 0}, "max_reach"),
        ({"heights": "some"}, "heights"),
        ({"num_threads": 0}, "num_threads"),
    ],
)
def test_detect_rejects_bad_parameters(kwargs, match) -> None:
    with pytest.raises(ValueError, match=match):
        miem.detect(GOOD, **kwargs)


@pytest.mark.parametrize(
    "points, match",
    [
        (np.zeros((0, 3)), "at least 3"),
        (np.zeros((2, 3)), "at least 3"),
        (np.zeros((5, 2)), "shape"),
        (np.zeros(6), "shape"),
        (np.full((10, 3), np.nan), "fewer than 3 finite"),
        (np.ones((10, 3)), "degenerate"),  # all equal
        (np.outer(np.arange(10.0), [1.0, 2.0, 3.0]) + 1e5, "degenerate"),  # collinear
        (np.array([["1", "2", "3"]] * 3), "dtype"),
    ],
)
def test_fit_plane_rejects_bad_points(points, match) -> None:
    with pytest.raises(ValueError, match=match):
        miem.fit_plane(points)


def test_fit_plane_rejects_bad_method_and_vertical_lstsq() -> None:
    with pytest.raises(ValueError, match="method"):
        miem.fit_plane(np.eye(3), "ransac")
    vertical = np.array([[2.0, 0, 0], [2.0, 1, 0], [2.0, 0, 1], [2.0, 1, 1]])
    with pytest.raises(ValueError, match="collinear"):
        miem.fit_plane(vertical, "lstsq")


@pytest.mark.parametrize("step", [0, -1, 1.5, True])
def test_scan_line_rejects_bad_step(step) -> None:
    with pytest.raises(ValueError, match="step"):
        miem.scan_line_angles(np.zeros((5, 3)), step)


def test_scan_line_rejects_bad_shape() -> None:
    with pytest.raises(ValueError, match="shape"):
        miem.scan_line_heights(np.zeros((5, 3, 1)))


def test_short_line_is_all_nan() -> None:
    assert np.isnan(miem.scan_line_angles(np.zeros((2, 3)))).all()
    assert miem.scan_line_angles(np.zeros((0, 3))).shape == (0,)
