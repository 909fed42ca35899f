"""Independent NumPy reference implementation of miem (the test oracle).

This module is written from ``shared/METHOD.md`` (the project's reading of the paper) and
``docs/SPEC.md`` (the exact tie-breaking rules; SPEC.md wins where it is more precise) and from
nothing else: it shares no code with the C++ core (``miem._core``) and imports no other miem
module. The test-suite asserts that the core and this module give identical labels and flags and
equal floats within tight tolerances.

It is slow by design: every rule is written out the way the spec states it, with whole-grid array
operations per direction, scale and step, and every non-ABNORMAL cell re-judged on every pass
(no incremental bookkeeping). Use the compiled API for real data.

All geometry is computed in float64 whatever the input dtype; plane fits are computed on centred
data. Labels are ``uint8``: NORMAL 0, ABNORMAL 1, EDGE 2, INVALID 3.

Floating-point conventions (so that a careful core can match bit for bit where it matters):

* dot products are summed left to right, ``(x*x' + y*y') + z*z'``;
* the threshold is ``math.cos(theta0 * math.pi / 180.0)`` and a direction is flagged when
  ``cos >= threshold`` with ``cos = clip(u.v / sqrt((u.u) * (v.v)), -1, 1)``;
* the ``min_step`` test is ``sqrt(dx*dx + dy*dy + dz*dz) >= s * min_step`` (a real square root,
  not a comparison of squares);
* ``theta0="auto"``: ``angle = degrees(arccos(cos))`` as above, ``dev = 180.0 - angle``
  (0 where below ``1e-3``), ``sigma = median(dev) / 0.6745`` (``np.median``),
  ``theta0 = min(max(180.0 - 6.0 * sigma, 75.0), 170.0)``, then the threshold cosine as above;
* height test: ``h = n . P + d`` with ``d = -n . centroid`` of the window plane; absolute form
  ``|h| > t``; rms form ``|h| > k * sqrt(max(l0, 0) / n)`` and
  ``|h| > 1e-6 * sqrt((l1 + l2) / n)``, ``n`` the number of NORMAL cells in the window.
"""

from __future__ import annotations

import itertools
import math
import numbers
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from typing import Any, Optional

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "ABNORMAL",
    "DIRECTIONS",
    "EDGE",
    "INVALID",
    "MAX_K",
    "NORMAL",
    "RefDefect",
    "RefNormals",
    "RefPlane",
    "RefPointsResult",
    "RefResult",
    "detect",
    "detect_points",
    "estimate_normals",
    "fit_plane",
    "scan_line_angles",
    "scan_line_heights",
]

NORMAL: int = 0
ABNORMAL: int = 1
EDGE: int = 2
INVALID: int = 3

#: The four grid directions ``(dr, dc)``; direction ``k`` sets flag bit ``1 << k``.
DIRECTIONS: tuple[tuple[int, int], ...] = ((0, 1), (1, 0), (1, 1), (1, -1))

# Degeneracy thresholds of SPEC.md ("Plane fit").
_EIGEN_RANK_TOL = 1e-12
#: A window plane (SPEC "Height") exists only where its normal is unique: ``l1 - l0`` above this
#: times ``l2`` (equal smallest eigenvalues leave any normal in their plane; an ``l1`` within
#: round-off of the rank limit is no rank; above the core's accuracy at a double root).
_WINDOW_UNIQUE = 1e-6
_LSTSQ_DET_TOL = 1e-12

# Upper bound on the number of window entries (cells x window^2) processed at once by the
# height computation; keeps the temporaries at a few tens of MB.
_WINDOW_CHUNK_ENTRIES = 1 << 21


# --------------------------------------------------------------------------------------------
# Result types
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class RefPlane:
    """A plane ``normal . p + d = 0`` with ``|normal| = 1``.

    Attributes
    ----------
    normal : ndarray, shape (3,), float64
        Unit normal, oriented so that ``normal[2] > 0``, or, when ``|normal[2]| <= 1e-6``, so
        that its first component larger than that in magnitude is positive.
    d : float
        Offset, ``-normal . centroid`` (caller's length unit).
    centroid : ndarray, shape (3,), float64
        Mean of the points used.
    rms : float
        RMS orthogonal distance of the points used from the plane (caller's length unit).
    n_points : int
        Number of finite points used.
    """

    normal: NDArray[np.float64]
    d: float
    centroid: NDArray[np.float64]
    rms: float
    n_points: int

    def distance(self, points: ArrayLike) -> NDArray[np.float64]:
        """Signed distance of points from the plane.

        Parameters
        ----------
        points : array_like, shape (..., 3)
            Points (caller's length unit).

        Returns
        -------
        ndarray, shape (...), float64
            ``points @ normal + d``; positive on the side the normal points to.
        """
        p = np.asarray(points, dtype=np.float64)
        if p.ndim < 1 or p.shape[-1] != 3:
            raise ValueError(f"points: expected shape (..., 3), got {p.shape}")
        with np.errstate(invalid="ignore", over="ignore"):  # non-finite points give NaN / inf
            return _dot3(p, self.normal) + self.d


@dataclass(frozen=True, eq=False)
class RefDefect:
    """One connected group of ABNORMAL cells.

    Attributes
    ----------
    id : int
        Position in the defect list (ordered by ``|peak_height|`` descending, NaN last, ties by
        smallest member index).
    indices : ndarray, shape (count,), int64
        Flat cell indices ``r * W + c``, ascending.
    count : int
        Number of member cells.
    centroid : ndarray, shape (3,), float64
        Mean of the member points.
    normal : ndarray, shape (3,), float64
        Window-plane normal at the peak cell (the tool axis); NaN vector if none.
    peak_height : float
        Member height of largest magnitude (signed); NaN if no member has a finite height.
    mean_height : float
        Mean of the finite member heights; NaN if none.
    extent : float
        Twice the largest distance of a member from the centroid, measured in the plane
        orthogonal to ``normal`` (3-D distance when ``normal`` is NaN).
    kind : str
        ``"protrusion"``, ``"pit"`` or ``"isolated"``.
    """

    id: int
    indices: NDArray[np.int64]
    count: int
    centroid: NDArray[np.float64]
    normal: NDArray[np.float64]
    peak_height: float
    mean_height: float
    extent: float
    kind: str


@dataclass(frozen=True, eq=False)
class RefResult:
    """Result of :func:`detect` on an organized grid of shape ``(H, W, 3)``.

    Attributes
    ----------
    labels : ndarray, shape (H, W), uint8
        NORMAL 0, ABNORMAL 1, EDGE 2, INVALID 3.
    flags : ndarray, shape (H, W), uint8
        Bitmask of flagged directions (bit ``k`` for ``DIRECTIONS[k]``).
    angle : ndarray, shape (H, W), float64
        Smallest interior angle seen, in degrees; NaN where no direction was available.
    height : ndarray, shape (H, W), float64
        Signed distance from the window plane of the NORMAL cells (protrusion > 0, pit < 0);
        NaN where that plane cannot be fitted and for non-finite cells.
    plane : RefPlane or None
        Eigenvalue fit of every finite non-ABNORMAL cell (the MIEM plane); None if impossible.
    iterations : int
        Number of passes run: angle passes plus height passes.
    defects : list of RefDefect
        Connected groups of ABNORMAL cells, in SPEC.md order.
    params : dict
        Values used, after applying the preset: ``preset`` (str or None), ``theta0`` (float,
        degrees; the computed value when ``"auto"`` was asked), ``theta0_auto`` (bool),
        ``scales`` (tuple of int), ``max_gap``, ``min_step``, ``min_directions``,
        ``max_iterations``, ``window``, ``max_reach`` and ``height_tolerance`` (None, a float
        or the ``"<k>rms"`` string as given).
    """

    labels: NDArray[np.uint8]
    flags: NDArray[np.uint8]
    angle: NDArray[np.float64]
    height: NDArray[np.float64]
    plane: RefPlane | None
    iterations: int
    defects: list[RefDefect]
    params: dict[str, Any]


# --------------------------------------------------------------------------------------------
# Validation helpers
# --------------------------------------------------------------------------------------------


def _is_int(value: Any) -> bool:
    """True for Python / NumPy integers, False for bools (and everything else)."""
    return isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))


def _is_real(value: Any) -> bool:
    """True for Python / NumPy real numbers, False for bools (and everything else)."""
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def _check_int(name: str, value: Any, minimum: int, maximum: int | None = None) -> int:
    if not _is_int(value):
        raise ValueError(f"{name}: expected an integer, got {value!r}")
    v = int(value)
    if v < minimum or (maximum is not None and v > maximum):
        rng = f">= {minimum}" if maximum is None else f"in {minimum}..{maximum}"
        raise ValueError(f"{name}: expected an integer {rng}, got {v}")
    return v


#: SPEC "Numbers": the range of finite coordinate magnitudes the tests compute without overflow.
COORDINATE_MAX = 1e18
COORDINATE_MIN = 1e-18


def _as_points_array(name: str, data: ArrayLike) -> NDArray[Any]:
    """Convert to an array and check that its dtype is integer or floating and its finite
    coordinates are in the SPEC range."""
    arr = np.asarray(data)
    if arr.dtype.kind not in "iuf":
        raise ValueError(
            f"{name}: expected a numeric (integer or floating) array, got dtype {arr.dtype}"
        )
    mags = np.abs(arr[np.isfinite(arr)].astype(np.float64))
    top = float(mags.max()) if mags.size else 0.0
    if top > COORDINATE_MAX or 0.0 < top < COORDINATE_MIN:
        raise ValueError(
            f"{name}: finite coordinates reach a magnitude of {top:.3g}, outside the range the "
            f"method computes without overflow (at most {COORDINATE_MAX:g}, largest at least "
            f"{COORDINATE_MIN:g}); rescale the points"
        )
    return arr


# --------------------------------------------------------------------------------------------
# Small float helpers
# --------------------------------------------------------------------------------------------


def _dot3(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Dot product over the last axis (length 3), summed left to right."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


_ORIENT_TOL = 1e-6  # a unit-normal component this small is a rounding residue when orienting


def _orient(normals: NDArray[np.float64]) -> NDArray[np.float64]:
    """Orient unit normals ``(..., 3)``: ``n_z > 0``, or if ``|n_z| <= 1e-6`` the first
    component larger than that in magnitude positive (SPEC "Plane fit")."""
    nx, ny, nz = normals[..., 0], normals[..., 1], normals[..., 2]
    lead = np.where(np.abs(nz) > _ORIENT_TOL, nz, np.where(np.abs(nx) > _ORIENT_TOL, nx, ny))
    sign = np.where(lead < 0, -1.0, 1.0)
    return normals * sign[..., None] + 0.0  # + 0.0 turns -0.0 into 0.0


# --------------------------------------------------------------------------------------------
# Plane fit (METHOD section 1, SPEC "Plane fit")
# --------------------------------------------------------------------------------------------


def _eigen_plane(pts: NDArray[np.float64]) -> RefPlane | None:
    """Eigenvalue fit of finite points ``(N, 3)``; None when impossible."""
    n = pts.shape[0]
    if n < 3:
        return None
    c = pts.mean(axis=0)
    d = pts - c
    scatter = d.T @ d
    evals, evecs = np.linalg.eigh(scatter)
    l0, l1, l2 = (float(x) for x in evals)
    if not (l2 > 0.0) or l1 <= _EIGEN_RANK_TOL * l2:
        return None
    normal = _orient(evecs[:, 0].copy())
    return _make_plane(normal, c, math.sqrt(max(l0, 0.0) / n), n)


def _lstsq_plane(pts: NDArray[np.float64]) -> RefPlane | None:
    """Least-squares fit ``z = a x + b y + e`` of finite points ``(N, 3)``; None if singular."""
    n = pts.shape[0]
    if n < 3:
        return None
    c = pts.mean(axis=0)
    d = pts - c
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    sxx = float(dx @ dx)
    syy = float(dy @ dy)
    sxy = float(dx @ dy)
    sxz = float(dx @ dz)
    syz = float(dy @ dz)
    prod = sxx * syy
    det = prod - sxy * sxy
    if prod == 0.0 or det <= _LSTSQ_DET_TOL * prod:
        return None
    a = (sxz * syy - syz * sxy) / det
    b = (syz * sxx - sxz * sxy) / det
    normal = np.array([-a, -b, 1.0])
    normal /= math.sqrt(float(normal @ normal))
    dist = _dot3(d, normal)
    rms = math.sqrt(float(np.mean(dist * dist)))
    return _make_plane(normal, c, rms, n)


def _make_plane(
    normal: NDArray[np.float64], centroid: NDArray[np.float64], rms: float, n: int
) -> RefPlane:
    normal = np.array(normal, dtype=np.float64)
    centroid = np.array(centroid, dtype=np.float64)
    normal.setflags(write=False)
    centroid.setflags(write=False)
    d = -float(_dot3(normal, centroid))
    return RefPlane(normal=normal, d=d, centroid=centroid, rms=float(rms), n_points=int(n))


def fit_plane(points: ArrayLike, method: str = "eigen") -> RefPlane:
    """Fit a plane to points (reference implementation).

    Parameters
    ----------
    points : array_like, shape (..., 3), integer or floating
        Points in the caller's length unit. Rows with any non-finite coordinate are ignored.
    method : {"eigen", "lstsq"}
        ``"eigen"``: smallest-eigenvalue eigenvector of the centred scatter matrix (paper
        eq. 4-17), ``rms = sqrt(max(l0, 0) / N)``. ``"lstsq"``: the paper's least-squares
        baseline ``z = a x + b y + e``, reported as a unit-normal plane with the RMS orthogonal
        distance.

    Returns
    -------
    RefPlane
        The oriented plane (``n_z > 0``, or first non-zero component positive).

    Raises
    ------
    ValueError
        Non-numeric dtype, last dimension not 3, unknown ``method``, fewer than 3 finite points,
        or degenerate points (eigen: ``l2 <= 0`` or ``l1 <= 1e-12 * l2``; lstsq: singular 2x2
        normal equations).
    """
    if method not in ("eigen", "lstsq"):
        raise ValueError(f"method: expected 'eigen' or 'lstsq', got {method!r}")
    arr = _as_points_array("points", points)
    if arr.ndim < 1 or arr.shape[-1] != 3:
        raise ValueError(f"points: expected shape (..., 3), got {arr.shape}")
    pts = arr.reshape(-1, 3).astype(np.float64)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if pts.shape[0] < 3:
        raise ValueError(f"points: need at least 3 finite points, got {pts.shape[0]}")
    plane = _eigen_plane(pts) if method == "eigen" else _lstsq_plane(pts)
    if plane is None:
        raise ValueError(
            f"points: degenerate configuration (all equal or collinear) for method {method!r}"
        )
    return plane


# --------------------------------------------------------------------------------------------
# Scan lines (METHOD section 2, SPEC "Scan-line angles")
# --------------------------------------------------------------------------------------------


def _line_array(line: ArrayLike, step: Any) -> tuple[NDArray[np.float64], int]:
    arr = _as_points_array("line", line)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"line: expected shape (N, 3), got {arr.shape}")
    s = _check_int("step", step, 1)
    return arr.astype(np.float64), s


def _line_angles(p: NDArray[np.float64], step: int) -> NDArray[np.float64]:
    n = p.shape[0]
    out = np.full(n, np.nan)
    if n < 2 * step + 1:
        return out
    mid = p[step : n - step]
    u = p[0 : n - 2 * step] - mid
    v = p[2 * step : n] - mid
    with np.errstate(invalid="ignore", over="ignore"):
        uu = _dot3(u, u)
        vv = _dot3(v, v)
        uv = _dot3(u, v)
        ok = (
            np.all(np.isfinite(p[0 : n - 2 * step]), axis=1)
            & np.all(np.isfinite(mid), axis=1)
            & np.all(np.isfinite(p[2 * step : n]), axis=1)
            & (uu != 0.0)
            & (vv != 0.0)
        )
        cos = np.clip(uv[ok] / np.sqrt(uu[ok] * vv[ok]), -1.0, 1.0)
    ang = np.full(mid.shape[0], np.nan)
    ang[ok] = np.degrees(np.arccos(cos))
    out[step : n - step] = ang
    return out


def scan_line_angles(line: ArrayLike, step: int = 1) -> NDArray[np.float64]:
    """Interior angle at each point of a scan line (paper eq. 18-19, reference).

    Parameters
    ----------
    line : array_like, shape (N, 3), integer or floating
        Consecutive points of one profile (caller's length unit).
    step : int, optional
        Neighbour offset ``>= 1``: ``A = P[i - step]``, ``B = P[i + step]``.

    Returns
    -------
    ndarray, shape (N,), float64
        ``degrees(arccos(clip(u.v / sqrt((u.u)(v.v)), -1, 1)))`` with ``u = A - P``,
        ``v = B - P``, in [0, 180]; 180 on a straight run. NaN at the ends, where any of the
        three points is non-finite, or where ``u`` or ``v`` has zero length.
    """
    p, s = _line_array(line, step)
    return _line_angles(p, s)


def scan_line_heights(line: ArrayLike, step: int = 1) -> NDArray[np.float64]:
    """Height of each point over the line through its predecessors (paper eq. 20, reference).

    Parameters
    ----------
    line : array_like, shape (N, 3), integer or floating
        Consecutive points of one profile (caller's length unit).
    step : int, optional
        Neighbour offset ``>= 1``.

    Returns
    -------
    ndarray, shape (N,), float64
        ``D_i = sin(theta_{i-step}) * |P_i - P_{i-step}|`` (caller's length unit, >= 0) with
        ``theta`` from :func:`scan_line_angles`; NaN where that angle is NaN (in particular for
        ``i < 2 * step``), where ``i - step`` is outside the line, or where ``P_i`` is
        non-finite.
    """
    p, s = _line_array(line, step)
    n = p.shape[0]
    theta = _line_angles(p, s)
    out = np.full(n, np.nan)
    if n <= s:
        return out
    prev_theta = theta[0 : n - s]  # theta_{i - step} for i = step .. n - 1
    diff = p[s:n] - p[0 : n - s]
    with np.errstate(invalid="ignore", over="ignore"):
        length = np.sqrt(_dot3(diff, diff))
    ok = np.isfinite(prev_theta) & np.all(np.isfinite(p[s:n]), axis=1)
    vals = np.full(n - s, np.nan)
    vals[ok] = np.sin(np.radians(prev_theta[ok])) * length[ok]
    out[s:n] = vals
    return out


# --------------------------------------------------------------------------------------------
# Organized detection (METHOD sections 3-7, SPEC "Organized detection")
# --------------------------------------------------------------------------------------------


def _shifted(a: NDArray[Any], oy: int, ox: int, fill: Any) -> NDArray[Any]:
    """``out[r, c] = a[r + oy, c + ox]`` where that is inside the grid, else ``fill``."""
    h, w = a.shape[:2]
    out = np.full_like(a, fill)
    if abs(oy) >= h or abs(ox) >= w:
        return out
    out[max(0, -oy) : min(h, h - oy), max(0, -ox) : min(w, w - ox)] = a[
        max(0, oy) : min(h, h + oy), max(0, ox) : min(w, w + ox)
    ]
    return out


def _neighbour(
    grid: NDArray[np.float64],
    usable: NDArray[np.bool_],
    direction: tuple[int, int],
    scale: int,
    side: int,
    max_gap: int,
    min_step: float | None,
    max_reach: int,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """The neighbour of every cell at ``scale`` on ``side`` of ``direction`` (SPEC pseudo-code).

    Returns the neighbour points ``(H, W, 3)`` (NaN where none) and the found mask ``(H, W)``.
    """
    h, w = usable.shape
    dr, dc = direction
    found = np.zeros((h, w), dtype=bool)
    done = np.zeros((h, w), dtype=bool)
    gaps = np.zeros((h, w), dtype=np.int64)
    nb = np.full((h, w, 3), np.nan)
    inside_all = np.ones((h, w), dtype=bool)
    k_last = scale + max_gap + (max_reach if min_step is not None else 0)
    for k in range(scale, k_last + 1):
        oy, ox = side * k * dr, side * k * dc
        inside = _shifted(inside_all, oy, ox, False)
        use_k = _shifted(usable, oy, ox, False)
        q = _shifted(grid, oy, ox, np.nan)
        active = ~done
        # Outside the grid: none.
        done |= active & ~inside
        active &= inside
        # Not usable: a gap; too many gaps: none.
        gap_now = active & ~use_k
        gaps[gap_now] += 1
        done |= gap_now & (gaps > max_gap)
        cand = active & use_k
        if min_step is not None:
            diff = q - grid
            dist = np.sqrt(_dot3(diff, diff))
            cand &= dist >= scale * min_step
        found |= cand
        nb[cand] = q[cand]
        done |= cand
        if done.all():
            break
    return nb, found


def _isolated(usable: NDArray[np.bool_], max_gap: int) -> NDArray[np.bool_]:
    """Cells with no usable cell at ``k = 1 .. 1 + max_gap`` steps along any of 8 rays."""
    any_usable = np.zeros(usable.shape, dtype=bool)
    for dr, dc in DIRECTIONS:
        for g in (-1, 1):
            for k in range(1, max_gap + 2):
                any_usable |= _shifted(usable, g * k * dr, g * k * dc, False)
    return ~any_usable


def _judge_pass(
    grid: NDArray[np.float64],
    usable: NDArray[np.bool_],
    cos0: float,
    scales: Sequence[int],
    max_gap: int,
    min_step: float | None,
    max_reach: int,
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.uint8], NDArray[np.float64]]:
    """Available / flagged direction counts, flag bitmask and smallest angle for every cell."""
    h, w = usable.shape
    n_avail = np.zeros((h, w), dtype=np.int64)
    n_flag = np.zeros((h, w), dtype=np.int64)
    flags = np.zeros((h, w), dtype=np.uint8)
    angle = np.full((h, w), np.nan)
    for k_dir, direction in enumerate(DIRECTIONS):
        dir_avail = np.zeros((h, w), dtype=bool)
        dir_flag = np.zeros((h, w), dtype=bool)
        for s in scales:
            a_pts, a_ok = _neighbour(grid, usable, direction, s, -1, max_gap, min_step, max_reach)
            b_pts, b_ok = _neighbour(grid, usable, direction, s, +1, max_gap, min_step, max_reach)
            u = a_pts - grid
            v = b_pts - grid
            uu = _dot3(u, u)
            vv = _dot3(v, v)
            uv = _dot3(u, v)
            avail = a_ok & b_ok & (uu != 0.0) & (vv != 0.0)
            cos = np.full((h, w), np.nan)
            cos[avail] = np.clip(uv[avail] / np.sqrt(uu[avail] * vv[avail]), -1.0, 1.0)
            flagged = avail & (cos >= cos0)
            ang = np.full((h, w), np.nan)
            ang[avail] = np.degrees(np.arccos(cos[avail]))
            angle = np.fmin(angle, ang)
            dir_avail |= avail
            dir_flag |= flagged
        n_avail += dir_avail
        n_flag += dir_flag
        flags |= np.where(dir_flag, np.uint8(1 << k_dir), np.uint8(0)).astype(np.uint8)
    return n_avail, n_flag, flags, angle


