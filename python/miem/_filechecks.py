"""Header checks run by :mod:`miem.io` before any parser allocates or loops.

A scan file's header declares sizes, counts and offsets; a corrupt or hostile header can declare
gigabytes in a kilobyte file, or a loop of four billion records. Each check here compares what the
header declares with the file's real length (or a bound that any honest file meets) and raises
:class:`ScanFileError` naming the field, so that a reader never allocates more than a small
multiple of the file's size (README "Guarantees").
"""

from __future__ import annotations

import struct
import zipfile
from pathlib import Path

import numpy as np

from .io import ScanFileError

#: Largest number of values per PCD point (sum of COUNT): a PCL histogram descriptor has 308.
PCD_MAX_VALUES = 4096
#: LZF cannot expand data more than about 100 times (a 2-3 byte token copies at most 264 bytes).
LZF_MAX_RATIO = 132
#: LAZ point data decompresses to at most this many times its size (measured: 3,000 for millions
#: of identical points in laspy's default chunks; real scans 5 to 10).
LAZ_MAX_RATIO = 4096
#: A miem grid record in a LAS file may announce at most this many cells per stored point (plus
#: a floor for small grids): an honest grid stores its finite points, and a scan with fewer than
#: 1 return in 64 cells is not a scan.
LAS_MAX_CELLS_PER_POINT = 64
LAS_MIN_CELLS = 1 << 16
#: Deflate cannot expand data more than 1032 times.
DEFLATE_MAX_RATIO = 1032
_HEADER_LIMIT = 1 << 20  # bytes of text header (PCD, PLY) read before giving up


def _need(path: Path, ok: bool, reason: str) -> None:
    if not ok:
        raise ScanFileError(path, reason)


# ---------------------------------------------------------------------------------------------
# PCD


def pcd_header(path: Path) -> tuple[dict, int]:
    """The PCD header as ``{KEY: [tokens]}`` and the offset of the point data.

    Raises
    ------
    ScanFileError
        No DATA line, bad numbers, or sizes that the file cannot hold.
    """
    header: dict[str, list[str]] = {}
    with open(path, "rb") as fh:
        while True:
            raw = fh.readline(4096)
            if not raw or fh.tell() > _HEADER_LIMIT:
                raise ScanFileError(path, "no PCD header (no DATA line)")
            line = raw.decode("utf-8", errors="replace").strip()
            if not line or line.startswith("#"):
                continue
            key, *tokens = line.split()
            header[key.upper()] = tokens
            if key.upper() == "DATA":
                break
        start = fh.tell()
    _check_pcd(path, header, start)
    return header, start


def _ints(path: Path, header: dict, key: str, minimum: int) -> list[int]:
    try:
        vals = [int(t) for t in header.get(key, [])]
    except ValueError:
        raise ScanFileError(path, f"bad PCD header: {key} {' '.join(header[key])}") from None
    if not vals or any(v < minimum for v in vals):
        raise ScanFileError(path, f"bad PCD header: {key} must hold integers >= {minimum}, got "
                                  f"{' '.join(header.get(key, [])) or 'nothing'}")
    return vals


