"""The detectors compared by the accuracy benchmark, each with its tuning grid.

Every contender sees the same scene: miem the organized grid ``(H, W, 3)``, the cloud methods
its finite points flattened to ``(N, 3)`` (their verdicts are mapped back to the cells). Each
also knows the scene's sampling step (a scanner's step is always known), so length parameters
are given in steps. A contender splits its parameters into *structural* ones (a new, costly
computation) and *thresholds* (a cheap cut of the same scores), so that the tuning grid search
computes each score once.

Contenders:

- ``miem_paper``: ``miem.detect`` with the paper's settings (``preset="paper"``), not tuned;
- ``miem``: ``miem.detect`` with the settings chosen on the tuning split;
- ``global_eig``: one eigenvalue plane fitted to the whole scan, flag ``|d| > k rms``;
- ``local_plane``: CloudCompare's noise filter: the plane of each point's k nearest neighbours
  (the point excluded), flag the point when its distance is above ``n`` times the neighbours'
  rms distance (relative mode) or above an absolute error (absolute mode);
- ``o3d_sor``, ``o3d_ror``: Open3D ``remove_statistical_outlier`` and ``remove_radius_outlier``
  (removed points are flagged);
- ``o3d_plane``: Open3D ``segment_plane`` (RANSAC), flag points farther than a cut;
- ``lof``: scikit-learn ``LocalOutlierFactor``, flag points whose LOF exceeds a threshold.
"""

from __future__ import annotations

import inspect
import itertools
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import miem
import numpy as np

__all__ = [
    "CONTENDERS",
    "Contender",
    "miem_kwargs",
    "miem_supports",
]


def miem_supports(name: str) -> bool:
    """True when the installed ``miem.detect`` takes the keyword `name` (a detection parameter
    field, or an explicit argument)."""
    fields = miem.DetectParams.fields() if hasattr(miem, "DetectParams") else {}
    return name in fields or name in inspect.signature(miem.detect).parameters


def miem_kwargs(params: dict, step: float) -> dict:
    """``miem.detect`` keyword arguments from tuning parameters.

    ``min_step_steps`` and ``height_tolerance_steps`` are lengths in sampling steps; they are
    turned into ``min_step`` and ``height_tolerance`` in the scene's units. Lists become tuples.
    """
    out = {}
    for key, value in params.items():
        if key == "min_step_steps":
            out["min_step"] = None if value is None else value * step
        elif key == "height_tolerance_steps":
            out["height_tolerance"] = None if value is None else value * step
        else:
            out[key] = tuple(value) if isinstance(value, list) else value
    return out


def _product(**axes: list) -> list[dict]:
    keys = list(axes)
    return [dict(zip(keys, values)) for values in itertools.product(*axes.values())]


@dataclass
class Contender:
    """One detector.

    Attributes
    ----------
    name : str
        Short name (tables, JSON).
    title : str
        What it is, for the tables.
    prepare : callable
        ``prepare(points, finite, step, **structural) -> state``: the costly part.
    flag : callable
        ``flag(state, step, **threshold) -> bool (N,)`` over the finite points (or ``(H, W)``
        for a grid method).
    structural : list of dict
        Tuning grid of the structural parameters.
    thresholds : list of dict
        Tuning grid of the thresholds.
    grid_method : bool
        True: works on the organized grid; False: on the flattened finite points.
    fixed : dict or None
        Parameters used without tuning (``miem_paper``).
    """

    name: str
    title: str
    prepare: Callable[..., Any]
    flag: Callable[..., np.ndarray]
    structural: list[dict] = field(default_factory=lambda: [{}])
    thresholds: list[dict] = field(default_factory=lambda: [{}])
    grid_method: bool = False
    fixed: dict | None = None

    def split(self, params: dict) -> tuple[dict, dict]:
        """Split parameters into (structural, threshold) parts."""
        tkeys = set().union(*(t.keys() for t in self.thresholds))
        return (
            {k: v for k, v in params.items() if k not in tkeys},
            {k: v for k, v in params.items() if k in tkeys},
        )

    def state(self, points: np.ndarray, step: float, structural: dict) -> tuple[Any, np.ndarray]:
        """Run the costly part on a scene; returns (state, finite mask)."""
        finite = np.isfinite(points).all(axis=-1)
        src = points if self.grid_method else np.ascontiguousarray(points[finite])
        return self.prepare(src, step, **structural), finite

    def mask(self, state: Any, finite: np.ndarray, step: float, threshold: dict) -> np.ndarray:
        """Flagged cells ``(H, W)`` from a state."""
        out = self.flag(state, step, **threshold)
        if self.grid_method:
            return np.asarray(out, dtype=bool) & finite
        cells = np.zeros(finite.shape, dtype=bool)
        cells[finite] = out
        return cells

    def run(self, points: np.ndarray, step: float, params: dict) -> tuple[np.ndarray, float]:
        """Flagged cells and wall time (seconds) with the given parameters."""
        s, t = self.split(params)
        t0 = time.perf_counter()
        state, finite = self.state(points, step, s)
        cells = self.mask(state, finite, step, t)
        return cells, time.perf_counter() - t0


