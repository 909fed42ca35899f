"""The length unit of a scan file, which no common scan format records.

Detection itself is scale-free with the default settings (angles, cells, multiples of the local
rms and of the measured point spacing), but reports, plots and any absolute length a user passes
(``min_step``, a ``height_tolerance`` in length units, ``radius``) are read in the scan's unit.
Laser-profiler exports of workpieces are in millimetres; room and robot-cell clouds are in
metres. :func:`guess_units` tells the two apart from the scan's extent and point spacing.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["UnitGuess", "guess_units", "length_warning"]

#: A scan smaller than this (in its own units) with points closer than ``METRE_SPACING`` is in
#: metres: a workpiece in millimetres spanning under 10 mm with 20 um spacing is rarer than a
#: metre-scale cloud (a room, a cell, a car door) with millimetre spacing.
METRE_EXTENT = 10.0
METRE_SPACING = 0.02


@dataclass(frozen=True)
class UnitGuess:
    """What :func:`guess_units` concluded, and from what.

    Attributes
    ----------
    unit : str
        ``"m"`` or ``"mm"``.
    extent : float
        Largest side of the box holding the central 98 % of the finite points, scan units.
    spacing : float
        Median distance between neighbouring points (along profiles for a grid; nearest
        neighbour of a subsample for a cloud, an upper bound), scan units.
    """

    unit: str
    extent: float
    spacing: float

    @property
    def reason(self) -> str:
        return f"spans {self.extent:.4g} with a point spacing of {self.spacing:.3g}"


def _spacing(points: np.ndarray) -> float:
    if points.ndim == 3 and points.shape[1] > 1:
        step = np.linalg.norm(np.diff(points, axis=1), axis=-1)
        step = step[np.isfinite(step) & (step > 0)]
        return float(np.median(step)) if step.size else float("nan")
    flat = points.reshape(-1, 3)
    flat = flat[np.isfinite(flat).all(axis=1)]
    if flat.shape[0] < 3:
        return float("nan")
    if flat.shape[0] > 20000:  # a subsample: its spacing is an upper bound of the cloud's
        flat = flat[np.random.default_rng(0).choice(flat.shape[0], 20000, replace=False)]
    from ._unorganized import point_spacing

    try:
        return float(point_spacing(flat))
    except ValueError:
        return float("nan")


def guess_units(points: Any) -> UnitGuess:
    """Guess whether a scan is in metres or millimetres.

    Parameters
    ----------
    points : array_like, shape (N, 3) or (H, W, 3)
        The scan; NaN points are ignored.

    Returns
    -------
    UnitGuess
        ``unit="m"`` when the scan spans less than 10 units with points closer than 0.02 units,
        else ``"mm"``.
    """
    from ._api import _as_float_array

    pts = _as_float_array(points, "points")
    if pts.ndim not in (2, 3) or pts.shape[-1] != 3:
        raise ValueError(f"points: expected shape (N, 3) or (H, W, 3), got {pts.shape}")
    flat = pts.reshape(-1, 3)
    flat = flat[np.isfinite(flat).all(axis=1)]
    if flat.shape[0] == 0:
        return UnitGuess("mm", float("nan"), float("nan"))
    lo, hi = np.percentile(flat, [1, 99], axis=0)
    extent = float(np.max(hi - lo))
    spacing = _spacing(pts)
    metres = extent < METRE_EXTENT and np.isfinite(spacing) and spacing < METRE_SPACING
    return UnitGuess("m" if metres else "mm", extent, spacing)


def length_warning(name: str, value: float, guess: UnitGuess) -> str | None:
    """A warning when an absolute length makes no sense for the scan (None when it does).

    A length larger than the scan, or below a hundredth of its point spacing, was almost
    certainly given in the wrong unit.
    """
    if not np.isfinite(guess.extent) or value <= 0:
        return None
    if value > guess.extent:
        return (f"{name}={value:g} is larger than the scan itself, which {guess.reason} "
                f"(units look like {guess.unit}): was it given in the wrong unit?")
    if np.isfinite(guess.spacing) and value < guess.spacing / 100:
        return (f"{name}={value:g} is below 1/100 of the point spacing: the scan "
                f"{guess.reason} (units look like {guess.unit}): was it given in the wrong unit?")
    return None
