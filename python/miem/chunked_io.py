"""Scan files as Dask arrays, read block by block, and a writer that streams results back.

Nothing is loaded whole: each block of the returned array reads its own slice of the file when
it is computed (on whichever worker runs it), so memory follows the chunk size, not the scan.
The file must be reachable by the same path from every worker (a shared or local disk).

- :func:`open_npy`: ``.npy`` of shape ``(H, W, 3)`` (a grid) or ``(N, 3)`` (a cloud).
- :func:`open_pcd`: binary PCD; organized (``HEIGHT > 1``) as ``(H, W, 3)``, else ``(N, 3)``.
- :func:`open_las`: LAS/LAZ as ``(N, 3)`` float64 (laspy's chunked reader, one seek per block).
- :class:`NpyWriter`: a ``.npy`` target for ``dask.array.store`` (labels, heights).
- :class:`LasWriter`: a copy of a LAS/LAZ file with ``miem_label`` / ``miem_height`` point
  fields, each a ``dask.array.store`` target (the labels go back beside the points they judge).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Union

import numpy as np

import dask.array as da

__all__ = ["LasWriter", "NpyWriter", "open_las", "open_npy", "open_pcd"]

PathLike = Union[str, "os.PathLike[str]"]


def _path(path: PathLike) -> Path:
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"path: no such file: {p}")
    return p


def _positive(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name}: expected an integer >= 1, got {value!r}")
    return int(value)


class _Memmap:
    """A picklable view of a fixed-layout binary array in a file: each __getitem__ maps the file
    and copies the requested slice (only that slice is read)."""

    def __init__(self, path: Path, offset: int, dtype: np.dtype, shape: tuple) -> None:
        self.path, self.offset, self.dtype, self.shape = str(path), int(offset), dtype, shape
        self.ndim = len(shape)

    def __getitem__(self, key: Any) -> np.ndarray:
        mm = np.memmap(self.path, dtype=self.dtype, mode="r", offset=self.offset,
                       shape=self.shape)
        return np.array(mm[key])


def _xyz_chunks(shape: tuple, chunks: Any) -> tuple:
    if len(shape) == 3:  # a grid: tiles or whole rows, the coordinates in one chunk
        rows, cols = (chunks, shape[1]) if np.isscalar(chunks) else tuple(chunks)[:2]
        return (_positive("chunks", rows), _positive("chunks", cols), 3)
    return (_positive("chunks", chunks if np.isscalar(chunks) else tuple(chunks)[0]), 3)


def open_npy(path: PathLike, chunks: Any = 4096) -> "da.Array":
    """A ``.npy`` scan as a Dask array read block by block (memory-mapped per block).

    Parameters
    ----------
    path : str or path
        ``(H, W, 3)`` grid or ``(N, 3)`` cloud, float32 or float64, C order.
    chunks : int or (int, int)
        Grid: rows per block, or ``(rows, cols)`` tiles. Cloud: points per block.

    Returns
    -------
    dask.array.Array
    """
    p = _path(path)
    from . import _filechecks

    _filechecks.check_npy(p)  # the header against the file's length
    try:
        mm = np.load(p, mmap_mode="r")  # the header only: no data is read
    except Exception as exc:
        raise ValueError(f"path: {p} is not a .npy file ({exc})") from None
    shape, dtype, offset = mm.shape, mm.dtype, int(mm.offset)
    fortran = mm.ndim > 1 and mm.flags.f_contiguous and not mm.flags.c_contiguous
    del mm
    if fortran or dtype.kind != "f" or dtype.itemsize not in (4, 8):
        raise ValueError(f"path: expected a C-order float32/float64 array, got {dtype}"
                         f"{' (Fortran order)' if fortran else ''}")
    if len(shape) not in (2, 3) or shape[-1] != 3:
        raise ValueError(f"path: expected shape (H, W, 3) or (N, 3), got {shape}")
    return da.from_array(_Memmap(p, offset, dtype, shape), chunks=_xyz_chunks(shape, chunks),
                         asarray=False, name=f"npy-{p.name}-{p.stat().st_mtime_ns}")


def _pcd_record(header: dict) -> np.dtype:
    """The little-endian record of a binary PCD point, from its FIELDS/SIZE/TYPE/COUNT."""
    fields, sizes, types = header["FIELDS"], header["SIZE"], header["TYPE"]
    counts = header.get("COUNT", ["1"] * len(fields))
    spec, seen = [], set()
    for k, (name, size, kind, count) in enumerate(zip(fields, sizes, types, counts)):
        name = name if name not in seen else f"{name}#{k}"  # e.g. repeated "_" padding
        seen.add(name)
        code = {"F": "f", "I": "i", "U": "u"}.get(kind.upper(), "V")
        base = f"<{code}{size}" if code != "V" else f"V{size}"
        spec.append((name, base) if int(count) == 1 else (name, base, (int(count),)))
    return np.dtype(spec)


class _PcdXYZ:
    """x, y, z of a binary PCD's records as float (the record layout from its header); each
    __getitem__ maps the file and reads only the records asked for."""

    def __init__(self, path: Path, offset: int, record: np.dtype, shape: tuple) -> None:
        self.path, self.offset, self.record, self.shape = str(path), int(offset), record, shape
        self.ndim = len(shape)
        single = all(record[k].kind == "f" and record[k].itemsize == 4 for k in "xyz")
        self.dtype = np.dtype(np.float32 if single else np.float64)

    def __getitem__(self, key: tuple) -> np.ndarray:
        mm = np.memmap(self.path, dtype=self.record, mode="r", offset=self.offset,
                       shape=self.shape[:-1])
        rec = mm[key[:-1]]
        return np.stack([rec[k].astype(self.dtype) for k in "xyz"], axis=-1)[..., key[-1]]


def open_pcd(path: PathLike, chunks: Any = 4096) -> "da.Array":
    """A binary PCD scan as a Dask array read block by block.

    Parameters
    ----------
    path : str or path
        ``DATA binary`` PCD with x, y, z fields. ``HEIGHT > 1``: an organized ``(H, W, 3)``
        grid; else ``(N, 3)``. (ascii and binary_compressed files cannot be read by blocks:
        convert them, e.g. with ``miem.io``.)
    chunks : int or (int, int)
        As for :func:`open_npy`.

    Returns
    -------
    dask.array.Array
    """
    p = _path(path)
    from . import _filechecks

    header, start = _filechecks.pcd_header(p)  # checked against the file's length
    data = (header.get("DATA") or [""])[0].lower()
    if data != "binary":
        raise ValueError(f"path: {p} is DATA {data}; only binary PCD is read by blocks "
                         "(convert it with miem.io.read / miem.io.write)")
    record = _pcd_record(header)
    if not {"x", "y", "z"} <= set(record.names or ()):
        raise ValueError(f"path: {p} has no x, y, z fields")
    width = int(header["WIDTH"][0])
    height = int(header.get("HEIGHT", ["1"])[0])
    shape = (height, width, 3) if height > 1 else (width * height, 3)
    return da.from_array(_PcdXYZ(p, start, record, shape), chunks=_xyz_chunks(shape, chunks), asarray=False,
                         name=f"pcd-{p.name}-{p.stat().st_mtime_ns}")


def _las_block(path: str, start: int, count: int) -> np.ndarray:
    import laspy

    with laspy.open(path) as reader:
        reader.seek(start)
        pts = reader.read_points(count)
    return np.stack([np.asarray(pts.x), np.asarray(pts.y), np.asarray(pts.z)], axis=-1)


def open_las(path: PathLike, chunks: int = 1 << 22) -> "da.Array":
    """A LAS/LAZ file as an ``(N, 3)`` float64 Dask array (scaled coordinates), each block
    read with laspy (a seek and ``read_points``; LAZ needs ``lazrs``).

    Parameters
    ----------
    path : str or path
    chunks : int
        Points per block.

    Returns
    -------
    dask.array.Array
    """
    import laspy
    from dask import delayed

    p = _path(path)
    step = _positive("chunks", chunks)
    try:
        with laspy.open(str(p)) as reader:
            n = int(reader.header.point_count)
    except Exception as exc:
        raise ValueError(f"path: {p} is not a LAS/LAZ file ({type(exc).__name__}: {exc})"
                         ) from None
    parts = [da.from_delayed(delayed(_las_block, pure=True)(str(p), s, min(step, n - s)),
                             (min(step, n - s), 3), np.float64) for s in range(0, n, step)]
    return da.concatenate(parts) if parts else da.zeros((0, 3), chunks=(1, 3))


class NpyWriter:
    """A ``.npy`` file as a target for ``dask.array.store``: each block is written into the file
    where it belongs, by whichever worker computed it (nothing is gathered).

    >>> w = NpyWriter("labels.npy", res.labels.shape, res.labels.dtype)
    >>> defects, _ = res.defects(da.store(res.labels, w, lock=False, compute=False))
    """

    def __init__(self, path: PathLike, shape: tuple, dtype: Any) -> None:
        self.path = str(path)
        self.shape = tuple(int(s) for s in shape)
        self.dtype = np.dtype(dtype)
        mm = np.lib.format.open_memmap(self.path, mode="w+", dtype=self.dtype, shape=self.shape)
        self.offset = int(mm.offset)
        del mm

    def __setitem__(self, key: Any, value: np.ndarray) -> None:
        mm = np.memmap(self.path, dtype=self.dtype, mode="r+", offset=self.offset,
                       shape=self.shape)
        mm[key] = value
        mm.flush()
        del mm


class _LasField:
    """One point field of an uncompressed LAS file as a ``dask.array.store`` target."""

    def __init__(self, path: str, offset: int, record: np.dtype, count: int, name: str) -> None:
        self.path, self.offset, self.record, self.name = path, offset, record, name
        self.shape, self.dtype = (count,), record[name]

    def __setitem__(self, key: Any, value: np.ndarray) -> None:
        mm = np.memmap(self.path, dtype=self.record, mode="r+", offset=self.offset,
                       shape=self.shape)
        mm[self.name][key] = value
        mm.flush()
        del mm


class LasWriter:
    """A copy of a LAS/LAZ file (written uncompressed, ``.las``) whose points carry two extra
    fields, ``miem_label`` (uint8: ``miem.NORMAL`` ... ``miem.INVALID``) and ``miem_height``
    (float64, the points' units; NaN until written), every other field copied unchanged.

    The copy is written once, chunk by chunk (laspy's chunk iterator: memory follows
    ``chunks``); then ``labels`` and ``height`` are targets for ``dask.array.store`` that write
    each block of results into the points it belongs to, on whichever worker computed it. The
    extra fields are standard LAS "extra bytes": CloudCompare, PDAL and laspy show them as
    scalar fields.

    >>> pts = open_las("part.laz")
    >>> res = miem.dask.detect_points(pts, radius=1.0, min_step=0.1)
    >>> out = LasWriter("part.laz", "part_labels.las")
    >>> da.store([res.labels, res.height], [out.labels, out.height], lock=False)

    Parameters
    ----------
    src : str or path
        The LAS/LAZ file the results belong to (as read by :func:`open_las`).
    dst : str or path
        The copy to write (``.las``; an existing file is replaced). Must differ from ``src``.
    chunks : int
        Points copied per step.
    """

    def __init__(self, src: PathLike, dst: PathLike, chunks: int = 1 << 22) -> None:
        import laspy

        from . import INVALID

        p = _path(src)
        step = _positive("chunks", chunks)
        out = Path(dst)
        if out.suffix.lower() != ".las":
            raise ValueError(f"dst: expected a .las path (written uncompressed, so that blocks "
                             f"can be written in any order), got {out}")
        if out.resolve() == p.resolve():
            raise ValueError(f"dst: must not be the source file {p}")
        try:
            reader = laspy.open(str(p))
        except Exception as exc:
            raise ValueError(f"src: {p} is not a LAS/LAZ file ({type(exc).__name__}: {exc})"
                             ) from None
        with reader:
            src_h = reader.header
            fmt = laspy.PointFormat(src_h.point_format.id)
            for dim in src_h.point_format.extra_dimensions:  # the source's own extra bytes
                fmt.add_extra_dimension(laspy.ExtraBytesParams(dim.name, dim.dtype))
            names = set(fmt.dimension_names)
            clash = names & {"miem_label", "miem_height"}
            if clash:
                raise ValueError(f"src: already has the field(s) {sorted(clash)}")
            header = laspy.LasHeader(point_format=fmt, version=src_h.version)
            header.offsets, header.scales = src_h.offsets, src_h.scales
            header.add_extra_dims([laspy.ExtraBytesParams("miem_label", np.uint8),
                                   laspy.ExtraBytesParams("miem_height", np.float64)])
            count = int(src_h.point_count)
            with laspy.open(str(out), mode="w", header=header) as writer:
                for chunk in reader.chunk_iterator(step):
                    rec = laspy.ScaleAwarePointRecord.zeros(len(chunk), header=header)
                    for name in chunk.array.dtype.names:
                        rec.array[name] = chunk.array[name]
                    rec.array["miem_label"] = int(INVALID)  # until written
                    rec.array["miem_height"] = np.nan
                    writer.write_points(rec)
        with laspy.open(str(out)) as check:
            offset = int(check.header.offset_to_point_data)
            record = check.header.point_format.dtype()
            if int(check.header.point_count) != count:
                raise ValueError(f"dst: wrote {check.header.point_count} of {count} points")
        self.path, self.count = str(out), count
        self.labels = _LasField(self.path, offset, record, count, "miem_label")
        self.height = _LasField(self.path, offset, record, count, "miem_height")
