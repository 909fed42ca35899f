"""Tests of the NumPy reference for unorganized clouds (``detect_points``, ``estimate_normals``).

Expected values come from geometry worked out by hand (lattices, spikes, creases, spheres) or
from a literal, per-point transcription of the docs/SPEC.md rules written below (brute-force
distances, one point and one candidate at a time); never from an earlier run of the reference.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np
import pytest
from miem import reference as ref

# The paper's angle test on clouds (theta0 75, scales (1,)); explicit arguments win.
paper_detect_points = functools.partial(ref.detect_points, theta0=75.0, scales=(1,),
                                        height_tolerance=None, edge_extent=0.0, min_group=0,
                                        isolated_tolerance=None, edge_tolerance=None)

N, A, E, INV = ref.NORMAL, ref.ABNORMAL, ref.EDGE, ref.INVALID


def lattice(n: int, h: float, *, m: int | None = None) -> np.ndarray:
    """Square lattice ``(n * m, 3)`` on z = 0, x = i * h, y = j * h, row index ``j * n + i``."""
    m = n if m is None else m
    j, i = np.mgrid[0:m, 0:n]
    pts = np.zeros((n * m, 3))
    pts[:, 0] = i.ravel() * h
    pts[:, 1] = j.ravel() * h
    return pts


def noisy_cloud(seed: int, n: int = 400) -> np.ndarray:
    """A rough random surface with spikes, a pit, floating dust, duplicates and NaN rows."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, 10.0, (n, 2))
    z = 0.3 * np.sin(0.5 * xy[:, 0]) + 0.1 * xy[:, 1] + rng.normal(0.0, 0.02, n)
    pts = np.c_[xy, z]
    pts[:4, 2] += [1.0, 0.8, -0.9, 0.5]  # spikes and a pit
    pts[4] = [5.0, 5.0, 6.0]  # floating dust
    pts[5] = pts[10]  # a duplicate
    pts[6, 1] = np.nan  # dropouts
    pts[7] = np.inf
    return pts


