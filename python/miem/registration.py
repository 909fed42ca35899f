"""Rigid registration of a scan onto a reference, orchestrating maintained libraries: a coarse
global alignment (FPFH features + RANSAC, Open3D) when no initial pose is given, then
coarse-to-fine point-to-plane ICP (small_gicp or Open3D). The fit is measured by miem's own core
(nearest reference point and signed distance along its normal), the same for every library.

Install the libraries with ``pip install "miem[compare]"``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np

from . import _core
from ._api import _as_float_array, _int, _real, _threads

__all__ = ["Registration", "register", "LIBRARIES", "apply_transform"]

#: Fine-registration libraries, best first (the order ``library="auto"`` tries them in), and the
#: default ICP variant: the fastest candidate within 2 % of the best RMSE on second_source.pcd
#: against target.pcd in bench/bench_compare.py (bench/results_compare.md).
LIBRARIES = ("open3d", "small_gicp")
#: Fine ICP variants: point-to-plane ICP and generalized ICP (plane-to-plane).
METHODS = ("point_to_plane", "gicp")
DEFAULT_METHOD = "point_to_plane"


class MissingDependencyError(ImportError):
    """A registration library is not installed."""


@dataclass(frozen=True)
class Registration:
    """A rigid transform from the scan's frame into the reference's, and how well it fits.

    Attributes
    ----------
    transform : ndarray, shape (4, 4)
        Homogeneous transform: ``reference_point = R @ scan_point + t``.
    coarse_transform : ndarray, shape (4, 4)
        The starting pose of the fine ICP (the given initial transform, or the global alignment).
    rmse : float
        RMS signed point-to-surface distance of the inlier scan points.
    inlier_fraction : float
        Finite scan points within ``inlier_distance`` of a reference point, over all finite ones.
    inlier_distance : float
        The distance used for the fit.
    library : str
        Fine-registration library used (``"small_gicp"`` or ``"open3d"``).
    method : str
        Fine ICP variant (``"gicp"`` or ``"point_to_plane"``).
    coarse : str
        ``"fpfh_ransac"`` (found automatically) or ``"given"``.
    voxel : float
        Downsampling voxel of the fine ICP.
    seconds : dict
        Wall time of the stages (``coarse``, ``fine``).
    """

    transform: np.ndarray
    coarse_transform: np.ndarray
    rmse: float
    inlier_fraction: float
    inlier_distance: float
    library: str
    method: str
    coarse: str
    voxel: float
    seconds: dict = field(default_factory=dict)

    @property
    def rotation(self) -> np.ndarray:
        return self.transform[:3, :3]

    @property
    def translation(self) -> np.ndarray:
        return self.transform[:3, 3]


def apply_transform(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``R @ p + t`` for every row of ``points`` (float64, a new array)."""
    t = np.asarray(transform, dtype=np.float64)
    return np.asarray(points, dtype=np.float64) @ t[:3, :3].T + t[:3, 3]


def _check_transform(value: Any, name: str) -> np.ndarray:
    try:
        t = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a 4 x 4 rigid transform, got {value!r}") from None
    if t.shape != (4, 4) or not np.isfinite(t).all():
        raise ValueError(f"{name}: expected a finite 4 x 4 rigid transform, got shape {t.shape}")
    r = t[:3, :3]
    if (not np.allclose(t[3], [0, 0, 0, 1], atol=1e-9)
            or not np.allclose(r @ r.T, np.eye(3), atol=1e-5) or np.linalg.det(r) < 0):
        raise ValueError(f"{name}: the upper 3 x 3 block must be a rotation (orthonormal, det "
                         "+1) and the last row 0 0 0 1")
    return t


def _finite_rows(points: Any, name: str) -> np.ndarray:
    arr = _as_float_array(points, name)
    if arr.ndim == 3 and arr.shape[2] == 3:
        arr = arr.reshape(-1, 3)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (N, 3) or (H, W, 3), got {arr.shape}")
    out = np.asarray(arr[np.isfinite(arr).all(axis=1)], dtype=np.float64)
    if len(out) < 10:
        raise ValueError(f"{name}: at least 10 finite points are needed, got {len(out)}")
    return out


def _spacing(points: np.ndarray) -> float:
    try:
        s = float(_core.point_spacing(points, 0))
    except ValueError:
        s = 0.0
    if not s > 0.0:
        raise ValueError("points: degenerate (more than half the points coincide)")
    return s


def _extent(points: np.ndarray) -> float:
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


def _import(library: str) -> Any:
    try:
        if library == "open3d":
            import open3d  # noqa: PLC0415

            return open3d
        if library == "small_gicp":
            import small_gicp  # noqa: PLC0415

            return small_gicp
    except ImportError:
        raise MissingDependencyError(
            f"{library} is not installed: pip install \"miem[compare]\" (or pip install "
            f"{'open3d-cpu' if library == 'open3d' else library})") from None
    raise ValueError(f"library: expected 'auto' or one of {LIBRARIES}, got {library!r}")


