"""Held-out-style unorganized scenes: the accuracy suite's organized scenes as clouds.

Every synthetic scene of :mod:`suite` (and the paper scene) is flattened, its x / y jittered by
up to a quarter sampling step (uniform in ``[-step/4, step/4]``), its rows shuffled and its
dropouts removed, so a detector sees an irregular cloud with no order. The truth labels follow
the points. Same splits as the suite (tune / test).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import zlib

import numpy as np

from suite import Scene, scenes

__all__ = ["Cloud", "clouds", "to_cloud"]


@dataclass(frozen=True)
class Cloud:
    """One unorganized scene: points ``(N, 3)``, per-point truth and kinds, the source scene."""

    scene: Scene
    points: np.ndarray
    truth: np.ndarray
    kinds: np.ndarray

    @property
    def name(self) -> str:
        return self.scene.name

    @property
    def step(self) -> float:
        return self.scene.step


def to_cloud(scene: Scene, seed: int = 0) -> Cloud:
    """The scene as a jittered, shuffled cloud without dropouts (deterministic in ``seed``)."""
    rng = np.random.default_rng(zlib.crc32(scene.name.encode()) + seed)
    pts = scene.points.reshape(-1, 3).astype(np.float64)
    truth = scene.truth.reshape(-1)
    kinds = scene.kinds.reshape(-1)
    keep = np.isfinite(pts).all(axis=1)
    pts, truth, kinds = pts[keep], truth[keep], kinds[keep]
    pts = pts.copy()
    q = 0.25 * scene.step
    pts[:, :2] += rng.uniform(-q, q, (len(pts), 2))
    order = rng.permutation(len(pts))
    return Cloud(scene, np.ascontiguousarray(pts[order]), truth[order], kinds[order])


def clouds(split: str) -> Iterator[Cloud]:
    """The synthetic and paper scenes of ``split`` as clouds (real crops are left out: their
    truth depends on the grid detector's own labels)."""
    for scene in scenes(split, real=False):
        yield to_cloud(scene)
