"""Tests of the surfaces and defect kinds added to ``miem.simulate`` for the accuracy benchmark.

Shell, saddle, fillet and edge-strip surfaces; 3 x 3 clusters, burr ridges, spatter domes,
height ranges; :func:`miem.simulate.inject_defects` on a given scan. Checked against the formulas
the docstrings state.
"""

from __future__ import annotations

import math

import miem
import numpy as np
import pytest
from miem import simulate as sim

N, A, E, INV = sim.NORMAL, sim.ABNORMAL, sim.EDGE, sim.INVALID


def test_extra_surfaces_formulas() -> None:
    step = 0.3
    shell = sim.make_scan(surface="shell", defects={}, step=step)
    x, y, z = (shell.points[..., i] for i in range(3))
    r = 1.5 * math.hypot(x.max(), y.max())
    np.testing.assert_allclose(z, np.sqrt(r * r - x * x - y * y) - r, rtol=0, atol=1e-12)
    saddle = sim.make_scan(surface="saddle", defects={}, radius=50.0)
    x, y, z = (saddle.points[..., i] for i in range(3))
    np.testing.assert_allclose(z, (x * x - y * y) / 100.0, rtol=0, atol=1e-12)
    for scan in (shell, saddle):
        assert not (scan.truth == E).any()


def test_fillet_surface_and_band() -> None:
    step, rf, face = 0.3, 8.0, 45.0
    scan = sim.make_scan(surface="fillet", defects={}, step=step, fillet_radius=rf,
                         flange_deg=face, line_angle_deg=0.0)
    x, z = scan.points[..., 0], scan.points[..., 2]
    rad = rf * step
    s1 = rad * math.sin(math.radians(face))
    arc = np.clip(x, 0.0, s1)
    want = rad - np.sqrt(rad * rad - arc * arc) + math.tan(math.radians(face)) * np.maximum(
        x - s1, 0.0
    )
    np.testing.assert_allclose(z, want, rtol=0, atol=1e-12)
    band = (x >= -1.5 * step) & (x <= s1 + 1.5 * step)
    assert np.array_equal(scan.truth == E, band)
    # tangent continuity: the slope never jumps by more than the arc turns over one step in x
    # (1 / (rf cos(theta)) rad per step, largest where the arc meets the face)
    slope = np.degrees(np.arctan(np.diff(z[0]) / step))
    turn = math.degrees(1.0 / (rf * math.cos(math.radians(face))))
    assert np.abs(np.diff(slope)).max() < turn + 1e-6
    assert slope.min() == pytest.approx(0.0, abs=1e-9)
    assert slope.max() == pytest.approx(face, abs=1e-9)


def test_strip_surface() -> None:
    scan = sim.make_scan(surface="strip", defects={"spike": 3}, step=0.5, line_offset=2.0,
                         strip_height=3.0)
    col = round(2.0 / 0.5 + 127 / 2.0)
    assert np.array_equal(np.flatnonzero((scan.truth == E).any(axis=0)), [col])
    assert (scan.truth[:, col] == E).all()
    np.testing.assert_allclose(scan.clean[:, col, 2], 1.5)
    for d in scan.defects:
        assert all(abs(c - col) > 5 for _, c in d.cells)
    res = miem.detect(scan.points)  # the paper's settings: the bead is EDGE, the spikes found
    assert np.array_equal(res.labels == A, scan.truth == A)
    assert (res.labels[scan.truth == E] == E).all()


