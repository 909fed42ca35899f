"""miem.chunked_io: scan files read block by block equal the whole-file readers; lying headers
and unsupported layouts are rejected; NpyWriter streams blocks into a .npy."""

from __future__ import annotations

import numpy as np
import pytest

import miem
import miem.io as mio

dask = pytest.importorskip("dask", reason="miem[dask] not installed")
import dask.array as da  # noqa: E402

from miem import chunked_io as cio  # noqa: E402


@pytest.fixture(autouse=True)
def _sync():
    with dask.config.set(scheduler="sync"):
        yield


def grid(h=37, w=29, dtype=np.float32) -> np.ndarray:
    rng = np.random.default_rng(0)
    g = rng.normal(size=(h, w, 3)).astype(dtype)
    g[3, 4] = np.nan
    return g


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_npy_grid_and_cloud(tmp_path, dtype) -> None:
    g = grid(dtype=dtype)
    np.save(tmp_path / "g.npy", g)
    a = cio.open_npy(tmp_path / "g.npy", chunks=(10, 8))
    assert a.chunks == ((10, 10, 10, 7), (8, 8, 8, 5), (3,)) and a.dtype == dtype
    np.testing.assert_array_equal(a.compute(), g)
    np.testing.assert_array_equal(a[12:20, 3:9].compute(), g[12:20, 3:9])
    np.save(tmp_path / "p.npy", g.reshape(-1, 3))
    b = cio.open_npy(tmp_path / "p.npy", chunks=100)
    assert b.chunks[0][0] == 100
    np.testing.assert_array_equal(b.compute(), g.reshape(-1, 3))


def test_npy_bad_files(tmp_path) -> None:
    g = grid()
    np.save(tmp_path / "g.npy", g)
    data = (tmp_path / "g.npy").read_bytes()
    (tmp_path / "short.npy").write_bytes(data[:-100])  # the header promises more than is there
    with pytest.raises(ValueError, match="truncated"):
        cio.open_npy(tmp_path / "short.npy")
    np.save(tmp_path / "f.npy", np.asfortranarray(g))
    with pytest.raises(ValueError, match="Fortran"):
        cio.open_npy(tmp_path / "f.npy")
    np.save(tmp_path / "i.npy", np.zeros((4, 3), dtype=np.int32))
    with pytest.raises(ValueError, match="float32/float64"):
        cio.open_npy(tmp_path / "i.npy")
    np.save(tmp_path / "s.npy", np.zeros((4, 2)))
    with pytest.raises(ValueError, match="shape"):
        cio.open_npy(tmp_path / "s.npy")
    (tmp_path / "x.npy").write_bytes(b"not a numpy file at all")
    with pytest.raises(ValueError, match="npy"):
        cio.open_npy(tmp_path / "x.npy")
    with pytest.raises(ValueError, match="no such file"):
        cio.open_npy(tmp_path / "missing.npy")
    with pytest.raises(ValueError, match="chunks"):
        cio.open_npy(tmp_path / "g.npy", chunks=0)


def test_pcd_organized_and_not(tmp_path) -> None:
    pytest.importorskip("pypcd4")
    g = grid()
    mio.write(tmp_path / "g.pcd", g, encoding="binary")
    a = cio.open_pcd(tmp_path / "g.pcd", chunks=(9, 29))
    assert a.shape == g.shape
    np.testing.assert_array_equal(a.compute(), mio.read(tmp_path / "g.pcd").points)
    np.testing.assert_array_equal(a.compute(), g)
    mio.write(tmp_path / "p.pcd", g.reshape(-1, 3), encoding="binary")
    b = cio.open_pcd(tmp_path / "p.pcd", chunks=128)
    np.testing.assert_array_equal(b.compute(), g.reshape(-1, 3))
    data = (tmp_path / "p.pcd").read_bytes()
    (tmp_path / "short.pcd").write_bytes(data[:-60])
    with pytest.raises(ValueError, match="truncated"):
        cio.open_pcd(tmp_path / "short.pcd")
    mio.write(tmp_path / "a.pcd", g.reshape(-1, 3), encoding="ascii")
    with pytest.raises(ValueError, match="only binary"):
        cio.open_pcd(tmp_path / "a.pcd")


