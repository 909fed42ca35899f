"""Scans larger than one machine: MIEM on Dask arrays (``pip install miem[dask]``).

Organized scans are Dask arrays ``(H, W, 3)`` chunked into tiles or whole rows. Each block is
detected with :func:`miem.detect` on the block plus a halo of context (the blocks overlap as with
``dask.array.map_overlap``; the halo may be larger than a chunk) and trimmed back to its home
cells, so the labels, flags, angles and heights equal ``miem.detect`` on the whole grid exactly.

The halo (cells, in every direction) comes from the configuration, see :func:`grid_halo`::

    R    = max(scales) + max_gap (+ max_reach when min_step is set)  # one angle pass reads R
    L    = max_iterations * R                                        # the angle passes
         + max_iterations * (window // 2 + edge_extent)              # the height passes, if on
    halo = L + window // 2                                           # the final heights

A cell's label after ``p`` angle passes depends only on the cells within ``p R`` (a pass reads
the usable mask of the previous one within ``R``); a height pass reads the labels in the window
and the compactness of EDGE groups, which an ``edge_extent`` ball decides; the heights and the
defects' normals read the final labels within ``window // 2``. Passes that find nothing new leave
the labels as they are, so a block that stops earlier or later than the whole grid still agrees
on its home cells. Blocks start on the core's 64-cell window-fit tiles, so that window sums are
added in the same order as on the whole grid and heights agree to the last bit (``strict=True``
also makes the halo cover that rounding in the height passes, see :func:`grid_halo`).

Defects are 8-connected components of ABNORMAL cells: a component inside one block's home cells
(not touching an inner block border) is taken from that block's detection as is; components
touching inner borders are joined across blocks (union-find over their border cells) and each
joined defect is detected once more on its bounding box plus the halo, which gives exactly the
fields (centroid, heights, normal, extent, kind) ``miem.detect`` reports. The list is then
ordered and numbered as ``miem.detect`` orders it.

Global quantities are not computed by the blocks: ``theta0="auto"`` (a median over the whole
scan) is rejected, the MIEM plane and the iteration count are not reported.
"""

from __future__ import annotations

import dataclasses
import operator
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

import dask
import dask.array as da
from dask import delayed

import miem
from miem._api import ABNORMAL, Defect

__all__ = ["DaskDetectResult", "detect", "grid_halo"]

_LABEL_KEYS = ("labels", "flags", "angle", "height")
_PARAM_KEYS = ("theta0", "scales", "max_gap", "min_step", "min_directions", "max_iterations",
               "window", "height_tolerance", "edge_extent", "max_reach", "heights")
_DTYPES = {"labels": np.uint8, "flags": np.uint8, "angle": np.float64, "height": np.float64}


def _probe_params(args: tuple, kwargs: dict) -> dict:
    """The parameters ``miem.detect(grid, *args, **kwargs)`` resolves (presets, overrides and
    checks exactly as miem.detect does them), from a run on a tiny plane."""
    yy, xx = np.mgrid[0:5, 0:5].astype(np.float64)
    probe = np.dstack([xx, yy, 0.01 * xx * yy])
    return dict(miem.detect(probe, *args, **kwargs).params)


#: The core's window-fit tile (cpp/src/organized.cpp, window_fits: box sums per 64 x 64 tile in
#: tile-local coordinates). Blocks start on multiples of it, so that every home cell's window sums
#: are added in the same order as on the whole grid and heights agree to the last bit.
_TILE = 64


