"""Grinding targets: geometry against independently computed poses, selection, merging, ordering,
bad transforms. The expected values come from the scan's construction, not from the code."""

from __future__ import annotations

import dataclasses
import itertools
import json

import numpy as np
import pytest

import miem
from miem import _core

STEP = 0.5


def rot(axis: str, deg: float) -> np.ndarray:
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
            "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


def rigid(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Textbook unit-quaternion (w, x, y, z) rotation matrix."""
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def abc_to_matrix(abc: np.ndarray) -> np.ndarray:
    a, b, c = abc
    return rot("z", a) @ rot("y", b) @ rot("x", c)


# A tilted plane z = A x + B y + C in the sensor frame (the sensor looks down -z), with a spike.
A, B, C = 0.3, -0.2, 5.0
SPIKE_CELL, SPIKE_DZ = (20, 24), 2.0
T_SENSOR = rigid(rot("z", 30) @ rot("x", 160), [400.0, -120.0, 650.0])


def tilted_scan(h: int = 44, w: int = 48) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w] * STEP
    grid = np.dstack([x, y, A * x + B * y + C])
    grid[SPIKE_CELL + (2,)] += SPIKE_DZ
    return grid


def plane_normal_sensor() -> np.ndarray:
    n = np.array([-A, -B, 1.0])
    return n / np.linalg.norm(n)


@pytest.fixture(scope="module")
def tilted():
    grid = tilted_scan()
    return grid, miem.detect(grid)


def test_tilted_plane_target_in_base_frame(tilted) -> None:
    grid, res = tilted
    plan = miem.plan_targets(res, grid, T_SENSOR)
    assert len(plan) == 1
    t = plan.targets[0]
    R, tr = T_SENSOR[:3, :3], T_SENSOR[:3, 3]
    spike = grid[SPIKE_CELL]
    np.testing.assert_allclose(t.point, R @ spike + tr, atol=1e-9)
    np.testing.assert_allclose(t.point_scan, spike, atol=1e-12)
    n_base = R @ plane_normal_sensor()
    np.testing.assert_allclose(t.normal, n_base, atol=1e-9)
    np.testing.assert_allclose(t.approach_axis, -n_base, atol=1e-9)
    np.testing.assert_allclose(t.rotation[:, 2], -n_base, atol=1e-9)
    # tool x: the scan direction (sensor y) in the base frame, projected onto the tangent plane
    ref = R @ np.array([0.0, 1.0, 0.0])
    x = ref - ref.dot(n_base) * n_base
    np.testing.assert_allclose(t.rotation[:, 0], x / np.linalg.norm(x), atol=1e-9)
    np.testing.assert_allclose(t.rotation.T @ t.rotation, np.eye(3), atol=1e-12)
    assert np.linalg.det(t.rotation) == pytest.approx(1.0, abs=1e-12)
    # quaternion: unit, w >= 0, the same rotation
    assert np.linalg.norm(t.quaternion) == pytest.approx(1.0, abs=1e-12)
    assert t.quaternion[0] >= 0
    np.testing.assert_allclose(quat_to_matrix(t.quaternion), t.rotation, atol=1e-12)
    np.testing.assert_allclose(abc_to_matrix(t.abc), t.rotation, atol=1e-12)
    # depth = orthogonal height of the spike over the plane; area = the tilted cell
    n_s = plane_normal_sensor()
    assert t.depth == pytest.approx(SPIKE_DZ * n_s[2], abs=1e-9)
    area = STEP * STEP * np.sqrt(1 + A * A + B * B)
    assert t.area == pytest.approx(area, rel=1e-9)
    assert t.volume == pytest.approx(t.depth * area, rel=1e-9)
    assert t.count == 1 and t.defect_ids == (res.defects[0].id,)
    assert t.peak_index == SPIKE_CELL[0] * grid.shape[1] + SPIKE_CELL[1]


def test_standoff_approach_retract_along_normal(tilted) -> None:
    grid, res = tilted
    tool = miem.Tool(standoff=1.5, approach=25.0, retract=40.0)
    t = miem.plan_targets(res, grid, T_SENSOR, tool=tool).targets[0]
    np.testing.assert_allclose(t.position, t.point + 1.5 * t.normal, atol=1e-9)
    np.testing.assert_allclose(t.approach_point, t.position + 25.0 * t.normal, atol=1e-9)
    np.testing.assert_allclose(t.retract_point, t.position + 40.0 * t.normal, atol=1e-9)


def test_toward_sensor_flips_normal_and_x_reference(tilted) -> None:
    grid, res = tilted
    R = T_SENSOR[:3, :3]
    t = miem.plan_targets(res, grid, T_SENSOR, toward_sensor=(0, 0, -1),
                          x_axis=(1.0, 0.0, 0.0)).targets[0]
    n_base = -(R @ plane_normal_sensor())
    np.testing.assert_allclose(t.normal, n_base, atol=1e-9)
    x = np.array([1.0, 0, 0]) - n_base[0] * n_base
    np.testing.assert_allclose(t.rotation[:, 0], x / np.linalg.norm(x), atol=1e-9)


def test_per_profile_transforms(tilted) -> None:
    grid, res = tilted
    h = grid.shape[0]
    stack = np.stack([T_SENSOR @ rigid(rot("z", 0.2 * r) @ rot("x", 0.1 * r), [0, 0.3 * r, 0])
                      for r in range(h)])
    t = miem.plan_targets(res, grid, stack).targets[0]
    r0 = SPIKE_CELL[0]
    np.testing.assert_allclose(t.point, stack[r0, :3, :3] @ grid[SPIKE_CELL] + stack[r0, :3, 3],
                               atol=1e-9)
    np.testing.assert_allclose(t.normal, stack[r0, :3, :3] @ plane_normal_sensor(), atol=1e-9)
    np.testing.assert_allclose(quat_to_matrix(t.quaternion), t.rotation, atol=1e-12)
    # a constant stack is the single transform
    same = miem.plan_targets(res, grid, np.repeat(T_SENSOR[None], h, axis=0)).targets[0]
    one = miem.plan_targets(res, grid, T_SENSOR).targets[0]
    np.testing.assert_allclose(same.position, one.position, atol=1e-12)
    np.testing.assert_allclose(same.rotation, one.rotation, atol=1e-12)
    assert same.area == pytest.approx(one.area, rel=1e-12)


def test_calibration_files(tilted, tmp_path) -> None:
    grid, res = tilted
    js = tmp_path / "cal.json"
    js.write_text(json.dumps({"T_base_sensor": T_SENSOR.tolist()}))
    ym = tmp_path / "cal.yaml"
    ym.write_text("T_base_sensor:\n" + "".join(
        f"  - [{', '.join(repr(float(v)) for v in row)}]\n" for row in T_SENSOR))
    bare = tmp_path / "bare.json"
    bare.write_text(json.dumps(T_SENSOR.tolist()))
    for f in (js, ym, bare):
        np.testing.assert_array_equal(miem.read_transform(f), T_SENSOR)
    a = miem.plan_targets(res, grid, js).targets[0]
    b = miem.plan_targets(res, grid, T_SENSOR).targets[0]
    np.testing.assert_array_equal(a.position, b.position)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"pose": [1, 2, 3]}))
    with pytest.raises(ValueError, match="T_base_sensor.*bad.json.*key"):
        miem.read_transform(bad)
    bad.write_text("{not json")
    with pytest.raises(ValueError, match="T_base_sensor.*JSON"):
        miem.read_transform(bad)
    with pytest.raises(ValueError, match="T_base_sensor.*cannot read"):
        miem.read_transform(tmp_path / "missing.json")


@pytest.mark.parametrize("T, match", [
    (np.diag([2.0, 1.0, 1.0, 1.0]), "T_base_sensor: .*not orthonormal"),
    (rigid(np.array([[1, 0.1, 0], [0, 1, 0], [0, 0, 1]]), [0, 0, 0]), "not orthonormal"),
    (np.diag([-1.0, 1.0, 1.0, 1.0]), "T_base_sensor: .*reflection"),
    (np.where(np.eye(4) == 1, np.nan, 0.0), "T_base_sensor: .*NaN"),
    (np.eye(3), r"T_base_sensor: expected shape \(4, 4\)"),
    (np.eye(4)[:3], r"T_base_sensor: expected shape"),
    (np.zeros((5, 4, 4)) + np.eye(4), r"T_base_sensor: expected shape .*one per profile"),
    (np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1.0]]), "last row"),
    ("not a file.json", "T_base_sensor.*cannot read"),
    ([[1, 2], [3]], "T_base_sensor"),
])
def test_bad_transforms(tilted, T, match) -> None:
    grid, res = tilted
    with pytest.raises(ValueError, match=match):
        miem.plan_targets(res, grid, T)


def test_bad_arguments(tilted) -> None:
    grid, res = tilted
    cases = [
        (dict(at="middle"), "at:"), (dict(kinds=("burr",)), "kinds:"), (dict(kinds=()), "kinds:"),
        (dict(min_height=-1), "min_height"), (dict(min_count=0), "min_count"),
        (dict(tool=miem.Tool(radius=-1)), "tool.radius"), (dict(tool=3.0), "tool:"),
        (dict(tool=miem.Tool(standoff=np.nan)), "tool.standoff"),
        (dict(roi=np.zeros((3, 3), bool)), "roi:"), (dict(x_axis=(0, 0, 0)), "x_axis"),
        (dict(x_axis="tool"), "x_axis"), (dict(toward_sensor=(0, 0)), "toward_sensor"),
        (dict(start=np.eye(3)), "start:"), (dict(order=1), "order:"),
        (dict(edge_clearance=np.inf), "edge_clearance"),
    ]
    for kw, match in cases:
        with pytest.raises(ValueError, match=match):
            miem.plan_targets(res, grid, **kw)
    with pytest.raises(ValueError, match="scan:"):
        miem.plan_targets(res, grid[:-1])
    with pytest.raises(ValueError, match="result:"):
        miem.plan_targets(grid, grid)


def test_inputs_unchanged(tilted) -> None:
    grid, res = tilted
    g0, l0, h0, T0 = grid.copy(), res.labels.copy(), res.height.copy(), T_SENSOR.copy()
    miem.plan_targets(res, grid, T_SENSOR, tool=miem.Tool(radius=2.0))
    np.testing.assert_array_equal(grid, g0)
    np.testing.assert_array_equal(res.labels, l0)
    np.testing.assert_array_equal(res.height, h0)
    np.testing.assert_array_equal(T_SENSOR, T0)


def test_float32_scan_same_targets(tilted) -> None:
    grid, _ = tilted
    g32 = grid.astype(np.float32)
    res = miem.detect(g32)
    t = miem.plan_targets(res, g32, T_SENSOR).targets[0]
    np.testing.assert_allclose(t.point, T_SENSOR[:3, :3] @ g32[SPIKE_CELL].astype(np.float64)
                               + T_SENSOR[:3, 3], atol=1e-9)


# ---------------------------------------------------------------------------------------------
# hand-made selection, merging and ordering cases on a flat plate (1 mm cells, z = 0)


def plate(spikes: dict, h: int = 40, w: int = 60) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    grid = np.dstack([x, y, np.zeros_like(x)])
    for (r, c), dz in spikes.items():
        grid[r, c, 2] = dz
    return grid


def hand_result(grid: np.ndarray, groups: list) -> miem.DetectResult:
    """A detection result made by hand on a flat plate (z = 0 is the surface): each group of
    cells is one ABNORMAL defect, heights are the z values."""
    h, w, _ = grid.shape
    labels = np.zeros((h, w), np.uint8)
    defects = []
    for cells in groups:
        idx = np.array(sorted(r * w + c for r, c in cells), dtype=np.int64)
        labels.reshape(-1)[idx] = miem.ABNORMAL
        z = grid.reshape(-1, 3)[idx, 2]
        peak = float(z[np.argmax(np.abs(z))])
        defects.append(miem.Defect(
            id=0, indices=idx, cells=np.stack([idx // w, idx % w], 1), count=idx.size,
            centroid=grid.reshape(-1, 3)[idx].mean(0), normal=np.array([0.0, 0.0, 1.0]),
            peak_height=peak, mean_height=float(z.mean()), extent=0.0,
            kind="protrusion" if peak > 0 else "pit"))
    defects.sort(key=lambda d: -abs(d.peak_height))
    defects = [dataclasses.replace(d, id=i) for i, d in enumerate(defects)]
    return miem.DetectResult(labels=labels, flags=np.zeros_like(labels),
                             angle=np.full((h, w), np.nan), height=grid[..., 2].copy(),
                             plane=None, iterations=1, defects=defects)


def test_pits_and_isolated_not_targeted_by_default() -> None:
    grid = plate({(10, 10): 2.0, (20, 40): -2.0})
    res = miem.detect(grid)
    assert sorted(d.kind for d in res.defects) == ["pit", "protrusion"]
    plan = miem.plan_targets(res, grid)
    assert len(plan) == 1 and plan.targets[0].depth == pytest.approx(2.0)
    assert plan.rejected["kind"] == 1 and plan.defects_in == 2 and plan.defects_used == 1
    both = miem.plan_targets(res, grid, kinds=("protrusion", "pit"))
    assert sorted(t.depth for t in both.targets) == pytest.approx([-2.0, 2.0])
    pit = [t for t in both.targets if t.depth < 0][0]
    np.testing.assert_allclose(pit.point, [40.0, 20.0, -2.0])
    np.testing.assert_allclose(pit.normal, [0, 0, 1])  # toward the scanner, not into the pit
    assert pit.volume == pytest.approx(2.0)  # 2 mm below the surface over a 1 mm^2 cell
    iso = dataclasses.replace(res, defects=[dataclasses.replace(d, kind="isolated")
                                            for d in res.defects])
    assert len(miem.plan_targets(iso, grid)) == 0
    assert len(miem.plan_targets(iso, grid, kinds="isolated")) == 2


def test_min_height_count_area() -> None:
    cluster = [(25, 20), (25, 21), (26, 20)]
    grid = plate({(10, 10): 0.5, (10, 30): 2.0, (25, 20): 1.5, (25, 21): 1.2, (26, 20): 1.0})
    res = hand_result(grid, [[(10, 10)], [(10, 30)], cluster])
    plan = miem.plan_targets(res, grid, min_height=1.0)
    assert sorted(t.count for t in plan.targets) == [1, 3] and plan.rejected["height"] == 1
    plan = miem.plan_targets(res, grid, min_count=2)
    assert [t.count for t in plan.targets] == [3] and plan.rejected["size"] == 2
    plan = miem.plan_targets(res, grid, min_area=2.5)  # 1 mm^2 per cell of the flat plate
    assert [t.count for t in plan.targets] == [3]
    assert plan.targets[0].area == pytest.approx(3.0)
    assert plan.targets[0].volume == pytest.approx(1.5 + 1.2 + 1.0)
    np.testing.assert_allclose(plan.targets[0].point, [20.0, 25.0, 1.5])


def test_region_of_interest_mask_and_polygon() -> None:
    grid = plate({(10, 10): 2.0, (10, 40): 2.4})
    res = miem.detect(grid)
    mask = np.zeros(res.labels.shape, bool)
    mask[:, :25] = True
    plan = miem.plan_targets(res, grid, roi=mask)
    assert len(plan) == 1 and plan.targets[0].point[0] == 10.0 and plan.rejected["roi"] == 1
    poly = np.array([[30.0, 0.0], [59.0, 0.0], [59.0, 39.0], [30.0, 39.0]])
    plan = miem.plan_targets(res, grid, roi=poly)
    assert len(plan) == 1 and plan.targets[0].point[0] == 40.0


def test_edge_points_never_targeted() -> None:
    grid = plate({(10, 10): 2.0, (10, 40): 2.4})
    res = miem.detect(grid)
    labels = res.labels.copy()
    labels[10, 42] = miem.EDGE  # a feature edge 2 mm (and 2.4 mm down) from the second spike
    edged = dataclasses.replace(res, labels=labels)
    plan = miem.plan_targets(edged, grid, edge_clearance=3.2)
    assert [t.point[0] for t in plan.targets] == [10.0] and plan.rejected["edge"] == 1
    assert len(miem.plan_targets(edged, grid, edge_clearance=3.1)) == 2  # sqrt(4 + 5.76) = 3.12
    labels = res.labels.copy()
    labels[10, 40] = miem.EDGE  # the defect's only point relabelled EDGE
    plan = miem.plan_targets(dataclasses.replace(res, labels=labels), grid)
    assert [t.point[0] for t in plan.targets] == [10.0] and plan.rejected["size"] == 1


def test_merge_within_tool_radius_single_linkage() -> None:
    # three spikes 3 mm apart in a row (a chain: the ends are 6 mm apart), one far away
    spikes = {(10, 10): 1.0, (10, 13): 1.3, (10, 16): 1.1, (30, 45): 0.8}
    grid = plate(spikes)
    res = hand_result(grid, [[k] for k in spikes])
    apart = miem.plan_targets(res, grid, tool=miem.Tool(radius=3.0))  # 3.0 is not closer
    assert len(apart) == 4
    plan = miem.plan_targets(res, grid, tool=miem.Tool(radius=3.1))  # 3.015 and 3.007 apart
    assert len(plan) == 2
    chain = max(plan.targets, key=lambda t: t.count)
    ids = {d.id for d in res.defects if d.cells[0, 0] == 10}
    assert chain.count == 3 and set(chain.defect_ids) == ids
    assert list(chain.defect_ids) == sorted(chain.defect_ids)
    np.testing.assert_allclose(chain.point, [13.0, 10.0, 1.3])  # the deepest member's peak
    assert chain.depth == pytest.approx(1.3)
    assert chain.area == pytest.approx(3.0) and chain.volume == pytest.approx(3.4)
    cen = miem.plan_targets(res, grid, tool=miem.Tool(radius=3.1), at="centroid")
    chain = max(cen.targets, key=lambda t: t.count)
    np.testing.assert_allclose(chain.point, [13.0, 10.0, 3.4 / 3])


def _length(pts: np.ndarray, start=None) -> float:
    if start is not None:
        pts = np.vstack([start, pts])
    return float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())


def test_order_nearest_neighbour_then_two_opt() -> None:
    # From (30, 20) nearest neighbour visits (30, 27), (34, 34), (22, 25), (46, 20): 54.6 mm with
    # a crossing; 2-opt uncrosses it to (22, 25), (30, 27), (34, 34), (46, 20): 44.2 mm, which
    # is the shortest of the 24 orders.
    xy = [(22, 25), (46, 20), (34, 34), (30, 27)]
    grid = plate({(y, x): 2.0 for x, y in xy})
    res = miem.detect(grid)
    start = np.array([30.0, 20.0, 2.0])
    plan = miem.plan_targets(res, grid, start=start)
    want = np.array([[22, 25, 2], [30, 27, 2], [34, 34, 2], [46, 20, 2]], dtype=float)
    np.testing.assert_array_equal(np.array([t.point for t in plan.targets]), want)
    assert plan.path_length == pytest.approx(_length(want, start))
    nn = np.array([[30, 27, 2], [34, 34, 2], [22, 25, 2], [46, 20, 2]], dtype=float)
    assert _length(nn, start) > plan.path_length + 10
    pts = np.array([[x, y, 2.0] for x, y in xy])
    best = min(_length(pts[list(p)], start) for p in itertools.permutations(range(4)))
    assert plan.path_length == pytest.approx(best)
    assert [t.index for t in plan.targets] == [0, 1, 2, 3]
    pose = np.eye(4)
    pose[:3, 3] = start
    again = miem.plan_targets(res, grid, start=pose)
    np.testing.assert_array_equal(np.array([t.point for t in again.targets]), want)
    unordered = miem.plan_targets(res, grid, start=start, order=False)
    assert len(unordered) == 4 and [t.depth for t in unordered.targets] == [2.0] * 4
    # no start: the path begins at the deepest target
    grid[25, 22, 2] = 2.5  # not deeper than the others by much, but the deepest
    res = miem.detect(grid)
    first = miem.plan_targets(res, grid).targets[0]
    np.testing.assert_array_equal(first.point, [22, 25, 2.5])


def test_order_is_two_opt_optimal_and_beats_nearest_neighbour() -> None:
    rng = np.random.default_rng(3)
    for trial in range(20):
        pts = rng.uniform(0, 100, size=(int(rng.integers(2, 9)), 3))
        start = rng.uniform(0, 100, size=3)
        order = _core.order_path(list(pts), start)
        assert sorted(order) == list(range(len(pts)))
        # independent nearest neighbour tour
        left, cur, nn = list(range(len(pts))), start, []
        while left:
            k = min(left, key=lambda i: np.linalg.norm(pts[i] - cur))
            nn.append(k)
            left.remove(k)
            cur = pts[k]
        got = _length(pts[order], start)
        assert got <= _length(pts[nn], start) + 1e-9
        # no segment reversal shortens it (2-opt local optimum), and brute force bounds it
        seq = [start] + [pts[i] for i in order]
        for i, j in itertools.combinations(range(1, len(seq)), 2):
            rev = seq[:i] + seq[i:j + 1][::-1] + seq[j + 1:]
            assert _length(np.array(rev)) >= got - 1e-9
        best = min(_length(pts[list(p)], start) for p in itertools.permutations(range(len(pts))))
        assert got >= best - 1e-9


def test_abc_and_quaternion_round_trip() -> None:
    rng = np.random.default_rng(7)
    mats = [abc_to_matrix(v) for v in rng.uniform(-180, 180, size=(50, 3))]
    mats += [abc_to_matrix((40.0, 90.0, 10.0)), abc_to_matrix((0.0, -90.0, 25.0)),
             rot("x", 180), rot("y", 180), rot("z", 180), np.eye(3)]
    for R in mats:
        abc = np.array(_core.abc_from_rotation(R))
        np.testing.assert_allclose(abc_to_matrix(abc), R, atol=1e-9)
        assert -90.0 <= abc[1] <= 90.0
        q = np.array(_core.quaternion_from_rotation(R))
        assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-12) and q[0] >= 0
        np.testing.assert_allclose(quat_to_matrix(q), R, atol=1e-9)


def test_cloud_result() -> None:
    grid = plate({(10, 10): 2.0, (20, 30): 2.5}, h=30, w=40)
    pts = grid.reshape(-1, 3)
    res = miem.detect_points(pts)
    plan = miem.plan_targets(res, pts, T_SENSOR)
    got = sorted((t.point_scan[0], t.point_scan[1]) for t in plan.targets)
    assert got == [(10.0, 10.0), (30.0, 20.0)]
    for t in plan.targets:
        np.testing.assert_allclose(t.point, T_SENSOR[:3, :3] @ t.point_scan + T_SENSOR[:3, 3],
                                   atol=1e-9)
        np.testing.assert_allclose(t.normal, T_SENSOR[:3, :3] @ [0, 0, 1], atol=1e-9)
        assert t.area == pytest.approx(res.params["spacing"] ** 2)
    with pytest.raises(ValueError, match="T_base_sensor.*organized"):
        miem.plan_targets(res, pts, np.repeat(T_SENSOR[None], 2, axis=0))


def test_default_approach_is_20_mm_in_the_scan_units(tilted) -> None:
    grid, res = tilted
    for units, dist in (("mm", 20.0), ("m", 0.02), ("cm", 2.0)):
        t = miem.plan_targets(res, grid, units=units).targets[0]
        np.testing.assert_allclose(t.approach_point - t.position, dist * t.normal, atol=1e-12)
        np.testing.assert_allclose(t.retract_point - t.position, dist * t.normal, atol=1e-12)
    with pytest.raises(ValueError, match="tool.approach"):
        miem.plan_targets(res, grid, units="furlong")
    t = miem.plan_targets(res, grid, units="furlong", tool=miem.Tool(approach=1.0, retract=2.0))
    np.testing.assert_allclose(t.targets[0].retract_point - t.targets[0].position,
                               2.0 * t.targets[0].normal, atol=1e-12)