def _window_fits(
    grid: NDArray[np.float64],
    normal_mask: NDArray[np.bool_],
    finite: NDArray[np.bool_],
    window: int,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Window plane of the NORMAL cells around every finite cell.

    Returns the height ``(H, W)`` and the oriented window normal ``(H, W, 3)`` (NaN where the fit
    is impossible or the cell is non-finite). Each window is fitted on its own centred data.
    """
    height, normals, _, _ = _window_planes(grid, normal_mask, finite, window)
    return height, normals


def _window_planes(
    grid: NDArray[np.float64],
    normal_mask: NDArray[np.bool_],
    cells: NDArray[np.bool_],
    window: int,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """Window plane of the NORMAL cells around every cell of ``cells`` (finite cells only).

    Returns the height ``(H, W)``, the oriented window normal ``(H, W, 3)``, the eigenvalues
    ``l0 <= l1 <= l2`` of the window's centred scatter ``(H, W, 3)`` (all three NaN where the fit
    is impossible or the cell is not in ``cells``) and the number of NORMAL cells in the window
    ``(H, W)`` (0 outside ``cells``).
    """
    h, w = cells.shape
    half = window // 2
    ww = window * window
    xp = np.zeros((h + 2 * half, w + 2 * half, 3))
    xp[half : half + h, half : half + w] = np.where(normal_mask[..., None], grid, 0.0)
    mp = np.zeros((h + 2 * half, w + 2 * half), dtype=bool)
    mp[half : half + h, half : half + w] = normal_mask
    # (H, W, 3, window, window) and (H, W, window, window) read-only views.
    xw = np.lib.stride_tricks.sliding_window_view(xp, (window, window), axis=(0, 1))
    mw = np.lib.stride_tricks.sliding_window_view(mp, (window, window), axis=(0, 1))

    height = np.full((h, w), np.nan)
    normals = np.full((h, w, 3), np.nan)
    eigvals = np.full((h, w, 3), np.nan)
    count = np.zeros((h, w), dtype=np.int64)
    rows_per_chunk = max(1, _WINDOW_CHUNK_ENTRIES // max(1, w * ww))
    for r0 in range(0, h, rows_per_chunk):
        r1 = min(h, r0 + rows_per_chunk)
        rr, cc = np.nonzero(cells[r0:r1])
        if rr.size == 0:
            continue
        x = xw[r0:r1][rr, cc].reshape(rr.size, 3, ww)
        m = mw[r0:r1][rr, cc].reshape(rr.size, ww)
        cnt = m.sum(axis=1)
        count[rr + r0, cc] = cnt
        fit = cnt >= 3
        if not fit.any():
            continue
        x, m, cnt = x[fit], m[fit], cnt[fit]
        rr, cc = rr[fit] + r0, cc[fit]
        centroid = x.sum(axis=2) / cnt[:, None]
        dev = np.where(m[:, None, :], x - centroid[:, :, None], 0.0)
        scatter = dev @ dev.transpose(0, 2, 1)
        evals, evecs = np.linalg.eigh(scatter)
        l1, l2 = evals[:, 1], evals[:, 2]
        # a plane (SPEC "Plane fit") with a unique normal (SPEC "Height")
        good = (l2 > 0.0) & ~(l1 <= _EIGEN_RANK_TOL * l2) & (l1 - evals[:, 0] > _WINDOW_UNIQUE * l2)
        if not good.any():
            continue
        nrm = _orient(evecs[good, :, 0])
        c_good = centroid[good]
        d = -_dot3(nrm, c_good)
        p = grid[rr[good], cc[good]]
        height[rr[good], cc[good]] = _dot3(p, nrm) + d
        normals[rr[good], cc[good]] = nrm
        eigvals[rr[good], cc[good]] = evals[good]
    return height, normals, eigvals, count


def _components(mask: NDArray[np.bool_]) -> list[NDArray[np.int64]]:
    """8-connected components of ``mask``, each as ascending flat indices (BFS)."""
    h, w = mask.shape
    flat = mask.ravel()
    seen = np.zeros(h * w, dtype=bool)
    comps: list[NDArray[np.int64]] = []
    for start in np.flatnonzero(flat):
        start = int(start)
        if seen[start]:
            continue
        seen[start] = True
        stack = [start]
        members = []
        while stack:
            i = stack.pop()
            members.append(i)
            r, c = divmod(i, w)
            for dr in (-1, 0, 1):
                for dc in (-1, 0, 1):
                    if dr == 0 and dc == 0:
                        continue
                    r2, c2 = r + dr, c + dc
                    if 0 <= r2 < h and 0 <= c2 < w:
                        j = r2 * w + c2
                        if flat[j] and not seen[j]:
                            seen[j] = True
                            stack.append(j)
        comps.append(np.array(sorted(members), dtype=np.int64))
    return comps


def _summarize(
    idx: NDArray[np.int64],
    members: NDArray[np.float64],
    hs: NDArray[np.float64],
    where: NDArray[np.int64],
    height: NDArray[np.float64],
    normals: NDArray[np.float64],
    touches: bool,
) -> tuple[Any, ...]:
    """One defect's fields (SPEC "Defects"): ``idx`` output indices, ``members`` the points,
    ``hs`` their heights, ``where`` their positions in ``height`` / ``normals``, ``touches``
    whether a finite non-ABNORMAL point is adjacent."""
    centroid = members.mean(axis=0)
    fin = np.isfinite(hs)
    if fin.any():
        pos = int(np.argmax(np.abs(hs[fin])))  # first in index order on ties
        peak_at = int(where[fin][pos])
        peak = float(height[peak_at])
        mean_h = float(np.mean(hs[fin]))
        normal = normals[peak_at].copy()
    else:
        peak = math.nan
        mean_h = math.nan
        normal = np.full(3, np.nan)
    off = members - centroid
    if np.all(np.isfinite(normal)):
        off = off - _dot3(off, normal)[:, None] * normal
    extent = 2.0 * float(np.max(np.sqrt(_dot3(off, off))))
    if not touches or math.isnan(peak):
        kind = "isolated"
    elif peak < 0:
        kind = "pit"
    else:
        kind = "protrusion"
    return (idx, centroid, normal, peak, mean_h, extent, kind)


def _ordered_defects(raw: list[tuple[Any, ...]]) -> list[RefDefect]:
    """Defects by |peak| descending (NaN last, ties by first index), numbered in that order."""

    def order(item: tuple[Any, ...]) -> tuple[bool, float, int]:
        peak_ = item[3]
        nan = math.isnan(peak_)
        return (nan, 0.0 if nan else -abs(peak_), int(item[0][0]))

    out = []
    for i, (idx, centroid, normal, peak, mean_h, extent, kind) in enumerate(
        sorted(raw, key=order)
    ):
        idx.setflags(write=False)
        centroid.setflags(write=False)
        normal.setflags(write=False)
        out.append(
            RefDefect(
                id=i,
                indices=idx,
                count=int(idx.size),
                centroid=centroid,
                normal=normal,
                peak_height=peak,
                mean_height=mean_h,
                extent=extent,
                kind=kind,
            )
        )
    return out


def _defects(
    grid: NDArray[np.float64],
    labels: NDArray[np.uint8],
    height: NDArray[np.float64],
    normals: NDArray[np.float64],
    finite: NDArray[np.bool_],
) -> list[RefDefect]:
    abnormal = labels == ABNORMAL
    # Cells with a finite non-ABNORMAL cell among their 8 neighbours.
    keep = finite & ~abnormal
    touches = np.zeros(labels.shape, dtype=bool)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr or dc:
                touches |= _shifted(keep, dr, dc, False)

    pts = grid.reshape(-1, 3)
    h_flat = height.ravel()
    n_flat = normals.reshape(-1, 3)
    t_flat = touches.ravel()
    raw = [
        _summarize(idx, pts[idx], h_flat[idx], idx, h_flat, n_flat, bool(t_flat[idx].any()))
        for idx in _components(abnormal)
    ]
    return _ordered_defects(raw)


class _Unset:
    """Type of :data:`_UNSET`: "not given by the caller" (the preset or default applies)."""

    def __repr__(self) -> str:
        return "<unset>"


#: Default of the :func:`detect` parameters that a preset may set.
_UNSET: Any = _Unset()

#: Values used when neither the caller nor the preset gives a parameter.
_DEFAULTS: dict[str, Any] = {
    "theta0": 75.0,
    "scales": (1,),
    "max_gap": 1,
    "min_step": None,
    "min_directions": None,
    "max_iterations": 10,
    "window": 21,
    "max_reach": 32,
    "height_tolerance": None,
    "edge_extent": 0,
    "edge_tolerance": None,
    "edge_window": 15,
    "z_resolution": None,
    "z_noise": None,
}

#: Presets of :func:`detect` (SPEC "Presets"): name -> parameter values. Explicit keyword
#: arguments override them; parameters a preset does not list take their default.
_PRESETS: dict[str, dict[str, Any]] = {
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
        "edge_tolerance": None,
        "edge_window": 15,
        "z_resolution": None,
        "z_noise": None,
    },
    "recommended": {
        "theta0": 90.0,
        "scales": (1, 2),
        "max_gap": 1,
        "min_step": "auto",
        "min_directions": None,
        "max_iterations": 10,
        "window": 21,
        "height_tolerance": "4.5rms",
        "edge_extent": 12,
        "edge_tolerance": 4.0,
        "edge_window": 15,
        "z_resolution": "auto",
        "z_noise": "auto",
    },
}

# theta0="auto" (SPEC "Beyond the paper"): theta0 = clip(180 - K * median(dev) / MAD, MIN, MAX).
_AUTO_K = 6.0
_AUTO_MIN = 75.0
_AUTO_MAX = 170.0
_AUTO_MAD = 0.6745
_AUTO_STRAIGHT = 1e-3  # degrees: a smaller 180 - angle is a straight triple's round-off, read as 0
# Height test, rms form: |h| must also exceed this times sqrt((l1 + l2) / n) (round-off floor):
# clouds 1e-9; grids 1e-6, above the resolution of a window's l0 (the window sums' round-off),
# so that on a noise-free surface (float32 quantisation only) the verdict is not decided by
# rounding, which differs between window sums formed in another order (ProfileStream, tiles).
_HEIGHT_RMS_FLOOR = 1e-9
_GRID_HEIGHT_RMS_FLOOR = 1e-6
# "<k>rms": k a plain decimal (digits, optional fraction, optional exponent), no sign or space.
_RMS_RE = re.compile(r"((?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?)rms")


#: The preset used when none is given (SPEC "Parameters"): the best measured one.
_DEFAULT_PRESET = "recommended"


def _resolve_preset(preset: Any, given: dict[str, Any]) -> dict[str, Any]:
    """Parameter values: the caller's where given, else the preset's (default: "recommended"),
    else the default."""
    if preset is None:
        table: dict[str, Any] = _PRESETS[_DEFAULT_PRESET]
    elif isinstance(preset, str) and preset in _PRESETS:
        table = _PRESETS[preset]
    else:
        names = ", ".join(repr(k) for k in _PRESETS)
        raise ValueError(f"preset: expected None or one of {names}, got {preset!r}")
    out = {}
    for name, value in given.items():
        if value is not _UNSET:
            out[name] = value
        elif name in table:
            out[name] = table[name]
        else:
            out[name] = _DEFAULTS[name]
    return out


def _parse_height_tolerance(value: Any) -> tuple[str, float] | None:
    """``None`` -> None; ``t > 0`` -> ("abs", t); ``"<k>rms"`` with ``k > 0`` -> ("rms", k)."""
    if value is None:
        return None
    if isinstance(value, str):
        match = _RMS_RE.fullmatch(value)
        if match is not None:
            k = float(match.group(1))
            if math.isfinite(k) and k > 0.0:
                return ("rms", k)
    elif _is_real(value) and math.isfinite(float(value)) and float(value) > 0.0:
        return ("abs", float(value))
    raise ValueError(
        "height_tolerance: expected None, a finite length > 0 or a string '<k>rms' with a "
        f"finite k > 0 (e.g. '4rms'), got {value!r}"
    )


def _auto_theta0(
    grid: NDArray[np.float64],
    finite: NDArray[np.bool_],
    scales: Sequence[int],
    max_gap: int,
    min_step: float | None,
    max_reach: int,
) -> float:
    """SPEC ``theta0="auto"``: from the pass-1 angles with every finite cell usable."""
    # The angle does not depend on the threshold; any cosine will do.
    _, _, _, angle = _judge_pass(grid, finite, 1.0, scales, max_gap, min_step, max_reach)
    angle = np.where(_isolated(finite, max_gap), np.nan, angle)  # as pass 1 records it
    a = angle[finite & np.isfinite(angle)]
    if a.size == 0:
        return _AUTO_MIN
    dev = 180.0 - a
    dev[dev < _AUTO_STRAIGHT] = 0.0
    sigma = float(np.median(dev)) / _AUTO_MAD
    return min(max(180.0 - _AUTO_K * sigma, _AUTO_MIN), _AUTO_MAX)


def _count_image(mask: NDArray[np.bool_]) -> NDArray[np.int64]:
    """The integral image of a mask, ``(h + 1, w + 1)``: ``s[a, b]`` counts the True cells of
    rows ``< a`` and columns ``< b``."""
    h, w = mask.shape
    s = np.zeros((h + 1, w + 1), dtype=np.int64)
    s[1:, 1:] = np.cumsum(np.cumsum(mask.astype(np.int64), axis=0), axis=1)
    return s


def _edge_n_min(r: int) -> int:
    """The least support of an edge sub-window of half-size ``r`` (SPEC "Edge test" step 3):
    fewer valid cells make it empty, as many missing ones keep a cell from being quiet."""
    return max(3, (r * r) // 2)


def _box_count(mask: NDArray[np.bool_], window: int) -> NDArray[np.int64]:
    """Number of True cells in the ``window x window`` square around each cell (clipped)."""
    h, w = mask.shape
    half = window // 2
    s = _count_image(mask)
    r0 = np.clip(np.arange(h) - half, 0, h)
    r1 = np.clip(np.arange(h) + half + 1, 0, h)
    c0 = np.clip(np.arange(w) - half, 0, w)
    c1 = np.clip(np.arange(w) + half + 1, 0, w)
    return (s[r1][:, c1] - s[r0][:, c1] - s[r1][:, c0] + s[r0][:, c0]).astype(np.int64)


def _half_counts(mask: NDArray[np.bool_], r: int) -> NDArray[np.int64]:
    """The largest number of True cells in one of the four half sub-windows around each cell
    (SPEC "Edge test" step 2: rows ``-r..r`` and columns ``-r..-1`` or ``1..r``, columns
    ``-r..r`` and rows ``-r..-1`` or ``1..r``; clipped)."""
    h, w = mask.shape
    s = _count_image(mask)
    rows, cols = np.arange(h)[:, None], np.arange(w)[None, :]

    def rect(a0: Any, a1: Any, b0: Any, b1: Any) -> NDArray[np.int64]:
        a0, a1 = np.clip(a0, 0, h), np.clip(a1, 0, h)  # rows [a0, a1), columns [b0, b1)
        b0, b1 = np.clip(b0, 0, w), np.clip(b1, 0, w)
        return s[a1, b1] - s[a0, b1] - s[a1, b0] + s[a0, b0]

    left = rect(rows - r, rows + r + 1, cols - r, cols)
    right = rect(rows - r, rows + r + 1, cols + 1, cols + r + 1)
    up = rect(rows - r, rows, cols - r, cols + r + 1)
    down = rect(rows + 1, rows + r + 1, cols - r, cols + r + 1)
    return np.maximum(np.maximum(left, right), np.maximum(up, down))


def _compact_edges(
    edge: NDArray[np.bool_], extent: int, invalid: NDArray[np.bool_] | None = None, gap: int = 0
) -> NDArray[np.bool_]:
    """EDGE cells of EDGE groups whose bounding box's longer side is <= extent.

    Two EDGE cells are linked when they are 8-neighbours, or ``k`` cells apart along one of the
    8 directions (``2 <= k <= 1 + gap``) with every cell between them ``invalid`` (the caller's
    bridge cells: dropouts and the angle passes' ABNORMAL cells, which do not cut a feature
    line; SPEC "height_tolerance" step 1).
    """
    h, w = edge.shape
    out = np.zeros_like(edge)
    seen = np.zeros_like(edge)
    reach = 1 + (gap if invalid is not None else 0)
    offsets = [(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if (dr, dc) != (0, 0)]
    for r0, c0 in zip(*np.nonzero(edge)):
        if seen[r0, c0]:
            continue
        stack, members = [(r0, c0)], []
        seen[r0, c0] = True
        while stack:
            r, c = stack.pop()
            members.append((r, c))
            for dr, dc in offsets:
                for k in range(1, reach + 1):
                    rr, cc = r + k * dr, c + k * dc
                    if not (0 <= rr < h and 0 <= cc < w):
                        break
                    if edge[rr, cc]:
                        if not seen[rr, cc]:
                            seen[rr, cc] = True
                            stack.append((rr, cc))
                        break
                    if invalid is None or not invalid[rr, cc]:
                        break
        rows = [m[0] for m in members]
        cols = [m[1] for m in members]
        if max(max(rows) - min(rows), max(cols) - min(cols)) + 1 <= extent:
            for m in members:
                out[m] = True
    return out


def _height_pass(
    grid: NDArray[np.float64],
    normal_mask: NDArray[np.bool_],
    compact_mask: NDArray[np.bool_],
    line_mask: NDArray[np.bool_],
    window: int,
    tolerance: tuple[str, float],
    z_floor: float = 0.0,
) -> NDArray[np.bool_]:
    """One height pass (SPEC "height_tolerance"): the NORMAL and compact-EDGE cells that become
    ABNORMAL. With an absolute tolerance a cell with a feature-line EDGE cell in its window is
    not tested (in the rms form the bend the window straddles raises the rms). In the rms form
    ``|h|`` must also exceed ``z_floor`` (1.5 x the z resolution, SPEC "z_resolution")."""
    height, _, evals, count = _window_planes(grid, normal_mask, normal_mask | compact_mask,
                                             window)
    exists = (normal_mask | compact_mask) & np.isfinite(height)
    mode, value = tolerance
    if mode == "abs":
        exists &= _box_count(line_mask, window) == 0
    absh = np.abs(height)
    if mode == "abs":
        return exists & (absh > value)
    n = np.maximum(count, 1).astype(np.float64)
    rms = np.sqrt(np.maximum(evals[..., 0], 0.0) / n)
    floor = _GRID_HEIGHT_RMS_FLOOR * np.sqrt((evals[..., 1] + evals[..., 2]) / n)
    return exists & (absh > value * rms) & (absh > floor) & (absh > z_floor)


# --------------------------------------------------------------------------------------------
# Edge-aware test (SPEC "Edge test"): one-sided sub-windows at feature lines and outlines
# --------------------------------------------------------------------------------------------

def _edge_sides(r: int) -> tuple[tuple[int, int, int, int], ...]:
    """The 8 one-sided sub-windows of half-size ``r``: inclusive offsets
    ``(row_lo, row_hi, col_lo, col_hi)`` from the cell; the cell's own row or column is never in
    them. Halves left, right, up, down; quadrants up-left, up-right, down-left, down-right."""
    return (
        (-r, r, -r, -1), (-r, r, 1, r), (-r, -1, -r, r), (1, r, -r, r),
        (-r, -1, -r, -1), (-r, -1, 1, r), (1, r, -r, -1), (1, r, 1, r),
    )


#: A sub-window is *clean* when its rms is at most this times the smallest rms of the cell's
#: sub-windows (a sub-window straddling a feature line has a far larger rms).
_EDGE_CLEAN_RATIO = 2.0
#: Edge test sides and sectors (SPEC "Edge test" and "Unorganized clouds: edge test", step 3):
#: a smallest eigenvalue at most this times the largest is round-off (an exactly flat support:
#: a noise-free plane, 3 points), its rms 0.
_FLAT_L0 = 1e-12
#: A sub-window's support is on a line in (x, y) when the determinant of its (x, y) scatter is
#: at most this times its trace squared (SPEC "Edge test" step 3).
_EDGE_LINE_TOL = 1e-6
#: A valid sub-window whose plane is steeper than 70 degrees (oriented normal ``u_z`` below
#: this) is *steep* (SPEC "Edge test" step 4): never clean, so P is not tested against it (a scan
#: from above does not resolve such a surface: the plane fits a sub-window narrow across a
#: step, both levels at once); as an opposite side its centroid still counts.
_EDGE_STEEP_COS = 0.3420201433256687  # cos(70 degrees)
#: Opposite sub-windows (indices into :func:`_edge_sides`).
_EDGE_OPPOSITE = ((0, 1), (2, 3), (4, 7), (5, 6))
#: The sub-windows on the same side of the cell as each one (SPEC "Edge test" step 5,
#: outlines): a half and its two quadrants; a quadrant alone.
_EDGE_SAME_SIDE = ((0, 4, 6), (1, 5, 7), (2, 4, 5), (3, 6, 7), (4,), (5,), (6,), (7,))
#: Each sub-window's opposite.
_EDGE_OPPOSITE_OF = tuple(a + b - k for k in range(8) for a, b in _EDGE_OPPOSITE if k in (a, b))
#: Outlines (step 5): the opposite sub-window is an *outline* when at least this share of the
#: cells of its full (unclipped) extent has no return ...
_OUTLINE_EMPTY = 0.9
#: ... and P stands above the clean sub-window by more than this times its tolerance.
_OUTLINE_HEIGHT = 1.5


def _edge_rms(evals: NDArray[np.float64], n: NDArray[np.float64]) -> NDArray[np.float64]:
    """A side's or sector's rms from its eigenvalues ``(..., 3)`` and point count: 0 where
    ``l0 <= _FLAT_L0 l2`` (round-off: an exactly flat support)."""
    l0 = evals[..., 0]
    return np.sqrt(np.where(l0 > _FLAT_L0 * evals[..., 2], l0, 0.0) / n)


def _moment_images(
    grid: NDArray[np.float64],
    support: NDArray[np.bool_],
    invalid: NDArray[np.bool_],
    origin: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Integral images ``(H + 1, W + 1, 11)`` of the edge test's moments (SPEC "Edge test" step
    3): n, x, y, z, xx, xy, xz, yy, yz, zz of the ``support`` cells relative to ``origin``,
    and the ``invalid`` count; a rectangle's sums are ``s[r1, c1] - s[r0, c1] - s[r1, c0] +
    s[r0, c0]``."""
    hh, ww = support.shape
    p = np.where(support[..., None], grid - origin, 0.0)
    terms = _moment_terms(p)
    terms[..., 0] = support
    terms = np.concatenate([terms, invalid[..., None]], axis=-1)
    s = np.zeros((hh + 1, ww + 1, 11))
    s[1:, 1:] = np.cumsum(np.cumsum(terms, axis=0), axis=1)
    return s


