"""Typed Python API over the C++ core: argument checks, conversions and result types."""

from __future__ import annotations

import enum
import math
import numbers
import warnings
from dataclasses import dataclass, field
from typing import Any, Literal, Optional, Sequence

import numpy as np

from . import _core
from .params import (
    CLOUD_PRESETS,
    DEFAULT_PRESET,
    PRESETS,
    DetectParams,
    _int,
    _real,
    resolve_params,
)

__all__ = [
    "Label",
    "NORMAL",
    "ABNORMAL",
    "EDGE",
    "INVALID",
    "Plane",
    "Defect",
    "DetectResult",
    "fit_plane",
    "scan_line_angles",
    "scan_line_heights",
    "detect",
    "PRESETS",
    "CLOUD_PRESETS",
    "DEFAULT_PRESET",
    "DetectParams",
]


class Label(enum.IntEnum):
    """Per-point labels (stored as ``uint8``)."""

    NORMAL = 0  #: on the surface
    ABNORMAL = 1  #: flagged in every available direction, or a lone return: grind or discard
    EDGE = 2  #: flagged in some directions only: a designed feature edge, never ground
    INVALID = 3  #: non-finite coordinates (a dropout)


NORMAL = Label.NORMAL
ABNORMAL = Label.ABNORMAL
EDGE = Label.EDGE
INVALID = Label.INVALID


