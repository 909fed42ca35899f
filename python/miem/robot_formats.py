"""Writers of grinding plans in the formats robot cells consume, and parsers for them.

- JSON and CSV: every target field; units, frame and angle conventions named in the header.
- ROS ``geometry_msgs/PoseArray`` as a message dict (YAML or JSON): metres, quaternion
  ``(x, y, z, w)`` fields.
- ABB RAPID: a module of ``robtarget`` constants ``[[x,y,z],[q1,q2,q3,q4],[cf1,cf4,cf6,cfx],
  [extax]]`` (mm, quaternion w first) and a procedure of ``MoveL`` approach / target / retract.
- KUKA KRL: a ``.src`` of ``LIN`` moves and a ``.dat`` of ``E6POS`` points ``X,Y,Z,A,B,C``
  (mm, degrees; ``A, B, C`` = rotations about Z, Y, X).

The parsers read back what the writers write (for round-trip tests and for checking a file
before it goes to a controller); they are not general RAPID or KRL parsers.
"""

from __future__ import annotations

import csv
import io
import json
import math
import re
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple, Union

import numpy as np

from .targets import UNIT_SCALE, TargetPlan

__all__ = [
    "FORMATS",
    "UNIT_SCALE",
    "ids_text",
    "to_json",
    "to_csv",
    "to_pose_array",
    "to_rapid",
    "to_krl",
    "write",
    "parse_csv",
    "parse_rapid",
    "parse_krl",
]

#: Output formats of :func:`write` and the file suffixes they use.
FORMATS = {"json": (".json",), "csv": (".csv",), "ros": (".yaml",), "ros-json": (".json",),
           "rapid": (".mod",), "krl": (".src", ".dat")}


PathLike = Union[str, Path]
_CSV_COLUMNS = ["index", "x", "y", "z", "qw", "qx", "qy", "qz", "a", "b", "c", "nx", "ny", "nz",
                "approach_x", "approach_y", "approach_z", "retract_x", "retract_y", "retract_z",
                "depth", "area", "volume", "count", "defect_ids"]


def _scale_to(plan: TargetPlan, unit: str) -> float:
    """Factor from the plan's units to `unit`."""
    if plan.units not in UNIT_SCALE:
        raise ValueError(f"units: the plan's unit {plan.units!r} is not one of "
                         f"{sorted(UNIT_SCALE)}; {unit} output needs a known unit")
    return UNIT_SCALE[plan.units] / UNIT_SCALE[unit]


def ids_text(ids: Tuple[int, ...], limit: int = 8) -> str:
    """Defect ids for a comment or a table cell: the first `limit`, then how many in all."""
    head = " ".join(str(i) for i in ids[:limit])
    return head if len(ids) <= limit else f"{head} ... ({len(ids)} defects)"


def _num(v: float) -> Optional[float]:
    return float(v) if math.isfinite(v) else None


def _vec(v: np.ndarray, scale: float = 1.0) -> List[float]:
    return [float(x) * scale for x in v]


# ---------------------------------------------------------------------------------------------
# JSON / CSV


def to_json(plan: TargetPlan) -> Dict[str, Any]:
    """The plan as a JSON-ready dict (lengths in the plan's units, angles in degrees)."""
    return {
        "format": "miem-targets/1",
        "units": plan.units,
        "frame": plan.frame,
        "quaternion_order": "w, x, y, z",
        "abc": "KUKA A, B, C degrees: R = Rz(A) Ry(B) Rx(C)",
        "tool_axes": "rotation columns = tool x, y, z in the frame; z = approach axis = -normal",
        "path_length": plan.path_length,
        "start": None if plan.start is None else _vec(plan.start),
        "defects_in": plan.defects_in,
        "defects_used": plan.defects_used,
        "rejected": dict(plan.rejected),
        "targets": [
            {
                "index": t.index, "point": _vec(t.point), "point_scan": _vec(t.point_scan),
                "position": _vec(t.position), "normal": _vec(t.normal),
                "approach_axis": _vec(t.approach_axis),
                "rotation": [_vec(r) for r in t.rotation], "quaternion": _vec(t.quaternion),
                "abc": _vec(t.abc), "approach_point": _vec(t.approach_point),
                "retract_point": _vec(t.retract_point), "depth": _num(t.depth),
                "area": t.area, "volume": t.volume, "count": t.count,
                "defect_ids": list(t.defect_ids), "peak_index": t.peak_index,
            }
            for t in plan.targets
        ],
    }


