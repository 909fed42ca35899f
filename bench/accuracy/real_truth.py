"""Burr truth of the real scan ``second_source.pcd``, derived from its golden sample ``target.pcd``.

The two files (``shared/data/real``, see its SOURCES.md) are scans of the same part type in
different frames: ``second_source`` (a laser profiler, burred) and ``target`` (burr-free).
The truth is derived here, without miem, in four steps:

1. **Grid.** ``second_source`` is rebuilt into its 426 x 724 grid: one row per profile (runs of
   equal ``y`` in file order), column ``round((x - x_min) / 0.05)``.
2. **Registration** of the golden sample onto the scan (Open3D, a bench dependency): FPFH
   features on 0.6 mm voxels, RANSAC on feature matches, then point-to-plane ICP at 1.0, 0.5 and
   0.3 mm. RANSAC is randomised, so the result is stored in ``real_registration.json`` (written
   by ``python bench/accuracy/real_truth.py --register``) with its fitness; every other step is
   deterministic.
3. **Deviation.** For every scan point, its nearest golden-sample point ``q`` and that point's
   normal ``n`` (PCA of its 20 nearest golden points, oriented ``n_z > 0`` in the scan frame:
   outward, towards the profiler). Signed deviation ``dev = n . (p - q)``. Where the golden
   normal is within 20 degrees of horizontal (a wall, which a height-field scan sees only at its
   top), the sign is meaningless and ``dev = |p - q|`` (a scan point off a wall stands out of it),
   unless the point lies *under the golden surface as the profiler sees it*: more than
   ``0.2 - band`` below the highest golden point within 0.15 mm in ``x, y`` (a little more than
   the golden sample's point spacing, 0.13 mm median). Then ``dev = -|p - q|``: material is
   missing there (a groove, or returns from below the part's outline), which is not a burr.
   Without this, a groove next to a golden wall read as a burr as deep as the groove: 1,013 BURR
   cells of the real scan, 895 of them the 2 mm groove of profiles 322-327 (its nearest golden
   points lie on the step wall 0.8 mm away) and 105 returns 10-12 mm below the top beyond the
   lower outline (profiles 381-384).
   A point is **not covered** when no golden point lies within 0.5 mm of it in ``x, y``.
4. **Classes** per cell: ``BURR`` when ``dev > 0.2 + band``, ``CLEAN`` when
   ``|dev| < 0.2 - band`` (band 0.05 mm: registration and part-to-part error are of that
   order), ``DONTCARE`` in between and for inward deviations below ``-(0.2 - band)`` (dents and
   multipath returns are not burrs, and flagging them is not a burr false alarm), ``UNCOVERED``,
   and ``DROPOUT`` for cells without a point. **Burr regions**: 8-connected components of cells
   with ``dev > 0.2``; a region is *found* when at least one of its BURR cells is flagged.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from suite import REAL_DIR, _window_rms  # noqa: E402

SOURCE, TARGET = "second_source.pcd", "target.pcd"
REGISTRATION = HERE / "real_registration.json"
THRESHOLD, BAND, COVER_XY, WALL_DEG, SEEN_XY = 0.2, 0.05, 0.5, 20.0, 0.15
CLEAN, BURR, DROPOUT, DONTCARE, UNCOVERED = 0, 1, 3, 4, 5

__all__ = ["BURR", "CLEAN", "DONTCARE", "DROPOUT", "UNCOVERED", "RealTruth", "available",
           "register", "score_mask", "source_grid", "truth"]


def available() -> bool:
    """True when both files are readable."""
    return (REAL_DIR / SOURCE).is_file() and (REAL_DIR / TARGET).is_file()


def _read(name: str) -> np.ndarray:
    import miem.io

    return np.asarray(miem.io.read(REAL_DIR / name).points, dtype=np.float64).reshape(-1, 3)


@lru_cache(maxsize=1)
def source_grid() -> np.ndarray:
    """The scan as its ``(426, 724, 3)`` grid (NaN = no point)."""
    pts = _read(SOURCE)
    line = np.concatenate([[0], np.cumsum(np.diff(pts[:, 1]) != 0)])
    col = np.round((pts[:, 0] - pts[:, 0].min()) / 0.05).astype(np.int64)
    grid = np.full((int(line.max()) + 1, int(col.max()) + 1, 3), np.nan)
    grid[line, col] = pts
    return grid


def _cloud(a: np.ndarray):  # noqa: ANN202 (open3d type)
    import open3d as o3d

    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(a)
    return pc


def register(seed: int = 2, voxel: float = 0.6) -> dict:
    """Golden sample -> scan frame: FPFH + RANSAC, then point-to-plane ICP (see module doc)."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    grid = source_grid()
    scan = grid[np.isfinite(grid).all(-1)]
    src, dst = _cloud(_read(TARGET)), _cloud(scan)

    def features(pc):  # noqa: ANN001, ANN202
        down = pc.voxel_down_sample(voxel)
        down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
        f = reg.compute_fpfh_feature(
            down, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))
        return down, f

    (sd, sf), (dd, df) = features(src), features(dst)
    o3d.utility.random.seed(seed)
    coarse = reg.registration_ransac_based_on_feature_matching(
        sd, dd, sf, df, True, 1.5 * voxel, reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
         reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
        reg.RANSACConvergenceCriteria(200_000, 0.999))
    dst.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.5, max_nn=30))
    t, fine = coarse.transformation, None
    for dist in (1.0, 0.5, 0.3):
        fine = reg.registration_icp(src, dst, dist, t, reg.TransformationEstimationPointToPlane(),
                                    reg.ICPConvergenceCriteria(max_iteration=60))
        t = fine.transformation
    return {"transform": np.asarray(t).tolist(), "ransac_fitness": coarse.fitness,
            "icp_fitness": fine.fitness, "icp_rmse": fine.inlier_rmse, "seed": seed,
            "voxel": voxel}