def _moment_terms(p: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per point ``(..., 3)``: 1, x, y, z, xx, xy, xz, yy, yz, zz (the edge test's moments)."""
    terms = [np.ones(p.shape[:-1])] + [p[..., a] for a in range(3)]
    terms += [p[..., a] * p[..., b] for a in range(3) for b in range(a, 3)]
    return np.stack(terms, axis=-1)


def _scatter(m: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
    """From moment sums ``(N, >= 10)`` (n, x, y, z, xx, xy, xz, yy, yz, zz): ``max(n, 1)``, the
    centroid and the centred scatter ``(N, 3, 3)``."""
    nn = np.maximum(m[:, 0], 1.0)
    cen = m[:, 1:4] / nn[:, None]
    cov = np.empty((m.shape[0], 3, 3))
    idx = 4
    for a in range(3):
        for b in range(a, 3):
            cov[:, a, b] = cov[:, b, a] = m[:, idx] - nn * cen[:, a] * cen[:, b]
            idx += 1
    return nn, cen, cov


def _quiet_cells(
    grid: NDArray[np.float64],
    labels: NDArray[np.uint8],
    r: int,
    window: int,
    floor: float,
    removed: NDArray[np.bool_],
) -> NDArray[np.bool_]:
    """SPEC "Edge test" step 1: the quiet cells, which pass 1 leaves out, on the labels at the
    start of the edge test (``window``: the height test's; ``removed``: the cells its last pass
    made ABNORMAL when no pass re-fitted the windows around them). A NORMAL cell is quiet when
    every cell of the grid within ``r`` rows and columns is NORMAL, INVALID or ABNORMAL (no
    EDGE), each of its four half sub-windows (step 2, clipped at the grid border) holds fewer
    than ``n_min`` INVALID or ABNORMAL cells (no sub-window of step 3 is empty: a quadrant lies
    within a half), no ``removed`` cell lies within ``window // 2``, and its height-window
    plane (the NORMAL cells of its window, itself included, as the height test fits them on the
    labels after its passes) is smooth, ``rms = sqrt(max(l0, 0) / n) <= _EDGE_QUIET_ROUGH *
    floor`` or flat to round-off (``l0 <= _FLAT_L0 * l2``, step 3's rms of 0: a noise-free
    plane, whose ``floor`` is often 0), with the cell within ``_EDGE_QUIET_H * rms`` of it, or
    within the height test's round-off floor ``1e-6 sqrt((l1 + l2) / n)``."""
    normal = labels == NORMAL
    side = 2 * r + 1
    cand = normal & (_box_count(labels == EDGE, side) == 0)
    cand &= _half_counts((labels == INVALID) | (labels == ABNORMAL), r) < _edge_n_min(r)
    cand &= _box_count(removed, 2 * (window // 2) + 1) == 0
    height, _, evals, count = _window_planes(grid, normal, cand, window)
    n = count.astype(np.float64)
    l0 = np.maximum(evals[..., 0], 0.0)
    h2n = height * height * n
    with np.errstate(invalid="ignore"):
        near = (h2n <= _EDGE_QUIET_H ** 2 * l0) | (h2n <= 1e-12 * (evals[..., 1] + evals[..., 2]))
        smooth = (l0 <= (_EDGE_QUIET_ROUGH * floor) ** 2 * n) | \
            (evals[..., 0] <= _FLAT_L0 * evals[..., 2])
        return cand & np.isfinite(height) & smooth & near


def _side_sums(s: NDArray[np.float64], rr: NDArray[np.intp], cc: NDArray[np.intp], r: int,
               k: int) -> NDArray[np.float64]:
    """The moments (``_moment_images`` channels) of sub-window ``k`` of each cell
    ``(rr, cc)``, clipped at the grid border: one rectangle sum of the integral images ``s``."""
    hh, ww = s.shape[0] - 1, s.shape[1] - 1
    a0, a1, b0, b1 = _edge_sides(r)[k]
    r0, r1 = np.clip(rr + a0, 0, hh), np.clip(rr + a1 + 1, 0, hh)
    c0, c1 = np.clip(cc + b0, 0, ww), np.clip(cc + b1 + 1, 0, ww)
    return s[r1, c1] - s[r0, c1] - s[r1, c0] + s[r0, c0]


def _side_fits(
    grid: NDArray[np.float64],
    support: NDArray[np.bool_],
    invalid: NDArray[np.bool_],
    cells: NDArray[np.bool_],
    r: int,
    origin: NDArray[np.float64],
    images: Optional[NDArray[np.float64]] = None,
) -> tuple[NDArray[np.float64], ...]:
    """Height and rms of every cell of ``cells`` against the plane of the ``support`` cells of
    each of its 8 sub-windows (SPEC "Edge test"), from integral images of the moments
    (``images``: ``_moment_images`` of these arguments, when the caller has them).

    Returns ``h``, ``rms``, ``spread = sqrt((l1 + l2) / n)``, ``valid``, the normals, centroids,
    ``empty`` and the support's (x, y) covariance ``(Sxx, Syy, Sxy)``, of shape ``(8, N)``
    (``(8, N, 3)``) for the ``N`` cells of ``cells`` in row-major order.
    """
    s = _moment_images(grid, support, invalid, origin) if images is None else images
    rr, cc = np.nonzero(cells)
    pt = grid[rr, cc] - origin
    n_min = _edge_n_min(r)
    hs = np.full((8, rr.size), np.nan)
    rms = np.full((8, rr.size), np.nan)
    spread = np.full((8, rr.size), np.nan)
    valid = np.zeros((8, rr.size), dtype=bool)
    normals = np.full((8, rr.size, 3), np.nan)
    centroids = np.full((8, rr.size, 3), np.nan)
    empty = np.zeros((8, rr.size), dtype=bool)
    cov2 = np.zeros((8, rr.size, 3))
    for k in range(8):
        m = _side_sums(s, rr, cc, r, k)
        ok = m[:, 0] >= n_min
        nn, cen, cov = _scatter(m)
        cov2[k] = np.stack([cov[:, 0, 0] / nn, cov[:, 1, 1] / nn, cov[:, 0, 1] / nn], axis=-1)
        # support on a line in (x, y) (one row or column of cells): no plane (its normal would
        # be horizontal and its smallest eigenvalue round-off)
        a, b, d = cov[:, 0, 0], cov[:, 1, 1], cov[:, 0, 1]
        ok &= a * b - d * d > _EDGE_LINE_TOL * ((a + b) * (a + b))
        cov[~ok] = np.eye(3)
        evals, evecs = np.linalg.eigh(cov)
        ok &= (evals[:, 2] > 0.0) & ~(evals[:, 1] <= _EIGEN_RANK_TOL * evals[:, 2])
        nrm = _orient(evecs[:, :, 0])
        hs[k] = np.where(ok, _dot3(pt - cen, nrm), np.nan)
        rms[k] = np.where(ok, _edge_rms(evals, nn), np.nan)
        spread[k] = np.where(ok, np.sqrt((evals[:, 1] + evals[:, 2]) / nn), np.nan)
        valid[k] = ok
        normals[k] = nrm
        centroids[k] = cen
        empty[k] = m[:, 10] >= n_min
    return hs, rms, spread, valid, normals, centroids, empty, cov2


#: A smooth curved surface (SPEC "Edge test" step 4): each quadrant's rms^2 at least
#: _CURVED_BEND times the residual variance the quadratic surface leaves about its plane, and at
#: most _CURVED_FIT times it plus the floor^2; that variance's terms in A11^2 Sxx^2 and
#: A22^2 Syy^2 carry _CURVED_LATTICE (cells uniform along x and y).
_CURVED_BEND = 0.5
_CURVED_FIT = 1.25
_CURVED_LATTICE = 0.2


def _curved(
    h: NDArray[np.float64],
    rms: NDArray[np.float64],
    level: NDArray[np.bool_],
    nrm: NDArray[np.float64],
    cen: NDArray[np.float64],
    empty: NDArray[np.bool_],
    cov2: NDArray[np.float64],
    pt: NDArray[np.float64],
    k: float,
    floor: NDArray[np.float64],
) -> NDArray[np.bool_]:
    """SPEC "Edge test" step 4, smooth curved surface: for each cell (``pt``: P relative to the
    origin; ``level``: :func:`_clean_sides`'; the rest :func:`_side_fits`' arrays), whether its
    four quadrants (sides 4-7) are level (valid, not steep), not empty and bend as one
    quadratic surface ``z = 1/2 v'Av`` would (A from the differences of opposite quadrants'
    slopes at their centroids; each quadrant's vertical rms^2 between _CURVED_BEND and
    _CURVED_FIT times the residual variance such a surface leaves about its plane, plus
    ``floor^2`` above), and P lies within
    ``max(k sigma, floor)`` of where that surface puts it above every quadrant's plane,
    ``1/2 m'Am - 1/2 tr(AS)`` (``sigma^2``: the quadrants' mean vertical rms^2 less the
    surface's residual variance)."""
    q = slice(4, 8)
    ok = (level[q] & ~empty[q]).all(axis=0)
    uz = np.where(ok, nrm[q, :, 2], 1.0)
    gx, gy = -nrm[q, :, 0] / uz, -nrm[q, :, 1] / uz
    mx, my = cen[q, :, 0] - pt[:, 0], cen[q, :, 1] - pt[:, 1]
    hv = h[q] / uz
    r2 = (rms[q] / uz) * (rms[q] / uz)
    d11, d21 = mx[3] - mx[0], my[3] - my[0]
    d12, d22 = mx[2] - mx[1], my[2] - my[1]
    det = d11 * d22 - d12 * d21
    ok &= np.abs(det) > _EDGE_LINE_TOL * (d11 * d11 + d12 * d12 + d21 * d21 + d22 * d22)
    det = np.where(ok, det, 1.0)
    b11, b21 = gx[3] - gx[0], gy[3] - gy[0]
    b12, b22 = gx[2] - gx[1], gy[2] - gy[1]
    a11 = (b11 * d22 - b12 * d21) / det
    a22 = (b22 * d11 - b21 * d12) / det
    a12 = 0.5 * ((b12 * d11 - b11 * d12) / det + (b21 * d22 - b22 * d21) / det)
    sxx, syy, sxy = cov2[q, :, 0], cov2[q, :, 1], cov2[q, :, 2]
    at = 0.5 * (a11 * mx * mx + 2.0 * a12 * mx * my + a22 * my * my) - \
        0.5 * (a11 * sxx + 2.0 * a12 * sxy + a22 * syy)
    bend = _CURVED_LATTICE * (a11 * a11 * sxx * sxx + a22 * a22 * syy * syy) + \
        a12 * a12 * sxx * syy
    with np.errstate(invalid="ignore"):
        ok &= ((r2 >= _CURVED_BEND * bend) & (r2 <= _CURVED_FIT * bend + floor * floor)).all(axis=0)
        worst = np.abs(hv - at).max(axis=0)
        noise = np.maximum(r2 - bend, 0.0).sum(axis=0)
        return ok & (worst <= np.maximum(k * np.sqrt(0.25 * noise), floor))


#: A quiet cell (SPEC "Edge test" step 1), not judged: within this many rms of its height
#: window's plane, whose rms is at most _EDGE_QUIET_ROUGH times the tolerance floor.
_EDGE_QUIET_H = 4.0
_EDGE_QUIET_ROUGH = 0.75
#: The edge test's precision floor (SPEC "Edge test" step 3): every tolerance is at least this
#: many epsilons of the input type times the cell's largest absolute coordinate.
_EDGE_PRECISION = 4.0
_EDGE_PRECISION_F64 = _EDGE_PRECISION * float(np.finfo(np.float64).eps)  # (float64 input)

#: The edge test's tiles (SPEC "Edge test" step 3): rows x columns, fixed in grid coordinates.
_EDGE_TILE = (64, 128)


#: Fin directions (SPEC "Edge test" step 6): along columns, along rows, both diagonals.
_FIN_DIRECTIONS = ((1, 0), (0, 1), (1, 1), (1, -1))


def _fins(
    grid: NDArray[np.float64],
    labels: NDArray[np.uint8],
    cells: NDArray[np.bool_],
    r: int,
) -> NDArray[np.bool_]:
    """The cells of ``cells`` that are *fins* (SPEC "Edge test" step 6): thin material standing
    proud of the ground on both sides along a direction, taller than that ground is apart."""
    hh, ww = labels.shape
    ground = (labels == NORMAL) | (labels == EDGE)
    z = np.where(ground, grid[..., 2], np.inf)
    zm = np.where(labels != INVALID, grid[..., 2], -np.inf)  # material: any cell with a return
    xy = grid[..., :2]
    out = np.zeros_like(cells)
    rr, cc = np.nonzero(cells)
    zp = grid[rr, cc, 2]

    def at(a: NDArray[np.float64], r1: NDArray[np.int64], c1: NDArray[np.int64],
           fill: float) -> NDArray[np.float64]:
        inside = (r1 >= 0) & (r1 < hh) & (c1 >= 0) & (c1 < ww)
        shape = (rr.size,) + a.shape[2:]
        v = np.full(shape, fill)
        v[inside] = a[r1[inside], c1[inside]]
        return v

    for dr, dc in _FIN_DIRECTIONS:
        lows = []
        for sg in (-1, 1):
            zmin = np.full(rr.size, np.inf)
            pmin = np.full((rr.size, 2), np.nan)
            for j in range(1, r + 1):  # outward: among equal minima the nearest one
                r1, c1 = rr + sg * j * dr, cc + sg * j * dc
                zj = at(z, r1, c1, np.inf)
                lower = zj < zmin
                zmin = np.where(lower, zj, zmin)
                pmin = np.where(lower[:, None], at(xy, r1, c1, np.nan), pmin)
            lows.append((zmin, pmin))
        (za, pa), (zb, pb) = lows
        base = np.maximum(za, zb)
        height = zp - base
        dx, dy = pa[:, 0] - pb[:, 0], pa[:, 1] - pb[:, 1]
        with np.errstate(invalid="ignore"):  # no ground on a side: base = inf
            half = base + 0.5 * height
        wide = np.zeros(rr.size, dtype=bool)  # a neighbour along d above half height
        for sg in (-1, 1):
            wide |= at(zm, rr + sg * dr, cc + sg * dc, -np.inf) > half
        long = np.ones(rr.size, dtype=bool)  # and along the fin's line, both ways within r
        er, ec = (dc, dr) if dr == 0 or dc == 0 else (dr, -dc)  # the perpendicular direction
        for sg in (-1, 1):
            up = np.zeros(rr.size, dtype=bool)
            for j in range(1, r + 1):
                up |= at(zm, rr + sg * j * er, cc + sg * j * ec, -np.inf) > half
            long &= up
        fin = np.isfinite(base) & (height > 0.0) & (height * height > dx * dx + dy * dy)
        fin &= wide & long
        out[rr[fin], cc[fin]] = True
    return out


#: Hanging directions (SPEC "Edge test" step 6): per sub-window of :func:`_edge_sides`, the
#: step (row, column) from the sub-window towards P and on beyond it.
_HANG_DIRECTIONS = ((0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (1, -1), (-1, 1), (-1, -1))
#: A hanging cell's shelf: the surface beyond it lies more than this times as deep below P as
#: P lies below the top (a staircase of two equal steps stays clean).
_HANG_SHELF = 2.0


#: P is *attached* to a sub-window (SPEC "Edge test" step 5) unless, on its way towards it,
#: this many INVALID cells in a row come before the first cell on the sub-window's plane.
_EDGE_ATTACH_GAP = 2


def _attached(
    grid: NDArray[np.float64],
    labels: NDArray[np.uint8],
    cells: NDArray[np.bool_],
    r: int,
    origin: NDArray[np.float64],
    nrm: NDArray[np.float64],
    cen: NDArray[np.float64],
    tol: NDArray[np.float64],
) -> NDArray[np.bool_]:
    """(8, N) for the cells of ``cells`` (row-major): is P *attached* to each sub-window (SPEC
    "Edge test" step 5)? Along ``P - j d``, ``j = 1..r`` inside the grid (``d`` the step from
    the sub-window towards P, :data:`_HANG_DIRECTIONS`), no ``_EDGE_ATTACH_GAP`` INVALID cells
    in a row before the first cell with a return on the sub-window's plane (``|u . (q - o -
    m)| <= t``; ``nrm``, ``cen``, ``tol`` (8, N, ...) its normal, centroid and tolerance)."""
    hh, ww = labels.shape
    rr, cc = np.nonzero(cells)
    out = np.ones((len(_HANG_DIRECTIONS), rr.size), dtype=bool)
    for k, (dr, dc) in enumerate(_HANG_DIRECTIONS):
        run = np.zeros(rr.size, dtype=np.int64)
        done = np.zeros(rr.size, dtype=bool)
        for j in range(1, r + 1):
            a, b = rr - j * dr, cc - j * dc
            inside = (a >= 0) & (a < hh) & (b >= 0) & (b < ww)
            a, b = np.clip(a, 0, hh - 1), np.clip(b, 0, ww - 1)
            done |= ~inside
            ret = labels[a, b] != INVALID
            run = np.where(ret, 0, run + 1)
            gap = ~done & (run >= _EDGE_ATTACH_GAP)
            out[k] &= ~gap
            on = ret & ~(np.abs(_dot3((grid[a, b] - origin) - cen[k], nrm[k])) > tol[k])
            done |= gap | on
    return out


def _hanging(
    grid: NDArray[np.float64],
    labels: NDArray[np.uint8],
    cells: NDArray[np.bool_],
    r: int,
    below: NDArray[np.bool_],
    h: NDArray[np.float64],
    normals: NDArray[np.float64],
) -> NDArray[np.bool_]:
    """The cells of ``cells`` (row-major) that *hang* (SPEC "Edge test" step 6) below one of the
    sub-windows marked in ``below`` (8, N): both conditions of :func:`_hang_conditions` hold
    towards that sub-window."""
    out = np.zeros(below.shape[1], dtype=bool)
    for k in range(len(_HANG_DIRECTIONS)):
        if below[k].any():
            steep, shelf = _hang_conditions(grid, labels, cells, r, k, h[k], normals[k])
            out |= below[k] & steep & shelf
    return out


#: Ledges (SPEC "Edge test" step 6): a ledge's cells lie level with P within
#: ``min(_LEDGE_LEVEL * depth, t)`` along the top's normal ...
_LEDGE_LEVEL = 0.5
#: ... and the step from the top down onto the ledge exceeds the largest step along the ledge
#: by more than this times the top's tolerance (on a rounded bend the steps grow outwards).
_LEDGE_JUMP = 1.0
#: ... and a ledge holds at most this many cells along that direction, P included (burrs on
#: edges are 1-4 points wide; a wider level band below a top is a surface of the part).
_LEDGE_CELLS = 5


def _ledges(
    grid: NDArray[np.float64],
    labels: NDArray[np.uint8],
    cells: NDArray[np.bool_],
    r: int,
    below: NDArray[np.bool_],
    h: NDArray[np.float64],
    nrm: NDArray[np.float64],
    cen: NDArray[np.float64],
    tol: NDArray[np.float64],
    origin: NDArray[np.float64],
) -> NDArray[np.bool_]:
    """The cells of ``cells`` (row-major) on a *ledge* (SPEC "Edge test" step 6) below one of
    the sub-windows marked in ``below`` (8, N; ``h``, ``nrm``, ``cen``, ``tol`` (8, N, ...)
    each sub-window's height of P, normal, centroid and tolerance): along the sub-window's
    direction ``d`` the cells level with P (2 to ``_LEDGE_CELLS`` of them, P included) run
    from a ground cell on its plane, which steps down onto them by more than their largest
    step plus ``_LEDGE_JUMP`` tolerances, to a ground cell that drops steeper than 45 degrees
    to more than ``_HANG_SHELF`` times P's depth below P."""
    hh, ww = labels.shape
    ground = (labels == NORMAL) | (labels == EDGE)
    rr, cc = np.nonzero(cells)
    p = grid[rr, cc]
    out = np.zeros(rr.size, dtype=bool)
    for k, (dr, dc) in enumerate(_HANG_DIRECTIONS):
        if not below[k].any():
            continue
        u, depth = nrm[k], -h[k]
        level = np.minimum(_LEDGE_LEVEL * depth, tol[k])
        widest = np.zeros(rr.size)  # the largest step between consecutive ledge cells
        ends = []
        for sign in (-1, 1):  # towards the sub-window (the top), then beyond P
            going = below[k].copy()
            run = np.zeros(rr.size, dtype=np.int64)
            prev = p.copy()
            end = np.full((rr.size, 3), np.nan)
            last = np.full((rr.size, 3), np.nan)
            on_ground = np.zeros(rr.size, dtype=bool)
            for j in range(1, r + 1):
                a, b = rr + sign * j * dr, cc + sign * j * dc
                inside = (a >= 0) & (a < hh) & (b >= 0) & (b < ww)
                a, b = np.clip(a, 0, hh - 1), np.clip(b, 0, ww - 1)
                ret = inside & (labels[a, b] != INVALID)
                x = np.where(ret[:, None], grid[a, b], np.nan)
                lvl = ret & (np.abs(_dot3(x - p, u)) <= level)
                stop = going & ~lvl
                end[stop], last[stop] = x[stop], prev[stop]
                on_ground |= stop & inside & ground[a, b]
                on = going & lvl
                widest[on] = np.maximum(widest[on], np.abs(_dot3(x[on] - prev[on], u[on])))
                prev[on] = x[on]
                run += on
                going &= lvl
            ends.append((on_ground, end, last, run))
        (g_in, top, t_last, n_in), (g_out, low, l_last, n_out) = ends
        on_top = g_in & ~(np.abs(_dot3((top - origin) - cen[k], u)) > tol[k])
        jump = _dot3(top - t_last, u) > widest + _LEDGE_JUMP * tol[k]
        w = low - l_last
        fall = -_dot3(w, u)
        steep = (fall > 0.0) & (fall * fall > _dot3(w, w) - fall * fall)
        shelf = g_out & (_dot3(low - p, u) < -_HANG_SHELF * depth)
        width = n_in + n_out + 1  # the level cells, P included
        out |= below[k] & on_top & jump & steep & shelf & (width >= 2) & (width <= _LEDGE_CELLS)
    return out


def _hang_conditions(
    grid: NDArray[np.float64],
    labels: NDArray[np.uint8],
    cells: NDArray[np.bool_],
    r: int,
    k: int,
    h: NDArray[np.float64],
    u: NDArray[np.float64],
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """For the cells of ``cells`` (row-major) below sub-window ``k`` (``h`` their heights over
    its plane, ``u`` its normals), SPEC "Edge test" step 6's two conditions of hanging apart:
    *steep* (steeper than 45 degrees below the top's last ground cell, NORMAL or EDGE, towards
    the sub-window, or beyond a step that drops that steeply on a path of ABNORMAL cells from
    that ground cell) and *shelf* (ground beyond P more than ``_HANG_SHELF`` times as deep
    again)."""
    hh, ww = labels.shape
    dr, dc = _HANG_DIRECTIONS[k]
    ground = (labels == NORMAL) | (labels == EDGE)
    hung = labels == ABNORMAL
    rr, cc = np.nonzero(cells)
    p = grid[rr, cc]
    depth = -h

    def inside(r1: NDArray[np.int64], c1: NDArray[np.int64]) -> NDArray[np.bool_]:
        return (r1 >= 0) & (r1 < hh) & (c1 >= 0) & (c1 < ww)

    # P to the nearest ground cell towards the sub-window (the top's last sample: the angle
    # passes often label it EDGE, and the nearest NORMAL cell lies further back)
    v = np.full((rr.size, 3), np.nan)
    found = np.zeros(rr.size, dtype=bool)
    # the path P - j d towards the ground cell: while it runs over ABNORMAL cells (`chain`),
    # any step from a cell to the next one towards P that drops steeper than 45 degrees
    prev = p.copy()
    chain = np.ones(rr.size, dtype=bool)
    drop = np.zeros(rr.size, dtype=bool)
    via = np.zeros(rr.size, dtype=bool)  # the path passed an ABNORMAL cell
    for j in range(1, r + 1):
        r1, c1 = rr - j * dr, cc - j * dc
        ok = inside(r1, c1)
        hit = np.zeros(rr.size, dtype=bool)
        hit[ok] = ground[r1[ok], c1[ok]]
        on = np.zeros(rr.size, dtype=bool)
        on[ok] = hung[r1[ok], c1[ok]]
        step = ~found & chain & (hit | on)  # x = this cell, y = prev
        x = np.zeros((rr.size, 3))
        x[step] = grid[r1[step], c1[step]]
        w = prev - x
        along_w = _dot3(w, u)
        drop |= step & (along_w < 0.0) & (along_w * along_w > _dot3(w, w) - along_w * along_w)
        prev[step & on] = x[step & on]
        via |= step & on
        chain &= found | hit | on
        hit &= ~found
        v[hit] = grid[r1[hit], c1[hit]] - p[hit]
        found |= hit
    along = _dot3(v, u)
    steep = found & (depth * depth > _dot3(v, v) - along * along)
    steep |= found & chain & via & drop
    low = np.full(rr.size, np.inf)  # the deepest ground cell beyond P, along u
    for hit, d in _beyond(grid, labels, cells, r, k, u):
        low = np.minimum(low, np.where(hit, d, np.inf))
    return steep, low < -_HANG_SHELF * depth


def _ground_line(
    grid: NDArray[np.float64],
    labels: NDArray[np.uint8],
    cells: NDArray[np.bool_],
    r: int,
    step: tuple[int, int],
) -> Iterator[tuple[NDArray[np.bool_], NDArray[np.float64]]]:
    """The ground cells (NORMAL or EDGE) ``x = P + j step`` from the cells P of ``cells``
    (row-major), ``j = 1..r`` in order: per ``j``, which P have one there (inside the grid; a
    straight line that leaves the grid does not come back) and ``x - P`` (NaN where none)."""
    hh, ww = labels.shape
    ground = (labels == NORMAL) | (labels == EDGE)
    rr, cc = np.nonzero(cells)
    p = grid[rr, cc]
    for j in range(1, r + 1):
        r1, c1 = rr + j * step[0], cc + j * step[1]
        ok = (r1 >= 0) & (r1 < hh) & (c1 >= 0) & (c1 < ww)
        hit = np.zeros(rr.size, dtype=bool)
        hit[ok] = ground[r1[ok], c1[ok]]
        v = np.full((rr.size, 3), np.nan)
        v[hit] = grid[r1[hit], c1[hit]] - p[hit]
        yield hit, v


def _beyond(
    grid: NDArray[np.float64],
    labels: NDArray[np.uint8],
    cells: NDArray[np.bool_],
    r: int,
    k: int,
    u: NDArray[np.float64],
) -> Iterator[tuple[NDArray[np.bool_], NDArray[np.float64]]]:
    """The ground cells beyond the cells P of ``cells`` (row-major) away from sub-window ``k``,
    ``x = P + j d`` for ``j = 1..r`` in order (SPEC "Edge test" step 6: a hanging cell's shelf,
    a lip's dip and rise): per ``j``, which P have one there (NORMAL or EDGE, inside the grid)
    and its ``u . (x - P)`` (NaN where none)."""
    for hit, v in _ground_line(grid, labels, cells, r, _HANG_DIRECTIONS[k]):
        d = np.full(hit.size, np.nan)
        d[hit] = _dot3(v[hit], u[hit])
        yield hit, d


#: Lips at a concave feature (SPEC "Edge test" step 6): beyond P the surface falls back by more
#: than this times the clean side's tolerance (2 x edge_k rms: a profile offset of a few rms, as
#: on the real scans, is no lip) ...
_EDGE_LIP_TOL = 2.0
#: ... and by more than this share of P's height over that side's plane (a lip, not the edge of
#: a terrace whose next cells lie level with P), then rises above that plane by as much.
_EDGE_LIP_DIP = 0.5


def _nearest_ground(
    grid: NDArray[np.float64],
    labels: NDArray[np.uint8],
    cells: NDArray[np.bool_],
    r: int,
    step: tuple[int, int],
    u: NDArray[np.float64],
) -> tuple[NDArray[np.bool_], NDArray[np.float64], NDArray[np.float64]]:
    """For the cells P of ``cells`` (row-major): is there a ground cell along ``step``
    (:func:`_ground_line`), and for the nearest one ``x``, ``s = u . (x - P)`` and ``w``, its
    distance from P along ``u``'s plane (``sqrt(|x - P|^2 - s^2)``); 0 where there is none."""
    n = int(cells.sum())
    found = np.zeros(n, dtype=bool)
    s = np.zeros(n)
    w = np.zeros(n)
    for hit, v in _ground_line(grid, labels, cells, r, step):
        new = hit & ~found
        s[new] = _dot3(v[new], u[new])
        w[new] = np.sqrt(np.maximum(_dot3(v[new], v[new]) - s[new] * s[new], 0.0))
        found |= new
    return found, s, w


def _lips(
    grid: NDArray[np.float64],
    labels: NDArray[np.uint8],
    cells: NDArray[np.bool_],
    r: int,
    lip: NDArray[np.bool_],
    normals: NDArray[np.float64],
    h: NDArray[np.float64],
    tol: NDArray[np.float64],
) -> NDArray[np.bool_]:
    """The cells of ``cells`` (row-major; ``lip``, ``normals``, ``h``, ``tol``: (8, N), N the
    cells set in ``cells``) that are *lips at a concave feature* (SPEC "Edge test" step 6):
    above a clean sub-window ``a`` marked in ``lip``, and along the cells ``P + j d`` beyond P
    away from ``a`` (``j = 1..r``, ground cells only: NORMAL or EDGE), with
    ``D = max(_EDGE_LIP_TOL t, _EDGE_LIP_DIP h)`` (``t``, ``h``: ``a``'s tolerance and P's
    height over ``a``'s plane), first a *dip* (a cell lower than P along ``a``'s normal by more
    than ``D``; or P itself: above the chord from the nearest ground cell towards ``a`` to the
    first one beyond P by more than ``D``, that first one lower than P by more than ``2 t``),
    then a *rise*: the last of these ground cells, after the dip, lies above ``a``'s plane by
    more than ``D`` (the surface goes on rising, unlike a fin beyond P)."""
    out = np.zeros(lip.shape[1], dtype=bool)
    for k in range(len(_HANG_DIRECTIONS)):
        if not lip[k].any():
            continue
        hk = h[k]
        dip = np.maximum(_EDGE_LIP_TOL * tol[k], _EDGE_LIP_DIP * hk)
        dr, dc = _HANG_DIRECTIONS[k]
        okq, sq, wq = _nearest_ground(grid, labels, cells, r, (-dr, -dc), normals[k])
        ok1, s1, w1 = _nearest_ground(grid, labels, cells, r, (dr, dc), normals[k])
        with np.errstate(invalid="ignore", divide="ignore"):
            chord = (sq * w1 + s1 * wq) / (wq + w1)  # the chord's height at P
            # a dip at P itself (a lip whose next cells already climb the concave side)
            dipped = (okq & ok1 & (s1 < -_EDGE_LIP_TOL * tol[k]) & (wq + w1 > 0.0)
                      & (-chord > dip))
        risen = np.zeros(out.size, dtype=bool)  # the last ground cell so far: after a dip, high
        for hit, d in _beyond(grid, labels, cells, r, k, normals[k]):
            risen[hit] = dipped[hit] & (hk[hit] + d[hit] > dip[hit])
            dipped |= hit & (d < -dip)
        out |= lip[k] & risen
    return out


def _outline_lips(
    images: NDArray[np.float64],
    cells: NDArray[np.bool_],
    r: int,
    clean: NDArray[np.bool_],
    fits: NDArray[np.bool_],
    h: NDArray[np.float64],
    tol: NDArray[np.float64],
    empty: NDArray[np.bool_],
    attached: NDArray[np.bool_],
) -> NDArray[np.bool_]:
    """The cells of ``cells`` (row-major) that are a *lip before an outline* (SPEC "Edge
    test" step 5): above a clean sub-window by more than _OUTLINE_HEIGHT tolerances, attached
    to it, its opposite an outline, and fitting no clean sub-window on its own side."""
    rr, cc = np.nonzero(cells)
    full = np.array([(2 * r + 1) * r] * 4 + [r * r] * 4, dtype=np.float64)
    outline = np.stack([_side_sums(images, rr, cc, r, k)[:, 10] for k in range(8)])
    outline = empty & (outline >= _OUTLINE_EMPTY * full[:, None])
    beyond = outline[list(_EDGE_OPPOSITE_OF)]
    out = np.zeros(h.shape[1], dtype=bool)
    for x in range(8):
        near = fits[list(_EDGE_SAME_SIDE[x])].any(axis=0)
        out |= clean[x] & (h[x] > _OUTLINE_HEIGHT * tol[x]) & beyond[x] & attached[x] & ~near
    return out


#: Crossings (SPEC "Edge test" step 6): P stands proud of a clean sub-window by more than
#: this times the tolerance's floor (min_step / 2, 1.5 z_resolution, 2 z_noise) too, every
#: clean sub-window it fits past the feature.
_CROSSING_FLOOR = 2.5


def _crossings(
    proud_of: NDArray[np.bool_],
    fits: NDArray[np.bool_],
    h: NDArray[np.float64],
    tol: NDArray[np.float64],
    nrm: NDArray[np.float64],
    cen: NDArray[np.float64],
    floor: float,
) -> NDArray[np.bool_]:
    """The cells that are *lips across a convex feature* (SPEC "Edge test" step 6): standing
    proud of a clean sub-window ``x`` (``proud_of[x]``: step 5, attached), above it by more
    than _CROSSING_FLOOR times the tolerance floor ``floor`` (step 3) too, and every clean
    sub-window they fit *past the feature* (its centroid more than x's tolerance below x's
    plane): the far face's plane, extended back over P, does not clear P."""
    out = np.zeros(h.shape[1], dtype=bool)
    for x in range(8):
        cleared = np.zeros(h.shape[1], dtype=bool)
        for c in range(8):
            cleared |= fits[c] & ~(_dot3(nrm[x], cen[c] - cen[x]) < -tol[x])
        out |= proud_of[x] & (h[x] > _CROSSING_FLOOR * floor) & ~cleared
    return out


#: Valleys (SPEC "Edge test" step 6): P lies above both opposite clean sub-windows by more
#: than this times their tolerances ...
_VALLEY_HEIGHT = 1.75
#: ... the opposite sub-window's centroid lies above the first one's plane by more than this
#: times its tolerance (the far face rises: a concave feature) ...
_VALLEY_CENTROID = 2.0
#: ... the two planes meet at more than 4 degrees (a crease, not a gently curved surface: on
#: a noise-free one the centroid test alone passes a bead), cos 4 degrees ...
_VALLEY_COS = 0.9975640502598242
#: ... the scan's spacing is regular up to P on both sides: the gap from P to its neighbour
#: towards a sub-window is at most this times the gap from that neighbour to the next ...
_VALLEY_GAP = 3.0
#: ... towards the lower side the raised run (P included) holds at most this many cells ...
_VALLEY_CELLS = 4
#: ... and steps up from that side's plane by more than its largest rise plus this many
#: tolerances (a fillet rises ever more steeply: no step).
_VALLEY_JUMP = 1.5


def _valleys(
    grid: NDArray[np.float64],
    labels: NDArray[np.uint8],
    cells: NDArray[np.bool_],
    r: int,
    level: NDArray[np.bool_],
    h: NDArray[np.float64],
    tol: NDArray[np.float64],
    nrm: NDArray[np.float64],
    cen: NDArray[np.float64],
) -> NDArray[np.bool_]:
    """The cells of ``cells`` (row-major) *in a valley* (SPEC "Edge test" step 6); ``level``: the
    valid sub-windows that are not steep, clean or not."""
    hh, ww = labels.shape
    rr, cc = np.nonzero(cells)
    p = grid[rr, cc]
    regular = np.zeros(level.shape, dtype=bool)
    if r >= 2:
        for k, (dr, dc) in enumerate(_HANG_DIRECTIONS):
            u = nrm[k]
            q, ok = [], np.ones(rr.size, dtype=bool)
            for j in (1, 2):
                a, b = rr - j * dr, cc - j * dc
                inside = (a >= 0) & (a < hh) & (b >= 0) & (b < ww)
                a, b = np.clip(a, 0, hh - 1), np.clip(b, 0, ww - 1)
                ok &= inside & (labels[a, b] != INVALID)
                q.append(grid[a, b])

            def along(v: NDArray[np.float64]) -> NDArray[np.float64]:
                s = _dot3(v, u)
                return np.sqrt(np.maximum(_dot3(v, v) - s * s, 0.0))

            regular[k] = ok & (along(q[0] - p) <= _VALLEY_GAP * along(q[1] - q[0]))
    high = level & (h > _VALLEY_HEIGHT * tol) & regular
    out = np.zeros(rr.size, dtype=bool)
    for a, b in _EDGE_OPPOSITE:
        for x, y in ((a, b), (b, a)):
            rise = _dot3(nrm[x], cen[y] - cen[x])  # y's centroid over x's plane
            cand = high[x] & high[y] & (rise > _VALLEY_CENTROID * tol[x]) & (
                _dot3(nrm[x], nrm[y]) < _VALLEY_COS)
            if not cand.any():
                continue
            u, hx, tx = nrm[x], h[x], tol[x]
            dr, dc = _HANG_DIRECTIONS[x]
            # towards x (within _VALLEY_CELLS steps): the raised ground cells, then the first
            # on x's plane (the base)
            prev = hx.copy()  # height over x's plane of the last raised cell
            widest = np.zeros(rr.size)  # the largest rise between consecutive raised cells
            going = cand.copy()
            based = np.zeros(rr.size, dtype=bool)
            jump = np.zeros(rr.size)
            reach = min(r, _VALLEY_CELLS)
            for hit, v in _ground_line(grid, labels, cells, reach, (-dr, -dc)):
                hv = _dot3(v, u) + hx
                on = hit & going & ~(np.abs(hv) > tx)
                based |= on
                jump[on] = prev[on] - hv[on]
                up = hit & going & ~on
                widest[up] = np.maximum(widest[up], prev[up] - hv[up])
                prev[up] = hv[up]
                going &= ~hit | up
            # ... and beyond P: the rise onto the next ground cell
            ok1, s1, _ = _nearest_ground(grid, labels, cells, r, (dr, dc), u)
            widest = np.where(ok1, np.maximum(widest, s1), widest)
            out |= cand & based & (jump > widest + _VALLEY_JUMP * tx)
    return out


#: Isolated spikes (SPEC "Edge test" step 7): P lies more than this times its tolerance off
#: every clean side (2 x edge_k rms: never a cell that fits a clean side) ...
_EDGE_SPIKE_TOL = 2.0
#: ... and its neighbours' median distance to the cleanest side's plane is below this times P's.
_EDGE_SPIKE_ISO = 0.2
#: A neighbour is *raised* when its signed distance lies on P's side beyond this times |h|.
_EDGE_SPIKE_RAISED = 0.5


def _spike_corner(res: list[float], h: float) -> bool:
    """Step 7's last condition: P is the corner of a raised patch (not an isolated spike) when
    a raised neighbour lies in its row and one in its column. ``res``: the signed distances of
    P's 8 neighbours (row-major, P left out; NaN without a return) to the cleanest side's
    plane."""
    s, lim = (1.0 if h > 0.0 else -1.0), _EDGE_SPIKE_RAISED * abs(h)
    up = [s * v > lim for v in res]  # NaN: not raised
    return (up[3] or up[4]) and (up[1] or up[6])


def _spikes(
    grid: NDArray[np.float64],
    labels: NDArray[np.uint8],
    cells: NDArray[np.bool_],
    origin: NDArray[np.float64],
    h: NDArray[np.float64],
    tol: NDArray[np.float64],
    level: NDArray[np.bool_],
    clean: NDArray[np.bool_],
    rms: NDArray[np.float64],
    nrm: NDArray[np.float64],
    cen: NDArray[np.float64],
) -> NDArray[np.bool_]:
    """The cells of ``cells`` (row-major; side arrays of shape (8, N)) that are *isolated
    spikes* (SPEC "Edge test" step 7): NORMAL, all 8 neighbours inside the grid, more than
    ``_EDGE_SPIKE_TOL`` x tol off every clean side, and the median over the neighbours with a
    return of their distance to the cleanest side's plane below ``_EDGE_SPIKE_ISO`` x P's, and
    not the corner of a raised patch (``_spike_corner``)."""
    hh, ww = labels.shape
    rr, cc = np.nonzero(cells)
    out = np.zeros(rr.size, dtype=bool)
    far = ~(clean & ~(np.abs(h) > _EDGE_SPIKE_TOL * tol)).any(axis=0) & clean.any(axis=0)
    far &= (labels[rr, cc] == NORMAL) & (rr >= 1) & (rr + 1 < hh) & (cc >= 1) & (cc + 1 < ww)
    cleanest = np.argmin(np.where(level, rms, np.inf), axis=0)  # the first smallest
    for i in np.flatnonzero(far):
        s = cleanest[i]
        u, m = nrm[s, i], cen[s, i]
        res = [float(_dot3((grid[rr[i] + a, cc[i] + b] - origin) - m, u))
               if labels[rr[i] + a, cc[i] + b] != INVALID else math.nan
               for a in (-1, 0, 1) for b in (-1, 0, 1) if a or b]
        d = sorted(abs(v) for v in res if not math.isnan(v))
        if not d:
            continue
        n = len(d)
        median = d[n // 2] if n % 2 else (d[n // 2 - 1] + d[n // 2]) / 2.0
        out[i] = (median < _EDGE_SPIKE_ISO * abs(h[s, i])
                  and not _spike_corner(res, float(h[s, i])))
    return out


def _edge_pass(
    grid: NDArray[np.float64],
    labels: NDArray[np.uint8],
    candidates: NDArray[np.bool_],
    window: int,
    k: float,
    floor: float = 0.0,
    precision: float = _EDGE_PRECISION_F64,
) -> NDArray[np.bool_]:
    """One edge pass (SPEC "Edge test"): the candidate cells that become ABNORMAL, tile by
    tile (each tile's sums over the tile and ``r`` cells around it, from its own origin);
    ``floor`` the least tolerance (``min_step / 2``, ``1.5 z_resolution``: step 3), and
    ``precision`` times the cell's largest absolute coordinate."""
    cells = candidates & ((labels == NORMAL) | (labels == EDGE))
    return _tiled(grid, labels, cells, window, lambda g, lab, sel, r, origin: _edge_verdicts(
        g, lab, sel, r, k, origin, floor, precision=precision))


def _tiled(
    grid: NDArray[np.float64],
    labels: NDArray[np.uint8],
    cells: NDArray[np.bool_],
    window: int,
    verdicts: Any,
) -> NDArray[np.bool_]:
    """``verdicts(grid, labels, cells, r, origin)`` of the ``cells``, tile by tile (SPEC "Edge
    test" step 3: each tile's sums over the tile and ``r`` cells around it, from its origin)."""
    out = np.zeros_like(cells)
    hh, ww = cells.shape
    r = window // 2
    for t0 in range(0, hh, _EDGE_TILE[0]):
        for u0 in range(0, ww, _EDGE_TILE[1]):
            t1, u1 = min(hh, t0 + _EDGE_TILE[0]), min(ww, u0 + _EDGE_TILE[1])
            if not cells[t0:t1, u0:u1].any():
                continue
            tile = grid[t0:t1, u0:u1]
            fin = np.isfinite(tile).all(axis=-1)
            origin = tile[np.unravel_index(np.argmax(fin), fin.shape)]  # first finite cell
            e0, e1, f0, f1 = max(0, t0 - r), min(hh, t1 + r), max(0, u0 - r), min(ww, u1 + r)
            sel = np.zeros((e1 - e0, f1 - f0), dtype=bool)
            sel[t0 - e0:t1 - e0, u0 - f0:u1 - f0] = cells[t0:t1, u0:u1]
            out[e0:e1, f0:f1] |= verdicts(grid[e0:e1, f0:f1], labels[e0:e1, f0:f1], sel, r,
                                          origin)
    return out


def _clean_sides(
    rms: NDArray[np.float64],
    spread: NDArray[np.float64],
    valid: NDArray[np.bool_],
    nrm: NDArray[np.float64],
    k: float,
    floor: float | NDArray[np.float64] = 0.0,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_], NDArray[np.float64]]:
    """SPEC "Edge test" steps 3-4 on :func:`_side_fits`' results: which sub-windows are valid
    and not steep (``level``), which are *clean* (level, rms at most twice the best level
    one's) and each one's tolerance ``t`` (with its round-off floor, as the height test's, and
    at least ``floor``, one value or one per cell: :func:`edge_test`'s from the min_step and z
    resolution in use and the cell's precision floor)."""
    level = valid & (nrm[..., 2] >= _EDGE_STEEP_COS)
    best = np.min(np.where(level, rms, np.inf), axis=0)
    clean = level & (rms <= _EDGE_CLEAN_RATIO * best)
    return level, clean, np.maximum(np.maximum(k * rms, _HEIGHT_RMS_FLOOR * spread), floor)


def _edge_verdicts(
    grid: NDArray[np.float64],
    labels: NDArray[np.uint8],
    cells: NDArray[np.bool_],
    r: int,
    k: float,
    origin: NDArray[np.float64],
    floor: float = 0.0,
    fits_only: bool = False,
    precision: float = _EDGE_PRECISION_F64,
) -> NDArray[np.bool_]:
    """Steps 4-7 of the edge test for the cells of ``cells`` (sums relative to ``origin``;
    ``floor``: the least tolerance, step 3, and ``precision`` times the cell's largest absolute
    coordinate); with ``fits_only``, step 9's verdict instead: the cells that fit a clean
    sub-window that is not empty."""
    out = np.zeros_like(cells)
    support, invalid = labels == NORMAL, labels == INVALID
    images = _moment_images(grid, support, invalid, origin)  # the pass's, for step 3
    h, rms, spread, valid, nrm, cen, empty, cov2 = _side_fits(
        grid, support, invalid, cells, r, origin, images)
    # each cell's floor: the least tolerance, or its precision floor when larger (step 3)
    cell_floor = np.maximum(floor, precision * np.abs(grid[cells]).max(axis=-1))
    level, clean, tol = _clean_sides(rms, spread, valid, nrm, k, cell_floor)
    fits = clean & ~(np.abs(h) > tol)
    if fits_only:
        out[cells] = (fits & ~empty).any(axis=0)
        return out
    # P stands proud (outward, above the plane) of a clean side whose opposite side has no
    # support (an outline) or falls away below that plane (a convex edge, a wall top).
    attached = _attached(grid, labels, cells, r, origin, nrm, cen, tol)
    # P below a clean side x whose opposite y has no return or is clean with P above it and
    # falls away: P lies between a top and the lower surface beyond (a hanging candidate)
    under = clean & (h < -tol)  # P below a clean side: hanging or a ledge (step 6)
    opp = list(_EDGE_OPPOSITE_OF)
    drop = _dot3(nrm, cen[opp] - cen) < -tol  # the opposite's centroid below each plane
    falls = empty[opp] | (valid[opp] & drop)
    proud_of = clean & (h > tol) & falls & attached  # per side (the crossing rule's too)
    proud = proud_of.any(axis=0)
    below = under & (empty[opp] | (clean[opp] & (h[opp] > tol[opp]) & drop))
    fin = _fins(grid, labels, cells, r)[cells]  # (SPEC step 6: reach r, inside the tile's frame)
    out[cells] = ~fits.any(axis=0) & (proud | fin)
    # before an outline, only the sub-windows on P's side of it may clear P: the others lie
    # along the outline and hold the lip itself (step 5, outlines)
    out[cells] |= _outline_lips(images, cells, r, clean, fits, h, tol, empty, attached)
    # a lip across a convex feature: the far face's plane, extended back over P, lies above the
    # near face there, and a fit to it does not clear P (step 6)
    out[cells] |= _crossings(proud_of, fits, h, tol, nrm, cen, floor)
    # a lip at a concave feature: P above a clean side, and beyond P the surface dips, then
    # rises above that side's plane (step 6)
    lip = clean & (h > tol)
    lip[:, fits.any(axis=0)] = False
    has = lip.any(axis=0)
    if has.any():
        sel = cells.copy()
        sel[cells] = has
        has[has] = _lips(grid, labels, sel, r, lip[:, has], nrm[:, has], h[:, has], tol[:, has])
        out[cells] |= has
    # in a valley: P above both of two opposite level sides of a concave feature (step 6)
    out[cells] |= ~fits.any(axis=0) & _valleys(grid, labels, cells, r, level, h, tol, nrm, cen)
    # a hanging cell that fits no clean side with a return (an empty side's support is the last
    # returns before a dropout, often the hanging material itself bridged to the floor beyond)
    hang = ~(fits & ~empty).any(axis=0)
    if hang.any():
        sel = cells.copy()
        sel[cells] = hang
        hang[hang] = _hanging(grid, labels, sel, r, below[:, hang], h[:, hang], nrm[:, hang]) | \
            _ledges(grid, labels, sel, r, under[:, hang], h[:, hang], nrm[:, hang], cen[:, hang],
                    tol[:, hang], origin)
        out[cells] |= hang
    # an isolated spike far off every clean side that no other step flags (step 7)
    out[cells] |= _spikes(grid, labels, cells, origin, h, tol, level, clean, rms, nrm, cen)
    # on a smooth curved surface: no rule applies (step 4; its quadrants decide, whether or
    # not P fits a clean side)
    pt = grid[cells] - origin
    out[cells] &= ~_curved(h, rms, level, nrm, cen, empty, cov2, pt, k, cell_floor)
    return out


def edge_test(
    grid: NDArray[np.float64],
    labels: NDArray[np.uint8],
    *,
    window: int,
    tolerance: float,
    max_iterations: int,
    min_step: float | None = None,
    z_resolution: float | None = None,
    lines: NDArray[np.bool_] | None = None,
    z_noise: float | None = None,
    height_window: int | None = None,
    height_removed: NDArray[np.bool_] | None = None,
    precision: float = _EDGE_PRECISION_F64,
) -> tuple[NDArray[np.uint8], int]:
    """Edge passes on top of the angle and height passes (SPEC "Edge test").

    ``labels`` (H, W) are those after the height passes; ``height_window`` the height test's
    window when it ran and ``height_removed`` the cells its last pass made ABNORMAL when the
    passes ended with ``max_iterations`` (no pass re-fitted the windows around them; else
    none; pass 1 leaves out the quiet cells, step 1; None: no cell is quiet); ``min_step``,
    ``z_resolution`` and ``z_noise`` the ones in use (None: off; no sub-window's tolerance is
    below ``min_step / 2``, ``1.5 z_resolution`` or ``2 z_noise``, step 3); ``lines`` the
    feature-line EDGE cells (step 9: the ABNORMAL cells beside them that fit a clean side with
    a return become EDGE before pass 1; None: no such step); ``precision`` the input's (step 3: every tolerance at
    least ``precision`` times the cell's largest absolute coordinate: ``_EDGE_PRECISION``
    epsilons of the input type, float64's by default, as :func:`detect` gives them); returns
    the new labels and the number of edge passes run.
    """
    floor = max(0.5 * min_step if min_step is not None and min_step > 0 else 0.0,
                _Z_RESOLUTION_FACTOR * z_resolution
                if z_resolution is not None and z_resolution > 0 else 0.0,
                2.0 * z_noise if z_noise is not None and z_noise > 0 else 0.0)
    labels = labels.copy()
    passes = 0
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        if lines is not None:  # step 9
            near = _box_count(lines, 3) > 0
            back = _tiled(grid, labels, near & (labels == ABNORMAL), window,
                          lambda g, lab, sel, r, origin: _edge_verdicts(
                              g, lab, sel, r, tolerance, origin, floor, fits_only=True,
                              precision=precision))
            labels[back] = EDGE
        todo = (labels == NORMAL) | (labels == EDGE)
        if height_window is not None:
            removed = (np.zeros(labels.shape, dtype=bool) if height_removed is None
                       else height_removed)
            todo &= ~_quiet_cells(grid, labels, window // 2, height_window, floor, removed)
        for _ in range(max_iterations):
            passes += 1
            new = _edge_pass(grid, labels, todo, window, tolerance, floor, precision)
            labels[new] = ABNORMAL
            if not new.any():
                break
            # only cells with a new ABNORMAL cell in their window can change
            todo = _box_count(new, window) > 0
    return labels, passes


#: min_step="auto" reads this many rows from the grid's first row with a finite cell
#: (SPEC "min_step='auto'"), so that a stream can decide it and batch need not read the scan.
AUTO_MIN_STEP_ROWS = 256
#: z_resolution="auto" pools the z values of the first Z_GAP_CELLS cells, row by row, of the
#: first Z_GAP_ROWS sample rows (SPEC "z_resolution").
Z_GAP_ROWS = 32
Z_GAP_CELLS = 65536


def _auto_survey(
    g: NDArray[np.float64], finite: NDArray[np.bool_]
) -> tuple[float | None, float | None]:
    """SPEC "min_step='auto'" and "z_noise" (reference): over the first AUTO_MIN_STEP_ROWS rows
    from the first row with a finite cell, per grid axis, the median distance of finite
    neighbour pairs and the robust z noise ``1.4826 median|z[i-1] - 2 z[i] + z[i+1]| / sqrt(6)``
    of finite triples; returns (min_step: ``4 * max(noise)`` when above ``min(spacing)``, else
    None; z_noise: ``max(noise)``), (None, None) without an axis to measure."""
    rows = np.flatnonzero(finite.any(axis=1))
    if rows.size == 0:
        return None, None
    first = int(rows[0])  # the first AUTO_MIN_STEP_ROWS rows from the first with a finite cell
    g, finite = g[first:first + AUTO_MIN_STEP_ROWS], finite[first:first + AUTO_MIN_STEP_ROWS]
    spacing, noise = [], []
    for gg, ff in ((g, finite), (g.transpose(1, 0, 2), finite.T)):
        dist, d2 = [], []
        for row, fin in zip(gg, ff):
            for c in range(row.shape[0] - 1):
                if fin[c] and fin[c + 1]:
                    dist.append(math.sqrt(float(np.sum((row[c + 1] - row[c]) ** 2))))
            ok = fin[:-2] & fin[1:-1] & fin[2:]
            d2.extend(np.abs(row[:-2, 2] - 2.0 * row[1:-1, 2] + row[2:, 2])[ok].tolist())
        if dist and d2:
            spacing.append(float(np.median(dist)))
            noise.append(1.4826 * float(np.median(d2)) / math.sqrt(6.0))
    if not spacing:
        return None, None
    m = 4.0 * max(noise)
    return (m if m > min(spacing) else None), max(noise)


def _auto_min_step(g: NDArray[np.float64], finite: NDArray[np.bool_]) -> float | None:
    """min_step="auto" (:func:`_auto_survey`)."""
    return _auto_survey(g, finite)[0]


#: The rms tolerances' floor in z steps (SPEC "z_resolution").
_Z_RESOLUTION_FACTOR = 1.5


def _auto_z_resolution(g: NDArray[np.float64], finite: NDArray[np.bool_]) -> float | None:
    """SPEC "z_resolution" (reference): over the rows min_step="auto" reads (the first
    AUTO_MIN_STEP_ROWS from the first row with a finite cell), the smallest non-zero
    ``|z[r, c + 1] - z[r, c]|`` of finite neighbours, and the smallest gap between two distinct
    z values of the finite cells among the first Z_GAP_CELLS cells of the first Z_GAP_ROWS of
    those rows, whichever is smaller; None when there is neither."""
    rows = np.flatnonzero(finite.any(axis=1))
    if rows.size == 0:
        return None
    first = int(rows[0])
    z = g[first:first + AUTO_MIN_STEP_ROWS, :, 2]
    ok = finite[first:first + AUTO_MIN_STEP_ROWS]
    d = np.abs(z[:, 1:] - z[:, :-1])[ok[:, 1:] & ok[:, :-1]]
    pooled = z[:Z_GAP_ROWS].reshape(-1)[:Z_GAP_CELLS]  # the first cells, row by row
    levels = np.unique(pooled[ok[:Z_GAP_ROWS].reshape(-1)[:Z_GAP_CELLS]])
    d = np.concatenate([d, levels[1:] - levels[:-1]])
    d = d[d > 0.0]
    return float(d.min()) if d.size else None


def _validate_detect_params(
    theta0: Any,
    scales: Any,
    max_gap: Any,
    min_step: Any,
    min_directions: Any,
    max_iterations: Any,
    window: Any,
    max_reach: Any,
) -> tuple[float, tuple[int, ...], int, float | None, int | None, int, int, int]:
    if (
        not _is_real(theta0)
        or not math.isfinite(float(theta0))
        or not (0.0 < float(theta0) < 180.0)
    ):
        raise ValueError(f"theta0: expected a finite angle in degrees in (0, 180), got {theta0!r}")
    is_seq = isinstance(scales, Sequence) and not isinstance(scales, (str, bytes))
    is_seq = is_seq or (isinstance(scales, np.ndarray) and scales.ndim == 1)
    scale_list = list(scales) if is_seq else []
    if len(scale_list) == 0 or not all(_is_int(s) and int(s) >= 1 for s in scale_list):
        raise ValueError(f"scales: expected a non-empty sequence of integers >= 1, got {scales!r}")
    gap = _check_int("max_gap", max_gap, 0)
    if min_step is not None and (
        not _is_real(min_step) or not math.isfinite(float(min_step)) or float(min_step) < 0.0
    ):
        raise ValueError(f"min_step: expected None or a finite length >= 0, got {min_step!r}")
    step = None if min_step is None else float(min_step)
    reach = _check_int("max_reach", max_reach, 1)
    min_dir = None if min_directions is None else _check_int("min_directions", min_directions, 1, 4)
    iters = _check_int("max_iterations", max_iterations, 1)
    win = _check_int("window", window, 3)
    if win % 2 == 0:
        raise ValueError(f"window: expected an odd integer >= 3, got {win}")
    return (float(theta0), tuple(int(s) for s in scale_list), gap, step, min_dir, iters, win, reach)


def detect(
    grid: ArrayLike,
    theta0: float | str = _UNSET,
    scales: Sequence[int] = _UNSET,
    max_gap: int = _UNSET,
    min_step: float | None = _UNSET,
    min_directions: int | None = _UNSET,
    max_iterations: int = _UNSET,
    window: int = _UNSET,
    max_reach: int = _UNSET,
    height_tolerance: float | str | None = _UNSET,
    edge_extent: int = _UNSET,
    edge_tolerance: float | None = _UNSET,
    edge_window: int = _UNSET,
    z_resolution: float | str | None = _UNSET,
    z_noise: float | str | None = _UNSET,
    preset: str | None = None,
) -> RefResult:
    """Detect abnormal points in an organized scan (MIEM, reference implementation).

    Every parameter but ``grid`` and ``preset`` may be left out: it then takes the preset's
    value (without a preset: ``"recommended"``, SPEC "Parameters": theta0 90, scales (1, 2),
    height_tolerance "4.5rms", edge_extent 12), or, when the preset does not set it, the
    default shown (the paper's value). A value given explicitly always wins.

    Parameters
    ----------
    grid : array_like, shape (H, W, 3), integer or floating
        Organized scan: row ``r`` is one profile, column ``c`` runs along it (caller's length
        unit). A point with any non-finite coordinate is a dropout. Never modified.
    theta0 : float or "auto", optional
        Threshold angle in degrees, in the open interval (0, 180): a direction is flagged when
        its interior angle is ``<= theta0``. Default 75. ``"auto"``: computed from the pass-1
        angles, ``clip(180 - 6 * median(180 - angle) / 0.6745, 75, 170)`` (75 when no angle is
        available); the value used is in ``params["theta0"]``.
    scales : sequence of int, optional
        Neighbour scales (each ``>= 1``); a direction is available / flagged when it is at any
        scale. Default ``(1,)``, the paper's behaviour.
    max_gap : int, optional
        Number of unusable cells (dropouts, removed points) a neighbour search may skip, ``>= 0``.
        Default 1.
    min_step : float or None, optional
        If set (finite, ``>= 0``, caller's length unit), the neighbour at scale ``s`` is the
        first usable cell at least ``s * min_step`` away from the point. Default None.
    min_directions : int or None, optional
        If set (1..4), the number of flagged directions that suffices for ABNORMAL (capped at
        the available count); ``None`` (default) means all available directions.
    max_iterations : int, optional
        Maximum number of angle passes, ``>= 1``, and, separately, of height passes. Default 10.
    window : int, optional
        Side, in cells, of the square window of the local plane used for ``height`` and the
        height test; odd ``>= 3``. Default 21.
    max_reach : int, optional
        With ``min_step``, how many extra cells beyond ``scale + max_gap`` the search may go,
        ``>= 1``. Default 32.
    height_tolerance : float, str or None, optional
        Height test (beyond the paper), run after the angle passes: a NORMAL cell whose signed
        distance ``h`` from the window plane of the NORMAL cells around it (itself included)
        exceeds the tolerance becomes ABNORMAL; repeated until a pass adds none (at most
        ``max_iterations`` passes). A float ``t > 0``: ``|h| > t`` (caller's length unit). A
        string ``"<k>rms"`` with ``k > 0`` (e.g. ``"4rms"``): ``|h| > k * rms`` of that window
        plane (and above a round-off floor). EDGE cells are never changed. None (default): off.
    edge_tolerance : float or None, optional
        Edge test (SPEC "Edge test", beyond the paper), run after the height passes: the
        tolerance ``k > 0`` in rms units of the one-sided sub-window planes. None (default): off.
    edge_window : int, optional
        Side, in cells, of the edge test's sub-windows (half-size ``edge_window // 2``); odd
        ``>= 3``. Default 11.
    z_resolution : float, "auto" or None, optional
        The scan's z step: the height test's rms form and the edge test need more than
        ``1.5 z_resolution`` (SPEC "z_resolution"); ``"auto"`` measures it. Default None.
    z_noise : float, "auto" or None, optional
        The scan's z noise sigma: the edge test's tolerances are at least ``2 z_noise`` (SPEC
        "z_noise"); ``"auto"`` measures it as ``min_step="auto"`` does. Default None.
    preset : {None, "recommended", "paper"}, optional
        Named parameter set; ``"paper"`` is the paper's method exactly (the defaults shown),
        None means ``"recommended"``.

    Returns
    -------
    RefResult
        Labels, flags, angles (degrees), heights, the MIEM plane, the number of passes, the
        defects and the parameter values used.

    Raises
    ------
    ValueError
        Bad grid (dtype, shape, fewer than 3 finite points) or bad parameter; the message names
        the argument.
    """
    opts = _resolve_preset(
        preset,
        {
            "theta0": theta0,
            "scales": scales,
            "max_gap": max_gap,
            "min_step": min_step,
            "min_directions": min_directions,
            "max_iterations": max_iterations,
            "window": window,
            "max_reach": max_reach,
            "height_tolerance": height_tolerance,
            "edge_extent": edge_extent,
            "edge_tolerance": edge_tolerance,
            "edge_window": edge_window,
            "z_resolution": z_resolution,
            "z_noise": z_noise,
        },
    )
    auto = isinstance(opts["theta0"], str) and opts["theta0"] == "auto"
    step_auto = isinstance(opts["min_step"], str) and opts["min_step"] == "auto"
    noise = opts["z_noise"]
    noise_auto = isinstance(noise, str) and noise == "auto"
    if not (noise is None or noise_auto or (_is_real(noise) and math.isfinite(float(noise))
                                            and float(noise) >= 0.0)):
        raise ValueError(f"z_noise: expected a length >= 0, 'auto' or None, got {noise!r}")
    if step_auto or noise_auto:  # one survey gives both (SPEC "min_step='auto'", "z_noise")
        arr0 = np.asarray(_as_points_array("grid", grid), dtype=np.float64)
        if arr0.ndim != 3 or arr0.shape[2] != 3:
            raise ValueError(f"grid: expected shape (H, W, 3), got {arr0.shape}")
        survey = _auto_survey(arr0, np.all(np.isfinite(arr0), axis=2))
        if step_auto:
            opts["min_step"] = survey[0]
        if noise_auto:
            noise = survey[1]
    noise = None if noise is None else float(noise)
    (theta0_deg, scale_tuple, gap, step, min_dir, iters, win, reach) = _validate_detect_params(
        _DEFAULTS["theta0"] if auto else opts["theta0"],
        opts["scales"],
        opts["max_gap"],
        opts["min_step"],
        opts["min_directions"],
        opts["max_iterations"],
        opts["window"],
        opts["max_reach"],
    )
    tolerance = _parse_height_tolerance(opts["height_tolerance"])
    extent = 0 if opts["edge_extent"] is None else _check_int("edge_extent", opts["edge_extent"], 0)
    edge_k = opts["edge_tolerance"]
    if edge_k is not None and (
        not _is_real(edge_k) or not math.isfinite(float(edge_k)) or not float(edge_k) > 0.0
    ):
        raise ValueError(f"edge_tolerance: expected None or a finite number > 0, got {edge_k!r}")
    edge_win = _check_int("edge_window", opts["edge_window"], 3)
    if edge_win % 2 == 0:
        raise ValueError(f"edge_window: expected an odd integer >= 3, got {edge_win}")
    zres = opts["z_resolution"]
    zres_auto = isinstance(zres, str) and zres == "auto"
    if not (zres is None or zres_auto or (_is_real(zres) and math.isfinite(float(zres))
                                          and float(zres) >= 0.0)):
        raise ValueError(f"z_resolution: expected a length >= 0, 'auto' or None, got {zres!r}")
    arr = _as_points_array("grid", grid)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"grid: expected shape (H, W, 3), got {arr.shape}")
    g = np.array(arr, dtype=np.float64, copy=True)
    precision = _precision(arr)  # (SPEC "Edge test" step 3)
    finite = np.all(np.isfinite(g), axis=2)
    if int(finite.sum()) < 3:
        raise ValueError(f"grid: need at least 3 finite points, got {int(finite.sum())}")
    # Dropouts become NaN so that no inf - inf arithmetic happens below; they are never read
    # as neighbours (not usable) and are reported INVALID.
    g[~finite] = np.nan
    if zres_auto:  # SPEC "z_resolution"
        zres = _auto_z_resolution(g, finite)
    zres = None if zres is None else float(zres)
    z_floor = _Z_RESOLUTION_FACTOR * zres if zres is not None and zres > 0 else 0.0

    h, w = finite.shape
    labels = np.full((h, w), INVALID, dtype=np.uint8)
    labels[finite] = NORMAL
    flags = np.zeros((h, w), dtype=np.uint8)
    angle = np.full((h, w), np.nan)
    abnormal = np.zeros((h, w), dtype=bool)

    passes = 0
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        if auto:
            theta0_deg = _auto_theta0(g, finite, scale_tuple, gap, step, reach)
        cos0 = math.cos(theta0_deg * math.pi / 180.0)
        while True:
            passes += 1
            usable = finite & ~abnormal
            judged = usable  # every finite, not yet ABNORMAL cell is judged
            n_avail, n_flag, pass_flags, pass_angle = _judge_pass(
                g, usable, cos0, scale_tuple, gap, step, reach
            )
            isolated = _isolated(usable, gap)
            need = n_avail if min_dir is None else np.minimum(n_avail, min_dir)
            new_abn = judged & (isolated | ((n_avail >= 2) & (n_flag >= need)))
            rest = judged & ~new_abn
            labels[new_abn] = ABNORMAL
            labels[rest & (n_flag > 0)] = EDGE
            labels[rest & (n_flag == 0)] = NORMAL
            flags[judged] = np.where(isolated, np.uint8(0), pass_flags)[judged]
            angle[judged] = np.where(isolated, np.nan, pass_angle)[judged]
            abnormal |= new_abn
            if not new_abn.any() or passes >= iters:
                break

        if tolerance is not None:
            # Height passes (Jacobi: the NORMAL set is fixed within a pass); at most `iters`
            # of them, on top of the angle passes. Flags and angles are left as they are.
            # EDGE groups link across dropouts and the angle passes' ABNORMAL cells
            bridge = ~finite | (labels == ABNORMAL)
            # the cells the last height pass removed when the passes end with iters (a pass
            # after it would have re-fitted their windows: the edge test's quiet rule)
            unfitted = np.zeros(labels.shape, dtype=bool)
            for _ in range(iters):
                passes += 1
                compact = _compact_edges(labels == EDGE, extent, bridge, gap)
                new_abn = _height_pass(
                    g, labels == NORMAL, compact, (labels == EDGE) & ~compact, win, tolerance,
                    z_floor,
                )
                labels[new_abn] = ABNORMAL
                abnormal |= new_abn
                unfitted = new_abn
                if not new_abn.any():
                    break

    if edge_k is not None:  # SPEC "Edge test": after the height passes
        # step 9's feature lines: the EDGE groups that are not compact (every EDGE cell
        # without the height test; the height passes change no feature-line cell)
        lines = labels == EDGE
        if tolerance is not None:
            lines &= ~_compact_edges(lines, extent, bridge, gap)
        labels, edge_passes = edge_test(g, labels, window=edge_win, tolerance=float(edge_k),
                                        max_iterations=iters, min_step=step, z_resolution=zres,
                                        z_noise=noise, lines=lines, precision=precision,
                                        height_window=win if tolerance is not None else None,
                                        height_removed=unfitted if tolerance is not None
                                        else None)
        passes += edge_passes
        abnormal = labels == ABNORMAL

    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        plane = _eigen_plane(g[finite & ~abnormal])
        height, normals = _window_fits(g, labels == NORMAL, finite, win)
        defects = _defects(g, labels, height, normals, finite)

    params: dict[str, Any] = {
        "preset": preset,
        "theta0": float(theta0_deg),
        "theta0_auto": auto,
        "scales": scale_tuple,
        "max_gap": gap,
        "min_step": step,
        "min_step_auto": step_auto,
        "min_directions": min_dir,
        "max_iterations": iters,
        "window": win,
        "max_reach": reach,
        "height_tolerance": (
            None
            if tolerance is None
            else (tolerance[1] if tolerance[0] == "abs" else str(opts["height_tolerance"]))
        ),
        "edge_tolerance": None if edge_k is None else float(edge_k),
        "edge_window": edge_win,
        "z_resolution": zres,
        "z_resolution_auto": zres_auto,
        "z_noise": noise,
        "z_noise_auto": noise_auto,
    }
    return RefResult(
        labels=labels,
        flags=flags,
        angle=angle,
        height=height,
        plane=plane,
        iterations=passes,
        defects=defects,
        params=params,
    )


# --------------------------------------------------------------------------------------------
# Unorganized clouds (METHOD sections 3-7, SPEC "Unorganized clouds")
# --------------------------------------------------------------------------------------------

# Conventions of this section, where SPEC.md leaves the arithmetic open:
#
# * every distance (neighbourhood, link, spacing) is ``sqrt(dx*dx + dy*dy + dz*dz)`` of
#   ``q - p``, compared with ``<=`` (not a comparison of squares); the k-d tree only proposes
#   candidates;
# * ``spacing`` is ``np.median`` (mean of the two middle values for an even count) of exact
#   nearest-other distances; a duplicate is a nearest other point at distance 0;
# * ``q != p`` means another row: duplicates of ``p`` are in ``Q`` (they count and enter the
#   fit) but are never direction neighbours (``|t| = 0``);
# * sector bound ``math.cos((90.0 / K) * math.pi / 180.0)``; direction coefficients
#   ``math.cos(k * math.pi / K)``, ``math.sin(k * math.pi / K)``; side -1 tests ``-(t . d_k)``;
# * the sign of ``e1`` cannot change any result (flipping it flips ``e2`` and every ``d_k``,
#   which only swaps the two sides of each direction);
# * plane fits are computed on offsets from the point (centred data); height is evaluated as
#   ``-n . (c - p)``, which equals ``n . p + d`` up to rounding.

#: Largest ``K`` accepted by :func:`detect_points` (the flag bitmask is ``uint8``).
MAX_K: int = 8

# Ball queries of the k-d tree are run with a radius enlarged by this relative amount; the exact
# ``sqrt(dx*dx + dy*dy + dz*dz) <= r`` test is then applied to the candidates, so the k-d tree's
# own rounding never decides membership.
_BALL_SLACK = 1e-9


@dataclass(frozen=True, eq=False)
class RefPointsResult:
    """Result of :func:`detect_points` on an unorganized cloud of shape ``(N, 3)``.

    Attributes
    ----------
    labels : ndarray, shape (N,), uint8
        NORMAL 0, ABNORMAL 1, EDGE 2, INVALID 3.
    flags : ndarray, shape (N,), uint8
        Bitmask of flagged directions (bit ``k`` for direction ``d_k``).
    angle : ndarray, shape (N,), float64
        Smallest interior angle seen, in degrees; NaN where no direction was available.
    height : ndarray, shape (N,), float64
        Signed distance from the plane of the NORMAL points within ``radius`` (protrusion > 0,
        pit < 0); NaN where that plane cannot be fitted and for non-finite points.
    degenerate : ndarray, shape (N,), bool
        Points whose neighbourhood plane was degenerate (all equal or collinear) in the pass
        that gave their label (such points are NORMAL).
    plane : RefPlane or None
        Eigenvalue fit of every finite non-ABNORMAL point (the MIEM plane); None if impossible.
    iterations : int
        Number of passes run.
    defects : list of RefDefect
        Groups of ABNORMAL points (``indices`` are row indices into the input), in SPEC.md order.
    params : dict
        Values used: ``spacing``, ``radius``, ``min_step``, ``link`` (floats, caller's length
        unit) and ``K`` (int).
    """

    labels: NDArray[np.uint8]
    flags: NDArray[np.uint8]
    angle: NDArray[np.float64]
    height: NDArray[np.float64]
    degenerate: NDArray[np.bool_]
    plane: RefPlane | None
    iterations: int
    defects: list[RefDefect]
    params: dict[str, Any]


@dataclass(frozen=True, eq=False)
class RefNormals:
    """Result of :func:`estimate_normals`.

    Attributes
    ----------
    normals : ndarray, shape (N, 3), float64
        Oriented unit normals (``n_z > 0``, or first non-zero component positive); NaN where
        not valid.
    rms : ndarray, shape (N,), float64
        RMS orthogonal distance of the neighbourhood from its plane; NaN where not valid.
    count : ndarray, shape (N,), int64
        Number of finite points within ``radius`` (the point itself included); 0 for non-finite
        rows.
    valid : ndarray, shape (N,), bool
        True where a plane could be fitted (finite point, at least 3 points, not degenerate).
    """

    normals: NDArray[np.float64]
    rms: NDArray[np.float64]
    count: NDArray[np.int64]
    valid: NDArray[np.bool_]


def _check_length(name: str, value: Any, allow_zero: bool) -> float:
    """A finite length ``> 0`` (or ``>= 0`` with ``allow_zero``)."""
    ok = _is_real(value) and math.isfinite(float(value))
    ok = ok and (float(value) >= 0.0 if allow_zero else float(value) > 0.0)
    if not ok:
        rel = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name}: expected a finite length {rel}, got {value!r}")
    return float(value)


def _precision(arr: NDArray[Any]) -> float:
    """SPEC "Edge test" step 3's relative precision of an input array: ``_EDGE_PRECISION``
    epsilons of float32 for a float32 array, of float64 for any other (computed in float64)."""
    return _EDGE_PRECISION * float(np.finfo(
        np.float32 if arr.dtype == np.float32 else np.float64).eps)


def _cloud_array(points: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """A float64 copy of an ``(N, 3)`` cloud (NaN in non-finite rows) and its finite mask."""
    arr = _as_points_array("points", points)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"points: expected shape (N, 3), got {arr.shape}")
    p = np.array(arr, dtype=np.float64, copy=True)
    finite = np.all(np.isfinite(p), axis=1)
    p[~finite] = np.nan
    return p, finite


def _kdtree(pts: NDArray[np.float64]) -> Any:
    from scipy.spatial import cKDTree  # optional dependency, needed by the unorganized oracle

    return cKDTree(pts)


def _query_radius(r: float) -> float:
    return r * (1.0 + _BALL_SLACK) if r < 1e300 else math.inf


def _ball_pairs(
    tree: Any,
    pts: NDArray[np.float64],
    queries: NDArray[np.float64],
    radius: float,
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
    """All pairs ``(i, j)`` with ``|pts[j] - queries[i]| <= radius`` (exact test).

    Returns ``i``, ``j`` (sorted by ``i`` then ``j``), the offsets ``w = pts[j] - queries[i]``
    and their lengths ``sqrt(w.w)``.
    """
    nq = queries.shape[0]
    if nq == 0 or pts.shape[0] == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty.copy(), np.zeros((0, 3)), np.zeros(0)
    lists = tree.query_ball_point(queries, _query_radius(radius), return_sorted=True)
    counts = np.fromiter((len(x) for x in lists), dtype=np.int64, count=nq)
    total = int(counts.sum())
    pj = np.fromiter(itertools.chain.from_iterable(lists), dtype=np.int64, count=total)
    pi = np.repeat(np.arange(nq, dtype=np.int64), counts)
    w = pts[pj] - queries[pi]
    dist = np.sqrt(_dot3(w, w))
    keep = dist <= radius
    return pi[keep], pj[keep], w[keep], dist[keep]


def _spacing(tree: Any, pts: NDArray[np.float64]) -> float:
    """Median over the points of the distance to the nearest other point (exact distances)."""
    n = pts.shape[0]
    kd_dist, kd_idx = tree.query(pts, k=2)
    own = np.arange(n)
    # First neighbour with a different index (with duplicates, the point itself may come second).
    first_other = np.where(kd_idx[:, 0] != own, kd_dist[:, 0], kd_dist[:, 1])
    # Re-derive the nearest distance with the exact formula among all points the k-d tree puts
    # at (about) that distance, so that the k-d tree's rounding does not leak into the result.
    radii = np.where(first_other < 1e300, first_other * (1.0 + _BALL_SLACK), np.inf)
    lists = tree.query_ball_point(pts, radii, return_sorted=True)
    nearest = np.empty(n)
    for i in range(n):
        js = np.array([j for j in lists[i] if j != i], dtype=np.int64)
        w = pts[js] - pts[i]
        nearest[i] = float(np.min(np.sqrt(_dot3(w, w))))
    return float(np.median(nearest))


def _group_fits(
    gi: NDArray[np.int64], w: NDArray[np.float64], n_groups: int, fit: NDArray[np.bool_]
) -> tuple[
    NDArray[np.int64],
    NDArray[np.float64],
    NDArray[np.float64],
    NDArray[np.float64],
    NDArray[np.bool_],
]:
    """Eigenvalue plane fit of each group of offsets (SPEC "Plane fit", batched).

    ``gi`` is the group of each offset ``w`` (an offset from the group's own point, so the fit
    is on centred, origin-free data). Only groups with ``fit`` and at least 3 members are
    fitted. Returns the member count, the centroid of the offsets ``(G, 3)``, the eigenvalues
    ``(G, 3)`` (ascending), the eigenvectors ``(G, 3, 3)`` (columns) and the mask of groups whose
    fit is possible (``l2 > 0`` and ``l1 > 1e-12 * l2``); NaN elsewhere.
    """
    cnt = np.bincount(gi, minlength=n_groups).astype(np.int64)
    cen = np.full((n_groups, 3), np.nan)
    evals = np.full((n_groups, 3), np.nan)
    evecs = np.full((n_groups, 3, 3), np.nan)
    ok = np.zeros(n_groups, dtype=bool)
    todo = fit & (cnt >= 3)
    if not todo.any():
        return cnt, cen, evals, evecs, ok
    sel = todo[gi]
    g, ws = gi[sel], w[sel]
    sums = np.stack([np.bincount(g, weights=ws[:, a], minlength=n_groups) for a in range(3)], 1)
    cen[todo] = sums[todo] / cnt[todo, None]
    dev = ws - cen[g]
    scatter = np.zeros((n_groups, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            s_ab = np.bincount(g, weights=dev[:, a] * dev[:, b], minlength=n_groups)
            scatter[:, a, b] = s_ab
            scatter[:, b, a] = s_ab
    ev, vec = np.linalg.eigh(scatter[todo])
    evals[todo] = ev
    evecs[todo] = vec
    l1, l2 = ev[:, 1], ev[:, 2]
    ok[todo] = (l2 > 0.0) & ~(l1 <= _EIGEN_RANK_TOL * l2)
    return cnt, cen, evals, evecs, ok


def _first_per_group(
    cand: NDArray[np.bool_], gi: NDArray[np.int64], n_groups: int
) -> NDArray[np.int64]:
    """Position of the first True of ``cand`` in each group (``gi`` sorted); -1 where none."""
    pos = np.flatnonzero(cand)
    first = np.full(n_groups, -1, dtype=np.int64)
    if pos.size:
        g = gi[pos]
        head = np.ones(pos.size, dtype=bool)
        head[1:] = g[1:] != g[:-1]
        first[g[head]] = pos[head]
    return first


def _tangent_basis(
    evals: NDArray[np.float64],
    evecs: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Oriented normal ``n``, ``e1`` and ``e2 = n x e1`` for stacks of eigenvalues ``(G, 3)``
    (ascending) and eigenvector matrices ``(G, 3, 3)``.

    ``e1`` is the largest-eigenvalue eigenvector when ``l2 - l1 > 1e-6 l2``, else the coordinate
    axis least aligned with ``n`` projected onto the tangent plane; its component of largest
    magnitude is made positive (SPEC.md)."""
    n = _orient(evecs[:, :, 0])
    e1 = evecs[:, :, 2].copy()
    tie = ~(evals[:, 2] - evals[:, 1] > 1e-6 * evals[:, 2])
    if tie.any():
        nt = n[tie]
        axis = np.argmin(np.abs(nt), axis=1)  # first on ties
        a = np.zeros_like(nt)
        a[np.arange(nt.shape[0]), axis] = 1.0
        proj = a - _dot3(a, nt)[:, None] * nt
        e1[tie] = proj / np.sqrt(_dot3(proj, proj))[:, None]
    lead = np.argmax(np.abs(e1), axis=1)  # first on ties
    sign = np.where(e1[np.arange(e1.shape[0]), lead] < 0.0, -1.0, 1.0)
    e1 = e1 * sign[:, None] + 0.0
    e2 = np.stack(
        [
            n[:, 1] * e1[:, 2] - n[:, 2] * e1[:, 1],
            n[:, 2] * e1[:, 0] - n[:, 0] * e1[:, 2],
            n[:, 0] * e1[:, 1] - n[:, 1] * e1[:, 0],
        ],
        axis=1,
    )
    return n, e1, e2


def _points_pass(
    pi: NDArray[np.int64],
    pj: NDArray[np.int64],
    w: NDArray[np.float64],
    dist: NDArray[np.float64],
    usable: NDArray[np.bool_],
    cos0: float,
    scales: tuple[int, ...],
    min_step: float,
    k_dirs: int,
) -> tuple[
    NDArray[np.int64],
    NDArray[np.bool_],
    NDArray[np.int64],
    NDArray[np.int64],
    NDArray[np.uint8],
    NDArray[np.float64],
]:
    """One pass over the usable points of a cloud.

    Returns, per point: the neighbourhood size ``|Q|``, the mask of possible neighbourhood
    fits, the available and flagged direction counts, the flag bitmask and the smallest angle.
    """
    n_pts = usable.shape[0]
    m = usable[pi] & usable[pj]  # usable p and usable q (q != p: self pairs are not in the list)
    pi, pj, w, dist = pi[m], pj[m], w[m], dist[m]
    cnt, _, evals, evecs, ok = _group_fits(pi, w, n_pts, usable)

    n_avail = np.zeros(n_pts, dtype=np.int64)
    n_flag = np.zeros(n_pts, dtype=np.int64)
    flags = np.zeros(n_pts, dtype=np.uint8)
    angle = np.full(n_pts, np.nan)
    if not ok.any():
        return cnt, ok, n_avail, n_flag, flags, angle

    # Pairs of the points whose plane fit succeeded, ordered by (p, |w|, index of q).
    sel = ok[pi]
    pi, pj, w, dist = pi[sel], pj[sel], w[sel], dist[sel]
    order = np.lexsort((pj, dist, pi))
    pi, pj, w = pi[order], pj[order], w[order]

    normal = np.full((n_pts, 3), np.nan)
    e1 = np.full((n_pts, 3), np.nan)
    e2 = np.full((n_pts, 3), np.nan)
    normal[ok], e1[ok], e2[ok] = _tangent_basis(evals[ok], evecs[ok])

    nq = normal[pi]
    wn = _dot3(w, nq)
    t = w - wn[:, None] * nq
    tlen = np.sqrt(_dot3(t, t))
    cos_half = math.cos((90.0 / k_dirs) * math.pi / 180.0)
    bound = tlen * cos_half
    positive = tlen > 0.0
    # Scale s: the neighbour beyond (2s - 1) * min_step (with the default min_step, half a
    # spacing: the s-th point along the direction).
    step_ok = [tlen >= (2 * s - 1) * min_step for s in scales]

    for k in range(k_dirs):
        ck = math.cos(k * math.pi / k_dirs)
        sk = math.sin(k * math.pi / k_dirs)
        dk = ck * e1 + sk * e2
        td = _dot3(t, dk[pi])
        in_plus = positive & (td >= bound)
        in_minus = positive & (-td >= bound)
        dir_avail = np.zeros(n_pts, dtype=bool)
        dir_flag = np.zeros(n_pts, dtype=bool)
        for s_ok in step_ok:
            first_a = _first_per_group(in_minus & s_ok, pi, n_pts)  # side -1: A
            first_b = _first_per_group(in_plus & s_ok, pi, n_pts)  # side +1: B
            both = (first_a >= 0) & (first_b >= 0)
            u = w[first_a[both]]
            v = w[first_b[both]]
            uu = _dot3(u, u)
            vv = _dot3(v, v)
            uv = _dot3(u, v)
            good = (uu != 0.0) & (vv != 0.0)
            cos = np.clip(uv[good] / np.sqrt(uu[good] * vv[good]), -1.0, 1.0)
            idx = np.flatnonzero(both)[good]
            dir_avail[idx] = True
            dir_flag[idx[cos >= cos0]] = True
            angle[idx] = np.fmin(angle[idx], np.degrees(np.arccos(cos)))
        n_avail += dir_avail
        n_flag += dir_flag
        flags[dir_flag] |= np.uint8(1 << k)
    return cnt, ok, n_avail, n_flag, flags, angle


def _points_defects(
    pts: NDArray[np.float64],
    rows: NDArray[np.int64],
    abnormal: NDArray[np.bool_],
    height: NDArray[np.float64],
    normals: NDArray[np.float64],
    link: float,
) -> list[RefDefect]:
    """Defects of a cloud: groups of ABNORMAL points under ``distance <= link``.

    ``pts`` are the finite points (in input order), ``rows`` their row indices in the input;
    ``height`` and ``normals`` are per finite point.
    """
    abn = np.flatnonzero(abnormal)
    if abn.size == 0:
        return []
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    a_pts = pts[abn]
    a_tree = _kdtree(a_pts)
    pi, pj, _, _ = _ball_pairs(a_tree, a_pts, a_pts, link)
    graph = coo_matrix((np.ones(pi.size), (pi, pj)), shape=(abn.size, abn.size))
    n_comp, comp = connected_components(graph, directed=False)

    keep = np.flatnonzero(~abnormal)  # finite, non-ABNORMAL
    touches = np.zeros(abn.size, dtype=bool)
    if keep.size:
        k_pts = pts[keep]
        ti, _, _, _ = _ball_pairs(_kdtree(k_pts), k_pts, a_pts, link)
        touches[ti] = True

    raw = []
    for c in range(n_comp):
        loc = np.flatnonzero(comp == c)  # ascending, hence ascending input rows
        idx = rows[abn[loc]].astype(np.int64)
        raw.append(_summarize(idx, a_pts[loc], height[abn[loc]], abn[loc], height, normals,
                              bool(touches[loc].any())))
    return _ordered_defects(raw)


def _cloud_groups(
    pts: NDArray[np.float64], members: NDArray[np.int64], link: float
) -> list[NDArray[np.int64]]:
    """Groups of ``pts[members]`` under ``distance <= link`` (each ascending, as positions
    into ``pts``), in order of their smallest member."""
    if members.size == 0:
        return []
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    sub = pts[members]
    pi, pj, _, _ = _ball_pairs(_kdtree(sub), sub, sub, link)
    graph = coo_matrix((np.ones(pi.size), (pi, pj)), shape=(members.size, members.size))
    n_comp, comp = connected_components(graph, directed=False)
    groups = [members[np.flatnonzero(comp == c)] for c in range(n_comp)]
    groups.sort(key=lambda g: int(g[0]))
    return groups


def _duplicate_representatives(pts: NDArray[np.float64], merge: float) -> NDArray[np.int64]:
    """SPEC "Duplicate points": for each point, the smallest position among the points linked
    to it by ``distance <= merge`` (transitively)."""
    groups = _cloud_groups(pts, np.arange(pts.shape[0], dtype=np.int64), merge)
    rep = np.empty(pts.shape[0], dtype=np.int64)
    for g in groups:
        rep[g] = g[0]
    return rep


def _floating(
    pts: NDArray[np.float64], usable: NDArray[np.bool_], radius: float, min_group: int
) -> NDArray[np.bool_]:
    """SPEC "Floating groups": usable points whose group (usable points linked by
    ``distance <= radius``) has fewer than ``min_group`` points."""
    out = np.zeros(usable.shape[0], dtype=bool)
    for g in _cloud_groups(pts, np.flatnonzero(usable), radius):
        if g.size < min_group:
            out[g] = True
    return out


def _cloud_compact_edges(
    pts: NDArray[np.float64], edge: NDArray[np.bool_], link: float, extent: float
) -> NDArray[np.bool_]:
    """EDGE points of groups (``distance <= link``) at most ``extent`` across: twice the largest
    distance of a member from the group's centroid."""
    out = np.zeros(edge.shape[0], dtype=bool)
    for g in _cloud_groups(pts, np.flatnonzero(edge), link):
        q = pts[g]
        d = q - q.mean(axis=0)
        if 2.0 * float(np.sqrt(np.max(_dot3(d, d)))) <= extent:
            out[g] = True
    return out


def _cloud_height_pass(
    hi: NDArray[np.int64],
    hj: NDArray[np.int64],
    hw: NDArray[np.float64],
    outer: NDArray[np.bool_],
    normal: NDArray[np.bool_],
    compact: NDArray[np.bool_],
    line: NDArray[np.bool_],
    tolerance: tuple[str, float],
    stats: NDArray[np.float64] | None = None,
    isolated: float | None = None,
    spacing: float = 0.0,
) -> NDArray[np.bool_]:
    """One cloud height pass: the NORMAL and compact-EDGE points that become ABNORMAL (with
    ``stats``, also each point's surroundings rms where the test gave a verdict, NaN elsewhere).

    ``(hi, hj, hw)`` are the pairs within the height radius, each point paired with itself too;
    ``outer`` marks the pairs farther apart than ``radius`` (the plane is fitted to those: the
    surroundings, not the point's own bump). ``isolated`` (a multiple of the rms, or None: off)
    turns on the isolated-point rule (with the "<k>rms" tolerance only). ``spacing`` is the
    unit of the bead rule's lengths (SPEC step 3), which spares the points on a designed bead.
    """
    n_pts = normal.shape[0]
    tested = normal | compact
    sel = normal[hj] & outer
    cnt, cen, evals, evecs, ok = _group_fits(hi[sel], hw[sel], n_pts, tested)
    near_line = np.zeros(n_pts, dtype=bool)
    near_line[hi[line[hj]]] = True
    exists = tested & ok & ~near_line
    nrm = np.full((n_pts, 3), np.nan)
    nrm[exists] = _orient(evecs[exists][:, :, 0])
    h = np.full(n_pts, np.nan)
    h[exists] = -_dot3(nrm[exists], cen[exists])
    absh = np.abs(h)
    mode, value = tolerance
    n = np.maximum(cnt, 1).astype(np.float64)
    rms = np.sqrt(np.maximum(evals[:, 0], 0.0) / n)
    if stats is not None:  # the surroundings' rms where the test gave a verdict (edge test),
        # 0 where exactly flat (round-off, as a sector's)
        stats[:] = np.where(exists, _edge_rms(evals, n), np.nan)
    floor = _HEIGHT_RMS_FLOOR * np.sqrt((evals[:, 1] + evals[:, 2]) / n)
    if mode == "abs":
        out = exists & (absh > value)
    else:
        out = exists & (absh > value * rms) & (absh > floor)
    if isolated is not None:  # (with a length tolerance too, when it is given)
        # The isolated-point rule: |h| > isolated * rms, and the NORMAL points q != p within
        # radius lie about the surroundings plane as loosely as its rms says (the median of
        # their |heights| is at least _CLOUD_ISOLATED_MEDIAN * rms): p alone stands out of a
        # smooth neighbourhood.
        cand = exists & ~out & (absh > isolated * rms) & (absh > floor)
        ins = cand[hi] & normal[hj] & ~outer & (hi != hj)
        gi = hi[ins]
        hq = np.abs(_dot3(nrm[gi], hw[ins] - cen[gi]))
        med = _group_medians(gi, hq, n_pts)
        out = out | (cand & (med >= _CLOUD_ISOLATED_MEDIAN * rms))
    # The bead rule: a point on a designed bead one point wide keeps its label.
    usable = normal | compact | line
    pairs = out[hi] & (hj != hi) & usable[hj]
    pi, pw = hi[pairs], hw[pairs]
    for i in np.flatnonzero(out):
        if _cloud_bead(pw[pi == i], nrm[i], cen[i], spacing):
            out[i] = False
    return out


#: Cloud height test, bead rule (SPEC "Unorganized clouds: floating groups and height test",
#: step 3): the run holds the points within this share of |h| of the point's level ...
_CLOUD_BEAD_LEVEL = 0.5
#: ... and is at most this many spacings wide (rms across the line) ...
_CLOUD_BEAD_WIDTH = 0.25
#: ... reaches within this many spacings of the farthest usable points both ways ...
_CLOUD_BEAD_MARGIN = 2.0
#: ... and has at least this share of the other usable points on each side.
_CLOUD_BEAD_SIDE = 0.25


def _cloud_bead(
    w: NDArray[np.float64], u: NDArray[np.float64], c: NDArray[np.float64], spacing: float
) -> bool:
    """SPEC "Unorganized clouds: floating groups and height test", step 3, the bead rule: is a
    point on a designed bead one point wide across its surroundings? ``w``: the offsets from it
    of the usable points within the height radius (not itself); ``u``, ``c``: the surroundings
    plane's oriented normal and centroid offset."""
    h = -float(u @ c)
    raised = np.abs(np.sign(h) * ((w - c) @ u) - abs(h)) < _CLOUD_BEAD_LEVEL * abs(h)
    run = np.vstack([np.zeros((1, 3)), w[raised]])  # the point itself at offset 0
    if run.shape[0] < 3:
        return False
    m = run.mean(axis=0)
    evals, evecs = np.linalg.eigh((run - m).T @ (run - m) / run.shape[0])
    if not evals[1] < (_CLOUD_BEAD_WIDTH * spacing) ** 2:
        return False
    line = evecs[:, 2] - (evecs[:, 2] @ u) * u
    norm = float(np.sqrt(line @ line))
    if not norm > 0.0:
        return False
    line = line / norm
    along = np.concatenate([[0.0], w @ line])
    run_along = np.concatenate([[0.0], w[raised] @ line])
    margin = _CLOUD_BEAD_MARGIN * spacing
    if not (run_along.min() <= along.min() + margin and run_along.max() >= along.max() - margin):
        return False
    side = (w[~raised] - m) @ np.cross(u, line)
    plus, minus = int(np.count_nonzero(side > 0.0)), int(np.count_nonzero(side < 0.0))
    return plus + minus > 0 and min(plus, minus) >= _CLOUD_BEAD_SIDE * (plus + minus)


def _group_medians(
    gi: NDArray[np.int64], v: NDArray[np.float64], n_groups: int
) -> NDArray[np.float64]:
    """NumPy's median of ``v`` per group ``gi`` (NaN for groups of fewer than 3 values)."""
    out = np.full(n_groups, np.nan)
    o = np.lexsort((v, gi))
    gi, v = gi[o], v[o]
    cnt = np.bincount(gi, minlength=n_groups)
    start = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    has = np.flatnonzero(cnt >= 3)
    lo = start[has] + (cnt[has] - 1) // 2
    hi = start[has] + cnt[has] // 2
    out[has] = (v[lo] + v[hi]) / 2.0
    return out


#: Cloud height test, isolated-point rule: the median |height| of a point's inner NORMAL
#: neighbours over its surroundings plane must be at least this multiple of the plane's rms.
_CLOUD_ISOLATED_MEDIAN = 0.5
#: Cloud edge test (SPEC "Unorganized clouds: edge test"): a point's surroundings rms in the
#: first height pass above this multiple of the median makes it a candidate.
_CLOUD_EDGE_SUSPECT = 1.5
#: Cloud edge test (step 7): the wide scale's sector radius, in edge radii.
_CLOUD_EDGE_WIDE = 1.5
#: Cloud edge test: 8 quarter-disk and 8 half-disk sectors.
_CLOUD_SECTORS = 16
#: Cloud edge test: a sector with fewer finite points than this fraction of a full one is empty
#: (a steep face, sampled more sparsely in 3-D, keeps about half; 0.35 chosen on the tune split
#: of the held-out-style clouds: 0.25 missed burrs hanging past wall tops).
_CLOUD_EMPTY = 0.35
#: ... and, as the opposite of a hanging point (SPEC step 5), below this fraction: a face
#: falling away steeper than 45 degrees past a convex crease keeps about 0.3-0.35.
_CLOUD_HANG_EMPTY = 0.3
#: ... unless its support's plane runs through P steeper than 45 degrees against the opposite
#: sector's: |u_a . u_b| below cos 45 degrees (sqrt(0.5) rounded to double).
_CLOUD_FACE_COS = float(np.sqrt(0.5))
#: ... and is smooth: its rms at most this times the cleanest valid sector's (a plane through
#: material hanging level with P and the floor beyond it is not a face).
_CLOUD_FACE_CLEAN = 3.0


def _turned(s: int, by: int) -> int:
    """Sector ``s`` turned by ``by`` octants within its width (8 quarter, then 8 half sectors):
    ``by = 4`` its opposite, ``+-1`` its neighbours."""
    return (s // 8) * 8 + (s % 8 + by) % 8


def _cloud_frames(
    tree: Any, pts: NDArray[np.float64], idx: NDArray[np.int64], radius: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """Tangent directions ``e1``, ``e2`` of the points ``idx`` from the plane of the finite
    points within ``radius`` (the point included; the edge test passes its sector radius), with
    the tangent basis rule of the angle test; ``ok`` False where that plane is impossible."""
    m = idx.size
    e1 = np.full((m, 3), np.nan)
    e2 = np.full((m, 3), np.nan)
    pi, _, w, _ = _ball_pairs(tree, pts, pts[idx], radius)
    _, _, evals, evecs, ok = _group_fits(pi, w, m, np.ones(m, dtype=bool))
    if ok.any():
        _, e1[ok], e2[ok] = _tangent_basis(evals[ok], evecs[ok])
    return e1, e2, ok


def _octants(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.int64]:
    """SPEC "Unorganized clouds: edge test" step 3: the octant of each tangent offset
    ``(a, b) != 0``, the 45-degree wedge ``[45 o, 45 o + 45)`` degrees of ``atan2(b, a)`` in
    ``[0, 360)`` that holds it, decided by exact comparisons (a point on a boundary belongs to
    the wedge that starts there)."""
    upper = (b > 0.0) | ((b == 0.0) & (a > 0.0))  # [0, 180)
    return np.select(
        [upper & (a > 0.0), upper, a < 0.0],
        [np.where(b < a, 0, 1), np.where(b > -a, 2, 3), np.where(-b < -a, 4, 5)],
        np.where(a < -b, 6, 7),
    ).astype(np.int64)


def _cloud_edge_pass(
    tree: Any,
    pts: NDArray[np.float64],
    labels: NDArray[np.uint8],
    cand: NDArray[np.int64],
    e1: NDArray[np.float64],
    e2: NDArray[np.float64],
    r_edge: float,
    gap: float,
    k: float,
    veto: NDArray[np.bool_] | None = None,
    hanging: bool = True,
    precision: float = _EDGE_PRECISION_F64,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_], NDArray[np.bool_]]:
    """One cloud edge pass at one scale: which of the points ``cand`` (tangent directions
    ``e1``, ``e2``) become ABNORMAL (SPEC steps 3-6: they stand proud of a clean sector and fit
    no clean sector that is not past the feature (the crossing rule), or fit none and hang below
    one or are a lip at a concave feature beyond one), the support being the NORMAL points of
    ``labels``; which are *level* (step 7: within ``t`` of every clean sector's plane); and
    per sector ``(M, 16)`` where the level rule *vetoes* an outline (step 7: the sector valid,
    its opposite empty, a clean neighbour of that at its level). ``veto``: the narrow scale's,
    for the wide one (no outline where it is set); ``hanging`` False: without step 5 (the wide
    scale); ``precision``: step 3's precision floor, times P's largest absolute coordinate."""
    m = cand.size
    out = np.zeros(m, dtype=bool)
    if m == 0:
        return out, out.copy(), np.zeros((0, _CLOUD_SECTORS), dtype=bool)
    pi, pj, w, dist = _ball_pairs(tree, pts, pts[cand], r_edge)
    a = _dot3(w, e1[pi])
    b = _dot3(w, e2[pi])
    rho = np.sqrt(a * a + b * b)
    keep = (pj != cand[pi]) & (rho > 0.0) & (rho >= gap)
    pi, pj, w, a, b, dist = pi[keep], pj[keep], w[keep], a[keep], b[keep], dist[keep]
    octant = _octants(a, b)
    # Sectors 0-7: s holds octants s, s + 1 (90 degrees); sectors 8-15: 8 + s holds octants
    # s .. s + 3 (180 degrees). An octant o lies in sectors o, o - 1 and 8 + o - 3 .. 8 + o.
    lists = [(octant - d) % 8 for d in (0, 1)] + [8 + (octant - d) % 8 for d in range(4)]
    sec_i = np.concatenate([pi * _CLOUD_SECTORS + s for s in lists])
    sec_j = np.tile(pj, len(lists))
    sec_w = np.tile(w, (len(lists), 1))
    n_groups = m * _CLOUD_SECTORS
    finite = np.bincount(sec_i, minlength=n_groups).astype(np.float64).reshape(m, -1)
    full = np.concatenate([np.repeat(np.max(finite[:, :8], axis=1)[:, None], 8, axis=1),
                           np.repeat(np.max(finite[:, 8:], axis=1)[:, None], 8, axis=1)], axis=1)
    sup = labels[sec_j] == NORMAL
    cnt, cen, evals, evecs, ok = _group_fits(
        sec_i[sup], sec_w[sup], n_groups, np.ones(n_groups, dtype=bool))
    cnt = cnt.reshape(m, -1).astype(np.float64)
    ok = ok.reshape(m, -1)
    half = full / 2.0
    valid = ok & (cnt >= np.maximum(3.0, half))  # at least half a full sector of support
    empty = finite < _CLOUD_EMPTY * full  # hardly any returns: the surface ends
    gone = finite < _CLOUD_HANG_EMPTY * full  # beyond a hanging point: nothing in reach
    nrm = np.full((n_groups, 3), np.nan)
    good = ok.reshape(-1)
    nrm[good] = _orient(evecs[good][:, :, 0])
    nrm = nrm.reshape(m, -1, 3)
    cen = cen.reshape(m, -1, 3)
    evals = evals.reshape(m, -1, 3)
    n = np.maximum(cnt, 1.0)
    h = -np.einsum("ijk,ijk->ij", nrm, cen)  # u . (P - centroid), centroid = P + cen
    rms = _edge_rms(evals, n)
    spread = np.sqrt((evals[:, :, 1] + evals[:, :, 2]) / n)
    # the floor: round-off, or P's precision floor when larger (step 3)
    floor = np.maximum(_HEIGHT_RMS_FLOOR * spread,
                       (precision * np.abs(pts[cand]).max(axis=1))[:, None])
    tol = np.maximum(k * rms, floor)
    best = np.min(np.where(valid, rms, np.inf), axis=1)
    # a gone sector is in reach after all when its support (a plane: at least 3 points, rms at
    # most _CLOUD_FACE_CLEAN x best) runs through P (within its own tolerance) steeper than 45
    # degrees against the opposite sector's plane: a face falling away past a convex bend,
    # sampled sparsely in 3-D (SPEC step 5); gone is only read opposite a clean sector
    opp = [_turned(s, 4) for s in range(_CLOUD_SECTORS)]
    tilt = np.abs(np.einsum("isj,isj->is", nrm, nrm[:, opp]))  # NaN without both planes
    gone &= ~(ok & (rms <= _CLOUD_FACE_CLEAN * best[:, None]) & ~(np.abs(h) > tol)
              & (tilt < _CLOUD_FACE_COS))
    clean = valid & (rms <= _EDGE_CLEAN_RATIO * best[:, None])
    level = ~(clean & (np.abs(h) > tol)).any(axis=1)  # step 7: the wide scale is not asked
    # P fits a clean sector within the cleanest sector's tolerance (k best, floored as the
    # sector's own): a clean sector of larger rms (e.g. one holding part of the burr run itself)
    # does not lend P its wider tolerance.
    fits = clean & ~(np.abs(h) > np.maximum(k * best[:, None], floor))
    proud = np.zeros(m, dtype=bool)
    across = np.zeros(m, dtype=bool)  # stands proud and fits only sectors past the feature
    below = np.zeros((m, _CLOUD_SECTORS), dtype=bool)  # hanging, the first condition
    vetoes = np.zeros((m, _CLOUD_SECTORS), dtype=bool)  # the level rule's, per sector
    for s in range(_CLOUD_SECTORS):
        o = _turned(s, 4)  # the opposite sector of the same width
        drop = np.einsum("ij,ij->i", nrm[:, s], cen[:, o] - cen[:, s])
        # the level rule: an empty opposite is an outline unless a clean neighbour of it (the
        # same width, turned by +-45 degrees) lies at this sector's level (at this scale or, for
        # the wide one, at the narrow one)
        for c in (_turned(o, -1), _turned(o, 1)):
            lvl = np.abs(np.einsum("ij,ij->i", nrm[:, s], cen[:, c] - cen[:, s]))
            vetoes[:, s] |= valid[:, s] & empty[:, o] & clean[:, c] & ~(lvl > tol[:, s])
        outline = empty[:, o] & ~vetoes[:, s]
        if veto is not None:
            outline &= ~veto[:, s]
        # the opposite falls away: the centroid of its support (at least 3 points; no plane
        # needed: a flange falling away steeply leaves its sector too few points to be valid)
        falls = outline | ((cnt[:, o] >= 3.0) & (drop < -tol[:, s]))
        # the top rule: no valid sector's centroid above P along this sector's normal
        above = np.einsum("ij,isj->is", nrm[:, s], cen) > 0.0
        top = ~(valid & above).any(axis=1)
        proud_s = clean[:, s] & (h[:, s] > tol[:, s]) & falls & top
        proud |= proud_s
        # the crossing rule: the clean sectors P fits all lie beyond the feature, their
        # centroids below this sector's plane (u_s . (m_c - m_s) < -t_s): P stands proud of its
        # own side and only the surface past the crease, extended back, runs through it
        lvl = np.einsum("ij,isj->is", nrm[:, s], cen - cen[:, s][:, None, :])
        past = lvl < -tol[:, s][:, None]
        across |= proud_s & ~(fits & ~past).any(axis=1)
        # P below this sector, the opposite empty or clean with P above it and falling away
        beyond = gone[:, o] | (clean[:, o] & (h[:, o] > tol[:, o]) & (drop < -tol[:, s]))
        below[:, s] = clean[:, s] & (h[:, s] < -tol[:, s]) & beyond
    out = ~fits.any(axis=1)
    hang = out & ~proud & below.any(axis=1) & hanging
    if hang.any():
        hang[hang] = _cloud_hanging(
            labels, sec_i, sec_j, sec_w, np.tile(dist, len(lists)), sup, hang, below[hang],
            h[hang], nrm[hang], cen[hang], tol[hang], gone[hang])
    # the lips' sectors: clean, P above them, the opposite's support centroid (at least 3
    # points) above their plane by more than _CLOUD_LIP_RISE x h
    rise = np.einsum("isj,isj->is", nrm, cen[:, opp] - cen)
    raised = clean & (h > tol) & (cnt[:, opp] >= 3.0) & (rise > _CLOUD_LIP_RISE * h)
    lip = out & ~proud & ~hang & raised.any(axis=1)
    if lip.any():
        lip[lip] = _cloud_lips(labels, pi, pj, w, a, b, lip, raised[lip], h[lip], nrm[lip],
                               tol[lip], r_edge)
    return (out & (proud | hang | lip)) | across, level, vetoes


#: Cloud hanging rule (SPEC "Unorganized clouds: edge test" step 5): the surface beyond a
#: hanging point lies more than this times as deep below it as it lies below the top.
_CLOUD_HANG_SHELF = 2.0
#: ... and a hanging point extends a ledge (material below the sector's plane already removed)
#: when that material lies within this times P's depth of P's level.
_CLOUD_LEDGE_LEVEL = 0.5


def _cloud_hanging(
    labels: NDArray[np.uint8],
    sec_i: NDArray[np.int64],
    sec_j: NDArray[np.int64],
    sec_w: NDArray[np.float64],
    sec_d: NDArray[np.float64],
    sup: NDArray[np.bool_],
    sel: NDArray[np.bool_],
    below: NDArray[np.bool_],
    h: NDArray[np.float64],
    nrm: NDArray[np.float64],
    cen: NDArray[np.float64],
    tol: NDArray[np.float64],
    gone: NDArray[np.bool_],
) -> NDArray[np.bool_]:
    """Which candidates of ``sel`` (mask over the pass's candidates) *hang* (SPEC "Unorganized
    clouds: edge test" step 5) below one of the sectors marked in ``below`` ``(M, 16)`` (one row
    per selected candidate, as ``h``, ``nrm``, ``cen``, ``tol`` and ``gone``: fewer than
    ``_CLOUD_HANG_EMPTY`` of a full sector's returns). Sector memberships: group
    ``sec_i = candidate * 16 + sector`` of point ``sec_j`` at offset ``sec_w`` (distance
    ``sec_d``), ``sup`` the support members."""
    S = _CLOUD_SECTORS
    m = below.shape[0]
    row = np.full(sel.size, -1, dtype=np.int64)
    row[sel] = np.arange(m)
    gr = row[sec_i // S]  # the member's selected candidate, -1 for the others
    gs = sec_i % S
    mine = gr >= 0

    def nearest(pick: NDArray[np.bool_]) -> NDArray[np.float64]:
        # per (candidate, sector), the offset of its picked member nearest to P (smallest
        # distance, then smallest index); NaN where none
        order = np.lexsort((sec_j[pick], sec_d[pick], gr[pick] * S + gs[pick]))
        grp = (gr[pick] * S + gs[pick])[order]
        first = np.ones(grp.size, dtype=bool)
        first[1:] = grp[1:] != grp[:-1]
        out = np.full((m * S, 3), np.nan)
        out[grp[first]] = sec_w[pick][order][first]
        return out.reshape(m, S, 3)

    def off_plane(pick: NDArray[np.bool_]) -> NDArray[np.float64]:
        # the picked members' signed distances from their sector's plane
        return _dot3(sec_w[pick] - cen[gr[pick], gs[pick]], nrm[gr[pick], gs[pick]])

    # the support point on each sector's plane nearest to P (the top's, not material hanging
    # below it) ...
    su = sup & mine
    su[su] = ~(np.abs(off_plane(su)) > tol[gr[su], gs[su]])
    near = nearest(su)
    # ... and the ABNORMAL member below it (more than its tolerance) nearest to P: a ledge
    ab = mine & (labels[sec_j] == ABNORMAL)
    ab[ab] = off_plane(ab) < -tol[gr[ab], gs[ab]]
    hung = nearest(ab)
    ground = mine & ((labels[sec_j] == NORMAL) | (labels[sec_j] == EDGE))
    out = np.zeros(m, dtype=bool)
    for s in range(S):
        if not below[:, s].any():
            continue
        o = _turned(s, 4)
        u = nrm[:, s]
        delta = -h[:, s]
        v = near[:, s]
        along = _dot3(v, u)
        # q lies above P more steeply than 45 degrees (NaN: no such q)
        steep = (along > 0.0) & (along * along > _dot3(v, v) - along * along)
        # ... or P extends a ledge already removed: that ABNORMAL member y lies nearer than q
        # and level with P (|u . y| <= _CLOUD_LEDGE_LEVEL x delta), q above P
        y = hung[:, s]
        level = np.abs(_dot3(y, u)) <= _CLOUD_LEDGE_LEVEL * delta
        steep |= (along > 0.0) & (_dot3(y, y) < _dot3(v, v)) & level
        # the shelf: the opposite sector gone (the surface beyond is out of reach) or a ground
        # point there deeper than _CLOUD_HANG_SHELF x delta along u
        g = ground & (gs == o)
        low = np.full(m, np.inf)
        np.minimum.at(low, gr[g], _dot3(sec_w[g], u[gr[g]]))
        shelf = gone[:, o] | (low < -_CLOUD_HANG_SHELF * delta)
        out |= below[:, s] & steep & shelf
    return out


#: Cloud lips at a concave feature (SPEC "Unorganized clouds: edge test" step 6): the grid's dip
#: (_EDGE_LIP_TOL, _EDGE_LIP_DIP); the opposite sector's support centroid lies above the
#: sector's plane by more than this times P's height (a bead one point wide through P lifts it
#: by about 0.13 h at the default radius) ...
_CLOUD_LIP_RISE = 0.25
#: ... and the strip beyond P reaches this times the edge radius either side of its ray.
_CLOUD_LIP_STRIP = 0.1
#: A sector's bisector in the tangent plane, ``45 o + 45`` degrees from ``e1`` towards ``e2``
#: (quarter sector ``o``) or ``45 (o - 8) + 90`` (half sector): per multiple of 45 degrees,
#: its ``(cos, sin)``.
_R2 = float(np.sqrt(0.5))
_CLOUD_TURNS = ((1.0, 0.0), (_R2, _R2), (0.0, 1.0), (-_R2, _R2), (-1.0, 0.0), (-_R2, -_R2),
                (0.0, -1.0), (_R2, -_R2))


def _cloud_lips(
    labels: NDArray[np.uint8],
    pi: NDArray[np.int64],
    pj: NDArray[np.int64],
    w: NDArray[np.float64],
    a: NDArray[np.float64],
    b: NDArray[np.float64],
    sel: NDArray[np.bool_],
    raised: NDArray[np.bool_],
    h: NDArray[np.float64],
    nrm: NDArray[np.float64],
    tol: NDArray[np.float64],
    r_edge: float,
) -> NDArray[np.bool_]:
    """Which candidates of ``sel`` (mask over the pass's candidates) are *lips at a concave
    feature* (SPEC "Unorganized clouds: edge test" step 6) beyond one of the sectors marked in
    ``raised`` ``(M, 16)`` (clean, P above it, its opposite rising; one row per selected
    candidate, as ``h``, ``nrm`` and ``tol``): along the strip beyond P (the ground members
    with ``along > |across|`` and ``|across| <= _CLOUD_LIP_STRIP r_edge`` about the bisector
    of the opposite sector, in order of ``along``, then index), a point before the last dips
    and the last lies above the sector's plane. Sector members: candidate ``pi`` (of the
    pass), point ``pj``, offset ``w``, tangent offset ``(a, b)``."""
    m = raised.shape[0]
    row = np.full(sel.size, -1, dtype=np.int64)
    row[sel] = np.arange(m)
    gr = row[pi]
    ground = (gr >= 0) & ((labels[pj] == NORMAL) | (labels[pj] == EDGE))
    out = np.zeros(m, dtype=bool)
    for s in range(_CLOUD_SECTORS):
        if not raised[:, s].any():
            continue
        o = _turned(s, 4)
        c, sn = _CLOUD_TURNS[(o % 8 + 1 + o // 8) % 8]
        along = c * a + sn * b  # how far beyond P, away from s
        across = c * b - sn * a
        g = ground & (along > np.abs(across)) & ~(np.abs(across) > _CLOUD_LIP_STRIP * r_edge)
        g &= raised[np.maximum(gr, 0), s]
        # in strip order per candidate: the furthest along first (the last), then the index
        order = np.flatnonzero(g)[np.lexsort((pj[g], -along[g], gr[g]))]
        grp = gr[order]
        d = _dot3(w[order], nrm[grp, s])  # u_s . (x - P)
        first = np.ones(grp.size, dtype=bool)
        first[1:] = grp[1:] != grp[:-1]
        last = np.full(m, -np.inf)
        last[grp[first]] = d[first]
        low = np.full(m, np.inf)  # the lowest point before the last
        np.minimum.at(low, grp[~first], d[~first])
        dip = np.maximum(_EDGE_LIP_TOL * tol[:, s], _EDGE_LIP_DIP * h[:, s])
        out |= raised[:, s] & (low < -dip) & (h[:, s] + last > tol[:, s])
    return out


def _cloud_edge_test(
    tree: Any,
    pts: NDArray[np.float64],
    labels: NDArray[np.uint8],
    suspect: NDArray[np.bool_],
    r_edge: float,
    gap: float,
    k: float,
    iters: int,
    precision: float = _EDGE_PRECISION_F64,
) -> int:
    """Edge passes (SPEC "Unorganized clouds: edge test") on ``labels`` in place, at the two
    scales ``r_edge`` and ``_CLOUD_EDGE_WIDE * r_edge`` (step 7); ``precision`` the input's
    (step 3's precision floor); returns the number of passes run."""
    todo = suspect & ((labels == NORMAL) | (labels == EDGE))
    cand_all = np.flatnonzero(todo)
    scales = []  # per scale: its radius, its frames and each point's frame (-1: none)
    testable = np.zeros(pts.shape[0], dtype=bool)
    for r_s in (r_edge, _CLOUD_EDGE_WIDE * r_edge):
        e1, e2, ok = _cloud_frames(tree, pts, cand_all, r_s)
        frame_of = np.full(pts.shape[0], -1, dtype=np.int64)
        frame_of[cand_all[ok]] = np.flatnonzero(ok)
        testable |= frame_of >= 0
        scales.append((r_s, e1, e2, frame_of))
    r_wide = scales[-1][0]
    passes = 0
    judge = testable.copy()
    for _ in range(iters):
        passes += 1
        cand = np.flatnonzero(judge & ((labels == NORMAL) | (labels == EDGE)))
        flag = np.zeros(pts.shape[0], dtype=bool)  # ABNORMAL at either scale (Jacobi)
        asked = np.ones(pts.shape[0], dtype=bool)  # the wide scale: not level at the narrow one
        veto = np.zeros((pts.shape[0], _CLOUD_SECTORS), dtype=bool)  # the narrow scale's
        for scale, (r_s, e1, e2, frame_of) in enumerate(scales):
            c = cand[(frame_of[cand] >= 0) & asked[cand]]
            f = frame_of[c]
            hit, level, vetoes = _cloud_edge_pass(tree, pts, labels, c, e1[f], e2[f], r_s, gap,
                                                  k, veto[c] if scale else None, not scale,
                                                  precision)
            flag[c[hit]] = True
            asked[c[level]] = False
            veto[c] = vetoes
        new = np.flatnonzero(flag)
        labels[new] = ABNORMAL
        if new.size == 0:
            break
        # only candidates with a new ABNORMAL point within the wide radius can change
        near = np.zeros(pts.shape[0], dtype=bool)
        lists = tree.query_ball_point(pts[new], _query_radius(r_wide))
        for i, js in zip(new, lists):
            js = np.asarray(js, dtype=np.int64)
            d = pts[js] - pts[i]
            near[js[np.sqrt(_dot3(d, d)) <= r_wide]] = True
        judge = testable & near
    return passes


def detect_points(
    points: ArrayLike,
    theta0: float = 90.0,
    scales: Sequence[int] = (1, 2),
    min_step: float | None = None,
    min_directions: int | None = None,
    max_iterations: int = 10,
    radius: float | None = None,
    K: int = 4,
    link: float | None = None,
    height_tolerance: float | str | None = "7rms",
    edge_extent: float = 12.0,
    min_group: int = 40,
    height_radius: float | None = None,
    merge_distance: float = 0.0,
    spacing: float | None = None,
    edge_tolerance: float | None = 4.0,
    edge_radius: float | None = None,
    isolated_tolerance: float | None = 5.0,
) -> RefPointsResult:
    """Detect abnormal points in an unorganized cloud (MIEM, reference implementation).

    The defaults are the recommended preset's cloud values (SPEC "Parameters"); the paper's
    method is ``theta0=75, scales=(1,), height_tolerance=None, edge_extent=0, min_group=0`` (the
    isolated-point rule belongs to the height test).

    Parameters
    ----------
    points : array_like, shape (N, 3), integer or floating
        The cloud (caller's length unit), in no particular order. Rows with any non-finite
        coordinate are INVALID and take no part. Never modified.
    theta0 : float, optional
        Threshold angle in degrees, in the open interval (0, 180): a direction is flagged when
        its interior angle is ``<= theta0``.
    scales : sequence of int, optional
        Neighbour scales (each ``>= 1``): at scale ``s`` a neighbour's tangent offset must be at
        least ``s * min_step`` long. A direction is available / flagged when it is at any scale.
    min_step : float or None, optional
        Shortest tangent offset of a direction neighbour (finite, ``>= 0``); None means
        ``0.5 * spacing``.
    min_directions : int or None, optional
        If set (1..K), the number of flagged directions that suffices for ABNORMAL (capped at
        the available count); None means all available directions.
    max_iterations : int, optional
        Maximum number of passes, ``>= 1``.
    radius : float or None, optional
        Neighbourhood radius (finite, ``> 0``); None means ``5 * spacing``, where ``spacing``
        is the median distance from a finite point to its nearest other finite point.
    K : int, optional
        Number of directions, ``2 <= K <= 8``: ``d_k = cos(k pi/K) e1 + sin(k pi/K) e2`` in
        the tangent plane, each with a sector of half-width ``90/K`` degrees on both sides.
    link : float or None, optional
        ABNORMAL points closer than this (``<=``) belong to the same defect (finite, ``> 0``);
        None means ``radius``.
    height_tolerance : float, str or None, optional
        Height test (SPEC "Unorganized clouds: floating groups and height test"): None (off),
        a length ``> 0`` or ``"<k>rms"``.
    edge_extent : float, optional
        With the height test: EDGE groups (``distance <= link``) at most ``edge_extent``
        spacings across are compact and height-tested; larger ones are feature lines. ``>= 0``.
    min_group : int, optional
        ``0`` (off) or ``>= 3``: after the angle passes, usable points whose group (linked by
        ``distance <= radius``) has fewer than ``min_group`` points are ABNORMAL.
    height_radius : float or None, optional
        Radius of the height planes (test and output heights); None means ``2 * radius``.
    merge_distance : float, optional
        SPEC "Duplicate points": finite rows within this distance (``<=``, transitively) are
        one point, the group's smallest row; the others take its results. ``>= 0``.
    spacing : float or None, optional
        The unit of the defaults (radius, min_step) and of ``edge_extent``; None means the
        median nearest-neighbour distance of the distinct points. ``> 0``.
    edge_tolerance : float or None, optional
        Edge test (SPEC "Unorganized clouds: edge test"): None (off) or ``k > 0`` (default 4).
    edge_radius : float or None, optional
        Radius of the edge test's sectors (it also judges at 1.5 times it, SPEC step 7); None
        means ``height_radius``. ``> 0``.
    isolated_tolerance : float or None, optional
        With the height test (either tolerance), the isolated-point rule (SPEC "Unorganized
        clouds: floating groups and height test", step 3): None (off) or ``k > 0``, in
        multiples of the surroundings rms.

    Returns
    -------
    RefPointsResult
        Per-point labels, flags, angles (degrees), heights and degenerate mask, the MIEM plane,
        the number of passes, the defects and the parameter values used.

    Raises
    ------
    ValueError
        Bad points (dtype, shape, fewer than 3 finite points, ``spacing == 0``) or a bad
        parameter; the message names the argument.
    """
    theta0_deg, scale_tuple, _, _, _, iters, _, _ = _validate_detect_params(
        theta0, scales, 1, min_step, None, max_iterations, 3, 1
    )
    k_dirs = _check_int("K", K, 2, MAX_K)
    min_dir = (
        None if min_directions is None else _check_int("min_directions", min_directions, 1, k_dirs)
    )
    r_in = None if radius is None else _check_length("radius", radius, allow_zero=False)
    link_in = None if link is None else _check_length("link", link, allow_zero=False)
    hr_in = (
        None if height_radius is None
        else _check_length("height_radius", height_radius, allow_zero=False)
    )
    tolerance = _parse_height_tolerance(height_tolerance)
    extent = _check_length("edge_extent", edge_extent, allow_zero=True)
    group = _check_int("min_group", min_group, 0)
    if 0 < group < 3:
        raise ValueError(f"min_group: expected 0 (off) or an integer >= 3, got {group}")

    merge = _check_length("merge_distance", merge_distance, allow_zero=True)
    spacing_in = None if spacing is None else _check_length("spacing", spacing, allow_zero=False)
    edge_k = None if edge_tolerance is None else _check_length(
        "edge_tolerance", edge_tolerance, allow_zero=False)
    re_in = None if edge_radius is None else _check_length(
        "edge_radius", edge_radius, allow_zero=False)
    iso_k = None if isolated_tolerance is None else _check_length(
        "isolated_tolerance", isolated_tolerance, allow_zero=False)

    p, finite = _cloud_array(points)
    precision = _precision(_as_points_array("points", points))  # (edge test step 3)
    n_all = p.shape[0]
    all_rows = np.flatnonzero(finite).astype(np.int64)
    if all_rows.size < 3:
        raise ValueError(f"points: need at least 3 finite points, got {all_rows.size}")
    rep = _duplicate_representatives(p[all_rows], merge)  # positions into all_rows
    if np.all(rep == rep[0]):
        raise ValueError("points: all finite points are one point (no spacing, no surface)")
    distinct = rep == np.arange(all_rows.size)
    rows = all_rows[distinct]
    pts = p[rows]
    n_pts = pts.shape[0]
    if n_pts < 3:
        raise ValueError(
            "points: fewer than 3 distinct points after merging duplicates within merge_distance"
        )

    tree = _kdtree(pts)
    spacing = _spacing(tree, pts) if spacing_in is None else spacing_in
    r = 5.0 * spacing if r_in is None else r_in
    step = 0.5 * spacing if min_step is None else float(min_step)
    lnk = r if link_in is None else link_in
    hr = 2.0 * r if hr_in is None else hr_in
    cos0 = math.cos(theta0_deg * math.pi / 180.0)

    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        # Every pair (p, q), q != p, |q - p| <= radius, fixed for the whole run.
        pi, pj, w, dist = _ball_pairs(tree, pts, pts, r)
        not_self = pi != pj
        pi, pj, w, dist = pi[not_self], pj[not_self], w[not_self], dist[not_self]

        labels = np.full(n_pts, NORMAL, dtype=np.uint8)
        flags = np.zeros(n_pts, dtype=np.uint8)
        angle = np.full(n_pts, np.nan)
        degenerate = np.zeros(n_pts, dtype=bool)
        abnormal = np.zeros(n_pts, dtype=bool)
        passes = 0
        while True:
            passes += 1
            judged = ~abnormal  # usable = finite and not ABNORMAL; all of them are judged
            cnt, fit_ok, n_avail, n_flag, pass_flags, pass_angle = _points_pass(
                pi, pj, w, dist, judged, cos0, scale_tuple, step, k_dirs
            )
            small = judged & (cnt < 3)
            need = n_avail if min_dir is None else np.minimum(n_avail, min_dir)
            new_abn = small | (judged & fit_ok & (n_avail >= 2) & (n_flag >= need))
            rest = judged & ~new_abn
            labels[new_abn] = ABNORMAL
            labels[rest & (n_flag > 0)] = EDGE
            labels[rest & (n_flag == 0)] = NORMAL
            flags[judged] = np.where(small, np.uint8(0), pass_flags)[judged]
            angle[judged] = np.where(small, np.nan, pass_angle)[judged]
            degenerate[judged] = (~small & ~fit_ok)[judged]
            abnormal |= new_abn
            if not new_abn.any() or passes >= iters:
                break

        if group:
            floating = _floating(pts, ~abnormal, r, group)
            labels[floating] = ABNORMAL
            abnormal |= floating

        # Pairs within the height radius, each point paired with itself (offset 0) too.
        hi, hj, hw, hd = _ball_pairs(tree, pts, pts, hr)
        re_used = hr if re_in is None else re_in
        first_rms = np.full(n_pts, np.nan)  # NaN: no height verdict (every point, test off)
        if tolerance is not None:
            outer = hd > r
            for it in range(iters):
                passes += 1
                edge = labels == EDGE
                compact = _cloud_compact_edges(pts, edge, lnk, extent * spacing)
                new_abn = _cloud_height_pass(
                    hi, hj, hw, outer, labels == NORMAL, compact, edge & ~compact, tolerance,
                    first_rms if it == 0 else None, iso_k, spacing,
                )
                labels[new_abn] = ABNORMAL
                abnormal |= new_abn
                if not new_abn.any():
                    break
        if edge_k is not None:
            # Candidates: where the first height pass gave no verdict, or saw rough
            # surroundings (rms above _CLOUD_EDGE_SUSPECT x the median).
            fin = np.isfinite(first_rms)
            med = float(np.median(first_rms[fin])) if fin.any() else np.inf
            suspect = ~fin | (first_rms > _CLOUD_EDGE_SUSPECT * med)
            passes += _cloud_edge_test(tree, pts, labels, suspect, re_used, step, edge_k,
                                       iters, precision)
            abnormal = labels == ABNORMAL

        plane = _eigen_plane(pts[~abnormal])

        # Height: plane of the NORMAL points within the height radius, the point itself
        # included.
        is_normal = labels == NORMAL
        sel = is_normal[hj]
        hi, hw = hi[sel], hw[sel]
        _, cen, _, evecs, ok = _group_fits(hi, hw, n_pts, np.ones(n_pts, dtype=bool))
        h_normals = np.full((n_pts, 3), np.nan)
        h_normals[ok] = _orient(evecs[ok][:, :, 0])
        height = np.full(n_pts, np.nan)
        # n . p + d with d = -n . c, evaluated as -n . (c - p) on the centred offsets.
        height[ok] = -_dot3(h_normals[ok], cen[ok])

        defects = _points_defects(pts, rows, abnormal, height, h_normals, lnk)

    dup_rows = all_rows[~distinct]
    of_rows = all_rows[rep[~distinct]]  # the row each duplicate duplicates

    def scatter(values: NDArray[Any], fill: Any) -> NDArray[Any]:
        out = np.full((n_all,) + values.shape[1:], fill, dtype=values.dtype)
        out[rows] = values
        out[dup_rows] = out[of_rows]
        return out

    if dup_rows.size:
        defects = [
            replace(d, indices=np.sort(np.concatenate(
                [d.indices, dup_rows[np.isin(of_rows, d.indices)]])).astype(np.int64))
            for d in defects
        ]
        defects = [replace(d, count=int(d.indices.size)) for d in defects]

    return RefPointsResult(
        labels=scatter(labels, INVALID),
        flags=scatter(flags, 0),
        angle=scatter(angle, np.nan),
        height=scatter(height, np.nan),
        degenerate=scatter(degenerate, False),
        plane=plane,
        iterations=passes,
        defects=defects,
        params={"spacing": spacing, "radius": r, "min_step": step, "link": lnk, "K": k_dirs,
                "height_radius": hr, "min_group": group, "edge_extent": extent,
                "merge_distance": merge, "merged": int(dup_rows.size),
                "edge_tolerance": edge_k,
                "edge_radius": None if edge_k is None else re_used,
                "isolated_tolerance": iso_k,
                "height_tolerance": (
                    None if tolerance is None
                    else (tolerance[1] if tolerance[0] == "abs" else str(height_tolerance))
                )},
    )


def estimate_normals(points: ArrayLike, radius: float) -> RefNormals:
    """Local surface normals of an unorganized cloud (reference implementation).

    Parameters
    ----------
    points : array_like, shape (N, 3), integer or floating
        The cloud (caller's length unit). Rows with any non-finite coordinate get no normal.
        Never modified.
    radius : float
        Neighbourhood radius (finite, ``> 0``): each finite point's plane is fitted to the
        finite points within ``radius`` of it (``<=``), the point itself included.

    Returns
    -------
    RefNormals
        Oriented normals, rms, neighbourhood counts and the valid mask (False for non-finite
        rows, fewer than 3 points, and degenerate neighbourhoods).

    Raises
    ------
    ValueError
        Bad points (dtype, shape) or bad ``radius``.
    """
    r = _check_length("radius", radius, allow_zero=False)
    p, finite = _cloud_array(points)
    n_all = p.shape[0]
    rows = np.flatnonzero(finite)
    pts = p[finite]
    n_pts = pts.shape[0]
    normals = np.full((n_all, 3), np.nan)
    rms = np.full(n_all, np.nan)
    count = np.zeros(n_all, dtype=np.int64)
    valid = np.zeros(n_all, dtype=bool)
    if n_pts == 0:
        return RefNormals(normals=normals, rms=rms, count=count, valid=valid)
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        tree = _kdtree(pts)
        pi, _, w, _ = _ball_pairs(tree, pts, pts, r)  # includes each point itself
        cnt, _, evals, evecs, ok = _group_fits(pi, w, n_pts, np.ones(n_pts, dtype=bool))
        nrm = np.full((n_pts, 3), np.nan)
        nrm[ok] = _orient(evecs[ok][:, :, 0])
        rr = np.full(n_pts, np.nan)
        rr[ok] = np.sqrt(np.maximum(evals[ok, 0], 0.0) / cnt[ok])
    normals[rows] = nrm
    rms[rows] = rr
    count[rows] = cnt
    valid[rows] = ok
    return RefNormals(normals=normals, rms=rms, count=count, valid=valid)
