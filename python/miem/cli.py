"""The ``miem`` command line: detect, fit, simulate, plot, plan.

``miem detect SCAN...`` labels scans and writes, per scan, the labelled cloud and a defect report
(JSON and CSV) for the grinding robot, and prints a summary table. ``miem fit`` compares the
least-squares, eigenvalue and MIEM planes; ``miem simulate`` writes the paper's surface or a
generated scan; ``miem plot`` draws a labelled scan. Run ``miem COMMAND --help`` for the options.

Exit status: 0 when every input was processed, 1 when at least one failed (the others are still
processed), 2 on a usage error.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import inspect
import json
import math
import os
import re
import signal
import sys
import threading
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from . import io as mio

__all__ = ["main"]

_WRITE_FORMATS = [name for name, spec in mio.FORMATS.items() if spec["write"]]
_READ_FORMATS = list(mio.FORMATS)
_AXES = {"x": 0, "y": 1, "z": 2}


class _Failure(Exception):
    """One input could not be processed; the message is printed, the batch goes on."""


# miem.io's keyword arguments -> the options that set them: the library's messages name its
# keywords ("pass step="), the command line's must name its flags ("use --line-step").
_IO_FLAGS = {
    "format": "--input-format", "step": "--line-step", "line_tol": "--line-tol",
    "line_axis": "--line-axis", "along_axis": "--along-axis", "duplicates": "--duplicates",
}
_NAMES = "|".join(_IO_FLAGS)
_KEYWORD = re.compile(r"(?<![-\w])(%s)=(?:'([^']*)'((?: or '[^']*')*)|([^\s,;()]+))?" % _NAMES)
_ADVICE = re.compile(r"\b(check|pass) ((?:%s)(?:(?:,| and| or) (?:%s))*)\b" % (_NAMES, _NAMES))


def _cli_words(message: str) -> str:
    """`message` with miem.io keywords (``step=``, ``duplicates='first' or 'last'``, "check
    step and along_axis") replaced by the options that set them (``--line-step``,
    ``--duplicates first or last``, "check --line-step and --along-axis")."""

    def keyword(m: re.Match) -> str:
        flag = _IO_FLAGS[m.group(1)]
        if m.group(2) is not None:  # a quoted choice, maybe followed by "or 'other'"
            return f"{flag} {m.group(2)}{m.group(3).replace(chr(39), '')}"
        return flag + (f" {m.group(4)}" if m.group(4) else "")

    def advice(m: re.Match) -> str:
        names = re.sub(r"\b(%s)\b" % _NAMES, lambda k: _IO_FLAGS[k.group(1)], m.group(2))
        return f"{'use' if m.group(1) == 'pass' else 'check'} {names}"

    out = _KEYWORD.sub(keyword, message)
    out = _ADVICE.sub(advice, out)
    return re.sub(r"\bpass (--[\w-]+)", r"use \1", out)


# The scan-line options, which the messages about rebuilding a grid name.
_LINE_OPTIONS = "--line-step, --line-axis, --along-axis, --line-tol"


def _cli_advice(message: str, layout: str | None) -> str:
    """A warning of miem.detect in the command line's words (`_cli_words`): its radius is
    ``--radius``, and its advice on a cloud that looks like a grid (keep it with ``shape=``,
    rebuild it with ``grid_from_scanlines``) becomes the layout options (`layout`: the
    ``--layout`` given)."""
    from ._api import _AS_CLOUD

    text = _cli_words(message).replace("a smaller radius", "a smaller --radius")
    looks, sep, _ = text.partition(_AS_CLOUD)
    if not sep:
        return text
    return looks + sep + (
        ", as --layout cloud asks; drop it to rebuild its grid" if layout == "cloud" else
        f": no grid could be rebuilt from its scan lines; see {_LINE_OPTIONS} or --layout "
        "scanlines")


# The detection options are generated from the fields of miem.DetectParams (miem/params.py):
# every field organized detection honours is an option, with its unit, help and default there.


class _Unset:
    """Default of a detection option not given: the preset's (or the config file's) value."""

    def __repr__(self) -> str:
        return "<from the preset>"


_UNSET: Any = _Unset()


def _grid_fields() -> dict[str, dict[str, Any]]:
    from .params import DetectParams

    return DetectParams.fields("grid")


def _cloud_only_fields() -> dict[str, dict[str, Any]]:
    from .params import DetectParams

    grid = _grid_fields()
    return {k: v for k, v in DetectParams.fields("cloud").items() if k not in grid}


def _option(name: str) -> str:
    """A field's option: --edge-extent for edge_extent, --k for K."""
    return "--" + name.lower().replace("_", "-")


def _fmt_default(value: Any, help: str = "") -> str:
    if value is None:  # None is "off", or a value derived from the scan as the help says
        derived = re.search(r"None: ([^;]*)", help)
        return derived.group(1) if derived else "off"
    if isinstance(value, (tuple, list)):
        return " ".join(str(v) for v in value)
    return f"{value:g}" if isinstance(value, float) else str(value)


# ---------------------------------------------------------------------------------------------
# argument parsing