def grid_halo(params: dict, strict: bool = False) -> int:
    """Cells of context a block needs on every side for exact labels and heights.

    Parameters
    ----------
    params : dict
        Resolved parameters, as in ``miem.detect(...).params``.
    strict : bool
        Also cover the rounding of the core's window sums: they are box sums over 64-cell tiles,
        so the last bit of a window fit depends on labels up to ``63 + window // 2`` cells away;
        ``strict`` lets each height pass reach that far (a height-test decision can differ only
        where ``|h|`` equals the tolerance to the last bit; the tests see none without it).

    Returns
    -------
    int
        ``max_iterations * R (+ max_iterations * (window // 2 + edge_extent) with the height
        test) + window // 2``, with ``R = max(scales) + max_gap (+ max_reach with min_step)``.
    """
    reach = max(params["scales"]) + params["max_gap"]
    if params["min_step"] is not None:
        reach += params["max_reach"]
    reach = max(reach, 1 + params["max_gap"])  # the isolation test's reach
    half = params["window"] // 2
    lag = params["max_iterations"] * reach
    if params["height_tolerance"] is not None:
        per_pass = half + params["edge_extent"]
        if strict:
            per_pass = max(per_pass, _TILE - 1 + half)
        lag += params["max_iterations"] * per_pass
    return lag + half


def _as_grid(grid: Any) -> "da.Array":
    if not isinstance(grid, da.Array):
        grid = da.from_array(np.asarray(grid))
    if grid.ndim != 3 or grid.shape[2] != 3:
        raise ValueError(f"grid: expected a Dask array of shape (H, W, 3), got {grid.shape}")
    if grid.dtype.kind not in "fiu":
        raise ValueError(f"grid: expected a real numeric array, got dtype {grid.dtype}")
    if grid.shape[0] * grid.shape[1] < 3:
        raise ValueError(f"grid: need at least 3 points, got {grid.shape[0] * grid.shape[1]}")
    if len(grid.chunks[2]) != 1:
        grid = grid.rechunk({2: 3})
    return grid


