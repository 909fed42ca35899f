"""NumPy/SciPy reference for the deviation from a reference surface (docs/SPEC.md, "Deviation
from a reference"): written from the spec, independently of the core, as the oracle the tests
compare ``miem.compare`` with. Needs SciPy; slow and simple on purpose.
"""

from __future__ import annotations

from dataclasses import dataclass
import numpy as np
from numpy.typing import ArrayLike, NDArray

WITHIN, EXCESS, MISSING, NOT_COVERED = 0, 1, 2, 3


@dataclass
class RefDeviation:
    deviation: NDArray[np.float64]  # NaN where not covered
    distance: NDArray[np.float64]  # to the nearest reference point, NaN where not covered
    nearest: NDArray[np.int64]  # row of the nearest reference point, -1 where not covered
    covered: NDArray[np.bool_]


@dataclass
class RefDeviationDefect:
    indices: NDArray[np.int64]
    peak_height: float
    mean_height: float
    centroid: NDArray[np.float64]
    kind: str


def deviation(scan: ArrayLike, reference: ArrayLike, normals: ArrayLike, max_distance: float,
              max_lateral: float = float("inf")) -> RefDeviation:
    """Nearest usable reference point q (finite point and normal) within ``max_distance`` of each
    finite scan point p (ties: lowest row); deviation ``n_q . (p - q)``; covered when q exists and
    the lateral offset ``|(p - q) - dev n_q|`` is at most ``max_lateral``."""
    from scipy.spatial import cKDTree

    p = np.asarray(scan, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    nrm = np.asarray(normals, dtype=np.float64)
    usable = np.isfinite(ref).all(1) & np.isfinite(nrm).all(1)
    rows = np.flatnonzero(usable)
    dev = np.full(len(p), np.nan)
    dist = np.full(len(p), np.nan)
    nearest = np.full(len(p), -1, dtype=np.int64)
    finite = np.isfinite(p).all(1)
    if rows.size == 0 or not finite.any():
        return RefDeviation(dev, dist, nearest, np.zeros(len(p), bool))
    tree = cKDTree(ref[rows])
    idx = np.flatnonzero(finite)
    pts = p[finite]
    d, k = tree.query(pts, k=min(2, rows.size))
    d, k = d.reshape(len(pts), -1), k.reshape(len(pts), -1)
    hit = d[:, 0] <= max_distance
    best = k[:, 0].copy()
    # Ties to the lowest row: resolve wherever the two nearest are equally far.
    if d.shape[1] == 2:
        for a in np.flatnonzero(hit & (d[:, 0] == d[:, 1])):
            tied = tree.query_ball_point(pts[a], d[a, 0] * (1 + 1e-12))
            d2 = np.sum((pts[a] - ref[rows[tied]]) ** 2, axis=1)
            best[a] = min(t for t, v in zip(tied, d2) if v == d2.min())
    k = best
    i = idx[hit]
    q = rows[k[hit]]
    diff = p[i] - ref[q]
    n = nrm[q]
    dv = (diff[:, 0] * n[:, 0] + diff[:, 1] * n[:, 1]) + diff[:, 2] * n[:, 2]
    t = diff - dv[:, None] * n
    over = (t[:, 0] * t[:, 0] + t[:, 1] * t[:, 1]) + t[:, 2] * t[:, 2] <= max_lateral**2
    dist[i] = np.sqrt((diff[:, 0] * diff[:, 0] + diff[:, 1] * diff[:, 1]) + diff[:, 2] * diff[:, 2])
    nearest[i] = q
    dev[i[over]] = dv[over]
    covered = np.zeros(len(p), bool)
    covered[i[over]] = True
    return RefDeviation(dev, dist, nearest, covered)


def label_deviation(points: ArrayLike, dev: ArrayLike, covered: ArrayLike, tolerance: float,
                    dont_care: float, link: float) -> tuple[NDArray[np.uint8],
                                                            list[RefDeviationDefect]]:
    """Labels and defects: groups of out-of-tolerance points of one sign linked by distance
    ``<= link``; a group whose peak ``|deviation|`` is not above ``tolerance + dont_care`` is
    WITHIN. Defects ordered by ``|peak|`` descending, ties by first index."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    p = np.asarray(points, dtype=np.float64)
    dv = np.asarray(dev, dtype=np.float64)
    cov = np.asarray(covered, dtype=bool) & np.isfinite(p).all(1) & np.isfinite(dv)
    labels = np.where(cov, WITHIN, NOT_COVERED).astype(np.uint8)
    defects: list[RefDeviationDefect] = []
    for sign, label, kind in ((1.0, EXCESS, "protrusion"), (-1.0, MISSING, "pit")):
        cand = np.flatnonzero(cov & (sign * np.where(cov, dv, 0.0) > tolerance))
        if cand.size == 0:
            continue
        # query_pairs is strict at r in some SciPy versions: widen, then filter exactly.
        pairs = cKDTree(p[cand]).query_pairs(link * (1 + 1e-9) + 1e-300, output_type="ndarray")
        if len(pairs):
            d2 = np.sum((p[cand[pairs[:, 0]]] - p[cand[pairs[:, 1]]]) ** 2, axis=1)
            pairs = pairs[d2 <= link * link]
        m = len(cand)
        g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])) if len(pairs)
                       else (np.zeros(0), (np.zeros(0, int), np.zeros(0, int))), shape=(m, m))
        _, comp = connected_components(g, directed=False)
        for c in np.unique(comp):
            members = np.sort(cand[comp == c])
            vals = dv[members]
            peak_pos = int(np.argmax(np.abs(vals)))  # first on ties
            peak = float(vals[peak_pos])
            if not abs(peak) > tolerance + dont_care:
                continue
            labels[members] = label
            defects.append(RefDeviationDefect(members, peak, float(vals.mean()),
                                              p[members].mean(axis=0), kind))
    defects.sort(key=lambda d: (-abs(d.peak_height), int(d.indices[0])))
    return labels, defects