def _int_at_least(minimum: int):
    """An argparse type: an integer >= minimum."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if v < minimum:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {v}")
        return v

    return parse


_positive_int = _int_at_least(1)
_nonneg_int = _int_at_least(0)


def _finite_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return v


def _field_value(text: str) -> Any:
    """A field value from the command line: 'off' / 'none' -> None, an integer, a number, else
    the text ('auto', '4.5rms', 'abnormal'); miem.DetectParams checks it."""
    t = text.strip()
    if t.lower() in ("off", "none"):
        return None
    try:
        return int(t)
    except ValueError:
        pass
    try:
        v = float(t)
    except ValueError:
        return t.lower()
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return v


def _add_detect_options(parser: argparse.ArgumentParser) -> None:
    from .params import DEFAULT_PRESET, PRESETS

    g = parser.add_argument_group(
        "detection parameters",
        f"Generated from miem.DetectParams. The defaults below are preset '{DEFAULT_PRESET}', "
        "the best measured configuration; '--preset paper' runs the paper's method exactly. "
        "--config FILE (JSON or TOML, see 'miem config') replaces the preset's values, and an "
        "option given here overrides both. 'off' switches an optional parameter off.",
    )
    g.add_argument("--preset", choices=sorted(PRESETS), default=None,
                   help=f"named parameter set (default: {DEFAULT_PRESET})")
    g.add_argument("--config", metavar="FILE",
                   help="detection parameters from a JSON or TOML file (e.g. the output of "
                        "'miem config'); a 'preset' key in it picks the base")
    for name, meta in _grid_fields().items():
        unit = f" [{meta['unit']}]" if meta["unit"] else ""
        kw: dict[str, Any] = {"nargs": "+"} if isinstance(meta["default"], tuple) else {}
        g.add_argument(_option(name), dest=name, type=_field_value,
                       metavar=meta["metavar"], default=_UNSET,
                       help=f"{meta['help']}{unit} (default: "
                            f"{_fmt_default(meta['default'], meta['help'])})",
                       **kw)
    g.add_argument("--threads", type=_positive_int, metavar="N",
                   help="worker threads (default: all cores); results do not depend on it")
    s = parser.add_argument_group(
        "reading",
        "Unorganized files (N x 3, e.g. a PCD with HEIGHT 1) are rebuilt into a grid from "
        "their scan lines (miem.io.grid_from_scanlines: a new profile starts where the "
        "line coordinate changes, in file order or, for points in another order, sorted by "
        "it) when they lie on scan lines, else the cloud detector runs on the points (see "
        "--layout).",
    )
    s.add_argument("--input-format", choices=_READ_FORMATS, metavar="FORMAT",
                   help="read every input as FORMAT instead of guessing from its suffix "
                        f"({', '.join(_READ_FORMATS)})")
    s.add_argument("--line-step", type=_finite_float, metavar="LENGTH",
                   help="point spacing along a profile, in the scan's units "
                        "(default: estimated from the data)")
    s.add_argument("--line-axis", choices=list(_AXES), default=None,
                   help="coordinate that is constant within a profile (default: y, else x: "
                        "both are tried)")
    s.add_argument("--along-axis", choices=list(_AXES), default=None,
                   help="coordinate that runs along a profile (default: the other of x and y)")
    s.add_argument("--line-tol", type=_finite_float, metavar="LENGTH",
                   help="change of the line coordinate that starts a new profile "
                        "(default: half the point spacing)")
    s.add_argument("--layout", choices=["auto", "scanlines", "cloud"], default="auto",
                   help="how to treat an unorganized file: 'scanlines' rebuilds a grid from "
                        "its scan lines, 'cloud' runs the cloud detector on the points as "
                        "they are; 'auto' (default) rebuilds when the points lie on scan lines "
                        "(in file order, or in any order: rows sorted by line position) and "
                        "at least half the grid's cells are filled, runs the cloud detector "
                        "otherwise, and says which it took")
    s.add_argument("--duplicates", choices=["error", "first", "last"], default="error",
                   help="two points in one grid cell: fail, or keep the first/last "
                        "(default: error)")
    _add_cloud_options(parser)


def _add_cloud_options(parser: argparse.ArgumentParser) -> None:
    c = parser.add_argument_group(
        "cloud detector parameters",
        "Generated from the cloud part of miem.DetectParams: its fields that organized "
        "detection does not have (the shared ones are the detection options above). They apply "
        "to scans the cloud detector runs on (see --layout) and are refused for grids.")
    for name, meta in _cloud_only_fields().items():
        unit = f" [{meta['unit']}]" if meta["unit"] else ""
        c.add_argument(_option(name), dest=name, type=_field_value, metavar=meta["metavar"],
                       default=_UNSET,
                       help=f"{meta['help']}{unit} (default: "
                            f"{_fmt_default(meta['default'], meta['help'])})")


def _add_common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--units", default=None, metavar="NAME",
                        help="the scan's length unit, for reports and plots (default: m or mm, "
                             "guessed per scan from its extent and point spacing; a mismatch "
                             "with a given unit is warned about)")


def _build_parser() -> argparse.ArgumentParser:
    from . import __version__

    fmt = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(
        prog="miem",
        description="Find abnormal points (burr tips, weld spatter, dust, pits, dropouts) in "
                    "laser scans with the Multidimensional Improved Eigenvalue Method.",
        epilog="Run 'miem COMMAND --help' for the options of a command. Scan formats: PCD "
               "(ascii, binary, binary_compressed), PLY, LAS/LAZ, XYZ/CSV/TXT columns, NumPy "
               ".npy/.npz, Gocator CSV export (read only). Exit status: 0 all inputs done, 1 "
               "some input failed, 2 usage error.",
        formatter_class=fmt,
    )
    parser.add_argument("--version", action="version", version=f"miem {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    # detect
    p = sub.add_parser(
        "detect", formatter_class=fmt,
        help="label scans, write labelled clouds and defect reports",
        description="Label each scan (NORMAL, ABNORMAL, EDGE, INVALID) and write, per scan, "
                    "into the output directory:\n"
                    "  NAME.labels.EXT     the points with fields label (0 NORMAL, 1 ABNORMAL, "
                    "2 EDGE, 3 INVALID),\n"
                    "                      flags (bitmask of flagged directions), angle "
                    "(degrees), height (signed\n"
                    "                      distance from the local surface, scan units)\n"
                    "  NAME.defects.json   defects: id, count, kind, centroid, normal (tool "
                    "axis), peak height, peak point,\n"
                    "                      mean height, extent, point indices into "
                    "NAME.labels.EXT\n"
                    "  NAME.defects.csv    the same, one row per defect (without indices)\n"
                    "and print a summary table. A scan that fails is reported and the others are "
                    "still processed.",
    )
    p.add_argument("scans", nargs="+", metavar="SCAN", help="scan files")
    p.add_argument("-o", "--out-dir", default=".", metavar="DIR",
                   help="output directory, created if missing (default: the current directory)")
    p.add_argument("--format", choices=["same"] + _WRITE_FORMATS, default="same",
                   help="format of the labelled cloud (default: same as the input; PCD for a "
                        "Gocator CSV)")
    p.add_argument("--encoding", choices=["binary", "binary_compressed", "ascii"],
                   help="PCD/PLY encoding of the labelled cloud (default: binary; PLY has no "
                        "compression, binary_compressed means binary there)")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="print nothing but errors")
    p.add_argument("--no-progress", action="store_true",
                   help="no progress bar on stderr (it is shown only on a terminal)")
    _add_common(p)
    _add_detect_options(p)
    p.set_defaults(func=_cmd_detect)

    # config
    from .params import DEFAULT_PRESET, PRESETS

    p = sub.add_parser(
        "config", formatter_class=fmt,
        help="print a complete detection config to start from (JSON or TOML)",
        description="Print every detection parameter of a preset (miem.DetectParams), with its "
                    "unit and meaning in TOML comments, to edit and pass back with "
                    "'miem detect --config FILE'.",
    )
    p.add_argument("--preset", choices=sorted(PRESETS), default=DEFAULT_PRESET,
                   help=f"the preset to print (default: {DEFAULT_PRESET})")
    p.add_argument("--format", choices=["toml", "json"], default="toml",
                   help="output format (default: toml)")
    p.add_argument("-o", "--output", metavar="FILE", help="write to FILE instead of stdout")
    p.set_defaults(func=_cmd_config)

    # fit
    p = sub.add_parser(
        "fit", formatter_class=fmt,
        help="compare the least-squares, eigenvalue and MIEM planes",
        description="Fit a plane to each scan three ways and print them side by side: least "
                    "squares z = ax + by + c (the paper's baseline), the eigenvalue method "
                    "(all points) and MIEM (the eigenvalue fit without the ABNORMAL points). "
                    "Planes are n . p + d = 0 with a unit normal n (n_z > 0); rms is the RMS "
                    "orthogonal distance of the fitted points; tilt is the angle between a "
                    "plane's normal and the MIEM normal.",
    )
    p.add_argument("scans", nargs="+", metavar="SCAN", help="scan files")
    _add_common(p)
    _add_detect_options(p)
    p.set_defaults(func=_cmd_fit)

    # simulate
    from . import simulate as sim

    p = sub.add_parser(
        "simulate", formatter_class=fmt,
        help="write the paper's surface or a generated scan",
        description="Write a synthetic organized scan with ground truth in the field 'truth' "
                    "(0 normal, 1 injected defect, 2 designed edge, 3 dropout).\n"
                    "  paper  the paper's surface z = 2/5 exp(-x^2/50), x in [-50, 30], "
                    "y in [-50, 50] mm,\n"
                    "         two edge strips and 5 abnormal points (2 on the strips)\n"
                    "  scan   a workpiece surface (--surface) with spikes, pits, dust, clusters",
    )
    p.add_argument("kind", choices=["paper", "scan"], help="what to generate")
    p.add_argument("-o", "--output", required=True, metavar="FILE",
                   help="output scan file; its suffix selects the format")
    p.add_argument("--step", type=_finite_float, metavar="LENGTH",
                   help="grid spacing in mm (default: 0.5 for paper, 0.3 for scan)")
    p.add_argument("--noise", type=_finite_float, default=0.0, metavar="FRACTION",
                   help="z noise standard deviation as a fraction of the step (default: 0)")
    p.add_argument("--dropout", type=_finite_float, default=0.0, metavar="FRACTION",
                   help="fraction of cells without a return (NaN), 0-0.5 (default: 0)")
    p.add_argument("--seed", type=_nonneg_int, default=0, help="random seed (default: 0)")
    p.add_argument("--shape", type=_positive_int, nargs=2, metavar=("H", "W"),
                   default=[128, 128],
                   help="scan: profiles and points per profile (default: 128 128)")
    p.add_argument("--surface", choices=list(sim.SURFACES), default="plane",
                   help="scan: the workpiece surface (default: plane)")
    p.add_argument("--defects", default="spike=2,pit=2,dust=1", metavar="KIND=N,...",
                   help=f"scan: defects to inject, kinds {', '.join(sim.DEFECT_KINDS)} "
                        "(default: spike=2,pit=2,dust=1; 'none' for none)")
    p.add_argument("--origin", type=_finite_float, nargs=3, metavar=("X", "Y", "Z"),
                   default=[0.0, 0.0, 0.0],
                   help="scan: shift of the whole scan in mm, e.g. a robot-base position "
                        "(default: 0 0 0)")
    p.add_argument("--encoding", choices=["binary", "binary_compressed", "ascii"],
                   help="PCD/PLY encoding (default: binary)")
    p.set_defaults(func=_cmd_simulate)

    # plot
    p = sub.add_parser(
        "plot", formatter_class=fmt,
        help="draw a scan coloured by label, with a height map and the largest defects",
        description="Detect, then draw a PNG: the cloud coloured by label (ABNORMAL red, EDGE "
                    "blue, NORMAL grey) with the largest defects numbered, a height map of z "
                    "with those defects circled, and a table of them. Needs matplotlib "
                    "(pip install \"miem[plot]\").",
    )
    p.add_argument("scan", metavar="SCAN", help="scan file")
    p.add_argument("-o", "--output", metavar="PNG",
                   help="output image (default: SCAN's name with .png, in the current "
                        "directory)")
    p.add_argument("--view", choices=["3d", "top"], default="3d",
                   help="first panel: perspective or top view (default: 3d)")
    p.add_argument("--title", help="figure title (default: the scan's file name)")
    p.add_argument("--max-labels", type=_nonneg_int, default=10, metavar="N",
                   help="defects to number and list, largest first (default: 10)")
    p.add_argument("--size", type=_finite_float, nargs=2, default=[16.0, 6.0],
                   metavar=("W", "H"), help="figure size in inches (default: 16 6)")
    p.add_argument("--dpi", type=_positive_int, default=100,
                   help="pixels per inch; the PNG is W*dpi x H*dpi pixels (default: 100)")
    _add_common(p)
    _add_detect_options(p)
    p.set_defaults(func=_cmd_plot)

    # plan (python/miem/_cli_plan.py)
    from ._cli_plan import add_parser as add_plan_parser

    add_plan_parser(sub)

    from ._cli_compare import add_parser as add_compare  # compare: deviation from a reference

    add_compare(sub)
    return parser


# ---------------------------------------------------------------------------------------------
# shared steps


def _detect_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """The miem.detect arguments: the preset (or the default), then --config, then the options.

    Raises
    ------
    ValueError
        A parameter out of range or a bad config file (checked once here, so that a bad option
        is a usage error rather than a failure of every scan).
    """
    from .params import DEFAULT_PRESET, PRESETS, load_config, resolve_params

    params, _ = resolve_params(None, args.preset, {}, "grid")
    if args.config is not None:
        params = load_config(args.config, base=params)
    given = {name: getattr(args, name) for name in _grid_fields()}
    given = {k: (tuple(v) if isinstance(v, list) else v) for k, v in given.items()
             if v is not _UNSET}
    filed = params  # the preset and the file, before the options
    params = params.for_path("grid", **given)
    params.check("grid")
    # As a preset plus the fields that differ from it, so that reports name the preset.
    name = args.preset or next((n for n, p in PRESETS.items() if p == params), DEFAULT_PRESET)
    mine, base = params.flat("grid"), PRESETS[name].flat("grid")
    diff = {k: v for k, v in mine.items() if v != base[k]}
    # For scans the cloud detector runs on (_cloud_kwargs): the file's angle and cloud values
    # that differ from the preset (a file holds every part; grids read angle and grid), then
    # the options given.
    mine, base = filed.flat("cloud"), PRESETS[name].flat("cloud")
    args.cloud_kwargs = {"preset": name, **{k: v for k, v in mine.items() if v != base[k]},
                         **given, "num_threads": args.threads}
    return {"preset": name, **diff, "num_threads": args.threads}


def _kwargs_or_exit(args: argparse.Namespace) -> dict[str, Any] | None:
    try:
        return _detect_kwargs(args)
    except ValueError as exc:
        msg = str(exc)
        name = msg.split(":", 1)[0]
        if name in _grid_fields():  # name the option the user typed
            msg = f"{_option(name)}{msg[len(name):]}"
        print(f"miem: error: bad detection parameter: {msg}", file=sys.stderr)
        return None


class _Loaded:
    """A scan ready for detection: the grid, and how to map cells back to the file's points."""

    def __init__(self, data: mio.ScanData, grid: np.ndarray, index: np.ndarray | None,
                 units: str = "mm", layout: str = "grid") -> None:
        self.data = data
        self.grid = grid  # (H, W, 3), or the (N, 3) points for the cloud detector
        self.index = index  # input point -> flat cell (-1: not in the grid); None otherwise
        self.units = units  # the scan's length unit, for reports and plots
        self.layout = layout  # "grid" (organized file), "scanlines" (rebuilt) or "cloud"

    @property
    def shape_text(self) -> str:
        return "cloud" if self.layout == "cloud" else "x".join(map(str, self.grid.shape[:2]))


