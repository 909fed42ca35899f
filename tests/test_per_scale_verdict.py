"""SPEC "Judgment" with several scales: a cell is ABNORMAL only when every available direction
is flagged at one and the same scale. Directions flagged at different scales do not add up (a
designed edge crossing the grid obliquely), a scale that sees fewer directions does not judge
alone, `flags` still holds every direction flagged at any scale, and with one scale (the
paper's) the rule is the paper's.

Expected labels come from geometry worked out by hand below; core == reference (grids and
clouds) and stream == batch on scenes where the rule decides."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import miem
import numpy as np
import pytest
from miem import reference as ref

sys.path.insert(0, str(Path(__file__).resolve().parent))
from stream_batch import assert_stream_equals_batch  # noqa: E402

NORMAL, ABNORMAL, EDGE = miem.NORMAL, miem.ABNORMAL, miem.EDGE


def _flat(h: int, w: int) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.dstack([xx, yy, np.zeros((h, w))])


def _cross(g: np.ndarray, r: int, c: int, far: int = 2) -> None:
    """Around the flat cell (r, c) (unit spacing): its 4 row / column neighbours raised 2, the
    4 diagonal cells `far` steps away raised far + 1.

    Scale 1: along the row u = (-1, 0, 2), v = (1, 0, 2): u.v = 3 > 0, 53.13 deg, flagged (the
    column alike); the diagonals (+-1, +-1, 0): u.v = -2, 180 deg, not flagged.
    Scale `far`: along the row (+-far, 0, 0): 180 deg; the diagonals (+-far, +-far, far + 1):
    u.v = (far + 1)^2 - 2 far^2 > 0 for far 2 and 3 (1 and -2: far 3 needs more, below), so
    flagged at theta0 90 for far = 2."""
    for dr, dc in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        g[r + dr, c + dc, 2] = 2.0
    hi = 3.0 if far == 2 else 5.0  # far 3: (+-3, +-3, 5): u.v = 25 - 18 = 7 > 0
    for dr, dc in ((far, far), (-far, -far), (far, -far), (-far, far)):
        g[r + dr, c + dc, 2] = hi


def _detect_both(g: np.ndarray, **kw):
    core, oracle = miem.detect(g, preset="paper", **kw), ref.detect(g, preset="paper", **kw)
    np.testing.assert_array_equal(core.labels, oracle.labels)
    np.testing.assert_array_equal(core.flags, oracle.flags)
    np.testing.assert_allclose(core.angle, oracle.angle, rtol=0, atol=1e-9, equal_nan=True)
    return core


@pytest.mark.parametrize("far", [2, 3])
def test_directions_flagged_at_different_scales_do_not_add_up(far: int) -> None:
    g = _flat(15, 15)
    _cross(g, 7, 7, far)
    one = dict(theta0=90.0, max_iterations=1)
    # every direction is flagged at some scale (flags 15: the old "any scale" rule's ABNORMAL),
    # but at no single scale: EDGE
    res = _detect_both(g, scales=(1, far), **one)
    assert res.flags[7, 7] == 15
    assert res.labels[7, 7] == EDGE
    assert res.angle[7, 7] == pytest.approx(math.degrees(math.acos(3 / 5)), abs=1e-9)
    # each scale alone: its own two directions
    assert _detect_both(g, scales=(1,), **one).flags[7, 7] == 0b0011
    assert _detect_both(g, scales=(far,), **one).flags[7, 7] == 0b1100
    # min_directions 2: scale 1 alone has 2 of its 4 available directions flagged
    res = _detect_both(g, scales=(1, far), min_directions=2, **one)
    assert res.labels[7, 7] == ABNORMAL and res.flags[7, 7] == 15
    assert_stream_equals_batch(g, miem.PRESETS["paper"].replace(scales=(1, far), **one))


def test_a_scale_that_sees_fewer_directions_does_not_judge_alone() -> None:
    # The cross's row / column neighbours raised 2 (flagged at scale 1, 53.13 deg); its
    # diagonal neighbours are dropouts and max_gap is 0, so the diagonals are available at
    # scale 2 only, flat there: 180 deg, not flagged. All 4 directions are available, 2 are
    # flagged at scale 1 (both of those scale 1 sees): not every available direction, EDGE.
    g = _flat(15, 15)
    for dr, dc in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        g[7 + dr, 7 + dc, 2] = 2.0
    for dr, dc in ((1, 1), (-1, -1), (1, -1), (-1, 1)):
        g[7 + dr, 7 + dc] = np.nan
    one = dict(theta0=90.0, max_gap=0, max_iterations=1)
    res = _detect_both(g, scales=(1, 2), **one)
    assert res.flags[7, 7] == 0b0011 and res.labels[7, 7] == EDGE
    # scale 1 alone sees 2 directions, both flagged: ABNORMAL
    assert _detect_both(g, scales=(1,), **one).labels[7, 7] == ABNORMAL
    assert_stream_equals_batch(g, miem.PRESETS["paper"].replace(scales=(1, 2), **one))


def test_a_spike_and_a_two_cell_burr_are_still_abnormal() -> None:
    g = _flat(16, 16)
    g[4, 4, 2] = 2.0  # a spike: (+-1, 0, -2): u.v = 3; (+-1, +-1, -2): u.v = 2: all flagged
    # a 2 x 2 burr of height 3 at rows / columns 9-10. Its cell (9, 9) at scale 1: along the
    # row (-1, 0, -3) and (1, 0, 0): u.v = -1, not flagged (the column and the diagonal alike;
    # the anti-diagonal (1, -1, -3), (-1, 1, -3): u.v = 7, flagged). At scale 2 every neighbour
    # is off the burr: (+-2, 0, -3): u.v = 5; (+-2, +-2, -3): u.v = 1: all 4 flagged.
    g[9:11, 9:11, 2] = 3.0
    res = _detect_both(g, theta0=90.0, scales=(1, 2), max_iterations=1)
    assert res.labels[4, 4] == ABNORMAL and res.flags[4, 4] == 15
    assert (res.labels[9:11, 9:11] == ABNORMAL).all()
    paper = _detect_both(g, theta0=90.0, scales=(1,), max_iterations=1)
    assert paper.labels[9, 9] == EDGE and paper.flags[9, 9] == 0b1000


def _wall(seed: int, noise: float = 0.006, angle: float = 11.0, h: int = 40, w: int = 80):
    """A flat plate with a vertical 1.5 mm step down along a line `angle` degrees off the rows
    (profiles 0.1 mm apart, points 0.05 mm apart along them), Gaussian noise: the designed edge
    of bench/accuracy/wall_alarms.md. Returns the grid and the cells within 2 points of it."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = xx * 0.05, yy * 0.1
    phi = math.radians(angle)
    d = -(x - x[0, w // 2]) * math.sin(phi) + (y - y[h // 2, 0]) * math.cos(phi)
    z = np.where(d < 0, 0.0, -1.5) + rng.normal(0.0, noise, (h, w))
    return np.dstack([x, y, z]), np.abs(d) < 0.1


@pytest.mark.parametrize("seed", [2, 4])
def test_a_step_eleven_degrees_off_the_rows_stays_edge(seed: int) -> None:
    # Every ray that crosses the step is > 90 degrees without noise (90 + atan(L / 1.5)); with
    # 6 um of noise on 50 um arms some crossing rays tip below 90, at scale 1 in some
    # directions and at scale 2 in the others: these seeds have cells flagged in all four
    # directions that way. The step is a designed edge: nothing on it is ABNORMAL.
    g, band = _wall(seed)
    kw = dict(theta0=90.0, scales=(1, 2))
    res = _detect_both(g, **kw)
    assert ((res.flags == 15) & band).any()
    assert not (res.labels == ABNORMAL).any()
    assert_stream_equals_batch(g, miem.PRESETS["paper"].replace(**kw))


def _planted(seed: int, far: int, h: int = 44, w: int = 52,
             dropout: float = 0.03) -> tuple[np.ndarray, list]:
    """A tilted, noisy plate (unit spacing) with crosses (_cross), spikes, 2 x 2 burrs and
    dropouts away from them. Returns the grid and the crosses' centres."""
    rng = np.random.default_rng(seed)
    g = _flat(h, w)
    g[:, :, 2] = 0.05 * g[:, :, 0] - 0.02 * g[:, :, 1]
    busy = np.zeros((h, w), dtype=bool)
    centres = []
    m = far + 2
    for _ in range(60):
        r, c = int(rng.integers(m, h - m)), int(rng.integers(m, w - m))
        if busy[r - m:r + m + 1, c - m:c + m + 1].any():
            continue
        busy[r - m:r + m + 1, c - m:c + m + 1] = True
        kind = len(centres) % 3 if len(centres) < 9 else 0
        if kind == 0:
            plate = g[r - far:r + far + 1, c - far:c + far + 1, 2].copy()
            g[r - far:r + far + 1, c - far:c + far + 1, 2] = 0.0
            _cross(g, r, c, far)
            g[r - far:r + far + 1, c - far:c + far + 1, 2] += plate  # on the tilted plate
            centres.append((r, c))
        elif kind == 1:
            g[r, c, 2] += 1.5
            centres.append(None)
        else:
            g[r:r + 2, c:c + 2, 2] += 4.0
            centres.append(None)
    g[:, :, 2] += rng.normal(0.0, 0.01, (h, w))
    drop = (rng.random((h, w)) < dropout) & ~busy
    g[drop] = np.nan
    return g, [p for p in centres if p is not None]


@pytest.mark.parametrize("far", [2, 3])
@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("extra", [{}, {"max_gap": 2}, {"min_step": 0.9, "max_reach": 3},
                                   {"min_directions": 3}])
def test_core_equals_reference_and_stream_equals_batch(far: int, seed: int, extra: dict) -> None:
    g, centres = _planted(seed, far)
    assert len(centres) >= 3
    kw = dict(theta0=90.0, scales=(1, far), **extra)
    if "min_directions" not in extra:
        # pass 1: the crosses' centres are flagged in all 4 directions across the scales and
        # stay EDGE (later passes remove the raised cells around them as spikes)
        first = _detect_both(g, max_iterations=1, **kw)
        for r, c in centres:
            assert first.flags[r, c] == 15 and first.labels[r, c] == EDGE, (r, c)
    res = _detect_both(g, **kw)
    assert (res.labels == ABNORMAL).any()
    assert_stream_equals_batch(g, miem.PRESETS["paper"].replace(**kw))


def test_clouds_judge_per_scale_too() -> None:
    # A point at the origin with 8 rays of 3 points each (1, 2 and 3.3 away, 45 degrees apart):
    # the axis rays raised 1.5 at 1, the diagonal rays raised 2.5 at 2. The neighbourhood is
    # symmetric: plane z = const, in-plane isotropic, so e1 = x and the K = 4 directions are
    # the axes (bits 0, 2) and diagonals (bits 1, 3). Scale 1 (|t| >= 0.5, nearest |w|): on the
    # axes (+-1, 0, 1.5) (|w| 1.80 < 2): u.v = 1.25 > 0, flagged; on the diagonals the flat
    # points 1 away: 180 deg. Scale 2 (|t| >= 1.5): on the axes the flat points 2 away: 180
    # deg; on the diagonals (+-1.41, +-1.41, 2.5): u.v = 2.25 > 0, flagged.
    pts = [(0.0, 0.0, 0.0)]
    for a in range(8):
        cx, cy, axis = math.cos(a * math.pi / 4), math.sin(a * math.pi / 4), a % 2 == 0
        pts += [(cx, cy, 1.5 if axis else 0.0), (2 * cx, 2 * cy, 0.0 if axis else 2.5),
                (3.3 * cx, 3.3 * cy, 0.0)]
    pts = np.array(pts)
    kw = dict(theta0=90.0, K=4, radius=3.5, min_step=0.5, max_iterations=1,
              height_tolerance=None, edge_tolerance=None, isolated_tolerance=None, min_group=0)
    for scales, flags, label in (((1, 2), 15, EDGE), ((1,), 0b0101, EDGE), ((2,), 0b1010, EDGE)):
        core, oracle = miem.detect_points(pts, scales=scales, **kw), ref.detect_points(
            pts, scales=scales, **kw)
        np.testing.assert_array_equal(core.labels, oracle.labels)
        np.testing.assert_array_equal(core.flags, oracle.flags)
        assert core.flags[0] == flags and core.labels[0] == label, scales
    assert miem.detect_points(pts, scales=(1, 2), **kw).angle[0] == pytest.approx(
        math.degrees(math.acos(1.25 / 3.25)), abs=1e-9)
    # min_directions 2: scale 1 has 2 of its 4 directions flagged
    assert miem.detect_points(pts, scales=(1, 2), min_directions=2, **kw).labels[0] == ABNORMAL


def test_one_scale_is_the_papers_rule() -> None:
    # With one scale a cell (all 4 directions available: no dropout, off the border, pass 1)
    # is ABNORMAL exactly when all 4 are flagged, or min_directions of them.
    g, _ = _planted(0, 2, dropout=0.0)
    inner = np.zeros(g.shape[:2], dtype=bool)
    inner[1:-1, 1:-1] = True
    for md, need in ((None, 4), (3, 3)):
        res = _detect_both(g, theta0=90.0, scales=(1,), min_directions=md, max_iterations=1)
        n_flag = np.array([[bin(int(f)).count("1") for f in row] for row in res.flags])
        np.testing.assert_array_equal(res.labels[inner] == ABNORMAL, (n_flag >= need)[inner])
        np.testing.assert_array_equal(res.labels[inner] == EDGE,
                                      ((n_flag > 0) & (n_flag < need))[inner])


def test_more_scales_than_the_row_kernel_holds() -> None:
    # the row kernel keeps 6 scales' bits; with 7 the scalar judge decides every cell
    g, _ = _planted(3, 2)
    for scales in ((1, 2, 3, 4, 5, 6), (1, 2, 3, 4, 5, 6, 7)):
        res = _detect_both(g, theta0=90.0, scales=scales)
        assert (res.labels == ABNORMAL).any() and (res.labels == EDGE).any()
        assert_stream_equals_batch(g, miem.PRESETS["paper"].replace(theta0=90.0, scales=scales))
