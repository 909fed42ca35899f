"""Held-out-style unorganized scenes: the accuracy suite's organized scenes as clouds.

Every synthetic scene of :mod:`suite` (and the paper scene) is flattened, its x / y jittered by
up to a quarter sampling step (uniform in ``[-step/4, step/4]``), its rows shuffled and its
dropouts removed, so a detector sees an irregular cloud with no order. The truth labels follow
the points. Same splits as the suite (tune / test, and the diagnosis set third).

The jitter moves a point along x / y but keeps its ``z``: on a surface of slope ``g`` it adds
noise across the surface of about ``g * step / (4 sqrt 3)`` (uniform), which the organized scene
does not have (on ``tune-edge_cut-0``, 0.5 mm steps on a 7-degree slope, the sector rms is
0.009 mm against 0.006 mm from the scene's own noise).

Run as a script for the losses per kind: ``python bench/accuracy/clouds.py [--split tune]
[--kinds edge_cut,...] [--no-grid]``: F1, misses (FN) and false alarms on the designed edge and
on normal surface (FA), and for the edge kinds the burr cells found per burr height band, with
the organized detector on the same scenes beside it (the quality the clouds are measured
against).
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
    region: np.ndarray | None = None  # burr region per point (edge kinds), -1 elsewhere

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
    region = None if scene.region is None else scene.region.reshape(-1)[keep][order]
    return Cloud(scene, np.ascontiguousarray(pts[order]), truth[order], kinds[order], region)


def clouds(split: str) -> Iterator[Cloud]:
    """The synthetic and paper scenes of ``split`` as clouds (real crops are left out: their
    truth depends on the grid detector's own labels)."""
    for scene in scenes(split, real=False):
        yield to_cloud(scene)


#: Burr height bands (mm) of the loss report: low burrs rise b/2..b, within a few noise rms.
BANDS = (0.0, 0.1, 0.2, np.inf)


def _losses(split: str, kinds: set[str] | None, grid: bool) -> list[str]:
    """The loss report's lines (see the module doc)."""
    import miem
    from score import Counts, confusion

    per: dict[str, dict[str, list]] = {}
    for c in clouds(split):
        kind = c.scene.spec.group
        if kinds and kind not in kinds:
            continue
        runs = [("cloud", miem.detect(c.points).labels == miem.ABNORMAL, c.truth, c.region)]
        if grid:
            runs.append(("grid", (miem.detect(c.scene.points).labels == miem.ABNORMAL).ravel(),
                         c.scene.truth.ravel(),
                         None if c.scene.region is None else c.scene.region.ravel()))
        for name, flagged, truth, region in runs:
            d = per.setdefault(kind, {}).setdefault(name, [Counts(), np.zeros((2, 3), int)])
            d[0] = d[0] + confusion(flagged, truth)
            if region is not None:
                hgt = c.scene.region_height
                for r in range(hgt.size):
                    band = int(np.searchsorted(BANDS, hgt[r], side="right")) - 1
                    m = region == r
                    d[1][0, band] += int(np.count_nonzero(flagged & m))
                    d[1][1, band] += int(np.count_nonzero(m))
    lines = [f"split {split}: F1, burr cells missed (FN), false alarms on the designed edge and "
             "on normal surface (FA edge / FA normal); edge kinds: burr cells found per height "
             "band (mm)",
             "| kind | detector | F1 | TP | FN | FA edge | FA normal | " +
             " | ".join(f"b {lo:g}-{hi:g}" for lo, hi in zip(BANDS[:-1], BANDS[1:])) + " |",
             "|" + "---|" * (7 + len(BANDS) - 1)]
    for kind, d in per.items():
        for name, (cnt, bands) in d.items():
            cells = [f"{bands[0, b]}/{bands[1, b]}" if bands[1, b] else "-"
                     for b in range(len(BANDS) - 1)]
            lines.append(f"| {kind} | {name} | {cnt.f1:.3f} | {cnt.tp} | {cnt.fn} | "
                         f"{cnt.fp_edge} | {cnt.fp_normal} | " + " | ".join(cells) + " |")
    return lines


def main(argv: list[str] | None = None) -> int:
    """Print the loss report (see the module doc)."""
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--split", choices=("tune", "test", "third"), default="tune")
    ap.add_argument("--kinds", default="", help="comma-separated focus kinds (default: all)")
    ap.add_argument("--no-grid", action="store_true",
                    help="skip the organized detector on the same scenes")
    args = ap.parse_args(argv)
    kinds = {k for k in args.kinds.split(",") if k} or None
    print("\n".join(_losses(args.split, kinds, not args.no_grid)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