def to_csv(plan: TargetPlan) -> str:
    """One row per target; ``#`` comment lines name the units, frame and conventions."""
    buf = io.StringIO()
    buf.write(f"# miem grinding targets: {len(plan.targets)} targets, path order\n")
    buf.write(f"# units: {plan.units}; frame: {plan.frame}; quaternion: w x y z; "
              "a b c: KUKA degrees, R = Rz(a) Ry(b) Rx(c); n: surface normal (approach = -n)\n")
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(_CSV_COLUMNS)
    for t in plan.targets:
        w.writerow([t.index, *(repr(float(v)) for v in t.position),
                    *(repr(float(v)) for v in t.quaternion), *(repr(float(v)) for v in t.abc),
                    *(repr(float(v)) for v in t.normal),
                    *(repr(float(v)) for v in t.approach_point),
                    *(repr(float(v)) for v in t.retract_point),
                    repr(float(t.depth)), repr(float(t.area)), repr(float(t.volume)), t.count,
                    " ".join(str(i) for i in t.defect_ids)])
    return buf.getvalue()


def parse_csv(text: str) -> Tuple[Dict[str, str], List[Dict[str, Any]]]:
    """Header (units, frame) and rows of a CSV written by :func:`to_csv`."""
    header: Dict[str, str] = {}
    body = []
    for line in text.splitlines():
        if line.startswith("#"):
            for part in line[1:].split(";"):
                if ":" in part:
                    k, v = part.split(":", 1)
                    header.setdefault(k.strip(), v.strip())
        elif line.strip():
            body.append(line)
    rows = []
    for rec in csv.DictReader(body):
        row: Dict[str, Any] = {}
        for k, v in rec.items():
            if k == "defect_ids":
                row[k] = tuple(int(i) for i in v.split())
            elif k in ("index", "count"):
                row[k] = int(v)
            else:
                row[k] = float(v)
        rows.append(row)
    return header, rows


# ---------------------------------------------------------------------------------------------
# ROS


def to_pose_array(plan: TargetPlan, frame_id: Optional[str] = None, with_approach: bool = False,
                  stamp: Tuple[int, int] = (0, 0)) -> Dict[str, Any]:
    """A ``geometry_msgs/PoseArray`` message dict (ROS 2 field names), positions in metres
    (REP 103).

    Parameters
    ----------
    frame_id : str, optional
        ``header.frame_id`` (default: the plan's frame name).
    with_approach : bool
        False: one pose per target. True: approach, target, retract poses per target (the
        tool path, all with the target's orientation).
    stamp : (int, int)
        ``header.stamp`` seconds and nanoseconds.
    """
    s = _scale_to(plan, "m")

    def pose(p: np.ndarray, q: np.ndarray) -> Dict[str, Any]:
        return {"position": dict(zip("xyz", _vec(p, s))),
                "orientation": {"x": float(q[1]), "y": float(q[2]), "z": float(q[3]),
                                "w": float(q[0])}}

    poses = []
    for t in plan.targets:
        pts = [t.approach_point, t.position, t.retract_point] if with_approach else [t.position]
        poses.extend(pose(p, t.quaternion) for p in pts)
    return {"header": {"stamp": {"sec": int(stamp[0]), "nanosec": int(stamp[1])},
                       "frame_id": frame_id or plan.frame},
            "poses": poses}


# ---------------------------------------------------------------------------------------------
# ABB RAPID

_IDENT = re.compile(r"^[A-Za-z][A-Za-z0-9_]{0,31}$")


def _ident(name: str, what: str, limit: int = 32) -> str:
    if not _IDENT.match(name) or len(name) > limit:
        raise ValueError(f"{what}: expected an identifier (a letter, then letters, digits or _; "
                         f"at most {limit} characters), got {name!r}")
    return name


def _f(v: float, digits: int) -> str:
    s = f"{float(v):.{digits}f}"
    return "0" + s[s.index("."):] if s.startswith("-0.") and float(s) == 0 else s