def _check_pcd(path: Path, header: dict, start: int) -> None:
    fields = header.get("FIELDS", [])
    size = _ints(path, header, "SIZE", 1)
    count = _ints(path, header, "COUNT", 1) if "COUNT" in header else [1] * len(fields)
    types = header.get("TYPE", [])
    _need(path, len(fields) == len(size) == len(count) == len(types) > 0,
          f"bad PCD header: FIELDS, SIZE, TYPE and COUNT differ in length ({len(fields)}, "
          f"{len(size)}, {len(types)}, {len(count)})")
    values = sum(count)
    _need(path, values <= PCD_MAX_VALUES,
          f"bad PCD header: COUNT declares {values:,} values per point (at most "
          f"{PCD_MAX_VALUES:,} are read)")
    width = _ints(path, header, "WIDTH", 0)[0]
    height = _ints(path, header, "HEIGHT", 0)[0] if "HEIGHT" in header else 1
    points = _ints(path, header, "POINTS", 0)[0] if "POINTS" in header else width * height
    _need(path, width * height == points,
          f"header says WIDTH {width} x HEIGHT {height} but POINTS {points}")
    item = sum(s * c for s, c in zip(size, count))
    need = points * item
    have = path.stat().st_size - start
    data = (header.get("DATA") or [""])[0].lower()
    if data == "binary":
        _need(path, have >= need, f"truncated: header says {points} points ({need:,} bytes), "
                                  f"the file holds {have:,} bytes of point data")
    elif data == "binary_compressed":
        with open(path, "rb") as fh:
            fh.seek(start)
            sizes = fh.read(8)
        _need(path, len(sizes) == 8, "truncated: no compressed sizes after DATA")
        compressed, uncompressed = struct.unpack("<II", sizes)
        _need(path, compressed <= have - 8,
              f"truncated: compressed size {compressed:,} bytes, the file holds {have - 8:,}")
        _need(path, uncompressed == need,
              f"corrupt: uncompressed size {uncompressed:,} bytes, {points} points need {need:,}")
        _need(path, need <= LZF_MAX_RATIO * compressed + 64,
              f"corrupt: {compressed:,} compressed bytes cannot hold {need:,} bytes of points")
    elif data == "ascii":
        # Every value takes at least one character and one separator.
        _need(path, 2 * points * values <= have + 1,
              f"truncated: header says {points} points of {values} values, the file holds "
              f"{have:,} bytes of text")
    else:
        raise ScanFileError(path, f"bad PCD header: DATA {data!r} (ascii, binary or "
                                  "binary_compressed)")


# ---------------------------------------------------------------------------------------------
# LAS / LAZ