def _pick_library(library: str) -> str:
    if library != "auto":
        _import(library)
        return library
    for name in LIBRARIES:
        try:
            _import(name)
            return name
        except MissingDependencyError:
            continue
    raise MissingDependencyError('registration needs small_gicp or Open3D: pip install '
                                 '"miem[compare]"')


def _o3d_cloud(o3d: Any, points: np.ndarray) -> Any:
    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(points)
    return pc


def _fpfh_ransac(scan: np.ndarray, ref: np.ndarray, voxel: float, seed: int,
                 threads: int) -> tuple[np.ndarray, float]:
    """Open3D's FPFH + RANSAC global registration at one voxel size: (transform, fitness)."""
    o3d = _import("open3d")
    reg = o3d.pipelines.registration
    o3d.utility.random.seed(seed)

    def features(points: np.ndarray) -> tuple[Any, Any]:
        pc = _o3d_cloud(o3d, points).voxel_down_sample(voxel)
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.0 * voxel, max_nn=30))
        f = reg.compute_fpfh_feature(
            pc, o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel, max_nn=100))
        return pc, f

    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        s, sf = features(scan)
        r, rf = features(ref)
        dist = 1.5 * voxel
        res = reg.registration_ransac_based_on_feature_matching(
            s, r, sf, rf, True, dist, reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
             reg.CorrespondenceCheckerBasedOnDistance(dist)],
            reg.RANSACConvergenceCriteria(100_000, 0.999))
    return np.asarray(res.transformation, dtype=np.float64), float(res.fitness)


class _Fine:
    """Point-to-plane ICP on voxel-downsampled clouds with one library, the reference prepared
    once and reused for every stage."""

    def __init__(self, library: str, method: str, ref: np.ndarray, scan: np.ndarray,
                 voxel: float, threads: int) -> None:
        self.library = library
        self.method = method
        self.threads = max(1, threads)
        self.voxel = voxel
        if library == "small_gicp":
            sg = _import("small_gicp")
            self.sg = sg
            # preprocess_points estimates normals and covariances (PLANE_ICP and GICP).
            self.target, self.tree = sg.preprocess_points(
                ref, downsampling_resolution=voxel, num_neighbors=20, num_threads=self.threads)
            self.source, _ = sg.preprocess_points(
                scan, downsampling_resolution=voxel, num_neighbors=20, num_threads=self.threads)
        else:
            o3d = _import("open3d")
            self.o3d = o3d
            self.target = _o3d_cloud(o3d, ref).voxel_down_sample(voxel)
            self.target.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
            self.source = _o3d_cloud(o3d, scan).voxel_down_sample(voxel)
            if method == "gicp":
                self.source.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))

    def align(self, init: np.ndarray, max_distance: float, iterations: int = 30) -> np.ndarray:
        if self.library == "small_gicp":
            r = self.sg.align(self.target, self.source, self.tree, init_T_target_source=init,
                              registration_type="GICP" if self.method == "gicp" else
                              "PLANE_ICP",
                              max_correspondence_distance=max_distance,
                              num_threads=self.threads, max_iterations=iterations,
                              rotation_epsilon=1e-5, translation_epsilon=1e-5 * self.voxel)
            return np.asarray(r.T_target_source, dtype=np.float64)
        reg = self.o3d.pipelines.registration
        criteria = reg.ICPConvergenceCriteria(max_iteration=iterations)
        if self.method == "gicp":
            r = reg.registration_generalized_icp(
                self.source, self.target, max_distance, init,
                reg.TransformationEstimationForGeneralizedICP(), criteria)
        else:
            r = reg.registration_icp(self.source, self.target, max_distance, init,
                                     reg.TransformationEstimationPointToPlane(), criteria)
        return np.asarray(r.transformation, dtype=np.float64)

    def refine(self, init: np.ndarray, start: float, end: float) -> np.ndarray:
        """Stages of halving correspondence distance from `start` down to `end`."""
        t = init
        d = max(start, end)
        while True:
            t = self.align(t, d)
            if d <= end:
                return t
            d = max(d / 2.0, end)


def _fit(surface: Any, scan: np.ndarray, transform: np.ndarray, inlier_distance: float,
         threads: int) -> tuple[float, float]:
    """(rmse, inlier_fraction) by miem's core."""
    dev, _, _, covered = surface.deviation(apply_transform(transform, scan), inlier_distance,
                                           float("inf"), threads)
    n_in = int(covered.sum())
    if n_in == 0:
        return float("nan"), 0.0
    return float(np.sqrt(np.mean(dev[covered] ** 2))), n_in / len(scan)


def _unit_up_normals(ref: np.ndarray, spacing: float, threads: int) -> np.ndarray:
    """Normals for the fit only (sign irrelevant: the rmse squares the deviation)."""
    normals, _, _, _ = _core.estimate_normals(ref, 3.0 * spacing, threads)
    return normals


