"""Tests of the NumPy reference (``miem.reference``) alone.

Expected values come from geometry worked out by hand (planes, triangles, spikes, ridges) or from
a literal, per-cell transcription of the docs/SPEC.md pseudo-code written below; never from an
earlier run of the reference itself.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from miem import reference as ref

# These tests pin the paper's semantics: every call runs preset="paper" (explicit arguments
# and another preset still win).
paper_detect = functools.partial(ref.detect, preset="paper")

N, A, E, INV = ref.NORMAL, ref.ABNORMAL, ref.EDGE, ref.INVALID


def flat_grid(h: int, w: int, dx: float = 1.0, dy: float = 1.0) -> np.ndarray:
    """Grid ``(h, w, 3)`` on z = 0 with x = c * dx, y = r * dy."""
    r, c = np.mgrid[0:h, 0:w]
    g = np.zeros((h, w, 3))
    g[..., 0] = c * dx
    g[..., 1] = r * dy
    return g


# --------------------------------------------------------------------------------------------
# fit_plane
# --------------------------------------------------------------------------------------------


def test_fit_plane_known_plane() -> None:
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-10, 10, (2, 200))
    pts = np.c_[x, y, 0.3 * x - 0.2 * y + 5.0]
    plane = ref.fit_plane(pts)
    # z - 0.3 x + 0.2 y - 5 = 0  ->  n = (-0.3, 0.2, 1) / |.|, d = -5 / |.|
    norm = math.sqrt(0.09 + 0.04 + 1.0)
    np.testing.assert_allclose(plane.normal, [-0.3 / norm, 0.2 / norm, 1.0 / norm], atol=1e-12)
    assert plane.d == pytest.approx(-5.0 / norm, abs=1e-12)
    # rms = sqrt(l0 / N): l0 carries round-off of order eps * l2, so its square root is ~1e-8
    assert plane.rms < 1e-6
    assert plane.n_points == 200
    np.testing.assert_allclose(plane.centroid, pts.mean(axis=0), atol=1e-12)
    np.testing.assert_allclose(plane.distance(pts), 0.0, atol=1e-11)
    # A point 2 units along the normal above the plane.
    above = pts[0] + 2.0 * plane.normal
    assert plane.distance(above) == pytest.approx(2.0, abs=1e-12)
    assert plane.distance(above[None, None, :]).shape == (1, 1)


def test_fit_plane_drops_nonfinite_and_accepts_any_leading_shape() -> None:
    rng = np.random.default_rng(1)
    x, y = rng.uniform(-1, 1, (2, 20))
    pts = np.c_[x, y, 2.0 * x + 1.0].reshape(4, 5, 3)
    pts[0, 0] = [np.nan, 0.0, 0.0]
    pts[1, 2, 2] = np.inf
    plane = ref.fit_plane(pts)
    assert plane.n_points == 18
    norm = math.sqrt(5.0)
    np.testing.assert_allclose(plane.normal, [-2.0 / norm, 0.0, 1.0 / norm], atol=1e-12)
    assert plane.d == pytest.approx(-1.0 / norm, abs=1e-12)


@pytest.mark.parametrize("method", ["eigen", "lstsq"])
def test_fit_plane_orientation_nz_positive(method: str) -> None:
    rng = np.random.default_rng(2)
    for _ in range(20):
        a, b = rng.uniform(-3, 3, 2)
        x, y = rng.uniform(-5, 5, (2, 30))
        pts = np.c_[x, y, a * x + b * y + rng.normal(0, 0.01, 30)]
        for p in (pts, pts[::-1], -pts):
            assert ref.fit_plane(p, method=method).normal[2] > 0


def test_fit_plane_orientation_vertical_planes() -> None:
    rng = np.random.default_rng(3)
    u, v = rng.uniform(-5, 5, (2, 40))
    # x = const: normal (1, 0, 0), first non-zero component positive.
    plane = ref.fit_plane(np.c_[np.full(40, 2.0), u, v])
    np.testing.assert_allclose(plane.normal, [1.0, 0.0, 0.0], atol=1e-15)
    assert plane.d == pytest.approx(-2.0, abs=1e-12)
    # y = const: normal (0, 1, 0).
    plane = ref.fit_plane(np.c_[u, np.full(40, -3.0), v])
    np.testing.assert_allclose(plane.normal, [0.0, 1.0, 0.0], atol=1e-15)
    assert plane.d == pytest.approx(3.0, abs=1e-12)


@pytest.mark.parametrize("method", ["eigen", "lstsq"])
def test_fit_plane_rms_checkerboard(method: str) -> None:
    # z = +-h in a checkerboard on a symmetric 4 x 4 layout: the best plane is z = 0 and every
    # point is h away from it, so rms == h.
    h = 0.125
    r, c = np.mgrid[0:4, 0:4]
    z = np.where((r + c) % 2 == 0, h, -h)
    pts = np.c_[c.ravel() - 1.5, r.ravel() - 1.5, z.ravel()]
    plane = ref.fit_plane(pts, method=method)
    assert plane.rms == pytest.approx(h, rel=1e-12)
    np.testing.assert_allclose(plane.normal, [0.0, 0.0, 1.0], atol=1e-12)


def test_fit_plane_lstsq_equals_eigen_on_exact_plane() -> None:
    rng = np.random.default_rng(4)
    x, y = rng.uniform(-10, 10, (2, 50))
    pts = np.c_[x, y, -0.7 * x + 1.3 * y - 2.0]
    pe = ref.fit_plane(pts, method="eigen")
    pl = ref.fit_plane(pts, method="lstsq")
    np.testing.assert_allclose(pl.normal, pe.normal, atol=1e-12)
    assert pl.d == pytest.approx(pe.d, abs=1e-10)
    assert pl.rms == pytest.approx(0.0, abs=1e-12)


def test_fit_plane_lstsq_matches_numpy_lstsq_on_noisy_data() -> None:
    rng = np.random.default_rng(5)
    x, y = rng.uniform(-10, 10, (2, 100))
    z = 0.4 * x + 0.1 * y + 3.0 + rng.normal(0, 0.5, 100)
    pts = np.c_[x, y, z]
    (a, b, e), *_ = np.linalg.lstsq(np.c_[x, y, np.ones(100)], z, rcond=None)
    n = np.array([-a, -b, 1.0]) / math.hypot(a, b, 1.0)
    plane = ref.fit_plane(pts, method="lstsq")
    np.testing.assert_allclose(plane.normal, n, atol=1e-12)
    assert plane.d == pytest.approx(-e * n[2], abs=1e-10)  # the plane passes through (0, 0, e)
    rms = math.sqrt(np.mean(((pts - pts.mean(axis=0)) @ n) ** 2))
    assert plane.rms == pytest.approx(rms, rel=1e-10)
    # The orthogonal (eigen) fit has the smaller RMS orthogonal distance.
    assert ref.fit_plane(pts).rms <= plane.rms


def test_fit_plane_far_from_origin() -> None:
    rng = np.random.default_rng(6)
    x, y = rng.uniform(-5, 5, (2, 100))
    pts = np.c_[x, y, 0.1 * x + rng.normal(0, 1e-3, 100)]
    p0 = ref.fit_plane(pts)
    p1 = ref.fit_plane(pts + [1e5, -2e5, 1e5])
    np.testing.assert_allclose(p1.normal, p0.normal, atol=1e-9)
    assert p1.rms == pytest.approx(p0.rms, rel=1e-6)


@pytest.mark.parametrize(
    "pts",
    [
        np.full((10, 3), np.nan),
        np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [np.nan, 0.0, 0.0]]),
        np.zeros((0, 3)),
        np.ones((5, 3)),  # all equal
        np.c_[np.arange(6.0), 2.0 * np.arange(6.0), -np.arange(6.0)],  # collinear
    ],
)
@pytest.mark.parametrize("method", ["eigen", "lstsq"])
def test_fit_plane_errors(pts: np.ndarray, method: str) -> None:
    with pytest.raises(ValueError, match="points"):
        ref.fit_plane(pts, method=method)


def test_fit_plane_bad_input() -> None:
    good = np.random.default_rng(7).normal(size=(10, 3))
    with pytest.raises(ValueError, match="points"):
        ref.fit_plane(good[:, :2])
    with pytest.raises(ValueError, match="points"):
        ref.fit_plane(np.array([["a", "b", "c"]] * 4))
    with pytest.raises(ValueError, match="points"):
        ref.fit_plane(good > 0)
    with pytest.raises(ValueError, match="method"):
        ref.fit_plane(good, method="ransac")
    # vertical plane: the least-squares model z = f(x, y) is singular
    u, v = np.random.default_rng(8).uniform(size=(2, 10))
    with pytest.raises(ValueError, match="points"):
        ref.fit_plane(np.c_[np.zeros(10), u, v], method="lstsq")
    # integer input is fine
    plane = ref.fit_plane(np.array([[0, 0, 1], [1, 0, 1], [0, 1, 1], [1, 1, 1]]))
    np.testing.assert_allclose(plane.normal, [0, 0, 1], atol=1e-15)
    assert plane.d == pytest.approx(-1.0)


# --------------------------------------------------------------------------------------------
# Scan lines
# --------------------------------------------------------------------------------------------


def test_scan_line_angles_triangles_and_straight_line() -> None:
    right = np.array([[1.0, 0, 0], [0, 0, 0], [0, 1.0, 0]])
    out = ref.scan_line_angles(right)
    assert out.shape == (3,) and out.dtype == np.float64
    assert np.isnan(out[0]) and np.isnan(out[2])
    assert out[1] == pytest.approx(90.0, abs=1e-12)

    equilateral = np.array([[1.0, 0, 0], [0, 0, 0], [0.5, math.sqrt(3) / 2, 0]])
    assert ref.scan_line_angles(equilateral)[1] == pytest.approx(60.0, abs=1e-9)

    line = np.c_[np.arange(6.0), 2 * np.arange(6.0), -np.arange(6.0)]
    np.testing.assert_allclose(ref.scan_line_angles(line)[1:-1], 180.0, atol=1e-6)


def test_scan_line_angles_nan_rules_and_step() -> None:
    pts = np.array(
        [[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [2, 0, 0], [3, 0, 1], [4, 0, np.nan], [5, 0, 0]]
    )
    out = ref.scan_line_angles(pts)
    assert np.isnan(out[0]) and np.isnan(out[-1])
    assert out[1] == pytest.approx(180.0)
    assert np.isnan(out[2]) and np.isnan(out[3])  # duplicate point: zero-length u or v
    assert np.isnan(out[4]) and np.isnan(out[5])  # a non-finite point among the three
    # step = 2: at i = 2, A = P0, B = P4: u = (-2, 0, 0), v = (1, 0, 1) -> 135 degrees
    out2 = ref.scan_line_angles(pts, step=2)
    assert np.all(np.isnan(out2[[0, 1, 5, 6]]))
    assert out2[2] == pytest.approx(135.0, abs=1e-12)
    assert np.all(np.isnan(ref.scan_line_angles(pts[:2])))
    with pytest.raises(ValueError, match="step"):
        ref.scan_line_angles(pts, step=0)
    with pytest.raises(ValueError, match="step"):
        ref.scan_line_angles(pts, step=True)
    with pytest.raises(ValueError, match="line"):
        ref.scan_line_angles(pts[:, :2])


def test_scan_line_heights_eq20_by_hand() -> None:
    # Profile in the x-z plane: P0 (0,0), P1 (1,0), P2 (2,1), P3 (3,1).
    # theta_1 = angle(P0 - P1, P2 - P1) = 135 deg; D_2 = sin 135 * |P2 - P1| = (sqrt2/2) sqrt2 = 1,
    # the height of P2 over the line P0 P1 (the x axis).
    # theta_2 = 135 deg; D_3 = sin 135 * 1 = 1/sqrt2, the distance of P3 from the line z = x - 1.
    line = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 1], [3, 0, 1]])
    out = ref.scan_line_heights(line)
    assert np.isnan(out[0]) and np.isnan(out[1])
    assert out[2] == pytest.approx(1.0, abs=1e-12)
    assert out[3] == pytest.approx(1.0 / math.sqrt(2.0), abs=1e-12)


def test_scan_line_heights_straight_and_step() -> None:
    line = np.c_[np.arange(8.0), np.zeros(8), np.zeros(8)]
    line[5, 2] = 0.5  # P5 sits 0.5 over the straight run P3 P4
    out = ref.scan_line_heights(line)
    assert out[3] == pytest.approx(0.0, abs=1e-12)
    assert out[5] == pytest.approx(0.5, abs=1e-12)
    out2 = ref.scan_line_heights(line, step=2)
    assert np.all(np.isnan(out2[:4]))
    assert out2[4] == pytest.approx(0.0, abs=1e-12)
    # D_5 = sin(theta_3) |P5 - P3| with theta_3 = angle(P1 - P3, P5 - P3): 0.5 over line P1 P3
    assert out2[5] == pytest.approx(0.5, abs=1e-12)
    # D_7 = sin(theta_5) |P7 - P5|: the distance of P7 (7, 0) from the line P3 (3, 0) P5 (5, 0.5)
    assert out2[7] == pytest.approx(2.0 / math.sqrt(4.25), abs=1e-12)
    line[6] = np.nan
    out3 = ref.scan_line_heights(line)
    assert np.isnan(out3[6]) and np.isnan(out3[7])


# --------------------------------------------------------------------------------------------
# detect: hand-made grids
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("h", [5.0, -5.0])
def test_detect_single_spike(h: float) -> None:
    g = flat_grid(9, 9)
    g[4, 4, 2] = h
    res = paper_detect(g)
    expected = np.zeros((9, 9), dtype=np.uint8)
    expected[4, 4] = A
    np.testing.assert_array_equal(res.labels, expected)
    assert res.labels.dtype == np.uint8 and res.flags.dtype == np.uint8
    assert res.flags[4, 4] == 15
    assert np.count_nonzero(res.flags) == 1
    # smallest angle: along the profile / across, 2 atan(1 / |h|)
    assert res.angle[4, 4] == pytest.approx(math.degrees(2 * math.atan(1 / abs(h))), abs=1e-9)
    # the window plane of the NORMAL cells is z = 0
    assert res.height[4, 4] == pytest.approx(h, abs=1e-12)
    np.testing.assert_allclose(np.delete(res.height.ravel(), 40), 0.0, atol=1e-12)
    assert res.iterations == 2
    assert res.plane is not None
    np.testing.assert_allclose(res.plane.normal, [0, 0, 1], atol=1e-12)
    assert res.plane.d == pytest.approx(0.0, abs=1e-12)
    assert res.plane.n_points == 80
    assert res.plane.rms == pytest.approx(0.0, abs=1e-12)
    # corners: no direction available; elsewhere straight runs
    assert np.isnan(res.angle[0, 0]) and np.isnan(res.angle[8, 8])
    assert res.angle[0, 4] == pytest.approx(180.0)
    (d,) = res.defects
    assert d.id == 0 and d.count == 1
    np.testing.assert_array_equal(d.indices, [40])
    assert d.indices.dtype == np.int64
    np.testing.assert_allclose(d.centroid, [4.0, 4.0, h])
    np.testing.assert_allclose(d.normal, [0, 0, 1], atol=1e-12)
    assert d.peak_height == pytest.approx(h, abs=1e-12)
    assert d.mean_height == pytest.approx(h, abs=1e-12)
    assert d.extent == 0.0
    assert d.kind == ("protrusion" if h > 0 else "pit")


def test_detect_spike_on_tilted_plane() -> None:
    g = flat_grid(9, 9)
    g[..., 2] = 0.1 * g[..., 0] + 0.2 * g[..., 1]
    g[4, 4, 2] += 3.0
    res = paper_detect(g)
    assert res.labels[4, 4] == A
    assert np.count_nonzero(res.labels) == 1
    # a vertical offset of 3 over the plane z = 0.1 x + 0.2 y is 3 n_z along its normal
    assert res.height[4, 4] == pytest.approx(3.0 / math.sqrt(1.05), abs=1e-12)
    np.testing.assert_allclose(np.delete(res.height.ravel(), 40), 0.0, atol=1e-12)
    np.testing.assert_allclose(
        res.defects[0].normal, np.array([-0.1, -0.2, 1.0]) / math.sqrt(1.05), atol=1e-12
    )


def test_detect_spike_neighbours_edge_then_normal() -> None:
    # theta0 = 120: in pass 1 each of the 8 neighbours of a tall spike sees it at ~101-106 deg in
    # exactly one direction (EDGE, one flag bit); once the spike is removed the gap is bridged
    # and they become NORMAL again.
    g = flat_grid(9, 9)
    g[4, 4, 2] = 5.0
    one = paper_detect(g, theta0=120.0, max_iterations=1)
    assert one.iterations == 1
    expected_flags = {
        (4, 3): 1, (4, 5): 1, (3, 4): 2, (5, 4): 2,
        (3, 3): 4, (5, 5): 4, (3, 5): 8, (5, 3): 8,
    }  # fmt: skip
    for (r, c), bit in expected_flags.items():
        assert one.labels[r, c] == E
        assert one.flags[r, c] == bit
    # (4, 5) along the profile: u = (-1, 0, 5), v = (1, 0, 0)
    assert one.angle[4, 5] == pytest.approx(math.degrees(math.acos(-1 / math.sqrt(26))))
    assert one.labels[4, 4] == A
    assert np.count_nonzero(one.labels) == 9

    full = paper_detect(g, theta0=120.0)
    assert full.iterations == 2
    assert np.count_nonzero(full.labels) == 1 and full.labels[4, 4] == A
    assert np.count_nonzero(full.flags) == 1 and full.flags[4, 4] == 15
    # the ABNORMAL cell keeps the angle of the pass that judged it
    assert full.angle[4, 4] == pytest.approx(math.degrees(2 * math.atan(0.2)))
    assert full.angle[4, 5] == pytest.approx(180.0)


def test_detect_burr_two_wide_needs_scale_two() -> None:
    g = flat_grid(9, 9)
    g[4, 4, 2] = g[4, 5, 2] = 4.0
    # scale 1: along the profile each burr cell has a flat and a raised neighbour (104 deg):
    # 3 of 4 directions flagged -> EDGE (the paper misses 2-wide defects)
    res1 = paper_detect(g)
    assert res1.iterations == 1
    assert res1.labels[4, 4] == E and res1.labels[4, 5] == E
    assert res1.flags[4, 4] == 2 | 4 | 8 and res1.flags[4, 5] == 2 | 4 | 8
    assert np.count_nonzero(res1.labels) == 2
    assert res1.defects == []
    assert res1.height[4, 4] == pytest.approx(4.0, abs=1e-12)  # EDGE is not in the window plane

    # scale 2 along the profile: (-2, 0, -4) . (2, 0, -4) / 20 = 0.6 -> 53 deg, flagged
    res2 = paper_detect(g, scales=(1, 2))
    assert res2.iterations == 2
    assert res2.labels[4, 4] == A and res2.labels[4, 5] == A
    assert np.count_nonzero(res2.labels) == 2
    assert res2.flags[4, 4] == 15
    assert res2.angle[4, 4] == pytest.approx(math.degrees(math.acos(15 / 17)))  # across
    (d,) = res2.defects
    np.testing.assert_array_equal(d.indices, [40, 41])
    assert d.count == 2
    np.testing.assert_allclose(d.centroid, [4.5, 4.0, 4.0])
    assert d.peak_height == pytest.approx(4.0, abs=1e-12)
    assert d.mean_height == pytest.approx(4.0, abs=1e-12)
    assert d.extent == pytest.approx(1.0, abs=1e-12)  # 2 * 0.5 in the plane z = const
    assert d.kind == "protrusion"


def test_detect_ridge_is_edge_and_min_directions() -> None:
    # Roof z = -3 |c - 4|: the ridge is flagged along the profile (2 atan(1/3) = 36.9 deg) and
    # on both diagonals (acos(7/11) = 50.5 deg) but straight across profiles: EDGE.
    g = flat_grid(7, 9)
    g[..., 2] = -3.0 * np.abs(g[..., 0] - 4.0)
    res = paper_detect(g)
    assert res.iterations == 1
    np.testing.assert_array_equal(res.labels[:, 4], E)
    np.testing.assert_array_equal(res.flags[1:-1, 4], 1 | 4 | 8)
    np.testing.assert_array_equal(res.flags[[0, -1], 4], 1)  # ends: only along the profile
    assert np.count_nonzero(res.labels) == 7
    assert res.angle[3, 4] == pytest.approx(math.degrees(2 * math.atan(1 / 3)))
    assert res.defects == []

    res3 = paper_detect(g, min_directions=3)
    np.testing.assert_array_equal(res3.labels[1:-1, 4], A)
    np.testing.assert_array_equal(res3.labels[[0, -1], 4], E)  # a == 1 never makes ABNORMAL
    assert np.count_nonzero(res3.labels) == 7
    assert len(res3.defects) == 1 and res3.defects[0].count == 5


def test_detect_lone_point_in_nan_is_isolated_dust() -> None:
    g = np.full((12, 12, 3), np.nan)
    g[0:3, 0:3] = flat_grid(3, 3)
    g[9, 9] = [9.0, 9.0, 2.0]
    res = paper_detect(g)
    assert res.labels[9, 9] == A
    assert res.flags[9, 9] == 0 and np.isnan(res.angle[9, 9])
    np.testing.assert_array_equal(res.labels[0:3, 0:3], N)
    assert np.count_nonzero(res.labels == INV) == 144 - 10
    assert res.height[9, 9] == pytest.approx(2.0, abs=1e-12)  # the 3 x 3 block is in the window
    (d,) = res.defects
    assert d.kind == "isolated" and d.peak_height == pytest.approx(2.0)

    small = paper_detect(g, window=3)  # no NORMAL cell in the 3 x 3 window of the lone point
    assert np.isnan(small.height[9, 9])
    (d,) = small.defects
    assert d.kind == "isolated"
    assert np.isnan(d.peak_height) and np.isnan(d.mean_height)
    assert np.all(np.isnan(d.normal))
    assert d.extent == 0.0


def test_detect_isolation_depends_on_max_gap() -> None:
    g = np.full((7, 7, 3), np.nan)
    g[0:3, 0:3] = flat_grid(3, 3)
    g[2, 4] = [4.0, 2.0, 0.0]  # two cells from (2, 2), one NaN in between
    res = paper_detect(g, max_gap=1)
    assert res.labels[2, 4] == N  # not isolated; no direction has both neighbours
    assert res.flags[2, 4] == 0 and np.isnan(res.angle[2, 4])
    res0 = paper_detect(g, max_gap=0)
    assert res0.labels[2, 4] == A


def test_detect_max_gap_bridges_dropouts() -> None:
    g = flat_grid(5, 9)
    g[2, 4] = np.nan
    g[2, 2, 2] = 0.25  # gentle bump, never flagged
    res = paper_detect(g)
    assert res.labels[2, 4] == INV
    assert res.flags[2, 4] == 0 and np.isnan(res.angle[2, 4]) and np.isnan(res.height[2, 4])
    assert np.count_nonzero(res.labels) == 1
    # (2, 3) along the profile bridges the dropout: A = (2, 2) z = 0.25, B = (2, 5) z = 0:
    # u = (-1, 0, 0.25), v = (2, 0, 0); but across profiles it is straight (180 deg)
    assert res.angle[2, 3] == pytest.approx(math.degrees(math.acos(-1 / math.sqrt(1.0625))))


def test_detect_min_step() -> None:
    # Profiles 0.05 apart along, 1.0 across; a 0.1 bump reads as 53 deg between its immediate
    # neighbours (EDGE: flagged along the profile only), but with min_step = 0.5 the neighbours
    # are 10 cells (0.5) away: 2 atan(0.5 / 0.1) = 157 deg, not flagged.
    g = flat_grid(5, 40, dx=0.05, dy=1.0)
    g[2, 20, 2] = 0.1
    res = paper_detect(g)
    assert res.labels[2, 20] == E and res.flags[2, 20] == 1
    assert res.angle[2, 20] == pytest.approx(math.degrees(2 * math.atan(0.5)), abs=1e-9)
    res_s = paper_detect(g, min_step=0.5)
    assert res_s.labels[2, 20] == N and res_s.flags[2, 20] == 0
    assert res_s.angle[2, 20] == pytest.approx(math.degrees(2 * math.atan(5.0)), abs=1e-9)
    # max_reach too short to reach 0.5 away: along the profile becomes unavailable
    res_r = paper_detect(g, min_step=0.5, max_reach=3)
    assert res_r.labels[2, 20] == N
    assert res_r.angle[2, 20] > 160.0


def test_detect_defect_order_and_kinds() -> None:
    g = flat_grid(15, 15)
    g[3, 3, 2] = 5.0
    g[10, 10, 2] = -8.0
    g[10, 3, 2] = 5.0
    res = paper_detect(g)
    assert [d.id for d in res.defects] == [0, 1, 2]
    assert [int(d.indices[0]) for d in res.defects] == [10 * 15 + 10, 3 * 15 + 3, 10 * 15 + 3]
    assert [d.kind for d in res.defects] == ["pit", "protrusion", "protrusion"]
    assert res.defects[0].peak_height == pytest.approx(-8.0, abs=1e-12)


def test_detect_invalid_cells() -> None:
    rng = np.random.default_rng(9)
    g = flat_grid(10, 10)
    g[..., 2] = rng.normal(0, 0.05, (10, 10))
    g[1, 2] = np.nan
    g[5, 5, 0] = np.inf
    g[7, 1, 1] = -np.inf
    res = paper_detect(g)
    for r, c in [(1, 2), (5, 5), (7, 1)]:
        assert res.labels[r, c] == INV
        assert res.flags[r, c] == 0
        assert np.isnan(res.angle[r, c]) and np.isnan(res.height[r, c])
    assert np.count_nonzero(res.labels == INV) == 3


# --------------------------------------------------------------------------------------------
# detect: input handling
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"theta0": 0.0}, "theta0"),
        ({"theta0": 180.0}, "theta0"),
        ({"theta0": float("nan")}, "theta0"),
        ({"theta0": float("inf")}, "theta0"),
        ({"theta0": True}, "theta0"),
        ({"theta0": "75"}, "theta0"),
        ({"scales": ()}, "scales"),
        ({"scales": (0,)}, "scales"),
        ({"scales": (1, -2)}, "scales"),
        ({"scales": (1.5,)}, "scales"),
        ({"scales": (True,)}, "scales"),
        ({"scales": 1}, "scales"),
        ({"scales": "1"}, "scales"),
        ({"max_gap": -1}, "max_gap"),
        ({"max_gap": 1.0}, "max_gap"),
        ({"max_gap": False}, "max_gap"),
        ({"min_step": -0.1}, "min_step"),
        ({"min_step": float("nan")}, "min_step"),
        ({"min_step": float("inf")}, "min_step"),
        ({"max_reach": 0}, "max_reach"),
        ({"min_directions": 0}, "min_directions"),
        ({"min_directions": 5}, "min_directions"),
        ({"max_iterations": 0}, "max_iterations"),
        ({"window": 4}, "window"),
        ({"window": 1}, "window"),
        ({"window": 21.0}, "window"),
    ],
)
def test_detect_bad_parameters(kwargs: dict, name: str) -> None:
    with pytest.raises(ValueError, match=name):
        paper_detect(flat_grid(5, 5), **kwargs)


def test_detect_accepts_numpy_scalars() -> None:
    g = flat_grid(7, 7)
    g[3, 3, 2] = 5.0
    res = paper_detect(
        g,
        theta0=np.float32(75.0),
        scales=np.array([1, 2]),
        max_gap=np.int64(1),
        min_step=np.float64(0.0),
        min_directions=np.int32(4),
        max_iterations=np.uint8(3),
        window=np.int16(5),
        max_reach=np.int64(2),
    )
    assert res.labels[3, 3] == A
    np.testing.assert_array_equal(res.labels, paper_detect(g, scales=[1, 2], window=5).labels)


@pytest.mark.parametrize(
    "grid",
    [
        np.full((5, 5, 3), np.nan),
        np.r_[flat_grid(1, 2), np.full((1, 2, 3), np.nan)].reshape(2, 2, 3),
        np.zeros((0, 4, 3)),
        flat_grid(5, 5)[..., :2],
        flat_grid(5, 5).reshape(25, 3),
        np.full((3, 3, 3), "x"),
        flat_grid(5, 5) > 0,
    ],
)
def test_detect_bad_grid(grid: np.ndarray) -> None:
    with pytest.raises(ValueError, match="grid"):
        paper_detect(grid)


def test_detect_does_not_modify_input() -> None:
    rng = np.random.default_rng(10)
    g = flat_grid(16, 16)
    g[..., 2] = rng.normal(0, 1.0, (16, 16))
    g[rng.random((16, 16)) < 0.1] = np.nan
    g[2, 3, 1] = np.inf
    copy = g.copy()
    paper_detect(g, scales=(1, 2), min_step=0.5)
    np.testing.assert_array_equal(g, copy)
    g32 = g.astype(np.float32)
    copy32 = g32.copy()
    paper_detect(g32)
    np.testing.assert_array_equal(g32, copy32)


def test_detect_float32_same_as_float64_of_same_values() -> None:
    rng = np.random.default_rng(11)
    g = flat_grid(24, 20, dx=0.3, dy=0.5)
    g[..., 2] = rng.normal(0, 0.4, (24, 20))
    g[rng.random((24, 20)) < 0.05] = np.nan
    g32 = g.astype(np.float32)
    r32 = paper_detect(g32, scales=(1, 2))
    r64 = paper_detect(g32.astype(np.float64), scales=(1, 2))
    assert np.count_nonzero(r64.labels == A) > 0
    np.testing.assert_array_equal(r32.labels, r64.labels)
    np.testing.assert_array_equal(r32.flags, r64.flags)
    np.testing.assert_array_equal(r32.angle, r64.angle)
    np.testing.assert_array_equal(r32.height, r64.height)
    # integer input is read as float64
    gi = np.rint(np.nan_to_num(g, nan=0.0) * 8).astype(np.int64)
    np.testing.assert_array_equal(paper_detect(gi).labels, paper_detect(gi.astype(np.float64)).labels)


def test_detect_large_offset_same_labels() -> None:
    # Coordinates on a dyadic lattice, so that adding the offset is exact and so are all the
    # differences: labels, flags and angles must be identical; heights equal within 1e-6.
    rng = np.random.default_rng(12)
    g = flat_grid(32, 32)
    g[..., 2] = rng.integers(-16, 17, (32, 32)) / 32.0
    spikes = rng.random((32, 32)) < 0.03
    g[spikes, 2] += rng.choice([-4.0, 4.0], np.count_nonzero(spikes))
    g[rng.random((32, 32)) < 0.03] = np.nan
    offset = np.array([1e5, -2e5, 1e5])
    r0 = paper_detect(g, scales=(1, 2))
    r1 = paper_detect(g + offset, scales=(1, 2))
    assert np.count_nonzero(r0.labels == A) > 0
    np.testing.assert_array_equal(r1.labels, r0.labels)
    np.testing.assert_array_equal(r1.flags, r0.flags)
    np.testing.assert_array_equal(r1.angle, r0.angle)
    np.testing.assert_allclose(r1.height, r0.height, atol=1e-6, equal_nan=True)
    assert r0.plane is not None and r1.plane is not None
    np.testing.assert_allclose(r1.plane.normal, r0.plane.normal, atol=1e-9)
    assert len(r0.defects) == len(r1.defects)
    for d0, d1 in zip(r0.defects, r1.defects):
        np.testing.assert_array_equal(d1.indices, d0.indices)
        assert d1.kind == d0.kind


# --------------------------------------------------------------------------------------------
# detect against a literal per-cell transcription of the SPEC.md pseudo-code
# --------------------------------------------------------------------------------------------

_DIRS = [(0, 1), (1, 0), (1, 1), (1, -1)]


def _literal_labels(
    g: np.ndarray,
    theta0: float,
    scales: tuple[int, ...],
    max_gap: int,
    min_step: float | None,
    min_directions: int | None,
    max_iterations: int,
    max_reach: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Labels, flags, angle and pass count, one cell and one step at a time (pure Python)."""
    h, w = g.shape[:2]
    pts = [[tuple(float(x) for x in g[r, c]) for c in range(w)] for r in range(h)]
    finite = [[all(math.isfinite(x) for x in pts[r][c]) for c in range(w)] for r in range(h)]
    labels = np.full((h, w), INV, dtype=np.uint8)
    flags = np.zeros((h, w), dtype=np.uint8)
    angle = np.full((h, w), np.nan)
    abnormal = [[False] * w for _ in range(h)]
    cos0 = math.cos(theta0 * math.pi / 180.0)

    def neighbour(usable, r, c, dr, dc, s, side):
        p = pts[r][c]
        gaps, k = 0, s
        while True:
            if min_step is not None and k > s + max_gap + max_reach:
                return None
            rr, cc = r + side * k * dr, c + side * k * dc
            if not (0 <= rr < h and 0 <= cc < w):
                return None
            if not usable[rr][cc]:
                gaps += 1
                if gaps > max_gap:
                    return None
            else:
                q = pts[rr][cc]
                dist = math.sqrt(
                    (q[0] - p[0]) * (q[0] - p[0])
                    + (q[1] - p[1]) * (q[1] - p[1])
                    + (q[2] - p[2]) * (q[2] - p[2])
                )
                if min_step is None or dist >= s * min_step:
                    return q
            k += 1

    passes = 0
    while True:
        passes += 1
        usable = [[finite[r][c] and not abnormal[r][c] for c in range(w)] for r in range(h)]
        new = []
        for r in range(h):
            for c in range(w):
                if not usable[r][c]:
                    continue
                p = pts[r][c]
                isolated = True
                for dr, dc in _DIRS:
                    for side in (-1, 1):
                        for k in range(1, max_gap + 2):
                            rr, cc = r + side * k * dr, c + side * k * dc
                            if 0 <= rr < h and 0 <= cc < w and usable[rr][cc]:
                                isolated = False
                n_avail = n_flag = 0
                bits = 0
                best = math.nan
                for kd, (dr, dc) in enumerate(_DIRS):
                    avail = flagged = False
                    for s in scales:
                        a = neighbour(usable, r, c, dr, dc, s, -1)
                        b = neighbour(usable, r, c, dr, dc, s, +1)
                        if a is None or b is None:
                            continue
                        u = [a[i] - p[i] for i in range(3)]
                        v = [b[i] - p[i] for i in range(3)]
                        uu = u[0] * u[0] + u[1] * u[1] + u[2] * u[2]
                        vv = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
                        uv = u[0] * v[0] + u[1] * v[1] + u[2] * v[2]
                        if uu == 0.0 or vv == 0.0:
                            continue
                        cs = min(1.0, max(-1.0, uv / math.sqrt(uu * vv)))
                        avail = True
                        flagged = flagged or cs >= cos0
                        ang = math.degrees(math.acos(cs))
                        best = ang if math.isnan(best) else min(best, ang)
                    n_avail += avail
                    n_flag += flagged
                    bits |= (1 << kd) if flagged else 0
                if isolated:
                    labels[r, c], flags[r, c], angle[r, c] = A, 0, math.nan
                    new.append((r, c))
                    continue
                need = n_avail if min_directions is None else min(n_avail, min_directions)
                if n_avail >= 2 and n_flag >= need:
                    labels[r, c] = A
                    new.append((r, c))
                else:
                    labels[r, c] = E if n_flag > 0 else N
                flags[r, c], angle[r, c] = bits, best
        for r, c in new:
            abnormal[r][c] = True
        if not new or passes >= max_iterations:
            return labels, flags, angle, passes


