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
  not a comparison of squares).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "ABNORMAL",
    "DIRECTIONS",
    "EDGE",
    "INVALID",
    "NORMAL",
    "RefDefect",
    "RefPlane",
    "RefResult",
    "detect",
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
        Unit normal, oriented so that ``normal[2] > 0``, or, when ``normal[2] == 0``, so that
        its first non-zero component is positive.
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
        Number of passes run.
    defects : list of RefDefect
        Connected groups of ABNORMAL cells, in SPEC.md order.
    """

    labels: NDArray[np.uint8]
    flags: NDArray[np.uint8]
    angle: NDArray[np.float64]
    height: NDArray[np.float64]
    plane: RefPlane | None
    iterations: int
    defects: list[RefDefect]


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


def _as_points_array(name: str, data: ArrayLike) -> NDArray[Any]:
    """Convert to an array and check that its dtype is integer or floating."""
    arr = np.asarray(data)
    if arr.dtype.kind not in "iuf":
        raise ValueError(
            f"{name}: expected a numeric (integer or floating) array, got dtype {arr.dtype}"
        )
    return arr


# --------------------------------------------------------------------------------------------
# Small float helpers
# --------------------------------------------------------------------------------------------


def _dot3(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Dot product over the last axis (length 3), summed left to right."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _orient(normals: NDArray[np.float64]) -> NDArray[np.float64]:
    """Orient normals ``(..., 3)``: ``n_z > 0``, or if ``n_z == 0`` first non-zero positive."""
    nx, ny, nz = normals[..., 0], normals[..., 1], normals[..., 2]
    lead = np.where(nz != 0, nz, np.where(nx != 0, nx, ny))
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
    h, w = finite.shape
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
    rows_per_chunk = max(1, _WINDOW_CHUNK_ENTRIES // max(1, w * ww))
    for r0 in range(0, h, rows_per_chunk):
        r1 = min(h, r0 + rows_per_chunk)
        rr, cc = np.nonzero(finite[r0:r1])
        if rr.size == 0:
            continue
        x = xw[r0:r1][rr, cc].reshape(rr.size, 3, ww)
        m = mw[r0:r1][rr, cc].reshape(rr.size, ww)
        cnt = m.sum(axis=1)
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
        good = (l2 > 0.0) & ~(l1 <= _EIGEN_RANK_TOL * l2)
        if not good.any():
            continue
        nrm = _orient(evecs[good, :, 0])
        c_good = centroid[good]
        d = -_dot3(nrm, c_good)
        p = grid[rr[good], cc[good]]
        height[rr[good], cc[good]] = _dot3(p, nrm) + d
        normals[rr[good], cc[good]] = nrm
    return height, normals


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
    raw = []
    for idx in _components(abnormal):
        members = pts[idx]
        centroid = members.mean(axis=0)
        hs = h_flat[idx]
        fin = np.isfinite(hs)
        if fin.any():
            fin_idx = idx[fin]
            pos = int(np.argmax(np.abs(hs[fin])))  # first in index order on ties
            peak_cell = int(fin_idx[pos])
            peak = float(h_flat[peak_cell])
            mean_h = float(np.mean(hs[fin]))
            normal = n_flat[peak_cell].copy()
        else:
            peak = math.nan
            mean_h = math.nan
            normal = np.full(3, np.nan)
        off = members - centroid
        if np.all(np.isfinite(normal)):
            off = off - _dot3(off, normal)[:, None] * normal
        extent = 2.0 * float(np.max(np.sqrt(_dot3(off, off))))
        if not t_flat[idx].any() or math.isnan(peak):
            kind = "isolated"
        elif peak < 0:
            kind = "pit"
        else:
            kind = "protrusion"
        raw.append((idx, centroid, normal, peak, mean_h, extent, kind))

    def order(item: tuple[Any, ...]) -> tuple[bool, float, int]:
        peak_ = item[3]
        nan = math.isnan(peak_)
        return (nan, 0.0 if nan else -abs(peak_), int(item[0][0]))

    raw.sort(key=order)
    out = []
    for i, (idx, centroid, normal, peak, mean_h, extent, kind) in enumerate(raw):
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
    theta0: float = 75.0,
    scales: Sequence[int] = (1,),
    max_gap: int = 1,
    min_step: float | None = None,
    min_directions: int | None = None,
    max_iterations: int = 10,
    window: int = 21,
    max_reach: int = 32,
) -> RefResult:
    """Detect abnormal points in an organized scan (MIEM, reference implementation).

    Parameters
    ----------
    grid : array_like, shape (H, W, 3), integer or floating
        Organized scan: row ``r`` is one profile, column ``c`` runs along it (caller's length
        unit). A point with any non-finite coordinate is a dropout. Never modified.
    theta0 : float, optional
        Threshold angle in degrees, in the open interval (0, 180): a direction is flagged when
        its interior angle is ``<= theta0``.
    scales : sequence of int, optional
        Neighbour scales (each ``>= 1``); a direction is available / flagged when it is at any
        scale. ``(1,)`` is the paper's behaviour.
    max_gap : int, optional
        Number of unusable cells (dropouts, removed points) a neighbour search may skip, ``>= 0``.
    min_step : float or None, optional
        If set (finite, ``>= 0``, caller's length unit), the neighbour at scale ``s`` is the
        first usable cell at least ``s * min_step`` away from the point.
    min_directions : int or None, optional
        If set (1..4), the number of flagged directions that suffices for ABNORMAL (capped at
        the available count); ``None`` means all available directions.
    max_iterations : int, optional
        Maximum number of passes, ``>= 1``.
    window : int, optional
        Side, in cells, of the square window of the local plane used for ``height``; odd ``>= 3``.
    max_reach : int, optional
        With ``min_step``, how many extra cells beyond ``scale + max_gap`` the search may go,
        ``>= 1``.

    Returns
    -------
    RefResult
        Labels, flags, angles (degrees), heights, the MIEM plane, the number of passes and the
        defects.

    Raises
    ------
    ValueError
        Bad grid (dtype, shape, fewer than 3 finite points) or bad parameter; the message names
        the argument.
    """
    (theta0_deg, scale_tuple, gap, step, min_dir, iters, win, reach) = _validate_detect_params(
        theta0, scales, max_gap, min_step, min_directions, max_iterations, window, max_reach
    )
    arr = _as_points_array("grid", grid)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"grid: expected shape (H, W, 3), got {arr.shape}")
    g = np.array(arr, dtype=np.float64, copy=True)
    finite = np.all(np.isfinite(g), axis=2)
    if int(finite.sum()) < 3:
        raise ValueError(f"grid: need at least 3 finite points, got {int(finite.sum())}")
    # Dropouts become NaN so that no inf - inf arithmetic happens below; they are never read
    # as neighbours (not usable) and are reported INVALID.
    g[~finite] = np.nan

    h, w = finite.shape
    cos0 = math.cos(theta0_deg * math.pi / 180.0)
    labels = np.full((h, w), INVALID, dtype=np.uint8)
    labels[finite] = NORMAL
    flags = np.zeros((h, w), dtype=np.uint8)
    angle = np.full((h, w), np.nan)
    abnormal = np.zeros((h, w), dtype=bool)

    passes = 0
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
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

        plane = _eigen_plane(g[finite & ~abnormal])
        height, normals = _window_fits(g, labels == NORMAL, finite, win)
        defects = _defects(g, labels, height, normals, finite)

    return RefResult(
        labels=labels,
        flags=flags,
        angle=angle,
        height=height,
        plane=plane,
        iterations=passes,
        defects=defects,
    )
