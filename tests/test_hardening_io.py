"""Readers never allocate or loop on what a header claims: each lying header found by the
bad-input sweep (issue 16, items 2-4) gives a ScanFileError naming the file within seconds, and
all of them together stay under 200 MB peak, read in one fresh interpreter with an address-space
cap. Each file is a small scan written here with the one header field under test changed."""

from __future__ import annotations

import json
import struct
import zipfile

import numpy as np
import pytest

import miem
import miem.io as mio

pytest.importorskip("laspy")
pytest.importorskip("lazrs")
pytest.importorskip("plyfile")
pytest.importorskip("pypcd4")

PEAK_MB = 200
SECONDS = 5.0


def _grid(h=4, w=5, dropout=True):
    y, x = np.mgrid[0:h, 0:w] * 0.5
    g = np.dstack([x, y, np.zeros_like(x)])
    if dropout:
        g[1, 1] = np.nan
    return g


def _patched(src, dst, offset, fmt, *values):
    b = bytearray(src.read_bytes())
    struct.pack_into(fmt, b, offset, *values)
    dst.write_bytes(bytes(b))
    return dst


def _replaced(src, dst, old, new):
    raw = src.read_bytes()
    assert old in raw, (src, old)
    dst.write_bytes(raw.replace(old, new))
    return dst


def _cloud(n=5):
    return np.random.default_rng(0).random((n, 3))


