"""NeighborGrid: exact radius and nearest-neighbour queries against brute force in NumPy.

The oracle computes ``d = q - p`` in float64 and keeps ``dx*dx + dy*dy + dz*dz <= r*r``, which is
the grid's documented definition of "within r"; results must be equal as index sets, in
ascending order.
"""

from __future__ import annotations

import gc

import numpy as np
import pytest
from miem._unorganized import NeighborGrid


def brute(points: np.ndarray, q: np.ndarray, r: float) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    d = p - np.asarray(q, dtype=np.float64)
    d2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]
    return np.flatnonzero(np.isfinite(p).all(axis=1) & (d2 <= r * r))


def brute_nn(points: np.ndarray) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    fin = np.isfinite(p).all(axis=1)
    out = np.full(len(p), np.nan)
    q = p[fin]
    best = np.full(len(q), np.inf)
    for s in range(0, len(q), 512):
        d = q[s : s + 512, None, :] - q[None, :, :]
        d2 = d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]
        idx = np.arange(s, min(s + 512, len(q)))
        d2[idx - s, idx] = np.inf
        best[s : s + 512] = d2.min(axis=1)
    out[fin] = np.sqrt(best)
    return out


def check_queries(points: np.ndarray, cell: float, radii, rng, n_queries: int = 60) -> None:
    grid = NeighborGrid(points, cell)
    n = len(points)
    for r in radii:
        for i in rng.choice(n, size=min(n, n_queries), replace=False):
            got = grid.radius_query(int(i), r)
            assert got.dtype == np.int64
            np.testing.assert_array_equal(got, brute(points, points[i], r))


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_random_cloud_matches_brute_force(dtype):
    rng = np.random.default_rng(0)
    pts = rng.uniform(-5, 5, (3000, 3)).astype(dtype)
    # r below, at and well above the cell size (a query then spans many cells)
    check_queries(pts, 0.7, [0.0, 0.3, 0.7, 1.9, 4.0], rng)


def test_far_from_origin_matches_brute_force():
    rng = np.random.default_rng(1)
    pts = rng.uniform(0, 20, (4000, 3)) * [1, 1, 0.05] + [1e5, -1e5, 3e4]
    check_queries(pts, 0.5, [0.5, 1.3], rng)
    grid = NeighborGrid(pts, 0.5)
    np.testing.assert_array_equal(grid.nearest_distances(), brute_nn(pts))


def test_very_uneven_density():
    rng = np.random.default_rng(2)
    dense = rng.uniform(0, 1, (5000, 3)) * [1, 1, 0.01]
    far = np.array([[1e4, 0, 0], [0, -1e4, 7], [1e4, 1e4, 1e4], [1e4 + 3, 0, 0], [-5e3, 2e3, 1]])
    pts = np.vstack([dense, far])
    grid = NeighborGrid(pts, 0.05)
    assert grid.num_cells <= len(pts)  # nothing dense over the bounding box
    for i in list(range(0, 5000, 97)) + list(range(5000, 5005)):
        for r in (0.02, 0.05, 4.0):
            np.testing.assert_array_equal(grid.radius_query(i, r), brute(pts, pts[i], r))
    nn = grid.nearest_distances()
    np.testing.assert_array_equal(nn, brute_nn(pts))
    assert nn[5000] == nn[5003] == 3.0


def test_query_by_xyz_inside_and_outside():
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(2000, 3))
    grid = NeighborGrid(pts, 0.4)
    for q in np.vstack([rng.normal(size=(40, 3)) * 2, [[50.0, 0, 0], [-9, -9, -9]]]):
        for r in (0.2, 0.4, 1.1, 100.0):
            np.testing.assert_array_equal(grid.radius_query(q, r), brute(pts, q, r))
    at_origin = grid.radius_query((0.0, 0.0, 0.0), 0.5)
    np.testing.assert_array_equal(at_origin, brute(pts, [0, 0, 0], 0.5))


def test_points_exactly_at_r_are_included():
    g = np.stack(np.meshgrid(np.arange(7.0), np.arange(7.0), np.arange(3.0), indexing="ij"), -1)
    pts = g.reshape(-1, 3)
    grid = NeighborGrid(pts, 2.0)
    i = int(np.flatnonzero((pts == [3, 3, 1]).all(axis=1))[0])
    got = grid.radius_query(i, 2.0)
    np.testing.assert_array_equal(got, brute(pts, pts[i], 2.0))
    assert np.flatnonzero((pts == [5, 3, 1]).all(axis=1))[0] in got  # at distance exactly 2


