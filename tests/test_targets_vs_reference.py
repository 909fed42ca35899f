"""miem.plan_targets (C++ core) against miem.reference_targets (NumPy, from SPEC.md) on random
scans: random surfaces, spikes, pits, dropouts, transforms (single and per profile), options."""

from __future__ import annotations

import numpy as np
import pytest

import miem
from miem import reference_targets as ref


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def random_scan(rng: np.random.Generator) -> np.ndarray:
    h, w = int(rng.integers(24, 48)), int(rng.integers(24, 48))
    y, x = np.mgrid[0:h, 0:w] * 0.5
    a, b = rng.uniform(-0.4, 0.4, size=2)
    z = a * x + b * y + 0.3 * np.sin(x / 4) + rng.normal(0, 0.002, size=x.shape)
    grid = np.dstack([x, y, z])
    for _ in range(int(rng.integers(3, 12))):
        r, c = int(rng.integers(2, h - 2)), int(rng.integers(2, w - 2))
        grid[r, c, 2] += rng.choice([-1, 1]) * rng.uniform(1.0, 3.0)
        if rng.random() < 0.4:
            grid[r, c + 1, 2] += rng.uniform(1.0, 2.0)
    grid[rng.random(size=(h, w)) < 0.02] = np.nan
    return grid


def axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues' rotation formula."""
    k = axis / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def transforms(rng: np.random.Generator, h: int) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = random_rotation(rng), rng.uniform(-500, 500, size=3)
    if rng.random() < 0.5:
        return T
    # one transform per profile: the sensor wobbles a little and moves along from row to row
    stack = np.repeat(T[None], h, axis=0)
    axis = rng.normal(size=3)
    for r in range(h):
        stack[r, :3, :3] = T[:3, :3] @ axis_angle(axis, 0.004 * r)
        stack[r, :3, 3] += [0.0, 0.1 * r, 0.0]
    return stack


@pytest.mark.parametrize("seed", range(12))
def test_core_matches_reference(seed: int) -> None:
    rng = np.random.default_rng(seed)
    grid = random_scan(rng)
    res = miem.detect(grid, scales=(1, 2))
    T = transforms(rng, grid.shape[0])
    opts = dict(
        at=str(rng.choice(["peak", "centroid"])),
        kinds=("protrusion", "pit") if rng.random() < 0.5 else ("protrusion",),
        min_height=float(rng.choice([0.0, 0.8])), min_count=int(rng.choice([1, 2])),
        edge_clearance=float(rng.choice([0.0, 1.0])),
    )
    radius = float(rng.choice([0.0, 2.0, 6.0]))
    start = rng.uniform(-500, 500, size=3) if rng.random() < 0.5 else None
    x_axis = rng.normal(size=3) if rng.random() < 0.3 else None
    tool = miem.Tool(radius=radius, standoff=0.5, approach=10.0, retract=12.0)
    core = miem.plan_targets(res, grid, T, tool=tool, start=start,
                             x_axis="scan" if x_axis is None else x_axis, **opts)
    oracle = ref.plan_targets(grid, res.labels, res.height, res.defects, T, tool_radius=radius,
                              standoff=0.5, approach=10.0, retract=12.0, start=start,
                              x_axis=x_axis, **opts)
    assert core.rejected == oracle["rejected"]
    assert core.defects_used == oracle["defects_used"]
    assert len(core.targets) == len(oracle["targets"])
    assert core.path_length == pytest.approx(oracle["path_length"], rel=1e-9, abs=1e-9)
    for t, o in zip(core.targets, oracle["targets"]):
        assert t.defect_ids == o["defect_ids"] and t.count == o["count"]
        assert t.peak_index == o["peak_index"]
        for name in ("point", "point_scan", "normal", "position", "approach_point",
                     "retract_point", "rotation", "quaternion"):
            np.testing.assert_allclose(getattr(t, name), o[name], atol=1e-8, err_msg=name)
        np.testing.assert_allclose(t.abc, o["abc"], atol=1e-7)
        assert t.depth == pytest.approx(o["depth"], abs=1e-12)
        assert t.area == pytest.approx(o["area"], rel=1e-9, abs=1e-12)
        assert t.volume == pytest.approx(o["volume"], rel=1e-9, abs=1e-12)


def test_roi_and_cloud_match_reference() -> None:
    rng = np.random.default_rng(99)
    grid = random_scan(rng)
    res = miem.detect(grid)
    poly = np.array([[2.0, 2.0], [15.0, 1.0], [12.0, 11.0], [3.0, 9.0]])
    mask = np.zeros(res.labels.shape, bool)
    mask[::2] = True
    for kw, rkw in ((dict(roi=poly), dict(roi_polygon=poly)),
                    (dict(roi=mask), dict(roi_mask=mask))):
        core = miem.plan_targets(res, grid, kinds=("protrusion", "pit"), **kw)
        oracle = ref.plan_targets(grid, res.labels, res.height, res.defects, np.eye(4),
                                  kinds=("protrusion", "pit"), **rkw)
        assert core.rejected == oracle["rejected"]
        assert [t.defect_ids for t in core.targets] == [o["defect_ids"] for o in oracle["targets"]]
    pts = grid.reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    cres = miem.detect_points(pts)
    core = miem.plan_targets(cres, pts, tool=miem.Tool(radius=3.0))
    oracle = ref.plan_targets(pts, cres.labels, cres.height, cres.defects, np.eye(4),
                              tool_radius=3.0, point_area=cres.params["spacing"] ** 2)
    assert [t.defect_ids for t in core.targets] == [o["defect_ids"] for o in oracle["targets"]]
    for t, o in zip(core.targets, oracle["targets"]):
        np.testing.assert_allclose(t.position, o["position"], atol=1e-9)
        assert t.area == pytest.approx(o["area"])