def load_registration() -> np.ndarray:
    """The stored 4 x 4 transform (golden sample -> scan frame)."""
    return np.asarray(json.loads(REGISTRATION.read_text())["transform"], dtype=np.float64)


@dataclass(frozen=True)
class RealTruth:
    """Per-cell burr truth of the real scan.

    Attributes
    ----------
    grid : ndarray (H, W, 3)
    dev : ndarray (H, W)
        Signed deviation (mm) from the registered golden sample; NaN for dropouts and
        uncovered cells.
    classes : ndarray (H, W) uint8
        CLEAN, BURR, DROPOUT, DONTCARE or UNCOVERED.
    regions : list of ndarray
        Flat indices of each burr region (8-connected ``dev > THRESHOLD``).
    region_height : ndarray
        Largest deviation in each region (mm).
    nn_median : float
        Median scan-to-golden nearest distance over covered cells (registration quality).
    flat : ndarray (H, W) bool
        *Flat surface*: CLEAN cells at least 10 cells from any cell that is not CLEAN, whose
        5 x 5 local plane rms is at most 3 times the scan's median (where EDGE labels are
        banding, not features).
    """

    grid: np.ndarray
    dev: np.ndarray
    classes: np.ndarray
    regions: list
    region_height: np.ndarray
    nn_median: float
    flat: np.ndarray


def _components(mask: np.ndarray) -> list[np.ndarray]:
    from scipy import ndimage

    lab, n = ndimage.label(mask, structure=np.ones((3, 3), dtype=int))
    flat = lab.reshape(-1)
    order = np.argsort(flat, kind="stable")
    bounds = np.searchsorted(flat[order], np.arange(1, n + 2))
    return [order[bounds[i]:bounds[i + 1]] for i in range(n)]


def _seen_top(gold: np.ndarray, gold_xy, pts: np.ndarray) -> np.ndarray:  # noqa: ANN001
    """Per point, the highest golden ``z`` within ``SEEN_XY`` in ``x, y`` (the golden surface
    as a profiler above it sees it); ``-inf`` where there is none."""
    top = np.full(len(pts), -np.inf)
    for i, nb in enumerate(gold_xy.query_ball_point(pts[:, :2], SEEN_XY)):
        if nb:
            top[i] = gold[nb, 2].max()
    return top