@dataclass(frozen=True)
class Plane:
    """A plane ``normal . p + d = 0`` with a unit normal oriented so that ``normal[2] > 0``.

    Attributes
    ----------
    normal : ndarray, shape (3,), float64
        Unit normal.
    d : float
        Offset, in the points' units: ``d = -normal . centroid``.
    centroid : ndarray, shape (3,), float64
        Mean of the fitted points.
    rms : float
        RMS orthogonal distance of the fitted points from the plane (the paper's standard
        deviation), in the points' units.
    n_points : int
        Number of finite points used.
    eigenvalues : ndarray, shape (3,), float64
        Eigenvalues of the scatter matrix, ascending (units squared).
    method : str
        ``"eigen"`` or ``"lstsq"``.
    """

    normal: np.ndarray
    d: float
    centroid: np.ndarray
    rms: float
    n_points: int
    eigenvalues: np.ndarray
    method: str = "eigen"

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distances of points from the plane.

        Parameters
        ----------
        points : array_like, shape (..., 3)
            Points in the plane's units.

        Returns
        -------
        ndarray, shape (...), float64
            ``normal . p + d``: positive on the side the normal points to, NaN for non-finite
            points.
        """
        pts = _as_float_array(points, "points")
        if pts.ndim < 1 or pts.shape[-1] != 3:
            raise ValueError(f"points: expected shape (..., 3), got {pts.shape}")
        # Subtract the centroid first: exact for far-from-origin coordinates.
        with np.errstate(invalid="ignore"):
            dist = (pts.astype(np.float64, copy=False) - self.centroid) @ self.normal
        return np.where(np.isfinite(pts).all(axis=-1), dist, np.nan)[()]


@dataclass(frozen=True)
class Defect:
    """One connected group of ABNORMAL points (8-connected cells of an organized scan).

    Attributes
    ----------
    id : int
        Rank by ``|peak_height|`` (0 is the largest).
    indices : ndarray, shape (count,), int64
        Flat point indices (``row * W + col`` for a grid), ascending.
    cells : ndarray, shape (count, 2), int64
        ``(row, col)`` of each point.
    count : int
        Number of points.
    centroid : ndarray, shape (3,), float64
        Mean of the points.
    normal : ndarray, shape (3,), float64
        Local surface normal (tool axis) at the peak point; NaN when no local plane exists.
    peak_height : float
        Signed height of largest magnitude over the local surface (protrusion > 0, pit < 0).
    mean_height : float
        Mean height of the points.
    extent : float
        Diameter of the group in the local tangent plane, in the points' units.
    kind : str
        ``"protrusion"``, ``"pit"`` or ``"isolated"`` (a floating return with no surface around).
    """

    id: int
    indices: np.ndarray
    cells: np.ndarray
    count: int
    centroid: np.ndarray
    normal: np.ndarray
    peak_height: float
    mean_height: float
    extent: float
    kind: str


@dataclass(frozen=True)
class DetectResult:
    """What :func:`detect` returns. Per-point arrays have the grid's ``(H, W)`` shape.

    Attributes
    ----------
    labels : ndarray, (H, W), uint8
        :class:`Label` values.
    flags : ndarray, (H, W), uint8
        Bit ``k`` set when direction ``k`` was flagged: 0 along the profile, 1 across profiles,
        2 the ``(1, 1)`` diagonal, 3 the ``(1, -1)`` diagonal.
    angle : ndarray, (H, W), float64
        Smallest interior angle seen at the point, degrees; NaN where no direction was available.
    height : ndarray, (H, W), float64
        Signed distance from the plane of the NORMAL points in a ``window`` square around the
        point (protrusion > 0, pit < 0), in the grid's units; NaN where no such plane exists.
    plane : Plane or None
        The MIEM plane: eigenvalue fit of every finite non-ABNORMAL point (None if degenerate).
    iterations : int
        Passes run.
    defects : list of Defect
        Connected ABNORMAL groups, largest ``|peak_height|`` first.
    params : dict
        The parameters used.
    """

    labels: np.ndarray
    flags: np.ndarray
    angle: np.ndarray
    height: np.ndarray
    plane: Optional[Plane]
    iterations: int
    defects: list = field(default_factory=list)
    params: dict = field(default_factory=dict)

    @property
    def abnormal(self) -> np.ndarray:
        """Boolean mask of ABNORMAL points, shape (H, W)."""
        return self.labels == Label.ABNORMAL

    def counts(self) -> dict:
        """Number of points per label name."""
        return {lab.name: int(np.count_nonzero(self.labels == lab)) for lab in Label}


# ---------------------------------------------------------------------------------------------
# argument checks


def _xyz_fields(arr: np.ndarray, name: str) -> np.ndarray:
    """A structured array with x, y, z fields (``miem simulate``, plyfile's ``vertex.data``,
    NumPy record arrays) as a ``(..., 3)`` array of the widest of the three field types."""
    names = {n.lower(): n for n in arr.dtype.names or ()}
    if not {"x", "y", "z"} <= names.keys():
        raise ValueError(
            f"{name}: a structured array needs fields x, y and z, got fields "
            f"{list(arr.dtype.names)}"
        )
    cols = [arr[names[c]] for c in "xyz"]
    for col in cols:
        if col.dtype.kind not in "iuf" or col.dtype.shape:
            raise ValueError(
                f"{name}: field {col.dtype!s} of x, y, z must be a real number, got {col.dtype}"
            )
    return np.stack(cols, axis=-1).astype(np.result_type(*cols, np.float32), copy=False)


def _check_range(arr: np.ndarray, name: str, lower: bool = True) -> None:
    """ValueError when the finite coordinates leave the SPEC range ("Numbers"; one pass, no
    copy): the core's bounds and message (miem/views.hpp CoordinateRangeError), which its
    detectors raise themselves. With ``lower=False`` only the upper bound is checked (a stream
    sees one profile at a time, and the lower bound is about the whole scan)."""
    top = _core.finite_extent(arr, name)  # largest finite magnitude: one pass, in place
    _core.check_range(top, name, lower)


def _as_float_array(a: object, name: str, lower: bool = True,
                    check_range: bool = True) -> np.ndarray:
    """A float32/float64 native-order array view of `a` (copied only when it must be).

    A structured array with fields x, y, z is accepted wherever an ``(..., 3)`` array is.
    ``check_range=False`` leaves SPEC's coordinate range to the caller (the organized core and
    the stream check it in the pass that reads every coordinate anyway).
    """
    try:
        arr = np.asarray(a)
    except Exception as exc:  # pragma: no cover - numpy raises many kinds here
        raise ValueError(f"{name}: cannot be converted to an array ({exc})") from None
    if arr.dtype.names is not None:
        arr = _xyz_fields(arr, name)
    kind = arr.dtype.kind
    if kind in "iu" or (kind == "f" and arr.dtype.itemsize not in (4, 8)):
        arr = arr.astype(np.float64)
    elif kind != "f":
        raise ValueError(f"{name}: expected a real numeric array, got dtype {arr.dtype}")
    if not arr.dtype.isnative:  # big-endian data: one copy into native float32 / float64
        arr = arr.astype(np.float32 if arr.itemsize == 4 else np.float64)
    item = arr.itemsize
    if not arr.flags.aligned or any(s % item for s in arr.strides):
        arr = arr.copy()  # aligned and C-ordered: the core never reads a misaligned value
    if check_range:
        _check_range(arr, name, lower)
    return arr


def _threads(num_threads: Optional[int]) -> int:
    """0 (all cores) or the request clamped to ``miem._core.max_threads()`` (README
    "Guarantees": results never depend on the thread count, so clamping only bounds the cost)."""
    if num_threads is None:
        return 0
    return min(_int("num_threads", num_threads, 1, maximum=2**63), _core.max_threads())


def _plane(t: tuple, method: str) -> Plane:
    normal, d, centroid, rms, n, ev = t
    return Plane(normal, float(d), centroid, float(rms), int(n), ev, method)


# ---------------------------------------------------------------------------------------------
# public functions


def fit_plane(
    points: np.ndarray,
    method: Literal["eigen", "lstsq"] = "eigen",
    *,
    num_threads: Optional[int] = None,
) -> Plane:
    """Fit a plane to points.

    Parameters
    ----------
    points : array_like, shape (N, 3) or (..., 3)
        Coordinates (float32 or float64 are used without a copy; integers are converted).
        Rows with a non-finite coordinate are ignored (dropouts).
    method : {"eigen", "lstsq"}
        ``"eigen"``: the eigenvalue method (smallest eigenvector of the centred scatter matrix,
        paper eq. 4-17). ``"lstsq"``: least squares ``z = a x + b y + c`` (the paper's baseline).
    num_threads : int, optional
        Threads for large inputs (default: all cores). The result does not depend on it.

    Returns
    -------
    Plane

    Raises
    ------
    ValueError
        Wrong shape or dtype, fewer than 3 finite points, or degenerate points (all equal,
        collinear; for ``"lstsq"`` also a plane containing the z axis).
    """
    if method not in ("eigen", "lstsq"):
        raise ValueError(f"method: expected 'eigen' or 'lstsq', got {method!r}")
    pts = _as_float_array(points, "points")
    if pts.ndim < 1 or pts.shape[-1] != 3:
        raise ValueError(f"points: expected shape (N, 3) or (..., 3), got {pts.shape}")
    pts = pts.reshape(-1, 3)
    if pts.shape[0] < 3:
        raise ValueError(f"points: need at least 3 points, got {pts.shape[0]}")
    return _plane(_core.fit_plane(pts, method, _threads(num_threads)), method)


def _line(line: np.ndarray, step: int) -> tuple:
    arr = _as_float_array(line, "line")
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"line: expected shape (N, 3), got {arr.shape}")
    return arr, _int("step", step, 1)


def scan_line_angles(line: np.ndarray, step: int = 1) -> np.ndarray:
    """Interior angle at every point of one scan line (paper eq. 18-19).

    Parameters
    ----------
    line : array_like, shape (N, 3)
        Points in scan order (one profile). Non-finite points are dropouts.
    step : int
        Neighbours are ``step`` points before and after.

    Returns
    -------
    ndarray, shape (N,), float64
        Angle in degrees, 180 on a straight run, small at a spike; NaN at the ends, next to
        dropouts and where a neighbour coincides with the point.
    """
    arr, step = _line(line, step)
    return _core.scan_line_angles(arr, step)


def scan_line_heights(line: np.ndarray, step: int = 1) -> np.ndarray:
    """Paper eq. 20: height of each point over the line through its predecessors.

    ``D_i = sin(theta_{i-step}) * |P_i - P_{i-step}|``, with ``theta`` from
    :func:`scan_line_angles`.

    Parameters
    ----------
    line : array_like, shape (N, 3)
        Points in scan order.
    step : int
        As for :func:`scan_line_angles`.

    Returns
    -------
    ndarray, shape (N,), float64
        Non-negative heights in the line's units; NaN where the angle is undefined.
    """
    arr, step = _line(line, step)
    return _core.scan_line_heights(arr, step)


def _is_open3d(obj: object) -> bool:
    return type(obj).__module__.startswith("open3d") and hasattr(obj, "points")


def _with_shape(arr: np.ndarray, shape: object) -> np.ndarray:
    """A flattened organized scan ``(H*W, 3)`` back as its ``(H, W, 3)`` grid (a view)."""
    try:
        h, w = (int(v) for v in shape)  # type: ignore[union-attr]
        ok = all(isinstance(v, (numbers.Integral, np.integer)) for v in shape)  # type: ignore
    except (TypeError, ValueError):
        ok = False
    if not ok or h < 1 or w < 1:
        raise ValueError(f"shape: expected (H, W), two integers >= 1, got {shape!r}")
    if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] != h * w:
        raise ValueError(f"shape: ({h}, {w}) needs an (H*W, 3) = ({h * w}, 3) array, got "
                         f"{arr.shape}")
    return arr.reshape(h, w, 3)


def _looks_like_grid(arr: np.ndarray) -> str:
    """Why an ``(N, 3)`` array looks like a flattened organized scan ("" when it does not):
    rows (NaN rows left out) in scan-line order (at least 90 % of the steps
    between consecutive rows within 0.5-1.5x of their median, which is within 2x of
    ``sqrt(area / N)``)."""
    n = arr.shape[0]
    if n < 64:
        return ""
    # (Every call on a cloud runs this, before the core: a sum first, since a finite sum means
    # every coordinate is finite, and per-column extremes, 8x faster than axis=0 reductions of
    # an (N, 3) array; the same values.)
    with np.errstate(over="ignore", invalid="ignore"):
        all_finite = bool(np.isfinite(arr.sum()))
    if not all_finite:
        finite = np.isfinite(arr).all(axis=1)
        nan_rows = int(n - finite.sum())
        if nan_rows == n:
            return ""
        arr = arr[finite]
        n = arr.shape[0]
    lo = np.array([arr[:, k].min() for k in range(3)])
    hi = np.array([arr[:, k].max() for k in range(3)])
    ext = np.sort(hi - lo)
    if not ext[1] > 0:
        return ""
    sample = arr[: min(n, 100_000)].astype(np.float64)
    steps = np.sqrt(np.sum(np.diff(sample, axis=0) ** 2, axis=1))
    typical = math.sqrt(ext[2] * ext[1] / n)
    med = float(np.median(steps))
    regular = np.mean((steps >= 0.5 * med) & (steps <= 1.5 * med)) >= 0.9
    if 0 < med <= 2.0 * typical and regular:
        return "consecutive rows are evenly spaced neighbours, in scan-line order"
    return ""


def _grid_or_cloud(data: object) -> np.ndarray:
    """detect's array: an (H, W, 3) grid is left to the core's coordinate-range check (in angle
    pass 1, which reads every coordinate anyway); anything else is checked here."""
    if _is_open3d(data):
        from .io import from_open3d

        data = from_open3d(data)
    arr = _as_float_array(data, "grid", check_range=False)
    if arr.ndim != 3:
        _check_range(arr, "grid")
    return arr


#: How detect's advice on a cloud that looks like a grid goes on after saying so (the command
#: line replaces what follows with its options: cli._cli_advice).
_AS_CLOUD = "; it is detected as an unorganized cloud"


def detect(
    grid: np.ndarray,
    params: Optional[DetectParams] = None,
    *,
    preset: Optional[str] = None,
    num_threads: Optional[int] = None,
    shape: Optional[Sequence[int]] = None,
    layout: Optional[str] = None,
    **overrides: Any,
) -> DetectResult:
    """Find abnormal points in a scan with MIEM: an organized grid or an unorganized cloud.

    Each finite point is tested in four directions (along the profile, across profiles, both
    diagonals): a direction is flagged when the interior angle between its neighbours is at most
    ``theta0``. Flagged in every available direction: ABNORMAL; in some only: EDGE (a designed
    feature edge); in none: NORMAL. ABNORMAL points are removed and the rest judged again, up to
    ``max_iterations`` passes; then (beyond the paper) the height test turns NORMAL points far
    from their local plane into ABNORMAL, and the edge test turns points standing proud of a
    feature line or the scan's outline (burrs on cut edges and wall tops) into ABNORMAL. See
    ``docs/SPEC.md`` for the exact rules.

    The parameters are a :class:`miem.DetectParams` (each field's unit and meaning is listed
    there and in ``docs/SPEC.md`` "Parameters"): ``params``, or a named ``preset``
    (:data:`miem.PRESETS`), or by default the recommended preset, the best measured
    configuration (theta0 90, scales (1, 2), min_step "auto", height_tolerance "4.5rms",
    edge_extent 12, edge_tolerance 4, edge_window 15; bench/accuracy/RESULTS.md and
    results_edges.md give its scores against the paper's method). ``preset="paper"``
    runs the paper's method exactly. Keyword ``overrides`` (any field name, e.g.
    ``theta0=80``) replace single fields.

    An unorganized cloud (``(N, 3)`` points, or an ``open3d.geometry.PointCloud``) goes to
    :func:`miem.detect_points`; per-point arrays then have shape ``(N,)``. Clouds run the same
    preset with their own neighbourhoods (``docs/SPEC.md`` "Unorganized clouds") and refuse the
    grid-only fields (``max_gap``, ``window``, ``max_reach``, ``edge_window``,
    ``theta0="auto"``); grids refuse the cloud part's own (``radius``, ``K``, ``link``,
    ``min_group``, ...: :class:`miem.DetectParams`). A cloud
    whose points lie on a profiler's scan lines (an export without its grid, in scan order or
    not) is better detected as the grid rebuilt from them: ``layout="auto"``.

    Parameters
    ----------
    grid : array_like, shape (H, W, 3) or (N, 3)
        Organized scan: row = one laser profile, column = position along it. float32 or
        float64 are read in place (any strides; a column-major grid, e.g. Fortran order, is
        copied into C order once, which is faster); NaN (any non-finite coordinate) marks a
        dropout.
    params : DetectParams or mapping, optional
        The full parameter set (not together with ``preset``).
    preset : {"recommended", "paper"}, optional
        A named parameter set.
    num_threads : int, optional
        Threads (default: all cores). Labels do not depend on it.
    shape : (int, int), optional
        An organized scan that arrives flattened (an ``(H*W, 3)`` array, e.g. an Open3D cloud
        read from an organized PCD): its ``(H, W)``, so that it keeps its grid and gets the
        organized detector. Without it (and without ``layout``), an ``(N, 3)`` array is an
        unorganized cloud; a warning says when one looks like a flattened grid (rows in
        scan-line order) or like a profiler scan in another order.
    layout : {"auto", "scanlines", "cloud"}, optional
        For an ``(N, 3)`` array, as ``miem detect FILE --layout``: ``"auto"`` rebuilds the grid
        of the points' scan lines when they lie on them (``miem.io.grid_from_scanlines``, in
        file order or by line position, both horizontal layouts tried; at least half its cells
        filled) and runs the organized detector on it, else the cloud detector;
        ``"scanlines"`` always rebuilds (a ValueError when no grid can be); ``"cloud"`` is the
        cloud detector without advice. A rebuilt grid's result is per input row, like a
        cloud's: each row gets its cell's label, flags, angle and height (rows not in the
        grid, the non-finite ones: INVALID, NaN), defects list input rows, ``degenerate`` is
        None, and ``params`` adds ``layout="scanlines"``, ``grid_shape``, ``scan_order``
        (``"file"`` or ``"line"``) and ``line_axis``. Not with ``shape`` nor for a grid.
    **overrides
        Fields of :class:`miem.DetectParams` that replace those of ``params`` / the preset.

    Returns
    -------
    DetectResult
        For an unorganized cloud, a :class:`miem.PointsDetectResult` (adds ``degenerate``).
        ``params`` records every field used, ``preset`` (its name, ``"custom"`` for ``params``)
        and, with ``theta0="auto"``, the threshold found (``theta0``, ``theta0_auto``); with
        ``min_step="auto"``, the value used (``min_step``, None when off; ``min_step_auto``);
        likewise ``z_resolution`` and ``z_noise``.

    Raises
    ------
    ValueError
        Wrong shape or dtype, fewer than 3 finite points, a parameter out of range or not
        implemented for this kind of data (the message names it), an unknown field name.

    Examples
    --------
    >>> import numpy as np, miem
    >>> y, x = np.mgrid[0:32, 0:32] * 0.5
    >>> grid = np.dstack([x, y, np.zeros_like(x)])
    >>> grid[10, 12, 2] = 3.0                     # a 3 mm spike
    >>> res = miem.detect(grid)
    >>> np.argwhere(res.labels == miem.ABNORMAL).tolist(), round(res.defects[0].peak_height, 6)
    ([[10, 12]], 3.0)
    >>> miem.detect(grid, preset="paper").params["theta0"]
    75.0
    """
    arr = _grid_or_cloud(grid)
    try:
        return _detect_array(arr, params, preset, num_threads, shape, layout, overrides)
    except ValueError as exc:
        # a grid's coordinate range is the core's (its error says "rescale the points"); the
        # range error still comes before any other
        if arr.ndim == 3 and "rescale the points" not in str(exc):
            _range_error_first(arr)
        raise


def _range_error_first(arr: np.ndarray) -> None:
    """The coordinate-range ValueError of ``arr`` (SPEC "Numbers"), if it has one, in place of
    another error about it: the range is reported before anything else, whichever check found
    the other first."""
    try:
        _check_range(arr, "grid")
    except ValueError as exc:
        raise exc from None


def _detect_array(arr: np.ndarray, params: Optional[DetectParams], preset: Optional[str],
                  num_threads: Optional[int], shape: Optional[Sequence[int]],
                  layout: Optional[str], overrides: dict) -> DetectResult:
    """detect's body, for ``arr`` from _grid_or_cloud."""
    from . import _layout

    nt = _threads(num_threads)
    _layout.check_layout(layout, arr, shape)
    if shape is not None:
        arr = _with_shape(arr, shape)
    elif layout in ("auto", "scanlines"):
        built = _layout.rebuild(arr, layout)
        if built is not None:
            return _layout.detect_rebuilt(
                *built, lambda g: _detect_grid(g, params, preset, overrides, nt))
    elif layout is None and arr.ndim == 2 and arr.shape[1] == 3:
        _advise_layout(arr)
    if arr.ndim == 2 and arr.shape[1] == 3:
        from ._unorganized import _detect_cloud

        p, name = resolve_params(params, preset, overrides, "cloud")
        return _detect_cloud(arr, p, name, nt, advise=True)
    return _detect_grid(arr, params, preset, overrides, nt)


