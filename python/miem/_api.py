"""Typed Python API over the C++ core: argument checks, conversions and result types."""

from __future__ import annotations

import enum
import math
import warnings
import numbers
import re
from dataclasses import dataclass, field
from typing import Any, Literal, Optional, Sequence, Union

import numpy as np

from . import _core

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
        return (pts.astype(np.float64, copy=False) - self.centroid) @ self.normal


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


def _as_float_array(a: object, name: str) -> np.ndarray:
    """A float32/float64 native-order array view of `a` (copied only when it must be).

    A structured array with fields x, y, z is accepted wherever an ``(..., 3)`` array is.
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
    return arr


def _int(name: str, value: object, minimum: int, maximum: int = 2**30) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name}: expected an integer >= {minimum}, got {value!r}")
    v = int(value)
    if v < minimum:
        raise ValueError(f"{name}: expected an integer >= {minimum}, got {v}")
    if v > maximum:
        raise ValueError(f"{name}: expected an integer in {minimum}..{maximum}, got {v}")
    return v


def _real(name: str, value: object) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name}: expected a real number, got {value!r}")
    v = float(value)
    if not np.isfinite(v):
        raise ValueError(f"{name}: must be finite, got {v}")
    return v


def _theta0(value: object) -> float:
    v = _real("theta0", value)
    if not 0.0 < v < 180.0:
        raise ValueError(f"theta0: expected 0 < theta0 < 180 degrees, got {v}")
    return v


def _scales(value: object) -> list:
    if isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_)):
        value = (value,)
    try:
        out = [_int("scales", s, 1) for s in value]  # type: ignore[union-attr]
    except TypeError:
        raise ValueError(f"scales: expected integers >= 1, got {value!r}") from None
    if not out:
        raise ValueError("scales: must contain at least one scale")
    return out


def _min_step(value: object) -> Optional[float]:
    if value is None:
        return None
    v = _real("min_step", value)
    if v < 0:
        raise ValueError(f"min_step: expected a length >= 0 or None, got {v}")
    return v


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


class _Default:
    """Marks a parameter the caller did not give: its value comes from the preset."""

    def __repr__(self) -> str:
        return "<from preset>"


DEFAULT: Any = _Default()

#: Named parameter sets for :func:`detect`. ``"paper"`` is the paper's method exactly.
PRESETS: dict = {
    "paper": {
        "theta0": 75.0,
        "scales": (1,),
        "max_gap": 1,
        "min_step": None,
        "min_directions": None,
        "max_iterations": 10,
        "window": 21,
        "height_tolerance": None,
        "edge_extent": 0,
    },
    # Chosen on the tuning split of bench/accuracy (bench/accuracy/recommended.json): overall F1
    # 0.96 on the test split against 0.20 for "paper" (bench/accuracy/RESULTS.md).
    "recommended": {
        "theta0": 90.0,
        "scales": (1, 2),
        "max_gap": 1,
        "min_step": None,
        "min_directions": None,
        "max_iterations": 10,
        "window": 21,
        "height_tolerance": "4.5rms",
        "edge_extent": 12,
    },
}

#: Cloud-only values of each preset (unorganized ``(N, 3)`` input), on top of :data:`PRESETS`.
#: "recommended" was chosen on the tuning split of the held-out-style cloud scenes
#: (``bench/accuracy/clouds.py``; ``bench/bench_unorganized.py`` reports the test split). Its
#: ``height_tolerance`` differs from the grids' because the cloud test fits the point's
#: surroundings only (SPEC "Unorganized clouds: floating groups and height test").
CLOUD_PRESETS: dict = {
    "paper": {"height_tolerance": None, "edge_extent": 0, "min_group": 0},
    "recommended": {"height_tolerance": "7rms", "edge_extent": 12, "min_group": 40},
}

#: The preset used when ``preset`` is not given: the paper's method, so that a plain call, the
#: streaming detector (which has no height test) and the C++ defaults agree. For production use
#: ``preset="recommended"``, which wins the accuracy benchmark (README, bench/accuracy/).
DEFAULT_PRESET = "paper"

_RMS = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*rms\s*$")


def _height_tolerance(value: object) -> tuple:
    """(absolute, k_rms) from None, a length or a '<k>rms' string; 0 means off."""
    if value is None:
        return 0.0, 0.0
    if isinstance(value, str):
        m = _RMS.match(value)
        if not m or not float(m.group(1)) > 0 or not np.isfinite(float(m.group(1))):
            raise ValueError(
                f"height_tolerance: expected a length > 0, '<k>rms' with k > 0 (e.g. '4rms') "
                f"or None, got {value!r}")
        return 0.0, float(m.group(1))
    v = _real("height_tolerance", value)
    if not v > 0:
        raise ValueError(f"height_tolerance: expected a length > 0, got {v}")
    return v, 0.0


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
    finite = np.isfinite(arr).all(axis=1)
    nan_rows = int(n - finite.sum())
    if nan_rows:
        if nan_rows == n:
            return ""
        arr = arr[finite]
        n = arr.shape[0]
    lo, hi = arr.min(axis=0), arr.max(axis=0)
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


def _resolve(preset: Optional[str], given: dict) -> dict:
    name = DEFAULT_PRESET if preset is None else preset
    if name not in PRESETS:
        raise ValueError(f"preset: expected one of {sorted(PRESETS)}, got {preset!r}")
    out = dict(PRESETS[name])
    out.update({k: v for k, v in given.items() if v is not DEFAULT})
    return out


def detect(
    grid: np.ndarray,
    theta0: Union[float, str] = DEFAULT,
    scales: Union[int, Sequence[int]] = DEFAULT,
    max_gap: int = DEFAULT,
    min_step: Optional[float] = DEFAULT,
    min_directions: Optional[int] = DEFAULT,
    max_iterations: int = DEFAULT,
    window: int = DEFAULT,
    *,
    preset: Optional[str] = None,
    height_tolerance: Union[None, float, str] = DEFAULT,
    edge_extent: int = DEFAULT,
    max_reach: int = 32,
    heights: Literal["all", "abnormal"] = "all",
    num_threads: Optional[int] = None,
    radius: Optional[float] = None,
    K: int = 4,
    link: Optional[float] = None,
    min_group: int = DEFAULT,
    height_radius: Optional[float] = None,
    shape: Optional[Sequence[int]] = None,
) -> DetectResult:
    """Find abnormal points in a scan with MIEM: an organized grid or an unorganized cloud.

    Each finite point is tested in four directions (along the profile, across profiles, both
    diagonals): a direction is flagged when the interior angle between its neighbours is at most
    ``theta0``. Flagged in every available direction: ABNORMAL; in some only: EDGE (a designed
    feature edge); in none: NORMAL. ABNORMAL points are removed and the rest judged again, up to
    ``max_iterations`` passes. See ``docs/SPEC.md`` for the exact rules.

    Parameters not given come from ``preset`` (default ``"paper"``: the values in brackets).

    An unorganized cloud (``(N, 3)`` points, or an ``open3d.geometry.PointCloud``) goes to
    :func:`miem.detect_points` (tangent-plane directions in a ``radius`` neighbourhood, SPEC.md
    "Unorganized clouds"): ``theta0`` (a number), ``scales``, ``min_step``, ``min_directions``,
    ``max_iterations``, ``height_tolerance``, ``edge_extent`` (in spacings), ``radius``, ``K``,
    ``link``, ``min_group``, ``height_radius``, ``heights`` and ``num_threads`` apply, with the
    preset's cloud values (:data:`miem.CLOUD_PRESETS`); the grid-only ``max_gap``, ``window``,
    ``max_reach`` and ``theta0="auto"`` raise ValueError. Per-point arrays then have shape
    ``(N,)``.

    Parameters
    ----------
    grid : array_like, shape (H, W, 3)
        Organized scan: row = one laser profile, column = position along it. float32 or
        float64 are read in place (any strides); NaN (any non-finite coordinate) marks a dropout.
    theta0 : float or "auto"
        [75] Threshold angle in degrees, ``0 < theta0 < 180``. ``"auto"`` derives it from the
        scan's own angle statistics: ``clip(180 - 6 sigma, 75, 170)`` with ``sigma`` a robust
        spread of ``180 - angle``, so small burrs are caught on quiet scans without false alarms
        on noisy ones (``result.params["theta0"]`` holds the value used).
    scales : int or sequence of int
        [(1,)] Neighbour distances in cells; ``(1, 2)`` also catches defects two cells wide.
    max_gap : int
        [1] Unusable cells (dropouts, removed points) that may be skipped to reach a neighbour.
    min_step : float, optional
        [None] Minimum neighbour distance in the grid's units (per scale: ``s * min_step``), so
        that the test sees the same physical scale along and across profiles. None: off.
    min_directions : int, optional
        [None] Flagged directions needed for ABNORMAL (1-4); None: all available ones.
    max_iterations : int
        [10] Maximum number of passes (>= 1).
    window : int
        [21] Side, in cells, of the square used for the local plane under each point (odd, >= 3).
    preset : {"paper", "recommended"}, optional
        A named parameter set (:data:`miem.PRESETS`); explicit arguments override its values.
        ``"recommended"`` (theta0 90, scales (1, 2), height_tolerance "4.5rms", edge_extent 12)
        won the accuracy benchmark (overall F1 0.96 against 0.20 for ``"paper"``).
    height_tolerance : float, str or None
        [None] Height test, beyond the paper: after the angle passes, a NORMAL point farther than
        this from its local plane becomes ABNORMAL (catches smooth spatter domes and wide burrs
        the angle test cannot see). A length in the grid's units, or ``"<k>rms"`` for ``k`` times
        the local plane's rms. None: off. The test abstains where a feature line (a group of
        EDGE points longer than ``edge_extent``) lies in the window.
    edge_extent : int or None
        [0] (None: 0) With the height test: groups of EDGE points (8-connected) whose bounding box is at
        most this many cells on its longer side are compact (a defect's halo, a short burr
        ridge, a spatter dome) and are height-tested like NORMAL points; longer groups are
        designed feature lines (creases, flanges, strips) and are never changed.
    max_reach : int
        With ``min_step``: how many cells beyond ``scale + max_gap`` the search may go.
    heights : {"all", "abnormal"}
        Which points get a height: all finite points, or only ABNORMAL ones (faster; the others
        are NaN).
    num_threads : int, optional
        Threads (default: all cores). Labels do not depend on it.
    radius, K, link : optional
        Unorganized clouds only: neighbourhood radius (default 5 x the median point spacing),
        number of tangent-plane directions (2-8) and defect linking distance (default
        ``radius``); see :func:`miem.detect_points`.
    min_group, height_radius : optional
        Unorganized clouds only: floating groups smaller than ``min_group`` points are
        ABNORMAL; radius of the height planes (default ``2 * radius``).
    shape : (int, int), optional
        An organized scan that arrives flattened (an ``(H*W, 3)`` array, e.g. an Open3D cloud
        read from an organized PCD): its ``(H, W)``, so that it keeps its grid and gets the
        organized detector. Without it, an ``(N, 3)`` array is an unorganized cloud; a warning
        says when one looks like a flattened grid (rows in scan-line order).

    Returns
    -------
    DetectResult
        For an unorganized cloud, a :class:`miem.PointsDetectResult` (adds ``degenerate``).

    Raises
    ------
    ValueError
        Wrong shape or dtype, fewer than 3 finite points, or a parameter out of range.

    Examples
    --------
    >>> import numpy as np, miem
    >>> y, x = np.mgrid[0:32, 0:32] * 0.5
    >>> grid = np.dstack([x, y, np.zeros_like(x)])
    >>> grid[10, 12, 2] = 3.0                     # a 3 mm spike
    >>> res = miem.detect(grid)
    >>> np.argwhere(res.labels == miem.ABNORMAL).tolist(), round(res.defects[0].peak_height, 6)
    ([[10, 12]], 3.0)
    """
    if _is_open3d(grid):
        from .io import from_open3d

        grid = from_open3d(grid)
    arr = _as_float_array(grid, "grid")
    if shape is not None:
        arr = _with_shape(arr, shape)
    elif arr.ndim == 2 and arr.shape[1] == 3:
        why = _looks_like_grid(arr)
        if why:
            warnings.warn(
                f"detect: this ({arr.shape[0]}, 3) cloud looks like a flattened organized scan "
                f"({why}); it is detected as an unorganized cloud. Pass shape=(H, W) to keep "
                "its grid, or rebuild one with miem.io.grid_from_scanlines",
                UserWarning, stacklevel=2)
    if arr.ndim == 2 and arr.shape[1] == 3:
        given = {"max_gap": max_gap, "window": window}
        bad = sorted(k for k, v in given.items() if v is not DEFAULT)
        if max_reach != 32:
            bad.append("max_reach")
        if isinstance(theta0, str):
            bad.append("theta0='auto'")
        if bad:
            raise ValueError(f"{', '.join(bad)}: apply to organized grids (H, W, 3) only, "
                             f"not to an unorganized cloud {arr.shape}")
        cfg = _resolve(preset, {
            "theta0": theta0, "scales": scales, "min_step": min_step,
            "min_directions": min_directions, "max_iterations": max_iterations,
        })
        from ._unorganized import detect_points

        name = DEFAULT_PRESET if preset is None else preset
        cloud = dict(CLOUD_PRESETS[name])
        cloud.update({k: v for k, v in {"height_tolerance": height_tolerance,
                                        "edge_extent": edge_extent,
                                        "min_group": min_group}.items() if v is not DEFAULT})
        res = detect_points(
            arr, theta0=cfg["theta0"], scales=cfg["scales"],
            min_step=cfg["min_step"], min_directions=cfg["min_directions"],
            max_iterations=cfg["max_iterations"], radius=radius, K=K, link=link,
            heights=heights, num_threads=num_threads, height_radius=height_radius, **cloud,
        )
        res.params["preset"] = DEFAULT_PRESET if preset is None else preset
        return res
    if (radius is not None or K != 4 or link is not None or min_group is not DEFAULT
            or height_radius is not None):
        raise ValueError("radius, K, link, min_group, height_radius: apply to unorganized clouds "
                         "(N, 3) only")
    cfg = _resolve(preset, {
        "theta0": theta0, "scales": scales, "max_gap": max_gap, "min_step": min_step,
        "min_directions": min_directions, "max_iterations": max_iterations, "window": window,
        "height_tolerance": height_tolerance, "edge_extent": edge_extent,
    })
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"grid: expected shape (H, W, 3) or (N, 3), got {arr.shape}")
    if arr.shape[0] * arr.shape[1] < 3:
        raise ValueError(f"grid: need at least 3 points, got {arr.shape[0] * arr.shape[1]}")
    theta0 = cfg["theta0"]
    auto = isinstance(theta0, str)
    if auto:
        if theta0 != "auto":
            raise ValueError(f"theta0: expected degrees or 'auto', got {theta0!r}")
        theta0_v = 75.0
    else:
        theta0_v = _theta0(theta0)
    scale_list = _scales(cfg["scales"])
    gap = _int("max_gap", cfg["max_gap"], 0)
    min_step = cfg["min_step"]
    step = _min_step(min_step)
    step_v = -1.0 if step is None else step
    min_directions = cfg["min_directions"]
    md = 0 if min_directions is None else _int("min_directions", min_directions, 1)
    if md > 4:
        raise ValueError(f"min_directions: expected 1..4 or None, got {md}")
    iters = _int("max_iterations", cfg["max_iterations"], 1)
    win = _int("window", cfg["window"], 3)
    if win % 2 == 0:
        raise ValueError(f"window: expected an odd number of cells, got {win}")
    h_abs, h_k = _height_tolerance(cfg["height_tolerance"])
    extent = 0 if cfg["edge_extent"] is None else _int("edge_extent", cfg["edge_extent"], 0)
    reach = _int("max_reach", max_reach, 1)
    if heights not in ("all", "abnormal"):
        raise ValueError(f"heights: expected 'all' or 'abnormal', got {heights!r}")
    nt = _threads(num_threads)

    labels, flags, angle, height, plane_t, iterations, raw, theta0_used = _core.detect_organized(
        arr, theta0_v, scale_list, gap, step_v, reach, md, iters, win,
        0 if heights == "all" else 1, nt, auto, h_abs, h_k, extent,
    )
    width = arr.shape[1]
    defects = [
        Defect(
            id=int(i), indices=idx, cells=np.stack([idx // width, idx % width], axis=1),
            count=int(idx.size), centroid=c, normal=n, peak_height=float(pk),
            mean_height=float(mh), extent=float(ex), kind=str(kind),
        )
        for (i, idx, c, n, pk, mh, ex, kind) in raw
    ]
    params = dict(
        preset=DEFAULT_PRESET if preset is None else preset, theta0=float(theta0_used),
        theta0_auto=auto, scales=tuple(scale_list), max_gap=gap, min_step=min_step,
        min_directions=min_directions, max_iterations=iters, window=win,
        height_tolerance=cfg["height_tolerance"], edge_extent=extent, max_reach=reach,
        heights=heights,
    )
    return DetectResult(
        labels=labels, flags=flags, angle=angle, height=height,
        plane=None if plane_t is None else _plane(plane_t, "eigen"),
        iterations=int(iterations), defects=defects, params=params,
    )
