"""Synthetic burrs on cut edges, wall tops, creases and flanges (the accuracy suite's edge kinds).

Every scene is a height field sampled like a laser profiler: rows are profiles ``dy`` apart
(uneven: mostly ``dy``, some ``2 dy``, a few ``10 dy``), columns ``step`` apart along the profile,
``z`` with Gaussian noise, a per-profile offset and 1 um quantisation. A straight or curved
feature line crosses the scan at any angle; ``d`` is the signed distance (mm) of a cell from it
(negative on the part's main side):

==========  =================================================================================
kind        geometry (``z0``: a tilted plane)
==========  =================================================================================
edge_cut    ``z0`` where ``d < 0``; no return (NaN) beyond: the part's outline
edge_wall   ``z0`` where ``d < 0``, ``z0 - drop`` beyond (a wall top; drop 1-3 mm)
edge_crease ``z0 + tan(fold) * max(d, 0)``, fold +-(10-40) degrees
edge_flange ``z0 - tan(bend) * w * softplus(d / w)``: a rounded bend, ``w`` 0.5-1.5 mm
==========  =================================================================================

Burrs: 3-6 runs along the line, each 1-30 profiles long, on the last ``m`` (1-4) points before
the line (``-m * step <= d < 0``) raised ``b`` (0.05-0.5 mm, rising towards the line); on
``edge_wall`` some runs instead *hang* beyond the wall: ``m`` points past it at the top's level
less a droop of ``b``. Truth: DEFECT for the burr cells, EDGE for the designed feature (within
two steps of the line; the bend's width on flanges), NORMAL elsewhere, DROPOUT for NaN.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["EDGE_KINDS", "EdgeScene", "make_edge_scene"]

EDGE_KINDS = ("edge_cut", "edge_wall", "edge_crease", "edge_flange")
NORMAL, DEFECT, EDGE, DROPOUT = 0, 1, 2, 3
QUANTUM = 0.001


@dataclass(frozen=True, eq=False)
class EdgeScene:
    """One generated scene: points ``(H, W, 3)``, truth ``(H, W)``, the burr region of each
    defect cell ``(H, W)`` (-1 elsewhere) and each region's height (mm)."""

    points: np.ndarray
    truth: np.ndarray
    region: np.ndarray
    region_height: np.ndarray
    step: float


def _softplus(x: np.ndarray) -> np.ndarray:
    return np.logaddexp(0.0, x)


def make_edge_scene(kind: str, seed: int, *, shape: tuple[int, int] = (110, 130),
                    step: float = 0.1, noise: float = 0.01, curved: bool = False,
                    dropout: float = 0.005) -> EdgeScene:
    """Generate one edge scene (deterministic in ``seed``); see the module doc."""
    if kind not in EDGE_KINDS:
        raise ValueError(f"kind: expected one of {EDGE_KINDS}, got {kind!r}")
    rng = np.random.default_rng(seed)
    h, w = shape
    dy = 2.0 * step if rng.random() < 0.5 else step
    gaps = rng.choice([1.0, 2.0, 10.0], size=h - 1, p=[0.9, 0.08, 0.02])
    y = np.concatenate([[0.0], np.cumsum(gaps * dy)])
    x = np.arange(w) * step
    X, Y = np.meshgrid(x, y)
    cx, cy = x[w // 2] + rng.uniform(-0.1, 0.1) * x[-1], y[h // 2]
    phi = rng.uniform(0.0, np.pi)
    nx, ny = np.cos(phi), np.sin(phi)
    t = -(X - cx) * ny + (Y - cy) * nx  # along the line
    d = (X - cx) * nx + (Y - cy) * ny
    if curved:
        d = d + t * t / (2.0 * rng.uniform(4.0, 10.0)) * rng.choice([-1.0, 1.0])
    slope = np.tan(np.radians(rng.uniform(0.0, 15.0)))
    az = rng.uniform(0.0, 2.0 * np.pi)
    z0 = slope * (X * np.cos(az) + Y * np.sin(az))
    z = z0.copy()
    edge = np.zeros((h, w), dtype=bool)
    near = np.abs(d) < 2.0 * step
    if kind == "edge_cut":
        z[d >= 0] = np.nan
        edge = near & (d < 0)
    elif kind == "edge_wall":
        drop = rng.uniform(1.0, 3.0)
        z = np.where(d < 0, z0, z0 - drop)
        edge = near
    elif kind == "edge_crease":
        fold = np.radians(rng.uniform(10.0, 40.0)) * rng.choice([-1.0, 1.0])
        z = z0 + np.tan(fold) * np.maximum(d, 0.0)
        edge = near
    else:
        width = rng.uniform(0.5, 1.5)
        bend = np.radians(rng.uniform(20.0, 50.0))
        z = z0 - np.tan(bend) * width * _softplus(d / width)
        edge = np.abs(d) < 2.0 * width + step
    region = np.full((h, w), -1, dtype=np.int64)
    heights = []
    n_runs = int(rng.integers(3, 7))
    t_lo, t_hi = np.nanmin(np.where(np.abs(d) < step * 4, t, np.nan)), np.nanmax(
        np.where(np.abs(d) < step * 4, t, np.nan))
    starts = np.sort(rng.uniform(t_lo, t_hi, size=n_runs))
    for k, s0 in enumerate(starts):
        length = rng.integers(1, 31) * dy
        m = int(rng.integers(1, 5))
        b = rng.uniform(0.05, 0.5)
        along = (t >= s0) & (t < s0 + length) & (region < 0)
        hang = kind == "edge_wall" and rng.random() < 0.4
        if hang:
            cells = along & (d >= 0) & (d < m * step)
            z = np.where(cells, z0 - b, z)
        else:
            cells = along & (d < 0) & (d >= -m * step)
            rise = b * (0.5 + 0.5 * np.clip(1.0 + d / (m * step), 0.0, 1.0))
            z = np.where(cells, z + rise, z)
        if cells.any():
            region[cells] = len(heights)
            heights.append(b)
        del k
    z = z + rng.normal(0.0, noise, size=(h, w)) + rng.normal(0.0, noise / 2, size=(h, 1))
    z = np.round(z / QUANTUM) * QUANTUM
    z[rng.random((h, w)) < dropout] = np.nan
    pts = np.stack([X, Y, z], axis=-1)
    pts[~np.isfinite(z)] = np.nan
    truth = np.where(region >= 0, DEFECT, np.where(edge, EDGE, NORMAL)).astype(np.uint8)
    truth[~np.isfinite(z)] = DROPOUT
    region[~np.isfinite(z)] = -1
    return EdgeScene(pts, truth, region, np.asarray(heights, dtype=np.float64), float(step))
