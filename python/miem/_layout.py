"""``miem.detect(points, layout=...)``: a cloud whose points lie on a profiler's scan lines,
detected as the grid rebuilt from them (``miem.io.grid_from_scanlines``, as ``miem detect FILE``
does), with every result mapped back onto the input's rows."""

from __future__ import annotations

from typing import Any, Callable, Optional

import numpy as np

from ._api import Defect, DetectResult, Label

#: ``layout`` values (None: an ``(N, 3)`` array is a cloud, with advice when it looks like a
#: grid): the command line's ``--layout`` choices.
LAYOUTS = ("auto", "scanlines", "cloud")


def check_layout(layout: Optional[str], arr: np.ndarray, shape: Any) -> None:
    """A ValueError for a layout that is not one of LAYOUTS, or given for data that is not an
    ``(N, 3)`` cloud (a grid, or a cloud given its grid by ``shape``)."""
    if layout is None:
        return
    if not isinstance(layout, str) or layout not in LAYOUTS:
        raise ValueError(f"layout: expected one of {', '.join(map(repr, LAYOUTS))} or None, "
                         f"got {layout!r}")
    if shape is not None:
        raise ValueError(f"layout: {layout!r} is for (N, 3) clouds; shape= already gives the "
                         "grid (pass one of them)")
    if not (arr.ndim == 2 and arr.shape[1] == 3):
        raise ValueError(f"layout: {layout!r} is for (N, 3) clouds, got an array of shape "
                         f"{arr.shape} (a grid is detected as it is)")


#: What each caller that takes neither ``layout`` nor ``shape`` says instead (refuse_layout).
_INSTEAD = {
    "detect_points": "it runs the cloud detector; miem.detect(points, layout='auto') rebuilds "
                     "the grid of a cloud on scan lines, miem.detect(points, shape=(H, W)) keeps "
                     "a flattened grid",
    "miem.dask.detect": "it detects a cloud tile by tile and a grid as it is; give it the grid "
                        "(miem.io.grid_from_scanlines rebuilds one from scan lines, "
                        "points.reshape(H, W, 3) restores a flattened one)",
    "miem.dask.detect_points": "it runs the cloud detector tile by tile; give miem.dask.detect "
                               "the grid instead (miem.io.grid_from_scanlines rebuilds one "
                               "from scan lines, points.reshape(H, W, 3) restores a flattened "
                               "one)",
}


def refuse_layout(caller: str, kwargs: dict) -> None:
    """A ValueError naming ``layout`` or ``shape`` when ``kwargs`` has either: ``caller`` (a key
    of _INSTEAD) does not take them, and says what does."""
    for name in ("layout", "shape"):
        if name in kwargs:
            raise ValueError(f"{name}: {caller} does not take it: {_INSTEAD[caller]}")


def rebuild(arr: np.ndarray, layout: str) -> Optional[tuple[np.ndarray, np.ndarray, dict]]:
    """The grid of `arr`'s scan lines, the flat cell of each row (-1: not in the grid) and what
    the rebuild found (recorded in the result's params), as ``miem detect FILE`` finds it
    (``miem.io._rebuild_grid``); None for ``"auto"`` when the points are not on scan lines
    (``"scanlines"`` raises then)."""
    from .io import _rebuild_grid

    try:
        grid, index, order, line_axis = _rebuild_grid(arr, force=layout == "scanlines")
    except ValueError as exc:
        if layout == "scanlines":
            raise ValueError(f"layout: 'scanlines' but no grid could be rebuilt from the "
                             f"points' scan lines: {exc}") from exc
        return None
    info = {"layout": "scanlines", "grid_shape": tuple(int(s) for s in grid.shape[:2]),
            "scan_order": order, "line_axis": int(line_axis)}
    return grid, index, info


def on_points(values: np.ndarray, index: np.ndarray, label: bool = False) -> np.ndarray:
    """Per-cell `values` (H, W) as per-row values for the rows `index` points at (flat cells);
    a row in no cell (-1) gets what a dropout gets: NaN, INVALID for `label`s, else 0."""
    flat = np.asarray(values).reshape(-1)
    fill = np.nan if flat.dtype.kind == "f" else (Label.INVALID if label else 0)
    out = np.full(index.shape, fill, dtype=flat.dtype)
    ok = index >= 0
    out[ok] = flat[index[ok]]
    return out


def cell_rows(index: np.ndarray, cells: int) -> np.ndarray:
    """The input row of each flat cell (-1: empty), from `index` (row -> cell)."""
    rows = np.full(cells, -1, dtype=np.int64)
    ok = index >= 0
    rows[index[ok]] = np.flatnonzero(ok)
    return rows


def detect_rebuilt(grid: np.ndarray, index: np.ndarray, info: dict,
                   detect_grid: Callable[[np.ndarray], DetectResult]) -> DetectResult:
    """detect_grid on the rebuilt `grid`, as a per-row result of the cloud (`index`: each row's
    flat cell, -1 for none, as :func:`rebuild` gives it): labels, flags, angle
    and height of each row's cell (INVALID, 0, NaN, NaN for rows not in the grid: non-finite
    ones), defects with the rows of their cells (``indices``, ``cells = indices[:, None]``),
    the grid result's params plus `info`. No ``degenerate`` mask (the organized detector has
    none)."""
    from ._unorganized import PointsDetectResult

    res = detect_grid(grid)
    rows = cell_rows(index, grid.shape[0] * grid.shape[1])
    defects = []
    for d in res.defects:
        idx = np.sort(rows[np.asarray(d.indices, dtype=np.int64)])
        defects.append(Defect(id=d.id, indices=idx, cells=idx[:, None], count=int(idx.size),
                              centroid=d.centroid, normal=d.normal,
                              peak_height=d.peak_height, mean_height=d.mean_height,
                              extent=d.extent, kind=d.kind))
    return PointsDetectResult(
        labels=on_points(res.labels, index, label=True),
        flags=on_points(res.flags, index), angle=on_points(res.angle, index),
        height=on_points(res.height, index),
        plane=res.plane, iterations=res.iterations, defects=defects,
        params={**res.params, **info}, degenerate=None,
    )