@lru_cache(maxsize=1)
def truth() -> RealTruth:
    """The truth of the whole scan (see the module doc)."""
    from scipy.spatial import cKDTree

    grid = source_grid()
    h, w, _ = grid.shape
    t = load_registration()
    gold = _read(TARGET) @ t[:3, :3].T + t[:3, 3]
    fin = np.isfinite(grid).all(-1)
    pts = grid[fin]
    tree = cKDTree(gold)
    dist, idx = tree.query(pts)
    # golden normals (PCA of 20 nearest), only where needed
    need = np.unique(idx)
    _, nb = tree.query(gold[need], k=20)
    q = gold[nb] - gold[nb].mean(axis=1, keepdims=True)
    normals = np.linalg.eigh(np.einsum("kni,knj->kij", q, q))[1][:, :, 0]
    normals[normals[:, 2] < 0] *= -1.0
    lookup = np.zeros((len(gold), 3))
    lookup[need] = normals
    n = lookup[idx]
    diff = pts - gold[idx]
    dev = np.einsum("ij,ij->i", diff, n)
    wall = n[:, 2] < np.sin(np.radians(WALL_DEG))
    dev[wall] = dist[wall]
    gold_xy = cKDTree(gold[:, :2])
    under = wall.copy()
    under[wall] = pts[wall, 2] < _seen_top(gold, gold_xy, pts[wall]) - (THRESHOLD - BAND)
    dev[under] = -dist[under]  # under the golden surface: material missing, not a burr
    covered = gold_xy.query(pts[:, :2], distance_upper_bound=COVER_XY)[0] <= COVER_XY
    dev_grid = np.full((h, w), np.nan)
    dev_grid[fin] = np.where(covered, dev, np.nan)
    cls = np.full((h, w), DROPOUT, dtype=np.uint8)
    c = np.full(len(pts), DONTCARE, dtype=np.uint8)
    c[np.abs(dev) < THRESHOLD - BAND] = CLEAN
    c[dev > THRESHOLD + BAND] = BURR
    c[~covered] = UNCOVERED
    cls[fin] = c
    regions = _components(np.nan_to_num(dev_grid, nan=-1.0) > THRESHOLD)
    flat = dev_grid.reshape(-1)
    heights = np.array([flat[r].max() for r in regions])
    from scipy import ndimage

    rms = _window_rms(grid)
    smooth = np.isfinite(rms) & (rms <= 3.0 * np.nanmedian(rms))
    away = ~ndimage.binary_dilation(cls != CLEAN, structure=np.ones((21, 21), dtype=bool))
    flat = (cls == CLEAN) & away & smooth
    return RealTruth(grid, dev_grid, cls, regions, heights, float(np.median(dist[covered])), flat)


@dataclass(frozen=True)
class RealScore:
    """Scores of one flagged mask against the real truth."""

    tp: int
    fn: int
    fp: int
    precision: float
    recall: float
    regions: int
    regions_found: int
    regions_tall: int
    regions_tall_found: int

    @property
    def f1(self) -> float:
        d = 2 * self.tp + self.fp + self.fn
        return 2 * self.tp / d if d else float("nan")


def score_mask(flagged: np.ndarray, tr: RealTruth, tall: float = 0.3) -> RealScore:
    """Per-cell and per-region scores of ``flagged`` (H, W bool).

    Regions count when they hold at least one BURR cell; *tall* regions are those whose
    largest deviation exceeds ``tall`` mm.
    """
    flagged = np.asarray(flagged, dtype=bool)
    if flagged.shape != tr.classes.shape:
        raise ValueError(f"flagged: expected shape {tr.classes.shape}, got {flagged.shape}")
    burr, clean = tr.classes == BURR, tr.classes == CLEAN
    tp = int((flagged & burr).sum())
    fn = int((~flagged & burr).sum())
    fp = int((flagged & clean).sum())
    fb, bf = flagged.reshape(-1), burr.reshape(-1)
    n = found = n_tall = found_tall = 0
    for r, height in zip(tr.regions, tr.region_height):
        cells = r[bf[r]]
        if not len(cells):
            continue
        hit = bool(fb[cells].any())
        n += 1
        found += hit
        if height > tall:
            n_tall += 1
            found_tall += hit
    prec = tp / (tp + fp) if tp + fp else float("nan")
    rec = tp / (tp + fn) if tp + fn else float("nan")
    return RealScore(tp, fn, fp, prec, rec, n, found, n_tall, found_tall)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--register", action="store_true", help="recompute real_registration.json")
    args = ap.parse_args(argv)
    if not available():
        print(f"real scans not found in {REAL_DIR}")
        return 1
    if args.register or not REGISTRATION.is_file():
        result = register()
        REGISTRATION.write_text(json.dumps(result, indent=1) + "\n")
        print(f"registration: {result}")
    tr = truth()
    counts = {name: int((tr.classes == code).sum()) for name, code in
              (("clean", CLEAN), ("burr", BURR), ("dontcare", DONTCARE),
               ("uncovered", UNCOVERED), ("dropout", DROPOUT))}
    print(f"median nearest distance {tr.nn_median:.4f} mm; cells {counts}; "
          f"regions {len(tr.regions)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