def register(
    scan: Any,
    reference: Any,
    *,
    init_transform: Optional[Any] = None,
    library: str = "auto",
    method: str = DEFAULT_METHOD,
    voxel: Optional[float] = None,
    inlier_distance: Optional[float] = None,
    min_inlier_fraction: float = 0.2,
    seed: int = 0,
    num_threads: Optional[int] = None,
    _surface: Any = None,
) -> Registration:
    """Register ``scan`` onto ``reference`` (both point arrays, (N, 3) or (H, W, 3)).

    Parameters
    ----------
    scan, reference : array_like
        Points; non-finite rows are ignored.
    init_transform : array_like (4, 4), optional
        Rough pose of the scan in the reference's frame. None: found automatically by FPFH +
        RANSAC (Open3D) at voxel sizes of 1/30, 1/45, 1/20 and 1/60 of the smaller diagonal, each
        polished by a coarse ICP; the first with 90 % of the scan within half a voxel of the
        reference, else the best, wins.
    library : str
        Fine ICP library: ``"auto"`` (the first installed of :data:`LIBRARIES`), ``"small_gicp"``
        or ``"open3d"``.
    method : str
        ``"point_to_plane"`` (the default) or ``"gicp"`` (generalized ICP, plane-to-plane).
    voxel : float, optional
        Downsampling voxel of the fine ICP; default ``max(2 x scan spacing, 2 x reference
        spacing, diagonal / 200)`` (diagonal: the smaller of the two clouds' bounding boxes).
    inlier_distance : float, optional
        A scan point is an inlier of the fit when a reference point lies within this distance;
        default ``3 x voxel``.
    min_inlier_fraction : float
        Below this inlier fraction the registration has failed: ValueError.
    seed : int
        Seed of the RANSAC sampling.

    Raises
    ------
    ValueError
        Bad arguments, too few points, or a registration that does not overlap the reference.
    MissingDependencyError
        The library needed is not installed (an ImportError naming the extra).
    """
    src = _finite_rows(scan, "scan")
    ref = _finite_rows(reference, "reference")
    init = None if init_transform is None else _check_transform(init_transform, "init_transform")
    threads = _threads(num_threads)
    nthreads = threads if threads > 0 else max(1, _core_threads())
    seed = _int("seed", seed, 0)
    mif = _real("min_inlier_fraction", min_inlier_fraction)
    if not 0.0 <= mif <= 1.0:
        raise ValueError(f"min_inlier_fraction: expected 0..1, got {mif}")
    lib = _pick_library(library)
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    s_spacing, r_spacing = _spacing(src), _spacing(ref)
    if voxel is None:
        v = max(2.0 * s_spacing, 2.0 * r_spacing, min(_extent(src), _extent(ref)) / 200.0)
    else:
        v = _real("voxel", voxel)
        if not v > 0:
            raise ValueError(f"voxel: expected a length > 0, got {v}")
    if inlier_distance is None:
        d_in = 3.0 * v
    else:
        d_in = _real("inlier_distance", inlier_distance)
        if not d_in > 0:
            raise ValueError(f"inlier_distance: expected a length > 0, got {d_in}")
    surface = _surface
    if surface is None:
        surface = _core.ReferenceSurface(ref, _unit_up_normals(ref, r_spacing, threads),
                                         2.0 * r_spacing, threads)
    t0 = time.perf_counter()
    if init is None:
        # Global alignment candidates at a few scales, each polished by a quick ICP on clouds
        # downsampled to half its voxel; the one with most scan points near the reference wins.
        diag = min(_extent(src), _extent(ref))
        probe = src[:: max(1, len(src) // 20000)]
        best = None
        for k in (30.0, 45.0, 20.0, 60.0):
            cv = max(diag / k, v)
            t_c, _ = _fpfh_ransac(src, ref, cv, seed, nthreads)
            t_c = _Fine(lib, method, ref, src, cv / 2.0, nthreads).refine(t_c, 2.0 * cv, cv / 2.0)
            score = _fit(surface, probe, t_c, cv / 2.0, threads)[1]
            if best is None or score > best[0]:
                best = (score, t_c, cv)
            if score >= 0.9:
                break  # good enough: most of the scan lies on the reference
        assert best is not None
        coarse_t, start, how = best[1], best[2], "fpfh_ransac"
    else:
        coarse_t, start, how = init, 10.0 * v, "given"
    fine = _Fine(lib, method, ref, src, v, nthreads)
    t1 = time.perf_counter()
    # Halving correspondence distances down to 1.5 voxels, then one stage at 0.75 voxel that
    # leaves out what is not on the surface (burrs, outliers) and removes their pull.
    final = fine.align(fine.refine(coarse_t, start, 1.5 * v), 0.75 * v)
    t2 = time.perf_counter()
    rmse, frac = _fit(surface, src, final, d_in, threads)
    if frac < mif:
        raise ValueError(
            f"registration failed: only {100 * frac:.1f} % of the scan lies within "
            f"{d_in:.4g} of the reference (min_inlier_fraction={mif}); the scan and the "
            "reference do not overlap, or give init_transform (a rough pose)")
    return Registration(transform=final, coarse_transform=coarse_t, rmse=rmse,
                        inlier_fraction=frac, inlier_distance=d_in, library=lib, method=method, coarse=how,
                        voxel=v, seconds={"coarse": t1 - t0, "fine": t2 - t1})


def _core_threads() -> int:
    import os  # noqa: PLC0415

    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (
        os.cpu_count() or 1)
