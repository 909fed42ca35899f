"""Tests of miem.io: readers and writers of every format, broken files, atomic writes, scan-line
grids, the Gocator CSV reader and Open3D interop.

Expected values come from the arrays written, from the files decoded independently (header text,
raw bytes, the csv module, the format libraries called directly) or from the data's own
documentation (shared/data/real/SOURCES.md), never from an earlier run of miem.io itself.
"""

from __future__ import annotations

import csv
import os
import sys
import warnings
from pathlib import Path

import miem
import miem.io as mio
import numpy as np
import pytest

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
SECOND_SOURCE = REAL / "second_source.pcd"
GOCATOR = REAL / "replay_40959_2020-6-30(1).csv"

# (format, encoding) pairs that write; every one must round-trip.
CASES = [
    ("pcd", "binary"), ("pcd", "binary_compressed"), ("pcd", "ascii"),
    ("ply", "binary"), ("ply", "ascii"),
    ("las", None), ("laz", None),
    ("xyz", None), ("csv", None), ("txt", None),
    ("npy", None), ("npz", None),
]
SUFFIX = {"pcd": ".pcd", "ply": ".ply", "las": ".las", "laz": ".laz", "xyz": ".xyz",
          "csv": ".csv", "txt": ".txt", "npy": ".npy", "npz": ".npz"}


def make_grid(h: int = 6, w: int = 9, dtype: type = np.float64, seed: int = 0,
              origin: float = 0.0) -> tuple[np.ndarray, dict]:
    """A noisy grid with two dropouts and label/height/angle/flags fields."""
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[0:h, 0:w]
    g = np.stack([c * 0.3 + origin, r * 0.5 - origin, rng.normal(0, 0.05, (h, w))], axis=-1)
    g[1, 2] = np.nan
    g[h - 2, 0, 2] = np.inf
    g = g.astype(dtype)
    labels = rng.integers(0, 3, (h, w)).astype(np.uint8)
    labels[1, 2] = labels[h - 2, 0] = 3
    height = rng.normal(0, 1, (h, w))
    height[1, 2] = height[h - 2, 0] = np.nan
    angle = rng.uniform(0, 180, (h, w))
    angle[0, :] = np.nan
    flags = rng.integers(0, 16, (h, w)).astype(np.uint8)
    return g, {"label": labels, "height": height, "angle": angle, "flags": flags}


def coord_tol(fmt: str, enc: str | None, dtype: type) -> float:
    if fmt in ("las", "laz"):
        return 0.5e-6 + 1e-12  # scale 1e-6: rounding to the nearest unit
    if fmt == "pcd" and enc == "ascii":
        return 0.5e-10 + 1e-12  # pypcd4 prints floats with 10 decimals
    return 0.0


def assert_points(got: np.ndarray, want: np.ndarray, tol: float) -> None:
    assert got.shape == want.shape
    finite = np.isfinite(want).all(axis=-1)
    # Any non-finite coordinate is a dropout: it must come back non-finite in every coordinate
    # the format can hold (NaN/inf) and absent from nothing.
    assert np.array_equal(np.isfinite(got).all(axis=-1), finite)
    err = np.abs(got[finite].astype(np.float64) - want[finite].astype(np.float64)).max()
    assert err <= tol, err


# ---------------------------------------------------------------------------------------------
# round trips


@pytest.mark.parametrize(("fmt", "enc"), CASES)
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_round_trip_organized_with_fields(tmp_path: Path, fmt: str, enc: str | None,
                                          dtype: type) -> None:
    g, fields = make_grid(dtype=dtype)
    path = tmp_path / f"scan{SUFFIX[fmt]}"
    assert mio.write(path, g, fields, encoding=enc) == path
    scan = mio.read(path)
    assert scan.organized and scan.points.shape == g.shape
    assert scan.format == fmt and scan.path == path
    got_pts = scan.points
    if fmt in ("xyz", "csv", "txt"):
        # Text keeps no dtype: float32 values are printed with 9 digits, exact after a cast.
        assert got_pts.dtype == np.float64
        got_pts = got_pts.astype(dtype)
    else:
        assert got_pts.dtype == (np.float64 if fmt in ("las", "laz") else dtype)
    assert_points(got_pts, g, coord_tol(fmt, enc, dtype))
    finite = np.isfinite(g).all(axis=-1)
    for name, want in fields.items():
        got = scan.fields[name]
        assert got.shape == want.shape
        if fmt in ("las", "laz"):
            # LAS cannot hold NaN points: their fields come back NaN / 0 / INVALID for labels.
            np.testing.assert_array_equal(got[finite], want[finite])
            if name == "label":
                assert np.all(got[~finite] == 3)
            continue
        if fmt == "pcd" and enc == "ascii" and want.dtype.kind == "f":
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
        else:
            np.testing.assert_array_equal(got, want)
        if want.dtype.kind == "u":
            assert got.dtype.kind in "iu" and np.array_equal(got.astype(np.int64), want)


