"""The edge test on unorganized clouds (SPEC "Unorganized clouds: edge test", issue 11): a burr
raised along a cut outline, which the height test misses (its surroundings hold the burr run),
is found; the core equals the reference; labels do not depend on row order, a rigid motion, a
1e5 offset, float32 or the thread count."""

from __future__ import annotations

import numpy as np
import pytest

import miem
from miem import reference as ref

A = miem.ABNORMAL
ON = {"edge_tolerance": 3.0}


def cut_scene(seed: int, n: int = 56, step: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """A tilted plane cut along a line at 20 degrees, a burr run 2 points wide raised 0.12 mm
    on the cut's last points (along 40 % of the line); x / y jittered, rows shuffled. Returns
    the points and the burr mask."""
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[0:n, 0:n]
    x, y = c.ravel() * step, r.ravel() * step
    phi = np.radians(20.0)
    d = (x - 0.6 * n * step) * np.cos(phi) + (y - 0.5 * n * step) * np.sin(phi)
    t = -(x - 0.6 * n * step) * np.sin(phi) + (y - 0.5 * n * step) * np.cos(phi)
    keep = d < 0.0
    burr = keep & (d >= -2.0 * step) & (np.abs(t) < 0.2 * n * step)
    z = 0.05 * x + 0.02 * y + rng.normal(0.0, 0.005, x.size) + 0.12 * burr
    pts = np.column_stack([x, y, z])
    pts[:, :2] += rng.uniform(-0.25 * step, 0.25 * step, (x.size, 2))
    pts, burr = pts[keep], burr[keep]
    order = rng.permutation(len(pts))
    return np.ascontiguousarray(pts[order]), burr[order]


def _same(core: miem.DetectResult, oracle: ref.RefPointsResult) -> None:
    np.testing.assert_array_equal(core.labels, oracle.labels)
    np.testing.assert_array_equal(core.flags, oracle.flags)
    np.testing.assert_allclose(core.height, oracle.height, atol=1e-9, equal_nan=True)
    assert core.iterations == oracle.iterations
    assert core.params["edge_radius"] == pytest.approx(oracle.params["edge_radius"], rel=1e-12)
    assert [d.indices.tolist() for d in core.defects] == [
        d.indices.tolist() for d in oracle.defects]


@pytest.mark.parametrize("seed", [0, 1])
def test_burr_on_a_cut_outline_is_found(seed: int) -> None:
    pts, burr = cut_scene(seed)
    off = miem.detect(pts)
    on = miem.detect(pts, **ON)
    assert off.params["edge_tolerance"] is None and on.params["edge_tolerance"] == 3.0
    found_off = np.mean(off.labels[burr] == A)
    found_on = np.mean(on.labels[burr] == A)
    assert found_on >= 0.8 and found_on > found_off + 0.3, (found_off, found_on)
    # nothing else: every ABNORMAL point is a burr point
    assert not (on.labels[~burr] == A).any()
    assert on.stage_seconds is not None and "edge test" in on.stage_seconds


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("params", [ON, {**ON, "edge_radius": 1.5, "max_iterations": 3},
                                    {**ON, "height_tolerance": None}],
                         ids=["default-radius", "radius-iterations", "no-height-test"])
def test_core_matches_reference(seed: int, params: dict) -> None:
    pts, _ = cut_scene(seed, n=40)
    _same(miem.detect_points(pts, **params), ref.detect_points(pts, **params))


def test_invariances() -> None:
    pts, _ = cut_scene(2)
    base = miem.detect_points(pts, **ON)
    assert (base.labels == A).any()
    perm = np.random.default_rng(5).permutation(len(pts))
    np.testing.assert_array_equal(miem.detect_points(pts[perm], **ON).labels, base.labels[perm])
    ang = np.radians(37.0)
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + np.sin(ang) * kx + (1 - np.cos(ang)) * kx @ kx
    for moved in (pts @ rot.T + [3.0, -7.0, 11.0], pts + 1e5):
        res = miem.detect_points(moved, **ON)
        np.testing.assert_array_equal(res.labels == A, base.labels == A)
    p32 = (pts + 1e3).astype(np.float32)
    _same(miem.detect_points(p32, **ON), ref.detect_points(p32, **ON))
    for nt in (1, 2, 3):
        np.testing.assert_array_equal(miem.detect_points(pts, num_threads=nt, **ON).labels,
                                      base.labels)


@pytest.mark.parametrize("kwargs, name", [
    ({"edge_tolerance": 0.0}, "edge_tolerance"), ({"edge_tolerance": -1.0}, "edge_tolerance"),
    ({"edge_tolerance": float("nan")}, "edge_tolerance"), ({"edge_radius": 0.0}, "edge_radius"),
    ({"edge_tolerance": 3.0, "edge_radius": float("inf")}, "edge_radius"),
])
def test_bad_parameters(kwargs: dict, name: str) -> None:
    pts, _ = cut_scene(0, n=16)
    with pytest.raises(ValueError, match=name):
        miem.detect_points(pts, **kwargs)
    with pytest.raises(ValueError, match=name):
        ref.detect_points(pts, **kwargs)
