"""Scans larger than one machine: MIEM on Dask arrays (``pip install miem[dask]``).

Organized scans are Dask arrays ``(H, W, 3)`` chunked into tiles or whole rows. Each block is
detected with :func:`miem.detect` on the block plus a halo of context (the blocks overlap as with
``dask.array.map_overlap``; the halo may be larger than a chunk) and trimmed back to its home
cells, so the labels, flags, angles and heights equal ``miem.detect`` on the whole grid exactly.

The halo (cells, in every direction) comes from the configuration, see :func:`grid_halo`::

    R    = max(scales) + max_gap (+ max_reach when min_step is set)  # one angle pass reads R
    L    = max_iterations * R                                        # the angle passes
         + max_iterations * (window // 2 + edge_extent + max_gap)    # the height passes, if on
    halo = L + window // 2                                           # the final heights

A cell's label after ``p`` angle passes depends only on the cells within ``p R`` (a pass reads
the usable mask of the previous one within ``R``); a height pass reads the labels in the window
and the compactness of EDGE groups, which an ``edge_extent`` ball decides; the heights and the
defects' normals read the final labels within ``window // 2``. Passes that find nothing new leave
the labels as they are, so a block that stops earlier or later than the whole grid still agrees
on its home cells. Blocks start on the core's 64 x 128-cell window-fit tiles, so that window
sums are added in the same order as on the whole grid and heights agree to the last bit
(``strict=True`` also makes the halo cover that rounding in the height passes, see
:func:`grid_halo`). Parameters whose reach this module does not know are refused.

Defects are 8-connected components of ABNORMAL cells. Each block is detected with 16 more cells
of context (_MARGIN): a defect whose first cell is at home and which lies within those 16 cells
is taken from that block's detection as is. The home parts of components that touch an inner
block border are joined across blocks (union-find over their cells); a joined defect that no
block reported whole is detected once more on its bounding box plus the halo, which gives
exactly the fields (centroid, heights, normal, extent, kind) ``miem.detect`` reports. The list
is then ordered and numbered as ``miem.detect`` orders it.

Unorganized clouds (:func:`detect_points`) are cut into square x-y tiles with a halo of
:func:`points_halo`; three far sentinel points give every tile the whole cloud's minimum corner,
so that the core's neighbour grid, and the order of its sums, are the whole cloud's.

Global quantities: ``theta0="auto"`` (a median over the whole scan), a cloud's ``spacing``
(a median over the whole cloud) and the cloud edge test's candidate threshold (1.5 x the median
over the whole cloud of the first height pass's surroundings rms) are found first by an exact
distributed selection (:func:`auto_theta0`, ``_cloud_spacing``, ``_edge_rms_median``: the
tiles survey their home points, the median is selected over all of them and given to every
tile's detection through an internal hook, ``miem._unorganized._cloud_part``); the MIEM plane
and the iteration count are not reported.
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
from miem import _core
from miem._api import ABNORMAL, Defect
from miem._layout import refuse_layout

__all__ = ["DaskDetectResult", "DaskPointsResult", "auto_min_step", "auto_theta0", "auto_z_noise",
           "auto_z_resolution", "detect", "detect_points", "grid_halo", "points_halo"]

_LABEL_KEYS = ("labels", "flags", "angle", "height")
_DTYPES = {"labels": np.uint8, "flags": np.uint8, "angle": np.float64, "height": np.float64}


def _resolve_auto_lengths(grid: "da.Array", args: tuple, kwargs: dict, params: dict) -> tuple:
    """min_step, z_noise and z_resolution "auto" resolved first (:func:`auto_min_step`,
    :func:`auto_z_noise`, :func:`auto_z_resolution`: their 256 rows) and given to every block
    as the length (or None) each resolves to; params record them as auto."""
    from . import _dask_select as sel

    auto: dict = {}
    wanted = [k for k in ("min_step", "z_noise", "z_resolution") if params.get(f"{k}_auto")]
    rows = _sample_rows(_as_grid(grid), {}) if wanted else None  # (found once for all three)
    if "min_step" in wanted or "z_noise" in wanted:
        med = None if rows is None else _survey_medians(rows, {})  # (one survey gives both)
        if "min_step" in wanted:
            auto["min_step"] = None if med is None else sel.min_step_from_medians(med)
        if "z_noise" in wanted:
            auto["z_noise"] = None if med is None else sel.noise_from_medians(med)
    if "z_resolution" in wanted:
        auto["z_resolution"] = None if rows is None else _z_resolution_of(rows, {})
    if not auto:
        return kwargs, params
    kwargs = dict(kwargs, **auto)
    kw = {k: v for k, v in kwargs.items() if k != "_args"}
    return kwargs, dict(_probe_params(args, kw), **{f"{k}_auto": True for k in auto})


def _probe_params(args: tuple, kwargs: dict) -> dict:
    """The parameters ``miem.detect(grid, *args, **kwargs)`` resolves (presets, overrides and
    checks exactly as miem.detect does them), from a run on a tiny plane."""
    yy, xx = np.mgrid[0:5, 0:5].astype(np.float64)
    probe = np.dstack([xx, yy, 0.01 * xx * yy])
    return dict(miem.detect(probe, *args, **kwargs).params)


#: The core's window-fit tiles (cpp/src/window_fits.hpp: kBand x kStrip cells, moments relative
#: to a point of the tile, running sums from the tile's first rows and columns). Blocks start on
#: tile boundaries, so that every home cell's window sums are added in the same order as on the
#: whole grid and heights agree to the last bit.
_TILE = (64, 128)


#: Grid parameters whose reach grid_halo knows: every field organized detection reads
#: (generated from miem.DetectParams, hence from the C++ field table), what it derives
#: (theta0_auto; min_step_auto, z_noise_auto and z_resolution_auto: resolved first on their
#: 256 rows)
#: and the preset's name. A new grid field is known here at once: a field that reaches farther
#: than grid_halo's formula must widen it (tests/test_config.py runs every field on blocks).
_GRID_KNOWN = {"preset", "theta0_auto", "min_step_auto", "z_resolution_auto", "z_noise_auto",
               *miem.DetectParams.fields("grid")}


def grid_halo(params: dict, strict: bool = False) -> int:
    """Cells of context a block needs on every side for exact labels and heights.

    Parameters
    ----------
    params : dict
        Resolved parameters, as in ``miem.detect(...).params``.
    strict : bool
        Also cover the rounding of the core's window sums: they are sums over 64 x 128-cell
        tiles, so the last bit of a window fit depends on labels up to ``127 + window // 2``
        cells away;
        ``strict`` lets each height pass reach that far (a height-test decision can differ only
        where ``|h|`` equals the tolerance to the last bit; the tests see none without it).

    Returns
    -------
    int
        ``max_iterations * R (+ max_iterations * (window // 2 + edge_extent) with the height
        test) (+ max(2 * (edge_window // 2), window // 2 with the height test) + (max_iterations
        - 1) * (edge_window // 2) with the edge test) + window // 2``, with
        ``R = max(scales) + max_gap (+ max_reach with min_step)``. The edge test's sums are per
        64 x 128 tile too (docs/SPEC.md "Edge test"); ``strict`` covers them as the window sums.
    """
    _refuse_unknown(params, _GRID_KNOWN | {"halo", "chunks"})
    reach = max(params["scales"]) + params["max_gap"]
    if params["min_step"] is not None:
        reach += params["max_reach"]
    reach = max(reach, 1 + params["max_gap"])  # the isolation test's reach
    half = params["window"] // 2
    lag = params["max_iterations"] * reach
    if params["height_tolerance"] is not None:
        per_pass = half + params["edge_extent"] + params["max_gap"]  # groups link across gaps
        if strict:
            per_pass = max(per_pass, max(_TILE) - 1 + half)
        lag += params["max_iterations"] * per_pass
    if params.get("edge_tolerance") is not None:  # the edge passes, after the height passes
        # (and their step 9 before pass 1: the sub-windows again, and the feature lines beside
        # a cell, which the angle and height passes' reach already covers; pass 1's quiet cells
        # read the height passes' removals within window // 2)
        side = params["edge_window"] // 2
        if strict:
            side = max(side, max(_TILE) - 1 + side)
        quiet = half if params["height_tolerance"] is not None else 0
        lag += max(2 * side, quiet) + (params["max_iterations"] - 1) * side
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


def _span(a: int, b: int, n: int, halo: int, tile: int) -> tuple:
    """Rows (or columns) to detect for home rows [a, b) of n: the halo beyond the tiles that
    hold the home rows, starting on a tile boundary."""
    lo = max(0, (a // tile) * tile - halo)
    hi = min(n, -(-b // tile) * tile + halo)
    return (lo // tile) * tile, hi


def _homes(grid: "da.Array") -> list:
    """(r0, r1, c0, c1) of every block of the grid, row-major (the order of its chunks)."""
    r = np.cumsum((0,) + grid.chunks[0]).tolist()
    c = np.cumsum((0,) + grid.chunks[1]).tolist()
    return [(r[i], r[i + 1], c[j], c[j + 1]) for i in range(len(r) - 1)
            for j in range(len(c) - 1)]


def _with_arrays(summaries: list, arrays: tuple, compute_kwargs: dict) -> tuple:
    """Computes the per-block summaries and the caller's arrays in one pass, unfused so that
    they share each block's detection."""
    compute_kwargs.setdefault("optimize_graph", False)
    computed = dask.compute(summaries, *arrays, **compute_kwargs)
    return computed[0], computed[1:]


def _numbered(defects: list, rest: tuple, arrays: tuple):
    """Defects in miem.detect's order with their ids; with the computed arrays when asked."""
    defects = sorted(defects, key=_order_key)
    defects = [dataclasses.replace(d, id=k) for k, d in enumerate(defects)]
    return (defects, *rest) if arrays else defects


def _detect(data: np.ndarray, kwargs: dict) -> Any:
    """miem.detect with the caller's arguments (positional ones, e.g. a parameter set, travel
    under the key "_args")."""
    kw = dict(kwargs)
    return miem.detect(data, *kw.pop("_args", ()), **kw)


def _run_padded(ext: np.ndarray, kwargs: dict, sep: int) -> Any:
    """miem.detect on a block; a block with fewer than 3 finite points gets 3 points `sep` rows
    below it (beyond every reach and window), which change nothing on the block itself."""
    finite = np.isfinite(ext).all(axis=-1)
    if np.count_nonzero(finite) >= 3:
        return _detect(ext, kwargs), int(np.count_nonzero(finite))
    h, w = ext.shape[:2]
    pad = np.full((h + sep + 1, max(w, 3), 3), np.nan, dtype=ext.dtype)
    pad[:h, :w] = ext
    pad[-1, :3] = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    return _detect(pad, kwargs), int(np.count_nonzero(finite))


def _components(mask: np.ndarray) -> tuple:
    from scipy import ndimage

    return ndimage.label(mask, structure=np.ones((3, 3), dtype=bool))


def _find_objects(comp: np.ndarray) -> list:
    from scipy import ndimage

    return ndimage.find_objects(comp)


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
    comp, _ = _components(out["labels"] == ABNORMAL)
    open_parts = []
    inner = [comp[0] if r0 > 0 else None, comp[-1] if r1 < H else None,
             comp[:, 0] if c0 > 0 else None, comp[:, -1] if c1 < W else None]
    touching = np.unique(np.concatenate([b for b in inner if b is not None] + [[0]]))[1:]
    boxes = _find_objects(comp)
    for k in touching:  # only components on an inner border, each read within its box
        box = boxes[k - 1]
        rc = np.argwhere(comp[box] == k) + (r0 + box[0].start, c0 + box[1].start)
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
            rr, cc = _span(u[0], u[1], H, halo, _TILE[0]), _span(u[2], u[3], W, halo, _TILE[1])
            if (rr[1] - rr[0]) * (cc[1] - cc[0]) <= cap:
                reg[0] = u
                reg[1].append(members)
                break
        else:
            regions.append([box, [members]])
    out = []
    for box, members in regions:
        rr, cc = _span(box[0], box[1], H, halo, _TILE[0]), _span(box[2], box[3], W, halo,
                                                                     _TILE[1])
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
        blocks, rest = _with_arrays([delayed(_summary)(b) for b in self.blocks], arrays,
                                    compute_kwargs)
        n_finite = sum(b["n_finite"] for b in blocks)
        if n_finite < 3:
            raise ValueError(f"grid: fewer than 3 finite points (found {n_finite})")
        H, W = self.grid.shape[:2]
        out = [d for b in blocks for d in b["whole"]]
        have = {int(d.indices[0]) for d in out}
        groups = [g for g in _join([p for b in blocks for p in b["open"]], W)
                  if int(g[0]) not in have]
        pad = 2 * (self.halo + _MARGIN + max(_TILE))  # regions up to the size of a block's
        biggest = (max(self.grid.chunks[0]) + pad) * (max(self.grid.chunks[1]) + pad)
        tasks = [delayed(_redetect)(self.grid[r0:r1, c0:c1], (r0, c0), members, W, self.kwargs,
                                    self.halo + 1)
                 for r0, r1, c0, c1, members in _regions(groups, (H, W), self.halo, biggest)]
        out += [d for part in dask.compute(*tasks, **compute_kwargs) for d in part]
        return _numbered(out, rest, arrays)


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
        and checked by it.
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
        Bad shape or parameters (the messages of ``miem.detect``). A cloud ``(N, 3)`` goes to
        :func:`detect_points` (as ``miem.detect`` routes it). ``miem.detect``'s ``layout``
        and ``shape`` are refused: no grid is rebuilt here, so pass the grid itself.

    Notes
    -----
    ``theta0="auto"`` is a median over the whole scan: :func:`auto_theta0` surveys every block
    first (when ``detect`` is called; the pass-1 angles are held in the cluster's memory, 8
    bytes per point, until the median is found), then the blocks are detected with that value.
    """
    refuse_layout("miem.dask.detect", kwargs)
    if getattr(grid, "ndim", None) == 2 and grid.shape[-1] == 3 and not args:  # a cloud
        tile = kwargs.pop("tile", None)  # detect_points' own argument
        return _detect_points(grid, tile, num_threads, kwargs)  # type: ignore[return-value]
    grid = _as_grid(grid)
    kwargs = dict(kwargs, num_threads=num_threads)
    params = _probe_params(args, kwargs)
    kwargs, params = _resolve_auto_lengths(grid, args, kwargs, params)
    if args:  # positional parameters (a parameter set) go to every block as given
        kwargs = dict(kwargs, _args=args)
    if params.get("theta0_auto"):
        theta0 = auto_theta0(grid, kwargs, params)
        kwargs = dict(kwargs, theta0=theta0)
        params = dict(params, theta0=theta0)
    return _build(grid, kwargs, params, grid_halo(params, strict))


def _survey_block(ext: np.ndarray, home_slice: tuple, kwargs: dict, sep: int) -> np.ndarray:
    """The bit patterns of ``180 - angle`` (>= 0, so they order like the values; 0 below the
    straight-triple round-off) of the home cells' pass-1 angles, as theta0="auto" surveys them
    (docs/SPEC.md)."""
    ext = np.asarray(ext)
    res, _ = _run_padded(ext, kwargs, sep)
    ang = res.angle[home_slice]
    keep = np.isfinite(ext[home_slice]).all(axis=-1) & np.isfinite(ang)
    dev = 180.0 - ang[keep]
    dev[dev < _core.AUTO_THETA0_STRAIGHT] = 0.0
    return np.ascontiguousarray(dev).view(np.uint64)


def _hist(bits: np.ndarray, prefix: int, shift: int) -> np.ndarray:
    """Counts of the next 16 bits below `shift` among the patterns whose bits above it are
    `prefix`."""
    top = 64 - shift
    sel = bits if top == 0 else bits[(bits >> np.uint64(shift)) == np.uint64(prefix)]
    return np.bincount(((sel >> np.uint64(shift - 16)) & np.uint64(0xFFFF)).astype(np.int64),
                       minlength=1 << 16)


def _kth(blocks: list, k: int, **compute_kwargs: Any) -> float:
    """The k-th smallest (0-based) of the survey values, exactly: 4 rounds of 16-bit
    histograms over the bit patterns, narrowing the prefix (radix selection)."""
    prefix, shift = 0, 64
    while shift > 0:
        hists = dask.compute(*[delayed(_hist)(b, prefix, shift) for b in blocks],
                             **compute_kwargs)
        cum = np.cumsum(np.sum(hists, axis=0))
        digit = int(np.searchsorted(cum, k, side="right"))
        k -= int(cum[digit - 1]) if digit else 0
        prefix, shift = (prefix << 16) | digit, shift - 16
    return float(np.array([prefix], dtype=np.uint64).view(np.float64)[0])


def auto_theta0(grid: Any, kwargs: Optional[dict] = None, params: Optional[dict] = None,
                **compute_kwargs: Any) -> float:
    """theta0="auto" of ``miem.detect`` over a whole Dask-held grid, exactly as miem.detect
    derives it (SPEC.md "theta0='auto'"): the pass-1 angles of every block (with a halo of one
    pass), then the median of ``180 - angle`` by radix selection (no value is gathered).

    Parameters
    ----------
    grid : dask.array.Array, (H, W, 3)
    kwargs, params : dict, optional
        The detection's keywords and resolved parameters (default: the paper's).

    Returns
    -------
    float
        ``clip(180 - 6 median / 0.6745, 75, 170)``; 75 when no angle is finite.
    """
    grid = _as_grid(grid)
    kwargs = dict(kwargs or {})
    if params is None:
        kw = dict(kwargs)
        args = kw.pop("_args", ())
        params = _probe_params(args, kw)
        kwargs, params = _resolve_auto_lengths(grid, args, kwargs, params)
    survey = dict(kwargs, theta0=75.0, max_iterations=1, height_tolerance=None,
                  edge_tolerance=None, heights="abnormal")
    halo = grid_halo(dict(params, max_iterations=1, height_tolerance=None)) - \
        params["window"] // 2
    H, W = grid.shape[:2]
    blocks = []
    for r0, r1, c0, c1 in _homes(grid):
        er0, er1 = _span(r0, r1, H, halo, _TILE[0])
        ec0, ec1 = _span(c0, c1, W, halo, _TILE[1])
        sl = (slice(r0 - er0, r1 - er0), slice(c0 - ec0, c1 - ec0))
        blocks.append(delayed(_survey_block, pure=True)(grid[er0:er1, ec0:ec1], sl, survey,
                                                        halo + 1))
    blocks = list(dask.persist(*blocks, **compute_kwargs))
    m = sum(dask.compute(*[delayed(len)(b) for b in blocks], **compute_kwargs))
    if m == 0:
        return 75.0
    mid = m // 2
    med = _kth(blocks, mid, **compute_kwargs)
    if m % 2 == 0:
        med = 0.5 * (med + _kth(blocks, mid - 1, **compute_kwargs))
    return float(np.clip(180.0 - 6.0 * (med / 0.6745), 75.0, 170.0))


def auto_min_step(grid: Any, **compute_kwargs: Any) -> Optional[float]:
    """min_step="auto" of ``miem.detect`` on a Dask-held grid, exactly as miem.detect derives it
    (docs/SPEC.md "min_step='auto'": the first 256 rows from the first row with a finite cell):
    that row is found over the blocks (row blocks read in order until one has a finite cell:
    usually the first only), then four medians over the neighbour pairs and triples of the
    blocks of those rows, each block read with two more rows and columns, by radix selection in
    four rounds (the 256 rows are held on the workers between rounds, not read four times).

    Returns
    -------
    float or None
        The min_step length, or None (off: the unit neighbours lie far enough apart).
    """
    from . import _dask_select as sel

    rows = _sample_rows(_as_grid(grid), compute_kwargs)
    return None if rows is None else sel.min_step_from_medians(_survey_medians(rows,
                                                                               compute_kwargs))


def auto_z_noise(grid: Any, **compute_kwargs: Any) -> Optional[float]:
    """z_noise="auto" of ``miem.detect`` on a Dask-held grid (docs/SPEC.md "z_noise"): the
    larger robust sigma along and across of the survey :func:`auto_min_step` runs.

    Returns
    -------
    float or None
        The z noise, or None (no row with data, or no axis to measure).
    """
    from . import _dask_select as sel

    rows = _sample_rows(_as_grid(grid), compute_kwargs)
    return None if rows is None else sel.noise_from_medians(_survey_medians(rows,
                                                                            compute_kwargs))


def _sample_rows(grid: "da.Array", compute_kwargs: dict) -> Optional["da.Array"]:
    """The rows the "auto" lengths read: the 256 from the first row with a finite cell, held
    on the workers (None when no cell is finite)."""
    from .reference import AUTO_MIN_STEP_ROWS

    first = _first_data_row(grid, compute_kwargs)
    if first is None:
        return None
    return grid[first:first + AUTO_MIN_STEP_ROWS].persist(**compute_kwargs)


def _survey_medians(rows: "da.Array", compute_kwargs: dict) -> list:
    """The four medians of min_step="auto"'s survey over the sample rows: blocks read with two
    more rows and columns, radix selection in four rounds."""
    from . import _dask_select as sel

    H, W = rows.shape[:2]
    blocks = [(rows[r0:min(H, r1 + 2), c0:min(W, c1 + 2)], (r1 - r0, c1 - c0))
              for r0, r1, c0, c1 in _homes(rows)]
    return sel.medians(sel.min_step_survey, blocks, 4, **compute_kwargs)


def _first_data_row(grid: "da.Array", compute_kwargs: dict) -> Optional[int]:
    """The first row with a finite cell (row blocks read in order until one has one), or None."""
    start = 0
    for h in grid.chunks[0]:  # in order: a scan seldom starts with a block of dropouts only
        rows = da.isfinite(grid[start:start + h]).all(axis=-1).any(axis=1)
        hit = np.flatnonzero(np.asarray(dask.compute(rows, **compute_kwargs)[0]))
        if hit.size:
            return start + int(hit[0])
        start += h
    return None


def auto_z_resolution(grid: Any, **compute_kwargs: Any) -> Optional[float]:
    """z_resolution="auto" of ``miem.detect`` on a Dask-held grid (docs/SPEC.md
    "z_resolution"): the smallest non-zero z difference of finite neighbours along the
    profiles of the 256 rows from the first row with a finite cell, or between two z values of
    the finite cells of the first 32 of those rows (at most 65,536 cells) if smaller, computed
    by the core on those rows (brought to this process: 256 rows of the grid).

    Returns
    -------
    float or None
        The z step, or None (no two neighbours with different z there).
    """
    rows = _sample_rows(_as_grid(grid), compute_kwargs)
    return None if rows is None else _z_resolution_of(rows, compute_kwargs)


def _z_resolution_of(rows: "da.Array", compute_kwargs: dict) -> Optional[float]:
    """z_resolution="auto" on the sample rows, by the core (the rows brought here)."""
    local = dask.compute(rows, **compute_kwargs)[0]
    # as miem.detect reads it (float32 kept, other numbers as float64), in a fresh aligned copy
    local = np.array(local, dtype=np.float32 if local.dtype == np.float32 else np.float64)
    q = _core.auto_z_resolution(local)
    return None if q < 0 else float(q)


def _build(grid: "da.Array", kwargs: dict, params: dict, halo: int,
           margin: int = _MARGIN) -> DaskDetectResult:
    """The block graph: each block detected on itself plus `halo` cells, trimmed to home."""
    H, W = grid.shape[:2]
    sep = halo + 1
    blocks = []
    for home in _homes(grid):
        r0, r1, c0, c1 = home
        er0, er1 = _span(r0 - margin, r1 + margin, H, halo, _TILE[0])
        ec0, ec1 = _span(c0 - margin, c1 + margin, W, halo, _TILE[1])
        blocks.append(delayed(_detect_block, pure=True)(
            grid[er0:er1, ec0:ec1], (er0, ec0), home, (H, W), kwargs, sep, margin))
    params = dict(params, halo=halo, chunks=(grid.chunks[0], grid.chunks[1]))
    return _assemble(grid, blocks, params, kwargs)


# ---------------------------------------------------------------------------------------------
# unorganized clouds: spatial tiles with a halo

_POINT_KEYS = ("labels", "flags", "angle", "height", "degenerate")
_POINT_DTYPES = {"labels": np.uint8, "flags": np.uint8, "angle": np.float64,
                 "height": np.float64, "degenerate": bool}
_POINT_FILL = {"labels": int(miem.INVALID), "flags": 0, "angle": np.nan, "height": np.nan,
               "degenerate": False}


#: Cloud parameters whose reach points_halo knows: every field cloud detection reads (generated
#: from miem.DetectParams), what it records (merged) and the preset's name; any other parameter
#: that is on is refused.
_POINT_KNOWN = {"preset", "merged", *miem.DetectParams.fields("cloud")}
#: The cloud edge test's wide scale, in edge radii (SPEC "Unorganized clouds: edge test",
#: step 7): how far a pass reads.
_EDGE_WIDE = 1.5


def _probe_points(kwargs: dict) -> tuple:
    """The cloud parameters ``miem.detect(points, **kwargs)`` resolves, and whether any of them
    depends on the cloud's spacing (a median over the whole cloud: :func:`cloud_spacing`)."""
    rng = np.random.default_rng(0)
    probe = np.column_stack([rng.uniform(0, 8, (64, 2)), np.zeros(64)])
    a = dict(miem.detect(probe, **kwargs).params)
    b = dict(miem.detect(probe * 2.0, **kwargs).params)
    lengths = ("radius", "min_step", "link", "height_radius")
    derived = any(k in a and a[k] != b[k] for k in lengths)
    compact = a.get("height_tolerance") is not None and a.get("edge_extent", 0) > 0
    _refuse_unknown(a, _POINT_KNOWN)
    return a, (derived or compact) and kwargs.get("spacing") is None


def _nn_tile(pieces: list, box: tuple, merge: float, pad: float,
             sentinels: np.ndarray) -> np.ndarray:
    """The bit patterns of the distinct-point spacings (SPEC "Spacing") of a tile's home points,
    from the tile and the points within `pad` of it: exact up to `pad`, +inf beyond."""
    pieces = [p for p in pieces if p is not None]
    if not pieces:
        return np.zeros(0, np.uint64)
    pts = np.concatenate([p[1] for p in pieces])
    if pts.dtype.kind != "f":  # as miem.detect converts them
        pts = pts.astype(np.float64)
    n = pts.shape[0]
    nn = _core.distinct_spacings(np.concatenate([pts, sentinels.astype(pts.dtype)]), merge, 1)
    nn = nn[:n][_in_home(pts[:, :2].astype(np.float64), box)]
    nn = nn[~np.isnan(nn)]
    nn[nn > pad] = np.inf
    return np.ascontiguousarray(nn).view(np.uint64)


def _cloud_spacing(points: "da.Array", lo3: np.ndarray, hi3: np.ndarray, merge: float) -> float:
    """The whole cloud's spacing as ``miem.detect`` measures it (the median over the distinct
    points of the distance to the nearest other distinct point), from x-y tiles that each see
    their neighbours within an eighth of a tile, by exact distributed selection."""
    lo, hi = lo3[:2].astype(np.float64), hi3[:2].astype(np.float64)
    area = max(float(np.prod(hi - lo)), 1e-300)
    tile = max(float(np.sqrt(area * max(points.chunks[0]) / max(points.shape[0], 1))), 1e-300)
    pad = max(tile / 8.0, 4.0 * merge)
    sentinels = _sentinels(lo3, hi3, 4 * pad + float(np.max(hi3 - lo3)) + 1.0, points.dtype)
    n = (int(np.floor((hi[0] - lo[0]) / tile)) + 1, int(np.floor((hi[1] - lo[1]) / tile)) + 1)
    blocks = [delayed(_nn_tile, pure=True)(pieces, box, merge, pad, sentinels)
              for pieces, box in _homes_points(points, lo, tile, n, pad)]
    blocks = list(dask.persist(*blocks))
    m = sum(dask.compute(*[delayed(len)(b) for b in blocks]))
    if m < 3:
        raise ValueError(f"points: fewer than 3 distinct finite points (found {m}; "
                         "duplicates within merge_distance count once)")
    s = _median_of(blocks)
    if not np.isfinite(s):
        raise ValueError(f"points: the median spacing exceeds {pad:g} (an eighth of a tile); "
                         "pass spacing= (e.g. miem.point_spacing of a representative part)")
    if not s > 0:
        raise ValueError("points: spacing is 0 (more than half of the finite points are "
                         "duplicates within merge_distance)")
    return float(s)


def _homes_points(points: "da.Array", lo: np.ndarray, tile: float, n: tuple, pad: float
                  ) -> list:
    """For every tile: (its pieces of the input chunks within `pad` of it (from _split), its
    home box)."""
    starts = np.cumsum((0,) + points.chunks[0])
    splits = [delayed(_split, pure=True)(c, int(s), lo, tile, n, pad)
              for c, s in zip(points.to_delayed().ravel(), starts)]
    return [([delayed(dict.get)(sp, (i, j)) for sp in splits], _box(lo, tile, n, i, j))
            for i in range(n[0]) for j in range(n[1])]


def _box(lo: np.ndarray, tile: float, n: tuple, i: int, j: int) -> tuple:
    """Tile (i, j)'s home box; the outer tiles reach to infinity."""
    return (lo[0] + i * tile if i else -np.inf, lo[0] + (i + 1) * tile if i < n[0] - 1
            else np.inf, lo[1] + j * tile if j else -np.inf,
            lo[1] + (j + 1) * tile if j < n[1] - 1 else np.inf)


def _refuse_unknown(params: dict, known: set) -> None:
    """A parameter this module does not know may reach beyond the halo: refuse it when on."""
    on = sorted(k for k, v in params.items() if k not in known and v not in (None, 0, False))
    if on:
        raise ValueError(f"{', '.join(on)}: miem.dask does not know how far this reaches, so "
                         "blocks could differ from the whole scan; it is not supported here")


def points_halo(params: dict) -> float:
    """Distance (points' units) around a tile from which it needs points for exact results.

    ``max_iterations * radius`` (angle passes, each reads the neighbours within radius),
    ``+ min_group * radius`` (floating groups: a group of fewer than min_group points lies within
    that chain distance), ``+ max_iterations * (height_radius + link + edge_extent * spacing)``
    with the height test (a pass reads NORMAL points and feature-line EDGE points within
    height_radius; whether an EDGE point's group is compact, i.e. spans at most
    ``edge_extent * spacing``, is seen within that span plus link: a compact group lies within
    it, and a group that reaches beyond it is seen to), ``+ link + max(height_radius, link)``
    ``+ max_iterations * 1.5 * edge_radius`` with the cloud edge test (a pass judges a
    candidate from the points within 1.5 edge_radius, its wide scale, and a later pass only the
    candidates within that of a point the pass before made ABNORMAL; whether a point is a
    candidate is decided by the first height pass, within the reach above, and the whole
    cloud's median, found first),
    ``+ link + max(height_radius, link)`` so that the heights and the defects that leave the
    tile by up to ``link`` are exact.
    """
    r, link = params["radius"], params["link"]
    hr = params.get("height_radius") or r
    lag = params["max_iterations"] * r + params.get("min_group", 0) * r
    if params.get("height_tolerance") is not None:
        lag += params["max_iterations"] * _height_pass_reach(params)
    if params.get("edge_tolerance") is not None:
        lag += params["max_iterations"] * _EDGE_WIDE * (params.get("edge_radius") or hr)
    return lag + link + max(hr, link)


def _height_pass_reach(params: dict) -> float:
    """How far one height pass reads the labels before it (points_halo)."""
    compact = params.get("edge_extent", 0.0) * params["spacing"]
    return (params.get("height_radius") or params["radius"]) + params["link"] + compact


def _survey_halo(params: dict) -> float:
    """Distance around a tile from which it needs points for the first height pass's rms of its
    own points (the edge test's survey): the angle passes, the floating groups and one height
    pass of points_halo."""
    r = params["radius"]
    return (params["max_iterations"] * r + params.get("min_group", 0) * r
            + _height_pass_reach(params))


def _tile_of(xy: np.ndarray, origin: np.ndarray, size: float, n: tuple) -> tuple:
    ix = np.clip(np.floor((xy[:, 0] - origin[0]) / size), 0, n[0] - 1).astype(np.int64)
    iy = np.clip(np.floor((xy[:, 1] - origin[1]) / size), 0, n[1] - 1).astype(np.int64)
    return ix, iy


def _split(chunk: np.ndarray, start: int, origin: np.ndarray, size: float, n: tuple,
           pad: float) -> dict:
    """{tile: (global indices, points)} of the chunk's finite points within `pad` (in x and y)
    of each tile (a superset of what the tile needs)."""
    chunk = np.asarray(chunk)
    fin = np.flatnonzero(np.isfinite(chunk).all(axis=1))
    xy = chunk[fin, :2].astype(np.float64)
    lo = _tile_of(xy - pad, origin, size, n)
    hi = _tile_of(xy + pad, origin, size, n)
    out: dict = {}
    for i in range(int(lo[0].min(initial=0)), int(hi[0].max(initial=-1)) + 1):
        in_x = (lo[0] <= i) & (i <= hi[0])
        for j in range(int(lo[1][in_x].min(initial=0)), int(hi[1][in_x].max(initial=-1)) + 1):
            sel = in_x & (lo[1] <= j) & (j <= hi[1])
            if sel.any():
                out[(i, j)] = (fin[sel] + start, chunk[fin[sel]])
    return out


def _sentinels(lo: np.ndarray, hi: np.ndarray, far: float, dtype: np.dtype) -> np.ndarray:
    """Three points that give any subset of the cloud the whole cloud's minimum corner, each
    `far` beyond the cloud in two coordinates (alone: they change no other point's result).

    The core's neighbour grid puts its cells relative to the minimum corner and sums each
    neighbourhood in cell order; with the same corner a tile's sums run in the same order as
    the whole cloud's, and its heights and normals agree to the last bit."""
    top = hi.astype(np.float64) + far
    s = np.array([[lo[0], top[1], top[2]], [top[0], lo[1], top[2]], [top[0], top[1], lo[2]]],
                 dtype=np.float64)
    s[[0, 1, 2], [0, 1, 2]] = lo  # the minima exactly, in the cloud's own type
    return s.astype(dtype if np.dtype(dtype).kind == "f" else np.float64)


def _run_points(pts: np.ndarray, kwargs: dict, sentinels: np.ndarray, survey: bool = False
                ) -> Any:
    """miem.detect on part of a cloud, the sentinels appended (after every real point, so that
    index order and ties are kept); the edge test's candidates compare with the whole cloud's
    median (``kwargs["edge_rms_median"]``); ``survey``: the first height pass's rms per point
    instead (both: ``miem._unorganized._cloud_part``)."""
    from ._unorganized import _cloud_part

    return _cloud_part(np.concatenate([pts, sentinels.astype(pts.dtype, copy=False)
                                       if pts.dtype.kind == "f" else sentinels]),
                       survey=survey, **kwargs)


def _pieces_points(pieces: list, sentinels: np.ndarray) -> tuple:
    """The (global indices, points) of a tile's pieces (from _split), concatenated."""
    pieces = [p for p in pieces if p is not None]
    idx = np.concatenate([p[0] for p in pieces]) if pieces else np.zeros(0, np.int64)
    pts = np.concatenate([p[1] for p in pieces]) if pieces else np.zeros((0, 3),
                                                                        sentinels.dtype)
    return idx, pts


def _edge_rms_tile(pieces: list, box: tuple, kwargs: dict, sentinels: np.ndarray
                   ) -> np.ndarray:
    """The bit patterns of the first height pass's surroundings rms (>= 0) of a tile's home
    points where it gave a verdict: the values the cloud edge test's median is over."""
    idx, pts = _pieces_points(pieces, sentinels)
    rms = np.asarray(_run_points(pts, kwargs, sentinels, survey=True))[:idx.size]
    rms = rms[_in_home(pts[:, :2].astype(np.float64), box)]
    return np.ascontiguousarray(rms[np.isfinite(rms)]).view(np.uint64)


def _median_of(blocks: list) -> Optional[float]:
    """NumPy's median of the values the blocks' bit patterns hold (persisted), exactly by
    radix selection (:func:`_kth`); None when there is none."""
    m = sum(dask.compute(*[delayed(len)(b) for b in blocks]))
    if m == 0:
        return None
    mid = m // 2
    med = _kth(blocks, mid)
    if m % 2 == 0:
        med = (_kth(blocks, mid - 1) + med) / 2.0
    return med


def _edge_rms_median(homes: list, kwargs: dict, sentinels: np.ndarray) -> float:
    """The whole cloud's median of the cloud edge test's candidate rms (SPEC "Unorganized
    clouds: edge test" step 1), from every tile's home points (`homes`: _homes_points with
    _survey_halo), +inf when there is none, as the core takes it."""
    blocks = list(dask.persist(*[delayed(_edge_rms_tile, pure=True)(pieces, box, kwargs,
                                                                    sentinels)
                                 for pieces, box in homes]))
    med = _median_of(blocks)
    return np.inf if med is None else med


def _detect_tile(pieces: list, box: tuple, kwargs: dict, params: dict,
                 sentinels: np.ndarray) -> dict:
    """Detect one tile's points plus its halo; keep its home points' values, its whole defects
    (first point at home, inside the home box grown by `link`) and the open parts (home
    components within `link` of the box's sides)."""
    from scipy.spatial import cKDTree

    idx, pts = _pieces_points(pieces, sentinels)
    x0, x1, y0, y1 = box
    res = _run_points(pts, kwargs, sentinels)
    n = idx.size
    home_mask = np.zeros(n, bool)
    xy = pts[:, :2].astype(np.float64)
    home_mask[:] = _in_home(xy, box)
    out = {"index": idx[home_mask]}
    for k in _POINT_KEYS:
        out[k] = np.asarray(getattr(res, k))[:n][home_mask]
    link = params["link"]
    whole = []
    for d in res.defects:
        if d.indices[-1] >= n or not home_mask[d.indices[0]]:
            continue
        m = xy[d.indices]
        if (m[:, 0] >= x0 - link).all() and (m[:, 0] < x1 + link).all() and (
                m[:, 1] >= y0 - link).all() and (m[:, 1] < y1 + link).all():
            g = idx[d.indices]
            whole.append(dataclasses.replace(d, indices=g, cells=g[:, None]))
    abn = np.flatnonzero(home_mask & (np.asarray(res.labels)[:n] == ABNORMAL))
    open_parts = []
    if abn.size:
        tree = cKDTree(pts[abn].astype(np.float64))
        comp = _link_components(tree, link, abn.size)
        near = ((xy[abn, 0] - x0 <= link) | (x1 - xy[abn, 0] <= link)
                | (xy[abn, 1] - y0 <= link) | (y1 - xy[abn, 1] <= link))
        for c in np.unique(comp[near]):
            members = abn[comp == c]
            open_parts.append((idx[members], pts[members].astype(np.float64)))
    out["whole"], out["open"] = whole, open_parts
    return out


def _in_home(xy: np.ndarray, box: tuple) -> np.ndarray:
    x0, x1, y0, y1 = box  # half-open, the last tile closed (its bounds are +inf)
    return (xy[:, 0] >= x0) & (xy[:, 0] < x1) & (xy[:, 1] >= y0) & (xy[:, 1] < y1)


def _link_components(tree: Any, link: float, n: int) -> np.ndarray:
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    pairs = tree.query_pairs(link, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def _gather(results: list, start: int, stop: int) -> dict:
    """One input chunk's values from the tiles' home points."""
    out = {k: np.full(stop - start, _POINT_FILL[k], dtype=_POINT_DTYPES[k]) for k in _POINT_KEYS}
    for r in results:
        sel = (r["index"] >= start) & (r["index"] < stop)
        if sel.any():
            pos = r["index"][sel] - start
            for k in _POINT_KEYS:
                out[k][pos] = r[k][sel]
    return out


def _region_points(chunk: np.ndarray, start: int, boxes: list) -> list:
    chunk = np.asarray(chunk)
    fin = np.flatnonzero(np.isfinite(chunk).all(axis=1))
    xy = chunk[fin, :2].astype(np.float64)
    out = []
    for x0, x1, y0, y1 in boxes:
        sel = fin[(xy[:, 0] >= x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= y0) & (xy[:, 1] <= y1)]
        out.append((sel + start, chunk[sel]))
    return out


def _redetect_points(parts: list, groups: list, kwargs: dict, sentinels: np.ndarray) -> list:
    idx = np.concatenate([p[0] for p in parts])
    pts = np.concatenate([p[1] for p in parts])
    res = _run_points(pts, kwargs, sentinels)
    by_first = {int(idx[d.indices[0]]): d for d in res.defects if d.indices[-1] < idx.size}
    out = []
    for members in groups:
        d = by_first.get(int(members[0]))
        if d is None or not np.array_equal(idx[d.indices], members):  # pragma: no cover
            raise RuntimeError("miem.dask: a joined defect differs from its re-detection")
        out.append(dataclasses.replace(d, indices=members, cells=members[:, None]))
    return out


@dataclass
class DaskPointsResult:
    """What :func:`detect_points` returns: lazy per-point arrays (aligned with the input's
    chunks) and the defects on request.

    Attributes
    ----------
    labels, flags, angle, height, degenerate : dask.array.Array, (N,)
        As :class:`miem.PointsDetectResult` (equal to ``miem.detect`` on the whole cloud).
    params : dict
        The parameters used, plus ``halo`` (length), ``tile`` (length), ``tiles`` (nx, ny) and
        ``edge_rms_median``: the whole cloud's median the cloud edge test's candidates compare
        with (found from the tiles; None when the edge test or the height test is off, and
        +inf when no point had a surroundings plane).
    """

    labels: "da.Array"
    flags: "da.Array"
    angle: "da.Array"
    height: "da.Array"
    degenerate: "da.Array"
    params: dict
    points: "da.Array" = dataclasses.field(repr=False)
    tiles: list = dataclasses.field(repr=False)
    kwargs: dict = dataclasses.field(repr=False)
    sentinels: np.ndarray = dataclasses.field(repr=False)

    def defects(self, *arrays: "da.Array", **compute_kwargs: Any):
        """The defect list, equal to ``miem.detect(points).defects``; as
        :meth:`DaskDetectResult.defects` (arrays computed in the same pass)."""
        from scipy.spatial import cKDTree

        tiles, rest = _with_arrays([delayed(_tile_summary)(t) for t in self.tiles], arrays,
                                   compute_kwargs)
        if sum(t["n"] for t in tiles) < 3:
            raise ValueError("points: fewer than 3 finite points")
        out = [d for t in tiles for d in t["whole"]]
        have = {int(d.indices[0]) for d in out}
        parts = [p for t in tiles for p in t["open"]]
        groups = []
        if parts:
            idx = np.concatenate([p[0] for p in parts])
            pts = np.concatenate([p[1] for p in parts])
            comp = _link_components(cKDTree(pts), self.params["link"], idx.size)
            for c in np.unique(comp):
                members = np.unique(idx[comp == c])
                if int(members[0]) not in have:
                    groups.append((members, pts[comp == c]))
        pad = self.params["halo"]
        boxes = [(p[:, 0].min() - pad, p[:, 0].max() + pad, p[:, 1].min() - pad,
                  p[:, 1].max() + pad) for _, p in groups]
        if boxes:
            starts = np.cumsum((0,) + self.points.chunks[0])
            per_chunk = [delayed(_region_points)(c, int(s), boxes)
                         for c, s in zip(self.points.to_delayed().ravel(), starts)]
            tasks = [delayed(_redetect_points)([delayed(operator.getitem)(pc, k)
                                                for pc in per_chunk], [groups[k][0]],
                                               self.kwargs, self.sentinels)
                     for k in range(len(groups))]
            out += [d for part in dask.compute(*tasks, **compute_kwargs) for d in part]
        return _numbered(out, rest, arrays)


def _tile_summary(t: dict) -> dict:
    return {"whole": t["whole"], "open": t["open"], "n": int(t["index"].size)}


def _advise_dense(points: da.Array, radius: float, num_threads: Optional[int]) -> None:
    """miem.detect's dense-cluster advice (a UserWarning) for a Dask cloud: the same estimate,
    on the same even sample of rows, read from the chunks that hold them."""
    from miem._api import _threads
    from miem._unorganized import _dense_estimate, _dense_sample, _dense_warning

    idx = _dense_sample(points.shape[0])
    if idx is None:
        return
    sample = np.asarray(points[idx].compute())
    if sample.dtype not in (np.float32, np.float64):
        sample = sample.astype(np.float64)
    why = _dense_estimate(sample, points.shape[0], float(radius), _threads(num_threads))
    _dense_warning(points.shape[0], why, stacklevel=4)  # at the caller of detect(_points)


def detect_points(points: Any, *, tile: Optional[float] = None, num_threads: Optional[int] = 1,
                  **kwargs: Any) -> DaskPointsResult:
    """MIEM on an unorganized cloud held as a Dask array ``(N, 3)``, tile by tile, exactly as
    :func:`miem.detect` on the whole cloud.

    The cloud is cut into square tiles in x and y; each tile is detected with the points within
    :func:`points_halo` of it and keeps the values of its own points. Finding the tiles needs
    the cloud's x, y bounds, computed here (one pass over the points). Every preset runs
    completely, the default's cloud edge test included: its candidates compare each point's
    surroundings rms with their median over the whole cloud, so with the edge test and the
    height test on, the tiles are first detected up to the height passes (with the smaller
    halo that needs, ``_survey_halo``) to survey those rms (held as 8 bytes per point until
    the median is selected), and then detected with that median: about a third more CPU time
    than without the edge test (``edge_tolerance=None`` skips both).

    Parameters
    ----------
    points : dask.array.Array, shape (N, 3)
        The cloud, in any order, chunked by rows (a NumPy array is wrapped in one chunk).
    tile : float, optional
        Tile side in the points' units; default: about one input chunk's points per tile, and at
        least twice the halo.
    num_threads : int, optional
        Threads per tile detection (default 1).
    **kwargs
        As for :func:`miem.detect` on a cloud, with the same defaults. When a default depends
        on the whole cloud's median spacing (``radius``, ``min_step``, the compact-EDGE span)
        and ``spacing`` is not given, it is found first by one pass over the tiles (exact
        distributed selection, docs/SPEC.md "Blocks"); so is the edge test's median.

    Returns
    -------
    DaskPointsResult
    """
    refuse_layout("miem.dask.detect_points", kwargs)
    return _detect_points(points, tile, num_threads, kwargs)


def _detect_points(points: Any, tile: Optional[float], num_threads: Optional[int],
                   kwargs: dict) -> DaskPointsResult:
    """detect_points' work, for it and for :func:`detect` on a cloud (one frame deeper than
    either's caller: the dense-cluster warning points at that caller's line)."""
    if not isinstance(points, da.Array):
        points = da.from_array(np.asarray(points))
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points: expected a Dask array of shape (N, 3), got {points.shape}")
    if points.dtype.kind not in "fiu":
        raise ValueError(f"points: expected a real numeric array, got dtype {points.dtype}")
    if len(points.chunks[1]) != 1:
        points = points.rechunk({1: 3})
    kwargs = dict(kwargs, num_threads=num_threads)
    params, need_spacing = _probe_points(kwargs)
    fin = da.isfinite(points).all(axis=1)[:, None]
    lo3, hi3 = dask.compute(da.where(fin, points, np.inf).min(axis=0).astype(points.dtype),
                            da.where(fin, points, -np.inf).max(axis=0).astype(points.dtype))
    if not np.isfinite(lo3.astype(np.float64)).all():
        lo3 = hi3 = np.zeros(3, dtype=points.dtype)
    if need_spacing:
        kwargs["spacing"] = _cloud_spacing(points, lo3, hi3, params["merge_distance"])
        params, _ = _probe_points(kwargs)
    _advise_dense(points, params["radius"], num_threads)
    pad = points_halo(params)
    sentinels = _sentinels(lo3, hi3, 2 * (pad + params["radius"] + params["link"]) + 1.0,
                           points.dtype)
    lo, hi = lo3[:2].astype(np.float64), hi3[:2].astype(np.float64)
    if tile is None:
        area = max(float(np.prod(hi - lo)), 1e-300)
        per = max(points.chunks[0])
        tile = max(2 * pad, float(np.sqrt(area * per / max(points.shape[0], 1))))
    else:
        tile = float(tile)
        if not (np.isfinite(tile) and tile > 0):
            raise ValueError(f"tile: expected a length > 0, got {tile}")
    n = (int(np.floor((hi[0] - lo[0]) / tile)) + 1, int(np.floor((hi[1] - lo[1]) / tile)) + 1)
    if n[0] * n[1] > 1_000_000:
        raise ValueError(f"tile: {tile} makes {n[0]} x {n[1]} tiles; pass a larger tile")
    med = None
    if params.get("edge_tolerance") is not None and params.get("height_tolerance") is not None:
        # the edge test's candidates: a median over the whole cloud, selected from the tiles
        med = _edge_rms_median(_homes_points(points, lo, tile, n, _survey_halo(params)),
                               kwargs, sentinels)
        kwargs["edge_rms_median"] = med
    tiles = [delayed(_detect_tile, pure=True)(pieces, box, kwargs, params, sentinels)
             for pieces, box in _homes_points(points, lo, tile, n, pad)]
    starts = np.cumsum((0,) + points.chunks[0])
    arrays = {}
    for key in _POINT_KEYS:
        parts = []
        for k, size in enumerate(points.chunks[0]):
            g = delayed(_gather, pure=True)(tiles, int(starts[k]), int(starts[k + 1]))
            parts.append(da.from_delayed(delayed(operator.getitem)(g, key), (size,),
                                         np.dtype(_POINT_DTYPES[key])))
        arrays[key] = da.concatenate(parts)
    params = dict(params, halo=pad, tile=tile, tiles=n, edge_rms_median=med)
    return DaskPointsResult(params=params, points=points, tiles=tiles, kwargs=kwargs,
                            sentinels=sentinels, **arrays)