@pytest.mark.parametrize(("fmt", "enc"), CASES)
def test_round_trip_unorganized_far_from_origin(tmp_path: Path, fmt: str,
                                                enc: str | None) -> None:
    # Robot-base coordinates (1e4 mm): nothing may be lost to an uncentred float format.
    rng = np.random.default_rng(3)
    pts = rng.uniform(-50, 50, (40, 3)) + np.array([12_000.0, -8_000.0, 1_500.0])
    path = tmp_path / f"cloud{SUFFIX[fmt]}"
    mio.write(path, pts, {"label": np.arange(40, dtype=np.uint8) % 4}, encoding=enc)
    scan = mio.read(path)
    assert not scan.organized and scan.points.shape == (40, 3)
    tol = 0.5e-6 + 1e-9 if fmt in ("las", "laz") else (1e-10 if enc == "ascii" else 0.0)
    assert np.abs(scan.points - pts).max() <= tol
    np.testing.assert_array_equal(scan.fields["label"], np.arange(40) % 4)


def test_organized_pcd_header_is_width_by_height(tmp_path: Path) -> None:
    g, fields = make_grid(5, 7)
    for enc in ("binary", "binary_compressed", "ascii"):
        path = tmp_path / f"g_{enc}.pcd"
        mio.write(path, g, fields, encoding=enc)
        head = path.read_bytes()[:600].decode("ascii", errors="replace")
        assert "\nWIDTH 7\n" in head and "\nHEIGHT 5\n" in head and "\nPOINTS 35\n" in head
        assert f"\nDATA {enc}\n" in head
        assert "FIELDS x y z label height angle flags" in head


def test_binary_pcd_payload_decoded_by_hand(tmp_path: Path) -> None:
    g, fields = make_grid(3, 4, dtype=np.float32)
    path = tmp_path / "g.pcd"
    mio.write(path, g, {"label": fields["label"]})
    raw = path.read_bytes()
    start = raw.index(b"DATA binary\n") + len(b"DATA binary\n")
    rec = np.frombuffer(raw[start:], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                            ("label", "u1")])
    assert rec.shape == (12,)
    np.testing.assert_array_equal(rec["x"], g[..., 0].ravel())
    np.testing.assert_array_equal(rec["z"], g[..., 2].ravel())
    np.testing.assert_array_equal(rec["label"], fields["label"].ravel())


def test_ply_las_csv_npz_read_by_their_own_tools(tmp_path: Path) -> None:
    plyfile = pytest.importorskip("plyfile")
    laspy = pytest.importorskip("laspy")
    g, fields = make_grid(4, 5)
    finite = np.isfinite(g).all(axis=-1).ravel()

    mio.write(tmp_path / "a.ply", g, fields)
    v = plyfile.PlyData.read(str(tmp_path / "a.ply"))["vertex"].data
    np.testing.assert_array_equal(v["x"], g[..., 0].ravel())
    np.testing.assert_array_equal(v["label"], fields["label"].ravel())

    mio.write(tmp_path / "a.las", g, fields)
    las = laspy.read(str(tmp_path / "a.las"))
    assert len(las.points) == finite.sum()  # dropouts are not stored in LAS
    np.testing.assert_allclose(np.asarray(las.x), g[..., 0].ravel()[finite], atol=1e-6)
    np.testing.assert_array_equal(np.asarray(las["label"]), fields["label"].ravel()[finite])

    mio.write(tmp_path / "a.csv", g, fields)
    with open(tmp_path / "a.csv", newline="") as fh:
        rows = [r for r in csv.reader(fh) if not r[0].startswith("#")]
    assert rows[0] == ["x", "y", "z", "label", "height", "angle", "flags"]
    assert len(rows) == 1 + g.shape[0] * g.shape[1]
    assert float(rows[1 + 8][0]) == g.reshape(-1, 3)[8, 0]
    assert int(rows[1 + 8][3]) == fields["label"].ravel()[8]

    mio.write(tmp_path / "a.npz", g, fields)
    with np.load(tmp_path / "a.npz") as npz:
        np.testing.assert_array_equal(npz["points"], g)
        np.testing.assert_array_equal(npz["height"], fields["height"])


def test_las_standard_dimensions(tmp_path: Path) -> None:
    laspy = pytest.importorskip("laspy")
    pts = np.random.default_rng(2).normal(size=(10, 3))
    fields = {"intensity": np.arange(10, dtype=np.uint16) * 100,
              "classification": np.full(10, 7, dtype=np.uint8),
              "red": np.arange(10, dtype=np.uint16), "label": np.ones(10, dtype=np.uint8)}
    mio.write(tmp_path / "s.las", pts, fields)
    las = laspy.read(str(tmp_path / "s.las"))
    np.testing.assert_array_equal(np.asarray(las.intensity), fields["intensity"])
    np.testing.assert_array_equal(np.asarray(las.classification), 7)
    assert list(las.point_format.extra_dimension_names) == ["label"]
    back = mio.read(tmp_path / "s.las")
    # green and blue (all zero) and gps_time (zero) are not reported as fields
    assert sorted(back.fields) == ["classification", "intensity", "label", "red"]
    with pytest.raises(ValueError, match="do not fit"):
        mio.write(tmp_path / "t.las", pts, {"classification": np.full(10, 300.0)})
    assert not (tmp_path / "t.las").exists()