def test_new_defect_shapes_and_heights() -> None:
    step = 0.4
    scan = sim.make_scan(
        defects={"cluster3": 2, "ridge_along": 2, "ridge_across": 2, "spatter": 6},
        step=step, height=(1.0, 4.0), ridge_length=(4, 10), spatter_width=(2, 4), seed=9,
        shape=(160, 160),
    )
    w = scan.shape[1]
    moved = np.any(scan.points != scan.clean, axis=-1)
    assert np.array_equal(moved, scan.truth == A)
    widths = set()
    for d in scan.defects:
        rows = {r for r, _ in d.cells}
        cols = {c for _, c in d.cells}
        dz = np.array([scan.points[r, c, 2] - scan.clean[r, c, 2] for r, c in d.cells])
        assert d.indices == tuple(sorted(r * w + c for r, c in d.cells))
        assert 1.0 * step <= d.offset <= 4.0 * step
        assert all(scan.kinds[c] == d.kind for c in d.cells)
        if d.kind == "cluster3":
            assert len(rows) == len(cols) == 3 and len(d.cells) == 9
            np.testing.assert_allclose(dz, d.offset)
        elif d.kind == "ridge_along":
            assert len(rows) == 1 and 4 <= len(cols) <= 10 and len(cols) == len(d.cells)
            assert max(cols) - min(cols) == len(cols) - 1
            np.testing.assert_allclose(dz, d.offset)
        elif d.kind == "ridge_across":
            assert len(cols) == 1 and 4 <= len(rows) <= 10 and len(rows) == len(d.cells)
            assert max(rows) - min(rows) == len(rows) - 1
            np.testing.assert_allclose(dz, d.offset)
        else:  # spatter: a smooth dome, every cell at least 0.7 of the peak
            wd = len(rows)
            widths.add(wd)
            assert len(cols) == wd and 2 <= wd <= 4
            assert len(d.cells) == (wd * wd if wd < 4 else wd * wd - 4)
            assert np.all(dz > 0.7 * d.offset) and np.all(dz < d.offset + 1e-12)
            mid = (wd - 1) / 2.0
            big = wd / 2.0 + 0.5
            want = [d.offset * math.sqrt(1 - ((r - min(rows) - mid) ** 2
                                               + (c - min(cols) - mid) ** 2) / big**2)
                    for r, c in d.cells]
            np.testing.assert_allclose(dz, want, rtol=0, atol=1e-12)
    assert len(widths) >= 2


def test_height_range_and_old_seeds_unchanged() -> None:
    # a fixed height draws nothing extra: the old kinds give the old scans
    a = sim.make_scan(defects={"spike": 2, "cluster": 1}, seed=3)
    b = sim.make_scan(defects={"spike": 2, "cluster": 1}, seed=3, height=(6.0, 6.0))
    assert np.array_equal(a.points, b.points)
    c = sim.make_scan(defects={"spike": 20, "dust": 5}, seed=3, height=(0.5, 1.0),
                      dust_height=(10.0, 60.0), shape=(160, 160))
    for d in c.defects:
        lo, hi = (0.5, 1.0) if d.kind == "spike" else (10.0, 60.0)
        assert lo * c.step <= d.offset <= hi * c.step
    assert len({d.offset for d in c.defects}) == 25


def test_inject_defects_on_a_given_scan() -> None:
    base = sim.make_scan(surface="curved", defects={}, noise=0.02, dropout=0.02, seed=4)
    truth = base.truth.copy()
    truth[:, :20] = 4  # e.g. "unknown" cells of a real scan: kept, never given a defect
    allowed = truth == N
    kinds = {"spike": 3, "spatter": 2, "ridge_across": 1}
    got = sim.inject_defects(base.points, base.step, kinds, seed=1, truth=truth, allowed=allowed,
                             height=(2.0, 3.0), margin=4)
    assert np.array_equal(got.clean, base.points, equal_nan=True)
    moved = np.any(got.points != got.clean, axis=-1) & np.isfinite(got.points).all(axis=-1)
    assert np.array_equal(moved, got.truth == A)
    assert (got.truth[:, :20] == 4).all()
    assert np.array_equal((got.truth == INV)[:, 20:], (base.truth == INV)[:, 20:])
    assert len(got.defects) == 6 and got.surface == "given"
    again = sim.inject_defects(base.points, base.step, kinds, seed=1, truth=truth,
                               allowed=allowed, height=(2.0, 3.0), margin=4)
    assert np.array_equal(again.points, got.points, equal_nan=True)
    default = sim.inject_defects(base.points, base.step, ["pit"], seed=2)
    assert np.count_nonzero(default.truth == A) == 1


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"surface": "torus"}, "surface"),
        ({"surface": "strip", "line_offset": 1e3}, "off the grid"),
        ({"surface": "shell", "radius": 1.0}, "radius"),
        ({"fillet_radius": 0.0}, "fillet_radius"),
        ({"strip_height": -1.0}, "strip_height"),
        ({"ridge_length": 1}, "ridge_length"),
        ({"spatter_width": (4, 2)}, "spatter_width"),
        ({"height": (3.0, 1.0)}, "height"),
        ({"dust_height": 0.0}, "dust_height"),
    ],
)
def test_bad_arguments_more(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        sim.make_scan(**kwargs)


def test_inject_defects_bad_arguments() -> None:
    grid = np.zeros((20, 20, 3))
    with pytest.raises(ValueError, match="shape"):
        sim.inject_defects(np.zeros((20, 3)), 0.3, ["spike"])
    with pytest.raises(ValueError, match="truth"):
        sim.inject_defects(grid, 0.3, ["spike"], truth=np.zeros((3, 3), np.uint8))
    with pytest.raises(ValueError, match="cannot place"):
        sim.inject_defects(grid, 0.3, {"spike": 50})