# --------------------------------------------------------------------------------------------
# miem


def _miem_prepare(grid: np.ndarray, step: float, **params: Any) -> np.ndarray:
    kwargs = {**EDGE_STAGE, **miem_kwargs(params, step)}
    # The tuned fields over the paper's method (what the tuning grid was built on), with the
    # edge stage of the default (tuned by edges.py --tune) on top.
    return miem.detect(grid, preset="paper", heights="abnormal", **kwargs).labels == miem.ABNORMAL


def _paper_prepare(grid: np.ndarray, step: float, **params: Any) -> np.ndarray:
    # The paper's method exactly: no edge stage (the default's edge test and min_step="auto").
    kwargs = miem_kwargs(params, step)
    return miem.detect(grid, preset="paper", heights="abnormal", **kwargs).labels == miem.ABNORMAL


def _miem_flag(state: np.ndarray, step: float) -> np.ndarray:
    return state


def _miem_grid() -> list[dict]:
    """Stage-1 grid of the miem tuning (the stage-2 grid is built around its winner)."""
    theta0: list[Any] = [75.0, 90.0, 105.0, 120.0, 135.0, 150.0]
    if miem_supports("height_tolerance"):
        theta0.append("auto")
        heights: list[dict] = [{"height_tolerance": None}]
        heights += [{"height_tolerance": f"{k}rms"} for k in (3, 4, 5, 6, 8)]
        heights += [{"height_tolerance_steps": v} for v in (0.5, 1.0, 2.0)]
    else:
        heights = [{}]
    # `edge_extent` (proposed in prototype.py): used when the core has it.
    extra = {"edge_extent": 12} if miem_supports("edge_extent") else {}
    out = []
    for t, s, g, hgt in itertools.product(
        theta0, [(1,), (1, 2), (1, 2, 3)], [0, 1], heights
    ):
        out.append({"theta0": t, "scales": s, "max_gap": g, **hgt, **extra})
    return out


# The paper's method, as the core defines it: the fields the accuracy benchmark tunes and writes
# to recommended.json (heights and the cloud-only fields are not tuned).
_TUNED_FIELDS = ("theta0", "scales", "max_gap", "min_step", "min_directions", "max_iterations",
                 "window", "height_tolerance", "edge_extent")
PAPER = {k: miem.PRESETS["paper"].flat("grid")[k] for k in _TUNED_FIELDS}
#: The default's edge stage (``min_step``, the edge test), tuned by ``edges.py --tune`` and kept
#: by this benchmark's own tuning.
EDGE_STAGE = {k: miem.PRESETS["recommended"].flat("grid")[k]
              for k in ("min_step", "edge_tolerance", "edge_window")}


# --------------------------------------------------------------------------------------------
# cloud baselines


def _global_prepare(pts: np.ndarray, step: float) -> np.ndarray:
    plane = miem.fit_plane(pts)
    return np.abs(plane.distance(pts)) / max(plane.rms, 1e-300)


def _global_flag(z: np.ndarray, step: float, k: float) -> np.ndarray:
    return z > k


def _local_prepare(pts: np.ndarray, step: float, k: int) -> tuple[np.ndarray, np.ndarray]:
    from scipy.spatial import cKDTree

    _, idx = cKDTree(pts).query(pts, k=k + 1)
    nb = pts[idx[:, 1:]]  # the point itself excluded (it is its own nearest neighbour)
    cen = nb.mean(axis=1)
    d = nb - cen[:, None, :]
    cov = np.einsum("nki,nkj->nij", d, d) / k
    lam, vec = np.linalg.eigh(cov)
    normal = vec[:, :, 0]
    dist = np.abs(np.einsum("ni,ni->n", pts - cen, normal))
    sigma = np.sqrt(np.maximum(lam[:, 0], 0.0))
    return dist, sigma


def _local_flag(state: tuple, step: float, mode: str, value: float) -> np.ndarray:
    dist, sigma = state
    if mode == "rel":
        return dist > value * sigma
    return dist > value * step


def _o3d_cloud(pts: np.ndarray) -> Any:
    import open3d as o3d

    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(pts)
    return pcd


