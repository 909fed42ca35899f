"""Unorganized clouds (``(N, 3)`` points, no order): neighbour grid, normals and MIEM detection.

Typed wrappers over the C++ core (``miem._core``); the exact rules are in ``docs/SPEC.md``,
section "Unorganized clouds".
"""

from __future__ import annotations

import numbers
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Dict, Optional, Tuple, Union

import numpy as np

from . import _core
from ._api import (
    Defect,
    DetectResult,
    Plane,
    _as_float_array,
    _params_record,
    _threads,
)
from .params import DetectParams, _positive, _real, resolve_params

__all__ = [
    "NeighborGrid",
    "Normals",
    "PointsDetectResult",
    "detect_points",
    "estimate_normals",
    "point_spacing",
]

def _points(points: object, name: str = "points") -> np.ndarray:
    arr = _as_float_array(points, name)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (N, 3), got {arr.shape}")
    return arr


def _plane(t: tuple) -> Plane:
    normal, d, centroid, rms, n, ev = t
    return Plane(normal, float(d), centroid, float(rms), int(n), ev, "eigen")


class NeighborGrid:
    """Exact radius and nearest-neighbour queries on a point cloud, with a uniform grid.

    Points are sorted by cell (memory linear in N, nothing allocated over the bounding box);
    cell keys are computed relative to the cloud's minimum corner, so clouds far from the origin
    lose nothing. A point ``q`` is within ``r`` of ``p`` when ``dx*dx + dy*dy + dz*dz <= r*r``
    with ``d = q - p`` in float64 (float32 input is widened first): exactly what a brute-force
    search in float64 returns.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Coordinates. float32 and float64 arrays are used in place (the grid keeps a reference;
        do not modify them while the grid is in use); other real dtypes are converted to
        float64. Rows with a non-finite coordinate are not indexed.
    cell_size : float
        Cell edge length in the points' units, ``> 0``. Queries with ``r <= cell_size`` visit at
        most 27 cells; any ``r`` gives exact results. The size is enlarged (see
        :attr:`cell_size`) only when the extent would overflow the 64-bit cell key.
    num_threads : int, optional
        Threads for building (default: all cores). The grid does not depend on it.

    Raises
    ------
    ValueError
        Wrong shape or dtype, or ``cell_size`` not finite and > 0.

    Examples
    --------
    >>> import numpy as np, miem
    >>> pts = np.array([[0.0, 0, 0], [1, 0, 0], [0, 2, 0], [5, 5, 5]])
    >>> grid = miem.NeighborGrid(pts, cell_size=1.0)
    >>> grid.radius_query(0, 1.5).tolist()
    [0, 1]
    >>> grid.radius_query([0.0, 1.0, 0.0], 1.0).tolist()
    [0, 2]
    """

    def __init__(
        self, points: np.ndarray, cell_size: float, *, num_threads: Optional[int] = None
    ) -> None:
        arr = _points(points)
        cs = _positive("cell_size", cell_size)
        self._grid = _core.NeighborGrid(arr, cs, _threads(num_threads))
        self._points = arr  # the core keeps it alive too; this is for the property

    @property
    def points(self) -> np.ndarray:
        """The indexed array, shape (N, 3) (a view of the input when no conversion was needed)."""
        return self._points

    @property
    def cell_size(self) -> float:
        """Cell edge length used (the requested one unless it had to be enlarged)."""
        return float(self._grid.cell_size)

    @property
    def num_cells(self) -> int:
        """Number of occupied cells."""
        return int(self._grid.num_cells)

    @property
    def num_indexed(self) -> int:
        """Number of finite points indexed."""
        return int(self._grid.num_indexed)

    def __len__(self) -> int:
        return int(self._points.shape[0])

    def radius_query(
        self, i_or_xyz: Union[int, Sequence[float], np.ndarray], r: float
    ) -> np.ndarray:
        """Indices of the finite points within distance ``r``.

        Parameters
        ----------
        i_or_xyz : int or array_like, shape (3,)
            A row index into :attr:`points` (the point itself is part of the result; a
            non-finite row has no neighbours), or query coordinates.
        r : float
            Radius in the points' units, finite and ``>= 0``.

        Returns
        -------
        ndarray, shape (k,), int64
            Row indices, ascending.

        Raises
        ------
        ValueError
            Index out of range, coordinates not 3 finite numbers, or ``r`` not finite and >= 0.
        """
        rv = _real("r", r)
        if rv < 0:
            raise ValueError(f"r: expected a radius >= 0, got {rv}")
        if isinstance(i_or_xyz, (numbers.Integral, np.integer)) and not isinstance(
            i_or_xyz, (bool, np.bool_)
        ):
            i = int(i_or_xyz)
            n = len(self)
            if not 0 <= i < n:
                raise ValueError(f"i_or_xyz: index {i} is out of range for {n} points")
            return self._grid.query_index(i, rv)
        try:
            q = np.asarray(i_or_xyz, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(
                f"i_or_xyz: expected a row index or 3 coordinates, got {i_or_xyz!r}"
            ) from None
        if q.shape != (3,):
            raise ValueError(f"i_or_xyz: expected a row index or shape (3,), got shape {q.shape}")
        if not np.all(np.isfinite(q)):
            raise ValueError(f"i_or_xyz: coordinates must be finite, got {q.tolist()}")
        return self._grid.query_point(float(q[0]), float(q[1]), float(q[2]), rv)

    def nearest_distances(self, *, num_threads: Optional[int] = None) -> np.ndarray:
        """Distance from every point to its nearest other finite point.

        Returns
        -------
        ndarray, shape (N,), float64
            0 for a duplicated point, ``inf`` when there is no other finite point, NaN for
            non-finite rows. Does not depend on ``num_threads``.
        """
        return self._grid.nearest_distances(_threads(num_threads))

    def __repr__(self) -> str:
        return (
            f"NeighborGrid(n={len(self)}, indexed={self.num_indexed}, "
            f"cells={self.num_cells}, cell_size={self.cell_size:g})"
        )


@dataclass(frozen=True)
class Normals:
    """Local planes of a cloud (what :func:`estimate_normals` returns).

    Attributes
    ----------
    normals : ndarray, shape (N, 3), float64
        Oriented unit normals (``n_z > 0``; if ``|n_z| <= 1e-6`` the first larger component is
        positive); NaN rows where ``valid`` is False.
    rms : ndarray, shape (N,), float64
        RMS orthogonal distance of the fitted points from their plane, in the points' units;
        NaN where ``valid`` is False.
    count : ndarray, shape (N,), int64
        Points used for each fit (the point itself included); 0 for non-finite rows.
    valid : ndarray, shape (N,), bool
        False for non-finite rows, fewer than 3 points within the radius, or degenerate
        (collinear or identical) neighbourhoods.
    radius : float
        The radius used.
    """

    normals: np.ndarray
    rms: np.ndarray
    count: np.ndarray
    valid: np.ndarray
    radius: float


def estimate_normals(
    points: np.ndarray, radius: float, *, num_threads: Optional[int] = None
) -> Normals:
    """Normal and local flatness at every point from the points within ``radius``.

    For each finite point: the eigenvalue plane fit (``docs/SPEC.md``, "Plane fit") of the
    finite points within ``radius``, the point itself included.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Coordinates (float32 / float64 read in place, other real dtypes converted). Rows with a
        non-finite coordinate are dropouts.
    radius : float
        Neighbourhood radius in the points' units, finite and > 0.
    num_threads : int, optional
        Threads (default: all cores). The result does not depend on it.

    Returns
    -------
    Normals

    Raises
    ------
    ValueError
        Wrong shape or dtype, or ``radius`` not finite and > 0.
    """
    arr = _points(points)
    r = _positive("radius", radius)
    normals, rms, count, valid = _core.estimate_normals(arr, r, _threads(num_threads))
    return Normals(normals=normals, rms=rms, count=count, valid=valid, radius=r)


def point_spacing(points: np.ndarray, *, num_threads: Optional[int] = None) -> float:
    """Median distance from each finite point to its nearest other finite point.

    The mean of the two middle values for an even count (as :func:`numpy.median`).

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Coordinates; non-finite rows are ignored.
    num_threads : int, optional
        Threads (default: all cores).

    Returns
    -------
    float
        The spacing, in the points' units.

    Raises
    ------
    ValueError
        Fewer than 3 finite points, or spacing 0 (more than half the points are duplicates).
    """
    arr = _points(points)
    return float(_core.point_spacing(arr, _threads(num_threads)))


@dataclass(frozen=True)
class PointsDetectResult(DetectResult):
    """What :func:`detect_points` returns: a :class:`miem.DetectResult` whose per-point arrays
    have shape ``(N,)``, plus the ``degenerate`` mask.

    ``flags`` bit ``k`` is tangent direction ``k``; ``height`` is the signed distance from the
    plane of the NORMAL points within ``radius``; each :class:`miem.Defect` has row
    ``indices`` into the input and ``cells = indices[:, None]``. ``params`` records the values
    used, including ``spacing``, ``radius``, ``min_step`` and ``link``.

    Attributes
    ----------
    degenerate : ndarray, shape (N,), bool
        True where the point's last judgment met a degenerate neighbourhood (collinear or
        identical neighbours: no direction available, judged NORMAL).
    stage_seconds : dict of str to (float, float)
        Wall-clock and process CPU seconds of each stage of the run, in run order (a profile,
        for benchmarks; it varies from run to run and is no part of the result).
    """

    degenerate: Optional[np.ndarray] = None
    stage_seconds: Optional[Dict[str, Tuple[float, float]]] = field(default=None, compare=False, repr=False)


def detect_points(
    points: np.ndarray,
    params: Optional[DetectParams] = None,
    *,
    preset: Optional[str] = None,
    num_threads: Optional[int] = None,
    **overrides: Any,
) -> PointsDetectResult:
    """Find abnormal points in an unorganized cloud with MIEM.

    Each finite point's usable neighbours within ``radius`` define a local plane; ``K``
    directions in that plane are tested by the interior angle between the nearest neighbours on
    either side (at least ``s * min_step`` away in the tangent plane, within ``90/K`` degrees
    of the direction). Flagged in every available direction: ABNORMAL; in some: EDGE; in none:
    NORMAL. Fewer than 3 neighbours: ABNORMAL (a lone return). ABNORMAL points are removed and
    the points around them judged again, up to ``max_iterations`` passes. See ``docs/SPEC.md``,
    "Unorganized clouds", for the exact rules.

    The parameters are a :class:`miem.DetectParams`, as for :func:`miem.detect`: ``params``,
    a ``preset`` or the default preset (``"recommended"``: theta0 90, scales (1, 2), floating
    groups and the height test over the surroundings; ``"paper"`` is the paper's method), with
    keyword ``overrides``. Clouds read the ``angle`` part (``theta0`` in degrees: "auto" is
    refused for clouds; ``scales``, ``min_directions`` 1..K, ``max_iterations``) and the
    ``cloud`` part (``radius``, default ``5 * spacing`` with ``spacing`` the median
    nearest-neighbour distance, :func:`point_spacing`; ``K``; ``min_step``; ``link``;
    ``heights``; ``height_tolerance``; ``edge_extent``; ``min_group``; ``height_radius``;
    ``merge_distance``; ``edge_tolerance`` and ``edge_radius``: the cloud edge test, on by
    default, judging at ``edge_radius`` and at 1.5 times it, SPEC "Unorganized clouds: edge
    test"). A field of the ``grid`` part (``window``, ``max_gap``, the grid edge
    test, ...) is a ``ValueError`` naming it: clouds do not implement it.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        The cloud, any order. float32 / float64 are read in place (any strides); other real
        dtypes are converted. Rows with a non-finite coordinate are INVALID and take no part.
    params : DetectParams or mapping, optional
        The full parameter set (not together with ``preset``).
    preset : {"recommended", "paper"}, optional
        A named parameter set (default ``"recommended"``).
    num_threads : int, optional
        Threads (default: all cores). The results do not depend on it.
    **overrides
        Fields of :class:`miem.DetectParams`.

    Returns
    -------
    PointsDetectResult
        ``labels`` (N,) uint8, ``flags`` (N,) uint8, ``angle`` (N,) float64 degrees,
        ``height`` (N,) float64 in the points' units, ``degenerate`` (N,) bool, the MIEM
        ``plane``, ``iterations``, ``defects`` and ``params`` (with ``spacing``, ``radius``,
        ``min_step``, ``link`` as used).

    Raises
    ------
    ValueError
        Wrong shape or dtype, fewer than 3 distinct finite points (all points one point), a
        parameter out of range, or ``layout`` / ``shape`` (:func:`miem.detect`'s: this is
        the cloud detector).

    Examples
    --------
    >>> import numpy as np, miem
    >>> rng = np.random.default_rng(0)
    >>> y, x = np.mgrid[0:40, 0:40] * 0.4                # a 16 mm patch, 0.4 mm apart ...
    >>> pts = np.column_stack([x.ravel(), y.ravel(), np.zeros(1600)])
    >>> pts[:, :2] += rng.uniform(-0.1, 0.1, (1600, 2))  # ... sampled unevenly
    >>> pts[820, 2] = 1.0                                 # a 1 mm spike
    >>> res = miem.detect(pts, radius=2.0)
    >>> np.flatnonzero(res.labels == miem.ABNORMAL).tolist(), res.defects[0].kind
    ([820], 'protrusion')

    Notes
    -----
    The neighbourhood is a ball: a protrusion taller than about ``0.8 * radius`` keeps fewer
    than 3 neighbours (ABNORMAL, but its height is NaN and its defect ``isolated``). The default
    ``radius = 5 * spacing`` holds ~20 points on a uniformly random cloud (with 3 spacings,
    ~5 % of such points had fewer than 3 neighbours and their removal cascaded).
    """
    from ._layout import refuse_layout

    refuse_layout("detect_points", overrides)
    arr = _points(points)
    p, name = resolve_params(params, preset, overrides, "cloud")
    return _detect_cloud(arr, p, name, _threads(num_threads), advise=True)


#: The dense-cluster advice of detect_points / miem.detect (:func:`_dense_advice`): given for
#: clouds of at least this many rows ...
_DENSE_MIN_POINTS = 20_000
#: ... whose points have on average more than this many others within ``radius`` (an even scan
#: has about 50 at the default radius; the detector's time grows with the count) ...
_DENSE_MEAN = 500
#: ... estimated on an even sample of this many rows (their counts among themselves, scaled).
_DENSE_SAMPLE = 1 << 14


def _dense_advice(arr: np.ndarray, radius: float, nt: int) -> str:
    """Why detecting `arr` at `radius` costs far more than an even scan, or "": the mean count
    of other points within `radius` and the share above 1,000, estimated on an even sample of
    the rows (:func:`_dense_sample`, :func:`_dense_estimate`)."""
    idx = _dense_sample(arr.shape[0])
    return "" if idx is None else _dense_estimate(arr[idx], arr.shape[0], radius, nt)


def _dense_sample(n: int) -> Optional[np.ndarray]:
    """The rows the dense-cluster estimate reads in a cloud of n rows (an even sample of at
    most _DENSE_SAMPLE), or None below _DENSE_MIN_POINTS rows (no advice)."""
    if n < _DENSE_MIN_POINTS:
        return None
    return np.linspace(0, n - 1, min(n, _DENSE_SAMPLE)).astype(np.int64)


def _dense_estimate(sample: np.ndarray, n: int, radius: float, nt: int) -> str:
    """_dense_advice from the sampled rows of a cloud of n rows: each sampled point's count
    among the sample, times rows / sample, when their mean is above _DENSE_MEAN."""
    m = sample.shape[0]
    sample = sample[np.isfinite(sample).all(axis=1)]
    if sample.shape[0] < 2:
        return ""
    others = (_core.estimate_normals(sample, radius, nt)[2] - 1) * (n / m)
    mean = float(others.mean())
    if mean <= _DENSE_MEAN:
        return ""
    return (f"its points have about {mean:,.0f} others each within radius {radius:.4g} "
            f"({np.mean(others > 1000):.0%} of them more than 1,000), where an even scan has "
            "about 50 at the default radius")


def _dense_warning(n: int, why: str, stacklevel: int) -> None:
    """The dense-cluster advice as a UserWarning (nothing when `why` is empty)."""
    if why:
        warnings.warn(
            f"detect: this ({n}, 3) cloud is dense for its radius: {why}. The "
            "cloud detector's time grows with the points in each ball: drop dense clusters "
            "(such as returns around the scanner), or pass a smaller radius",
            UserWarning, stacklevel=stacklevel + 1)


def _detect_cloud(arr: np.ndarray, p: DetectParams, name: str, nt: int,
                  edge_rms_median: float = float("nan"),
                  advise: bool = False) -> PointsDetectResult:
    """detect_points on a checked (N, 3) float array with resolved parameters.
    ``edge_rms_median``: internal (miem.dask, see :func:`_cloud_part`). ``advise``: warn when
    the cloud is dense enough to make the run slow (:func:`_dense_advice`; the public entry
    points, not miem.dask's parts)."""
    if arr.shape[0] < 3:
        raise ValueError(f"points: need at least 3 points, got {arr.shape[0]}")
    core_params = p._core_cloud(nt)
    (labels, flags, angle, height, degenerate, plane_t, iterations, raw, spacing, radius_u,
     min_step_u, link_u, height_radius_u, merged, stages,
     edge_radius_u) = _core.detect_points(arr, core_params, edge_rms_median)
    defects = [
        Defect(
            id=int(i), indices=idx, cells=idx[:, None], count=int(idx.size), centroid=c,
            normal=n, peak_height=float(pk), mean_height=float(mh), extent=float(ex),
            kind=str(kind),
        )
        for (i, idx, c, n, pk, mh, ex, kind) in raw
    ]
    params = _params_record(
        p, name, "cloud", theta0=float(core_params.theta0_deg), theta0_auto=False,
        min_step=float(min_step_u), radius=float(radius_u), link=float(link_u),
        spacing=float(spacing), height_radius=float(height_radius_u), merged=int(merged),
        edge_radius=float(edge_radius_u) if edge_radius_u > 0 else p.cloud.edge_radius,
    )
    if advise:
        _dense_warning(arr.shape[0], _dense_advice(arr, float(radius_u), nt), stacklevel=3)
    return PointsDetectResult(
        labels=labels, flags=flags, angle=angle, height=height,
        plane=None if plane_t is None else _plane(plane_t),
        iterations=int(iterations), defects=defects, params=params, degenerate=degenerate,
        stage_seconds={name: (wall, cpu) for name, wall, cpu in stages},
    )


def _cloud_part(points: np.ndarray, edge_rms_median: Optional[float] = None, *,
                survey: bool = False, params: Optional[DetectParams] = None,
                preset: Optional[str] = None, num_threads: Optional[int] = None,
                **overrides: Any) -> Union[PointsDetectResult, np.ndarray]:
    """Internal hook for miem.dask, which detects a cloud in parts (docs/SPEC.md "Blocks");
    not a parameter of miem.detect. The cloud edge test's candidates compare each point's
    surroundings rms (the first height pass's) with their median over the whole cloud, which
    a part does not see.

    ``survey=True``: per row, that rms where the first height pass gave a verdict (NaN
    elsewhere and for rows merged into another); the run stops after the height passes.
    Otherwise :func:`detect_points` with the edge test's median replaced by
    ``edge_rms_median`` (the whole cloud's, selected from the parts' surveys; +inf when no
    point of the whole cloud had a verdict; None: the part's own)."""
    arr = _points(points)
    p, name = resolve_params(params, preset, overrides, "cloud")
    if survey:
        if arr.shape[0] < 3:
            raise ValueError(f"points: need at least 3 points, got {arr.shape[0]}")
        return _core.edge_rms_survey(arr, p._core_cloud(_threads(num_threads)))
    return _detect_cloud(arr, p, name, _threads(num_threads),
                         float("nan") if edge_rms_median is None else float(edge_rms_median))