def _random_grid(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    g = flat_grid(h, w, dx=0.5, dy=0.8)
    g[..., 2] = rng.normal(0, 0.15, (h, w))
    burrs = rng.random((h, w)) < 0.12
    g[burrs, 2] += rng.choice([-2.0, 2.0], np.count_nonzero(burrs))
    g[rng.random((h, w)) < 0.08] = np.nan
    return g


@pytest.mark.parametrize(
    "kwargs",
    [
        {},
        {"theta0": 100.0},
        {"scales": (1, 2)},
        {"scales": (2,), "max_gap": 0},
        {"max_gap": 2, "max_iterations": 2},
        {"min_directions": 2},
        {"min_step": 0.9, "max_reach": 3},
        {"min_step": 0.0, "scales": (1, 3), "max_gap": 0},
        {"min_step": 1.2, "scales": (1, 2), "min_directions": 3, "max_iterations": 1},
    ],
)
def test_detect_matches_literal_transcription(kwargs: dict) -> None:
    rng = np.random.default_rng(13)
    params = {
        "theta0": 75.0,
        "scales": (1,),
        "max_gap": 1,
        "min_step": None,
        "min_directions": None,
        "max_iterations": 10,
        "max_reach": 32,
    }
    params.update(kwargs)
    for h, w in [(12, 11), (9, 17)]:
        g = _random_grid(rng, h, w)
        res = paper_detect(g, **params)
        labels, flags, angle, passes = _literal_labels(g, **params)
        np.testing.assert_array_equal(res.labels, labels)
        np.testing.assert_array_equal(res.flags, flags)
        np.testing.assert_allclose(res.angle, angle, rtol=0, atol=1e-12)
        assert res.iterations == passes


def test_window_heights_match_per_cell_fit() -> None:
    rng = np.random.default_rng(14)
    g = _random_grid(rng, 13, 10)
    g[..., 2] += 0.3 * g[..., 0]
    for window in (3, 5, 21):
        res = paper_detect(g, window=window)
        half = window // 2
        for r in range(13):
            for c in range(10):
                if res.labels[r, c] == INV:
                    assert np.isnan(res.height[r, c])
                    continue
                r0, r1 = max(0, r - half), min(13, r + half + 1)
                c0, c1 = max(0, c - half), min(10, c + half + 1)
                sub = g[r0:r1, c0:c1][res.labels[r0:r1, c0:c1] == N]
                try:
                    plane = ref.fit_plane(sub)
                except ValueError:
                    assert np.isnan(res.height[r, c])
                    continue
                assert res.height[r, c] == pytest.approx(float(plane.distance(g[r, c])), abs=1e-10)


def test_defects_match_scipy_components() -> None:
    ndimage = pytest.importorskip("scipy.ndimage")
    rng = np.random.default_rng(15)
    g = _random_grid(rng, 30, 30)
    res = paper_detect(g, scales=(1, 2))
    lab, n = ndimage.label(res.labels == A, structure=np.ones((3, 3), dtype=int))
    assert n == len(res.defects) and n > 3
    comps = sorted(tuple(np.flatnonzero(lab.ravel() == i + 1)) for i in range(n))
    assert sorted(tuple(d.indices) for d in res.defects) == comps
    peaks = [abs(d.peak_height) for d in res.defects]
    finite_peaks = [p for p in peaks if not math.isnan(p)]
    assert finite_peaks == sorted(finite_peaks, reverse=True)
    assert all(math.isnan(p) for p in peaks[len(finite_peaks) :])
    assert [d.id for d in res.defects] == list(range(n))
    for d in res.defects:
        assert d.count == d.indices.size
        assert np.all(np.diff(d.indices) > 0)
        np.testing.assert_allclose(d.centroid, g.reshape(-1, 3)[d.indices].mean(axis=0))
        hs = res.height.ravel()[d.indices]
        if np.isfinite(hs).any():
            assert d.mean_height == pytest.approx(np.nanmean(hs))
            assert abs(d.peak_height) == pytest.approx(np.nanmax(np.abs(hs)))