def check_las(path: Path, compressed: bool) -> int:
    """Check a LAS/LAZ header's offsets and counts against the file; return the point count."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(375)
        _need(path, len(head) >= 227 and head[:4] == b"LASF",
              "not a LAS file (no LASF signature or a header shorter than 227 bytes)")
        minor = head[25]
        header_size, offset, n_vlrs = struct.unpack_from("<HII", head, 94)
        rec_len = struct.unpack_from("<H", head, 105)[0]
        n_points = struct.unpack_from("<I", head, 107)[0]
        _need(path, 227 <= header_size <= size,
              f"corrupt header: header size {header_size} (file {size:,} bytes)")
        _need(path, header_size <= offset <= size,
              f"corrupt header: point data offset {offset:,} outside {header_size}..{size:,}")
        _need(path, n_vlrs * 54 <= offset - header_size,
              f"corrupt header: {n_vlrs:,} VLRs do not fit in the {offset - header_size:,} bytes "
              "before the point data")
        n_evlrs, evlr_start = 0, 0
        if minor >= 4 and header_size >= 375 and len(head) >= 375:
            evlr_start, n_evlrs, n_points14 = struct.unpack_from("<QIQ", head, 235)
            n_points = n_points14 or n_points
        pos = header_size
        laszip = b""
        for i in range(n_vlrs):  # each VLR's length must keep it before the point data
            fh.seek(pos)
            raw = fh.read(54)
            _need(path, len(raw) == 54, f"truncated: VLR {i} of {n_vlrs}")
            length = struct.unpack_from("<H", raw, 20)[0]
            if raw[2:16] == b"laszip encoded" and struct.unpack_from("<H", raw, 18)[0] == 22204:
                laszip = fh.read(length)
            pos += 54 + length
            _need(path, pos <= offset, f"corrupt header: VLR {i} of {n_vlrs} runs past the point "
                                       f"data offset {offset:,}")
        if compressed and laszip:
            _check_laz_chunk(path, fh, laszip, offset, rec_len, size)
        payload = (evlr_start if n_evlrs and evlr_start > offset else size) - offset
        need = n_points * rec_len
        if compressed:
            _need(path, need <= LAZ_MAX_RATIO * max(payload, 1),
                  f"corrupt header: {n_points:,} points of {rec_len} bytes cannot be in "
                  f"{payload:,} compressed bytes")
        else:
            _need(path, need <= payload,
                  f"truncated: header says {n_points:,} points ({need:,} bytes), the file holds "
                  f"{payload:,} bytes of point data")
        if n_evlrs:
            _need(path, offset <= evlr_start and evlr_start + n_evlrs * 60 <= size,
                  f"corrupt header: {n_evlrs:,} EVLRs at offset {evlr_start:,} do not fit in "
                  f"the file ({size:,} bytes)")
            pos = evlr_start
            for i in range(n_evlrs):
                fh.seek(pos + 20)
                raw = fh.read(8)
                _need(path, len(raw) == 8, f"truncated: EVLR {i} of {n_evlrs}")
                pos += 60 + struct.unpack("<Q", raw)[0]
                _need(path, pos <= size, f"truncated: EVLR {i} of {n_evlrs} runs past the end")
    return int(n_points)


# Layers of each LASzip item type in a layered chunk (point formats 6-10); Byte14 has one per byte.
_LAZ_LAYERS = {10: 9, 11: 1, 12: 2, 13: 1}


def _check_laz_chunk(path: Path, fh, laszip: bytes, offset: int, rec_len: int, size: int) -> None:
    """LAZ: the chunk table's count and, for layered chunks (compressor 3), the first chunk's
    layer sizes must fit in the file.

    lazrs allocates the chunk table and each layer at their declared sizes before decoding (one
    corrupt count asks for tens of gigabytes, and a failed allocation aborts the process), so the
    counts are checked here: the table starts with a u32 version and a u32 chunk count; a layered
    chunk with the raw first point, a u32 point count and one u32 byte count per layer."""
    if len(laszip) < 34 or struct.unpack_from("<H", laszip, 0)[0] not in (2, 3):
        return
    layered = struct.unpack_from("<H", laszip, 0)[0] == 3
    n_items = struct.unpack_from("<H", laszip, 32)[0]
    _need(path, 0 < n_items and len(laszip) >= 34 + 6 * n_items,
          f"corrupt LASzip record: {n_items} items in {len(laszip)} bytes")
    # A fixed chunk size (0xFFFFFFFF: variable) is the point count lazrs' parallel decoder
    # allocates per chunk, whatever the file holds: bound it by what the file can hold, or by
    # 256 MiB for small files (laspy writes 50,000-point chunks even for 10 points).
    chunk_size = struct.unpack_from("<I", laszip, 12)[0]
    if chunk_size != 0xFFFFFFFF:
        room = max(LAZ_MAX_RATIO * max(size - offset, 1), 256 << 20)
        _need(path, chunk_size * max(rec_len, 1) <= room,
              f"corrupt LASzip record: chunks of {chunk_size:,} points of {rec_len} bytes "
              f"cannot be in {size - offset:,} compressed bytes")
    layers = 0
    for k in range(n_items):
        kind, item_size, _ = struct.unpack_from("<HHH", laszip, 34 + 6 * k)
        layers += item_size if kind == 14 else _LAZ_LAYERS.get(kind, 0)
    fh.seek(offset)
    raw = fh.read(8)
    _need(path, len(raw) == 8, "truncated: no LAZ chunk table offset")
    table = struct.unpack("<q", raw)[0]
    end = table if offset + 8 < table <= size else size
    if offset + 8 < table <= size - 8:  # the chunk table: u32 version, u32 number of chunks
        fh.seek(table)
        n_chunks = struct.unpack("<II", fh.read(8))[1]
        _need(path, n_chunks <= size - offset,
              f"corrupt LAZ chunk table: {n_chunks:,} chunks in {size - offset:,} bytes")
    if not layered:
        return
    fh.seek(offset + 8 + rec_len + 4)
    raw = fh.read(4 * layers)
    _need(path, len(raw) == 4 * layers, "truncated: the first LAZ chunk has no layer sizes")
    sizes = struct.unpack(f"<{layers}I", raw)
    room = end - fh.tell()
    _need(path, sum(sizes) <= room,
          f"corrupt LAZ chunk: its layers declare {sum(sizes):,} bytes, {room:,} are left")


def check_las_grid(path: Path, shape: tuple[int, int], index: np.ndarray) -> int:
    """Check a miem grid record ``(H, W)`` against the points it indexes; return ``H * W``.

    ``H == 0`` marks an unorganized cloud of ``W`` points with dropouts.
    """
    h, w = shape
    _need(path, h >= 0 and w >= 0, f"corrupt miem grid record: shape {h} x {w}")
    total = h * w if h > 0 else w
    n = int(index.size)
    limit = max(LAS_MAX_CELLS_PER_POINT * n, LAS_MIN_CELLS)
    _need(path, n <= total <= limit,
          f"corrupt miem grid record: {h} x {w} cells for {n:,} stored points (at most "
          f"{limit:,} cells, one stored point per {LAS_MAX_CELLS_PER_POINT} cells)")
    if n:
        _need(path, int(index.min()) >= 0 and int(index.max()) < total,
              "corrupt miem point index: outside the grid")
        _need(path, bool(np.all(np.diff(index) > 0)),
              "corrupt miem point index: not strictly increasing (cells repeat)")
    return total


# ---------------------------------------------------------------------------------------------
# PLY


_PLY_SIZES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2,
              "int16": 2, "uint16": 2, "int": 4, "uint": 4, "int32": 4, "uint32": 4,
              "float": 4, "float32": 4, "double": 8, "float64": 8}


def check_ply(path: Path) -> None:
    """Check the element counts of a PLY header against the bytes after ``end_header``."""
    lines: list[str] = []
    with open(path, "rb") as fh:
        while True:
            raw = fh.readline(4096)
            if not raw or fh.tell() > _HEADER_LIMIT:
                raise ScanFileError(path, "no PLY header (no end_header line)")
            line = raw.decode("ascii", errors="replace").strip()
            if line == "end_header":
                break
            lines.append(line)
        have = path.stat().st_size - fh.tell()
    binary = any(ln.startswith("format binary") for ln in lines)
    elements: list[list[int]] = []  # [count, bytes per row at least (binary), properties]
    for ln in lines:
        tok = ln.split()
        if len(tok) == 3 and tok[0] == "element":
            try:
                count = int(tok[2])
            except ValueError:
                raise ScanFileError(path, f"bad PLY header: {ln!r}") from None
            _need(path, count >= 0, f"bad PLY header: {ln!r}")
            elements.append([count, 0, 0])
        elif len(tok) >= 3 and tok[0] == "property" and elements:
            # A list costs at least its count (an empty list); other properties their type.
            elements[-1][1] += _PLY_SIZES.get(tok[2] if tok[1] == "list" else tok[1], 1)
            elements[-1][2] += 1
    # Binary rows take their sizes; text rows at least a character and a separator per value.
    need = sum(n * (row if binary else 2 * props) for n, row, props in elements)
    _need(path, need <= have,
          f"truncated: the header declares elements of {need:,} bytes at least, the file holds "
          f"{have:,} bytes after end_header")


# ---------------------------------------------------------------------------------------------
# NumPy


def _npy_header(fh, path: Path, name: str) -> int:
    """Bytes the array in an open .npy stream needs, from its header."""
    from numpy.lib import format as npformat

    try:
        version = npformat.read_magic(fh)
        if version == (1, 0):
            shape, _, dtype = npformat.read_array_header_1_0(fh)
        elif version == (2, 0):
            shape, _, dtype = npformat.read_array_header_2_0(fh)
        else:
            shape, _, dtype = npformat._read_array_header(fh, version)
    except Exception as exc:
        raise ScanFileError(path, f"corrupt .npy header{name}: {type(exc).__name__}: {exc}") \
            from exc
    _need(path, not dtype.hasobject, f"{name.strip() or 'the array'}: object arrays are not "
                                     "scan data")
    return int(np.prod(shape, dtype=object)) * dtype.itemsize


def check_npy(path: Path) -> None:
    """Check a .npy header's shape against the file's length."""
    with open(path, "rb") as fh:
        need = _npy_header(fh, path, "")
        have = path.stat().st_size - fh.tell()
    _need(path, need <= have, f"truncated: the header declares {need:,} bytes of data, the file "
                              f"holds {have:,}")


def check_npz(path: Path) -> None:
    """Check every member of a .npz archive: declared sizes against the compressed bytes and
    each array header against its member's size."""
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError, ValueError) as exc:
        raise ScanFileError(path, f"corrupt .npz file: {type(exc).__name__}: {exc}") from exc
    with zf:
        for info in zf.infolist():
            _need(path, info.file_size <= DEFLATE_MAX_RATIO * info.compress_size + 1024,
                  f"corrupt .npz member {info.filename!r}: {info.compress_size:,} compressed "
                  f"bytes cannot hold {info.file_size:,}")
            if not info.filename.endswith(".npy"):
                continue
            try:
                with zf.open(info) as fh:
                    need = _npy_header(fh, path, f" of {info.filename!r}")
                    have = info.file_size - fh.tell()
            except ScanFileError:
                raise
            except Exception as exc:
                raise ScanFileError(path, f"corrupt .npz member {info.filename!r}: "
                                          f"{type(exc).__name__}: {exc}") from exc
            _need(path, need <= have,
                  f"corrupt .npz member {info.filename!r}: the header declares {need:,} bytes, "
                  f"the member holds {have:,}")
