"""``miem compare SCAN REFERENCE``: outputs, the transform file round trip, errors, and the real
scan second_source.pcd against its golden sample target.pcd (skipped without ../shared)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

import miem
import miem.io
from miem.cli import main

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_compare import MOTION, make_reference, make_scan, rotation_error_deg  # noqa: E402

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"


@pytest.fixture()
def files(tmp_path):
    scan, height = make_scan(step=0.25)
    scan_path = tmp_path / "part.npy"
    np.save(scan_path, scan)
    ref_path = tmp_path / "golden.npy"
    np.save(ref_path, make_reference(0.15))
    tf = tmp_path / "pose.txt"
    np.savetxt(tf, MOTION)
    return tmp_path, scan_path, ref_path, tf, scan, height


def test_cli_compare_writes_reports(files, capsys) -> None:
    pytest.importorskip("open3d")
    tmp, scan_path, ref_path, tf, scan, height = files
    out = tmp / "out"
    rc = main(["compare", str(scan_path), str(ref_path), "-o", str(out), "--init-transform",
               str(tf), "--no-plot"])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "registration: given + " in text and "excess" in text
    doc = json.loads((out / "part.compare.json").read_text())
    t = np.array(doc["transform"])
    assert rotation_error_deg(t, MOTION) < 0.05
    np.testing.assert_allclose(np.loadtxt(out / "part.transform.txt"), t, atol=1e-9)
    assert doc["counts"]["EXCESS"] > 0 and doc["counts"]["MISSING"] == 0
    assert sum(doc["counts"].values()) == scan.shape[0] * scan.shape[1]
    cloud = miem.io.read(out / "part.deviation.npy")
    assert set(cloud.fields) >= {"deviation", "compare_label"}
    excess = cloud.fields["compare_label"].reshape(-1) == 1
    assert np.all(height.reshape(-1)[excess] > 0.1)  # excess points are on the burrs
    rows = (out / "part.compare.csv").read_text().splitlines()
    assert rows[0].startswith("id,kind,count,peak_deviation") and len(rows) == len(
        doc["defects"]) + 1
    assert doc["agreement"] is not None


def test_cli_compare_plot_and_no_register(files, capsys) -> None:
    pytest.importorskip("matplotlib")
    tmp, scan_path, ref_path, tf, scan, height = files
    out = tmp / "out"
    rc = main(["compare", str(scan_path), str(ref_path), "-o", str(out), "--init-transform",
               str(tf), "--no-register", "--no-agreement", "--tolerance", "0.3"])
    assert rc == 0
    assert "registration: none" in capsys.readouterr().out
    png = (out / "part.deviation.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    doc = json.loads((out / "part.compare.json").read_text())
    assert doc["registration"] is None and doc["parameters"]["tolerance"] == 0.3
    np.testing.assert_allclose(np.array(doc["transform"]), MOTION)


def test_cli_compare_errors(files, capsys) -> None:
    tmp, scan_path, ref_path, tf, scan, height = files
    bad = tmp / "bad.txt"
    bad.write_text("1 2 3\n")
    assert main(["compare", str(scan_path), str(ref_path), "--init-transform", str(bad),
                 "-o", str(tmp)]) == 1
    assert "4 x 4" in capsys.readouterr().err
    assert main(["compare", str(scan_path), str(tmp / "missing.pcd"), "-o", str(tmp),
                 "--no-register"]) == 1
    assert "missing.pcd" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(["compare", str(scan_path), str(ref_path), "--tolerance", "nan"])
    assert exc.value.code == 2


@pytest.mark.slow
def test_cli_second_source_against_target_without_initial_pose(tmp_path, capsys) -> None:
    if not (REAL / "second_source.pcd").exists() or not (REAL / "target.pcd").exists():
        pytest.skip(f"needs the shared real scans in {REAL}")
    pytest.importorskip("open3d")
    rc = main(["compare", str(REAL / "second_source.pcd"), str(REAL / "target.pcd"), "-o",
               str(tmp_path), "--no-plot"])
    text = capsys.readouterr().out
    assert rc == 0, text
    doc = json.loads((tmp_path / "second_source.compare.json").read_text())
    reg = doc["registration"]
    assert reg["coarse"] == "fpfh_ransac"
    # Found without a pose: most of the scan lies on the golden sample, within its noise.
    assert reg["inlier_fraction"] > 0.9 and reg["rmse"] < 0.2
    t = np.array(doc["transform"])
    pts = miem.io.read(REAL / "second_source.pcd").points
    aligned = pts @ t[:3, :3].T + t[:3, 3]
    ref = miem.io.read(REAL / "target.pcd").points
    from scipy.spatial import cKDTree

    d, _ = cKDTree(ref).query(aligned[::20])
    assert np.median(d) < 0.15  # independent check of the fit: nearest-point distances
    assert sum(doc["counts"].values()) == 250_681


def test_compare_reads_points_on_scan_lines_in_any_order(tmp_path) -> None:
    # as miem detect: an unorganized export on scan lines becomes its grid, in file order or,
    # shuffled, by line position; points off any scan line (jittered) stay a cloud
    from miem import simulate
    from miem._cli_compare import _scan

    scan = simulate.make_scan(shape=(30, 40), surface="tilted", noise=0.01, seed=1).points
    assert np.isfinite(scan).all()
    flat = scan.reshape(-1, 3)
    rng = np.random.default_rng(4)
    shuffled = flat[rng.permutation(len(flat))]
    np.save(tmp_path / "shuffled.npy", shuffled)
    _, grid, index = _scan(tmp_path / "shuffled.npy")
    np.testing.assert_array_equal(grid, scan)
    np.testing.assert_array_equal(grid.reshape(-1, 3)[index], shuffled)
    jittered = shuffled.copy()
    jittered[:, :2] += rng.uniform(-0.05, 0.05, (len(flat), 2))
    np.save(tmp_path / "jittered.npy", jittered)
    _, points, index = _scan(tmp_path / "jittered.npy")
    assert index is None and points.shape == (len(flat), 3)


def test_cli_compare_says_when_peaks_reach_the_coverage(tmp_path, capsys) -> None:
    # a bump 4 tall on a plane: its points above the coverage (max(10 x 0.2, 10 x 0.25) = 2.5)
    # have no reference point within reach, so its defect's peak stops just under 2.5
    yy, xx = np.mgrid[0:60, 0:60] * 0.25
    r = np.hypot(xx - 7.5, yy - 7.5)
    bump = np.where(r < 2.0, 4.0 * (1 - (r / 2.0) ** 2), 0.0)
    np.save(tmp_path / "part.npy", np.dstack([xx, yy, bump]))
    np.save(tmp_path / "golden.npy", np.dstack([xx, yy, 0 * xx]).reshape(-1, 3))
    base = ["compare", str(tmp_path / "part.npy"), str(tmp_path / "golden.npy"), "-o",
            str(tmp_path / "o"), "--no-register", "--no-agreement", "--no-plot"]
    assert main(base) == 0
    err = capsys.readouterr().err
    doc = json.loads((tmp_path / "o" / "part.compare.json").read_text())
    peak = max(d["peak_deviation"] for d in doc["defects"])
    assert 0.95 * 2.5 <= peak <= 2.5  # cut off by the coverage, as the note says
    assert "miem: note: 1 defect peaks within 5 % of the coverage (2.5 mm)" in err
    assert main(base + ["--coverage", "10"]) == 0
    err = capsys.readouterr().err
    doc = json.loads((tmp_path / "o" / "part.compare.json").read_text())
    assert max(d["peak_deviation"] for d in doc["defects"]) == pytest.approx(4.0, abs=0.05)
    assert "coverage" not in err