@pytest.mark.parametrize("ext", ["las", "laz"])
def test_las_blocks_equal_whole_file(tmp_path, ext) -> None:
    pytest.importorskip("laspy")
    if ext == "laz":
        pytest.importorskip("lazrs")
    pts = grid(50, 40, np.float64).reshape(-1, 3) * 100.0
    pts = pts[np.isfinite(pts).all(axis=1)]
    mio.write(tmp_path / f"p.{ext}", pts)
    a = cio.open_las(tmp_path / f"p.{ext}", chunks=333)
    assert a.chunks[0][0] == 333 and a.shape == pts.shape
    np.testing.assert_array_equal(a.compute(), mio.read(tmp_path / f"p.{ext}").points)
    np.testing.assert_array_equal(a[700:1400].compute(), mio.read(tmp_path / f"p.{ext}")
                                  .points[700:1400])
    (tmp_path / "bad.las").write_bytes(b"LASF" + b"\0" * 50)
    with pytest.raises(ValueError, match="LAS"):
        cio.open_las(tmp_path / "bad.las")


def test_npy_writer_streams_detection(tmp_path) -> None:
    import miem.dask as mdask

    yy, xx = np.mgrid[0:90, 0:70] * 0.3
    g = np.dstack([xx, yy, 0.01 * np.sin(xx)])
    g[30, 35, 2] += 2.0
    g[44, 20, 2] += 2.0  # a burr over two passes, cut by the block border at row 45
    g[45, 21, 2] += 1.0
    np.save(tmp_path / "g.npy", g)
    res = mdask.detect(cio.open_npy(tmp_path / "g.npy", chunks=(45, 35)), preset="paper")
    labels = cio.NpyWriter(tmp_path / "labels.npy", res.labels.shape, res.labels.dtype)
    height = cio.NpyWriter(tmp_path / "height.npy", res.height.shape, res.height.dtype)
    defects, *_ = res.defects(da.store([res.labels, res.height], [labels, height], lock=False,
                                       compute=False))
    want = miem.detect(g, preset="paper")
    np.testing.assert_array_equal(np.load(tmp_path / "labels.npy"), want.labels)
    np.testing.assert_array_equal(np.load(tmp_path / "height.npy"), want.height)
    assert [d.indices.tolist() for d in defects] == [d.indices.tolist() for d in want.defects]
    assert len(defects) == 2


@pytest.mark.parametrize("ext", ["las", "laz"])
def test_las_writer_streams_cloud_labels(tmp_path, ext) -> None:
    laspy = pytest.importorskip("laspy")
    if ext == "laz":
        pytest.importorskip("lazrs")
    import miem.dask as mdask

    rng = np.random.default_rng(3)
    xy = rng.uniform(0.0, 20.0, (3000, 2))
    pts = np.column_stack([xy, 0.02 * np.sin(xy[:, 0])])
    pts[[10, 1500, 2900], 2] += 1.5  # three spikes, in different chunks
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales, header.offsets = np.array([1e-4] * 3), np.zeros(3)
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts.T
    las.intensity = np.arange(3000) % 65536
    las.write(tmp_path / f"p.{ext}")
    cloud = cio.open_las(tmp_path / f"p.{ext}", chunks=700)
    kw = dict(preset="paper", radius=1.2, min_step=0.15)
    res = mdask.detect_points(cloud, **kw)
    out = cio.LasWriter(tmp_path / f"p.{ext}", tmp_path / "labels.las", chunks=500)
    da.store([res.labels, res.height], [out.labels, out.height], lock=False)
    back = laspy.read(tmp_path / "labels.las")
    want = miem.detect(cloud.compute(), **kw)  # the points as the file holds them
    np.testing.assert_array_equal(np.asarray(back["miem_label"]), want.labels)
    np.testing.assert_array_equal(np.asarray(back["miem_height"]), want.height)
    assert set(np.flatnonzero(want.labels == miem.ABNORMAL)) >= {10, 1500, 2900}
    # every source field is copied unchanged
    np.testing.assert_array_equal(back.X, las.X)
    np.testing.assert_array_equal(back.intensity, las.intensity)
    with pytest.raises(ValueError, match="dst: expected a .las"):
        cio.LasWriter(tmp_path / f"p.{ext}", tmp_path / "x.laz")
    with pytest.raises(ValueError, match="already has"):
        cio.LasWriter(tmp_path / "labels.las", tmp_path / "again.las")
    with pytest.raises(ValueError, match="src: .* not a LAS"):
        (tmp_path / "bad.las").write_bytes(b"LASF" + b"\0" * 50)
        cio.LasWriter(tmp_path / "bad.las", tmp_path / "o.las")