def _length_options() -> tuple[str, ...]:
    """Options that are lengths in the scan's unit (checked against the scan's size): the
    fields whose unit is a length, and the scan-line options."""
    fields = {**_grid_fields(), **_cloud_only_fields()}
    return tuple(k for k, m in fields.items() if m["unit"].startswith("length")) + (
        "line_step", "line_tol")


def _units(path: Path, grid: np.ndarray, args: argparse.Namespace) -> str:
    """The scan's unit (given, or guessed), warning when the scan and the options disagree."""
    from .units import guess_units, length_warning

    try:
        guess = guess_units(grid)
    except ValueError:
        return args.units or "mm"
    if args.units is not None and args.units.lower() in ("m", "mm") and \
            args.units.lower() != guess.unit:
        print(f"miem: warning: {path.name} {guess.reason}: that looks like {guess.unit}, "
              f"not the --units {args.units} given", file=sys.stderr)
    for name in _length_options():
        value = getattr(args, name, None)
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            text = length_warning(f"--{name.replace('_', '-')}", float(value), guess)
            if text:
                print(f"miem: warning: {path.name}: {text}", file=sys.stderr)
    return args.units or guess.unit


def _load(path: Path, args: argparse.Namespace) -> _Loaded:
    try:
        data = mio.read(path, format=args.input_format)
    except (OSError, ValueError, ImportError) as exc:
        raise _Failure(_cli_words(str(exc))) from exc
    if data.organized:
        if args.layout != "auto":
            _say(args, f"{path.name}: organized ({data.points.shape[0]} x "
                       f"{data.points.shape[1]} grid in the file); --layout does not apply")
        return _Loaded(data, data.points, None, _units(path, data.points, args))
    n = data.points.shape[0]
    why = "--layout cloud"
    if args.layout != "cloud":
        try:
            axes = {k: _AXES[v] for k, v in (("line_axis", args.line_axis),
                                              ("along_axis", args.along_axis)) if v}
            grid, index, order, la = mio._rebuild_grid(
                data.points, force=args.layout == "scanlines", step=args.line_step,
                line_tol=args.line_tol, duplicates=args.duplicates, **axes,
            )
            fill = float(np.isfinite(grid).all(axis=-1).mean())
            lines = f"profiles at constant {'xyz'[la]}"
            how = (f"in scan-line order ({lines})" if order == "file" else
                   f"on scan lines but not in their order ({lines}, rows sorted by it)")
            _say(args, f"{path.name}: unorganized ({n:,} points) {how}: "
                       f"rebuilt a {grid.shape[0]} x {grid.shape[1]} grid "
                       f"({fill:.0%} of its cells filled), grid detector")
            return _Loaded(data, grid, index, _units(path, grid, args), "scanlines")
        except ValueError as exc:
            if args.layout == "scanlines":
                raise _Failure(
                    f"{path}: the file is unorganized ({n:,} points) and no grid could be "
                    f"rebuilt from its scan lines: {_cli_words(str(exc))}; see {_LINE_OPTIONS}, "
                    "or --layout cloud"
                ) from exc
            why = "its points are not on scan lines (in file order or by line position)"
    _say(args, f"{path.name}: unorganized ({n:,} points), {why}: cloud detector")
    return _Loaded(data, data.points, None, _units(path, data.points, args), "cloud")