def _advise_layout(arr: np.ndarray) -> None:
    """detect's warning when an ``(N, 3)`` array given without ``layout`` looks like a
    flattened grid or a profiler scan in another order (its advice after _AS_CLOUD)."""
    why = _looks_like_grid(arr)
    what = "a flattened organized scan"
    advice = ("Pass shape=(H, W) to keep its grid, or layout='auto' to rebuild it where its "
              "points lie on scan lines")
    if not why:
        from .io import _on_scan_lines

        why = _on_scan_lines(arr)
        what = "a profiler scan whose points are not in scan-line order"
        advice = "Pass layout='auto' to rebuild its grid for the organized detector"
    if why:
        warnings.warn(f"detect: this ({arr.shape[0]}, 3) cloud looks like {what} "
                      f"({why}){_AS_CLOUD}. {advice}", UserWarning, stacklevel=3)


def _detect_grid(arr: np.ndarray, params: Any, preset: Optional[str], overrides: dict,
                 nt: int) -> DetectResult:
    """detect on an organized grid (``arr``: the caller's array, not yet checked)."""
    p, name = resolve_params(params, preset, overrides, "grid")
    core_params = p._core_grid(nt)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"grid: expected shape (H, W, 3) or (N, 3), got {arr.shape}")
    if arr.shape[0] * arr.shape[1] < 3:
        raise ValueError(f"grid: need at least 3 points, got {arr.shape[0] * arr.shape[1]}")
    if arr.shape[0] > 1 and abs(arr.strides[1]) > abs(arr.strides[0]):
        # column-major (Fortran order, as MATLAB files load): the core runs along rows, where
        # such a grid's neighbours lie a column apart; one copy into C order costs less
        # (bench/RESULTS.md "Memory layouts")
        arr = np.ascontiguousarray(arr)

    (labels, flags, angle, height, plane_t, iterations, raw, theta0_used,
     min_step_used, z_resolution_used, z_noise_used) = _core.detect_organized(arr, core_params)
    defects = _grid_defects(raw, arr.shape[1])
    return DetectResult(
        labels=labels, flags=flags, angle=angle, height=height,
        plane=None if plane_t is None else _plane(plane_t, "eigen"),
        iterations=int(iterations), defects=defects,
        params=_params_record(p, name, "grid", theta0=float(theta0_used),
                              theta0_auto=bool(core_params.theta0_auto),
                              min_step=None if min_step_used < 0 else float(min_step_used),
                              min_step_auto=bool(core_params.min_step_auto),
                              z_resolution=(None if z_resolution_used < 0
                                            else float(z_resolution_used)),
                              z_resolution_auto=bool(core_params.z_resolution_auto),
                              z_noise=None if z_noise_used < 0 else float(z_noise_used),
                              z_noise_auto=bool(core_params.z_noise_auto)),
    )


def _grid_defects(raw: list, width: int) -> "list[Defect]":
    """Defect objects from the core's (id, indices, centroid, normal, peak, mean, extent, kind)
    tuples of a grid ``width`` points wide."""
    return [
        Defect(
            id=int(i), indices=idx, cells=np.stack([idx // width, idx % width], axis=1),
            count=int(idx.size), centroid=c, normal=n, peak_height=float(pk),
            mean_height=float(mh), extent=float(ex), kind=str(kind),
        )
        for (i, idx, c, n, pk, mh, ex, kind) in raw
    ]


def _params_record(p: DetectParams, name: str, path: str, **extra: Any) -> dict:
    """``result.params``: the preset's name, every field the detector read, and what the run
    derived."""
    out = {"preset": name, **p.flat(path)}
    out.update(extra)
    return out
