"""estimate_normals against geometry (planes, spheres) and against a direct eigen fit per point."""

from __future__ import annotations

import numpy as np
import pytest
from miem._unorganized import estimate_normals


def oriented(n: np.ndarray) -> np.ndarray:
    """The SPEC orientation: n_z > 0, or if n_z == 0 the first non-zero component positive."""
    n = np.array(n, dtype=float)
    nz = np.flatnonzero(n[[2, 0, 1]] != 0)
    return n * np.sign(n[[2, 0, 1]][nz[0]])


def direct_fit(pts: np.ndarray):
    c = pts.mean(axis=0)
    w, v = np.linalg.eigh((pts - c).T @ (pts - c))
    if len(pts) < 3 or not w[2] > 0 or w[1] <= 1e-12 * w[2]:
        return None
    return oriented(v[:, 0]), np.sqrt(max(w[0], 0.0) / len(pts))


def test_tilted_plane_far_from_origin():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 10, (4000, 2))
    z = 0.3 * xy[:, 0] - 0.2 * xy[:, 1]
    pts = np.column_stack([xy, z]) + [2e4, -3e4, 500.0]
    res = estimate_normals(pts, 0.6)
    truth = np.array([-0.3, 0.2, 1.0]) / np.linalg.norm([-0.3, 0.2, 1.0])
    assert res.valid.all()
    assert res.normals.shape == (4000, 3) and res.normals.dtype == np.float64
    assert res.rms.shape == res.count.shape == res.valid.shape == (4000,)
    assert res.count.dtype == np.int64 and res.valid.dtype == np.bool_
    np.testing.assert_allclose(res.normals, np.broadcast_to(truth, (4000, 3)), atol=1e-9)
    # rms = sqrt(l0 / n): l0 is known to ~eps * l2, so an exact plane gives ~1e-8, not 0
    assert np.all(res.rms < 1e-7)
    assert res.radius == 0.6


def test_sphere_normals_follow_the_radius():
    rng = np.random.default_rng(1)
    R = 10.0
    d = rng.normal(size=(20000, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    centre = np.array([100.0, -50.0, 7.0])
    pts = centre + R * d
    res = estimate_normals(pts, 1.0)
    assert res.valid.all()
    cosang = np.abs(np.einsum("ij,ij->i", res.normals, d))
    err_deg = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
    # a 1-unit cap of a radius-10 sphere, ~60 random points: the fit tilts only by sampling
    assert np.median(err_deg) < 0.3 and err_deg.max() < 3.0
    assert np.all(res.normals[:, 2] >= 0)
    # the cap's sagitta r^2 / 2R sets the scale of the rms
    assert np.all(res.rms > 0) and np.all(res.rms < 1.0**2 / (2 * R))


def test_matches_direct_fit_and_brute_force_counts():
    rng = np.random.default_rng(2)
    pts = np.column_stack([rng.uniform(0, 5, (600, 2)), rng.normal(0, 0.05, 600)])
    pts[::40] = np.nan
    r = 0.4
    res = estimate_normals(pts, r)
    fin = np.isfinite(pts).all(axis=1)
    for i in range(len(pts)):
        if not fin[i]:
            assert res.count[i] == 0 and not res.valid[i] and np.isnan(res.normals[i]).all()
            continue
        d = pts - pts[i]
        d2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]
        nb = pts[fin & (d2 <= r * r)]
        assert res.count[i] == len(nb)
        fit = direct_fit(nb)
        if fit is None:
            assert not res.valid[i] and np.isnan(res.normals[i]).all() and np.isnan(res.rms[i])
        else:
            assert res.valid[i]
            np.testing.assert_allclose(res.normals[i], fit[0], atol=1e-10)
            np.testing.assert_allclose(res.rms[i], fit[1], rtol=1e-7, atol=1e-7)


def test_sparse_points_are_invalid():
    pts = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [10, 10, 0], [10.5, 10, 0]])
    res = estimate_normals(pts, 1.0)
    assert not res.valid.any()
    assert res.count.tolist() == [1, 1, 1, 2, 2]
    assert np.isnan(res.normals).all() and np.isnan(res.rms).all()


def test_collinear_points_are_invalid():
    t = np.linspace(0, 5, 60)
    line = np.column_stack([t, 2 * t + 1, -t]) + 1e3
    res = estimate_normals(line, 0.5)
    assert (res.count >= 3).all()
    assert not res.valid.any()
    assert np.isnan(res.normals).all()


def test_identical_points_are_invalid():
    res = estimate_normals(np.ones((10, 3)), 1.0)
    assert not res.valid.any() and (res.count == 10).all()


def test_vertical_plane_orientation():
    rng = np.random.default_rng(3)
    yz = rng.uniform(0, 4, (500, 2))
    pts = np.column_stack([np.full(500, 2.0), yz])  # the plane x = 2: normal along x, n_z = 0
    res = estimate_normals(pts, 0.7)
    assert res.valid.all()
    np.testing.assert_allclose(res.normals, np.broadcast_to([1.0, 0, 0], (500, 3)), atol=1e-12)


def test_float32_and_threads_give_identical_results():
    rng = np.random.default_rng(4)
    pts32 = (rng.uniform(0, 40, (30000, 3)) * [1, 1, 0.02]).astype(np.float32)
    a = estimate_normals(pts32, 0.5, num_threads=1)
    b = estimate_normals(pts32, 0.5, num_threads=2)
    c = estimate_normals(pts32.astype(np.float64), 0.5, num_threads=2)
    for x, y in ((a, b), (a, c)):
        np.testing.assert_array_equal(x.normals, y.normals)
        np.testing.assert_array_equal(x.rms, y.rms)
        np.testing.assert_array_equal(x.count, y.count)
        np.testing.assert_array_equal(x.valid, y.valid)


def test_empty_input():
    res = estimate_normals(np.zeros((0, 3)), 1.0)
    assert res.normals.shape == (0, 3) and res.valid.shape == (0,)


@pytest.mark.parametrize("radius", [0.0, -1.0, np.nan, np.inf, None])
def test_bad_radius(radius):
    with pytest.raises(ValueError, match="radius"):
        estimate_normals(np.zeros((5, 3)), radius)


def test_bad_shape():
    with pytest.raises(ValueError, match="points"):
        estimate_normals(np.zeros((5, 2)), 1.0)
    with pytest.raises(ValueError, match="num_threads"):
        estimate_normals(np.zeros((5, 3)), 1.0, num_threads=0)