def _bad_files(d):
    """{case: (path, words the message must contain)}"""
    out = {}
    las = d / "g.las"
    mio.write(las, _grid())
    at = las.read_bytes().find(struct.pack("<qq", 4, 5))
    assert at > 0
    for h, w in [(10000, 10000), (20000, 20000), (4, 2**40), (-4, 5)]:
        out[f"las-grid-{h}x{w}"] = (_patched(las, d / f"grid{h}x{w}.las", at, "<qq", h, w),
                                    ["miem grid record"])
    raw = bytearray(las.read_bytes())
    raw[at + 5] ^= 0x01  # one bit: H = 4 + 2**40
    (d / "flip.las").write_bytes(bytes(raw))
    out["las-grid-bit-flip"] = (d / "flip.las", ["miem grid record"])
    for suffix in (".las", ".laz"):
        good = d / f"c{suffix}"
        mio.write(good, _cloud())
        size = good.stat().st_size
        out[f"{suffix[1:]}-vlr-count"] = (
            _patched(good, d / f"vlr{suffix}", 100, "<I", 0xFFFFFFFF), ["VLRs"])
        out[f"{suffix[1:]}-evlr-count"] = (
            _patched(good, d / f"evlr{suffix}", 235, "<QI", size + 1000, 0xFFFFFFFF), ["EVLRs"])
        out[f"{suffix[1:]}-point-count"] = (
            _patched(good, d / f"n{suffix}", 247, "<Q", 10**12), ["points"])
    for enc in ("ascii", "binary", "binary_compressed"):
        good = d / f"{enc}.pcd"
        mio.write(good, np.zeros((300, 3)), encoding=enc)  # compressible: LZF keeps it
        out[f"pcd-{enc}-count"] = (
            _replaced(good, d / f"count-{enc}.pcd", b"COUNT 1 1 1\n", b"COUNT 1 1 1000000000\n"),
            ["COUNT"])
        big = _replaced(good, d / f"wide-{enc}.pcd", b"WIDTH 300\n", b"WIDTH 300000000\n")
        out[f"pcd-{enc}-points"] = (
            _replaced(big, big, b"POINTS 300\n", b"POINTS 300000000\n"), [])
    good = d / "binary_compressed.pcd"
    raw = good.read_bytes()
    start = raw.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n")
    compressed, _ = struct.unpack_from("<II", raw, start)
    out["pcd-lzf-size"] = (_patched(good, d / "lzf.pcd", start, "<II", compressed, 0xFFFFFFF0),
                           ["uncompressed size"])
    for enc in ("ascii", "binary"):
        good = d / f"{enc}.ply"
        mio.write(good, _cloud(), encoding=enc)
        out[f"ply-{enc}-count"] = (
            _replaced(good, d / f"count-{enc}.ply", b"element vertex 5\n",
                      b"element vertex 1000000000\n"), ["end_header"])
    npy = d / "a.npy"
    np.save(npy, np.zeros((5, 3)))
    # same header length: the shape field is padded with spaces
    out["npy-shape"] = (_replaced(npy, d / "shape.npy", b"(5, 3), }", b"(999999999,3),}"),
                        ["truncated"])
    inner = npy.read_bytes().replace(b"(5, 3), }", b"(999999999,3),}")
    with zipfile.ZipFile(d / "shape.npz", "w", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("points.npy", inner)
    out["npz-member-shape"] = (d / "shape.npz", ["points.npy"])
    return out


@pytest.fixture(scope="module")
def bad_files(tmp_path_factory):
    return _bad_files(tmp_path_factory.mktemp("bad"))


@pytest.fixture(scope="module")
def report(bad_files, isolated):
    paths = {k: str(p) for k, (p, _) in bad_files.items()}
    code = isolated.CASES + f"""
import miem.io
paths = {json.dumps(paths)}
result = run_cases({{k: (lambda p=p: miem.io.read(p)) for k, p in paths.items()}})
"""
    rep = isolated(code, timeout=120)
    assert rep["ok"], rep
    return rep


def test_all_lying_headers_stay_under_the_memory_bound(report):
    assert report["peak_mb"] < PEAK_MB, report["peak_mb"]


@pytest.mark.parametrize("case", [
    "las-grid-10000x10000", "las-grid-20000x20000", "las-grid-4x1099511627776", "las-grid--4x5",
    "las-grid-bit-flip", "las-vlr-count", "las-evlr-count", "las-point-count", "laz-vlr-count",
    "laz-evlr-count", "laz-point-count", "pcd-ascii-count", "pcd-binary-count",
    "pcd-binary_compressed-count", "pcd-ascii-points", "pcd-binary-points",
    "pcd-binary_compressed-points", "pcd-lzf-size", "ply-ascii-count", "ply-binary-count",
    "npy-shape", "npz-member-shape"])
def test_lying_header_gives_scan_file_error(report, bad_files, case):
    path, words = bad_files[case]
    rec = report["result"][case]
    assert not rec["ok"], f"{case}: {path.name} was read"
    assert "ScanFileError" in rec["mro"], rec
    assert path.name in rec["message"]
    for w in words:
        assert w in rec["message"], rec["message"]
    assert rec["seconds"] < SECONDS, rec


def test_the_good_files_still_read(bad_files, tmp_path):
    g = _grid()
    for suffix in (".las", ".laz", ".pcd", ".ply", ".npy", ".npz", ".xyz"):
        path = tmp_path / f"g{suffix}"
        mio.write(path, g)
        back = mio.read(path).points
        assert back.shape == g.shape, suffix
        np.testing.assert_array_equal(back, g)


def test_las_grid_index_must_increase(tmp_path):
    # a grid record that matches the cell count but indexes the same cell twice
    import laspy

    good = tmp_path / "g.las"
    mio.write(good, _grid())
    las = laspy.read(str(good))
    idx = np.asarray(las["index"]).copy()
    idx[1] = idx[0]
    las["index"] = idx
    bad = tmp_path / "dup.las"
    las.write(str(bad))
    with pytest.raises(mio.ScanFileError, match="strictly increasing"):
        mio.read(bad)


def test_big_endian_npy_reads_native_and_detects(tmp_path):
    g = _grid(32, 32, dropout=False)
    g[10, 12, 2] = 3.0
    path = tmp_path / "be.npy"
    np.save(path, g.astype(">f8"))
    scan = mio.read(path)
    assert scan.points.dtype.isnative and scan.points.dtype.itemsize == 8
    np.testing.assert_array_equal(scan.points, g)
    res = miem.detect(scan.points)
    assert np.argwhere(res.abnormal).tolist() == [[10, 12]]


def test_laz_fixed_chunk_size_beyond_the_file_is_refused():
    """Found by fuzz_laz: a LASzip record whose fixed chunk size (4.1e9 points of 38 bytes) made
    lazrs' parallel decoder ask for 157 GB and abort the process. Read in a child process, so a
    regression fails this test instead of killing the suite."""
    import subprocess
    import sys
    from pathlib import Path

    crash = Path(__file__).resolve().parents[1] / "fuzz" / "corpus" / "laz" / "regress-chunk-size.laz"
    code = ("import miem.io as m, sys\n"
            "try:\n    m.read(sys.argv[1])\nexcept m.ScanFileError as e:\n    print('refused:', e)\n")
    proc = subprocess.run([sys.executable, "-c", code, str(crash)], capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "refused:" in proc.stdout and "chunks of 4,127,145,136 points" in proc.stdout
