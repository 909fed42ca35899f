"""What a new user hands miem first: structured arrays, directories, files without extras."""

from __future__ import annotations

import sys

import numpy as np
import pytest

import miem
import miem.io as mio
from miem import simulate as sim


def _structured(points: np.ndarray, dtype=np.float32) -> np.ndarray:
    rec = np.empty(points.shape[:-1], dtype=[("x", dtype), ("y", dtype), ("z", dtype),
                                             ("truth", np.uint8)])
    rec["x"], rec["y"], rec["z"] = points[..., 0], points[..., 1], points[..., 2]
    rec["truth"] = 0
    return rec


@pytest.fixture(scope="module")
def scan():
    return sim.make_scan(shape=(40, 50), step=0.3, defects={"spike": 3}, seed=2)


def test_structured_grid_detects_like_the_plain_grid(scan):
    grid = scan.points.astype(np.float32)
    rec = _structured(grid)
    before = rec.copy()
    a, b = miem.detect(grid, preset="paper"), miem.detect(rec, preset="paper")
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_array_equal(rec, before)  # the caller's array is not changed


def test_structured_points_fit_plane_and_cloud(scan):
    pts = scan.points.reshape(-1, 3)
    rec = _structured(pts, np.float64)
    np.testing.assert_allclose(miem.fit_plane(rec).normal, miem.fit_plane(pts).normal)
    assert miem.point_spacing(rec) == pytest.approx(miem.point_spacing(pts))


def test_structured_profile_in_the_stream(scan):
    grid = scan.points
    s1, s2 = miem.ProfileStream(grid.shape[1]), miem.ProfileStream(grid.shape[1])
    for row in grid:
        a, b = s1.push(row), s2.push(_structured(row, np.float64))
        assert (a is None) == (b is None)
        if a is not None:
            np.testing.assert_array_equal(a.labels, b.labels)


def test_structured_array_without_xyz_is_refused():
    rec = np.zeros(5, dtype=[("a", "f8"), ("b", "f8"), ("c", "f8")])
    with pytest.raises(ValueError, match=r"points: a structured array needs fields x, y and z"):
        miem.fit_plane(rec)


def test_simulated_npy_file_is_a_detectable_array(tmp_path):
    """`miem simulate scan -o scan.npy` then `miem.detect(np.load('scan.npy'))` (Quickstart)."""
    from miem.cli import main

    assert main(["simulate", "scan", "-o", str(tmp_path / "scan.npy")]) == 0
    arr = np.load(tmp_path / "scan.npy")
    res = miem.detect(arr)
    assert res.labels.shape == arr.shape


def test_directory_is_named_as_a_directory(tmp_path):
    with pytest.raises(mio.ScanFileError, match="is a directory"):
        mio.read(tmp_path)


def test_pcd_written_and_read_back_without_pypcd4_for_writing(tmp_path, monkeypatch, scan):
    pts = scan.points.astype(np.float32)
    pts[0, 0] = np.nan
    labels = np.arange(pts.shape[0] * pts.shape[1], dtype=np.uint8).reshape(pts.shape[:2])
    monkeypatch.setitem(sys.modules, "pypcd4", None)  # not installed
    for enc in ("binary", "ascii"):
        mio.write(tmp_path / f"{enc}.pcd", pts, {"label": labels}, encoding=enc)
    with pytest.raises(mio.MissingDependencyError, match=r'pip install ".\[io\]"'):
        mio.write(tmp_path / "c.pcd", pts, encoding="binary_compressed")
    monkeypatch.undo()
    import pypcd4  # the independent parser reads what miem wrote

    for enc in ("binary", "ascii"):
        pc = pypcd4.PointCloud.from_path(tmp_path / f"{enc}.pcd")
        assert (pc.metadata.width, pc.metadata.height) == (pts.shape[1], pts.shape[0])
        xyz = pc.numpy(("x", "y", "z")).reshape(pts.shape)
        np.testing.assert_array_equal(xyz, pts)
        np.testing.assert_array_equal(pc.numpy(("label",)).reshape(labels.shape), labels)
