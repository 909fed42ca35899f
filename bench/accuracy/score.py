"""Scores of the accuracy benchmark: confusion counts of ABNORMAL against the truth labels.

A detector's output is a boolean mask of the cells it calls abnormal (for miem: label ABNORMAL;
for an outlier filter: the points it removes). Against the truth (see :mod:`suite`):

- true positive: a defect cell flagged; false negative: a defect cell not flagged;
- false alarm on a normal cell, false alarm on a designed-edge cell: both false positives;
- dropout and unknown cells are not scored (a cloud method never sees dropouts).

Precision, recall and F1 are those of the defect class; ``edge_fa`` and ``normal_fa`` are the
fractions of edge and normal cells flagged. Counts add up, so scores of a group of scenes are
computed from summed counts (micro averages), never by averaging ratios.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, fields

import numpy as np

__all__ = ["Counts", "confusion", "kind_counts"]

_NORMAL, _DEFECT, _EDGE = 0, 1, 2


def _ratio(num: float, den: float) -> float:
    """``num / den``, NaN when ``den == 0``."""
    return num / den if den else float("nan")


@dataclass(frozen=True)
class Counts:
    """Confusion counts of one scene or a sum of scenes.

    Attributes
    ----------
    tp : int
        Defect cells flagged.
    fn : int
        Defect cells not flagged.
    fp_normal : int
        Normal cells flagged.
    fp_edge : int
        Designed-edge cells flagged.
    n_normal : int
        Normal cells scored.
    n_edge : int
        Designed-edge cells scored.
    seconds : float
        Detector wall time.
    """

    tp: int = 0
    fn: int = 0
    fp_normal: int = 0
    fp_edge: int = 0
    n_normal: int = 0
    n_edge: int = 0
    seconds: float = 0.0

    def __add__(self, other: Counts) -> Counts:
        return Counts(*(getattr(self, f.name) + getattr(other, f.name) for f in fields(self)))

    @staticmethod
    def total(items: Iterable[Counts]) -> Counts:
        """Sum of counts (an empty sum is all zeros)."""
        out = Counts()
        for c in items:
            out = out + c
        return out

    @property
    def fp(self) -> int:
        """All false positives (normal and edge cells flagged)."""
        return self.fp_normal + self.fp_edge

    @property
    def n_defect(self) -> int:
        """Defect cells scored."""
        return self.tp + self.fn

    @property
    def precision(self) -> float:
        """``tp / (tp + fp)``; NaN when nothing was flagged."""
        return _ratio(self.tp, self.tp + self.fp)

    @property
    def recall(self) -> float:
        """``tp / (tp + fn)``; NaN without defects."""
        return _ratio(self.tp, self.n_defect)

    @property
    def f1(self) -> float:
        """``2 tp / (2 tp + fp + fn)``; NaN when there is neither a defect nor a flag."""
        return _ratio(2 * self.tp, 2 * self.tp + self.fp + self.fn)

    @property
    def edge_fa(self) -> float:
        """Fraction of designed-edge cells flagged; NaN without edge cells."""
        return _ratio(self.fp_edge, self.n_edge)

    @property
    def normal_fa(self) -> float:
        """Fraction of normal cells flagged."""
        return _ratio(self.fp_normal, self.n_normal)


def confusion(flagged: np.ndarray, truth: np.ndarray, seconds: float = 0.0) -> Counts:
    """Confusion counts of a flagged mask against truth labels.

    Parameters
    ----------
    flagged : array_like of bool, shape (H, W)
        Cells the detector calls abnormal.
    truth : array_like of uint8, shape (H, W)
        0 normal, 1 defect, 2 designed edge; other codes are not scored.
    seconds : float
        Detector wall time, carried along.

    Returns
    -------
    Counts
    """
    f = np.asarray(flagged, dtype=bool)
    t = np.asarray(truth)
    if f.shape != t.shape:
        raise ValueError(f"flagged {f.shape} and truth {t.shape} differ in shape")
    defect, normal, edge = t == _DEFECT, t == _NORMAL, t == _EDGE
    tp = int(np.count_nonzero(f & defect))
    return Counts(
        tp=tp,
        fn=int(np.count_nonzero(defect)) - tp,
        fp_normal=int(np.count_nonzero(f & normal)),
        fp_edge=int(np.count_nonzero(f & edge)),
        n_normal=int(np.count_nonzero(normal)),
        n_edge=int(np.count_nonzero(edge)),
        seconds=float(seconds),
    )


def kind_counts(flagged: np.ndarray, kinds: np.ndarray) -> dict[str, tuple[int, int]]:
    """Defect cells found per kind.

    Parameters
    ----------
    flagged : array_like of bool, shape (H, W)
        Cells the detector calls abnormal.
    kinds : array_like of str, shape (H, W)
        Defect kind per cell, ``""`` where there is no defect.

    Returns
    -------
    dict of str to (int, int)
        ``{kind: (found, total)}`` for every kind present.
    """
    f = np.asarray(flagged, dtype=bool)
    k = np.asarray(kinds)
    out = {}
    for name in np.unique(k[k != ""]):
        cells = k == name
        out[str(name)] = (int(np.count_nonzero(f & cells)), int(np.count_nonzero(cells)))
    return out