def rough_cloud(seed: int, n: int = 160) -> np.ndarray:
    """A dense wavy patch (use radius ~1) with spikes, pits, a floating pair, a collinear run
    (degenerate neighbourhoods), a duplicate and non-finite rows."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, 4.0, (n, 2))
    z = 0.3 * np.sin(1.5 * xy[:, 0]) * np.cos(1.2 * xy[:, 1]) + rng.normal(0.0, 0.05, n)
    pts = np.c_[xy, z]
    pts[:6, 2] += [0.8, 0.6, -0.7, 0.5, 0.4, -0.4]
    pts[6:8] = [[2.0, 2.0, 3.0], [2.1, 2.0, 3.0]]
    pts[8:12] = np.c_[10.0 + 0.3 * np.arange(4), np.zeros(4), np.zeros(4)]
    pts[12] = pts[20]
    pts[13, 0] = np.nan
    pts[14] = -np.inf
    return pts


# --------------------------------------------------------------------------------------------
# A literal transcription of SPEC.md "Unorganized clouds" (one point at a time)
# --------------------------------------------------------------------------------------------


def literal_detect_points(
    points: np.ndarray,
    *,
    theta0: float,
    scales: tuple[int, ...],
    min_step: float,
    min_directions: int | None,
    max_iterations: int,
    radius: float,
    K: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Labels, flags, angle, degenerate mask and passes, straight from the SPEC.md text."""
    n_all = points.shape[0]
    finite = [bool(np.all(np.isfinite(points[i]))) for i in range(n_all)]
    labels = np.array([N if f else INV for f in finite], dtype=np.uint8)
    flags = np.zeros(n_all, dtype=np.uint8)
    angle = np.full(n_all, np.nan)
    degenerate = np.zeros(n_all, dtype=bool)
    cos0 = math.cos(theta0 * math.pi / 180.0)
    cos_half = math.cos((90.0 / K) * math.pi / 180.0)

    def dist(a: int, b: int) -> float:
        w = points[b] - points[a]
        return math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])

    passes = 0
    while True:
        passes += 1
        usable = [finite[i] and labels[i] != A for i in range(n_all)]
        verdicts = []  # (point, label, flags, angle, degenerate) of this pass
        for p in range(n_all):
            if not usable[p]:
                continue
            q_set = [q for q in range(n_all) if q != p and usable[q] and dist(p, q) <= radius]
            if len(q_set) < 3:
                verdicts.append((p, A, 0, math.nan, False))
                continue
            x = points[q_set]
            dev = x - x.mean(axis=0)
            evals, evecs = np.linalg.eigh(dev.T @ dev)
            if not evals[2] > 0 or evals[1] <= 1e-12 * evals[2]:
                verdicts.append((p, N, 0, math.nan, True))  # no direction available
                continue
            nrm = evecs[:, 0].copy()
            lead = nrm[2] if nrm[2] != 0 else (nrm[0] if nrm[0] != 0 else nrm[1])
            if lead < 0:
                nrm = -nrm
            e1 = evecs[:, 2].copy()
            if not evals[2] - evals[1] > 1e-6 * evals[2]:  # in-plane isotropic: fixed axis
                axis = np.zeros(3)
                axis[int(np.argmin(np.abs(nrm)))] = 1.0
                e1 = axis - float(axis @ nrm) * nrm
                e1 = e1 / math.sqrt(float(e1 @ e1))
            if e1[int(np.argmax(np.abs(e1)))] < 0:
                e1 = -e1
            e2 = np.cross(nrm, e1)
            n_avail = n_flag = bits = 0
            smallest = math.nan
            for k in range(K):
                d = math.cos(k * math.pi / K) * e1 + math.sin(k * math.pi / K) * e2
                avail = flagged = False
                for s in scales:
                    side: dict[int, tuple[float, int] | None] = {}
                    for g in (-1, 1):
                        best: tuple[float, int] | None = None
                        for q in q_set:
                            w = points[q] - points[p]
                            t = w - float(w @ nrm) * nrm
                            tl = math.sqrt(float(t @ t))
                            if tl > 0 and tl >= (2 * s - 1) * min_step and g * float(t @ d) >= tl * cos_half:
                                key = (dist(p, q), q)
                                if best is None or key < best:
                                    best = key
                        side[g] = best
                    a_side, b_side = side[-1], side[1]
                    if a_side is None or b_side is None:
                        continue
                    u = points[a_side[1]] - points[p]
                    v = points[b_side[1]] - points[p]
                    uu, vv = float(u @ u), float(v @ v)
                    if uu == 0 or vv == 0:
                        continue
                    c = min(1.0, max(-1.0, float(u @ v) / math.sqrt(uu * vv)))
                    avail = True
                    flagged = flagged or c >= cos0
                    ang = math.degrees(math.acos(c))
                    smallest = ang if math.isnan(smallest) else min(smallest, ang)
                n_avail += avail
                n_flag += flagged
                bits |= (1 << k) if flagged else 0
            need = n_avail if min_directions is None else min(n_avail, min_directions)
            if n_avail >= 2 and n_flag >= need:
                label = A
            else:
                label = E if n_flag > 0 else N
            verdicts.append((p, label, bits, smallest, False))
        for p, label, bits, ang, degen in verdicts:  # Jacobi: applied after the pass
            labels[p], flags[p], angle[p], degenerate[p] = label, bits, ang, degen
        if not any(v[1] == A for v in verdicts) or passes >= max_iterations:
            break
    return labels, flags, angle, degenerate, passes


def literal_heights(points: np.ndarray, labels: np.ndarray, radius: float) -> np.ndarray:
    """SPEC.md "Height": plane of the NORMAL points within radius (the point itself included)."""
    out = np.full(points.shape[0], np.nan)
    for p in range(points.shape[0]):
        if labels[p] == INV:
            continue
        near = [
            q
            for q in range(points.shape[0])
            if labels[q] == N and np.linalg.norm(points[q] - points[p]) <= radius
        ]
        try:
            plane = ref.fit_plane(points[near])
        except ValueError:
            continue
        out[p] = plane.distance(points[p])
    return out


