"""SPEC "Edge test" step 4, smooth curved surface: a cell that lies on the quadratic surface its
four quadrants bend as is not judged by the rules of steps 5-7.
On a bowl every one-sided plane misses the cell by several of its rms, whatever the radius."""

from __future__ import annotations

import numpy as np
import pytest

import miem
from miem import reference as ref
from miem.simulate import make_scan
from miem.stream import ProfileStream

_DEFECTS = {"spike": 4, "pit": 4, "cluster": 2, "dust": 1, "spatter": 1}


def _bowl(noise: float = 0.002, seed: int = 1) -> miem.simulate.Scan:
    """A tightly curved bowl (radius 20 mm at 0.2 mm steps) with defects."""
    return make_scan((120, 140), step=0.2, surface="curved", noise=noise, radius=20.0, seed=seed,
                     defects=_DEFECTS)


def _without_rule(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ref, "_curved", lambda h, *a, **k: np.zeros(h.shape[1], dtype=bool))


def test_the_rule_clears_false_alarms_on_a_bowl(monkeypatch: pytest.MonkeyPatch) -> None:
    """With edge_tolerance=2 the rules flag dozens of noise cells of a smooth bowl: the rule
    clears them and no defect cell, and the core (1 and 2 threads) and the stream equal the
    reference with it."""
    scan = _bowl()
    truth = np.asarray(scan.truth) == miem.ABNORMAL
    want = ref.detect(scan.points, edge_tolerance=2.0).labels
    for nt in (1, 2):
        np.testing.assert_array_equal(
            miem.detect(scan.points, edge_tolerance=2.0, num_threads=nt).labels, want)
    p = miem.default_params("stream").replace(edge_tolerance=2.0)
    stream = ProfileStream(scan.points.shape[1], params=p)
    rows = [r for prof in scan.points if (r := stream.push(prof)) is not None]
    rows += list(stream.flush())
    np.testing.assert_array_equal(np.stack([r.labels for r in rows]),
                                  miem.detect(scan.points, params=p).labels)
    _without_rule(monkeypatch)
    before = ref.detect(scan.points, edge_tolerance=2.0).labels
    cleared = (before == miem.ABNORMAL) & (want != miem.ABNORMAL)
    assert cleared.sum() >= 20
    assert not (cleared & truth).any()  # every cell it cleared is a false alarm
    assert not ((want == miem.ABNORMAL) & (before != miem.ABNORMAL)).any()


def _cell_sides(g: np.ndarray, r: int = 7) -> tuple:
    """_side_fits' arrays of the centre cell of grid g (all cells NORMAL, origin its first),
    with ``valid`` replaced by _clean_sides' ``level``."""
    cells = np.zeros(g.shape[:2], dtype=bool)
    cells[g.shape[0] // 2, g.shape[1] // 2] = True
    support = np.isfinite(g).all(axis=-1)
    origin = g[0, 0]
    h, rms, spread, valid, nrm, cen, empty, cov2 = ref._side_fits(g, support, ~support, cells,
                                                                  r, origin)
    level = ref._clean_sides(rms, spread, valid, nrm, 4.0)[0]
    return (h, rms, spread, level, nrm, cen, empty, cov2), g[cells] - origin


def _grid(z: np.ndarray, step: float = 0.2) -> np.ndarray:
    rows, cols = z.shape
    x, y = np.meshgrid(np.arange(cols) * step, np.arange(rows) * step)
    return np.dstack([x, y, z])


@pytest.mark.parametrize("a, b", [(1.0, 1.0), (1.0, 0.5), (0.2, 0.2), (1.0, -1.0)])
def test_a_quadratic_surface_passes_and_a_crease_or_a_bump_does_not(a: float, b: float) -> None:
    """The reference's rule on a noise-free z = a x^2 + b y^2 (x, y in cells: any radius, a
    saddle too): the centre cell lies on it. Not on a V crease through the cell (its quadrants
    are planes), and not with a bump of 0.05 on the cell. The floor 0.01 stands for the
    tolerance a scan's noise gives: the sub-window planes are orthogonal fits, whose slopes
    differ from the surface's by about 1 % on the sphere (0.005 of P's predicted offset)."""
    rows = cols = 31
    yy, xx = np.mgrid[0:rows, 0:cols] - 15.0
    z = 0.01 * (a * xx * xx + b * yy * yy)
    (h, rms, spread, level, nrm, cen, empty, cov2), pt = _cell_sides(_grid(z))
    floor = np.array([0.01])
    assert ref._curved(h, rms, level, nrm, cen, empty, cov2, pt, 4.0, floor).all()
    crease = _grid(0.3 * np.abs(xx))
    (h, rms, spread, level, nrm, cen, empty, cov2), pt = _cell_sides(crease)
    assert not ref._curved(h, rms, level, nrm, cen, empty, cov2, pt, 4.0, floor).any()
    z[15, 15] += 0.05
    (h, rms, spread, level, nrm, cen, empty, cov2), pt = _cell_sides(_grid(z))
    assert not ref._curved(h, rms, level, nrm, cen, empty, cov2, pt, 4.0, floor).any()


def test_the_quadrants_alone_decide() -> None:
    """The core solves a cell's four halves only when its quadrants do not settle it (SPEC step
    4): so the rule must read sides 4-7 and nothing of sides 0-3. Scrambling the halves'
    planes, centroids and flags of a bowl's cell leaves the reference's verdict as it was; so
    does scrambling a crease's (whose quadrants say no)."""
    rows = cols = 31
    yy, xx = np.mgrid[0:rows, 0:cols] - 15.0
    floor = np.array([0.01])
    rng = np.random.default_rng(5)
    for z, want in ((0.01 * (xx * xx + 0.5 * yy * yy), True), (0.3 * np.abs(xx), False)):
        (h, rms, _, level, nrm, cen, empty, cov2), pt = _cell_sides(_grid(z))
        arrays = (h, rms, level, nrm, cen, empty, cov2)
        assert ref._curved(*arrays, pt, 4.0, floor).all() == want
        scrambled = []
        for a in arrays:
            a = a.copy()
            if a.dtype == bool:
                a[:4] = ~a[:4]
            else:
                a[:4] = rng.normal(size=a[:4].shape) * 1e3
            scrambled.append(a)
        assert ref._curved(*scrambled, pt, 4.0, floor).all() == want
