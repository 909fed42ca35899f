"""Tests of the reference's organized options beyond the paper (``miem.reference.detect``).

docs/SPEC.md, "Beyond the paper: automatic threshold, height test, presets": ``theta0="auto"``,
``height_tolerance`` and ``preset``. Expected values come from geometry worked out by hand (exact
angles of piecewise-linear profiles, a checkerboard of known amplitude, the window plane of a
single raised cell) or from the SPEC formula applied to the pass-1 angles; never from an earlier
run of the reference itself.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from miem import reference as ref

# The rules beyond the paper, each on top of the paper's method: preset="paper" unless a test
# gives another preset.
paper_detect = functools.partial(ref.detect, preset="paper")

N, A, E, INV = ref.NORMAL, ref.ABNORMAL, ref.EDGE, ref.INVALID


def flat_grid(h: int, w: int, dx: float = 1.0, dy: float = 1.0) -> np.ndarray:
    """Grid ``(h, w, 3)`` on z = 0 with x = c * dx, y = r * dy."""
    r, c = np.mgrid[0:h, 0:w]
    g = np.zeros((h, w, 3))
    g[..., 0] = c * dx
    g[..., 1] = r * dy
    return g


def checkerboard(h: int, w: int, e: float) -> np.ndarray:
    """Flat grid with z = +e on cells with even ``r + c`` and -e on the others."""
    g = flat_grid(h, w)
    r, c = np.mgrid[0:h, 0:w]
    g[..., 2] = np.where((r + c) % 2 == 0, e, -e)
    return g


def profile(z: list[float]) -> np.ndarray:
    """A single scan line ``(1, W, 3)`` at x = c, y = 0 with the given heights."""
    g = flat_grid(1, len(z))
    g[0, :, 2] = z
    return g


def auto_formula(dev_median: float) -> float:
    """SPEC: ``clip(180 - 6 * median(dev) / 0.6745, 75, 170)``."""
    return min(max(180.0 - 6.0 * (dev_median / 0.6745), 75.0), 170.0)


def fold_dome_scene() -> np.ndarray:
    """24 x 48 checkerboard (e = 0.02) with a 45-degree fold and a smooth dome.

    The fold runs along column 10 (z = 0 left of it, slope 1 to the right: interior angle 135 deg
    along the profile, 144.7 deg on the diagonals). The dome, on the 45-degree face, is a
    Gaussian bump of vertical amplitude 0.15 (7.5 times the checkerboard's rms) and sigma 1.5
    cells (3.5 cells at half height), centred at (12, 34), 24 columns from the fold.
    """
    g = checkerboard(24, 48, 0.02)
    r, c = np.mgrid[0:24, 0:48]
    g[..., 2] += np.where(c > 10, c - 10.0, 0.0)
    g[..., 2] += 0.15 * np.exp(-((r - 12.0) ** 2 + (c - 34.0) ** 2) / (2 * 1.5**2))
    return g


# --------------------------------------------------------------------------------------------
# theta0 = "auto"
# --------------------------------------------------------------------------------------------


def test_auto_noise_free_plane_is_170() -> None:
    # Dyadic slopes on an integer lattice: every u = -v exactly, every angle is 180, dev = 0,
    # sigma = 0, 180 - 0 clipped to auto_max.
    g = flat_grid(9, 11)
    g[..., 2] = 0.5 * g[..., 0] - 0.25 * g[..., 1] + 3.0
    res = paper_detect(g, theta0="auto")
    assert res.params["theta0"] == 170.0
    assert res.params["theta0_auto"] is True
    assert isinstance(res.params["theta0"], float)
    np.testing.assert_array_equal(res.labels, N)
    assert res.iterations == 1


def test_auto_even_count_median_of_kinked_profile() -> None:
    # One scan line: only the along-profile direction exists. Slopes 0, 0, 1/16, 1/8, -1 give
    # the interior cells 1..4 the deviations dev = 180 - angle:
    #   c1: 0; c2: atan(1/16); c3: atan(1/8) - atan(1/16); c4: atan(1/8) + 45 (degrees)
    # Four values, sorted 0 < c3 < c2 < c4: the median is the mean of the two middle ones,
    # (atan(1/16) + atan(1/8) - atan(1/16)) / 2 = atan(1/8) / 2 = 3.5625 deg.
    g = profile([0.0, 0.0, 0.0, 1 / 16, 3 / 16, 3 / 16 - 1.0])
    res = paper_detect(g, theta0="auto")
    at16, at8 = math.degrees(math.atan(1 / 16)), math.degrees(math.atan(1 / 8))
    np.testing.assert_allclose(
        180.0 - res.angle[0, 1:5], [0.0, at16, at8 - at16, at8 + 45.0], atol=1e-9
    )
    expected = auto_formula(at8 / 2)
    assert 75.0 < expected < 170.0  # 148.3: not clipped
    assert res.params["theta0"] == pytest.approx(expected, abs=1e-9)
    # c4 (127.9 deg) is below that threshold and c2, c3 (176.4 deg) are not; a single available
    # direction makes EDGE, never ABNORMAL.
    np.testing.assert_array_equal(res.labels[0], [N, N, N, N, E, N])
    assert res.flags[0, 4] == 1


def test_auto_odd_count_and_clip_to_75() -> None:
    # Slopes 0, 0, 0, 1/16, 1/4, -1/4: the five interior cells have devs 0, 0, atan(1/16),
    # atan(1/4) - atan(1/16), 2 atan(1/4), i.e. 0, 0, 3.58, 10.46, 28.07: the median is the
    # middle one, atan(1/16), and theta0 = 180 - 6 * 5.30 = 148.2.
    g = profile([0.0, 0.0, 0.0, 0.0, 1 / 16, 5 / 16, 1 / 16])
    res = paper_detect(g, theta0="auto")
    expected = auto_formula(math.degrees(math.atan(1 / 16)))
    assert 75.0 < expected < 170.0
    assert res.params["theta0"] == pytest.approx(expected, abs=1e-9)
    # Slopes 0, 1/4, 1, -1: devs atan(1/4), 45 - atan(1/4), 90, i.e. 14.04, 30.96, 90: the
    # median 30.96 gives 180 - 6 * 45.9 < 0 -> clipped to 75.
    res2 = paper_detect(profile([0.0, 0.0, 0.25, 1.25, 0.25]), theta0="auto")
    assert res2.params["theta0"] == 75.0


def test_auto_checkerboard_known_angles() -> None:
    # Checkerboard of amplitude e: along the profile and across profiles the interior angle is
    # 2 atan(1 / (2e)); the diagonal neighbours have the cell's own height (180 deg). Border
    # cells (but the corners) have the along-the-border direction only, with the same angle;
    # the corners have no direction (NaN, not counted). So every counted dev is the same.
    e = 0.02
    g = checkerboard(10, 13, e)
    res = paper_detect(g, theta0="auto")
    dev = 180.0 - math.degrees(2.0 * math.atan(1.0 / (2.0 * e)))
    assert res.params["theta0"] == pytest.approx(auto_formula(dev), abs=1e-9)  # 139.25 deg
    assert np.isnan(res.angle[0, 0]) and np.isnan(res.angle[-1, -1])
    np.testing.assert_array_equal(res.labels, N)  # 175.4 deg > 139.25 deg


def test_auto_no_finite_angle_is_75() -> None:
    # 2 x 2: no cell has neighbours on both sides in any direction.
    g = flat_grid(2, 2)
    g[1, 1, 2] = 0.5
    res = paper_detect(g, theta0="auto")
    assert res.params["theta0"] == 75.0
    assert np.all(np.isnan(res.angle))
    np.testing.assert_array_equal(res.labels, N)


@pytest.mark.parametrize(
    "kwargs",
    [
        {},
        {"scales": (1, 2)},
        {"scales": (2,), "max_gap": 0},
        {"min_step": 0.7, "max_reach": 4},
        {"max_gap": 2, "min_directions": 3},
    ],
)
def test_auto_is_formula_of_pass_one_angles(kwargs: dict) -> None:
    # The pass-1 angle does not depend on theta0, so one pass at any theta0 gives the angles the
    # automatic threshold is computed from (isolated cells included, as pass 1 records them).
    rng = np.random.default_rng(20)
    g = flat_grid(30, 26, dx=0.5)
    g[..., 2] = rng.normal(0.0, 0.02, (30, 26))
    spikes = rng.random((30, 26)) < 0.03
    g[spikes, 2] += rng.choice([-2.0, 2.0], np.count_nonzero(spikes))
    g[rng.random((30, 26)) < 0.08] = np.nan
    g[20:26, 0:6] = np.nan
    g[22, 2] = [1.0, 22.0, 0.3]  # lone return
    one = paper_detect(g, theta0=100.0, max_iterations=1, **kwargs)
    angles = one.angle[np.isfinite(one.angle)]
    expected = auto_formula(float(np.median(180.0 - angles)))
    assert 75.0 < expected < 170.0
    res = paper_detect(g, theta0="auto", **kwargs)
    assert res.params["theta0"] == pytest.approx(expected, rel=1e-12)
    # ... and it is the threshold actually used
    fixed = paper_detect(g, theta0=res.params["theta0"], **kwargs)
    np.testing.assert_array_equal(res.labels, fixed.labels)
    np.testing.assert_array_equal(res.flags, fixed.flags)
    assert fixed.params["theta0_auto"] is False


def test_auto_is_computed_once_before_pass_one() -> None:
    # A tall spike: its removal changes later passes but not the threshold, which comes from the
    # pass-1 angles of every finite cell (spike included).
    g = checkerboard(11, 11, 0.02)
    g[5, 5, 2] = 5.0
    res = paper_detect(g, theta0="auto")
    assert res.iterations == 2 and res.labels[5, 5] == A
    one = paper_detect(g, theta0=90.0, max_iterations=1)
    dev = 180.0 - one.angle[np.isfinite(one.angle)]
    assert res.params["theta0"] == pytest.approx(auto_formula(float(np.median(dev))), rel=1e-12)


# --------------------------------------------------------------------------------------------
# height_tolerance: one raised cell, by hand
# --------------------------------------------------------------------------------------------
#
# A cell raised by b on the plane z = 0, window 3. Its window holds itself and its 8 flat
# neighbours, symmetric about it, so the window plane is z = b / 9 and
#   h = b - b/9 = 8b/9,  l0 = (8/9 b)^2 + 8 (b/9)^2 = 8 b^2 / 9,  rms = sqrt(l0 / 9),
#   h / rms = sqrt(8) = 2.83.
# A neighbour sees the raised cell off-centre: its own residual is about b / 9 (well under both
# tests below). Once the raised cell is ABNORMAL every window is exactly flat: h = 0.

B = 0.1  # angle at the raised cell 2 atan(10) = 168.6 deg: the angle test misses it


def raised_cell() -> np.ndarray:
    g = flat_grid(9, 9)
    g[4, 4, 2] = B
    return g


def test_height_absolute_by_hand() -> None:
    g = raised_cell()
    assert np.count_nonzero(paper_detect(g, window=3).labels) == 0
    res = paper_detect(g, window=3, height_tolerance=0.088)  # 8b/9 = 0.0889 > 0.088
    expected = np.zeros((9, 9), dtype=np.uint8)
    expected[4, 4] = A
    np.testing.assert_array_equal(res.labels, expected)
    assert res.iterations == 3  # 1 angle pass + 2 height passes (the second finds nothing)
    assert res.params["height_tolerance"] == 0.088
    # heights are then computed from the final labels: the plane is z = 0
    assert res.height[4, 4] == pytest.approx(B, abs=1e-12)
    (d,) = res.defects
    assert d.kind == "protrusion" and d.peak_height == pytest.approx(B, abs=1e-12)

    res2 = paper_detect(g, window=3, height_tolerance=0.09)  # 0.0889 < 0.09
    np.testing.assert_array_equal(res2.labels, N)
    assert res2.iterations == 2  # 1 angle pass + 1 height pass
    # the window plane including the raised cell: h = 8b/9
    assert res2.height[4, 4] == pytest.approx(8 * B / 9, abs=1e-12)


def test_height_rms_by_hand() -> None:
    g = raised_cell()
    res = paper_detect(g, window=3, height_tolerance="2.5rms")  # sqrt(8) = 2.83 > 2.5
    assert np.count_nonzero(res.labels) == 1 and res.labels[4, 4] == A
    assert res.iterations == 3
    assert res.params["height_tolerance"] == "2.5rms"
    res3 = paper_detect(g, window=3, height_tolerance="3rms")  # 2.83 < 3
    np.testing.assert_array_equal(res3.labels, N)
    assert res3.iterations == 2
    # the ratio does not depend on b (while the window's z scatter 8 b^2 / 9 stays below its x
    # and y scatter 6, so that the plane stays horizontal): a 10 times taller raised cell (90 deg,
    # still not flagged at 75 deg) gives the same verdicts; the absolute form scales with b
    g_big = raised_cell()
    g_big[4, 4, 2] = 10.0 * B
    assert paper_detect(g_big, window=3).labels[4, 4] == N
    assert paper_detect(g_big, window=3, height_tolerance="2.5rms").labels[4, 4] == A
    assert paper_detect(g_big, window=3, height_tolerance="3rms").labels[4, 4] == N
    assert paper_detect(g_big, window=3, height_tolerance=0.88).labels[4, 4] == A
    assert paper_detect(g_big, window=3, height_tolerance=0.9).labels[4, 4] == N


@pytest.mark.parametrize("tol", ["4rms", "1e-6rms", 1e-6])
def test_height_exact_tilted_plane_far_away_flags_nothing(tol: float | str) -> None:
    # An exact plane: every h is round-off. In the rms form the rms is round-off too (l0 may even
    # come out <= 0); the floor |h| > 1e-9 sqrt((l1 + l2) / n) keeps such cells NORMAL.
    g = flat_grid(20, 24, dx=0.3, dy=0.7)
    g[..., 0] += 1234.5
    g[..., 1] -= 2345.25
    g[..., 2] = 0.1 * g[..., 0] - 0.37 * g[..., 1] + 999.123
    res = paper_detect(g, window=7, height_tolerance=tol)
    np.testing.assert_array_equal(res.labels, N)
    assert res.iterations == 2


# --------------------------------------------------------------------------------------------
# height_tolerance: a smooth dome and a designed fold in the same scene
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("theta0", [75.0, "auto"])
def test_height_catches_dome_not_fold(theta0: float | str) -> None:
    g = fold_dome_scene()
    base = paper_detect(g, theta0=theta0, window=15)
    # The angle test misses the dome (its angles are 172 deg and more) whatever the threshold:
    # at 75 deg nothing is flagged; "auto" (checkerboard dev 4.58 deg -> 139.25 deg) flags the
    # fold only, as a designed edge.
    assert np.count_nonzero(base.labels == A) == 0
    if theta0 == "auto":
        assert base.params["theta0"] == pytest.approx(
            auto_formula(2 * math.degrees(math.atan(2 * 0.02))), abs=1e-9
        )
        assert np.all(base.labels[:, 10] == E)
        assert np.count_nonzero(base.labels == E) == 24
    else:
        np.testing.assert_array_equal(base.labels, N)

    res = paper_detect(g, theta0=theta0, window=15, height_tolerance="3rms")
    abn = np.argwhere(res.labels == A)
    # the dome is caught: its top, and nothing farther than 2 cells from it ...
    assert res.labels[12, 34] == A
    assert len(abn) >= 5
    assert np.all(np.hypot(abn[:, 0] - 12, abn[:, 1] - 34) <= 2.0 + 1e-12)
    # ... the fold is not (its windows hold two planes; their residuals stay within 2 rms)
    assert np.all(abn[:, 1] > 24)
    # EDGE cells, flags and angles are those of the angle passes
    np.testing.assert_array_equal(res.labels == E, base.labels == E)
    np.testing.assert_array_equal(res.flags, base.flags)
    np.testing.assert_array_equal(res.angle, base.angle)
    assert res.iterations > 2
    (d,) = res.defects
    assert d.kind == "protrusion"
    # the top is 0.15 + e above the 45-degree face, vertically: (0.15 + e) cos 45 deg = 0.120
    # along its normal (the dome's tail, left in the window plane, lifts that plane a little)
    assert d.peak_height == pytest.approx(0.17 / math.sqrt(2.0), abs=0.005)
    np.testing.assert_allclose(d.normal, np.array([-1.0, 0.0, 1.0]) / math.sqrt(2.0), atol=1e-3)


def test_height_absolute_is_scale_blind_rms_is_not() -> None:
    # The absolute form with a tolerance just above the noise (2.5 e) also catches the dome. The
    # fold is EDGE with theta0="auto", so cells whose window holds it are not tested at all.
    g = fold_dome_scene()
    res = paper_detect(g, theta0="auto", window=15, height_tolerance=0.05)
    assert res.labels[12, 34] == A
    assert np.count_nonzero(res.labels[:, 3:18] == A) == 0  # within 7 cells of the fold
    assert np.all(res.labels[:, 10] == E)  # the fold itself is EDGE and stays EDGE
    # with the fold NORMAL (theta0 = 75) the absolute test takes it as well
    res75 = paper_detect(g, theta0=75.0, window=15, height_tolerance=0.05)
    assert np.any(res75.labels[:, 10] == A)
    # the rms form leaves the whole fold side alone, at any usual k
    for k in ("2.5rms", "3rms", "4rms"):
        res_k = paper_detect(g, theta0=75.0, window=15, height_tolerance=k)
        assert np.count_nonzero(res_k.labels[:, :24]) == 0


def test_height_fold_without_noise_rms_bound() -> None:
    # Noise-free fold, everything constant along the columns: within a window each column
    # contributes the same residual on every row, so |h| <= sqrt(m) rms with m <= window
    # columns: sqrt(15) < 4 and "4rms" can never flag it; the absolute test does.
    g = flat_grid(16, 30)
    g[..., 2] = np.where(g[..., 0] > 12, g[..., 0] - 12.0, 0.0)
    res = paper_detect(g, window=15, height_tolerance="4rms")
    np.testing.assert_array_equal(res.labels, N)
    assert res.iterations == 2
    res_abs = paper_detect(g, window=15, height_tolerance=0.25)
    assert np.count_nonzero(res_abs.labels == A) > 0


def test_height_never_changes_edge_cells() -> None:
    # A 2-wide burr at scale 1 is EDGE (3 of 4 directions flagged) with height 4 over the plane
    # of the NORMAL cells; the height test leaves it EDGE and the rest is exactly flat.
    g = flat_grid(9, 9)
    g[4, 4, 2] = g[4, 5, 2] = 4.0
    base = paper_detect(g)
    assert base.labels[4, 4] == E and base.labels[4, 5] == E
    for tol in (0.5, 1e-3, "4rms", "0.5rms"):
        res = paper_detect(g, height_tolerance=tol)
        np.testing.assert_array_equal(res.labels, base.labels)
        np.testing.assert_array_equal(res.flags, base.flags)
        assert res.iterations == 2
        assert res.height[4, 4] == pytest.approx(4.0, abs=1e-12)
        assert res.defects == []
    # the fold, EDGE at theta0 = 150: an absolute tolerance that would take the cells beside it
    # (as at theta0 = 75, where the fold is NORMAL) abstains wherever the fold is in the window
    fold = flat_grid(12, 20)
    fold[..., 2] = np.where(fold[..., 0] > 8, fold[..., 0] - 8.0, 0.0)
    res = paper_detect(fold, theta0=150.0, window=9, height_tolerance=0.01)
    np.testing.assert_array_equal(res.labels[:, 8], E)
    assert np.count_nonzero(res.labels == A) == 0
    assert np.count_nonzero(paper_detect(fold, window=9, height_tolerance=0.01).labels == A) > 0


def test_height_ignores_invalid_and_keeps_abnormal() -> None:
    # Angle passes remove a spike; dropouts stay INVALID; the height test then adds the raised
    # cell. iterations = 2 angle passes + 2 height passes.
    g = flat_grid(15, 15)
    g[3, 3, 2] = 5.0
    g[10, 10, 2] = B
    g[7, 2] = np.nan
    g[12, 6, 0] = np.inf
    base = paper_detect(g, window=3)
    assert base.iterations == 2 and np.count_nonzero(base.labels == A) == 1
    res = paper_detect(g, window=3, height_tolerance=0.08)
    assert res.iterations == 4
    assert res.labels[3, 3] == A and res.labels[10, 10] == A
    assert res.labels[7, 2] == INV and res.labels[12, 6] == INV
    assert np.count_nonzero(res.labels == A) == 2
    assert res.flags[3, 3] == 15 and res.flags[10, 10] == 0
    assert res.angle[10, 10] == pytest.approx(math.degrees(2 * math.atan(1 / B)))
    assert len(res.defects) == 2


# --------------------------------------------------------------------------------------------
# height_tolerance: iteration count
# --------------------------------------------------------------------------------------------


def test_height_passes_cascade_and_max_iterations_caps_them_separately() -> None:
    g = fold_dome_scene()
    kw = {"theta0": 75.0, "window": 15, "height_tolerance": "3rms"}
    full = paper_detect(g, **kw)
    n_height = full.iterations - 1  # one angle pass (nothing ABNORMAL)
    assert n_height >= 3  # removing the top exposes the shoulders, and so on
    full_abn = full.labels == A
    prev = np.zeros_like(full_abn)
    for cap in range(1, n_height):
        res = paper_detect(g, max_iterations=cap, **kw)
        # max_iterations caps the height passes on their own: even max_iterations = 1 runs one
        # angle pass and then one height pass
        assert res.iterations == 1 + cap
        abn = res.labels == A
        # every capped pass still adds cells, and only cells of the full result
        assert np.all(full_abn[abn]) and np.all(abn[prev])
        assert np.count_nonzero(abn) > np.count_nonzero(prev)
        prev = abn
    # the last pass of the full run found nothing new (and was counted)
    np.testing.assert_array_equal(prev, full_abn)
    res = paper_detect(g, max_iterations=n_height, **kw)
    assert res.iterations == full.iterations
    np.testing.assert_array_equal(res.labels, full.labels)


def test_height_after_capped_angle_passes() -> None:
    # Angle passes stop at max_iterations = 1 with the spike's neighbours EDGE (theta0 = 120);
    # one height pass follows and changes none of them.
    g = flat_grid(9, 9)
    g[4, 4, 2] = 5.0
    res = paper_detect(g, theta0=120.0, max_iterations=1, height_tolerance=0.5)
    assert res.iterations == 2
    assert res.labels[4, 4] == A
    assert np.count_nonzero(res.labels == E) == 8
    assert np.count_nonzero(res.labels == A) == 1


# --------------------------------------------------------------------------------------------
# Presets and parameter resolution
# --------------------------------------------------------------------------------------------


def test_preset_paper_is_the_paper_and_recommended_is_the_default() -> None:
    rng = np.random.default_rng(30)
    g = flat_grid(16, 16)
    g[..., 2] = rng.normal(0.0, 0.1, (16, 16))
    g[rng.random((16, 16)) < 0.05, 2] += 3.0
    paper = ref.detect(g, preset="paper")
    assert paper.params["preset"] == "paper"
    expected = {
        "theta0": 75.0,
        "theta0_auto": False,
        "scales": (1,),
        "max_gap": 1,
        "min_step": None,
        "min_directions": None,
        "max_iterations": 10,
        "window": 21,
        "max_reach": 32,
        "height_tolerance": None,
    }
    assert {k: paper.params[k] for k in expected} == expected
    # SPEC "Parameters": without a preset, "recommended" applies
    plain = ref.detect(g)
    rec = ref.detect(g, preset="recommended")
    np.testing.assert_array_equal(rec.labels, plain.labels)
    np.testing.assert_array_equal(rec.flags, plain.flags)
    np.testing.assert_array_equal(rec.height, plain.height)
    assert rec.iterations == plain.iterations and plain.params["preset"] is None
    expected.update(theta0=90.0, scales=(1, 2), height_tolerance="4.5rms")
    for params in (plain.params, rec.params):
        assert {k: params[k] for k in expected} == expected
    explicit = ref.detect(g, theta0=90.0, scales=(1, 2), height_tolerance="4.5rms",
                          edge_extent=12)
    np.testing.assert_array_equal(explicit.labels, plain.labels)


def test_explicit_arguments_override_preset() -> None:
    g = flat_grid(9, 9)
    g[4, 4, 2] = 5.0
    res = paper_detect(g, preset="paper", theta0=120.0, max_iterations=1)
    assert res.params["theta0"] == 120.0 and res.params["max_iterations"] == 1
    assert res.params["window"] == 21
    np.testing.assert_array_equal(res.labels, paper_detect(g, theta0=120.0, max_iterations=1).labels)
    assert np.count_nonzero(res.labels == E) == 8


def test_explicit_default_values_win_over_preset(monkeypatch: pytest.MonkeyPatch) -> None:
    # A preset with non-default values: an argument left out takes the preset's value, one
    # given explicitly wins even when it equals the default; one the preset does not list takes
    # the default.
    table = {
        "theta0": 120.0,
        "scales": (1, 2),
        "min_step": 0.5,
        "min_directions": 3,
        "max_iterations": 1,
        "window": 5,
        "height_tolerance": "4rms",
    }
    monkeypatch.setitem(ref._PRESETS, "test", table)
    g = flat_grid(9, 9)
    g[4, 4, 2] = 5.0
    res = paper_detect(g, preset="test")
    assert {k: res.params[k] for k in table} == table
    assert res.params["max_gap"] == 1 and res.params["max_reach"] == 32
    over = paper_detect(
        g,
        preset="test",
        theta0=75.0,
        scales=(1,),
        min_step=None,
        min_directions=None,
        max_iterations=10,
        window=21,
        height_tolerance=None,
    )
    assert over.params["preset"] == "test"
    plain = paper_detect(g)
    for k in table:
        assert over.params[k] == plain.params[k]
    np.testing.assert_array_equal(over.labels, plain.labels)
    assert over.iterations == plain.iterations == 2
    # half and half
    mixed = paper_detect(g, preset="test", min_step=None, height_tolerance=None)
    assert mixed.params["min_step"] is None and mixed.params["height_tolerance"] is None
    assert mixed.params["theta0"] == 120.0 and mixed.params["window"] == 5
    np.testing.assert_array_equal(
        mixed.labels,
        paper_detect(
            g, theta0=120.0, scales=(1, 2), min_directions=3, max_iterations=1, window=5
        ).labels,
    )


def test_preset_theta0_auto_and_positional_arguments(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(ref._PRESETS, "auto", {"theta0": "auto"})
    g = checkerboard(10, 13, 0.02)
    res = paper_detect(g, preset="auto")
    assert res.params["theta0_auto"] is True
    assert res.params["theta0"] == pytest.approx(paper_detect(g, theta0="auto").params["theta0"])
    assert paper_detect(g, 80.0, preset="auto").params["theta0"] == 80.0
    # the historical positional order still works
    pos = paper_detect(g, 75.0, (1,), 1, None, None, 10, 21, 32)
    assert pos.params["theta0"] == 75.0


# --------------------------------------------------------------------------------------------
# Bad values
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"theta0": "Auto"}, "theta0"),
        ({"theta0": "auto "}, "theta0"),
        ({"theta0": "AUTO"}, "theta0"),
        ({"theta0": "75"}, "theta0"),
        ({"theta0": None}, "theta0"),
        ({"height_tolerance": 0.0}, "height_tolerance"),
        ({"height_tolerance": -1.0}, "height_tolerance"),
        ({"height_tolerance": float("nan")}, "height_tolerance"),
        ({"height_tolerance": float("inf")}, "height_tolerance"),
        ({"height_tolerance": True}, "height_tolerance"),
        ({"height_tolerance": [1.0]}, "height_tolerance"),
        ({"height_tolerance": b"4rms"}, "height_tolerance"),
        ({"height_tolerance": ""}, "height_tolerance"),
        ({"height_tolerance": "4"}, "height_tolerance"),
        ({"height_tolerance": "rms"}, "height_tolerance"),
        ({"height_tolerance": "0rms"}, "height_tolerance"),
        ({"height_tolerance": "0.0rms"}, "height_tolerance"),
        ({"height_tolerance": "-4rms"}, "height_tolerance"),
        ({"height_tolerance": "+4rms"}, "height_tolerance"),
        ({"height_tolerance": " 4rms"}, "height_tolerance"),
        ({"height_tolerance": "4rms "}, "height_tolerance"),
        ({"height_tolerance": "4 rms"}, "height_tolerance"),
        ({"height_tolerance": "4RMS"}, "height_tolerance"),
        ({"height_tolerance": "4rmss"}, "height_tolerance"),
        ({"height_tolerance": "4.5.1rms"}, "height_tolerance"),
        ({"height_tolerance": "infrms"}, "height_tolerance"),
        ({"height_tolerance": "nanrms"}, "height_tolerance"),
        ({"height_tolerance": "1e400rms"}, "height_tolerance"),
        ({"height_tolerance": "4e"}, "height_tolerance"),
        ({"height_tolerance": "0x10rms"}, "height_tolerance"),
        ({"height_tolerance": "4_0rms"}, "height_tolerance"),
        ({"height_tolerance": "4mm"}, "height_tolerance"),
        ({"preset": "fast"}, "preset"),
        ({"preset": "Paper"}, "preset"),
        ({"preset": 1}, "preset"),
        ({"preset": ""}, "preset"),
    ],
)
def test_bad_values(kwargs: dict, name: str) -> None:
    with pytest.raises(ValueError, match=name):
        paper_detect(flat_grid(5, 5), **kwargs)


@pytest.mark.parametrize(
    ("tol", "recorded"),
    [
        ("4rms", "4rms"),
        ("2.5rms", "2.5rms"),
        (".5rms", ".5rms"),
        ("5.rms", "5.rms"),
        ("1e-1rms", "1e-1rms"),
        ("04rms", "04rms"),
        (0.25, 0.25),
        (1, 1.0),
        (np.float32(0.5), 0.5),
        (np.int64(2), 2.0),
    ],
)
def test_good_height_tolerance_values(tol: object, recorded: object) -> None:
    res = paper_detect(flat_grid(5, 5), height_tolerance=tol)
    assert res.params["height_tolerance"] == recorded
    assert type(res.params["height_tolerance"]) is type(recorded)
    np.testing.assert_array_equal(res.labels, N)
    assert res.iterations == 2


def test_auto_rejected_and_height_test_taken_by_detect_points() -> None:
    rng = np.random.default_rng(40)
    pts = np.c_[rng.uniform(0, 10, (200, 2)), np.zeros(200)]
    with pytest.raises(ValueError, match="theta0"):
        ref.detect_points(pts, theta0="auto")
    # clouds implement the height test (SPEC "Unorganized clouds"): the value is used
    assert ref.detect_points(pts, height_tolerance=1.0).params["height_tolerance"] == 1.0
    # bad values raise
    with pytest.raises(ValueError, match="height_tolerance"):
        ref.detect_points(pts, height_tolerance=-1.0)