def test_read_foreign_text_without_header(tmp_path: Path) -> None:
    path = tmp_path / "plain.xyz"
    path.write_text("1 2 3 0.5\n4 5 6 0.25\n\n7 8 9 1\n")
    scan = mio.read(path)
    np.testing.assert_array_equal(scan.points, [[1, 2, 3], [4, 5, 6], [7, 8, 9]])
    np.testing.assert_array_equal(scan.fields["col3"], [0.5, 0.25, 1.0])
    path = tmp_path / "named.csv"
    path.write_text("Z,Y,X,intensity\n3,2,1,10\n6,5,4,20\n")
    scan = mio.read(path)
    np.testing.assert_array_equal(scan.points, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(scan.fields["intensity"], [10, 20])


def test_npy_plain_and_structured(tmp_path: Path) -> None:
    g, fields = make_grid(3, 3)
    np.save(tmp_path / "plain.npy", g)
    scan = mio.read(tmp_path / "plain.npy")
    assert scan.organized and scan.fields == {}
    assert_points(scan.points, g, 0.0)
    mio.write(tmp_path / "s.npy", g, fields)
    arr = np.load(tmp_path / "s.npy")
    assert arr.dtype.names == ("x", "y", "z", "label", "height", "angle", "flags")
    assert arr.shape == (3, 3)


def test_result_fields_from_detect(tmp_path: Path) -> None:
    y, x = np.mgrid[0:20, 0:20] * 0.5
    grid = np.dstack([x, y, np.zeros_like(x)])
    grid[8, 9, 2] = 3.0
    res = miem.detect(grid)
    f = mio.result_fields(res)
    assert set(f) == {"label", "flags", "angle", "height"}
    mio.write(tmp_path / "r.ply", grid, f)
    back = mio.read(tmp_path / "r.ply")
    np.testing.assert_array_equal(back.fields["label"], res.labels)
    np.testing.assert_array_equal(back.fields["height"], res.height)
    assert back.fields["label"][8, 9] == miem.ABNORMAL


# ---------------------------------------------------------------------------------------------
# broken files


def _good_file(tmp_path: Path, fmt: str, enc: str | None) -> Path:
    g, fields = make_grid(20, 30)
    path = tmp_path / f"good{SUFFIX[fmt]}"
    mio.write(path, g, fields, encoding=enc)
    return path


@pytest.mark.parametrize(("fmt", "enc"), CASES)
def test_empty_file(tmp_path: Path, fmt: str, enc: str | None) -> None:
    path = tmp_path / f"empty{SUFFIX[fmt]}"
    path.write_bytes(b"")
    with pytest.raises(mio.ScanFileError, match="empty") as info:
        mio.read(path)
    assert isinstance(info.value, ValueError)
    assert str(path) in str(info.value) and info.value.path == path


@pytest.mark.parametrize(("fmt", "enc"), CASES)
def test_truncated_file(tmp_path: Path, fmt: str, enc: str | None) -> None:
    path = _good_file(tmp_path, fmt, enc)
    data = path.read_bytes()
    cut = tmp_path / f"cut{SUFFIX[fmt]}"
    # Text formats cut mid-row leave a ragged last row; binary formats lose their tail.
    cut.write_bytes(data[: len(data) * 2 // 3 + 1])
    with pytest.raises(mio.ScanFileError) as info:
        mio.read(cut)
    assert str(cut) in str(info.value)


@pytest.mark.parametrize(("fmt", "enc"), CASES)
def test_garbage_file(tmp_path: Path, fmt: str, enc: str | None) -> None:
    path = tmp_path / f"junk{SUFFIX[fmt]}"
    path.write_bytes(np.random.default_rng(1).integers(0, 256, 3000, dtype=np.uint8).tobytes())
    with pytest.raises(mio.ScanFileError) as info:
        mio.read(path)
    assert str(path) in str(info.value)


def test_pcd_header_lies(tmp_path: Path) -> None:
    header = ("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 10\n"
              "HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 10\nDATA binary\n")
    path = tmp_path / "short.pcd"
    path.write_bytes(header.encode() + np.zeros(4 * 3, dtype="<f4").tobytes())  # 4 of 10
    with pytest.raises(mio.ScanFileError, match="truncated"):
        mio.read(path)
    path = tmp_path / "wh.pcd"
    path.write_bytes(header.replace("HEIGHT 1", "HEIGHT 2").encode()
                     + np.zeros(10 * 3, dtype="<f4").tobytes())
    with pytest.raises(mio.ScanFileError, match="WIDTH 10 x HEIGHT 2"):
        mio.read(path)
    path = tmp_path / "noxyz.pcd"
    path.write_bytes(header.replace("FIELDS x y z", "FIELDS a b c").encode()
                     + np.zeros(10 * 3, dtype="<f4").tobytes())
    with pytest.raises(mio.ScanFileError, match="no x, y, z"):
        mio.read(path)


def test_text_problems(tmp_path: Path) -> None:
    path = tmp_path / "two.xyz"
    path.write_text("1 2\n3 4\n")
    with pytest.raises(mio.ScanFileError, match="at least 3 columns"):
        mio.read(path)
    path = tmp_path / "comments.txt"
    path.write_text("# nothing here\n\n")
    with pytest.raises(mio.ScanFileError, match="no data rows"):
        mio.read(path)
    path = tmp_path / "grid.txt"
    path.write_text("# miem-grid 2 3\n1 2 3\n4 5 6\n")
    with pytest.raises(mio.ScanFileError, match="announces 6 points"):
        mio.read(path)


def test_npz_without_points(tmp_path: Path) -> None:
    path = tmp_path / "x.npz"
    np.savez(path, a=np.zeros((3, 2)), b=np.zeros(4))
    with pytest.raises(mio.ScanFileError, match="no 'points' array"):
        mio.read(path)


def test_missing_file_unknown_suffix_and_directory(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="nope.pcd"):
        mio.read(tmp_path / "nope.pcd")
    (tmp_path / "scan.e57").write_bytes(b"x")
    with pytest.raises(ValueError, match="cannot tell the scan format"):
        mio.read(tmp_path / "scan.e57")
    (tmp_path / "d.ply").mkdir()
    with pytest.raises(mio.ScanFileError, match="directory"):
        mio.read(tmp_path / "d.ply")
    with pytest.raises(ValueError, match="format"):
        mio.write(tmp_path / "x.e57", np.zeros((3, 3)))
    with pytest.raises(ValueError, match="read but not written"):
        mio.write(tmp_path / "x.csv", np.zeros((3, 3)), format="gocator-csv")


def test_bad_write_arguments(tmp_path: Path) -> None:
    pts = np.zeros((4, 3))
    with pytest.raises(ValueError, match=r"shape \(N, 3\) or \(H, W, 3\)"):
        mio.write(tmp_path / "a.ply", np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"fields\['label'\]: expected shape \(4,\)"):
        mio.write(tmp_path / "a.ply", pts, {"label": np.zeros(5)})
    with pytest.raises(ValueError, match="identifiers other than x, y, z"):
        mio.write(tmp_path / "a.ply", pts, {"z": np.zeros(4)})
    with pytest.raises(ValueError, match="encoding"):
        mio.write(tmp_path / "a.pcd", pts, encoding="zip")
    assert list(tmp_path.iterdir()) == []


def test_missing_extra_names_the_pip_extra(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "a.ply"
    path.write_bytes(b"ply\n")
    monkeypatch.setitem(sys.modules, "plyfile", None)  # import plyfile -> ImportError
    with pytest.raises(mio.MissingDependencyError, match=r'pip install "miem\[io\]"'):
        mio.read(path)
    with pytest.raises(ImportError, match="plyfile"):
        mio.write(tmp_path / "b.ply", np.zeros((3, 3)))
    assert not (tmp_path / "b.ply").exists()


# ---------------------------------------------------------------------------------------------
# atomic writes


def test_failed_write_leaves_nothing_and_keeps_the_old_file(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    g, fields = make_grid()

    def broken_writer(tmp: Path, pts: np.ndarray, flds: dict, enc: object) -> None:
        tmp.write_bytes(b"ply\nformat binary_little_endian 1.0\n")  # half a file ...
        raise OSError("disk full")  # ... then the disk fills up

    monkeypatch.setitem(mio._WRITERS, "ply", broken_writer)
    new = tmp_path / "new.ply"
    with pytest.raises(OSError, match="disk full"):
        mio.write(new, g, fields)
    assert not new.exists()
    assert [p.name for p in tmp_path.iterdir()] == []  # no temporary file left behind

    monkeypatch.undo()
    old = tmp_path / "old.ply"
    mio.write(old, g, fields)
    before = old.read_bytes()
    monkeypatch.setitem(mio._WRITERS, "ply", broken_writer)
    with pytest.raises(OSError, match="disk full"):
        mio.write(old, g[:2], {k: v[:2] for k, v in fields.items()})
    assert old.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.ply"]


def test_write_replaces_and_sets_normal_permissions(tmp_path: Path) -> None:
    g, fields = make_grid()
    path = tmp_path / "a.pcd"
    mio.write(path, g, fields)
    mio.write(path, g[:3], {k: v[:3] for k, v in fields.items()})
    assert mio.read(path).points.shape == (3, 9, 3)
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.pcd"]


def test_write_into_missing_directory(tmp_path: Path) -> None:
    with pytest.raises(mio.ScanFileError, match="does not exist"):
        mio.write(tmp_path / "no" / "a.npy", np.zeros((3, 3)))


# ---------------------------------------------------------------------------------------------
# scan lines -> grid


def scanline_points(grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The finite cells of a grid in row-major (scan) order, and their flat cell index."""
    flat = grid.reshape(-1, 3)
    keep = np.flatnonzero(np.isfinite(flat).all(axis=1))
    return flat[keep], keep


def test_grid_from_scanlines_rebuilds_the_grid() -> None:
    rng = np.random.default_rng(5)
    h, w, step = 12, 30, 0.05
    c = np.mgrid[0:h, 0:w][1]
    ys = np.cumsum(rng.choice([0.1, 0.2, 1.0], size=h))  # uneven profile spacing
    grid = np.stack([c * step + 3.0, np.broadcast_to(ys[:, None], (h, w)),
                     rng.normal(0, 0.01, (h, w))], axis=-1)
    grid[rng.random((h, w)) < 0.2] = np.nan  # gaps inside profiles
    grid[:, 0] = np.nan
    grid[:, 0][3] = [3.0, ys[3], 0.0]  # column 0 holds one point: it sets the minimum x
    pts, cells = scanline_points(grid)
    for kwargs in ({}, {"step": step}, {"step": step, "line_tol": 0.01}):
        out, index = mio.grid_from_scanlines(pts, return_index=True, **kwargs)
        assert out.shape == grid.shape
        np.testing.assert_array_equal(out, grid)
        np.testing.assert_array_equal(index, cells)


def test_grid_from_scanlines_with_nan_rows_and_other_axes() -> None:
    # Profiles along y at constant x; non-finite input points are skipped (index -1).
    pts = np.array([[0.0, 0.0, 1], [0.0, 0.5, 2], [np.nan, 0, 0], [0.0, 1.0, 3],
                    [1.2, 0.5, 4], [1.2, 1.0, 5]])
    g, index = mio.grid_from_scanlines(pts, line_axis=0, along_axis=1, return_index=True)
    assert g.shape == (2, 3, 3)
    np.testing.assert_array_equal(index, [0, 1, -1, 2, 4, 5])
    assert np.isnan(g[1, 0]).all()
    np.testing.assert_array_equal(g[1, 2], [1.2, 1.0, 5])


def test_grid_from_scanlines_duplicates() -> None:
    pts = np.array([[0.0, 0, 1], [0.1, 0, 2], [0.1, 0, 3], [0.2, 0, 4], [0.0, 1, 5],
                    [0.1, 1, 6]])
    with pytest.raises(ValueError, match="1 points fall in a cell"):
        mio.grid_from_scanlines(pts, step=0.1)
    first = mio.grid_from_scanlines(pts, step=0.1, duplicates="first")
    last = mio.grid_from_scanlines(pts, step=0.1, duplicates="last")
    assert first[0, 1, 2] == 2 and last[0, 1, 2] == 3
    assert np.isfinite(first).all(axis=-1).sum() == 5


def test_grid_from_scanlines_by_line_position_in_any_order() -> None:
    # The grid of test_grid_from_scanlines_rebuilds_the_grid, its points shuffled: order="line"
    # gives the same grid (profiles in increasing y) and the index maps each input point to its
    # cell; the caller's array is not changed.
    rng = np.random.default_rng(6)
    h, w, step = 15, 40, 0.05
    c = np.mgrid[0:h, 0:w][1]
    ys = np.cumsum(rng.choice([0.1, 0.2, 1.0], size=h))
    grid = np.stack([c * step - 2.0, np.broadcast_to(ys[:, None], (h, w)),
                     rng.normal(0, 0.01, (h, w))], axis=-1)
    grid[rng.random((h, w)) < 0.2] = np.nan
    grid[:, 0] = np.nan
    grid[7, 0] = [-2.0, ys[7], 0.0]
    pts, cells = scanline_points(grid)
    perm = rng.permutation(len(pts))
    shuffled = np.vstack([pts[perm][:50], [[np.nan] * 3], pts[perm][50:]])
    before = shuffled.copy()
    for kwargs in ({}, {"step": step}):
        out, index = mio.grid_from_scanlines(shuffled, order="line", return_index=True, **kwargs)
        np.testing.assert_array_equal(out, grid)
        np.testing.assert_array_equal(index[50], -1)
        np.testing.assert_array_equal(np.delete(index, 50), cells[perm])
    np.testing.assert_array_equal(shuffled, before)
    # file order reads the shuffled points as one profile per change of y: no such grid
    with pytest.raises(ValueError):
        mio.grid_from_scanlines(shuffled, step=step, max_cells=10 * len(pts))
    # in scan-line order both orders agree
    np.testing.assert_array_equal(mio.grid_from_scanlines(pts, order="line"), grid)
    with pytest.raises(ValueError, match="order: expected 'file' or 'line'"):
        mio.grid_from_scanlines(pts, order="sorted")


def test_grid_from_scanlines_by_line_position_duplicates_in_file_order() -> None:
    # two points in one cell: "first" / "last" keep the first / last in the input's order,
    # whatever their sorted order (the later one has the smaller x)
    pts = np.array([[0.2, 1, 1], [0.11, 0, 2], [0.0, 0, 3], [0.09, 0, 4], [0.0, 1, 5],
                    [0.2, 0, 6]])
    with pytest.raises(ValueError, match="1 points fall in a cell"):
        mio.grid_from_scanlines(pts, step=0.1, order="line")
    first = mio.grid_from_scanlines(pts, step=0.1, order="line", duplicates="first")
    last = mio.grid_from_scanlines(pts, step=0.1, order="line", duplicates="last")
    assert first.shape == (2, 3, 3)
    assert first[0, 1, 2] == 2 and last[0, 1, 2] == 4
    np.testing.assert_array_equal(first[1, 2], [0.2, 1, 1])


def test_rebuilt_grid_of_a_jittered_or_random_cloud_is_refused() -> None:
    # what the command line does with an unorganized file: a grid from the scan lines in file
    # order, else by line position, else none (the cloud detector runs)
    rng = np.random.default_rng(2)
    y, x = np.mgrid[0:30, 0:40] * 0.1
    pts = np.stack([x, y, rng.normal(0, 0.01, x.shape)], axis=-1).reshape(-1, 3)
    grid, index, order, la = mio._rebuild_grid(pts)
    assert (order, la) == ("file", 1) and grid.shape == (30, 40, 3)
    shuffled = pts[rng.permutation(len(pts))]
    grid2, index2, order2, _ = mio._rebuild_grid(shuffled)
    assert order2 == "line"
    np.testing.assert_array_equal(grid2, grid)
    np.testing.assert_array_equal(grid2.reshape(-1, 3)[index2], shuffled)
    jittered = shuffled.copy()
    jittered[:, :2] += rng.uniform(-0.025, 0.025, (len(pts), 2))  # a quarter step
    with pytest.raises(ValueError):
        mio._rebuild_grid(jittered)
    with pytest.raises(ValueError):
        mio._rebuild_grid(rng.uniform(0, 10, (500, 3)))


def test_forced_rebuild_of_sparse_shuffled_profiles_takes_the_fullest_grid() -> None:
    # --layout scanlines (force): 60 % of a 30 x 40 scan's points gone, shuffled: no order
    # gives half a grid, so without force there is none; with it the fullest below that bound,
    # the one by line position (file order spreads the points over one profile each)
    rng = np.random.default_rng(5)
    y, x = np.mgrid[0:30, 0:40] * 0.1
    pts = np.stack([x, y, rng.normal(0, 0.01, x.shape)], axis=-1).reshape(-1, 3)
    kept = pts[rng.random(len(pts)) < 0.4]
    kept = kept[rng.permutation(len(kept))]
    with pytest.raises(ValueError):
        mio._rebuild_grid(kept, step=0.1)
    grid, index, order, la = mio._rebuild_grid(kept, force=True, step=0.1)
    assert (order, la) == ("line", 1) and grid.shape == (30, 40, 3)
    want = np.full((30 * 40, 3), np.nan)
    rows = np.rint(kept[:, 1] / 0.1).astype(int) * 40 + np.rint(kept[:, 0] / 0.1).astype(int)
    want[rows] = kept
    np.testing.assert_array_equal(grid.reshape(-1, 3), want)
    np.testing.assert_array_equal(index, rows)


def test_rebuilt_grid_of_profiles_at_constant_x() -> None:
    # a scanner moving along x: profiles at constant x (0.1 / 0.2 / 1.0 mm apart), points
    # 0.05 mm apart along y. Without axes given, the command line's rebuild finds that layout,
    # in file order and shuffled (where the y-x layout also passes the checks, but leaves the
    # columns between uneven profiles empty: the fuller grid is taken)
    rng = np.random.default_rng(3)
    h, w = 25, 60
    xs = np.cumsum(rng.choice([0.1, 0.2, 1.0], size=h, p=[0.6, 0.3, 0.1]))
    r, c = np.mgrid[0:h, 0:w]
    grid = np.stack([xs[r], c * 0.05, rng.normal(0, 0.01, (h, w))], axis=-1)
    pts = grid.reshape(-1, 3)
    got, index, order, la = mio._rebuild_grid(pts)
    assert (order, la) == ("file", 0)
    np.testing.assert_array_equal(got, grid)
    shuffled = pts[rng.permutation(len(pts))]
    got, index, order, la = mio._rebuild_grid(shuffled)
    assert (order, la) == ("line", 0)
    np.testing.assert_array_equal(got, grid)
    np.testing.assert_array_equal(got.reshape(-1, 3)[index], shuffled)
    # the axes given: only that layout (here the wrong one for file order: no grid)
    with pytest.raises(ValueError):
        mio._rebuild_grid(pts, line_axis=1, along_axis=0)


def test_grid_from_scanlines_rejects_non_scanline_clouds() -> None:
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="not evenly spaced"):
        mio.grid_from_scanlines(rng.uniform(0, 10, (500, 3)), step=0.05, line_tol=100.0)
    with pytest.raises(ValueError, match="cannot estimate the spacing"):
        mio.grid_from_scanlines(rng.uniform(0, 10, (500, 3)))
    with pytest.raises(ValueError, match="max_cells"):
        mio.grid_from_scanlines(np.array([[0.0, 0, 0], [1e6, 0, 0]]), step=1e-3)
    with pytest.raises(ValueError, match="line_axis and along_axis"):
        mio.grid_from_scanlines(np.zeros((3, 3)), line_axis=0, along_axis=0)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        mio.grid_from_scanlines(np.zeros((2, 2, 3)))


# ---------------------------------------------------------------------------------------------
# real files (shared/data/real, described in its SOURCES.md)


def _pcd_xyz_by_hand(path: Path) -> np.ndarray:
    """Decode a binary x y z F4 PCD without miem.io or pypcd4."""
    raw = path.read_bytes()
    end = raw.index(b"DATA binary\n") + len(b"DATA binary\n")
    header = raw[:end].decode("ascii")
    n = int(header.split("\nPOINTS ")[1].split()[0])
    assert "FIELDS x y z\n" in header and "SIZE 4 4 4\n" in header
    return np.frombuffer(raw[end:end + 12 * n], dtype="<f4").reshape(n, 3)


@pytest.mark.skipif(not SECOND_SOURCE.exists(), reason="shared/data/real not beside the repo")
def test_second_source_scanlines_to_grid() -> None:
    scan = mio.read(SECOND_SOURCE)
    assert not scan.organized and scan.points.shape == (250_681, 3)
    assert scan.points.dtype == np.float32
    ref = _pcd_xyz_by_hand(SECOND_SOURCE)
    np.testing.assert_array_equal(scan.points, ref)

    # Independent grid: walk the points in file order, new profile where y changes, column
    # round((x - min x) / 0.05) as SOURCES.md describes.
    xs = ref[:, 0].astype(np.float64)
    x0 = xs.min()
    cells: dict[tuple[int, int], int] = {}
    line, prev_y = -1, None
    for i, (x, y) in enumerate(zip(xs.tolist(), ref[:, 1].tolist())):
        if y != prev_y:
            line, prev_y = line + 1, y
        cells.setdefault((line, round((x - x0) / 0.05)), i)
    n_lines = line + 1
    assert n_lines == 426  # SOURCES.md: 426 profiles
    width = max(c for _, c in cells) + 1

    grid, index = mio.grid_from_scanlines(scan.points, step=0.05, return_index=True)
    assert grid.shape == (n_lines, width, 3)
    finite = np.isfinite(grid).all(axis=-1)
    # Every point gets a cell of its own: the finite count is 250,681 minus duplicates (none).
    assert finite.sum() == len(cells) == 250_681
    for (r, c), i in list(cells.items())[::997]:
        np.testing.assert_array_equal(grid[r, c], ref[i])
        assert index[i] == r * width + c
    # The first point (31.55, 9.4, -10.079) is a profile of its own (SOURCES.md).
    assert finite[0].sum() == 1
    # Estimating the step gives the same grid.
    np.testing.assert_array_equal(mio.grid_from_scanlines(scan.points), grid)
    # The points shuffled (as a tool that reorders them leaves them): by line position the
    # same grid, every point at its cell.
    perm = np.random.default_rng(0).permutation(len(ref))
    by_line, index2 = mio.grid_from_scanlines(scan.points[perm], order="line", return_index=True)
    np.testing.assert_array_equal(by_line, grid)
    np.testing.assert_array_equal(index2, index[perm])


@pytest.mark.skipif(not GOCATOR.exists(), reason="shared/data/real not beside the repo")
def test_gocator_csv() -> None:
    scan = mio.read(GOCATOR)
    assert scan.format == "gocator-csv" and scan.organized
    assert scan.points.shape == (428, 452, 3)  # SOURCES.md: 452 (W) x 428 (H)
    z = scan.points[..., 2]
    assert np.isfinite(z).sum() == 55_246  # SOURCES.md: 55,246 valid cells
    assert np.isnan(z).sum() == 138_210
    assert np.nanmin(z) == pytest.approx(-31.69) and np.nanmax(z) == pytest.approx(30.791)
    # Independent decode with the csv module.
    with open(GOCATOR, newline="") as fh:
        rows = list(csv.reader(fh))
    start = next(i for i, r in enumerate(rows) if r and r[0] == "Y\\X")
    xs = [float(v) for v in rows[start][1:] if v]
    assert len(xs) == 452
    np.testing.assert_array_equal(scan.points[..., 0][np.isfinite(z)],
                                  np.broadcast_to(np.array(xs), z.shape)[np.isfinite(z)])
    for k in (0, 150, 300, 427):
        row = rows[start + 1 + k]
        assert np.all(scan.points[k, :, 1][np.isfinite(z[k])] == float(row[0]))
        want = [float(v) if v.strip() else np.nan for v in row[1:453]]
        np.testing.assert_array_equal(z[k], want)
    assert mio.read_gocator_csv(GOCATOR).points.shape == (428, 452, 3)


def test_gocator_csv_truncated(tmp_path: Path) -> None:
    text = ("Info\nCSV Version\n2\nEnd\n\nPart\nFrame,Row Count,Column Count\n1,3,2\n"
            "Y\\X,0.0,0.5\n0.0,1.0,\n0.5,,2.0\n")
    path = tmp_path / "g.csv"
    path.write_text(text + "1.0,3.0,4.0\nEnd\n")
    scan = mio.read(path)
    assert scan.format == "gocator-csv" and scan.points.shape == (3, 2, 3)
    assert np.isfinite(scan.points).all(axis=-1).sum() == 4
    path.write_text(text + "End\n")
    with pytest.raises(mio.ScanFileError, match="truncated grid: Row Count 3, found 2"):
        mio.read(path)
    path.write_text(text.replace("Part\n", ""))
    with pytest.raises(mio.ScanFileError, match="no 'Part' block"):
        mio.read(path)


@pytest.mark.skipif(not REAL.exists(), reason="shared/data/real not beside the repo")
def test_organized_real_pcd_binary_compressed() -> None:
    # SOURCES.md: 640 x 480, 97,920 NaN points, fields x y z rgba, binary_compressed.
    scan = mio.read(REAL / "table_scene_mug_stereo_textured.pcd")
    assert scan.organized and scan.points.shape == (480, 640, 3)
    assert (~np.isfinite(scan.points).all(axis=-1)).sum() == 97_920
    assert set(scan.fields) == {"rgba"}


# ---------------------------------------------------------------------------------------------
# Open3D


def test_from_open3d_rejects_other_objects() -> None:
    with pytest.raises(ValueError, match="open3d.geometry.PointCloud"):
        mio.from_open3d(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="open3d.geometry.PointCloud"):
        mio.from_open3d("cloud.pcd")


def test_open3d_round_trip() -> None:
    o3d = pytest.importorskip("open3d")
    g, fields = make_grid()
    pcd = mio.to_open3d(g, fields["label"])
    assert isinstance(pcd, o3d.geometry.PointCloud)
    finite = np.isfinite(g).all(axis=-1).ravel()
    pts = mio.from_open3d(pcd)
    assert pts.dtype == np.float64 and pts.shape == (finite.sum(), 3)
    np.testing.assert_array_equal(pts, g.reshape(-1, 3)[finite])
    colors = np.asarray(pcd.colors)
    want = np.array([mio.LABEL_COLORS[int(v)] for v in fields["label"].ravel()[finite]])
    np.testing.assert_allclose(colors, want)
    # The array is a view of Open3D's buffer: no copy.
    assert np.shares_memory(mio.from_open3d(pcd), np.asarray(pcd.points))
    kept = mio.to_open3d(g, drop_invalid=False)
    assert len(kept.points) == g.shape[0] * g.shape[1] and not kept.has_colors()
    tpcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(g.reshape(-1, 3)[finite]))
    np.testing.assert_array_equal(mio.from_open3d(tpcd), g.reshape(-1, 3)[finite])
    with pytest.raises(ValueError, match="labels"):
        mio.to_open3d(g, np.full(g.shape[:2], 7, dtype=np.uint8))


def test_scan_data_properties() -> None:
    g, _ = make_grid(4, 5)
    scan = mio.ScanData(points=g, organized=True)
    assert scan.shape == (4, 5)
    assert scan.n_finite == 18


def test_scan_data_goes_where_its_points_go(tmp_path: Path) -> None:
    # miem.detect(miem.io.read(path)): a ScanData is its points array, for a grid and a cloud
    from miem import simulate

    scan = simulate.make_scan(shape=(40, 60), surface="tilted", noise=0.01, dropout=0.02,
                              defects={"spike": 3}, seed=7)
    mio.write(tmp_path / "grid.pcd", scan.points)
    flat = scan.points.reshape(-1, 3)
    mio.write(tmp_path / "cloud.ply", flat[np.isfinite(flat).all(axis=1)])
    for name in ("grid.pcd", "cloud.ply"):
        data = mio.read(tmp_path / name)
        assert np.asarray(data) is data.points  # no copy
        copied = np.array(data, dtype=np.float32, copy=True)
        assert copied.dtype == np.float32 and not np.shares_memory(copied, data.points)
        np.testing.assert_array_equal(copied, data.points.astype(np.float32))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # the cloud's scan-line advice
            got, want = miem.detect(data, num_threads=1), miem.detect(data.points, num_threads=1)
        np.testing.assert_array_equal(got.labels, want.labels)
        np.testing.assert_array_equal(miem.fit_plane(data).normal,
                                      miem.fit_plane(data.points).normal)
    # a grid file's labels are the scan's own
    np.testing.assert_array_equal(miem.detect(mio.read(tmp_path / "grid.pcd")).labels,
                                  miem.detect(scan.points).labels)
