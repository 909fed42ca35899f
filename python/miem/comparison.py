"""Compare a scan with a golden sample or a CAD model: registration, signed deviation along the
reference's outward normal, coverage, labels (excess / missing / within tolerance / not covered)
and defects in the same form as :func:`miem.detect`, and their agreement with MIEM's own labels.

The rules are in docs/SPEC.md, "Deviation from a reference". Registration needs
``pip install "miem[compare]"`` (small_gicp, Open3D, trimesh for meshes).

>>> res = miem.compare(scan, "golden.pcd", tolerance=0.2)
>>> res.counts(), res.registration.rmse, res.defects[0].peak_height
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Union

import numpy as np

from . import _core
from ._api import Defect, DetectResult, _as_float_array, _int, _real, _threads
from .registration import (
    DEFAULT_METHOD,
    MissingDependencyError,
    Registration,
    _check_transform,
    _spacing,
    apply_transform,
    register,
)

__all__ = [
    "DeviationLabel",
    "WITHIN",
    "EXCESS",
    "MISSING",
    "NOT_COVERED",
    "Reference",
    "Agreement",
    "CompareResult",
    "load_reference",
    "compare",
]

MESH_SUFFIXES = (".stl", ".obj", ".off", ".glb", ".gltf")


class DeviationLabel(enum.IntEnum):
    """Per-point labels of a comparison (stored as ``uint8``)."""

    WITHIN = 0  #: covered and within tolerance
    EXCESS = 1  #: material beyond the reference surface (a burr, spatter): grind
    MISSING = 2  #: material missing under the reference surface (a pit, over-grinding)
    NOT_COVERED = 3  #: no reference surface near the point (or a dropout): not judged


WITHIN = DeviationLabel.WITHIN
EXCESS = DeviationLabel.EXCESS
MISSING = DeviationLabel.MISSING
NOT_COVERED = DeviationLabel.NOT_COVERED


@dataclass(frozen=True)
class Reference:
    """A reference surface as points with normals.

    Attributes
    ----------
    points : ndarray, shape (M, 3), float64
    normals : ndarray, shape (M, 3), float64
        Unit normals; NaN rows have no local plane and are not part of the surface.
    kind : str
        ``"points"`` (a golden sample's scan: normals estimated, oriented at comparison time
        towards the scan's sensor) or ``"mesh"`` (a CAD model's dense sampling: outward face
        normals).
    spacing : float
        Median nearest-neighbour distance of the points (the sampling distance for a mesh).
    """

    points: np.ndarray
    normals: np.ndarray
    kind: str
    spacing: float

    @property
    def oriented(self) -> bool:
        return self.kind == "mesh"


def _trimesh() -> Any:
    try:
        import trimesh  # noqa: PLC0415
    except ImportError:
        raise MissingDependencyError(
            'mesh references need trimesh: pip install "miem[compare]"') from None
    return trimesh


def _is_mesh_file(path: Path) -> bool:
    suffix = path.suffix.lower()
    if suffix in MESH_SUFFIXES:
        return True
    if suffix == ".ply":  # a PLY with faces is a mesh
        with open(path, "rb") as f:
            head = f.read(4096)
        end = head.find(b"end_header")
        for line in head[: end if end >= 0 else len(head)].splitlines():
            parts = line.split()
            if len(parts) == 3 and parts[0] == b"element" and parts[1] == b"face":
                return parts[2] != b"0"
    return False


def _from_mesh(mesh: Any, spacing: Optional[float], max_points: int, seed: int) -> Reference:
    trimesh = _trimesh()
    if isinstance(mesh, trimesh.Scene):
        mesh = mesh.dump(concatenate=True)
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError("reference: the mesh has no triangles")
    area = float(mesh.area)
    if not area > 0.0:
        raise ValueError("reference: degenerate mesh (zero area)")
    s = _real("spacing", spacing) if spacing is not None else np.sqrt(area / max_points)
    if not s > 0:
        raise ValueError(f"spacing: expected a length > 0, got {s}")
    count = int(np.ceil(area / (s * s)))
    if count > max_points:
        count, s = max_points, float(np.sqrt(area / max_points))
    pts, face = trimesh.sample.sample_surface(mesh, count, seed=seed)
    normals = np.asarray(mesh.face_normals, dtype=np.float64)[face]
    return Reference(points=np.ascontiguousarray(pts, dtype=np.float64),
                     normals=np.ascontiguousarray(normals), kind="mesh", spacing=float(s))


def load_reference(
    source: Any,
    *,
    normals: Optional[Any] = None,
    normal_radius: Optional[float] = None,
    spacing: Optional[float] = None,
    max_points: int = 2_000_000,
    seed: int = 0,
    num_threads: Optional[int] = None,
) -> Reference:
    """A :class:`Reference` from points, a mesh, or a file.

    Parameters
    ----------
    source : array_like (M, 3) or (H, W, 3), trimesh.Trimesh, str or Path
        A golden sample's points; a mesh; or a file: STL / OBJ / OFF / GLB, or a PLY with faces,
        is a mesh (needs trimesh), anything else a scan read by :func:`miem.io.read`.
    normals : array_like (M, 3), optional
        Outward normals of the points (then used as given, not re-oriented).
    normal_radius : float, optional
        Radius of the normal estimation for points; default 3 x the point spacing.
    spacing : float, optional
        Sampling distance for a mesh (ignored for points); default ``sqrt(area / max_points)``
        (:func:`compare` passes half the scan's point spacing).
    max_points : int
        Most sample points drawn from a mesh.
    seed : int
        Seed of the mesh sampling.
    """
    threads = _threads(num_threads)
    max_points = _int("max_points", max_points, 100)
    seed = _int("seed", seed, 0)
    if isinstance(source, Reference):
        return source
    if isinstance(source, (str, Path)):
        path = Path(source)
        if not path.is_file():
            raise ValueError(f"reference: no such file: {path}")
        if _is_mesh_file(path):
            try:
                mesh = _trimesh().load(str(path), force="mesh")
            except (ValueError, OSError, KeyError, IndexError) as exc:
                raise ValueError(f"reference: {path}: cannot read the mesh ({exc})") from None
            return _from_mesh(mesh, spacing, max_points, seed)
        from . import io  # noqa: PLC0415

        source = io.read(path).points
    mod = type(source).__module__ or ""
    if mod.startswith("trimesh"):
        return _from_mesh(source, spacing, max_points, seed)
    if mod.startswith("open3d"):
        from .io import from_open3d  # noqa: PLC0415

        source = from_open3d(source)
    arr = _as_float_array(source, "reference")
    if arr.ndim == 3 and arr.shape[2] == 3:
        arr = arr.reshape(-1, 3)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"reference: expected shape (M, 3) or (H, W, 3), got {arr.shape}")
    pts = np.ascontiguousarray(arr[np.isfinite(arr).all(axis=1)], dtype=np.float64)
    if len(pts) < 10:
        raise ValueError(f"reference: at least 10 finite points are needed, got {len(pts)}")
    s = _spacing(pts)
    if normals is not None:
        n = np.array(_as_float_array(normals, "normals"), dtype=np.float64)
        if n.shape != arr.shape:
            raise ValueError(f"normals: expected shape {arr.shape}, got {n.shape}")
        n = n[np.isfinite(arr).all(axis=1)]
        length = np.linalg.norm(n, axis=1)
        bad = ~(length > 0)
        n = n / np.where(bad, 1.0, length)[:, None]
        n[bad] = np.nan
        return Reference(points=pts, normals=np.ascontiguousarray(n), kind="mesh", spacing=s)
    r = 3.0 * s if normal_radius is None else _real("normal_radius", normal_radius)
    if not r > 0:
        raise ValueError(f"normal_radius: expected a length > 0, got {r}")
    nrm, _, _, valid = _core.estimate_normals(pts, r, threads)
    if not valid.any():
        raise ValueError("reference: degenerate: no local plane could be fitted (the points are "
                         "collinear, coincide, or are too sparse for normal_radius="
                         f"{r:.4g})")
    return Reference(points=pts, normals=nrm, kind="points", spacing=s)


@dataclass(frozen=True)
class Agreement:
    """Defects seen by the comparison and by MIEM (:func:`miem.detect`) on the same scan.

    A comparison defect and a MIEM defect are the same when a point of one lies within ``link``
    of a point of the other.

    Attributes
    ----------
    both : tuple of (int, tuple of int)
        Comparison defect id and the ids of the MIEM defects matching it.
    compare_only : tuple of int
        Comparison defects no MIEM defect matches.
    miem_only : tuple of int
        MIEM defects on covered points that match no comparison defect.
    miem_not_covered : tuple of int
        MIEM defects whose points are all outside the reference's coverage (not judged).
    points : dict
        Point counts: ``both`` (ABNORMAL and EXCESS/MISSING), ``miem_only``, ``compare_only``.
    """

    both: tuple
    compare_only: tuple
    miem_only: tuple
    miem_not_covered: tuple
    points: dict

    def summary(self) -> str:
        return (f"{len(self.both)} defects seen by both, {len(self.compare_only)} by the "
                f"comparison only, {len(self.miem_only)} by MIEM only "
                f"({len(self.miem_not_covered)} MIEM defects not covered)")


@dataclass(frozen=True)
class CompareResult:
    """What :func:`compare` returns. Per-point arrays have the scan's shape without its last
    axis: ``(N,)`` for points, ``(H, W)`` for a grid.

    Attributes
    ----------
    deviation : ndarray, float64
        Signed distance from the reference surface along its outward normal (> 0 excess
        material, < 0 missing); NaN where not covered.
    distance : ndarray, float64
        Distance to the nearest reference point (NaN where none is within ``coverage``).
    covered : ndarray, bool
    labels : ndarray, uint8
        :class:`DeviationLabel` values.
    defects : list of Defect
        Excess (``kind="protrusion"``) and missing (``"pit"``) groups, largest ``|peak_height|``
        first; ``peak_height`` / ``mean_height`` are deviations, ``normal`` the reference's
        outward normal at the peak, ``centroid`` in the scan's frame.
    transform : ndarray, shape (4, 4)
        Scan frame to reference frame.
    registration : Registration or None
        None when ``register=False``.
    agreement : Agreement or None
    params : dict
        The values used: tolerance, dont_care, coverage, max_lateral, link, spacings.
    """

    deviation: np.ndarray
    distance: np.ndarray
    covered: np.ndarray
    labels: np.ndarray
    defects: list
    transform: np.ndarray
    registration: Optional[Registration]
    agreement: Optional[Agreement]
    params: dict = field(default_factory=dict)

    def counts(self) -> dict:
        """Points per label name."""
        c = np.bincount(self.labels.ravel(), minlength=4)
        return {lab.name: int(c[lab]) for lab in DeviationLabel}


def _agreement(points: np.ndarray, labels: np.ndarray, defects: list, detection: Any,
               link: float) -> Agreement:
    det_labels = np.asarray(detection.labels).ravel()
    if det_labels.shape != labels.shape:
        raise ValueError(f"detection: its labels have {det_labels.size} points, the scan "
                         f"{labels.size}")
    owner = np.full(len(points), -1, dtype=np.int64)
    for d in defects:
        owner[d.indices] = d.id
    flagged = np.flatnonzero(owner >= 0)
    grid = None
    if flagged.size:
        grid = _core.NeighborGrid(np.ascontiguousarray(points[flagged]), link, 0)
    matches: dict = {d.id: set() for d in defects}
    miem_only, not_covered = [], []
    for m in detection.defects:
        idx = np.asarray(m.indices)
        if np.all(labels[idx] == NOT_COVERED):
            not_covered.append(int(m.id))
            continue
        hit = set()
        if grid is not None:
            for i in idx:
                p = points[i]
                if np.isfinite(p).all():
                    hit.update(owner[flagged[grid.query_point(p[0], p[1], p[2], link)]].tolist())
        for c in hit:
            matches[c].add(int(m.id))
        if not hit:
            miem_only.append(int(m.id))
    abnormal = det_labels == 1
    out = (labels == EXCESS) | (labels == MISSING)
    return Agreement(
        both=tuple((c, tuple(sorted(ms))) for c, ms in sorted(matches.items()) if ms),
        compare_only=tuple(c for c, ms in sorted(matches.items()) if not ms),
        miem_only=tuple(miem_only), miem_not_covered=tuple(not_covered),
        points={"both": int(np.sum(abnormal & out)),
                "miem_only": int(np.sum(abnormal & ~out & (labels != NOT_COVERED))),
                "compare_only": int(np.sum(out & ~abnormal))})


def _positive(name: str, value: Any) -> float:
    v = _real(name, value)
    if not v > 0:
        raise ValueError(f"{name}: expected a length > 0, got {v}")
    return v


def compare(
    scan: Any,
    reference: Any,
    *,
    tolerance: float = 0.2,
    dont_care: float = 0.0,
    init_transform: Optional[Any] = None,
    register_scan: bool = True,
    library: str = "auto",
    method: str = DEFAULT_METHOD,
    coverage: Optional[float] = None,
    max_lateral: Optional[float] = None,
    link: Optional[float] = None,
    scan_up: Any = (0.0, 0.0, 1.0),
    detection: Union[str, None, DetectResult] = "auto",
    seed: int = 0,
    num_threads: Optional[int] = None,
) -> CompareResult:
    """Register a scan onto a reference and measure its deviation from it.

    Parameters
    ----------
    scan : array_like (N, 3) or (H, W, 3)
        The scan (NaN rows are dropouts: not covered).
    reference : array_like, trimesh.Trimesh, str, Path or Reference
        Golden sample points, a mesh (sampled at half the scan's point spacing), or a file (see
        :func:`load_reference`).
    tolerance : float
        ``|deviation| > tolerance`` is out of tolerance (scan units; 0.2 mm in deburring).
    dont_care : float
        Don't-care band above the tolerance: a group of out-of-tolerance points is a defect only
        when its peak ``|deviation|`` exceeds ``tolerance + dont_care``; otherwise its points are
        WITHIN (marginal noise is not ground).
    init_transform : array_like (4, 4), optional
        Rough pose of the scan in the reference's frame; default found automatically.
    register_scan : bool
        False: use ``init_transform`` (default identity) as is, no ICP.
    library, method : str
        Fine ICP library and variant (:func:`miem.register`).
    coverage : float, optional
        A scan point farther than this from every reference point is not covered; default
        ``max(10 x tolerance, 10 x reference spacing)`` (taller defects than this are not seen).
    max_lateral : float, optional
        A scan point whose offset from its nearest reference point along the surface exceeds
        this lies beyond the reference's edge: not covered. Default 3 x reference spacing.
    link : float, optional
        Out-of-tolerance points closer than this are one defect; default 3 x scan spacing.
    scan_up : array_like (3,)
        Direction towards the scanner in the scan's frame: a golden sample's estimated normals
        are oriented to face it (outwards). Ignored for meshes and given normals.
    detection : "auto", None or DetectResult
        MIEM's labels for the agreement: ``"auto"`` runs :func:`miem.detect` on the scan with its
        defaults; None skips the agreement.
    """
    from ._api import detect  # noqa: PLC0415

    arr = _as_float_array(scan, "scan")
    if arr.ndim == 3 and arr.shape[2] == 3:
        shape = arr.shape[:2]
    elif arr.ndim == 2 and arr.shape[1] == 3:
        shape = arr.shape[:1]
    else:
        raise ValueError(f"scan: expected shape (N, 3) or (H, W, 3), got {arr.shape}")
    pts = arr.reshape(-1, 3)
    tol = _positive("tolerance", tolerance)
    band = _real("dont_care", dont_care)
    if band < 0:
        raise ValueError(f"dont_care: expected a length >= 0, got {band}")
    threads = _threads(num_threads)
    up = np.array(scan_up, dtype=np.float64).ravel() if scan_up is not None else None
    if up is None or up.shape != (3,) or not np.isfinite(up).all() or not np.linalg.norm(up) > 0:
        raise ValueError(f"scan_up: expected a non-zero direction (3,), got {scan_up!r}")
    up = up / np.linalg.norm(up)
    if not (detection is None or isinstance(detection, DetectResult) or detection == "auto"):
        raise ValueError(f"detection: expected 'auto', None or a DetectResult, got {detection!r}")
    if not isinstance(register_scan, (bool, np.bool_)):
        raise ValueError(f"register_scan: expected True or False, got {register_scan!r}")
    finite = np.isfinite(pts).all(axis=1)
    if int(finite.sum()) < 10:
        raise ValueError(f"scan: at least 10 finite points are needed, got {int(finite.sum())}")
    s_spacing = _spacing(np.ascontiguousarray(pts[finite], dtype=np.float64))
    # A mesh is sampled at half the scan's spacing (at most max_points samples).
    ref = load_reference(reference, spacing=0.5 * s_spacing, num_threads=num_threads, seed=seed)
    cov = max(10 * tol, 10 * ref.spacing) if coverage is None else _positive("coverage", coverage)
    lat = 3.0 * ref.spacing if max_lateral is None else _positive("max_lateral", max_lateral)
    lnk = 3.0 * s_spacing if link is None else _positive("link", link)

    if register_scan:
        fit_surface = _core.ReferenceSurface(ref.points, ref.normals, 2.0 * ref.spacing, threads)
        reg = register(pts[finite], ref.points, init_transform=init_transform, library=library,
                       method=method, seed=seed, num_threads=num_threads, _surface=fit_surface)
        transform = reg.transform
    else:
        reg = None
        transform = (np.eye(4) if init_transform is None
                     else _check_transform(init_transform, "init_transform"))
    normals = ref.normals
    if not ref.oriented:
        flip = normals @ (transform[:3, :3] @ up) < 0
        normals = np.where(flip[:, None], -normals, normals)
    # Cells of cov / 8 (at least 2 spacings, at most 16: a huge coverage must not make one cell
    # hold the whole reference).
    cell = min(max(2.0 * ref.spacing, cov / 8.0), 16.0 * ref.spacing)
    surface = _core.ReferenceSurface(ref.points, np.ascontiguousarray(normals), cell, threads)
    aligned = apply_transform(transform, pts)
    dev, dist, nearest, covered = surface.deviation(aligned, cov, lat, threads)
    # Reference normals at each point's nearest reference point, in the scan's frame.
    at = np.full((len(pts), 3), np.nan)
    has = nearest >= 0
    at[has] = normals[nearest[has]] @ transform[:3, :3]
    labels, raw = _core.label_deviation(np.ascontiguousarray(pts, dtype=np.float64), dev,
                                        covered, at, tol, band, lnk)
    width = shape[1] if len(shape) == 2 else None
    defects = [
        Defect(id=int(i), indices=idx,
               cells=(np.stack(np.divmod(idx, width), axis=1) if width else idx[:, None]),
               count=int(idx.size), centroid=c, normal=n, peak_height=float(pk),
               mean_height=float(mh), extent=float(ex), kind=str(kind))
        for (i, idx, c, n, pk, mh, ex, kind) in raw
    ]
    agreement = None
    if detection is not None:
        det = detect(arr) if isinstance(detection, str) else detection
        agreement = _agreement(np.ascontiguousarray(pts, dtype=np.float64), labels, defects, det,
                               lnk)
    params = dict(tolerance=tol, dont_care=band, coverage=cov, max_lateral=lat, link=lnk,
                  scan_spacing=s_spacing, reference_spacing=ref.spacing,
                  reference_kind=ref.kind, reference_points=int(len(ref.points)))
    return CompareResult(
        deviation=dev.reshape(shape), distance=dist.reshape(shape),
        covered=covered.reshape(shape), labels=labels.reshape(shape), defects=defects,
        transform=transform, registration=reg, agreement=agreement, params=params)
