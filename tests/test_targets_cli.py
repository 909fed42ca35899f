"""``miem plan``: files written for each format, calibration errors, the real scan."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import miem
from miem import io as mio
from miem import robot_formats as rf
from miem.cli import main

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "second_source.pcd"
T = [[0.0, -1.0, 0.0, 850.0], [1.0, 0.0, 0.0, -120.0], [0.0, 0.0, 1.0, 310.0], [0, 0, 0, 1.0]]


@pytest.fixture()
def scan(tmp_path: Path) -> tuple[Path, Path]:
    y, x = np.mgrid[0:40, 0:60].astype(np.float64)
    grid = np.dstack([x, y, np.zeros_like(x)])
    grid[10, 10, 2], grid[30, 45, 2], grid[20, 30, 2] = 2.0, 3.0, -2.0
    path = tmp_path / "plate.npy"
    np.save(path, grid)
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps({"T_base_sensor": T}))
    return path, cal


def test_plan_rapid_and_krl(scan, tmp_path, capsys) -> None:
    path, cal = scan
    out = tmp_path / "plate.mod"
    assert main(["plan", str(path), "--transform", str(cal), "--format", "rapid", "-o",
                 str(out), "--approach", "30"]) == 0
    text = capsys.readouterr().out
    assert "3 defects -> 2 targets" in text and "1 kind" in text
    targets, moves = rf.parse_rapid(out.read_text())
    pos = sorted(tuple(np.round(v["pos"], 4)) for k, v in targets.items() if k.startswith("pT"))
    Tm = np.array(T)
    want = sorted(tuple(np.round(Tm[:3, :3] @ p + Tm[:3, 3], 4))
                  for p in ([10.0, 10.0, 2.0], [45.0, 30.0, 3.0]))
    assert pos == want
    np.testing.assert_allclose(targets["pA1"]["pos"] - targets["pT1"]["pos"], [0, 0, 30],
                               atol=1e-4)
    src = tmp_path / "plate.src"
    assert main(["plan", str(path), "--transform", str(cal), "--format", "krl", "-o",
                 str(src), "--kinds", "protrusion", "pit"]) == 0
    points, lin = rf.parse_krl(src.read_text(), src.with_suffix(".dat").read_text())
    assert len(lin) == 9 and len(points) == 9


@pytest.mark.parametrize("fmt", ["json", "csv", "ros", "ros-json"])
def test_plan_formats(scan, tmp_path, monkeypatch, fmt) -> None:
    path, cal = scan
    monkeypatch.chdir(tmp_path)
    assert main(["plan", str(path), "--transform", str(cal), "--format", fmt]) == 0
    suffix = {"json": ".targets.json", "csv": ".targets.csv", "ros": ".poses.yaml",
              "ros-json": ".poses.json"}[fmt]
    assert (tmp_path / ("plate" + suffix)).stat().st_size > 0


def test_plan_bad_transform_and_roi(scan, tmp_path, capsys) -> None:
    path, _ = scan
    bad = tmp_path / "scaled.json"
    bad.write_text(json.dumps(np.diag([2.0, 2.0, 2.0, 1.0]).tolist()))
    assert main(["plan", str(path), "--transform", str(bad)]) == 1
    err = capsys.readouterr().err
    assert "T_base_sensor" in err and "not orthonormal" in err
    assert main(["plan", str(path), "--roi", "0", "0", "1"]) == 2


def test_plan_plot(scan, tmp_path) -> None:
    pytest.importorskip("matplotlib")
    path, cal = scan
    png = tmp_path / "plan.png"
    assert main(["plan", str(path), "--transform", str(cal), "-o", str(tmp_path / "p.json"),
                 "--plot", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.skipif(not DATA.exists(), reason="shared data (../shared/data/real) not present")
def test_real_scan_targets(tmp_path) -> None:
    out = tmp_path / "ss.json"
    assert main(["plan", str(DATA), "--preset", "recommended", "--tool-radius", "3",
                 "--min-height", "0.2", "-o", str(out)]) == 0
    doc = json.loads(out.read_text())
    data = mio.read(DATA)
    grid = mio.grid_from_scanlines(data.points)
    res = miem.detect(grid, preset="recommended")
    prot = [d for d in res.defects if d.kind == "protrusion" and d.peak_height >= 0.2]
    assert 0 < len(doc["targets"]) <= len(prot)
    used = sorted(i for t in doc["targets"] for i in t["defect_ids"])
    assert used == sorted(d.id for d in prot)  # every selected defect is in exactly one target
    for t in doc["targets"]:
        assert np.isclose(np.linalg.norm(t["normal"]), 1.0) and t["depth"] >= 0.2
        p = np.array(t["point"])  # identity transform: the anchor is a measured point
        assert np.linalg.norm(data.points.astype(np.float64) - p, axis=1).min() == 0.0
