"""Unorganized detection (detect_points) on clouds whose answer follows from geometry.

The exact rule-by-rule comparison against the NumPy reference lives elsewhere; here: a spike and
a pit on a randomly sampled flat patch, floating dust, invariances (row order, rigid motion,
far-from-origin offset, dtype, thread count) and argument checks.
"""

from __future__ import annotations

import miem
import numpy as np
import pytest
from miem._unorganized import detect_points, point_spacing

NORMAL, ABNORMAL, EDGE, INVALID = 0, 1, 2, 3
STEP = 0.4


def patch(n: int = 40, seed: int = 1) -> np.ndarray:
    """A flat n x n patch sampled at STEP with +-STEP/4 jitter in x, y and 5 um z noise, in random
    row order (a truly unorganized cloud)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:n, 0:n] * STEP
    pts = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    pts[:, :2] += rng.uniform(-STEP / 4, STEP / 4, (x.size, 2))
    pts[:, 2] += rng.normal(0, 0.005, x.size)
    return rng.permutation(pts)


def nearest_to(pts: np.ndarray, x: float, y: float) -> int:
    return int(np.argmin((pts[:, 0] - x) ** 2 + (pts[:, 1] - y) ** 2))


def with_spike(height: float, seed: int = 1) -> tuple[np.ndarray, int]:
    pts = patch(seed=seed)
    i = nearest_to(pts, 8.0, 8.0)
    pts[i, 2] += height
    return pts, i


def test_spike_is_the_only_abnormal_point():
    pts, i = with_spike(1.0)
    res = detect_points(pts, preset="paper", radius=5 * STEP)
    assert np.flatnonzero(res.labels == ABNORMAL).tolist() == [i]
    assert (res.labels[np.arange(len(pts)) != i] == NORMAL).all()
    assert res.flags[i] == 0b1111 and res.angle[i] < 75.0
    assert res.iterations == 2
    assert len(res.defects) == 1
    d = res.defects[0]
    assert d.kind == "protrusion" and d.indices.tolist() == [i] and d.cells.tolist() == [[i]]
    assert d.count == 1 and d.id == 0
    assert d.peak_height == pytest.approx(1.0, abs=0.02)
    np.testing.assert_allclose(d.normal, [0, 0, 1], atol=0.02)
    np.testing.assert_array_equal(d.centroid, pts[i])
    assert d.extent == 0.0
    normal_h = res.height[res.labels == NORMAL]
    assert np.isfinite(normal_h).all() and np.abs(normal_h).max() < 0.03
    assert res.plane is not None and abs(res.plane.normal[2]) > 0.9999
    assert res.labels.shape == res.flags.shape == res.angle.shape == res.height.shape == (1600,)
    assert res.labels.dtype == np.uint8 and res.flags.dtype == np.uint8
    assert res.degenerate.dtype == np.bool_ and not res.degenerate.any()


def test_pit_is_found_with_a_negative_height():
    pts, i = with_spike(-1.5)
    res = detect_points(pts, radius=5 * STEP)
    assert np.flatnonzero(res.labels == ABNORMAL).tolist() == [i]
    assert res.defects[0].kind == "pit"
    assert res.defects[0].peak_height == pytest.approx(-1.5, abs=0.02)


def test_lone_far_point_is_isolated_dust():
    pts = np.vstack([patch(), [[8.0, 8.0, 25.0]]])
    res = detect_points(pts)
    lone = len(pts) - 1
    assert np.flatnonzero(res.labels == ABNORMAL).tolist() == [lone]
    assert np.isnan(res.angle[lone]) and res.flags[lone] == 0
    (d,) = res.defects
    assert d.kind == "isolated" and d.indices.tolist() == [lone]
    assert np.isnan(d.peak_height) and np.isnan(d.normal).all()


def test_defaults_are_recorded():
    pts = patch()
    res = detect_points(pts)
    sp = point_spacing(pts)
    assert res.params["spacing"] == sp
    assert res.params["radius"] == 5 * sp
    assert res.params["min_step"] == 0.5 * sp
    assert res.params["link"] == res.params["radius"]
    # the default for clouds: the recommended angle test
    rec = miem.PRESETS["recommended"]
    assert res.params["K"] == 4 and res.params["scales"] == rec.angle.scales
    assert res.params["theta0"] == rec.angle.theta0 == 90.0
    assert res.params["height_tolerance"] == rec.cloud.height_tolerance == "7rms"
    assert res.params["preset"] == "recommended"
    res = detect_points(pts, radius=1.5, min_step=0.1, link=0.7, K=6)
    assert (res.params["radius"], res.params["min_step"], res.params["link"]) == (1.5, 0.1, 0.7)
    assert res.params["K"] == 6


def test_two_nearby_spikes_form_one_defect_far_ones_two():
    pts = patch()
    a, b, c = nearest_to(pts, 6.0, 6.0), nearest_to(pts, 6.8, 6.0), nearest_to(pts, 12.0, 12.0)
    pts[[a, b, c], 2] += [1.5, 1.0, 1.2]
    res = detect_points(pts, radius=5 * STEP, link=1.5)
    assert sorted(np.flatnonzero(res.labels == ABNORMAL).tolist()) == sorted([a, b, c])
    assert [sorted(d.indices.tolist()) for d in res.defects] == [sorted([a, b]), [c]]
    assert [d.id for d in res.defects] == [0, 1]
    assert res.defects[0].peak_height > res.defects[1].peak_height > 0
    assert res.defects[0].count == 2 and res.defects[0].extent == pytest.approx(0.8, abs=0.25)
    res = detect_points(pts, radius=5 * STEP, link=0.2)
    assert len(res.defects) == 3


def test_row_order_does_not_change_the_labels():
    pts, _ = with_spike(1.0)
    pts = np.vstack([pts, [[3.0, 3.0, 30.0]]])
    base = detect_points(pts, radius=5 * STEP)
    perm = np.random.default_rng(9).permutation(len(pts))
    res = detect_points(pts[perm], radius=5 * STEP)
    np.testing.assert_array_equal(res.labels, base.labels[perm])
    np.testing.assert_array_equal(res.flags, base.flags[perm])
    np.testing.assert_allclose(res.angle, base.angle[perm], atol=1e-9, equal_nan=True)
    np.testing.assert_allclose(res.height, base.height[perm], atol=1e-9, equal_nan=True)
    assert [sorted(perm[d.indices].tolist()) for d in res.defects] == [
        sorted(d.indices.tolist()) for d in base.defects
    ]


def test_rigid_motion_does_not_change_the_labels():
    pts, _ = with_spike(1.0)
    ang = np.radians(35.0)
    axis = np.array([1.0, 2.0, 0.5]) / np.linalg.norm([1.0, 2.0, 0.5])
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R = np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K
    moved = pts @ R.T + [120.0, -40.0, 15.0]
    base = detect_points(pts, radius=5 * STEP)
    res = detect_points(moved, radius=5 * STEP)
    np.testing.assert_array_equal(res.labels, base.labels)
    np.testing.assert_allclose(res.angle, base.angle, atol=1e-7, equal_nan=True)
    # the normal stays on the same side (n_z > 0 before and after), so heights keep their sign
    np.testing.assert_allclose(res.height, base.height, atol=1e-9, equal_nan=True)
    np.testing.assert_allclose(res.defects[0].normal, R @ base.defects[0].normal, atol=1e-9)


def test_far_from_origin_offset():
    pts, _ = with_spike(1.0)
    base = detect_points(pts, radius=5 * STEP)
    res = detect_points(pts + [1e5, -1e5, 2e4], radius=5 * STEP)
    np.testing.assert_array_equal(res.labels, base.labels)
    np.testing.assert_array_equal(res.flags, base.flags)
    np.testing.assert_allclose(res.angle, base.angle, atol=1e-6, equal_nan=True)
    np.testing.assert_allclose(res.height, base.height, atol=1e-8, equal_nan=True)


def test_float32_threads_and_nan_rows():
    pts, _ = with_spike(1.0)
    pts32 = pts.astype(np.float32)
    a = detect_points(pts32, radius=5 * STEP, num_threads=1)
    b = detect_points(pts32.astype(np.float64), radius=5 * STEP, num_threads=2)
    for name in ("labels", "flags", "angle", "height", "degenerate"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    with_nan = np.vstack([pts, np.full((3, 3), np.nan)])
    with_nan[-2, 0] = 1.0  # one finite coordinate is not enough
    c = detect_points(with_nan, radius=5 * STEP)
    assert c.labels[-3:].tolist() == [INVALID] * 3
    assert np.isnan(c.height[-3:]).all() and np.isnan(c.angle[-3:]).all()
    np.testing.assert_array_equal(c.labels[:-3], detect_points(pts, radius=5 * STEP).labels)


def test_threads_give_identical_results_on_a_larger_cloud():
    rng = np.random.default_rng(5)
    pts = patch(n=80, seed=5)
    idx = rng.choice(len(pts), 30, replace=False)
    pts[idx, 2] += rng.uniform(-2, 2, 30)
    a = detect_points(pts, num_threads=1)
    b = detect_points(pts, num_threads=2)
    for name in ("labels", "flags", "angle", "height", "degenerate"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert a.iterations == b.iterations
    assert [d.indices.tolist() for d in a.defects] == [d.indices.tolist() for d in b.defects]


def test_heights_abnormal_only():
    pts, i = with_spike(1.0)
    full = detect_points(pts, radius=5 * STEP)
    part = detect_points(pts, radius=5 * STEP, heights="abnormal")
    assert part.height[i] == full.height[i]
    assert np.isnan(np.delete(part.height, i)).all()
    np.testing.assert_array_equal(part.labels, full.labels)


def test_collinear_points_are_degenerate_not_an_error():
    t = np.linspace(0, 10, 101)
    pts = np.column_stack([t, 0.5 * t, np.zeros_like(t)])
    res = detect_points(pts, radius=0.5)  # >= 4 neighbours even at the ends
    assert res.degenerate.all()
    assert (res.labels == NORMAL).all()
    assert np.isnan(res.angle).all()
    assert res.plane is None


@pytest.mark.parametrize(
    "points, match",
    [
        (np.zeros((0, 3)), "points"),
        (np.zeros((2, 3)), "points"),
        (np.array([[0.0, 0, 0], [1, 0, 0], [np.nan, 0, 0]]), "3 finite"),
        (np.ones((10, 3)), "spacing"),
        # (more than half duplicates is no longer an error: they are merged, SPEC "Duplicate
        # points"; all one point still is)
        (np.vstack([np.ones((6, 3)), np.full((2, 3), np.nan)]), "one point"),
        (np.zeros((5, 2)), "points"),
    ],
)
def test_bad_points(points, match):
    with pytest.raises(ValueError, match=match):
        detect_points(points)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(radius=0.0), "radius"),
        (dict(radius=-1.0), "radius"),
        (dict(radius=np.nan), "radius"),
        (dict(radius=np.inf), "radius"),
        (dict(K=1), "K"),
        (dict(K=9), "K"),
        (dict(K=2.0), "K"),
        (dict(min_step=-0.1), "min_step"),
        (dict(min_step=np.nan), "min_step"),
        (dict(link=0.0), "link"),
        (dict(theta0=0.0), "theta0"),
        (dict(theta0=180.0), "theta0"),
        (dict(scales=()), "scales"),
        (dict(scales=(1, 0)), "scales"),
        (dict(min_directions=5), "min_directions"),
        (dict(min_directions=0), "min_directions"),
        (dict(max_iterations=0), "max_iterations"),
        (dict(heights="some"), "heights"),
        (dict(num_threads=0), "num_threads"),
    ],
)
def test_bad_parameters(kwargs, match):
    with pytest.raises(ValueError, match=match):
        detect_points(patch(n=6), **kwargs)


@pytest.mark.parametrize("a_first", [True, False])
@pytest.mark.parametrize("threads", [1, 2])
def test_equal_distances_in_a_cone_go_to_the_smaller_index(a_first, threads):
    # SPEC "Unorganized clouds": a slot's neighbour is the nearest, then the smallest index. P's
    # +x cone holds A and B at the same distance (mirror images in y) and the -x cone C, so P's
    # angle is the angle APC or BPC, whichever of A and B has the smaller index. A far point
    # fixes the grid origin so that a cell boundary (y = -0.1) separates B (gathered first) from
    # A: the rule is not "first gathered".
    P, A, B, C = [0.0, 0, 0], [1.0, 0.2, 0], [1.0, -0.2, 0], [-1.0, 0.3, 0]
    rest = [[-2.0, 0, 0], [2.0, 0, 0], [-3.0, -2.6, 0]]
    pts = np.array([P, A, B, C] + rest if a_first else [P, B, A, C] + rest)
    res = detect_points(pts, radius=2.5, min_step=0.1, K=2, max_iterations=1,
                        num_threads=threads)
    q = np.array(A if a_first else B)
    c = np.array(C)
    expected = np.degrees(np.arccos(q @ c / np.sqrt((q @ q) * (c @ c))))
    assert res.angle[0] == pytest.approx(expected, abs=1e-9)
    other = np.array(B if a_first else A)
    assert abs(np.degrees(np.arccos(other @ c / np.sqrt((other @ other) * (c @ c))))
               - expected) > 1.0  # the two choices differ: the test can tell them apart