def to_rapid(plan: TargetPlan, module: str = "MiemTargets", proc: str = "Grind",
             tool: str = "tool0", wobj: str = "wobj0", speed: str = "v100",
             approach_speed: str = "v500", zone: str = "z1") -> str:
    """An ABB RAPID module: ``robtarget`` constants and a procedure of ``MoveL`` moves.

    Positions in mm, orientation ``[q1, q2, q3, q4]`` = ``(w, x, y, z)``. The robot
    configuration is unknown here: ``cf`` values are 0 and the procedure starts with
    ``ConfL\\Off``; external axes are unused (``9E9``).
    """
    for name, what in ((module, "module"), (proc, "proc"), (tool, "tool"), (wobj, "wobj"),
                       (speed, "speed"), (approach_speed, "approach_speed"), (zone, "zone")):
        _ident(name, what)
    s = _scale_to(plan, "mm")
    lines = [f"MODULE {module}",
             f"  ! miem grinding targets: {len(plan.targets)} targets in frame {plan.frame} "
             f"(mm, quaternion w x y z)"]
    names = []
    for t in plan.targets:
        k = t.index + 1
        for tag, p in (("pA", t.approach_point), ("pT", t.position), ("pR", t.retract_point)):
            q = ",".join(_f(v, 8) for v in t.quaternion)
            xyz = ",".join(_f(v, 4) for v in p * s)
            lines.append(f"  CONST robtarget {tag}{k}:=[[{xyz}],[{q}],[0,0,0,0],"
                         f"[9E9,9E9,9E9,9E9,9E9,9E9]];")
        names.append(k)
    lines.append(f"  PROC {proc}()")
    lines.append("    ConfL\\Off;")
    for k, t in zip(names, plan.targets):
        lines.append(f"    ! target {k}: depth {_f(t.depth * s, 3) if math.isfinite(t.depth) else 'n/a'}"
                     f" mm, defects {ids_text(t.defect_ids)}")
        lines.append(f"    MoveL pA{k},{approach_speed},{zone},{tool}\\WObj:={wobj};")
        lines.append(f"    MoveL pT{k},{speed},fine,{tool}\\WObj:={wobj};")
        lines.append(f"    MoveL pR{k},{approach_speed},{zone},{tool}\\WObj:={wobj};")
    lines += ["    ConfL\\On;", "  ENDPROC", "ENDMODULE", ""]
    return "\n".join(lines)


_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_ROBTARGET = re.compile(
    rf"CONST\s+robtarget\s+(\w+)\s*:=\s*\[\[({_NUM}),({_NUM}),({_NUM})\],"
    rf"\[({_NUM}),({_NUM}),({_NUM}),({_NUM})\],\[([-\d,]+)\],\[([^\]]*)\]\]\s*;")
_MOVEL = re.compile(r"^\s*MoveL\s+(\w+)\s*,", re.M)


def parse_rapid(text: str) -> Tuple[Dict[str, Dict[str, Any]], List[str]]:
    """``{name: {"pos": (3,), "quat": (4,) w first, "conf": (4,)}}`` and the MoveL order."""
    targets = {}
    for m in _ROBTARGET.finditer(text):
        g = m.groups()
        targets[g[0]] = {"pos": np.array(g[1:4], dtype=float),
                         "quat": np.array(g[4:8], dtype=float),
                         "conf": tuple(int(c) for c in g[8].split(","))}
    return targets, _MOVEL.findall(text)


# ---------------------------------------------------------------------------------------------
# KUKA KRL


def to_krl(plan: TargetPlan, name: str = "miem_targets", vel_cp: float = 0.1,
           approach_vel_cp: float = 0.5) -> Tuple[str, str]:
    """A KUKA KRL ``.src`` (``LIN`` moves) and ``.dat`` (``E6POS`` points) pair.

    Positions in mm, ``A, B, C`` in degrees about Z, Y, X. ``S`` and ``T`` are left out (``LIN``
    does not use them); ``$VEL.CP`` in m/s for the grinding and the approach moves. ``name``
    is the DEF / DEFDAT name, which KRL requires to be the file name (:func:`write` uses the
    file's stem).
    """
    _ident(name, "name", limit=24)
    for v, what in ((vel_cp, "vel_cp"), (approach_vel_cp, "approach_vel_cp")):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ValueError(f"{what}: expected a speed > 0 in m/s, got {v!r}")
    s = _scale_to(plan, "mm")
    dat = ["&ACCESS RVP", "&REL 1", f"DEFDAT {name}",
           f"; miem grinding targets: {len(plan.targets)} targets in frame {plan.frame} "
           "(mm, degrees)"]
    src = ["&ACCESS RVP", "&REL 1", f"DEF {name}( )",
           f"  ; miem grinding targets: {len(plan.targets)} targets in frame {plan.frame}",
           "  $APO.CDIS = 1.0"]
    for t in plan.targets:
        k = t.index + 1
        a, b, c = (_f(v, 5) for v in t.abc)
        for tag, p in (("XA", t.approach_point), ("XT", t.position), ("XR", t.retract_point)):
            x, y, z = (_f(v, 4) for v in p * s)
            dat.append(f"DECL E6POS {tag}{k}={{X {x},Y {y},Z {z},A {a},B {b},C {c},"
                       "E1 0.0,E2 0.0,E3 0.0,E4 0.0,E5 0.0,E6 0.0}")
        depth = _f(t.depth * s, 3) if math.isfinite(t.depth) else "n/a"
        src += [f"  ; target {k}: depth {depth} mm, defects {ids_text(t.defect_ids)}",
                f"  $VEL.CP = {approach_vel_cp:g}", f"  LIN XA{k} C_DIS",
                f"  $VEL.CP = {vel_cp:g}", f"  LIN XT{k}",
                f"  $VEL.CP = {approach_vel_cp:g}", f"  LIN XR{k} C_DIS"]
    dat += ["ENDDAT", ""]
    src += ["END", ""]
    return "\n".join(src), "\n".join(dat)


