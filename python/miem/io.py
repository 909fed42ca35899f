"""Scan files in and out: PCD, PLY, LAS/LAZ, text columns, NumPy, Gocator CSV, Open3D.

Every reader returns a :class:`ScanData`: the points, organized ``(H, W, 3)`` when the file keeps
a grid (an organized PCD, a Gocator height map, a file written here from a grid), else
``(N, 3)``, plus the file's other per-point fields. Every writer stores the points and any extra
per-point fields (for example ``label``, ``height``, ``angle`` from :func:`miem.detect`), writes to
a temporary file in the target's directory and renames it into place, so a failure never leaves
a half-written file behind and never replaces a good one.

The parsers are the maintained libraries of each format (``pypcd4``, ``plyfile``, ``laspy`` with
``lazrs``), installed with ``pip install "miem[io]"``; text, NumPy and Gocator CSV need only
NumPy. A broken file (empty, truncated, corrupt, no x/y/z) raises :class:`ScanFileError`, a
``ValueError`` that names the file and what is wrong.

>>> import miem, miem.io
>>> scan = miem.io.read("part.pcd")                 # organized PCD -> (H, W, 3)
>>> res = miem.detect(scan.points)
>>> miem.io.write("part_labels.ply", scan.points, miem.io.result_fields(res))
"""

from __future__ import annotations

import contextlib
import csv
import importlib
import io as _stdio
import os
import struct
import tempfile
import warnings
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Union

import numpy as np

__all__ = [
    "FORMATS",
    "LABEL_COLORS",
    "MissingDependencyError",
    "ScanData",
    "ScanFileError",
    "format_from_path",
    "from_open3d",
    "grid_from_scanlines",
    "read",
    "read_gocator_csv",
    "result_fields",
    "to_open3d",
    "write",
]

PathLike = Union[str, "os.PathLike[str]"]

#: Formats by name, with the file suffixes that select them and whether they can be written.
FORMATS: dict[str, dict[str, Any]] = {
    "pcd": {"suffixes": (".pcd",), "write": True, "extra": "io"},
    "ply": {"suffixes": (".ply",), "write": True, "extra": "io"},
    "las": {"suffixes": (".las",), "write": True, "extra": "io"},
    "laz": {"suffixes": (".laz",), "write": True, "extra": "io"},
    "xyz": {"suffixes": (".xyz", ".pts"), "write": True, "extra": None},
    "csv": {"suffixes": (".csv",), "write": True, "extra": None},
    "txt": {"suffixes": (".txt", ".asc"), "write": True, "extra": None},
    "npy": {"suffixes": (".npy",), "write": True, "extra": None},
    "npz": {"suffixes": (".npz",), "write": True, "extra": None},
    "gocator-csv": {"suffixes": (), "write": False, "extra": None},
}

#: RGB colours (0..1) used for each label by :func:`to_open3d` and the plots:
#: NORMAL grey, ABNORMAL red, EDGE blue, INVALID black.
LABEL_COLORS: dict[int, tuple[float, float, float]] = {
    0: (0.62, 0.62, 0.62),
    1: (0.86, 0.08, 0.08),
    2: (0.12, 0.42, 0.90),
    3: (0.0, 0.0, 0.0),
}

# Organized files written by miem keep their grid shape in the file:
_GRID_TAG = "miem-grid"  # PLY obj_info / text comment: "miem-grid H W"
_LAS_VLR_USER = "miem"  # LAS: VLR with the shape, plus an "index" extra dimension
_LAS_VLR_ID = 1
_PCD_ENCODINGS = ("ascii", "binary", "binary_compressed")


