"""The command line on unorganized files (issue 11): a grid is rebuilt when the points lie on
scan lines (in file order, or in any order: rows sorted by line position), the cloud detector runs
otherwise, the path taken is said and reported, and the reports index the input's points.
Expected values come from the Python API on the same points."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import miem
import miem.io as mio
import numpy as np
import pytest
from miem import cli, simulate

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"


def run(*args: str | Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "miem", *map(str, args)], capture_output=True,
                          text=True, timeout=300, check=False)


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("clouds")
    scan = simulate.make_scan(shape=(50, 60), surface="tilted", noise=0.01,
                              defects={"spike": 3, "cluster": 1}, seed=3)
    flat = scan.points.reshape(-1, 3)
    flat = flat[np.isfinite(flat).all(axis=1)]
    rng = np.random.default_rng(0)
    profiles = flat[rng.permutation(len(flat))]  # on scan lines, not in their order
    shuffled = profiles.copy()
    shuffled[:, :2] += rng.uniform(-0.075, 0.075, (len(flat), 2))  # a quarter of the 0.3 step
    shuffled = np.vstack([shuffled, shuffled[:100]])  # and exact duplicates
    mio.write(d / "shuffled.pcd", shuffled.astype(np.float32))
    mio.write(d / "profiles.pcd", profiles)
    mio.write(d / "lines.xyz", flat)
    return {"shuffled": d / "shuffled.pcd", "lines": d / "lines.xyz",
            "profiles": d / "profiles.pcd"}


def test_shuffled_cloud_runs_the_cloud_detector(files: dict, tmp_path: Path) -> None:
    res = run("detect", files["shuffled"], "--out-dir", tmp_path, "--radius", "2.0", "--k", "6",
              "--no-progress")
    assert res.returncode == 0, res.stderr
    assert "not on scan lines (in file order or by line position): cloud detector" in res.stderr
    doc = json.loads((tmp_path / "shuffled.defects.json").read_text())
    assert doc["layout"] == "cloud" and doc["grid"] is None
    pts = mio.read(files["shuffled"]).points
    api = miem.detect(pts, radius=2.0, K=6)
    assert doc["parameters"]["radius"] == 2.0 and doc["parameters"]["K"] == 6
    assert doc["parameters"]["merged"] == 100
    assert [d["indices"] for d in doc["defects"]] == [d.indices.tolist() for d in api.defects]
    labelled = mio.read(tmp_path / "shuffled.labels.pcd")
    np.testing.assert_array_equal(labelled.fields["label"].reshape(-1), api.labels)
    assert (api.labels == miem.ABNORMAL).sum() >= 3


def test_scan_line_order_is_rebuilt_and_cloud_options_rejected(files: dict,
                                                              tmp_path: Path) -> None:
    res = run("detect", files["lines"], "--out-dir", tmp_path, "--no-progress")
    assert res.returncode == 0, res.stderr
    assert "in scan-line order (profiles at constant y): rebuilt a 50 x 60 grid" in res.stderr
    assert json.loads((tmp_path / "lines.defects.json").read_text())["layout"] == "scanlines"
    bad = run("detect", files["lines"], "--out-dir", tmp_path, "--radius", "1", "--no-progress")
    assert bad.returncode == 1 and "--radius apply to the cloud detector only" in bad.stderr
    forced = run("detect", files["lines"], "--out-dir", tmp_path, "--layout", "cloud",
                 "--no-progress")
    assert forced.returncode == 0 and "--layout cloud: cloud detector" in forced.stderr
    # detect's advice on a flattened grid, in the command line's words (no Python warning)
    assert ("miem: warning: lines.xyz: detect: this (3000, 3) cloud looks like a flattened "
            "organized scan") in forced.stderr
    assert forced.stderr.count("as --layout cloud asks; drop it to rebuild its grid") == 1
    assert "UserWarning" not in forced.stderr and "shape=" not in forced.stderr
    fit = run("fit", files["shuffled"])
    assert fit.returncode == 0 and "MIEM" in fit.stdout


def test_sparse_profiles_get_the_advice_in_options(tmp_path: Path) -> None:
    # a profiler scan with 60 % of its points gone, shuffled: its grid would be 40 % full, so
    # the cloud detector runs, and detect's advice names the command line's options
    scan = simulate.make_scan(shape=(60, 80), surface="tilted", noise=0.01, seed=3)
    flat = scan.points.reshape(-1, 3)
    flat = flat[np.isfinite(flat).all(axis=1)]
    rng = np.random.default_rng(0)
    keep = flat[rng.random(len(flat)) < 0.4]
    mio.write(tmp_path / "sparse.xyz", keep[rng.permutation(len(keep))])
    res = run("detect", tmp_path / "sparse.xyz", "--out-dir", tmp_path / "o", "--no-progress")
    assert res.returncode == 0, res.stderr
    assert "not on scan lines (in file order or by line position): cloud detector" in res.stderr
    assert (f"miem: warning: sparse.xyz: detect: this ({len(keep)}, 3) cloud looks like a "
            "profiler scan whose points are not in scan-line order") in res.stderr
    assert ("no grid could be rebuilt from its scan lines; see --line-step, --line-axis, "
            "--along-axis, --line-tol or --layout scanlines") in res.stderr
    assert "grid_from_scanlines" not in res.stderr and "UserWarning" not in res.stderr
    # --layout scanlines takes the fullest grid any order gave: the 60 x 80 one, by line
    # position (in file order the shuffled points would spread over one profile per point)
    forced = run("detect", tmp_path / "sparse.xyz", "--out-dir", tmp_path / "f", "--layout",
                 "scanlines", "--no-progress")
    assert forced.returncode == 0, forced.stderr
    assert ("on scan lines but not in their order (profiles at constant y, rows sorted by it): "
            "rebuilt a 60 x 80 grid") in forced.stderr
    grid, index = mio.grid_from_scanlines(mio.read(tmp_path / "sparse.xyz").points,
                                          order="line", return_index=True)
    labels = mio.read(tmp_path / "f" / "sparse.labels.xyz").fields["label"].reshape(-1)
    np.testing.assert_array_equal(labels, miem.detect(grid).labels.reshape(-1)[index])


def test_points_on_scan_lines_in_any_order_get_their_grid(files: dict, tmp_path: Path) -> None:
    # the 50 x 60 scan's points shuffled: the grid detector on the grid rebuilt by line
    # position, labels reported per input point; the same labels as the organized scan's
    res = run("detect", files["profiles"], "--out-dir", tmp_path, "--no-progress", "--format",
              "csv")
    assert res.returncode == 0, res.stderr
    assert "on scan lines but not in their order (profiles at constant y, rows sorted by " \
           "it): rebuilt a 50 x 60 grid" in res.stderr
    assert json.loads((tmp_path / "profiles.defects.json").read_text())["layout"] == "scanlines"
    pts = mio.read(files["profiles"]).points
    organized = mio.read(files["lines"]).points  # the scan's finite cells, row by row
    grid = mio.grid_from_scanlines(organized)
    assert grid.shape == (50, 60, 3)
    api = miem.detect(grid)
    # each point's cell found independently: its (x, y) in the organized scan
    cell = {(x, y): i for i, (x, y) in enumerate(grid.reshape(-1, 3)[:, :2].tolist())}
    want = api.labels.ravel()[[cell[(x, y)] for x, y in pts[:, :2].tolist()]]
    labelled = mio.read(tmp_path / "profiles.labels.csv")
    np.testing.assert_array_equal(labelled.points, pts)
    np.testing.assert_array_equal(labelled.fields["label"], want)
    assert (want == miem.ABNORMAL).sum() >= 3


def test_plot_of_a_cloud(files: dict, tmp_path: Path) -> None:
    out = tmp_path / "c.png"
    res = run("plot", files["shuffled"], "-o", out)
    assert res.returncode == 0, res.stderr
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.skipif(not REAL.exists(), reason="needs ../shared/data/real")
def test_every_real_file_has_a_path(tmp_path: Path) -> None:
    args = argparse.Namespace(input_format=None, line_step=None, line_axis=None, along_axis=None,
                              line_tol=None, duplicates="error", layout="auto", units=None,
                              quiet=True)
    names = sorted(p for p in REAL.iterdir() if p.suffix in (".pcd", ".csv", ".ply"))
    assert len(names) >= 15
    layouts = {p.name: cli._load(p, args).layout for p in names}
    assert layouts["second_source.pcd"] == "scanlines"
    # cturtle: a height map on a 5 mm x-y grid stored column by column (x first): its rows
    # by line position (y), not in file order
    assert layouts["cturtle.pcd"] == "scanlines"
    assert layouts["office1.pcd"] == "grid" and layouts["target.pcd"] == "cloud"
    res = run("detect", REAL / "table_scene_lms400_outliers.pcd", REAL / "lamppost.pcd",
              "--out-dir", tmp_path,
              "--no-progress")
    assert res.returncode == 0, res.stderr


def test_config_cloud_table_and_generated_cloud_options(files: dict, tmp_path: Path) -> None:
    """A --config file's [cloud] table reaches the cloud detector (it was dropped), and every
    cloud-only field is an option (here --min-group, --isolated-tolerance); grids refuse them
    as options but simply do not read a file's cloud table."""
    cfg = tmp_path / "cell.toml"
    cfg.write_text('theta0 = 95.0\n[grid]\nwindow = 15\n[cloud]\nradius = 2.0\nK = 6\n'
                   'height_tolerance = "6rms"\n')
    res = run("detect", files["shuffled"], "--out-dir", tmp_path, "--config", cfg,
              "--min-group", "5", "--isolated-tolerance", "off", "--no-progress")
    assert res.returncode == 0, res.stderr
    doc = json.loads((tmp_path / "shuffled.defects.json").read_text())
    pts = mio.read(files["shuffled"]).points
    api = miem.detect(pts, theta0=95.0, radius=2.0, K=6, height_tolerance="6rms", min_group=5,
                      isolated_tolerance=None)
    got = doc["parameters"]
    assert (got["theta0"], got["radius"], got["K"], got["height_tolerance"], got["min_group"],
            got["isolated_tolerance"]) == (95.0, 2.0, 6, "6rms", 5, None)
    assert [d["indices"] for d in doc["defects"]] == [d.indices.tolist() for d in api.defects]
    # a grid reads the file's angle and grid tables (the cloud table is not its)
    res = run("detect", files["lines"], "--out-dir", tmp_path, "--config", cfg, "--no-progress")
    assert res.returncode == 0, res.stderr
    got = json.loads((tmp_path / "lines.defects.json").read_text())["parameters"]
    assert (got["theta0"], got["window"], got["height_tolerance"]) == (95.0, 15, "4.5rms")
    bad = run("detect", files["lines"], "--out-dir", tmp_path, "--min-group", "5",
              "--no-progress")
    assert bad.returncode == 1 and "--min-group apply to the cloud detector only" in bad.stderr