def test_nan_rows_duplicates_and_strided_input():
    rng = np.random.default_rng(4)
    base = rng.uniform(0, 3, (1500, 6))
    pts = base[:, 1:4]  # a strided view, not contiguous
    assert not pts.flags.c_contiguous
    work = pts.copy()
    work[::50] = np.nan
    work[1::50] = work[2::50]  # duplicates
    for arr in (pts, work):
        grid = NeighborGrid(arr, 0.3)
        for i in range(0, 1500, 37):
            np.testing.assert_array_equal(grid.radius_query(i, 0.45), brute(arr, arr[i], 0.45))
    grid = NeighborGrid(work, 0.3)
    assert grid.num_indexed == 1500 - 30
    assert grid.radius_query(0, 1.0).size == 0  # a NaN row has no neighbours
    nn = grid.nearest_distances()
    assert np.isnan(nn[0]) and nn[1] == 0.0
    np.testing.assert_array_equal(nn, brute_nn(work))


def test_nearest_distances_independent_of_threads():
    rng = np.random.default_rng(5)
    pts = rng.uniform(0, 30, (20000, 3)) * [1, 1, 0.1]
    grid = NeighborGrid(pts, 0.6)
    a = grid.nearest_distances(num_threads=1)
    b = grid.nearest_distances(num_threads=2)
    np.testing.assert_array_equal(a, b)
    sample = rng.choice(len(pts), 300, replace=False)
    d = pts[sample, None, :] - pts[None, :, :]
    d2 = d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]
    d2[np.arange(300), sample] = np.inf
    np.testing.assert_array_equal(a[sample], np.sqrt(d2.min(axis=1)))


def test_lone_point_has_infinite_nearest_distance():
    pts = np.array([[0.0, 0, 0], [np.nan, 0, 0]])
    nn = NeighborGrid(pts, 1.0).nearest_distances()
    assert nn[0] == np.inf and np.isnan(nn[1])


def test_huge_extent_enlarges_cells_and_stays_exact():
    rng = np.random.default_rng(6)
    pts = np.vstack([rng.uniform(0, 1e-3, (500, 3)), [[1e12, 1e12, 1e12], [-1e12, 5, 0]]])
    grid = NeighborGrid(pts, 1e-6)
    assert grid.cell_size > 1e-6
    assert grid.num_cells <= len(pts)
    for i in (0, 10, 499, 500, 501):
        np.testing.assert_array_equal(grid.radius_query(i, 2e-4), brute(pts, pts[i], 2e-4))
    np.testing.assert_array_equal(grid.nearest_distances(), brute_nn(pts))


def test_grid_keeps_points_alive():
    rng = np.random.default_rng(7)
    pts = rng.uniform(0, 1, (300, 3))
    expected = brute(pts, pts[5], 0.2)
    grid = NeighborGrid(pts.copy(), 0.2)  # the only reference to the copy is inside the grid
    gc.collect()
    np.testing.assert_array_equal(grid.radius_query(5, 0.2), expected)
    assert grid.points.shape == (300, 3) and len(grid) == 300


def test_integer_input_is_converted():
    pts = np.array([[0, 0, 0], [1, 0, 0], [3, 0, 0]])
    grid = NeighborGrid(pts, 1.0)
    assert grid.points.dtype == np.float64
    assert grid.radius_query(0, 1.0).tolist() == [0, 1]
    assert grid.radius_query(np.int64(2), 2.0).tolist() == [1, 2]


@pytest.mark.parametrize("cell", [0.0, -1.0, np.nan, np.inf, "1", None])
def test_bad_cell_size(cell):
    with pytest.raises(ValueError, match="cell_size"):
        NeighborGrid(np.zeros((4, 3)), cell)


@pytest.mark.parametrize(
    "points", [np.zeros((5, 2)), np.zeros(3), np.zeros((2, 3, 3)), np.array([["a", "b", "c"]])]
)
def test_bad_points(points):
    with pytest.raises(ValueError, match="points"):
        NeighborGrid(points, 1.0)


def test_bad_queries():
    grid = NeighborGrid(np.random.default_rng(8).uniform(0, 1, (10, 3)), 0.5)
    with pytest.raises(ValueError, match="r"):
        grid.radius_query(0, -0.1)
    with pytest.raises(ValueError, match="r"):
        grid.radius_query(0, np.nan)
    with pytest.raises(ValueError, match="r"):
        grid.radius_query(0, np.inf)
    with pytest.raises(ValueError, match="out of range"):
        grid.radius_query(10, 0.5)
    with pytest.raises(ValueError, match="out of range"):
        grid.radius_query(-1, 0.5)
    with pytest.raises(ValueError, match="i_or_xyz"):
        grid.radius_query(True, 0.5)
    with pytest.raises(ValueError, match="i_or_xyz"):
        grid.radius_query([0.0, 1.0], 0.5)
    with pytest.raises(ValueError, match="finite"):
        grid.radius_query([0.0, np.nan, 1.0], 0.5)
    with pytest.raises(ValueError, match="i_or_xyz"):
        grid.radius_query("abc", 0.5)
