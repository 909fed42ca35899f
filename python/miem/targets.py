"""Grinding targets in the robot's base frame: from a detection to tool poses and a short path.

The geometry (selection, merging, orientation, ordering) runs in the C++ core
(``miem::plan_targets``); this module checks arguments, reads calibration files and returns typed
results. The rules are in ``docs/SPEC.md`` ("Grinding targets"); :mod:`miem.robot_formats` writes
the plan for a robot controller.

>>> res = miem.detect(grid, preset="recommended")
>>> plan = miem.plan_targets(res, grid, "calib.json", tool=miem.Tool(radius=3.0))
>>> plan.targets[0].position, plan.targets[0].quaternion      # base frame, (w, x, y, z)
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Sequence, Tuple, Union

import numpy as np

from . import _core
from ._api import DetectResult, _as_float_array, _int, _real

__all__ = ["Tool", "Target", "TargetPlan", "plan_targets", "read_transform", "KINDS",
           "UNIT_SCALE"]

#: Defect kinds that can be targeted.
KINDS = ("protrusion", "pit", "isolated")

#: Length units and their size in metres (robot files convert with these).
UNIT_SCALE = {"m": 1.0, "mm": 1e-3, "um": 1e-6, "cm": 1e-2, "in": 0.0254}

_DEFAULT_CLEARANCE_MM = 20.0

PathLike = Union[str, Path]


@dataclass(frozen=True)
class Tool:
    """The grinding tool, in the scan's units.

    Attributes
    ----------
    radius : float
        Defects whose anchors are closer than this are merged into one target (0: no merging).
    standoff : float
        The tool pose sits this far from the surface point along the normal (e.g. a contact
        offset; 0: on the point).
    approach : float, optional
        The approach point is this far above the tool pose, along the normal (default: 20 mm
        in the plan's ``units``).
    retract : float, optional
        The retract point is this far above the tool pose, along the normal (default: 20 mm
        in the plan's ``units``).
    """

    radius: float = 0.0
    standoff: float = 0.0
    approach: Optional[float] = None
    retract: Optional[float] = None


@dataclass(frozen=True)
class Target:
    """One grinding target. Vectors are in the base frame, lengths in the scan's units.

    Attributes
    ----------
    index : int
        Position in the path (0 first).
    point : ndarray (3,)
        The anchor on the defect: its peak point or its centroid.
    point_scan : ndarray (3,)
        The anchor in scan coordinates (for plots on the height map).
    normal : ndarray (3,)
        Unit local surface normal, oriented toward the scanner.
    approach_axis : ndarray (3,)
        ``-normal``: the tool z axis, pointing into the surface.
    rotation : ndarray (3, 3)
        Tool orientation: columns are the tool x, y, z axes in the base frame.
    position : ndarray (3,)
        Tool pose origin: ``point + standoff * normal``.
    approach_point, retract_point : ndarray (3,)
        ``position + approach * normal`` and ``position + retract * normal``.
    quaternion : ndarray (4,)
        Unit quaternion ``(w, x, y, z)`` of ``rotation`` with ``w >= 0`` (ABB order).
    abc : ndarray (3,)
        KUKA angles A, B, C in degrees: ``rotation = Rz(A) Ry(B) Rx(C)``.
    depth : float
        Material to remove: the peak height of the deepest merged defect (signed; NaN if none).
    area : float
        Footprint of the member points in their tangent planes (units squared).
    volume : float
        Volume above the local surface (below it for a pit), units cubed.
    count : int
        Member points.
    defect_ids : tuple of int
        Ids of the merged defects (``result.defects[i].id``), ascending.
    peak_index : int
        Flat index (``row * W + col``) of the deepest defect's peak point.
    """

    index: int
    point: np.ndarray
    point_scan: np.ndarray
    normal: np.ndarray
    approach_axis: np.ndarray
    rotation: np.ndarray
    position: np.ndarray
    approach_point: np.ndarray
    retract_point: np.ndarray
    quaternion: np.ndarray
    abc: np.ndarray
    depth: float
    area: float
    volume: float
    count: int
    defect_ids: Tuple[int, ...]
    peak_index: int


@dataclass(frozen=True)
class TargetPlan:
    """What :func:`plan_targets` returns: targets in path order, and why defects were left out.

    Attributes
    ----------
    targets : list of Target
        In path order.
    path_length : float
        Length of the path through the anchors, from ``start`` when given.
    start : ndarray (3,) or None
        Start of the path in the base frame.
    defects_in : int
        Defects offered.
    defects_used : int
        Defects that ended in a target.
    rejected : dict
        Defects left out, per rule: ``kind``, ``height``, ``size``, ``roi``, ``edge``.
    units : str
        Length unit of the scan (and of every length here).
    frame : str
        Name of the base frame.
    params : dict
        The parameters used.
    """

    targets: list
    path_length: float
    start: Optional[np.ndarray]
    defects_in: int
    defects_used: int
    rejected: dict
    units: str = "mm"
    frame: str = "base"
    params: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.targets)

    @property
    def positions(self) -> np.ndarray:
        """Tool pose origins, shape (M, 3)."""
        return np.array([t.position for t in self.targets], dtype=np.float64).reshape(-1, 3)


# ---------------------------------------------------------------------------------------------
# transforms


def _matrix_from_doc(doc: Any, name: str) -> np.ndarray:
    if isinstance(doc, dict):
        keys = [k for k in ("T_base_sensor", "matrix", "transform") if k in doc]
        if not keys:
            raise ValueError(f"{name}: expected a key 'T_base_sensor' (or 'matrix') holding a "
                             f"4x4 matrix, found keys {sorted(doc)}")
        doc = doc[keys[0]]
    try:
        arr = np.asarray(doc, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: the matrix must be rows of numbers") from None
    return arr


def read_transform(path: PathLike) -> np.ndarray:
    """Read ``T_base_sensor`` from a small calibration file.

    JSON (``.json``) or YAML (``.yaml``/``.yml``, needs PyYAML): either a bare 4x4 list of rows,
    or a mapping with key ``T_base_sensor`` (or ``matrix``) holding one 4x4 matrix or a list of
    them (one per profile). The matrix maps scan coordinates to the base frame.

    Returns
    -------
    ndarray, shape (4, 4) or (K, 4, 4), float64
        Checked: finite and rigid.

    Raises
    ------
    ValueError
        Unreadable file, unknown layout, wrong shape, or not a rigid transform.
    """
    p = Path(path)
    name = f"T_base_sensor ({p})"
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{name}: cannot read the calibration file: {exc}") from None
    if p.suffix.lower() in (".yaml", ".yml"):
        try:
            import yaml
        except ImportError:  # pragma: no cover - PyYAML is in the io extra
            raise ValueError(f"{name}: reading YAML needs PyYAML (pip install pyyaml)") from None
        try:
            doc = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise ValueError(f"{name}: not valid YAML: {exc}") from None
    else:
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{name}: not valid JSON: {exc}") from None
    arr = _matrix_from_doc(doc, name)
    return _check_transforms(arr, None, name)


def _check_transforms(T: Any, rows: Optional[int], name: str = "T_base_sensor") -> np.ndarray:
    try:
        arr = np.array(T, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a 4x4 matrix of numbers") from None
    per_profile = f" or ({rows}, 4, 4) (one per profile)" if rows is not None else ""
    if not (arr.shape == (4, 4) or (arr.ndim == 3 and arr.shape[1:] == (4, 4))):
        raise ValueError(f"{name}: expected shape (4, 4){per_profile}, got {arr.shape}")
    stack = np.ascontiguousarray(arr.reshape(-1, 4, 4))
    if rows is not None and arr.ndim == 3 and stack.shape[0] not in (1, rows):
        raise ValueError(f"{name}: expected shape (4, 4) or ({rows}, 4, 4) (one per profile), "
                         f"got {arr.shape}")
    msg = _core.check_transforms(stack, stack.shape[0] if rows is None else rows)
    if msg is not None:
        raise ValueError(msg.replace("T_base_sensor", name, 1))
    return arr


# ---------------------------------------------------------------------------------------------
# planning


def _vec3(value: Any, name: str) -> np.ndarray:
    arr = _as_float_array(value, name).astype(np.float64).reshape(-1)
    if arr.shape != (3,) or not np.isfinite(arr).all():
        raise ValueError(f"{name}: expected 3 finite numbers, got {value!r}")
    return arr


def _start(value: Any) -> Optional[np.ndarray]:
    if value is None:
        return None
    arr = _as_float_array(value, "start").astype(np.float64)
    if arr.shape == (4, 4):
        arr = arr[:3, 3]
    if arr.shape != (3,) or not np.isfinite(arr).all():
        raise ValueError(f"start: expected a point (3,) or a pose (4, 4) in the base frame, got "
                         f"shape {arr.shape}")
    return arr


def _nonneg(name: str, value: Any) -> float:
    v = _real(name, value)
    if v < 0:
        raise ValueError(f"{name}: expected a length >= 0, got {v}")
    return v


def plan_targets(
    result: DetectResult,
    scan: np.ndarray,
    T_base_sensor: Union[None, np.ndarray, PathLike] = None,
    *,
    tool: Optional[Tool] = None,
    at: str = "peak",
    kinds: Sequence[str] = ("protrusion",),
    min_height: float = 0.0,
    min_area: float = 0.0,
    min_count: int = 1,
    roi: Optional[np.ndarray] = None,
    edge_clearance: float = 0.0,
    x_axis: Union[str, Sequence[float]] = "scan",
    toward_sensor: Sequence[float] = (0.0, 0.0, 1.0),
    start: Optional[np.ndarray] = None,
    order: bool = True,
    units: str = "mm",
    frame: str = "base",
) -> TargetPlan:
    """Turn detected defects into grinding targets in the robot's base frame.

    Defects are selected (kind, height, size, region of interest, distance from feature edges),
    defects closer than ``tool.radius`` are merged into one target, and the targets are ordered
    into a short path (nearest neighbour from ``start``, then 2-opt). Each target gets a full
    tool pose: z axis = ``-normal`` (the approach axis, into the surface), x axis along the scan
    direction (or ``x_axis``) in the tangent plane, ``y = z x x``. See docs/SPEC.md.

    Parameters
    ----------
    result : DetectResult
        From :func:`miem.detect` (or :func:`miem.detect_points`) on ``scan``.
    scan : array_like, shape (H, W, 3) or (N, 3)
        The scan the result came from, in scan (sensor) coordinates.
    T_base_sensor : array_like (4, 4) or (H, 4, 4), str or Path, optional
        Rigid transform base <- scan (``p_base = R p + t``); one per profile for a robot-swept
        scanner (row ``r`` of the grid uses ``T_base_sensor[r]``); or a calibration file (see
        :func:`read_transform`). Default: the identity (targets in scan coordinates).
    tool : Tool, optional
        Radius (merging), stand-off, approach and retract distances. Default ``Tool()``.
    at : {"peak", "centroid"}
        Where a target sits on its defect: the point of largest height, or the mean point.
    kinds : sequence of {"protrusion", "pit", "isolated"}
        Defect kinds to target. Default: protrusions only (pits are not ground; isolated
        returns are stray points or dust).
    min_height : float
        Keep defects with ``|peak_height| >= min_height``.
    min_area, min_count : float, int
        Keep defects with at least this footprint area (units squared) and this many points.
    roi : array_like, optional
        Region of interest: a boolean mask of the scan's point shape ((H, W), or (N,)), or a
        polygon (K, 2), K >= 3, in the scan's x-y plane. A defect is inside when its peak point
        is.
    edge_clearance : float
        Drop targets whose anchor is closer than this to an EDGE point (a designed feature
        edge). EDGE points themselves are never targeted.
    x_axis : "scan" or array_like (3,)
        Tool x reference: ``"scan"`` is the scan direction (the scan frame's y axis, along which
        profiles follow each other, in the base frame); or a base-frame vector.
    toward_sensor : array_like (3,)
        Direction from the surface toward the scanner in scan coordinates (default +z): normals
        are oriented to have a positive component along it.
    start : array_like (3,) or (4, 4), optional
        Start of the path in the base frame (a point or a pose). Default: the deepest target.
    order : bool
        Order into a short path; False keeps the targets deepest first.
    units : str
        The scan's length unit, written into the robot files (which convert to mm or m with
        :data:`UNIT_SCALE`); sets the 20 mm default approach and retract distances.
    frame : str
        Name of the base frame, written into the robot files.

    Returns
    -------
    TargetPlan

    Raises
    ------
    ValueError
        A bad argument (named in the message), or a transform that is not rigid or not finite.
    """
    if not isinstance(result, DetectResult):
        raise ValueError(f"result: expected a miem.DetectResult, got {type(result).__name__}")
    if tool is None:
        tool = Tool()
    if not isinstance(tool, Tool):
        raise ValueError(f"tool: expected a miem.Tool, got {type(tool).__name__}")
    pts = _as_float_array(scan, "scan")
    labels = np.asarray(result.labels)
    if pts.shape[:-1] != labels.shape or pts.shape[-1:] != (3,) or pts.ndim not in (2, 3):
        raise ValueError(f"scan: expected the scan the result came from, shape "
                         f"{labels.shape + (3,)}, got {pts.shape}")
    cloud = pts.ndim == 2
    grid = pts[None] if cloud else pts
    rows = grid.shape[0]
    if T_base_sensor is None:
        T = np.eye(4)
    elif isinstance(T_base_sensor, (str, Path)):
        T = read_transform(T_base_sensor)
    else:
        T = T_base_sensor
    if cloud and np.ndim(T) == 3 and len(T) != 1:
        raise ValueError("T_base_sensor: one transform per profile needs an organized scan "
                         "(H, W, 3); a cloud takes one (4, 4) transform")
    T = _check_transforms(T, rows)
    stack = np.ascontiguousarray(T.reshape(-1, 4, 4), dtype=np.float64)

    p = _core.TargetParams()
    if at not in ("peak", "centroid"):
        raise ValueError(f"at: expected 'peak' or 'centroid', got {at!r}")
    p.anchor = _core.TargetAnchor.peak if at == "peak" else _core.TargetAnchor.centroid
    if isinstance(kinds, str):
        kinds = (kinds,)
    kinds = tuple(kinds)
    bad = [k for k in kinds if k not in KINDS]
    if bad or not kinds:
        raise ValueError(f"kinds: expected one or more of {KINDS}, got {kinds!r}")
    p.protrusions, p.pits, p.isolated = ("protrusion" in kinds, "pit" in kinds,
                                         "isolated" in kinds)
    p.min_height = _nonneg("min_height", min_height)
    p.min_area = _nonneg("min_area", min_area)
    p.min_count = _int("min_count", min_count, 1)
    p.tool_radius = _nonneg("tool.radius", tool.radius)
    p.standoff = _real("tool.standoff", tool.standoff)
    for name in ("approach", "retract"):
        value = getattr(tool, name)
        if value is None:
            if units not in UNIT_SCALE:
                raise ValueError(f"tool.{name}: give it in the scan's units; the 20 mm default "
                                 f"needs units in {sorted(UNIT_SCALE)}, got {units!r}")
            value = _DEFAULT_CLEARANCE_MM * 1e-3 / UNIT_SCALE[units]
        setattr(p, name, _nonneg(f"tool.{name}", value))
    p.edge_clearance = _nonneg("edge_clearance", edge_clearance)
    toward = _vec3(toward_sensor, "toward_sensor")
    if not np.any(toward):
        raise ValueError("toward_sensor: must not be the zero vector")
    p.toward_sensor = toward
    if isinstance(x_axis, str):
        if x_axis != "scan":
            raise ValueError(f"x_axis: expected 'scan' or a vector (3,), got {x_axis!r}")
    else:
        ref = _vec3(x_axis, "x_axis")
        if not np.any(ref):
            raise ValueError("x_axis: must not be the zero vector")
        p.x_reference = ref
    start_v = _start(start)
    if start_v is not None:
        p.start = start_v
    if not isinstance(order, (bool, np.bool_)):
        raise ValueError(f"order: expected True or False, got {order!r}")
    p.order = bool(order)
    if cloud:
        spacing = result.params.get("spacing")
        if spacing is None or not np.isfinite(spacing) or spacing <= 0:
            raise ValueError("result: a cloud result needs params['spacing'] (from "
                             "miem.detect_points) for the defect areas")
        p.point_area = float(spacing) ** 2

    roi_mask = None
    if roi is not None:
        r = np.asarray(roi)
        if r.dtype == bool and r.shape == labels.shape:
            roi_mask = np.ascontiguousarray(r.reshape(-1), dtype=np.uint8)
        elif r.ndim == 2 and r.shape[1] == 2 and r.shape[0] >= 3 and r.dtype.kind in "iuf":
            poly = r.astype(np.float64)
            if not np.isfinite(poly).all():
                raise ValueError("roi: polygon vertices must be finite")
            p.roi_polygon = [v for v in poly]
        else:
            raise ValueError(f"roi: expected a boolean mask of shape {labels.shape} or a "
                             f"polygon (K, 2) with K >= 3, got {r.dtype} {r.shape}")
    defects = [(int(d.id), np.ascontiguousarray(d.indices, dtype=np.int64),
                np.asarray(d.normal, dtype=np.float64), float(d.peak_height), str(d.kind))
               for d in result.defects]
    lab = np.ascontiguousarray(labels.reshape(-1), dtype=np.uint8)
    height = np.ascontiguousarray(np.asarray(result.height).reshape(-1), dtype=np.float64)
    plan = _core.plan_targets(grid, lab, height, defects, stack, p, roi_mask)

    a = plan.arrays()
    targets = [
        Target(
            index=k, point=a["point"][k], point_scan=a["point_scan"][k], normal=a["normal"][k],
            approach_axis=-a["normal"][k], rotation=a["rotation"][k],
            position=a["position"][k], approach_point=a["approach_point"][k],
            retract_point=a["retract_point"][k], quaternion=a["quaternion"][k],
            abc=a["abc_deg"][k], depth=float(a["depth"][k]), area=float(a["area"][k]),
            volume=float(a["volume"][k]), count=int(a["count"][k]),
            defect_ids=tuple(int(i) for i in a["defect_ids"][k]),
            peak_index=int(a["peak_index"][k]),
        )
        for k in range(len(a["depth"]))
    ]
    params = dict(
        at=at, kinds=kinds, min_height=p.min_height, min_area=p.min_area,
        min_count=p.min_count, roi=None if roi is None else ("mask" if roi_mask is not None
                                                             else "polygon"),
        edge_clearance=p.edge_clearance, x_axis=x_axis if isinstance(x_axis, str)
        else [float(v) for v in p.x_reference], toward_sensor=[float(v) for v in toward],
        order=p.order, tool=tool, per_profile=stack.shape[0] > 1,
    )
    return TargetPlan(
        targets=targets, path_length=float(plan.path_length), start=start_v,
        defects_in=int(plan.defects_in), defects_used=int(plan.defects_used),
        rejected=dict(plan.rejected), units=str(units), frame=str(frame), params=params,
    )

