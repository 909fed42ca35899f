"""The cloud edge test's lips at a concave feature (SPEC "Unorganized clouds: edge test" step 6,
issue 11): a burr run raised on the last points before a concave crease, where the surface
beyond rises instead of falling away, is found; a clean concave crease and a concave fillet
stay clean; the core equals the reference (defaults, float32 1e3 mm away, 1 and 2 threads)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

import miem
from miem import reference as ref

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cloud_checks import (  # noqa: E402
    assert_core_is_reference_everywhere,
    pre_edge_pass,
    sectors_by_hand,
)

A = miem.ABNORMAL
K = 4.0  # the default edge_tolerance
STEP = 0.1
N = 44


def concave_scene(seed: int, lip: bool, fold_deg: float = 30.0, fillet: float | None = None,
                  b: float = 0.15, m: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """A tilted plane folding up by `fold_deg` past a line at 25 degrees (a concave crease; with
    `fillet`, rounded by a circle of that radius in mm); with `lip`, a burr run `m` points wide
    on the near side's last points (along 40 % of the line), raised from b / 2 to b towards the
    line (as the accuracy suite's burrs). x / y jittered by a quarter step, rows shuffled.
    Returns the points and the lip mask."""
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[0:N, 0:N]
    x, y = c.ravel() * STEP, r.ravel() * STEP
    phi = np.radians(25.0)
    d = (x - 0.5 * N * STEP) * np.cos(phi) + (y - 0.5 * N * STEP) * np.sin(phi)
    t = -(x - 0.5 * N * STEP) * np.sin(phi) + (y - 0.5 * N * STEP) * np.cos(phi)
    slope = np.tan(np.radians(fold_deg))
    if fillet is None:
        up = slope * np.maximum(d, 0.0)
    else:  # the circle up to the slope's angle, then the slope
        d1 = fillet * np.sin(np.radians(fold_deg))
        arc = fillet - np.sqrt(fillet * fillet - np.clip(d, 0.0, d1) ** 2)
        up = arc + slope * np.maximum(d - d1, 0.0)
    burr = lip & (d < 0.0) & (d >= -m * STEP) & (np.abs(t) < 0.2 * N * STEP)
    rise = b * (0.5 + 0.5 * np.clip(1.0 + d / (m * STEP), 0.0, 1.0))
    z = 0.04 * x + 0.02 * y + up + rng.normal(0.0, 0.01, x.size) + rise * burr
    pts = np.column_stack([x, y, z])
    pts[:, :2] += rng.uniform(-0.25 * STEP, 0.25 * STEP, (x.size, 2))
    order = rng.permutation(len(pts))
    return np.ascontiguousarray(pts[order]), burr[order]


def _lip_by_hand(pts: np.ndarray, normal: np.ndarray, ground: np.ndarray, i: int,
                 r_edge: float, gap: float) -> tuple[bool, bool]:
    """SPEC steps 2-4 and 6 for point i, computed here with SVDs and angles: (whether it fits a
    clean sector, whether it is a lip beyond one)."""
    hs = sectors_by_hand(pts, normal, i, r_edge, gap)
    fits = any(c and abs(h) <= K * hs.best for c, h in zip(hs.clean, hs.h))
    lip = False
    for s in range(16):
        if not hs.clean[s]:
            continue
        u, c, rms = hs.planes[s]
        h, t = hs.h[s], K * rms
        o = (s // 8) * 8 + (s % 8 + 4) % 8
        opp = hs.inside[o] & normal
        if not (h > t and opp.sum() >= 3 and u @ (hs.w[opp].mean(axis=0) - c) > 0.25 * h):
            continue  # not above s, or the surface beyond does not rise
        g = hs.bisector[o]  # the strip beyond P: within 45 degrees of g and 0.1 r_edge of it
        along = hs.rho * np.cos(hs.theta - g)
        across = hs.rho * np.sin(hs.theta - g)
        strip = np.flatnonzero(hs.member & ground & (along > np.abs(across))
                               & (np.abs(across) <= 0.1 * r_edge))
        if strip.size < 2:
            continue
        strip = strip[np.argsort(along[strip])]
        depth = hs.w[strip] @ u  # below P along s's normal: < 0
        dip = max(2 * t, 0.5 * h)
        lip |= bool(depth[:-1].min() < -dip and h + depth[-1] > t)
    return fits, lip


@pytest.mark.parametrize("fold_deg", [15.0, 30.0])
def test_lip_before_a_concave_crease_by_hand(fold_deg: float) -> None:
    """Lip points before a concave crease, judged here from the sectors in the first edge pass:
    they fit no clean sector and the surface beyond them dips below them, then rises above the
    plane they stand on (the opposite sector rising; no sector falls away, so no point stands
    proud): ABNORMAL in the core and the reference, and no point off the lip is."""
    caught = []
    for seed in (0, 1):
        pts, lip = concave_scene(seed, True, fold_deg)
        pre, r_edge, gap, normal, ground = pre_edge_pass(pts)
        mine = []
        for i in np.flatnonzero(lip & ground):
            fits, is_lip = _lip_by_hand(pts, normal, ground, int(i), r_edge, gap)
            if not fits and is_lip:
                mine.append(int(i))
        for fn in (miem.detect_points, ref.detect_points):
            lab = fn(pts).labels
            assert (lab[mine] == A).all(), seed
            assert not (lab[~lip] == A).any(), seed
        caught += mine
    assert len(caught) >= 5  # the case this test is about


@pytest.mark.parametrize("fillet", [None, 1.0])
@pytest.mark.parametrize("fold_deg", [15.0, 30.0])
def test_clean_concave_crease_and_fillet_stay_clean(fold_deg: float, fillet: float | None) -> None:
    """Without a lip the surface beyond a crease point never dips below it, and a point of a
    fillet lies above both faces' planes but the fillet only rises: no point is ABNORMAL."""
    for seed in (0, 1):
        pts, _ = concave_scene(seed, False, fold_deg, fillet)
        for fn in (miem.detect_points, ref.detect_points):
            assert not (fn(pts).labels == A).any(), seed


def test_core_matches_reference() -> None:
    pts, lip = concave_scene(2, True)
    assert (miem.detect_points(pts).labels[lip] == A).any()
    assert_core_is_reference_everywhere(pts)