def _removed(n: int, kept: list[int]) -> np.ndarray:
    out = np.ones(n, dtype=bool)
    out[np.asarray(kept, dtype=np.int64)] = False
    return out


def _sor_prepare(pts: np.ndarray, step: float, nb_neighbors: int, std_ratio: float) -> Any:
    _, kept = _o3d_cloud(pts).remove_statistical_outlier(
        nb_neighbors=nb_neighbors, std_ratio=std_ratio
    )
    return _removed(len(pts), kept)


def _ror_prepare(pts: np.ndarray, step: float, nb_points: int, radius_steps: float) -> Any:
    _, kept = _o3d_cloud(pts).remove_radius_outlier(
        nb_points=nb_points, radius=radius_steps * step
    )
    return _removed(len(pts), kept)


def _plane_prepare(pts: np.ndarray, step: float, ransac_steps: float) -> np.ndarray:
    import open3d as o3d

    o3d.utility.random.seed(0)
    origin = pts.mean(axis=0)  # RANSAC in float64 on centred data: far-from-origin frames
    (a, b, c, d), _ = _o3d_cloud(pts - origin).segment_plane(
        distance_threshold=ransac_steps * step, ransac_n=3, num_iterations=1000
    )
    return np.abs((pts - origin) @ np.array([a, b, c]) + d) / np.linalg.norm([a, b, c])


def _plane_flag(dist: np.ndarray, step: float, cut_steps: float) -> np.ndarray:
    return dist > cut_steps * step


def _lof_prepare(pts: np.ndarray, step: float, n_neighbors: int) -> np.ndarray:
    from sklearn.neighbors import LocalOutlierFactor

    lof = LocalOutlierFactor(n_neighbors=n_neighbors, n_jobs=1).fit(pts)
    return -lof.negative_outlier_factor_


def _lof_flag(score: np.ndarray, step: float, threshold: float) -> np.ndarray:
    return score > threshold


def _as_is(state: np.ndarray, step: float) -> np.ndarray:
    return state


def _contenders() -> dict[str, Contender]:
    paper = dict(PAPER)
    if miem_supports("height_tolerance"):
        paper["height_tolerance"] = None
    items = [
        Contender(
            "miem_paper", "miem, the paper's settings (theta0 75, scales (1,))",
            _paper_prepare, _miem_flag, grid_method=True, fixed=paper,
        ),
        Contender(
            "miem", "miem, recommended settings (tuned)", _miem_prepare, _miem_flag,
            structural=_miem_grid(), grid_method=True,
        ),
        Contender(
            "global_eig", "global eigenvalue plane, |d| > k rms", _global_prepare, _global_flag,
            thresholds=_product(k=[1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0]),
        ),
        Contender(
            "local_plane", "local plane of k neighbours (CloudCompare noise filter)",
            _local_prepare, _local_flag,
            structural=_product(k=[6, 12, 24]),
            thresholds=_product(mode=["rel"], value=[2.0, 3.0, 4.0, 6.0, 8.0, 12.0])
            + _product(mode=["abs"], value=[0.25, 0.5, 1.0, 2.0]),
        ),
        Contender(
            "o3d_sor", "Open3D remove_statistical_outlier", _sor_prepare, _as_is,
            structural=_product(nb_neighbors=[8, 16, 32, 64], std_ratio=[0.5, 1.0, 1.5, 2.0, 3.0,
                                                                          5.0]),
        ),
        Contender(
            "o3d_ror", "Open3D remove_radius_outlier", _ror_prepare, _as_is,
            structural=[
                {"radius_steps": r, "nb_points": n}
                for r, ns in ((1.5, (2, 4, 6, 8)), (2.5, (4, 8, 12, 16)), (4.0, (8, 16, 32, 45)))
                for n in ns
            ],
        ),
        Contender(
            "o3d_plane", "Open3D segment_plane (RANSAC) + distance cut", _plane_prepare,
            _plane_flag,
            structural=_product(ransac_steps=[0.5, 1.0, 2.0, 4.0]),
            thresholds=_product(cut_steps=[1.0, 2.0, 3.0, 5.0, 10.0, 20.0]),
        ),
        Contender(
            "lof", "scikit-learn LocalOutlierFactor", _lof_prepare, _lof_flag,
            structural=_product(n_neighbors=[10, 20, 40]),
            thresholds=_product(threshold=[1.2, 1.5, 2.0, 3.0, 5.0]),
        ),
    ]
    return {c.name: c for c in items}


#: Every contender by name, in table order.
CONTENDERS: dict[str, Contender] = _contenders()