_E6POS = re.compile(r"DECL\s+E6POS\s+(\w+)\s*=\s*\{([^}]*)\}")
_LIN = re.compile(r"^\s*LIN\s+(\w+)", re.M)


def parse_krl(src: str, dat: str) -> Tuple[Dict[str, Dict[str, float]], List[str]]:
    """``{name: {"X": .., "Y": .., "Z": .., "A": .., "B": .., "C": ..}}`` and the LIN order."""
    points = {}
    for m in _E6POS.finditer(dat):
        fields = {}
        for item in m.group(2).split(","):
            key, _, val = item.strip().partition(" ")
            fields[key] = float(val)
        points[m.group(1)] = fields
    return points, _LIN.findall(src)


# ---------------------------------------------------------------------------------------------


def write(plan: TargetPlan, path: PathLike, format: Optional[str] = None,
          **options: Any) -> List[Path]:
    """Write a plan; returns the files written (two for ``krl``: ``.src`` and ``.dat``).

    Parameters
    ----------
    path : str or Path
        Output file (for ``krl`` the ``.dat`` goes next to the ``.src``).
    format : {"json", "csv", "ros", "ros-json", "rapid", "krl"}, optional
        Default from the suffix: .json, .csv, .yaml/.yml (ros), .mod (rapid), .src (krl).
    options
        Passed to the format's function (:func:`to_rapid`, :func:`to_krl`,
        :func:`to_pose_array`). For ``krl`` the program name defaults to the file's stem.
    """
    p = Path(path)
    if format is None:
        by_suffix = {".json": "json", ".csv": "csv", ".yaml": "ros", ".yml": "ros",
                     ".mod": "rapid", ".src": "krl"}
        format = by_suffix.get(p.suffix.lower())
        if format is None:
            raise ValueError(f"format: cannot tell the format from {p.name!r}; give one of "
                             f"{sorted(FORMATS)}")
    if format not in FORMATS:
        raise ValueError(f"format: expected one of {sorted(FORMATS)}, got {format!r}")
    if format == "krl":
        src_path = p if p.suffix.lower() == ".src" else p.with_suffix(".src")
        dat_path = src_path.with_suffix(".dat")
        # KRL requires DEF / DEFDAT names equal to the file name.
        options.setdefault("name", src_path.stem)
        if options["name"].lower() != src_path.stem.lower():
            raise ValueError(f"name: KRL needs the program name to be the file name "
                             f"{src_path.stem!r}, got {options['name']!r}")
        src, dat = to_krl(plan, **options)
        src_path.write_text(src, encoding="utf-8")
        dat_path.write_text(dat, encoding="utf-8")
        return [src_path, dat_path]
    if format == "json":
        if options:
            raise ValueError(f"options: json takes none, got {sorted(options)}")
        text = json.dumps(to_json(plan), indent=1) + "\n"
    elif format == "csv":
        if options:
            raise ValueError(f"options: csv takes none, got {sorted(options)}")
        text = to_csv(plan)
    elif format == "rapid":
        text = to_rapid(plan, **options)
    else:
        msg = to_pose_array(plan, **options)
        if format == "ros-json":
            text = json.dumps(msg, indent=1) + "\n"
        else:
            import yaml

            text = yaml.safe_dump(msg, sort_keys=False)
    p.write_text(text, encoding="utf-8")
    return [p]