def _span(a: int, b: int, n: int, halo: int) -> tuple:
    """Rows (or columns) to detect for home rows [a, b) of n: the halo beyond the tiles that
    hold the home rows, starting on a tile boundary."""
    lo = max(0, (a // _TILE) * _TILE - halo)
    hi = min(n, -(-b // _TILE) * _TILE + halo)
    return (lo // _TILE) * _TILE, hi


def _run_padded(ext: np.ndarray, kwargs: dict, sep: int) -> Any:
    """miem.detect on a block; a block with fewer than 3 finite points gets 3 points `sep` rows
    below it (beyond every reach and window), which change nothing on the block itself."""
    finite = np.isfinite(ext).all(axis=-1)
    if np.count_nonzero(finite) >= 3:
        return miem.detect(ext, **kwargs), int(np.count_nonzero(finite))
    h, w = ext.shape[:2]
    pad = np.full((h + sep + 1, max(w, 3), 3), np.nan, dtype=ext.dtype)
    pad[:h, :w] = ext
    pad[-1, :3] = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    return miem.detect(pad, **kwargs), int(np.count_nonzero(finite))


def _touches(cells: np.ndarray, home: tuple, shape: tuple) -> bool:
    """True when a cell lies on an inner border of the home block (rows/cols shared with
    another block), i.e. the component may continue in a neighbouring block."""
    r0, r1, c0, c1 = home
    H, W = shape
    r, c = cells[:, 0], cells[:, 1]
    return bool(((r0 > 0) & (r == r0)).any() or ((r1 < H) & (r == r1 - 1)).any()
                or ((c0 > 0) & (c == c0)).any() or ((c1 < W) & (c == c1 - 1)).any())


def _components(mask: np.ndarray) -> tuple:
    from scipy import ndimage

    return ndimage.label(mask, structure=np.ones((3, 3), dtype=bool))


#: Cells beyond its home block within which a block reports a defect whole: defects that start
#: in the block and fit in this margin come from its own detection; larger ones crossing a
#: border are detected again on their bounding box.
_MARGIN = 16


def _detect_block(ext: np.ndarray, origin: tuple, home: tuple, shape: tuple, kwargs: dict,
                  sep: int, margin: int) -> dict:
    """Detect one block with its halo, trimmed to the home cells. Defects: `whole` (first cell
    at home, every cell within _MARGIN of it: exact as detected) and `open` (home parts of the
    components that touch an inner border, joined across blocks later)."""
    ext = np.asarray(ext)
    res, _ = _run_padded(ext, kwargs, sep)
    er0, ec0 = origin
    r0, r1, c0, c1 = home
    H, W = shape
    sl = (slice(r0 - er0, r1 - er0), slice(c0 - ec0, c1 - ec0))
    out = {k: np.ascontiguousarray(getattr(res, k)[sl]) for k in _LABEL_KEYS}
    m = margin
    whole = []
    for d in res.defects:
        cells = d.cells + (er0, ec0)
        first = cells[0]
        if not (r0 <= first[0] < r1 and c0 <= first[1] < c1):
            continue
        lo, hi = cells.min(axis=0), cells.max(axis=0)
        if lo[0] >= r0 - m and hi[0] < r1 + m and lo[1] >= c0 - m and hi[1] < c1 + m:
            whole.append(dataclasses.replace(d, indices=cells[:, 0] * W + cells[:, 1],
                                             cells=cells))
    comp, n = _components(out["labels"] == ABNORMAL)
    open_parts = []
    for k in range(1, n + 1):
        rc = np.argwhere(comp == k) + (r0, c0)
        if _touches(rc, home, shape):
            open_parts.append(rc[:, 0].astype(np.int64) * W + rc[:, 1])
    out["whole"] = whole
    out["open"] = open_parts
    out["n_finite"] = int(np.count_nonzero(np.isfinite(ext[sl]).all(axis=-1)))
    return out


def _join(parts: list, W: int) -> list:
    """Union-find over open components of different blocks that touch (8-connectivity)."""
    parent = list(range(len(parts)))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    owner = {}
    for k, idx in enumerate(parts):
        for i in idx.tolist():
            owner[i] = k
    for k, idx in enumerate(parts):
        for i in idx.tolist():
            r, c = divmod(i, W)
            for dr in (-1, 0, 1):
                for dc in (-1, 0, 1):
                    if (dr or dc) and 0 <= c + dc < W:
                        j = owner.get((r + dr) * W + c + dc)
                        if j is not None and j != k:
                            a, b = find(j), find(k)
                            if a != b:
                                parent[a] = b
    groups: dict = {}
    for k in range(len(parts)):
        groups.setdefault(find(k), []).append(parts[k])
    return [np.sort(np.concatenate(g)) for g in groups.values()]


def _order_key(d: Defect) -> tuple:
    nan = bool(np.isnan(d.peak_height))
    return (nan, 0.0 if nan else -abs(d.peak_height), int(d.indices[0]))


def _regions(groups: list, shape: tuple, halo: int, cap: int) -> list:
    """Detection regions (r0, r1, c0, c1, members...) for defects to detect again: each group's
    bounding box, its 8-neighbours and the halo; groups share a region while it stays <= cap
    cells."""
    H, W = shape
    regions: list = []
    for members in groups:
        r, c = np.divmod(members, W)
        box = (int(r.min()) - 1, int(r.max()) + 2, int(c.min()) - 1, int(c.max()) + 2)
        for reg in regions:
            u = (min(reg[0][0], box[0]), max(reg[0][1], box[1]), min(reg[0][2], box[2]),
                 max(reg[0][3], box[3]))
            rr, cc = _span(u[0], u[1], H, halo), _span(u[2], u[3], W, halo)
            if (rr[1] - rr[0]) * (cc[1] - cc[0]) <= cap:
                reg[0] = u
                reg[1].append(members)
                break
        else:
            regions.append([box, [members]])
    out = []
    for box, members in regions:
        rr, cc = _span(box[0], box[1], H, halo), _span(box[2], box[3], W, halo)
        out.append((rr[0], rr[1], cc[0], cc[1], members))
    return out


def _redetect(region: np.ndarray, origin: tuple, groups: list, W: int, kwargs: dict,
              sep: int) -> list:
    """The defects of `groups` (global flat indices each) from one detection of a region that
    holds their bounding boxes plus the halo."""
    region = np.asarray(region)
    res, _ = _run_padded(region, kwargs, sep)
    r0, c0 = origin
    by_first = {int(d.indices[0]): d for d in res.defects}
    out = []
    for members in groups:
        fr, fc = divmod(int(members[0]), W)
        d = by_first.get((fr - r0) * region.shape[1] + (fc - c0))
        if d is None:  # pragma: no cover - a broken halo
            raise RuntimeError("miem.dask: joined defect not found in its re-detection")
        cells = d.cells + (r0, c0)
        idx = cells[:, 0] * W + cells[:, 1]
        if not np.array_equal(idx, members):  # pragma: no cover - a broken halo
            raise RuntimeError("miem.dask: a joined defect differs from its re-detection")
        out.append(dataclasses.replace(d, indices=idx, cells=cells))
    return out


@dataclass
class DaskDetectResult:
    """What :func:`detect` returns: lazy per-cell arrays, and the defects on request.

    Attributes
    ----------
    labels, flags : dask.array.Array, (H, W), uint8
        As :class:`miem.DetectResult` (equal to ``miem.detect`` on the whole grid).
    angle, height : dask.array.Array, (H, W), float64
        As :class:`miem.DetectResult`.
    params : dict
        The parameters used (``miem.detect``'s), plus ``halo`` (cells) and ``chunks``.
    """

    labels: "da.Array"
    flags: "da.Array"
    angle: "da.Array"
    height: "da.Array"
    params: dict
    grid: "da.Array" = dataclasses.field(repr=False)
    blocks: list = dataclasses.field(repr=False)
    kwargs: dict = dataclasses.field(repr=False)

    @property
    def halo(self) -> int:
        """Cells of context per block side (:func:`grid_halo`)."""
        return int(self.params["halo"])

    def persist(self) -> "DaskDetectResult":
        """Keep every block's result in (cluster) memory, so that arrays and defects computed
        afterwards do not detect again."""
        blocks = dask.persist(*self.blocks)
        return _assemble(self.grid, list(blocks), self.params, self.kwargs)

    def defects(self, *arrays: "da.Array", **compute_kwargs: Any):
        """The defect list, equal to ``miem.detect(grid).defects`` (ids, order, fields).

        Parameters
        ----------
        *arrays : dask.array.Array, optional
            Arrays (e.g. ``res.labels``) or ``dask.array.store(..., compute=False)`` results to
            compute in the same pass, so that the blocks are detected once.
        **compute_kwargs
            Passed to ``dask.compute``.

        Returns
        -------
        list of Defect, or (list of Defect, *computed arrays) when arrays are given.

        Raises
        ------
        ValueError
            When the whole grid has fewer than 3 finite points (as ``miem.detect``).
        """
        summaries = [delayed(_summary)(b) for b in self.blocks]
        # unfused, so that the arrays and the summaries share each block's detection
        compute_kwargs.setdefault("optimize_graph", False)
        computed = dask.compute(summaries, *arrays, **compute_kwargs)
        blocks, rest = computed[0], computed[1:]
        n_finite = sum(b["n_finite"] for b in blocks)
        if n_finite < 3:
            raise ValueError(f"grid: fewer than 3 finite points (found {n_finite})")
        H, W = self.grid.shape[:2]
        out = [d for b in blocks for d in b["whole"]]
        have = {int(d.indices[0]) for d in out}
        groups = [g for g in _join([p for b in blocks for p in b["open"]], W)
                  if int(g[0]) not in have]
        pad = 2 * (self.halo + _MARGIN + _TILE)  # regions up to the size of a block's
        biggest = (max(self.grid.chunks[0]) + pad) * (max(self.grid.chunks[1]) + pad)
        tasks = [delayed(_redetect)(self.grid[r0:r1, c0:c1], (r0, c0), members, W, self.kwargs,
                                    self.halo + 1)
                 for r0, r1, c0, c1, members in _regions(groups, (H, W), self.halo, biggest)]
        out += [d for part in dask.compute(*tasks, **compute_kwargs) for d in part]
        out.sort(key=_order_key)
        out = [dataclasses.replace(d, id=k) for k, d in enumerate(out)]
        return (out, *rest) if arrays else out


def _summary(block: dict) -> dict:
    return {k: block[k] for k in ("whole", "open", "n_finite")}


def _assemble(grid: "da.Array", blocks: list, params: dict, kwargs: dict) -> DaskDetectResult:
    rows, cols = grid.chunks[0], grid.chunks[1]
    nc = len(cols)
    arrays = {}
    for key in _LABEL_KEYS:
        dt = np.dtype(_DTYPES[key])
        arrays[key] = da.block([
            [da.from_delayed(delayed(operator.getitem)(blocks[i * nc + j], key), (h, w), dt)
             for j, w in enumerate(cols)]
            for i, h in enumerate(rows)
        ])
    return DaskDetectResult(params=params, grid=grid, blocks=blocks, kwargs=kwargs, **arrays)


def detect(grid: Any, *args: Any, num_threads: Optional[int] = 1, strict: bool = False,
           **kwargs: Any) -> DaskDetectResult:
    """MIEM on an organized scan held as a Dask array, block by block, exactly as
    :func:`miem.detect` on the whole grid.

    Parameters
    ----------
    grid : dask.array.Array, shape (H, W, 3)
        The scan, chunked into tiles or whole rows (the coordinate axis in one chunk; a NumPy
        array is wrapped in one chunk). Chunks much larger than :func:`grid_halo` waste the
        least work on overlaps.
    *args, **kwargs
        Parameters as for :func:`miem.detect` (``preset``, ``theta0``, ``scales``, ...), resolved
        and checked by it. ``theta0="auto"`` is rejected: it is a median over the whole scan.
    num_threads : int, optional
        Threads per block detection (default 1: one per Dask worker thread; None: all cores).
    strict : bool
        A halo that also covers the rounding of the core's window sums (:func:`grid_halo`).

    Returns
    -------
    DaskDetectResult
        Lazy ``labels``, ``flags``, ``angle``, ``height`` and, with :meth:`~DaskDetectResult.
        defects`, the defect list.

    Raises
    ------
    ValueError
        Bad shape or parameters (the messages of ``miem.detect``), ``theta0="auto"``, or a
        cloud ``(N, 3)`` (use :func:`detect_points`).
    """
    grid = _as_grid(grid)
    kwargs = dict(kwargs, num_threads=num_threads)
    params = _probe_params(args, kwargs)
    if params.get("theta0_auto"):
        raise ValueError("theta0: 'auto' needs a survey of the whole scan, which miem.dask does "
                         "not run; pass the angle in degrees")
    if args:  # positional parameters: pass the resolved values as keywords
        kwargs = dict(kwargs, **{k: params[k] for k in _PARAM_KEYS if k in params})
    return _build(grid, kwargs, params, grid_halo(params, strict))


def _build(grid: "da.Array", kwargs: dict, params: dict, halo: int,
           margin: int = _MARGIN) -> DaskDetectResult:
    """The block graph: each block detected on itself plus `halo` cells, trimmed to home."""
    H, W = grid.shape[:2]
    sep = halo + 1
    blocks = []
    r_edges = np.cumsum((0,) + grid.chunks[0])
    c_edges = np.cumsum((0,) + grid.chunks[1])
    for i in range(len(grid.chunks[0])):
        for j in range(len(grid.chunks[1])):
            r0, r1 = int(r_edges[i]), int(r_edges[i + 1])
            c0, c1 = int(c_edges[j]), int(c_edges[j + 1])
            er0, er1 = _span(r0 - margin, r1 + margin, H, halo)
            ec0, ec1 = _span(c0 - margin, c1 + margin, W, halo)
            blocks.append(delayed(_detect_block, pure=True)(
                grid[er0:er1, ec0:ec1], (er0, ec0), (r0, r1, c0, c1), (H, W), kwargs, sep,
                margin))
    params = dict(params, halo=halo, chunks=(grid.chunks[0], grid.chunks[1]))
    return _assemble(grid, blocks, params, kwargs)