def _say(args: argparse.Namespace, text: str) -> None:
    """A note on stderr (which path a scan took), unless --quiet."""
    if not getattr(args, "quiet", False):
        print(f"miem: {text}", file=sys.stderr)


def _cloud_kwargs(loaded: _Loaded, kwargs: dict[str, Any], args: argparse.Namespace,
                  path: Path) -> dict[str, Any]:
    """The detect arguments for the path the scan took: for clouds the preset, the config
    file's angle and cloud values and the options (cloud-only ones included); for grids the
    grid's, and cloud-only options are rejected."""
    extra = {k: getattr(args, k, _UNSET) for k in _cloud_only_fields()}
    extra = {k: v for k, v in extra.items() if v is not _UNSET}
    if loaded.layout == "cloud":
        return {**getattr(args, "cloud_kwargs", kwargs), **extra}
    if extra:
        opts = ", ".join(_option(k) for k in extra)
        raise _Failure(f"{path}: {opts} apply to the cloud detector only, and this scan is "
                       f"a {loaded.shape_text} grid; drop them or pass --layout cloud")
    return kwargs


def _detect(loaded: _Loaded, kwargs: dict[str, Any], path: Path,
            args: argparse.Namespace | None = None) -> Any:
    from . import detect

    if args is not None:
        kwargs = _cloud_kwargs(loaded, kwargs, args, path)
    try:
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always", UserWarning)
            res = detect(loaded.grid, **kwargs)
    except ValueError as exc:
        raise _Failure(f"{path}: {_cli_words(str(exc))}") from exc
    for w in seen:  # detect's advice as the command line's other warnings, in its words
        if not issubclass(w.category, UserWarning):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
            continue
        text = _cli_advice(str(w.message), getattr(args, "layout", None))
        print(f"miem: warning: {path.name}: {text}", file=sys.stderr)
    return res