@pytest.mark.parametrize(
    "kwargs",
    [
        {},
        {"radius": 1.0},
        {"radius": 1.0, "K": 3},
        {"radius": 1.0, "K": 6, "scales": (1, 2)},
        {"radius": 1.0, "scales": (1, 2), "min_step": 0.3},
        {"radius": 1.0, "scales": (1, 3), "min_step": 0.1, "theta0": 135.0},
        {"radius": 1.0, "min_step": 0.0, "theta0": 150.0},
        {"radius": 1.0, "K": 5, "min_directions": 3, "theta0": 150.0},
        {"radius": 0.8, "min_directions": 2, "theta0": 120.0},
        {"radius": 1.0, "max_iterations": 1, "theta0": 120.0},
        {"radius": 1.0, "K": 2, "theta0": 120.0},
    ],
)
@pytest.mark.parametrize("seed", [0, 1])
def test_detect_points_matches_literal_transcription(kwargs: dict, seed: int) -> None:
    pts = rough_cloud(seed)
    res = paper_detect_points(pts, **kwargs)
    used = {
        "theta0": 75.0,
        "scales": (1,),
        "min_directions": None,
        "max_iterations": 10,
        **{k: v for k, v in kwargs.items() if k not in ("radius", "min_step", "K")},
    }
    # Duplicate points are merged (SPEC "Duplicate points"): row 12 duplicates row 20, so the
    # transcription runs without it and row 12 must then read like row 20.
    distinct = pts.copy()
    distinct[12] = np.nan
    labels, flags, angle, degenerate, passes = literal_detect_points(
        distinct,
        min_step=res.params["min_step"],
        radius=res.params["radius"],
        K=res.params["K"],
        **used,
    )
    for arr in (labels, flags, angle, degenerate):
        arr[12] = arr[20]
    assert res.params["merged"] == 1
    np.testing.assert_array_equal(res.labels, labels)
    np.testing.assert_array_equal(res.flags, flags)
    np.testing.assert_allclose(res.angle, angle, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(res.degenerate, degenerate)
    assert res.iterations == passes
    lab = res.labels.copy()
    lab[12] = INV
    heights = literal_heights(distinct, lab, res.params["height_radius"])
    heights[12] = heights[20]
    np.testing.assert_allclose(res.height, heights, rtol=0, atol=1e-9)


def test_spacing_radius_by_brute_force() -> None:
    pts = noisy_cloud(3, n=300)
    fin = pts[np.all(np.isfinite(pts), axis=1)]
    fin = np.unique(fin, axis=0)  # duplicates are merged before the spacing (SPEC)
    d = np.linalg.norm(fin[:, None, :] - fin[None, :, :], axis=2)
    np.fill_diagonal(d, np.inf)
    spacing = float(np.median(d.min(axis=1)))
    res = paper_detect_points(pts)
    assert res.params["spacing"] == pytest.approx(spacing, rel=1e-15)
    assert res.params["radius"] == 5.0 * res.params["spacing"]
    assert res.params["min_step"] == 0.5 * res.params["spacing"]
    assert res.params["link"] == res.params["radius"]


# --------------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_lattice_single_spike(sign: float) -> None:
    h = 0.5
    pts = lattice(21, h)
    spike = 10 * 21 + 10
    pts[spike, 2] = sign * 2 * h
    res = paper_detect_points(pts)
    expected = np.full(pts.shape[0], N, dtype=np.uint8)
    expected[spike] = A
    np.testing.assert_array_equal(res.labels, expected)
    assert res.height[spike] == pytest.approx(sign * 2 * h, abs=1e-12)
    # Nearest neighbours along a lattice axis (u = (-h, 0, -2h), v = (h, 0, -2h)):
    # cos = 3/5, 53.13 deg; every direction is flagged.
    assert res.angle[spike] == pytest.approx(math.degrees(math.acos(0.6)), abs=1e-9)
    assert res.flags[spike] == 0b1111
    assert res.iterations == 2
    assert not res.degenerate.any()
    np.testing.assert_allclose(np.delete(res.height, spike), 0.0, atol=1e-12)
    (d,) = res.defects
    assert d.id == 0 and d.count == 1 and d.indices.tolist() == [spike]
    assert d.kind == ("protrusion" if sign > 0 else "pit")
    assert d.peak_height == pytest.approx(sign * 2 * h, abs=1e-12)
    assert d.mean_height == d.peak_height
    np.testing.assert_allclose(d.normal, [0.0, 0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(d.centroid, pts[spike])
    assert d.extent == 0.0
    assert res.plane is not None
    np.testing.assert_allclose(res.plane.normal, [0.0, 0.0, 1.0], atol=1e-12)
    assert res.plane.n_points == pts.shape[0] - 1
    assert res.plane.rms < 1e-9


def test_spike_on_tilted_plane_far_from_origin() -> None:
    h = 0.5
    base = lattice(21, h)
    # Rotate the lattice 20 deg about x, then move it far away (robot base frame).
    a = math.radians(20.0)
    rot = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    nrm = rot @ np.array([0.0, 0.0, 1.0])
    spike = 10 * 21 + 10
    pts = base @ rot.T + np.array([3.0e4, -2.0e4, 1.5e4])
    pts[spike] += 1.0 * nrm
    res = paper_detect_points(pts)
    assert np.flatnonzero(res.labels != N).tolist() == [spike]
    assert res.labels[spike] == A
    assert res.height[spike] == pytest.approx(1.0, abs=1e-9)
    assert res.angle[spike] == pytest.approx(math.degrees(math.acos(0.6)), abs=1e-6)
    (d,) = res.defects
    np.testing.assert_allclose(d.normal, nrm, atol=1e-9)
    assert d.kind == "protrusion"


def test_lone_far_point_is_isolated_dust() -> None:
    pts = lattice(15, 1.0)
    pts = np.vstack([pts, [7.0, 7.0, 50.0]])
    res = paper_detect_points(pts)
    lone = pts.shape[0] - 1
    assert np.flatnonzero(res.labels != N).tolist() == [lone]
    assert res.flags[lone] == 0
    assert math.isnan(res.angle[lone])
    assert math.isnan(res.height[lone])  # no NORMAL point within radius
    (d,) = res.defects
    assert d.kind == "isolated" and d.indices.tolist() == [lone]
    assert math.isnan(d.peak_height) and math.isnan(d.mean_height)
    assert np.all(np.isnan(d.normal))
    assert res.iterations == 2  # pass 1 found a new ABNORMAL point, pass 2 found none


@pytest.mark.parametrize("size", [2, 3])
def test_floating_group_is_abnormal(size: int) -> None:
    pts = lattice(15, 1.0)
    group = np.array([[3.0, 3.0, 20.0], [3.5, 3.0, 20.0], [3.0, 3.5, 20.0]])[:size]
    pts = np.vstack([pts, group])
    res = paper_detect_points(pts)
    rows = list(range(225, 225 + size))
    assert np.flatnonzero(res.labels != N).tolist() == rows
    (d,) = res.defects  # 0.5 apart, link = radius = 3: one defect
    assert d.indices.tolist() == rows and d.kind == "isolated"
    np.testing.assert_allclose(d.centroid, group.mean(axis=0))


def test_two_wide_burr_needs_scale_two() -> None:
    h = 1.0
    pts = lattice(15, h)
    burr = [7 * 15 + 7, 7 * 15 + 8]
    pts[burr, 2] = 4.0
    # Scale 1: along the burr, the other burr point (level with it) is the nearest neighbour:
    # u = (1, 0, 0), v = (-1, 0, -4), an obtuse angle, so that direction is not flagged.
    res1 = paper_detect_points(pts, radius=6.0)
    assert not (res1.labels == A).any()
    assert np.all(res1.labels[burr] == E)
    assert res1.defects == []
    # Scale 2 with min_step = 0.4: the neighbours must be >= 3 * 0.4 = 1.2 away in the tangent
    # plane (scale s: (2s - 1) * min_step), so
    # the search passes over the other burr point onto the flat lattice, 2 cells away on both
    # sides: u = (-2, 0, -4), v = (2, 0, -4), cos = 12/20, 53.1 deg, flagged.
    res2 = paper_detect_points(pts, radius=6.0, scales=(1, 2), min_step=0.4)
    assert np.flatnonzero(res2.labels == A).tolist() == burr
    assert np.all(res2.flags[burr] == 0b1111)
    (d,) = res2.defects
    assert d.indices.tolist() == burr and d.count == 2
    assert d.peak_height == pytest.approx(4.0, abs=1e-12)
    assert d.extent == pytest.approx(1.0, abs=1e-12)  # two points 1 apart about their centroid


def test_crease_bend_of_30_degrees_is_all_normal() -> None:
    # z = 0 for x <= 0, z = tan(30 deg) x for x > 0: every interior angle is >= 105 deg.
    h = 0.5
    j, i = np.mgrid[0:21, -10:11]
    x, y = i.ravel() * h, j.ravel() * h
    z = np.where(x > 0, x * math.tan(math.radians(30.0)), 0.0)
    res = paper_detect_points(np.c_[x, y, z])
    assert np.all(res.labels == N)
    assert np.nanmin(res.angle) >= 105.0
    assert res.defects == []


def test_sharp_ridge_of_30_degrees_crest_not_abnormal() -> None:
    # Two faces meeting at 30 deg along the y axis, sampled every h along each face.
    h = 0.5
    half = math.radians(15.0)
    rows = []
    for yy in np.arange(21) * h:
        rows.append([0.0, yy, 0.0])
        for s in np.arange(1, 11) * h:
            rows.append([s * math.sin(half), yy, -s * math.cos(half)])
            rows.append([-s * math.sin(half), yy, -s * math.cos(half)])
    pts = np.array(rows)
    res = paper_detect_points(pts)
    crest = pts[:, 0] == 0.0
    assert crest.sum() == 21
    assert not np.any(res.labels[crest] == A)
    assert not np.any(res.labels == A)


def test_jacobi_passes_monotone() -> None:
    pts = noisy_cloud(4, n=500)
    prev = None
    for iters in (1, 2, 3, 10):
        res = paper_detect_points(pts, max_iterations=iters)
        assert 1 <= res.iterations <= iters
        abn = res.labels == A
        if prev is not None:
            assert np.all(abn[prev])  # once ABNORMAL, always ABNORMAL
        prev = abn


def test_defects_link_and_order() -> None:
    h = 1.0
    pts = lattice(25, h)
    s1, s2 = 6 * 25 + 6, 6 * 25 + 18  # 12 apart
    pts[s1, 2] = 2.5
    pts[s2, 2] = -3.0
    res = paper_detect_points(pts, radius=4.0)
    assert np.flatnonzero(res.labels == A).tolist() == [s1, s2]
    d0, d1 = res.defects
    assert (d0.id, d1.id) == (0, 1)
    assert d0.indices.tolist() == [s2] and d0.kind == "pit"  # |-3.0| > |2.5|
    assert d1.indices.tolist() == [s1] and d1.kind == "protrusion"
    assert res.params["link"] == 4.0
    gap = math.sqrt(12.0 * 12.0 + 5.5 * 5.5)  # 3-D distance between the two points
    res = paper_detect_points(pts, radius=4.0, link=gap)  # distance <= link: one defect
    (d,) = res.defects
    assert d.indices.tolist() == [s1, s2]
    assert d.peak_height == pytest.approx(-3.0, abs=1e-12)
    assert d.mean_height == pytest.approx(-0.25, abs=1e-12)
    assert d.extent == pytest.approx(12.0, abs=1e-12)
    assert d.kind == "pit"
    below = float(np.nextafter(gap, 0.0))
    assert len(paper_detect_points(pts, radius=4.0, link=below).defects) == 2


def test_defaults_recorded_on_known_lattice() -> None:
    h = 0.25
    pts = lattice(12, h, m=9)
    res = paper_detect_points(pts)
    off = {"min_group": 0, "edge_extent": 0.0, "height_tolerance": None,
           "merge_distance": 0.0, "merged": 0, "edge_tolerance": None, "edge_radius": None,
           "isolated_tolerance": None}
    assert res.params == {"spacing": h, "radius": 5 * h, "min_step": 0.5 * h, "link": 5 * h,
                          "K": 4, "height_radius": 10 * h, **off}
    assert isinstance(res.params["K"], int)
    res = paper_detect_points(pts, radius=1.0, min_step=0.1, K=6)
    assert res.params == {"spacing": h, "radius": 1.0, "min_step": 0.1, "link": 1.0, "K": 6,
                          "height_radius": 2.0, **off}
    res = paper_detect_points(pts, link=0.3)
    assert res.params["link"] == 0.3 and res.params["radius"] == 5 * h
    assert np.all(res.labels == N)


def test_spacing_median_and_duplicates() -> None:
    # Nearest-other distances 1, 1, 3, 3 (median of an even count: mean of the middle two).
    line = np.array([[0.0, 0, 0], [1.0, 0, 0], [10.0, 0, 0], [13.0, 0, 0]])
    res = paper_detect_points(line, radius=100.0)
    assert res.params["spacing"] == 2.0
    # Collinear: every neighbourhood plane is degenerate -> NORMAL, reported as degenerate.
    assert np.all(res.labels == N) and np.all(res.degenerate)
    assert np.all(np.isnan(res.angle)) and np.all(res.flags == 0)
    # A duplicated point is at distance 0 from its twin.
    pts = lattice(6, 1.0)
    dup = np.vstack([pts, pts[:5]])
    res = paper_detect_points(dup)
    assert res.params["spacing"] == 1.0
    # More than half duplicates: merged (SPEC "Duplicate points"), the spacing is the lattice's.
    both = paper_detect_points(np.vstack([pts, pts]))
    assert both.params["spacing"] == 1.0 and both.params["merged"] == len(pts)
    with pytest.raises(ValueError, match="one point"):
        paper_detect_points(np.vstack([pts[:1]] * 5))


def test_nonfinite_rows_are_invalid_and_indices_are_input_rows() -> None:
    h = 0.5
    pts = lattice(21, h)
    spike = 10 * 21 + 10
    pts[spike, 2] = 1.0
    bad = np.array([[np.nan, 0, 0], [0, np.inf, 0], [0, 0, -np.inf]])
    cloud = np.vstack([bad, pts])
    res = paper_detect_points(cloud)
    assert res.labels[:3].tolist() == [INV] * 3
    assert np.all(res.flags[:3] == 0)
    assert np.all(np.isnan(res.angle[:3])) and np.all(np.isnan(res.height[:3]))
    assert not res.degenerate[:3].any()
    (d,) = res.defects
    assert d.indices.tolist() == [spike + 3]
    ref_res = paper_detect_points(pts)
    np.testing.assert_array_equal(res.labels[3:], ref_res.labels)
    np.testing.assert_array_equal(res.height[3:], ref_res.height)
    assert res.params == ref_res.params


def test_result_dtypes_and_shapes() -> None:
    pts = noisy_cloud(5, n=200)
    res = paper_detect_points(pts)
    n = pts.shape[0]
    assert res.labels.shape == (n,) and res.labels.dtype == np.uint8
    assert res.flags.shape == (n,) and res.flags.dtype == np.uint8
    assert res.angle.shape == (n,) and res.angle.dtype == np.float64
    assert res.height.shape == (n,) and res.height.dtype == np.float64
    assert res.degenerate.shape == (n,) and res.degenerate.dtype == np.bool_
    assert set(np.unique(res.labels)) <= {N, A, E, INV}
    assert res.plane is not None
    flagged = res.flags != 0
    assert np.all(np.isfinite(res.angle[flagged]))
    assert np.all(res.angle[flagged] <= 75.0 + 1e-9)
    # ABNORMAL points in defects, each exactly once.
    members = np.sort(np.concatenate([d.indices for d in res.defects]))
    np.testing.assert_array_equal(members, np.flatnonzero(res.labels == A))
    peaks = [abs(d.peak_height) for d in res.defects if not math.isnan(d.peak_height)]
    assert peaks == sorted(peaks, reverse=True)


def test_k_eight_sets_all_bits() -> None:
    # A fine lattice so that every 22.5 deg sector holds a close neighbour of the spike.
    h = 0.25
    pts = lattice(29, h)
    spike = 14 * 29 + 14
    pts[spike, 2] = 2.0
    res = paper_detect_points(pts, K=8, radius=3.5)
    assert np.flatnonzero(res.labels != N).tolist() == [spike]
    assert res.labels[spike] == A
    assert int(res.flags[spike]) == (1 << 8) - 1
    # Closest pair: the two axis neighbours h away on either side.
    assert res.angle[spike] == pytest.approx(2.0 * math.degrees(math.atan(h / 2.0)), abs=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_permutation_invariance(seed: int) -> None:
    pts = noisy_cloud(seed + 10, n=600)
    perm = np.random.default_rng(seed).permutation(pts.shape[0])
    a = paper_detect_points(pts, scales=(1, 2))
    b = paper_detect_points(pts[perm], scales=(1, 2))
    np.testing.assert_array_equal(b.labels, a.labels[perm])
    np.testing.assert_array_equal(b.flags, a.flags[perm])
    np.testing.assert_array_equal(b.degenerate, a.degenerate[perm])
    np.testing.assert_allclose(b.angle, a.angle[perm], rtol=0, atol=1e-9)
    np.testing.assert_allclose(b.height, a.height[perm], rtol=0, atol=1e-9)
    assert b.params == pytest.approx(a.params)
    groups_a = {frozenset(d.indices.tolist()) for d in a.defects}
    groups_b = {frozenset(perm[d.indices].tolist()) for d in b.defects}
    assert groups_a == groups_b


def test_float32_and_integer_input() -> None:
    pts = noisy_cloud(6, n=300)
    p32 = pts.astype(np.float32)
    a = paper_detect_points(p32)
    b = paper_detect_points(p32.astype(np.float64))
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_array_equal(a.height, b.height)
    ints = lattice(10, 2.0).astype(np.int64)
    ints[55, 2] = 4
    res = paper_detect_points(ints)
    assert np.flatnonzero(res.labels == A).tolist() == [55]
    assert res.params["spacing"] == 2.0


def test_does_not_modify_input() -> None:
    pts = noisy_cloud(7, n=200)
    before = pts.copy()
    paper_detect_points(pts)
    ref.estimate_normals(pts, 1.0)
    np.testing.assert_array_equal(pts, before)


# --------------------------------------------------------------------------------------------
# estimate_normals
# --------------------------------------------------------------------------------------------


def test_estimate_normals_plane() -> None:
    rng = np.random.default_rng(8)
    xy = rng.uniform(-5.0, 5.0, (400, 2))
    pts = np.c_[xy, 0.5 * xy[:, 0] - 0.25 * xy[:, 1] + 100.0]
    res = ref.estimate_normals(pts, 1.5)
    expected = np.array([-0.5, 0.25, 1.0]) / math.sqrt(1.3125)
    d = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=2)
    count = (d <= 1.5).sum(axis=1)
    np.testing.assert_array_equal(res.count, count)
    assert res.count.dtype == np.int64
    ok = count >= 3
    np.testing.assert_array_equal(res.valid, ok)
    np.testing.assert_allclose(res.normals[ok], np.broadcast_to(expected, (ok.sum(), 3)), atol=1e-9)
    assert np.all(res.rms[ok] < 1e-6)


def test_estimate_normals_sphere_radial() -> None:
    # Fibonacci sphere of radius R: the local plane normal is the radial direction, oriented
    # n_z > 0.
    n, big_r = 3000, 10.0
    k = np.arange(n) + 0.5
    phi = np.arccos(1.0 - 2.0 * k / n)
    theta = math.pi * (1.0 + math.sqrt(5.0)) * k
    radial = np.c_[np.sin(phi) * np.cos(theta), np.sin(phi) * np.sin(theta), np.cos(phi)]
    pts = big_r * radial
    res = ref.estimate_normals(pts, 1.5)
    assert res.valid.all()
    away = np.abs(radial[:, 2]) > 0.2  # away from the equator, where n_z changes sign
    expected = radial * np.sign(radial[:, 2])[:, None]
    cos = np.sum(res.normals[away] * expected[away], axis=1)
    assert np.all(cos > math.cos(math.radians(2.0)))  # the poles are sampled unevenly
    assert np.median(cos) > math.cos(math.radians(0.5))
    assert np.all(res.normals[:, 2] >= 0.0)
    np.testing.assert_allclose(np.linalg.norm(res.normals, axis=1), 1.0, atol=1e-12)
    # A cap of chord radius a on a sphere of radius R has sagitta ~ a^2 / (2 R): rms is small
    # but non-zero.
    assert np.all(res.rms > 0.0) and np.all(res.rms < 1.5**2 / (2 * big_r))


def test_estimate_normals_invalid_cases() -> None:
    line = np.c_[np.arange(10.0), 2.0 * np.arange(10.0), np.zeros(10)]
    res = ref.estimate_normals(line, 5.0)
    assert not res.valid.any()
    assert np.all(np.isnan(res.normals)) and np.all(np.isnan(res.rms))
    assert res.count.tolist() == [3, 4, 5, 5, 5, 5, 5, 5, 4, 3]  # |step| = sqrt(5) < 2.5
    pts = np.vstack([lattice(5, 1.0), [[np.nan, 0, 0], [50.0, 50.0, 50.0], [50.0, 50.0, 50.0]]])
    res = ref.estimate_normals(pts, 1.5)
    assert res.valid[:25].all()
    assert res.count[25] == 0 and not res.valid[25]
    assert res.count[26] == 2 and res.count[27] == 2  # a duplicated pair: too few points
    assert not res.valid[26:].any()
    # Three coincident points: enough points, but all equal -> degenerate.
    res = ref.estimate_normals(np.zeros((3, 3)), 1.0)
    assert res.count.tolist() == [3, 3, 3] and not res.valid.any()
    # Empty and all-NaN clouds give empty / all-invalid results.
    res = ref.estimate_normals(np.zeros((0, 3)), 1.0)
    assert res.normals.shape == (0, 3) and res.valid.shape == (0,)
    res = ref.estimate_normals(np.full((4, 3), np.nan), 1.0)
    assert not res.valid.any() and res.count.tolist() == [0] * 4


# --------------------------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"radius": 0.0}, "radius"),
        ({"radius": -1.0}, "radius"),
        ({"radius": math.nan}, "radius"),
        ({"radius": math.inf}, "radius"),
        ({"radius": True}, "radius"),
        ({"radius": "1"}, "radius"),
        ({"K": 1}, "K"),
        ({"K": 4.0}, "K"),
        ({"K": True}, "K"),
        ({"K": ref.MAX_K + 1}, "K"),
        ({"min_step": -0.1}, "min_step"),
        ({"min_step": math.nan}, "min_step"),
        ({"link": 0.0}, "link"),
        ({"link": -2.0}, "link"),
        ({"link": math.inf}, "link"),
        ({"min_directions": 0}, "min_directions"),
        ({"min_directions": 5}, "min_directions"),
        ({"min_directions": 7, "K": 6}, "min_directions"),
        ({"theta0": 0.0}, "theta0"),
        ({"theta0": 180.0}, "theta0"),
        ({"scales": ()}, "scales"),
        ({"scales": (0,)}, "scales"),
        ({"max_iterations": 0}, "max_iterations"),
    ],
)
def test_detect_points_bad_parameters(kwargs: dict, name: str) -> None:
    with pytest.raises(ValueError, match=name):
        paper_detect_points(lattice(6, 1.0), **kwargs)


def test_detect_points_accepts_numpy_scalars_and_edge_values() -> None:
    pts = lattice(8, 1.0)
    res = paper_detect_points(
        pts, radius=np.float32(2.5), K=np.int64(6), min_step=0, link=np.float64(1.0)
    )
    assert res.params["K"] == 6 and res.params["min_step"] == 0.0
    res = paper_detect_points(pts, min_directions=6, K=6)
    assert np.all(res.labels == N)


@pytest.mark.parametrize(
    "points",
    [
        np.zeros((5, 2)),
        np.zeros((5, 3, 1)),
        np.zeros(3),
        np.zeros((5, 3), dtype=complex),
        np.array([["a", "b", "c"]] * 4),
        np.array([[1.0, 2.0, 3.0]] * 4, dtype=object),
        np.zeros((2, 3)),
        np.array([[0.0, 0, 0], [1, 0, 0], [np.nan, 0, 0], [0, 1, np.inf]]),
    ],
)
def test_detect_points_bad_points(points: Any) -> None:
    with pytest.raises(ValueError, match="points"):
        paper_detect_points(points)


@pytest.mark.parametrize("radius", [0.0, -1.0, math.nan, math.inf, None, "2"])
def test_estimate_normals_bad_radius(radius: Any) -> None:
    with pytest.raises(ValueError, match="radius"):
        ref.estimate_normals(lattice(4, 1.0), radius)


@pytest.mark.parametrize(
    "points", [np.zeros((5, 2)), np.zeros((2, 2, 3)), np.zeros((4, 3), dtype=complex)]
)
def test_estimate_normals_bad_points(points: np.ndarray) -> None:
    with pytest.raises(ValueError, match="points"):
        ref.estimate_normals(points, 1.0)
