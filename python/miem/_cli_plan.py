"""``miem plan``: detect, then write grinding targets in the robot's base frame and format.

Kept apart from cli.py (which owns the shared reading and detection options): this module adds
the subcommand's own options and its command.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

_FORMAT_SUFFIX = {"json": ".targets.json", "csv": ".targets.csv", "ros": ".poses.yaml",
                  "ros-json": ".poses.json", "rapid": ".mod", "krl": ".src"}


def add_parser(sub: Any) -> None:
    """Register ``plan`` on the subparsers of the miem command line."""
    from . import cli

    p = sub.add_parser(
        "plan", formatter_class=argparse.RawDescriptionHelpFormatter,
        help="detect, then write grinding targets for the robot (RAPID, KRL, ROS, CSV, JSON)",
        description="Detect defects, select the ones to grind (protrusions by default), merge "
                    "those closer than the tool radius, order them into a short path and write "
                    "the tool poses in the robot's base frame:\n"
                    "  rapid     ABB RAPID module: robtargets (mm, quaternion w x y z) and MoveL\n"
                    "  krl       KUKA KRL .src (LIN moves) and .dat (E6POS X Y Z A B C)\n"
                    "  ros       geometry_msgs/PoseArray message as YAML (metres)\n"
                    "  ros-json  the same as JSON\n"
                    "  csv       one row per target, units and frame in the header\n"
                    "  json      every field of every target\n"
                    "Tool z axis = approach axis = minus the surface normal; tool x along the "
                    "scan direction.",
    )
    p.add_argument("scan", metavar="SCAN", help="scan file")
    p.add_argument("--transform", metavar="FILE",
                   help="calibration file (JSON or YAML) with the 4x4 T_base_sensor mapping scan "
                        "coordinates to the base frame (default: identity)")
    p.add_argument("--format", choices=sorted(_FORMAT_SUFFIX), default="json",
                   help="output format (default: json)")
    p.add_argument("-o", "--output", metavar="FILE",
                   help="output file (default: SCAN's name with the format's suffix, in the "
                        "current directory)")
    p.add_argument("--frame", default="base", metavar="NAME",
                   help="name of the base frame written into the files (default: base)")
    p.add_argument("--plot", metavar="PNG",
                   help="also draw the scan with the targets and the path on the height map")
    g = p.add_argument_group("targets")
    g.add_argument("--tool-radius", type=cli._finite_float, default=0.0, metavar="LENGTH",
                   help="merge defects closer than this into one target (default: 0, no merge)")
    g.add_argument("--standoff", type=cli._finite_float, default=0.0, metavar="LENGTH",
                   help="tool pose offset from the surface along the normal (default: 0)")
    g.add_argument("--approach", type=cli._finite_float, metavar="LENGTH",
                   help="approach point above the pose, scan units (default: 20 mm)")
    g.add_argument("--retract", type=cli._finite_float, metavar="LENGTH",
                   help="retract point above the pose, scan units (default: 20 mm)")
    g.add_argument("--at", choices=["peak", "centroid"], default="peak",
                   help="target point on a defect (default: peak)")
    g.add_argument("--kinds", nargs="+", choices=["protrusion", "pit", "isolated"],
                   default=["protrusion"], help="defect kinds to grind (default: protrusion)")
    g.add_argument("--min-height", type=cli._finite_float, default=0.0, metavar="LENGTH",
                   help="smallest |peak height| to grind (default: 0)")
    g.add_argument("--min-area", type=cli._finite_float, default=0.0, metavar="AREA",
                   help="smallest defect area, units squared (default: 0)")
    g.add_argument("--min-count", type=cli._positive_int, default=1, metavar="N",
                   help="fewest points in a defect (default: 1)")
    g.add_argument("--edge-clearance", type=cli._finite_float, default=0.0, metavar="LENGTH",
                   help="skip targets closer than this to a feature edge (default: 0)")
    g.add_argument("--roi", type=cli._finite_float, nargs="+", metavar="X Y",
                   help="region of interest: polygon vertices x1 y1 x2 y2 ... in scan x-y")
    g.add_argument("--start", type=cli._finite_float, nargs=3, metavar=("X", "Y", "Z"),
                   help="start of the path in the base frame (default: the deepest target)")
    cli._add_common(p)
    cli._add_detect_options(p)
    p.set_defaults(func=_cmd_plan)


def _cmd_plan(args: argparse.Namespace) -> int:
    from . import cli
    from . import robot_formats as rf
    from .targets import Tool, plan_targets, read_transform

    path = Path(args.scan)
    stem = path.name[: -len(path.suffix)] if path.suffix else path.name
    out = Path(args.output) if args.output else Path(stem + _FORMAT_SUFFIX[args.format])
    if cli._is_same_file(out, path):
        print(f"miem: error: refusing to overwrite the input {path}", file=sys.stderr)
        return 2
    kwargs = cli._kwargs_or_exit(args)
    if kwargs is None:
        return 2
    roi = None
    if args.roi is not None:
        if len(args.roi) < 6 or len(args.roi) % 2:
            print("miem: error: --roi: expected at least 3 vertices as x y pairs",
                  file=sys.stderr)
            return 2
        roi = np.array(args.roi, dtype=np.float64).reshape(-1, 2)
    try:
        T = read_transform(args.transform) if args.transform else np.eye(4)
        tool = Tool(radius=args.tool_radius, standoff=args.standoff, approach=args.approach,
                    retract=args.retract)
        loaded = cli._load(path, args)
        result = cli._detect(loaded, kwargs, path, args)
        plan = plan_targets(result, loaded.grid, T, tool=tool, at=args.at, kinds=args.kinds,
                            min_height=args.min_height, min_area=args.min_area,
                            min_count=args.min_count, roi=roi,
                            edge_clearance=args.edge_clearance, start=args.start,
                            units=loaded.units, frame=args.frame)
        written = rf.write(plan, out, format=args.format)
        if args.plot:
            from ._plot import plot_scan

            plot_scan(loaded.grid, result, args.plot, title=path.name, units=loaded.units,
                      view="top", plan=plan)
            written.append(Path(args.plot))
    except cli._Failure as exc:
        print(f"miem: error: {exc}", file=sys.stderr)
        return 1
    except (OSError, ValueError, ImportError) as exc:
        print(f"miem: error: {path}: {exc}", file=sys.stderr)
        return 1
    _print_plan(plan, path, written)
    return 0


def _print_plan(plan: Any, path: Path, written: list) -> None:
    from . import robot_formats as rf

    u = plan.units
    rej = ", ".join(f"{n} {k}" for k, n in plan.rejected.items() if n) or "none"
    print(f"{path.name}: {plan.defects_in:,} defects -> {len(plan.targets)} targets "
          f"({plan.defects_used} defects used; left out: {rej}); path {plan.path_length:.1f} "
          f"{u} in frame {plan.frame}")
    if plan.targets:
        print(f"  {'#':>3} {'x':>10} {'y':>10} {'z':>10} {'depth':>7} {'area':>7} "
              f"{'pts':>4} defects")
        for t in plan.targets[:15]:
            depth = f"{t.depth:.3f}" if math.isfinite(t.depth) else "n/a"
            ids = rf.ids_text(t.defect_ids, limit=4)
            print(f"  {t.index + 1:>3} {t.position[0]:>10.3f} {t.position[1]:>10.3f} "
                  f"{t.position[2]:>10.3f} {depth:>7} {t.area:>7.3f} {t.count:>4} "
                  f"{ids}")
        if len(plan.targets) > 15:
            print(f"  ... {len(plan.targets) - 15} more")
    print("wrote " + ", ".join(str(w) for w in written))