def _is_same_file(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


# ---------------------------------------------------------------------------------------------
# progress on stderr


class _Progress:
    """A one-line progress bar on stderr, drawn only when stderr is a terminal."""

    def __init__(self, total: int, enabled: bool, stream: TextIO | None = None) -> None:
        self.stream = stream or sys.stderr
        self.total = max(total, 1)
        self.enabled = enabled and getattr(self.stream, "isatty", lambda: False)()
        self.width = 0

    def show(self, done: float, text: str) -> None:
        if not self.enabled:
            return
        frac = min(max(done / self.total, 0.0), 1.0)
        bar = "#" * round(24 * frac)
        line = f"[{bar:<24s}] {int(done)}/{self.total} {text}"
        if len(line) > 100:
            line = line[:97] + "..."
        pad = max(self.width - len(line), 0)
        self.stream.write("\r" + line + " " * pad)
        self.stream.flush()
        self.width = len(line)

    def close(self) -> None:
        if self.enabled and self.width:
            self.stream.write("\r" + " " * self.width + "\r")
            self.stream.flush()


# ---------------------------------------------------------------------------------------------
# detect


def _json_float(v: float) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def _json_vec(v: np.ndarray) -> list[float | None]:
    return [_json_float(x) for x in np.asarray(v, dtype=np.float64)]


def _defect_rows(loaded: _Loaded, result: Any) -> list[dict[str, Any]]:
    """Defects as plain dicts; indices refer to the points of the labelled output cloud."""
    from ._layout import cell_rows

    flat = loaded.grid.reshape(-1, 3)
    height = np.asarray(result.height).reshape(-1)
    inverse = None if loaded.index is None else cell_rows(loaded.index, flat.shape[0])
    rows = []
    for d in result.defects:
        cells = np.asarray(d.indices, dtype=np.int64)
        h = height[cells]
        k = int(np.nanargmax(np.abs(h))) if np.isfinite(h).any() else 0
        idx = cells if inverse is None else inverse[cells]
        rows.append({
            "id": int(d.id),
            "kind": str(d.kind),
            "count": int(d.count),
            "centroid": _json_vec(d.centroid),
            "normal": _json_vec(d.normal),
            "peak_height": _json_float(d.peak_height),
            "peak_point": _json_vec(flat[cells[k]]),
            "mean_height": _json_float(d.mean_height),
            "extent": _json_float(d.extent),
            "indices": [int(i) for i in np.sort(idx)],
        })
    return rows


def _compact_json(doc: Any) -> str:
    """JSON with two-space indents but each list of numbers on one line."""
    text = json.dumps(doc, indent=2, allow_nan=False)
    return re.sub(r"\[\s+([-+0-9.eE,\snul]*?)\s+\]",
                  lambda m: "[" + ", ".join(t.strip() for t in m.group(1).split(",")) + "]",
                  text)


def _write_reports(stem: Path, path: Path, loaded: _Loaded, result: Any, cloud: Path,
                   seconds: float) -> tuple[Path, Path]:
    from . import __version__

    rows = _defect_rows(loaded, result)
    plane = result.plane
    grid_shape = list(loaded.grid.shape[:2])
    doc = {
        "miem_version": __version__,
        "scan": str(path),
        "units": loaded.units,
        "format": loaded.data.format,
        "points": int(np.prod(loaded.data.points.shape[:-1])),
        "organized": bool(loaded.data.organized),
        "layout": loaded.layout,
        "grid": None if loaded.layout == "cloud" else grid_shape,
        "labelled_cloud": cloud.name,
        "parameters": {k: (list(v) if isinstance(v, tuple) else v)
                       for k, v in result.params.items()},
        "iterations": int(result.iterations),
        "counts": result.counts(),
        "plane": None if plane is None else {
            "normal": _json_vec(plane.normal), "d": _json_float(plane.d),
            "rms": _json_float(plane.rms), "n_points": int(plane.n_points),
        },
        "seconds": round(seconds, 4),
        "defects": rows,
    }
    json_path = stem.with_name(stem.name + ".defects.json")
    csv_path = stem.with_name(stem.name + ".defects.csv")
    with mio._atomic(json_path) as tmp:
        tmp.write_text(_compact_json(doc) + "\n", encoding="utf-8")
    header = ["id", "kind", "count", "peak_height", "mean_height", "extent",
              "centroid_x", "centroid_y", "centroid_z", "normal_x", "normal_y", "normal_z",
              "peak_x", "peak_y", "peak_z"]

    def cell(v: Any) -> str:
        return "nan" if v is None else (f"{v:.10g}" if isinstance(v, float) else str(v))

    with mio._atomic(csv_path) as tmp, open(tmp, "w", encoding="utf-8", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(header)
        for r in rows:
            w.writerow([cell(v) for v in (r["id"], r["kind"], r["count"], r["peak_height"],
                                          r["mean_height"], r["extent"], *r["centroid"],
                                          *r["normal"], *r["peak_point"])])
    return json_path, csv_path


def _output_fields(loaded: _Loaded, result: Any) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Points and fields of the labelled cloud: the input's points in the input's order."""
    res = mio.result_fields(result)
    fields = {k: v for k, v in loaded.data.fields.items() if k not in res}
    if loaded.index is None:
        fields.update(res)
        return loaded.data.points, fields
    from ._layout import on_points

    for k, v in res.items():
        fields[k] = on_points(v, loaded.index, label=k == "label")
    return loaded.data.points, fields


def _cmd_detect(args: argparse.Namespace) -> int:
    kwargs = _kwargs_or_exit(args)
    if kwargs is None:
        return 2
    out_dir = Path(args.out_dir)
    scans = [Path(s) for s in args.scans]
    # Output names are decided up front: two inputs must not write the same files, and no
    # output may replace an input.
    plan = []
    seen: dict[str, Path] = {}
    for path in scans:
        stem = path.name[: -len(path.suffix)] if path.suffix else path.name
        if stem in seen:
            print(f"miem: error: {path} and {seen[stem]} would write the same outputs "
                  f"({stem}.*); process them into different --out-dir", file=sys.stderr)
            return 2
        seen[stem] = path
        plan.append((path, out_dir / stem))
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        print(f"miem: error: cannot create the output directory {out_dir}: {exc}",
              file=sys.stderr)
        return 2

    progress = _Progress(len(scans), not (args.quiet or args.no_progress))
    summary = []
    failed = 0
    for i, (path, stem) in enumerate(plan):
        name = path.name
        t0 = time.perf_counter()
        try:
            progress.show(i, f"{name}: reading")
            loaded = _load(path, args)
            progress.show(i + 0.3, f"{name}: detecting")
            td = time.perf_counter()
            result = _detect(loaded, kwargs, path, args)
            t_detect = time.perf_counter() - td
            fmt = args.format
            if fmt == "same":
                fmt = loaded.data.format if mio.FORMATS[loaded.data.format]["write"] else "pcd"
            ext = mio.FORMATS[fmt]["suffixes"][0]
            cloud = stem.with_name(stem.name + ".labels" + ext)
            outputs = [cloud, stem.with_name(stem.name + ".defects.json"),
                       stem.with_name(stem.name + ".defects.csv")]
            for out in outputs:
                for src in scans:
                    if _is_same_file(out, src):
                        raise _Failure(f"{path}: refusing to overwrite the input {src} with "
                                       f"an output; choose another --out-dir")
            progress.show(i + 0.6, f"{name}: writing")
            pts, fields = _output_fields(loaded, result)
            enc = args.encoding if fmt in ("pcd", "ply") else None
            if fmt == "ply" and enc == "binary_compressed":
                enc = "binary"
            try:
                mio.write(cloud, pts, fields, format=fmt, encoding=enc)
            except (OSError, ValueError, ImportError) as exc:
                raise _Failure(f"{path}: cannot write {cloud}: {exc}") from exc
            seconds = time.perf_counter() - t0
            _write_reports(stem, path, loaded, result, cloud, seconds)
        except _Failure as exc:
            failed += 1
            progress.close()
            print(f"miem: error: {exc}", file=sys.stderr)
            continue
        counts = result.counts()
        peaks = [abs(d.peak_height) for d in result.defects if math.isfinite(d.peak_height)]
        summary.append((name, int(np.prod(loaded.data.points.shape[:-1])),
                        loaded.shape_text, counts["ABNORMAL"],
                        counts["EDGE"], len(result.defects), max(peaks) if peaks else math.nan,
                        t_detect, seconds, loaded.units))
    progress.close()
    if not args.quiet and summary:
        _print_summary(summary, out_dir, scans, failed)
    return 1 if failed else 0


def _print_summary(rows: list[tuple], out_dir: Path, scans: list[Path], failed: int) -> None:
    head = ("scan", "points", "grid", "abnormal", "edge", "defects", "max |peak|",
            "detect s", "total s")
    body = [(r[0], f"{r[1]:,}", r[2], f"{r[3]:,}", f"{r[4]:,}", f"{r[5]:,}",
             "-" if not math.isfinite(r[6]) else f"{r[6]:.3f} {r[9]}", f"{r[7]:.2f}",
             f"{r[8]:.2f}")
            for r in rows]
    widths = [max(len(h), *(len(b[j]) for b in body)) for j, h in enumerate(head)]
    left = {0}

    def line(cells: Sequence[str]) -> str:
        return "  ".join(c.ljust(w) if j in left else c.rjust(w)
                         for j, (c, w) in enumerate(zip(cells, widths)))

    print(line(head))
    print("  ".join("-" * w for w in widths))
    for b in body:
        print(line(b))
    done = len(rows)
    tail = f"{done} of {len(scans)} scans done" + (f", {failed} failed" if failed else "")
    print(f"{tail}; outputs in {out_dir}/ (NAME.labels.*, NAME.defects.json, "
          "NAME.defects.csv)")


# ---------------------------------------------------------------------------------------------
# config


def _cmd_config(args: argparse.Namespace) -> int:
    from .params import PRESETS, dump_config

    text = dump_config(PRESETS[args.preset], args.format)
    if args.output is None:
        sys.stdout.write(text)
        return 0
    try:
        Path(args.output).write_text(text, encoding="utf-8")
    except OSError as exc:
        print(f"miem: error: cannot write {args.output}: {exc}", file=sys.stderr)
        return 1
    return 0


# ---------------------------------------------------------------------------------------------
# fit


def _cmd_fit(args: argparse.Namespace) -> int:
    from . import fit_plane

    kwargs = _kwargs_or_exit(args)
    if kwargs is None:
        return 2
    failed = 0
    for n_scan, raw in enumerate(args.scans):
        path = Path(raw)
        try:
            loaded = _load(path, args)
            result = _detect(loaded, kwargs, path, args)
            pts = loaded.grid
            try:
                planes = [("least squares", fit_plane(pts, "lstsq")),
                          ("eigenvalue", fit_plane(pts, "eigen"))]
            except ValueError as exc:
                raise _Failure(f"{path}: {exc}") from exc
        except _Failure as exc:
            failed += 1
            print(f"miem: error: {exc}", file=sys.stderr)
            continue
        planes.append(("MIEM", result.plane))
        n_abn = result.counts()["ABNORMAL"]
        if n_scan:
            print()
        print(f"{path.name}: {loaded.data.n_finite:,} finite points, {n_abn:,} ABNORMAL "
              f"removed by MIEM ({result.iterations} passes)")
        print("plane n . p + d = 0, |n| = 1, n_z > 0; rms = RMS orthogonal distance; tilt = "
              "angle to the MIEM normal")
        ref = result.plane
        d_col, rms_col = f"d ({loaded.units})", f"rms ({loaded.units})"
        hdr = (f"{'method':14s} {'n_x':>11s} {'n_y':>11s} {'n_z':>11s} {d_col:>13s} "
               f"{rms_col:>13s} {'points':>10s} {'tilt (deg)':>11s}")
        print(hdr)
        print("-" * len(hdr))
        for name, pl in planes:
            if pl is None:
                print(f"{name:14s} {'(no plane: too few or degenerate points)':>60s}")
                continue
            tilt = math.nan
            if ref is not None:
                c = float(np.clip(abs(np.dot(pl.normal, ref.normal)), -1.0, 1.0))
                tilt = math.degrees(math.acos(c))
            n = pl.normal
            print(f"{name:14s} {n[0]:+11.6f} {n[1]:+11.6f} {n[2]:+11.6f} {pl.d:+13.6f} "
                  f"{pl.rms:13.6g} {pl.n_points:10,d} {tilt:11.4g}")
    return 1 if failed else 0


# ---------------------------------------------------------------------------------------------
# simulate


def _parse_defects(text: str) -> dict[str, int]:
    if text.strip().lower() in ("", "none"):
        return {}
    out: dict[str, int] = {}
    for item in text.split(","):
        kind, sep, count = item.partition("=")
        kind = kind.strip()
        try:
            n = int(count) if sep else 1
        except ValueError:
            raise ValueError(f"--defects: bad count in {item!r} (expected KIND=N)") from None
        out[kind] = out.get(kind, 0) + n
    return out


def _cmd_simulate(args: argparse.Namespace) -> int:
    from . import simulate as sim

    out = Path(args.output)
    try:
        mio.format_from_path(out)
        if args.kind == "paper":
            scan = sim.paper_scan(step=0.5 if args.step is None else args.step,
                                  noise=args.noise, seed=args.seed, dropout=args.dropout)
        else:
            scan = sim.make_scan(shape=tuple(args.shape),
                                 step=0.3 if args.step is None else args.step,
                                 surface=args.surface, noise=args.noise,
                                 defects=_parse_defects(args.defects), dropout=args.dropout,
                                 seed=args.seed, origin=tuple(args.origin))
        enc = args.encoding
        if out.suffix.lower() == ".ply" and enc == "binary_compressed":
            enc = "binary"
        mio.write(out, scan.points, {"truth": scan.truth}, encoding=enc)
    except (OSError, ValueError, ImportError) as exc:
        print(f"miem: error: {exc}", file=sys.stderr)
        return 1
    h, w = scan.shape
    kinds: dict[str, int] = {}
    for d in scan.defects:
        kinds[d.kind] = kinds.get(d.kind, 0) + 1
    what = ", ".join(f"{n} {k}" for k, n in kinds.items()) or "none"
    print(f"wrote {out}: {scan.surface} surface, {h} x {w} grid ({h * w:,} points, step "
          f"{scan.step:g} mm), injected defects: {what}; ground truth in field 'truth' "
          f"({int((scan.truth == 1).sum())} defect points, {int((scan.truth == 2).sum())} "
          f"edge, {int((scan.truth == 3).sum())} dropouts)")
    return 0


# ---------------------------------------------------------------------------------------------
# plot


def _cmd_plot(args: argparse.Namespace) -> int:
    from ._plot import plot_scan

    path = Path(args.scan)
    out = Path(args.output) if args.output else Path(path.stem + ".png")
    if _is_same_file(out, path):
        print(f"miem: error: refusing to overwrite the input {path}", file=sys.stderr)
        return 2
    kwargs = _kwargs_or_exit(args)
    if kwargs is None:
        return 2
    progress = _Progress(3, enabled=True)
    try:
        progress.show(0, f"reading {path.name}")
        loaded = _load(path, args)
        progress.show(1, f"detecting on {loaded.shape_text}")
        result = _detect(loaded, kwargs, path, args)
        progress.show(2, f"drawing {out.name}")
        plot_scan(loaded.grid, result, out, title=args.title or path.name, units=loaded.units,
                  view=args.view, max_labels=args.max_labels, size=tuple(args.size),
                  dpi=args.dpi)
    except _Failure as exc:
        progress.close()
        print(f"miem: error: {exc}", file=sys.stderr)
        return 1
    except (OSError, ValueError, ImportError) as exc:
        progress.close()
        print(f"miem: error: {path}: {exc}", file=sys.stderr)
        return 1
    progress.close()
    print(f"wrote {out} ({args.size[0] * args.dpi:.0f} x {args.size[1] * args.dpi:.0f} px): "
          f"{len(result.defects):,} defects, {result.counts()['ABNORMAL']:,} ABNORMAL points")
    return 0


# ---------------------------------------------------------------------------------------------


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``miem`` command line.

    Parameters
    ----------
    argv : sequence of str, optional
        Arguments without the program name (default: ``sys.argv[1:]``).

    Returns
    -------
    int
        Exit status: 0 success, 1 some input failed, 2 usage error.
    """
    parser = _build_parser()
    args = parser.parse_args(argv)
    try:
        with _sigterm_as_interrupt():
            return int(args.func(args))
    except _Terminated:
        print("miem: terminated", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print("miem: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 1


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that every ``finally`` and the writers' temporary-file
    cleanup run (a half-written output is removed, a good one is never replaced)."""


@contextlib.contextmanager
def _sigterm_as_interrupt():
    """Turn SIGTERM into :class:`_Terminated` while the command runs (main thread only, and only
    when nobody else installed a handler), then restore the previous handler."""
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL):
        yield
        return

    def handler(signum, frame):
        raise _Terminated()

    signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
