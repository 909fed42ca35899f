"""Core == reference on an unorganized cloud, as the cloud tests compare them: labels, flags,
heights, passes, the edge radius and the defects' members; and the cloud edge test's sectors of
one point computed by hand (SVDs and angles), for the tests' own verdicts."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

import miem
from miem import reference as ref


def pre_edge_pass(pts: np.ndarray) -> tuple[ref.RefPointsResult, float, float, np.ndarray,
                                             np.ndarray]:
    """The reference without the edge test on ``pts`` (the labels the first edge pass starts
    from) and what the by-hand sectors need: the edge radius, the gap, the support (NORMAL) and
    the ground (NORMAL or EDGE) masks."""
    pre = ref.detect_points(pts, edge_tolerance=None)
    normal = pre.labels == miem.NORMAL
    return (pre, pre.params["height_radius"], pre.params["min_step"], normal,
            normal | (pre.labels == miem.EDGE))


def assert_same_cloud_result(core: miem.DetectResult, oracle: ref.RefPointsResult) -> None:
    np.testing.assert_array_equal(core.labels, oracle.labels)
    np.testing.assert_array_equal(core.flags, oracle.flags)
    np.testing.assert_allclose(core.height, oracle.height, atol=1e-9, equal_nan=True)
    assert core.iterations == oracle.iterations
    assert core.params["edge_radius"] == pytest.approx(oracle.params["edge_radius"], rel=1e-12)
    assert [d.indices.tolist() for d in core.defects] == [
        d.indices.tolist() for d in oracle.defects]


def assert_core_is_reference_everywhere(pts: np.ndarray) -> None:
    """Core == reference with the defaults on ``pts`` and on its float32 copy 1e3 mm away, and
    the same labels on 1 and 2 threads."""
    assert_same_cloud_result(miem.detect_points(pts), ref.detect_points(pts))
    p32 = (pts + 1e3).astype(np.float32)
    assert_same_cloud_result(miem.detect_points(p32), ref.detect_points(p32))
    base = miem.detect_points(pts).labels
    for nt in (1, 2):
        np.testing.assert_array_equal(miem.detect_points(pts, num_threads=nt).labels, base)


@dataclass
class HandSectors:
    """SPEC "Unorganized clouds: edge test" steps 2-3 for point P (here with SVDs and angles,
    not the reference's code): offsets ``w = q - P``, their distance ``dist``, polar ``rho`` and
    ``theta`` in P's tangent frame, the sectors' ``member`` points, per sector (8 quarter, then
    8 half sectors) its points ``inside``, returns ``f``, ``full``, plane ``(u, centroid, rms)``
    (None: not valid), bisector angle, P's height ``h`` over it, ``clean``; and ``best``."""

    w: np.ndarray
    dist: np.ndarray
    rho: np.ndarray
    theta: np.ndarray
    member: np.ndarray
    inside: list
    f: np.ndarray
    full: np.ndarray
    planes: list
    bisector: list
    h: list
    clean: list
    best: float


def svd_plane(w: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The plane of points ``w`` (at least 3) by SVD: (unit normal, z component > 0 where
    nonzero; centroid; rms = smallest singular value / sqrt(count))."""
    c = w.mean(axis=0)
    _, sv, vt = np.linalg.svd(w - c, full_matrices=False)
    return (vt[2] if vt[2, 2] > 0 else -vt[2], c, float(sv[2] / np.sqrt(len(w))))


def sectors_by_hand(pts: np.ndarray, normal: np.ndarray, i: int, r_edge: float,
                    gap: float) -> HandSectors:
    """The sectors of point i (``normal``: the support, NORMAL at the start of the pass)."""
    w = pts - pts[i]
    dist = np.linalg.norm(w, axis=1)
    ball = dist <= r_edge
    _, _, vt = np.linalg.svd(w[ball] - w[ball].mean(axis=0))
    n = vt[2] if vt[2, 2] > 0 else -vt[2]
    e1 = vt[0] - (vt[0] @ n) * n
    e1 /= np.linalg.norm(e1)
    a, b = w @ e1, w @ np.cross(n, e1)
    rho = np.hypot(a, b)
    member = ball & (np.arange(len(pts)) != i) & (rho > 0) & (rho >= gap)
    theta = np.mod(np.arctan2(b, a), 2 * np.pi)
    octant = np.minimum((theta / (np.pi / 4)).astype(int), 7)
    octants = [[s, (s + 1) % 8] for s in range(8)] + [[(s + j) % 8 for j in range(4)]
                                                      for s in range(8)]
    bisector = [np.pi / 4 * (s + 1) for s in range(8)] + [np.pi / 4 * (s + 2) for s in range(8)]
    inside = [member & np.isin(octant, o) for o in octants]
    f = np.array([m.sum() for m in inside], float)
    full = np.array([f[:8].max()] * 8 + [f[8:].max()] * 8)
    planes = []
    for s, m in enumerate(inside):
        sel = m & normal
        if sel.sum() < max(3.0, full[s] / 2.0):
            planes.append(None)
            continue
        planes.append(svd_plane(w[sel]))
    best = min(p[2] for p in planes if p is not None)
    clean = [p is not None and p[2] <= 2 * best for p in planes]
    h = [None if p is None else -p[0] @ p[1] for p in planes]
    return HandSectors(w, dist, rho, theta, member, inside, f, full, planes, bisector, h, clean,
                       best)
