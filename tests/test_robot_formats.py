"""Robot file writers: each file is parsed back and compared with the plan's poses; KUKA angles
and ABB quaternions are turned back into rotation matrices independently."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

import miem
from miem import robot_formats as rf

# the geometry helpers of test_targets.py (tests run with --import-mode=importlib)
_spec = importlib.util.spec_from_file_location("_t", Path(__file__).with_name("test_targets.py"))
_t = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_t)
T_SENSOR, abc_to_matrix, plate, quat_to_matrix = _t.T_SENSOR, _t.abc_to_matrix, _t.plate, _t.quat_to_matrix


@pytest.fixture(scope="module")
def plan() -> miem.TargetPlan:
    grid = plate({(10, 10): 2.0, (12, 30): 2.5, (30, 45): 3.0, (25, 8): -2.0})
    res = miem.detect(grid)
    return miem.plan_targets(res, grid, T_SENSOR, kinds=("protrusion", "pit"),
                             tool=miem.Tool(standoff=0.5, approach=15.0, retract=25.0),
                             start=T_SENSOR[:3, 3])


def test_json_round_trip(plan, tmp_path) -> None:
    (f,) = rf.write(plan, tmp_path / "plan.json")
    doc = json.loads(f.read_text())
    assert doc["units"] == "mm" and doc["frame"] == "base" and len(doc["targets"]) == 4
    for t, d in zip(plan.targets, doc["targets"]):
        np.testing.assert_array_equal(d["position"], t.position)
        np.testing.assert_array_equal(d["quaternion"], t.quaternion)
        np.testing.assert_array_equal(d["rotation"], t.rotation)
        np.testing.assert_array_equal(d["approach_point"], t.approach_point)
        assert d["depth"] == t.depth and tuple(d["defect_ids"]) == t.defect_ids
    assert doc["path_length"] == plan.path_length


def test_csv_round_trip(plan, tmp_path) -> None:
    (f,) = rf.write(plan, tmp_path / "plan.csv")
    header, rows = rf.parse_csv(f.read_text())
    assert header["units"] == "mm" and header["frame"] == "base"
    assert len(rows) == len(plan.targets)
    for t, r in zip(plan.targets, rows):
        np.testing.assert_array_equal([r["x"], r["y"], r["z"]], t.position)
        np.testing.assert_array_equal([r["qw"], r["qx"], r["qy"], r["qz"]], t.quaternion)
        np.testing.assert_array_equal([r["a"], r["b"], r["c"]], t.abc)
        np.testing.assert_array_equal([r["nx"], r["ny"], r["nz"]], t.normal)
        assert r["depth"] == t.depth and r["defect_ids"] == t.defect_ids
        assert r["index"] == t.index and r["count"] == t.count


@pytest.mark.parametrize("fmt, name", [("ros", "poses.yaml"), ("ros-json", "poses.json")])
def test_ros_pose_array_round_trip(plan, tmp_path, fmt, name) -> None:
    (f,) = rf.write(plan, tmp_path / name, format=fmt, frame_id="base_link",
                     with_approach=True)
    text = f.read_text()
    msg = yaml.safe_load(text) if fmt == "ros" else json.loads(text)
    assert msg["header"]["frame_id"] == "base_link"
    poses = msg["poses"]
    assert len(poses) == 3 * len(plan.targets)
    for k, t in enumerate(plan.targets):
        for j, p in enumerate((t.approach_point, t.position, t.retract_point)):
            pose = poses[3 * k + j]
            got = np.array([pose["position"][a] for a in "xyz"])
            np.testing.assert_allclose(got, p / 1000.0, rtol=1e-15, atol=1e-15)  # metres
            o = pose["orientation"]
            q = np.array([o["w"], o["x"], o["y"], o["z"]])
            np.testing.assert_allclose(quat_to_matrix(q), t.rotation, atol=1e-12)
    only = rf.to_pose_array(plan)
    assert len(only["poses"]) == len(plan.targets) and only["header"]["frame_id"] == "base"


def test_rapid_module_round_trip(plan, tmp_path) -> None:
    (f,) = rf.write(plan, tmp_path / "grind.mod", tool="tGrinder", wobj="wobjPart")
    text = f.read_text()
    assert text.startswith("MODULE MiemTargets") and "ENDMODULE" in text
    assert "ConfL\\Off;" in text and "tGrinder\\WObj:=wobjPart;" in text
    targets, moves = rf.parse_rapid(text)
    n = len(plan.targets)
    assert len(targets) == 3 * n
    assert moves == [f"{tag}{k}" for k in range(1, n + 1) for tag in ("pA", "pT", "pR")]
    for t in plan.targets:
        k = t.index + 1
        for tag, p in (("pA", t.approach_point), ("pT", t.position), ("pR", t.retract_point)):
            rt = targets[f"{tag}{k}"]
            np.testing.assert_allclose(rt["pos"], p, atol=5e-5)  # mm, 4 decimals
            assert abs(np.linalg.norm(rt["quat"]) - 1) < 1e-7  # RAPID needs a unit quaternion
            np.testing.assert_allclose(quat_to_matrix(rt["quat"]), t.rotation, atol=1e-7)
            assert rt["conf"] == (0, 0, 0, 0)
    with pytest.raises(ValueError, match="tool:"):
        rf.to_rapid(plan, tool="my tool")


def test_krl_pair_round_trip(plan, tmp_path) -> None:
    src_path, dat_path = rf.write(plan, tmp_path / "grind.src")
    assert dat_path.name == "grind.dat"
    with pytest.raises(ValueError, match="name: KRL needs"):
        rf.write(plan, tmp_path / "grind.src", name="other")
    with pytest.raises(ValueError, match="name:"):
        rf.write(plan, tmp_path / "9 lives.src")
    src, dat = src_path.read_text(), dat_path.read_text()
    assert "DEF grind( )" in src and "DEFDAT grind" in dat and src.rstrip().endswith("END")
    points, moves = rf.parse_krl(src, dat)
    n = len(plan.targets)
    assert moves == [f"{tag}{k}" for k in range(1, n + 1) for tag in ("XA", "XT", "XR")]
    for t in plan.targets:
        k = t.index + 1
        for tag, p in (("XA", t.approach_point), ("XT", t.position), ("XR", t.retract_point)):
            e6 = points[f"{tag}{k}"]
            np.testing.assert_allclose([e6["X"], e6["Y"], e6["Z"]], p, atol=5e-5)
            abc = np.array([e6["A"], e6["B"], e6["C"]])
            np.testing.assert_allclose(abc, t.abc, atol=5e-6)
            np.testing.assert_allclose(abc_to_matrix(abc), t.rotation, atol=1e-6)


def test_units_and_formats(plan, tmp_path) -> None:
    metres = miem.TargetPlan(**{**plan.__dict__, "units": "m"})
    pa = rf.to_pose_array(metres)
    np.testing.assert_allclose(pa["poses"][0]["position"]["x"], plan.targets[0].position[0])
    targets, _ = rf.parse_rapid(rf.to_rapid(metres))
    np.testing.assert_allclose(targets["pT1"]["pos"], plan.targets[0].position * 1000, atol=1e-3)
    odd = miem.TargetPlan(**{**plan.__dict__, "units": "furlong"})
    with pytest.raises(ValueError, match="units:"):
        rf.to_rapid(odd)
    with pytest.raises(ValueError, match="format:"):
        rf.write(plan, tmp_path / "plan.txt")
    with pytest.raises(ValueError, match="format:"):
        rf.write(plan, tmp_path / "plan.txt", format="fanuc")
    empty = miem.TargetPlan(**{**plan.__dict__, "targets": []})
    assert rf.parse_rapid(rf.to_rapid(empty)) == ({}, [])
    assert rf.parse_csv(rf.to_csv(empty))[1] == []
