"""The cloud edge test's two scales (SPEC "Unorganized clouds: edge test", step 7): sectors
within the edge radius R and within 1.5 R, checked by hand from the sectors and against the core
and the reference."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

import miem
from miem import reference as ref

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cloud_checks import (  # noqa: E402
    assert_core_is_reference_everywhere,
    pre_edge_pass,
    sectors_by_hand,
)
from test_clouds_edge import flange_scene  # noqa: E402

A = miem.ABNORMAL
K = 4.0  # the default edge_tolerance
WIDE = 1.5  # the wide scale, in edge radii


def _falls_beyond(pts: np.ndarray, normal: np.ndarray, i: int, r: float, gap: float) -> tuple:
    """Steps 3-4 at sector radius r for point i, by hand: whether it stands proud (h > k rms)
    of a clean sector of which it is the top, and whether, for one of those, the opposite's
    support (at least 3 NORMAL points) has its centroid below that sector's plane by more
    than k rms (the surface beyond falls away)."""
    hs = sectors_by_hand(pts, normal, i, r, gap)
    proud = falls = False
    for s in range(16):
        if not hs.clean[s]:
            continue
        u, m, rms = hs.planes[s]
        if not -u @ m > K * rms or any(p is not None and u @ p[1] > 0 for p in hs.planes):
            continue
        proud = True
        o = (s // 8) * 8 + (s % 8 + 4) % 8
        sup = hs.inside[o] & normal
        falls |= sup.sum() >= 3 and u @ (hs.w[sup].mean(axis=0) - m) < -K * rms
    return proud, falls


def _fine_flange(seed: int, lip: bool) -> tuple[np.ndarray, np.ndarray]:
    # a bend of 35 degrees rounded over 1 mm, 0.05 mm steps: within R (10 spacings, ~0.4 mm)
    # the surface past the lip bends only a little
    return flange_scene(seed, lip, step=0.05, bend=35.0, width=1.0, b=0.2)


def test_the_wide_scale_sees_the_bend_fall_away() -> None:
    """Lip points before a gently rounded bend at 0.05 mm steps, judged here from the sectors on
    the labels the edge test starts from: each stands proud of a clean sector of which it is
    the top, but within R the surface beyond that sector's opposite bends too little to fall
    away below its plane; within 1.5 R it does. ABNORMAL in the core and the reference (at the
    narrow scale alone 5 of the 70 lip points were); nothing but the lip is ABNORMAL, and
    without the lip nothing is."""
    pts, lip = _fine_flange(0, True)
    pre, r_edge, gap, normal, _ = pre_edge_pass(pts)
    caught = []
    for i in np.flatnonzero(lip & (pre.labels != A)):
        proud_n, falls_n = _falls_beyond(pts, normal, int(i), r_edge, gap)
        _, falls_w = _falls_beyond(pts, normal, int(i), WIDE * r_edge, gap)
        if proud_n and not falls_n and falls_w:
            caught.append(int(i))
    assert len(caught) >= 5  # the case this test is about (9 points)
    for fn in (miem.detect_points, ref.detect_points):
        res = fn(pts)
        assert res.params["edge_radius"] == r_edge
        assert (res.labels[caught] == A).all()
        assert not (res.labels[~lip] == A).any()
        assert not (fn(_fine_flange(0, False)[0]).labels == A).any()
    assert_core_is_reference_everywhere(pts)


def test_two_scales_float32_and_threads() -> None:
    """The same labels in float32 and float64 and for 1 and 2 threads, on a scene where the
    wide scale decides (another seed)."""
    pts, lip = _fine_flange(1, True)
    base = miem.detect_points(pts, num_threads=1).labels
    assert (base[lip] == A).mean() > 0.9 and not (base[~lip] == A).any()
    np.testing.assert_array_equal(miem.detect_points(pts, num_threads=2).labels, base)
    np.testing.assert_array_equal(miem.detect_points(pts.astype(np.float32)).labels, base)
