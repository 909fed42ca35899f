"""The cloud height test's bead rule (SPEC "Unorganized clouds: floating groups and height test",
step 3): a designed bead one point wide across a plane (the paper's edge strips, jittered as the
held-out-style clouds) is not ABNORMAL; a spike on it and a ridge shorter than the ball are."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

import miem
from miem import reference as ref

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cloud_checks import assert_same_cloud_result  # noqa: E402

A = miem.ABNORMAL
N_SIDE, STEP = 60, 0.5


def plane_with_bead(seed: int, spike_row: int | None = None,
                    ridge: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A 60 x 60 lattice (step 0.5, noise 0.05 step) with a bead one point wide and 3 steps tall
    along the middle column, from border to border (or, with ``ridge=(first, last)``, only over
    those rows: a ridge); ``spike_row`` raises that bead point 3 steps more. x / y jittered by a
    quarter step, rows shuffled. Returns the points and the bead mask."""
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[0:N_SIDE, 0:N_SIDE]
    r, c = r.ravel(), c.ravel()
    bead = c == N_SIDE // 2
    if ridge is not None:
        bead &= (r >= ridge[0]) & (r <= ridge[1])
    z = np.where(bead, 3.0 * STEP, 0.0) + rng.normal(0.0, 0.05 * STEP, r.size)
    if spike_row is not None:
        z[spike_row * N_SIDE + N_SIDE // 2] += 3.0 * STEP
    pts = np.column_stack([c * STEP, r * STEP, z])
    pts[:, :2] += rng.uniform(-0.25 * STEP, 0.25 * STEP, (r.size, 2))
    order = rng.permutation(r.size)
    return pts[order], bead[order]


def _stands_out(pts: np.ndarray, normal: np.ndarray, i: int, radius: float) -> float:
    """|height| / rms of point i over the plane of the ``normal`` points (radius, 2 radius] away
    (SVD): SPEC's surroundings plane."""
    d = np.linalg.norm(pts - pts[i], axis=1)
    ring = pts[(d > radius) & (d <= 2.0 * radius) & normal]
    c = ring.mean(axis=0)
    _, sv, vt = np.linalg.svd(ring - c, full_matrices=False)
    return abs(float((pts[i] - c) @ vt[2])) / (sv[2] / np.sqrt(len(ring)))


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_a_bead_is_no_defect_for_the_height_test(seed: int) -> None:
    pts, bead = plane_with_bead(seed)
    # the height test alone (the edge test off): it sees the bead's points above their
    # surroundings by up to about 7 rms (seed 1: two of them beyond, flagged without the rule)
    res = miem.detect_points(pts, edge_tolerance=None)
    assert not np.any(res.labels == A), np.flatnonzero(res.labels == A)
    if seed == 1:  # the premise, over the NORMAL points the angle passes leave
        angle = miem.detect_points(pts, edge_tolerance=None, height_tolerance=None)
        normal, radius = angle.labels == miem.NORMAL, res.params["radius"]
        assert np.count_nonzero(normal[bead]) > 40  # the crest is mostly NORMAL, not EDGE
        assert max(_stands_out(pts, normal, i, radius) for i in np.flatnonzero(bead)) > 7.0
    # the whole detector: the bead's inner points (off the scan's border rows) stay unflagged
    full = miem.detect_points(pts)
    inner = bead & (pts[:, 1] > 2 * STEP) & (pts[:, 1] < (N_SIDE - 3) * STEP)
    assert not np.any(full.labels[inner] == A)


def test_a_spike_on_the_bead_is_found() -> None:
    pts, bead = plane_with_bead(1, spike_row=30)
    spike = np.flatnonzero(bead & (pts[:, 2] > 4.5 * STEP))
    assert spike.size == 1
    res = miem.detect_points(pts)
    assert np.flatnonzero(res.labels == A).tolist() == spike.tolist()


@pytest.mark.parametrize("seed", [0, 1])
def test_a_ridge_shorter_than_the_ball_is_found(seed: int) -> None:
    # 7 points (3 mm) long: it ends inside the ball of its points (height radius 4 mm)
    pts, ridge = plane_with_bead(seed, ridge=(26, 32))
    res = miem.detect_points(pts)
    assert np.all(res.labels[ridge] == A)
    assert not np.any(res.labels[~ridge] == A)


@pytest.mark.parametrize("kwargs", [{"seed": 1}, {"seed": 1, "spike_row": 30},
                                    {"seed": 0, "ridge": (26, 32)}])
def test_core_matches_reference(kwargs: dict) -> None:
    pts, _ = plane_with_bead(**kwargs)
    assert_same_cloud_result(miem.detect_points(pts), ref.detect_points(pts))