class ScanFileError(ValueError):
    """A scan file that cannot be read (empty, truncated, corrupt) or written.

    Attributes
    ----------
    path : pathlib.Path
        The file.
    reason : str
        What is wrong.
    """

    def __init__(self, path: PathLike, reason: str) -> None:
        self.path = Path(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


class MissingDependencyError(ImportError):
    """An optional package is not installed; the message names the pip extra to install."""


@dataclass(eq=False)
class ScanData:
    """A scan read from a file.

    Attributes
    ----------
    points : ndarray, shape (H, W, 3) or (N, 3), float32 or float64
        Coordinates in the file's units. Organized files give ``(H, W, 3)`` with NaN for cells
        without a return; others ``(N, 3)``.
    fields : dict of str to ndarray
        Other per-point fields (``label``, ``height``, ``intensity``, ...), each of shape
        ``points.shape[:-1]``.
    organized : bool
        True when ``points`` is a grid ``(H, W, 3)``.
    path : pathlib.Path or None
        The file it was read from.
    format : str
        Format name (a key of :data:`FORMATS`).
    """

    points: np.ndarray
    fields: dict[str, np.ndarray] = field(default_factory=dict)
    organized: bool = False
    path: Path | None = None
    format: str = ""

    @property
    def shape(self) -> tuple[int, ...]:
        """``(H, W)`` for a grid, ``(N,)`` otherwise."""
        return tuple(self.points.shape[:-1])

    @property
    def n_finite(self) -> int:
        """Number of points with three finite coordinates."""
        return int(np.count_nonzero(np.isfinite(self.points).all(axis=-1)))

    def __array__(self, dtype: Any = None, copy: bool | None = None) -> np.ndarray:
        """``points``, so that a ScanData goes wherever a point array does
        (``miem.detect(miem.io.read(path))``, ``np.asarray(scan)``)."""
        if copy:
            return np.array(self.points, dtype=dtype, copy=True)
        return np.asarray(self.points, dtype=dtype)


# ---------------------------------------------------------------------------------------------
# helpers


def _require(module: str, what: str, extra: str | None = "io", pip_name: str = "") -> Any:
    """Import an optional dependency or raise :class:`MissingDependencyError` naming the extra."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        hint = (f'pip install "miem[{extra}]" (from a source checkout: pip install ".[{extra}]")'
                if extra else f"pip install {pip_name or module}")
        raise MissingDependencyError(
            f"{what} needs the optional package {pip_name or module!r}, which is not installed: "
            f"{hint}"
        ) from exc


def format_from_path(path: PathLike) -> str:
    """The format name that a file name's suffix selects.

    Parameters
    ----------
    path : str or os.PathLike
        File name.

    Returns
    -------
    str
        A key of :data:`FORMATS` (``.csv`` gives ``"csv"``; :func:`read` then looks inside for a
        Gocator export).

    Raises
    ------
    ValueError
        Unknown suffix.
    """
    suffix = Path(path).suffix.lower()
    for name, spec in FORMATS.items():
        if suffix in spec["suffixes"]:
            return name
    known = sorted(s for spec in FORMATS.values() for s in spec["suffixes"])
    raise ValueError(
        f"{path}: cannot tell the scan format from the suffix {suffix!r}; use one of "
        f"{', '.join(known)} or pass format= (one of {', '.join(FORMATS)})"
    )


def _check_format(fmt: str) -> str:
    name = fmt.lower()
    if name not in FORMATS:
        raise ValueError(f"format: expected one of {', '.join(FORMATS)}, got {fmt!r}")
    return name


def _as_points(points: Any, name: str = "points") -> np.ndarray:
    arr = np.asarray(points)
    if arr.dtype.names is not None:
        from ._api import _xyz_fields

        arr = _xyz_fields(arr, name)
    if arr.dtype.kind in "iub":
        arr = arr.astype(np.float64)
    elif arr.dtype.kind != "f":
        raise ValueError(f"{name}: expected a real numeric array, got dtype {arr.dtype}")
    if arr.ndim not in (2, 3) or arr.shape[-1] != 3:
        raise ValueError(f"{name}: expected shape (N, 3) or (H, W, 3), got {arr.shape}")
    if arr.dtype.itemsize not in (4, 8):
        arr = arr.astype(np.float64)
    return arr


def _as_fields(fields: Mapping[str, Any] | None, shape: tuple[int, ...]) -> dict:
    out: dict[str, np.ndarray] = {}
    for key, value in (fields or {}).items():
        if not isinstance(key, str) or not key.isidentifier() or key.lower() in ("x", "y", "z"):
            raise ValueError(
                f"fields: names must be identifiers other than x, y, z; got {key!r}"
            )
        arr = np.asarray(value)
        if arr.dtype.kind == "b":
            arr = arr.astype(np.uint8)
        if arr.dtype.kind not in "iuf":
            raise ValueError(f"fields[{key!r}]: expected a numeric array, got dtype {arr.dtype}")
        if arr.shape != shape:
            raise ValueError(
                f"fields[{key!r}]: expected shape {shape} (one value per point), got {arr.shape}"
            )
        out[key] = arr
    return out


def result_fields(result: Any) -> dict[str, np.ndarray]:
    """The per-point arrays of a :class:`miem.DetectResult` as fields for :func:`write`.

    Parameters
    ----------
    result : miem.DetectResult
        What :func:`miem.detect` returned.

    Returns
    -------
    dict of str to ndarray
        ``label`` (uint8, :class:`miem.Label` values), ``flags`` (uint8 bitmask of the flagged
        directions), ``angle`` (float64, degrees, NaN where none) and ``height`` (float64, signed
        distance from the local surface in the scan's units, protrusion > 0).
    """
    return {
        "label": np.asarray(result.labels, dtype=np.uint8),
        "flags": np.asarray(result.flags, dtype=np.uint8),
        "angle": np.asarray(result.angle, dtype=np.float64),
        "height": np.asarray(result.height, dtype=np.float64),
    }


def _native(arr: np.ndarray) -> np.ndarray:
    """`arr` in native byte order (a big-endian file's values are swapped once, here)."""
    return arr if arr.dtype.isnative else arr.astype(arr.dtype.newbyteorder("="))


def _filechecks() -> Any:
    from . import _filechecks as checks  # imports ScanFileError from here

    return checks


def _scan(points: np.ndarray, fields: dict, path: Path, fmt: str) -> ScanData:
    """Validate what a reader produced and wrap it."""
    if points.ndim not in (2, 3) or points.shape[-1] != 3:
        raise ScanFileError(path, f"expected x, y, z coordinates, got an array {points.shape}")
    if points.dtype.kind == "f" and points.dtype.itemsize not in (4, 8):
        points = points.astype(np.float64)  # float16 / longdouble: the core reads 32 or 64 bits
    points = _native(points)
    fields = {k: _native(v) for k, v in fields.items()}
    n = int(np.prod(points.shape[:-1]))
    if n == 0:
        raise ScanFileError(path, "the file holds no points")
    for key, value in fields.items():
        if value.shape != points.shape[:-1]:
            raise ScanFileError(
                path, f"field {key!r} has {value.shape} values for {points.shape[:-1]} points"
            )
    return ScanData(points=points, fields=fields, organized=points.ndim == 3, path=path,
                    format=fmt)


@contextlib.contextmanager
def _atomic(path: Path) -> Iterator[Path]:
    """Yield a temporary path beside `path`; rename it onto `path` only if the block succeeds."""
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise ScanFileError(path, f"the directory {parent} does not exist")
    fd, tmp_name = tempfile.mkstemp(dir=parent, prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}")
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        # mkstemp makes the file private (0600); give it the permissions a new file would get.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def _read_bytes_head(path: Path, n: int = 512) -> bytes:
    with open(path, "rb") as fh:
        return fh.read(n)


# ---------------------------------------------------------------------------------------------
# reading


def read(path: PathLike, format: str | None = None) -> ScanData:
    """Read a scan file.

    Parameters
    ----------
    path : str or os.PathLike
        The file. Its suffix selects the format unless `format` is given: ``.pcd`` (ascii,
        binary, binary_compressed; ``HEIGHT > 1`` gives a grid), ``.ply``, ``.las``, ``.laz``,
        ``.xyz``/``.pts``/``.txt``/``.asc`` (whitespace columns), ``.csv`` (comma columns, or a
        Gocator CSV export, recognised by its ``Info`` header), ``.npy``, ``.npz``.
    format : str, optional
        One of :data:`FORMATS`, to override the suffix.

    Returns
    -------
    ScanData
        ``points`` ``(H, W, 3)`` for organized files, else ``(N, 3)``; float32 when the file
        stores float32, else float64. Other per-point values are in ``fields``.

    Raises
    ------
    FileNotFoundError
        No such file.
    ScanFileError
        Empty, truncated or corrupt file, or no x, y, z in it (a ``ValueError``).
    MissingDependencyError
        The format's library is not installed (an ``ImportError`` naming the pip extra).
    """
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such file")
    if p.is_dir():
        raise ScanFileError(p, "is a directory, not a scan file (name the files in it)")
    fmt = format_from_path(p) if format is None else _check_format(format)
    if p.stat().st_size == 0:
        raise ScanFileError(p, "the file is empty")
    if fmt == "csv" and _is_gocator(p):
        fmt = "gocator-csv"
    reader = _READERS[fmt]
    try:
        return reader(p)
    except (ScanFileError, MissingDependencyError, MemoryError):
        raise
    except Exception as exc:  # the parsers raise many kinds on a corrupt file
        raise ScanFileError(p, f"cannot read it as {fmt}: {type(exc).__name__}: {exc}") from exc
    except BaseException as exc:  # a Rust parser's panic (lazrs) is a BaseException
        if type(exc).__name__ != "PanicException":
            raise
        raise ScanFileError(p, f"cannot read it as {fmt}: the parser panicked: {exc}") from exc


def _is_gocator(path: Path) -> bool:
    head = _read_bytes_head(path, 64).lstrip(b"\xef\xbb\xbf").splitlines()
    return bool(head) and head[0].strip() == b"Info"


def _read_pcd(path: Path) -> ScanData:
    _require("pypcd4", "reading PCD files")
    from pypcd4 import PointCloud

    _filechecks().pcd_header(path)
    try:
        pc = PointCloud.from_path(path)
    except Exception as exc:
        raise ScanFileError(path, f"corrupt PCD file: {type(exc).__name__}: {exc}") from exc
    meta = pc.metadata
    data = pc.pc_data
    n = int(meta.points)
    if meta.width * meta.height != n:
        raise ScanFileError(
            path, f"header says WIDTH {meta.width} x HEIGHT {meta.height} but POINTS {n}"
        )
    if data.ndim == 0:  # np.loadtxt of a single ascii row
        data = data.reshape(1)
    if data.shape[0] != n:
        raise ScanFileError(
            path, f"truncated: header says {n} points, the data holds {data.shape[0]}"
        )
    names = data.dtype.names or ()
    if not {"x", "y", "z"} <= set(names):
        raise ScanFileError(path, f"no x, y, z fields (fields: {', '.join(names)})")
    pts = np.stack([data["x"], data["y"], data["z"]], axis=-1)
    if pts.dtype.kind != "f":
        pts = pts.astype(np.float64)
    fields = {k: np.ascontiguousarray(data[k]) for k in names
              if k not in ("x", "y", "z") and not k.startswith("#$%&~~")}
    if meta.height > 1:
        shape = (int(meta.height), int(meta.width))
        pts = pts.reshape(shape + (3,))
        fields = {k: v.reshape(shape) for k, v in fields.items()}
    return _scan(pts, fields, path, "pcd")


def _grid_tag(lines: list[str]) -> tuple[int, int] | None:
    for line in lines:
        parts = line.replace("#", " ").split()
        if len(parts) == 3 and parts[0] == _GRID_TAG:
            try:
                return int(parts[1]), int(parts[2])
            except ValueError:
                return None
    return None


def _reshape_grid(path: Path, pts: np.ndarray, fields: dict, grid: tuple[int, int] | None):
    if grid is None:
        return pts, fields
    h, w = grid
    if h * w != pts.shape[0]:
        raise ScanFileError(
            path, f"{_GRID_TAG} {h} {w} announces {h * w} points, the file holds {pts.shape[0]}"
        )
    return pts.reshape(h, w, 3), {k: v.reshape(h, w) for k, v in fields.items()}


def _read_ply(path: Path) -> ScanData:
    plyfile = _require("plyfile", "reading PLY files")
    _filechecks().check_ply(path)
    try:
        ply = plyfile.PlyData.read(str(path), mmap=False)
    except Exception as exc:
        raise ScanFileError(path, f"corrupt PLY file: {type(exc).__name__}: {exc}") from exc
    try:
        vertex = ply["vertex"]
    except KeyError:
        raise ScanFileError(path, "no 'vertex' element") from None
    data = vertex.data
    names = data.dtype.names or ()
    if not {"x", "y", "z"} <= set(names):
        raise ScanFileError(path, f"no x, y, z vertex properties (has: {', '.join(names)})")
    pts = np.stack([data["x"], data["y"], data["z"]], axis=-1)
    if pts.dtype.kind != "f" or pts.dtype.itemsize not in (4, 8):
        pts = pts.astype(np.float64)
    fields = {k: np.ascontiguousarray(data[k]) for k in names
              if k not in ("x", "y", "z") and data.dtype[k].kind in "iuf"
              and data.dtype[k].shape == ()}
    pts, fields = _reshape_grid(path, pts, fields, _grid_tag(list(ply.obj_info)))
    return _scan(pts, fields, path, "ply")


def _read_las(path: Path, fmt: str = "las") -> ScanData:
    laspy = _require("laspy", f"reading {fmt.upper()} files")
    if fmt == "laz":
        _require("lazrs", "reading LAZ files")
    _filechecks().check_las(path, compressed=fmt == "laz")
    try:
        las = laspy.read(str(path))
    except Exception as exc:
        raise ScanFileError(path, f"corrupt {fmt.upper()} file: {type(exc).__name__}: {exc}") \
            from exc
    n = len(las.points)
    if n != int(las.header.point_count):
        raise ScanFileError(
            path, f"truncated: header says {las.header.point_count} points, read {n}"
        )
    pts = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=-1)
    pts = pts.astype(np.float64)
    fields: dict[str, np.ndarray] = {}
    standard = set(las.point_format.dimension_names)
    for name in ("intensity", "classification", "gps_time", "red", "green", "blue"):
        # Standard dimensions that a writer left all zero carry no information: skip them.
        if name in standard and np.any(np.asarray(las[name]) != 0):
            fields[name] = np.asarray(las[name]).copy()
    for name in las.point_format.extra_dimension_names:
        arr = np.asarray(las[name])
        if arr.ndim == 1:
            fields[name] = arr.copy()
    shape = None
    for vlr in las.vlrs:
        if vlr.user_id == _LAS_VLR_USER and vlr.record_id == _LAS_VLR_ID:
            raw = bytes(vlr.record_data)
            if len(raw) != 16:
                raise ScanFileError(path, "corrupt miem grid record (VLR)")
            shape = tuple(int(v) for v in struct.unpack("<qq", raw))
    if shape is not None and "index" in fields:
        # The file holds only finite points; put them back in their cells.
        h, w = shape
        index = fields.pop("index").astype(np.int64)
        total = _filechecks().check_las_grid(path, shape, index)
        full = np.full((total, 3), np.nan)
        full[index] = pts
        pts = full
        for k, v in list(fields.items()):
            # Dropouts were not stored: NaN floats, 0 integers, and label INVALID (3).
            fill = np.nan if v.dtype.kind == "f" else (3 if k == "label" else 0)
            out = np.full(total, fill, dtype=v.dtype)
            out[index] = v
            fields[k] = out
        if h > 0:
            pts = pts.reshape(h, w, 3)
            fields = {k: v.reshape(h, w) for k, v in fields.items()}
    return _scan(pts, fields, path, fmt)


def _read_laz(path: Path) -> ScanData:
    return _read_las(path, "laz")


def _text_lines_head(path: Path, n: int = 64) -> list[str]:
    lines = []
    with open(path, encoding="utf-8", errors="replace") as fh:
        for i, line in enumerate(fh):
            if i >= n:
                break
            lines.append(line.rstrip("\r\n"))
    return lines


def _is_number(tok: str) -> bool:
    try:
        float(tok)
    except ValueError:
        return False
    return True


_UINT8_FIELDS = ("label", "flags", "truth")


def _fits_uint8(col: np.ndarray) -> bool:
    return bool(np.all(np.isfinite(col)) and np.all(col == np.round(col))
                and col.min() >= 0 and col.max() <= 255)


def _read_text(path: Path, fmt: str) -> ScanData:
    head = _text_lines_head(path)
    comments = [ln for ln in head if ln.lstrip().startswith(("#", "//"))]
    body = [ln for ln in head if ln.strip() and not ln.lstrip().startswith(("#", "//"))]
    if not body:
        raise ScanFileError(path, "no data rows (only comments or blank lines)")
    first = body[0]
    delimiter = "," if fmt == "csv" or ("," in first) else None
    tokens = [t.strip() for t in (first.split(",") if delimiter else first.split())]
    names: list[str] | None = None
    skip = 0
    if not all(_is_number(t) for t in tokens):
        names = [t.strip().strip('"').lower() for t in tokens]
        skip = head.index(first) + 1  # np.loadtxt counts comment lines in skiprows
    else:
        # "# x y z label ..." comment written by miem (or by hand) names the columns.
        for ln in comments:
            cand = ln.lstrip("#/ ").replace(",", " ").split()
            if len(cand) == len(tokens) and cand[:3] == ["x", "y", "z"]:
                names = cand
                break
    try:
        with warnings.catch_warnings():  # "input contained no data": reported just below
            warnings.filterwarnings("ignore", "loadtxt: input contained no data", UserWarning)
            table = np.loadtxt(path, delimiter=delimiter, comments=("#", "//"), skiprows=skip,
                               dtype=np.float64, ndmin=2, encoding="utf-8")
    except ValueError as exc:
        raise ScanFileError(path, f"bad text row: {exc}") from exc
    if table.shape[0] == 0:
        raise ScanFileError(path, "no data rows")
    ncol = table.shape[1]
    if ncol < 3:
        raise ScanFileError(path, f"expected at least 3 columns (x y z), got {ncol}")
    if names is None:
        names = ["x", "y", "z"] + [f"col{i}" for i in range(3, ncol)]
    if len(names) != ncol:
        raise ScanFileError(path, f"the header names {len(names)} columns, rows have {ncol}")
    try:
        ix = [names.index(a) for a in ("x", "y", "z")]
    except ValueError:
        raise ScanFileError(path, f"no x, y, z columns (header: {', '.join(names)})") from None
    pts = np.ascontiguousarray(table[:, ix])
    fields = {}
    for j, name in enumerate(names):
        if j in ix:
            continue
        col = table[:, j]
        key = name if name.isidentifier() else f"col{j}"
        if name in _UINT8_FIELDS and _fits_uint8(col):
            col = col.astype(np.uint8)
        fields[key] = np.ascontiguousarray(col)
    pts, fields = _reshape_grid(path, pts, fields, _grid_tag(comments))
    return _scan(pts, fields, path, fmt)


def _read_npy(path: Path) -> ScanData:
    _filechecks().check_npy(path)
    try:
        with open(path, "rb") as fh:
            arr = np.load(fh, allow_pickle=False)
    except Exception as exc:
        raise ScanFileError(path, f"corrupt .npy file: {type(exc).__name__}: {exc}") from exc
    if arr.dtype.names:
        names = arr.dtype.names
        if not {"x", "y", "z"} <= set(names):
            raise ScanFileError(path, f"structured array without x, y, z (has {names})")
        pts = np.stack([arr["x"], arr["y"], arr["z"]], axis=-1)
        fields = {k: np.ascontiguousarray(arr[k]) for k in names if k not in ("x", "y", "z")}
    else:
        pts, fields = arr, {}
    if pts.dtype.kind in "iu":
        pts = pts.astype(np.float64)
    if pts.dtype.kind != "f" or pts.ndim not in (2, 3) or pts.shape[-1] != 3:
        raise ScanFileError(path, f"expected an (N, 3) or (H, W, 3) float array, got "
                                  f"{pts.shape} {pts.dtype}")
    return _scan(pts, fields, path, "npy")


def _read_npz(path: Path) -> ScanData:
    _filechecks().check_npz(path)
    try:
        # Open the file here: np.load leaks its own handle when a truncated zip fails to open.
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except Exception as exc:
        raise ScanFileError(path, f"corrupt .npz file: {type(exc).__name__}: {exc}") from exc
    if "points" in arrays:
        key = "points"
    else:
        cands = [k for k, v in arrays.items() if v.ndim in (2, 3) and v.shape[-1] == 3]
        if len(cands) != 1:
            raise ScanFileError(
                path, f"no 'points' array and no single (N, 3) / (H, W, 3) array among "
                      f"{sorted(arrays)}"
            )
        key = cands[0]
    pts = arrays.pop(key)
    if pts.dtype.kind in "iu":
        pts = pts.astype(np.float64)
    if pts.dtype.kind != "f" or pts.ndim not in (2, 3) or pts.shape[-1] != 3:
        raise ScanFileError(path, f"'{key}' is not an (N, 3) or (H, W, 3) float array: "
                                  f"{pts.shape} {pts.dtype}")
    fields = {k: v for k, v in arrays.items()
              if v.shape == pts.shape[:-1] and v.dtype.kind in "iufb"}
    return _scan(pts, fields, path, "npz")


def read_gocator_csv(path: PathLike, frame: int = 0) -> ScanData:
    """Read a height map exported as CSV by the LMI Gocator software.

    The export holds text blocks (``Info``, ``DeviceInfo``, ...) and one ``Part`` block per
    frame: a line with ``Row Count``, ``Column Count`` and the offsets, a ``Y\\X`` line with the
    column x values, then one line per row: its y value and the row's z values (empty = no
    data).

    Parameters
    ----------
    path : str or os.PathLike
        The CSV file.
    frame : int
        Which ``Part`` block to read (0 = the first).

    Returns
    -------
    ScanData
        ``points`` ``(Row Count, Column Count, 3)`` float64 in the export's units (mm): x from
        the ``Y\\X`` line, y from each row, z; NaN where the cell is empty. ``format`` is
        ``"gocator-csv"``.

    Raises
    ------
    ScanFileError
        Not a Gocator export, no such frame, or a truncated/corrupt grid.
    """
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such file")
    if p.stat().st_size == 0:
        raise ScanFileError(p, "the file is empty")
    try:
        return _read_gocator(p, frame)
    except ScanFileError:
        raise
    except Exception as exc:
        raise ScanFileError(p, f"corrupt Gocator CSV: {type(exc).__name__}: {exc}") from exc


def _read_gocator(path: Path, frame: int = 0) -> ScanData:
    with open(path, encoding="utf-8-sig", errors="replace", newline="") as fh:
        lines = fh.read().splitlines()
    if not lines or lines[0].strip() != "Info":
        raise ScanFileError(path, "not a Gocator CSV export (the first line is not 'Info')")
    parts = [i for i, ln in enumerate(lines) if ln.strip() == "Part"]
    if not parts:
        raise ScanFileError(path, "no 'Part' block (no height map in this export)")
    if not 0 <= frame < len(parts):
        raise ScanFileError(path, f"frame {frame} requested, the file holds {len(parts)}")
    i = parts[frame]
    if i + 3 >= len(lines):
        raise ScanFileError(path, "truncated 'Part' block")
    keys = [k.strip() for k in next(csv.reader([lines[i + 1]]))]
    vals = [v.strip() for v in next(csv.reader([lines[i + 2]]))]
    info = dict(zip(keys, vals))
    try:
        n_rows = int(info["Row Count"])
        n_cols = int(info["Column Count"])
    except (KeyError, ValueError):
        raise ScanFileError(path, "the 'Part' block has no valid 'Row Count' / 'Column Count'") \
            from None
    header = lines[i + 3]
    if not header.startswith("Y\\X"):
        raise ScanFileError(path, "no 'Y\\X' line after the 'Part' header")
    xs = np.array([float(t) for t in header.split(",")[1:] if t.strip() != ""])
    if xs.size != n_cols:
        raise ScanFileError(path, f"'Y\\X' line has {xs.size} x values, Column Count {n_cols}")
    rows = lines[i + 4:i + 4 + n_rows]
    if len(rows) < n_rows or any(r.strip() in ("", "End") for r in rows):
        got = next((k for k, r in enumerate(rows) if r.strip() in ("", "End")), len(rows))
        raise ScanFileError(path, f"truncated grid: Row Count {n_rows}, found {got} rows")
    table = np.genfromtxt(_stdio.StringIO("\n".join(rows)), delimiter=",", dtype=np.float64,
                          filling_values=np.nan, invalid_raise=True, usecols=range(n_cols + 1))
    table = np.atleast_2d(table)
    if table.shape != (n_rows, n_cols + 1):
        raise ScanFileError(path, f"grid is {table.shape}, expected ({n_rows}, {n_cols + 1})")
    ys = table[:, 0]
    if not np.all(np.isfinite(ys)):
        raise ScanFileError(path, "a grid row has no y value")
    z = table[:, 1:]
    pts = np.empty((n_rows, n_cols, 3))
    pts[..., 0] = xs[None, :]
    pts[..., 1] = ys[:, None]
    pts[..., 2] = z
    pts[~np.isfinite(z)] = np.nan
    return _scan(pts, {}, path, "gocator-csv")


_READERS = {
    "pcd": _read_pcd,
    "ply": _read_ply,
    "las": _read_las,
    "laz": _read_laz,
    "xyz": lambda p: _read_text(p, "xyz"),
    "txt": lambda p: _read_text(p, "txt"),
    "csv": lambda p: _read_text(p, "csv"),
    "npy": _read_npy,
    "npz": _read_npz,
    "gocator-csv": _read_gocator,
}


# ---------------------------------------------------------------------------------------------
# writing


def write(
    path: PathLike,
    points: Any,
    fields: Mapping[str, Any] | None = None,
    *,
    format: str | None = None,
    encoding: str | None = None,
) -> Path:
    """Write a scan, with extra per-point fields, atomically.

    The file is written to a temporary file in the same directory and renamed onto `path` when
    complete: if anything fails, `path` is left as it was (absent or the old file) and the
    temporary file is removed.

    Parameters
    ----------
    path : str or os.PathLike
        Output file; its suffix selects the format unless `format` is given.
    points : array_like, shape (N, 3) or (H, W, 3), float
        Coordinates. A grid stays a grid: PCD stores ``WIDTH W HEIGHT H``; PLY, text and LAS
        record ``H W`` so that :func:`read` gives the grid back. NaN points (dropouts) are kept,
        except in LAS/LAZ, which cannot store NaN: there only finite points are written, each
        with its position in an ``index`` field, and :func:`read` puts them back as NaN (their
        fields come back as NaN, 0, or 3 = INVALID for ``label``).
    fields : mapping of str to array_like, optional
        Per-point values of shape ``points.shape[:-1]`` (for example :func:`result_fields`),
        stored as extra fields (PCD fields, PLY properties, LAS extra bytes, text columns, NumPy
        arrays) with their dtype.
    format : str, optional
        A writable key of :data:`FORMATS` (not ``"gocator-csv"``).
    encoding : str, optional
        PCD: ``"binary"`` (default), ``"binary_compressed"`` or ``"ascii"``. PLY: ``"binary"``
        (default, little endian) or ``"ascii"``. Ignored by the other formats.

    Returns
    -------
    pathlib.Path
        `path`.

    Raises
    ------
    ValueError
        Bad shapes, field names or format.
    ScanFileError
        The output directory does not exist.
    MissingDependencyError
        The format's library is not installed.
    """
    p = Path(path)
    fmt = format_from_path(p) if format is None else _check_format(format)
    if not FORMATS[fmt]["write"]:
        raise ValueError(f"format: {fmt!r} can be read but not written")
    pts = _as_points(points)
    flds = _as_fields(fields, pts.shape[:-1])
    enc = encoding
    if fmt == "pcd":
        enc = enc or "binary"
        if enc not in _PCD_ENCODINGS:
            raise ValueError(f"encoding: PCD accepts {', '.join(_PCD_ENCODINGS)}, got {enc!r}")
    elif fmt == "ply":
        enc = enc or "binary"
        if enc not in ("binary", "ascii"):
            raise ValueError(f"encoding: PLY accepts 'binary' or 'ascii', got {enc!r}")
    writer = _WRITERS[fmt]
    # Import the format's library before creating any file.
    if fmt == "pcd" and enc == "binary_compressed":
        _require("pypcd4", "writing binary_compressed PCD files")
    elif fmt in ("ply", "las", "laz"):
        _require({"ply": "plyfile", "las": "laspy", "laz": "laspy"}[fmt],
                 f"writing {fmt.upper()} files")
        if fmt == "laz":
            _require("lazrs", "writing LAZ files")
    with _atomic(p) as tmp:
        writer(tmp, pts, flds, enc)
    return p


def _flat(pts: np.ndarray, flds: dict) -> tuple[np.ndarray, dict]:
    return pts.reshape(-1, 3), {k: v.reshape(-1) for k, v in flds.items()}


def _pcd_columns(pts: np.ndarray, flds: dict) -> tuple[list[str], list[np.ndarray]]:
    flat, fflat = _flat(pts, flds)
    names = ["x", "y", "z"] + list(fflat)
    arrays = [flat[:, 0], flat[:, 1], flat[:, 2]] + list(fflat.values())
    types = [a.dtype for a in arrays]
    if any(t.kind not in "iuf" or t.itemsize not in (1, 2, 4, 8) for t in types):
        raise ValueError("fields: PCD stores 1, 2, 4 or 8 byte numbers only")
    types = [np.dtype(np.float32) if t == np.float16 else t.newbyteorder("<") for t in types]
    return names, [np.ascontiguousarray(a, dtype=t) for a, t in zip(arrays, types)]


def _write_pcd(tmp: Path, pts: np.ndarray, flds: dict, enc: str) -> None:
    """PCD v0.7. ascii and binary are written here (no extra needed); binary_compressed (LZF)
    through pypcd4."""
    names, arrays = _pcd_columns(pts, flds)
    h, w = (pts.shape[0], pts.shape[1]) if pts.ndim == 3 else (1, arrays[0].shape[0])
    if enc == "binary_compressed":
        from pypcd4 import Encoding, PointCloud

        pc = PointCloud.from_points(arrays, names, [a.dtype for a in arrays])
        pc.metadata.width, pc.metadata.height = w, h
        with open(tmp, "wb") as fh:
            pc.save(fh, encoding=Encoding(enc))
        return
    header = (
        "# .PCD v0.7 - Point Cloud Data file format (written by miem)\n"
        "VERSION 0.7\n"
        f"FIELDS {' '.join(names)}\n"
        f"SIZE {' '.join(str(a.dtype.itemsize) for a in arrays)}\n"
        f"TYPE {' '.join({'f': 'F', 'i': 'I', 'u': 'U'}[a.dtype.kind] for a in arrays)}\n"
        f"COUNT {' '.join('1' for _ in arrays)}\n"
        f"WIDTH {w}\nHEIGHT {h}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {w * h}\nDATA {enc}\n"
    )
    with open(tmp, "wb") as fh:
        fh.write(header.encode("ascii"))
        if enc == "binary":
            rec = np.empty(w * h, dtype=[(f"f{i}", a.dtype) for i, a in enumerate(arrays)])
            for i, a in enumerate(arrays):
                rec[f"f{i}"] = a
            fh.write(rec.tobytes())
        else:
            cols = [np.char.mod(_text_fmt(a), a) for a in arrays]
            for start in range(0, w * h, 65536):
                block = [c[start:start + 65536] for c in cols]
                fh.write(("\n".join(" ".join(r) for r in zip(*block)) + "\n").encode("ascii"))


def _write_ply(tmp: Path, pts: np.ndarray, flds: dict, enc: str) -> None:
    import plyfile

    flat, fflat = _flat(pts, flds)
    dt = [("x", flat.dtype), ("y", flat.dtype), ("z", flat.dtype)]
    dt += [(k, v.dtype.newbyteorder("<") if v.dtype.itemsize > 1 else v.dtype)
           for k, v in fflat.items()]
    rec = np.empty(flat.shape[0], dtype=dt)
    rec["x"], rec["y"], rec["z"] = flat[:, 0], flat[:, 1], flat[:, 2]
    for k, v in fflat.items():
        rec[k] = v
    obj_info = [f"{_GRID_TAG} {pts.shape[0]} {pts.shape[1]}"] if pts.ndim == 3 else []
    el = plyfile.PlyElement.describe(rec, "vertex")
    ply = plyfile.PlyData([el], text=enc == "ascii", byte_order="<",
                          comments=["written by miem"], obj_info=obj_info)
    with open(tmp, "wb") as fh:
        ply.write(fh)


def _las_scale(lo: float, hi: float) -> float:
    """Smallest power-of-ten scale (>= 1e-6) that keeps ``hi - lo`` inside int32."""
    span = max(abs(hi - lo), 1e-300)
    scale = 1e-6
    while span / scale > 2.0e9:
        scale *= 10.0
    return scale


def _write_las(tmp: Path, pts: np.ndarray, flds: dict, enc: str | None,
               compress: bool = False) -> None:
    import laspy

    flat, fflat = _flat(pts, flds)
    finite = np.isfinite(flat).all(axis=1)
    keep_index = pts.ndim == 3 or not finite.all()
    if not finite.any():
        raise ValueError("points: LAS/LAZ needs at least one finite point")
    sel = flat[finite].astype(np.float64)
    # Point format 6 (LAS 1.4, with gps_time); 7 adds RGB when the fields carry colours.
    rgb = {"red", "green", "blue"} & set(fflat)
    header = laspy.LasHeader(point_format=7 if rgb else 6, version="1.4")
    lo = sel.min(axis=0)
    hi = sel.max(axis=0)
    header.offsets = np.floor(lo)
    header.scales = np.array([_las_scale(lo[i], hi[i]) for i in range(3)])
    standard_names = set(header.point_format.dimension_names)
    # Fields with a standard LAS name (intensity, classification, ...) go into that dimension,
    # cast to its type; the others become extra-bytes dimensions with their own dtype.
    standard = {k: v for k, v in fflat.items() if k in standard_names}
    for bad in {"X", "Y", "Z"} & set(standard):
        raise ValueError(f"fields: {bad!r} is the LAS coordinate dimension")
    extra = {k: v for k, v in fflat.items() if k not in standard_names}
    if keep_index:
        if "index" in extra:
            raise ValueError("fields: 'index' is reserved in LAS files for the grid position")
        extra["index"] = np.arange(flat.shape[0], dtype=np.uint64)
    for name, v in extra.items():
        header.add_extra_dim(laspy.ExtraBytesParams(name=name, type=v.dtype))
    if keep_index:
        shape = (pts.shape[0], pts.shape[1]) if pts.ndim == 3 else (0, flat.shape[0])
        header.vlrs.append(laspy.VLR(user_id=_LAS_VLR_USER, record_id=_LAS_VLR_ID,
                                     description="grid shape H W",
                                     record_data=struct.pack("<qq", *shape)))
    las = laspy.LasData(header)
    las.x, las.y, las.z = sel[:, 0], sel[:, 1], sel[:, 2]
    for name, v in extra.items():
        las[name] = v[finite]
    for name, v in standard.items():
        dtype = np.asarray(las[name]).dtype
        vals = v[finite]
        if dtype.kind in "iu":
            info = np.iinfo(dtype)
            if vals.size and (not np.all(np.isfinite(vals)) or vals.min() < info.min
                              or vals.max() > info.max):
                raise ValueError(
                    f"fields[{name!r}]: values do not fit the LAS dimension type {dtype}"
                )
        las[name] = vals.astype(dtype)
    las.write(str(tmp), do_compress=compress)


def _write_laz(tmp: Path, pts: np.ndarray, flds: dict, enc: str | None) -> None:
    _write_las(tmp, pts, flds, enc, compress=True)


def _text_fmt(arr: np.ndarray) -> str:
    if arr.dtype.kind in "iu":
        return "%d"
    return "%.9g" if arr.dtype.itemsize <= 4 else "%.17g"


def _write_text(tmp: Path, pts: np.ndarray, flds: dict, fmt: str) -> None:
    flat, fflat = _flat(pts, flds)
    names = ["x", "y", "z"] + list(fflat)
    cols = [flat[:, 0], flat[:, 1], flat[:, 2]] + list(fflat.values())
    fmts = [_text_fmt(c) for c in cols]
    delim = "," if fmt == "csv" else " "
    with open(tmp, "w", encoding="utf-8", newline="\n") as fh:
        if pts.ndim == 3:
            fh.write(f"# {_GRID_TAG} {pts.shape[0]} {pts.shape[1]}\n")
        if fmt == "csv":
            fh.write(",".join(names) + "\n")
        else:
            fh.write("# " + " ".join(names) + "\n")
        # A record array keeps each column's dtype, so integers print exactly.
        rec = np.rec.fromarrays(cols, names=names)
        np.savetxt(fh, rec, fmt=fmts, delimiter=delim)


def _write_npy(tmp: Path, pts: np.ndarray, flds: dict, enc: str | None) -> None:
    if flds:
        dt = [("x", pts.dtype), ("y", pts.dtype), ("z", pts.dtype)]
        dt += [(k, v.dtype) for k, v in flds.items()]
        arr = np.empty(pts.shape[:-1], dtype=dt)
        arr["x"], arr["y"], arr["z"] = pts[..., 0], pts[..., 1], pts[..., 2]
        for k, v in flds.items():
            arr[k] = v
    else:
        arr = np.ascontiguousarray(pts)
    with open(tmp, "wb") as fh:
        np.save(fh, arr, allow_pickle=False)


def _write_npz(tmp: Path, pts: np.ndarray, flds: dict, enc: str | None) -> None:
    if "points" in flds:
        raise ValueError("fields: 'points' is reserved for the coordinates in .npz files")
    with open(tmp, "wb") as fh:
        np.savez_compressed(fh, points=pts, **flds)


_WRITERS = {
    "pcd": _write_pcd,
    "ply": _write_ply,
    "las": _write_las,
    "laz": _write_laz,
    "xyz": lambda t, p, f, e: _write_text(t, p, f, "xyz"),
    "txt": lambda t, p, f, e: _write_text(t, p, f, "txt"),
    "csv": lambda t, p, f, e: _write_text(t, p, f, "csv"),
    "npy": _write_npy,
    "npz": _write_npz,
}


# ---------------------------------------------------------------------------------------------
# scan lines -> grid


def grid_from_scanlines(
    points: Any,
    step: float | None = None,
    line_axis: int = 1,
    along_axis: int = 0,
    line_tol: float | None = None,
    *,
    duplicates: Literal["error", "first", "last"] = "error",
    max_offset: float = 0.25,
    max_cells: int = 200_000_000,
    return_index: bool = False,
    order: Literal["file", "line"] = "file",
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Rebuild an organized grid from points stored profile by profile.

    Many profiler exports (and PCD files written from them) are "unorganized" in the header but
    keep the scanner's order: one profile after another, each at a constant position along the
    motion (``line_axis``), its points evenly spaced along ``along_axis``. Row ``r`` of the grid is
    the ``r``-th profile in file order; column ``c`` is ``round((a - a_min) / step)`` for the
    along-profile coordinate ``a`` (``a_min`` over all points). Cells no point falls in are NaN.
    Tools that reorder points (a shuffle, a merge, some exporters) keep them on their profiles
    but lose that order: ``order="line"`` rebuilds such scans from the positions alone.

    Parameters
    ----------
    points : array_like, shape (N, 3), float
        Points in scan order. Non-finite points are skipped.
    step : float, optional
        Spacing of the points along a profile, in the points' units. Default: estimated from the
        differences of consecutive points within profiles (the median of those below 1.5 times
        their 10th percentile, so gaps do not count).
    line_axis : int
        Coordinate (0 x, 1 y, 2 z) that is constant within a profile and changes between
        profiles.
    along_axis : int
        Coordinate that runs along a profile.
    line_tol : float, optional
        A new profile starts where ``|line coordinate change| > line_tol`` between consecutive
        points. Default ``step / 2``.
    duplicates : {"error", "first", "last"}
        What to do when two points fall in the same cell: raise, or keep the first / last one in
        file order.
    max_offset : float
        Largest allowed distance of a point from its column's position, as a fraction of
        `step`: beyond it the points are not on a regular grid (wrong `step` or `along_axis`, or
        not a profiler scan) and a ``ValueError`` is raised.
    max_cells : int
        Largest grid (``H * W``) to allocate.
    return_index : bool
        Also return, for each input point, its flat cell index ``r * W + c`` (-1 for skipped
        points), to map per-cell results back onto the input order.
    order : {"file", "line"}
        ``"file"``: the points are in scan-line order, a profile's points one after another.
        ``"line"``: in any order; the points are sorted by their line coordinate (a stable
        sort) and a new profile starts where the sorted line coordinate changes by more than
        `line_tol`, so row ``r`` is the ``r``-th profile position from the lowest (the step,
        when estimated, from the first 2^18 points so sorted, each profile's along it). The
        two give the same grid for a file whose profiles are in increasing line position;
        two passes over the same line positions (profiles that share a position) are one
        profile with ``"line"``: duplicate cells. ``duplicates="first"`` / ``"last"``
        still mean in file order.

    Returns
    -------
    grid : ndarray, shape (H, W, 3), dtype of `points`
        The organized scan, NaN in empty cells.
    index : ndarray, shape (N,), int64
        Only with ``return_index=True``.

    Raises
    ------
    ValueError
        Bad arguments, fewer than 2 finite points, points that do not form scan lines on a
        regular step, a grid larger than `max_cells`, or duplicate cells with
        ``duplicates="error"``.

    Examples
    --------
    >>> scan = miem.io.read("second_source.pcd")       # (250681, 3), in scan-line order
    >>> grid = miem.io.grid_from_scanlines(scan.points, step=0.05)
    >>> grid.shape
    (426, 724, 3)
    """
    pts = _as_points(points)
    if pts.ndim != 2:
        raise ValueError(f"points: expected shape (N, 3) in scan order, got {pts.shape}")
    for name, ax in (("line_axis", line_axis), ("along_axis", along_axis)):
        if isinstance(ax, bool) or ax not in (0, 1, 2):
            raise ValueError(f"{name}: expected 0, 1 or 2, got {ax!r}")
    if line_axis == along_axis:
        raise ValueError(f"line_axis and along_axis must differ, both are {line_axis}")
    if order not in ("file", "line"):
        raise ValueError(f"order: expected 'file' or 'line', got {order!r}")
    if duplicates not in ("error", "first", "last"):
        raise ValueError(f"duplicates: expected 'error', 'first' or 'last', got {duplicates!r}")
    if not (isinstance(max_offset, (int, float)) and 0 < max_offset <= 0.5):
        raise ValueError(f"max_offset: expected a fraction in (0, 0.5], got {max_offset!r}")
    finite = np.isfinite(pts).all(axis=1)
    src = np.flatnonzero(finite)
    if src.size < 2:
        raise ValueError(f"points: need at least 2 finite points, got {src.size}")
    every = src.size == pts.shape[0]  # (then columns, not gathers)
    line = (pts[:, line_axis] if every else pts[src, line_axis]).astype(np.float64)
    along = (pts[:, along_axis] if every else pts[src, along_axis]).astype(np.float64)
    # "line": the profiles are read in sorted order (a stable sort by the line coordinate), then
    # everything else is in file order
    sort = np.argsort(line, kind="stable") if order == "line" else None
    line_s = line if sort is None else line[sort]
    dline = np.abs(np.diff(line_s))
    if line_tol is not None:
        line_tol = float(line_tol)
        if not (np.isfinite(line_tol) and line_tol >= 0):
            raise ValueError(f"line_tol: expected a length >= 0, got {line_tol!r}")
    if step is None:
        if sort is None:
            ls, al = line, along
        else:  # the first 2^18 points by line position, each profile's sorted along it
            m = min(src.size, 1 << 18)
            sub = sort[np.lexsort((along[sort[:m]], line_s[:m]))]
            ls, al = line[sub], along[sub]
        within = np.abs(np.diff(ls)) <= (line_tol if line_tol is not None else 0.0)
        d = np.abs(np.diff(al))[within]
        d = d[d > 0]
        if d.size == 0:
            raise ValueError(
                "step: cannot estimate the spacing along the profiles (no two consecutive points "
                "share a profile); pass step= and line_tol="
            )
        s10 = np.percentile(d, 10)
        step = float(np.median(d[d <= 1.5 * s10]))
    else:
        step = float(step)
        if not (np.isfinite(step) and step > 0):
            raise ValueError(f"step: expected a length > 0, got {step!r}")
    if line_tol is None:
        line_tol = 0.5 * step
    starts = np.flatnonzero(dline > line_tol) + 1
    row = np.zeros(src.size, dtype=np.int64)
    row[starts] = 1
    row = np.cumsum(row)
    if sort is not None:
        row[sort] = row.copy()
    pos = (along - along.min()) / step
    col = np.rint(pos).astype(np.int64)
    worst = float(np.max(np.abs(pos - col)))
    if worst > max_offset:
        raise ValueError(
            f"points are not evenly spaced by step={step:g} along axis {along_axis}: a point lies "
            f"{worst:.2f} steps off its column (max_offset={max_offset:g}); check step and "
            "along_axis, or the points are not in scan-line order (order='line' for points "
            "on profiles in another order)"
        )
    h = int(row.max()) + 1
    w = int(col.max()) + 1
    if h * w > max_cells:
        raise ValueError(
            f"the grid would be {h} x {w} = {h * w:,} cells (max_cells={max_cells:,}): the points "
            "do not look like scan lines, or step is too small"
        )
    flat = row * w + col
    taken = np.zeros(h * w, dtype=bool)  # (a byte a cell: a twelfth of the grid)
    taken[flat] = True
    if np.count_nonzero(taken) == src.size:  # no two points in one cell (no sort needed)
        keep = np.arange(src.size)
    else:
        seq = np.arange(src.size) if duplicates != "last" else np.arange(src.size)[::-1]
        _, first = np.unique(flat[seq], return_index=True)
        keep = np.sort(seq[first])
    del taken
    n_dup = src.size - keep.size
    if n_dup and duplicates == "error":
        raise ValueError(
            f"{n_dup} points fall in a cell already taken by another point of the same profile; "
            "pass duplicates='first' or 'last' to keep one, or check step"
        )
    grid = np.full((h, w, 3), np.nan, dtype=pts.dtype)
    if every and keep.size == src.size:
        grid.reshape(-1, 3)[flat] = pts
    else:
        grid.reshape(-1, 3)[flat[keep]] = pts[src[keep]]
    if not return_index:
        return grid
    index = np.full(pts.shape[0], -1, dtype=np.int64)
    index[src[keep]] = flat[keep]
    return grid, index


def _rebuild_grid(points: np.ndarray, force: bool = False,
                  **kw: Any) -> tuple[np.ndarray, np.ndarray, str, int]:
    """The command line's grid for an unorganized file: `grid_from_scanlines` in file order,
    else by line position (``order="line"``), keeping a grid only when at least half its cells
    hold a point (`_MIN_FILL`). Without `line_axis` / `along_axis` in `kw` both horizontal
    layouts are tried: profiles at constant y (along x), then at constant x (along y), file
    order for both before line order (in file order the first grid; in line order the one
    with the larger fill, the layout whose sample says fuller (`_sample_fill`) first and the
    other only when the first fills less than 90 %: a scan's true profiles fill their grid,
    read the other way its uneven profile spacing leaves empty columns). An order whose cheap
    look at a sample says no is not tried: file order when consecutive points do not mostly
    stay on their line (`_in_scan_order`), line order when the line coordinates are nearly all
    distinct (`_few_lines`). With `force`, when none gives a grid, the fullest grid that any
    order and layout gave below that bound (down to `_FORCE_FILL`), else the first layout's in
    file order. Returns (grid, index, the order taken, the line axis); raises the first
    ValueError when there is no grid. (The fill bound caps the grid at N / _MIN_FILL cells, N /
    _FORCE_FILL with `force`, so no attempt allocates a grid of one profile per point.)"""
    n = int(np.isfinite(points).all(axis=1).sum()) if points.ndim == 2 else 0
    cap = min(kw.pop("max_cells", 200_000_000),
              max(1, int(n / (_FORCE_FILL if force else _MIN_FILL))))
    la, aa = kw.pop("line_axis", None), kw.pop("along_axis", None)
    if la is None and aa is None:
        layouts = [(1, 0), (0, 1)]
    else:
        la = (1 if aa != 1 else 0) if la is None else la
        aa = ([a for a in (0, 1, 2) if a != la][0]) if aa is None else aa
        layouts = [(la, aa)]
    given = layouts[0]  # (force: the first layout, whatever the line order's sort)
    # the looks' samples, taken once: the first points (file order), an even stride (line order)
    samples = {"file": _sample_rows(points, _LOOK, even=False),
               "line": _sample_rows(points, _LOOK, even=True)}
    first: ValueError | None = None
    under: tuple | None = None  # (fill, grid, index, order, line axis): the fullest below bound
    for order in ("file", "line"):
        s = samples[order]
        best: tuple | None = None  # (fill, grid, index, line axis)
        if order == "line" and len(layouts) > 1:  # the likelier layout first (sorting is dear)
            # (stable, to 1 %: a square lattice fills both alike and stays y first)
            layouts = sorted(layouts, key=lambda ax: -round(_sample_fill(s, points.shape[0],
                                                                        *ax), 2))
        for la, aa in layouts:
            if best is not None and best[0] >= 0.9:
                break  # a layout that fills 90 % of its grid: the other cannot beat it by much
            look = _in_scan_order if order == "file" else _few_lines
            if not force and not look(s, la, aa):
                first = first or ValueError(
                    f"the points are not on scan lines along axis {aa} ({order} order)")
                continue
            try:
                grid, index = grid_from_scanlines(points, return_index=True, order=order,
                                                  max_cells=cap, line_axis=la, along_axis=aa,
                                                  **kw)
            except ValueError as exc:
                first = first or exc
                continue
            fill = float(np.isfinite(grid).all(axis=-1).mean())
            if fill < _MIN_FILL:
                first = first or ValueError(
                    f"a grid rebuilt from the scan lines would be only {fill:.0%} filled "
                    f"({grid.shape[0]} x {grid.shape[1]})")
                if force and (under is None or fill > under[0]):
                    under = (fill, grid, index, order, la)
            elif order == "file":
                return grid, index, order, la  # the scanner's own sequence
            elif best is None or fill > best[0]:
                best = (fill, grid, index, la)  # sorted: the layout that fills its grid best
        if best is not None:
            return best[1], best[2], order, best[3]
    if force:
        if under is not None:  # the fullest grid any order and layout gave
            return under[1], under[2], under[3], under[4]
        la, aa = given
        grid, index = grid_from_scanlines(points, return_index=True, line_axis=la,
                                          along_axis=aa, **kw)
        return grid, index, "file", la
    assert first is not None
    raise first


# Cheap looks at a sample of the points (whether they lie on scan lines) before any rebuild.
_LOOK = 1 << 16  # points in the command line's samples


def _sample_rows(points: np.ndarray, sample: int, even: bool) -> np.ndarray:
    """Up to `sample` finite points as float64: the first ones (consecutive) or an even
    stride."""
    if points.ndim != 2 or points.shape[0] < 3:
        return np.zeros((0, 3))
    s = points[:: max(1, points.shape[0] // sample)] if even else points[:sample]
    return s[np.isfinite(s).all(axis=1)].astype(np.float64)


def _distinct_step(values: np.ndarray) -> tuple[np.ndarray, float]:
    """The distinct values (sorted) and the smallest gap between them (0 with fewer than 2)."""
    u = np.unique(values)
    return u, float(np.diff(u).min()) if u.size > 1 else 0.0


def _in_scan_order(s: np.ndarray, la: int, aa: int) -> bool:
    """Whether consecutive points (`s`: the first ones) mostly stay on their line, as a scan
    in file order: at least 80 % of consecutive steps change the line coordinate less than the
    along coordinate (within a profile of W points, (W - 1) / W of them; in a shuffled or
    random cloud about half)."""
    if s.shape[0] < 3 or not {la, aa} <= {0, 1, 2}:
        return True  # (grid_from_scanlines says what is wrong)
    d = np.abs(np.diff(s, axis=0))
    return float(np.mean(d[:, la] < d[:, aa])) >= 0.8


def _sample_fill(s: np.ndarray, n: int, la: int, aa: int) -> float:
    """The share of its grid's cells a layout would fill, estimated from an even sample `s` of
    `n` points: n over (distinct line values in the sample) x (along range / the smallest gap
    between distinct along values). Read the wrong way, a scan's uneven profile spacing
    becomes columns, most of them empty."""
    if s.shape[0] < 3:
        return 0.0
    along, step = _distinct_step(s[:, aa])
    if along.size < 2:
        return 0.0
    cols = (along[-1] - along[0]) / step + 1.0
    return float(n / (np.unique(s[:, la]).size * cols))


def _few_lines(s: np.ndarray, la: int, aa: int = 0) -> bool:
    """Whether the line coordinates of an even sample `s` take few distinct values, as points
    on scan lines do (any order): at most 90 % distinct. A cloud's are nearly all distinct; a
    scan's are at most its profiles (more than 90 % distinct only when it has several times
    the sample's size in profiles)."""
    if s.shape[0] < 3 or la not in (0, 1, 2):
        return True  # (grid_from_scanlines says what is wrong)
    return np.unique(s[:, la]).size <= 0.9 * s.shape[0]


def _on_scan_lines(points: np.ndarray, sample: int = 1 << 14) -> str:
    """Why an ``(N, 3)`` cloud looks like a profiler scan whose points were reordered ("" when
    it does not), for `miem.detect`'s warning: in an even sample of up to `sample` points, y
    (or x) takes at most half as many distinct values as points (profile positions) and the
    other horizontal coordinate sits on a regular step (every sampled value within 0.1 steps
    of ``min + k step``, the step the smallest gap between its distinct values). A cheap look,
    not the rebuild."""
    if points.shape[0] < 256:
        return ""
    s = _sample_rows(points, sample, even=True)
    for la, aa in ((1, 0), (0, 1)):
        lines = np.unique(s[:, la]).size
        if not 2 <= lines <= 0.5 * s.shape[0]:
            continue
        along, step = _distinct_step(s[:, aa])
        if along.size < 3:
            continue
        pos = (along - along[0]) / step
        if float(np.max(np.abs(pos - np.rint(pos)))) <= 0.1:
            return (f"{lines} {'xyz'[la]} positions in a sample of {s.shape[0]} points, "
                    f"{'xyz'[aa]} on a {step:.6g} step")
    return ""


# A rebuilt grid is used (without force) when at least this share of its cells holds a point.
_MIN_FILL = 0.5
# With force (--layout scanlines), the fullest grid of at least this fill when none reaches
# _MIN_FILL (sparse profiles: a scan with most returns missing).
_FORCE_FILL = 0.05


# ---------------------------------------------------------------------------------------------
# Open3D


def from_open3d(pcd: Any) -> np.ndarray:
    """The points of an Open3D point cloud as an array (no copy for a legacy cloud).

    Parameters
    ----------
    pcd : open3d.geometry.PointCloud or open3d.t.geometry.PointCloud
        The cloud. Open3D itself is not imported here.

    Returns
    -------
    ndarray, shape (N, 3), float64 (float32 for a float32 tensor cloud)
        A view of ``pcd.points`` for a legacy cloud (``np.asarray``), the positions for a
        tensor cloud.

    Raises
    ------
    ValueError
        `pcd` is not an Open3D point cloud.
    """
    pts = getattr(pcd, "points", None)
    if pts is not None and not isinstance(pcd, np.ndarray):
        arr = np.asarray(pts)
    else:
        tensor = getattr(getattr(pcd, "point", None), "positions", None)
        if tensor is None:
            raise ValueError(
                f"pcd: expected an open3d.geometry.PointCloud, got {type(pcd).__name__}"
            )
        arr = tensor.cpu().numpy() if hasattr(tensor, "cpu") else np.asarray(tensor)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"pcd: its points have shape {arr.shape}, expected (N, 3)")
    return arr


def to_open3d(points: Any, labels: Any = None, *, drop_invalid: bool = True) -> Any:
    """An Open3D point cloud of `points`, coloured by label.

    Parameters
    ----------
    points : array_like, shape (N, 3) or (H, W, 3)
        Coordinates.
    labels : array_like of int, shape points.shape[:-1], optional
        :class:`miem.Label` values; points get :data:`LABEL_COLORS` (NORMAL grey, ABNORMAL red,
        EDGE blue). None: no colours.
    drop_invalid : bool
        Leave out points with a non-finite coordinate (Open3D's viewers and KD-trees do not
        accept them). With ``False`` every point is kept, in order.

    Returns
    -------
    open3d.geometry.PointCloud

    Raises
    ------
    MissingDependencyError
        Open3D is not installed (``pip install open3d``, or ``open3d-cpu`` on Linux x86-64).
    ValueError
        Bad shapes or labels.
    """
    pts = _as_points(points).reshape(-1, 3)
    lab = None
    if labels is not None:
        lab = np.asarray(labels)
        if lab.size != pts.shape[0] or lab.dtype.kind not in "iu":
            raise ValueError(
                f"labels: expected {pts.shape[0]} integer labels, got {lab.shape} {lab.dtype}"
            )
        lab = lab.reshape(-1)
        if lab.size and (lab.min() < 0 or lab.max() > 3):
            raise ValueError("labels: expected values 0..3 (miem.Label)")
    o3d = _require("open3d", "to_open3d", extra=None, pip_name="open3d")
    if drop_invalid:
        ok = np.isfinite(pts).all(axis=1)
        pts = pts[ok]
        lab = None if lab is None else lab[ok]
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(np.ascontiguousarray(pts, dtype=np.float64))
    if lab is not None:
        palette = np.array([LABEL_COLORS[i] for i in range(4)], dtype=np.float64)
        pcd.colors = o3d.utility.Vector3dVector(palette[lab.astype(np.intp)])
    return pcd
