"""``miem compare SCAN REFERENCE``: register a scan onto a golden sample or a CAD model, write
the deviation cloud, the defect reports, the transform and a deviation colour map, and print a
summary (self-contained: cli.py only adds the parser)."""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from . import io as mio
from .cli import _finite_float as _float  # one parser for finite numbers

__all__ = ["add_parser"]


def add_parser(sub: Any) -> None:
    """Add the ``compare`` subcommand to the ``miem`` subparsers."""
    p = sub.add_parser(
        "compare", formatter_class=argparse.RawDescriptionHelpFormatter,
        help="deviation from a golden sample or CAD model: registration, labels, defects",
        description="Register SCAN onto REFERENCE (a golden sample's scan, or a mesh: STL, OBJ, "
                    "OFF, PLY with faces), measure each point's signed distance from the "
                    "reference surface along its outward normal, label it (0 within tolerance, "
                    "1 excess material, 2 missing material, 3 not covered), group the "
                    "out-of-tolerance points into defects and compare them with MIEM's own. "
                    "Writes into the output directory:\n"
                    "  NAME.deviation.EXT      the scan's points with fields deviation, "
                    "compare_label\n"
                    "  NAME.compare.json       transform, fit, counts, defects, agreement\n"
                    "  NAME.compare.csv        the defects, one row each\n"
                    "  NAME.transform.txt      the 4 x 4 transform scan -> reference (for "
                    "--init-transform)\n"
                    "  NAME.deviation.png      deviation colour map (needs matplotlib)\n"
                    "Registration needs pip install \"miem[compare]\".",
    )
    p.add_argument("scan", metavar="SCAN", help="scan file")
    p.add_argument("reference", metavar="REFERENCE", help="reference scan or mesh file")
    p.add_argument("-o", "--out-dir", default=".", metavar="DIR",
                   help="output directory (default: the current directory)")
    p.add_argument("--tolerance", type=_float, default=0.2, metavar="LENGTH",
                   help="|deviation| above this is out of tolerance (default: 0.2)")
    p.add_argument("--dont-care", type=_float, default=0.0, metavar="LENGTH",
                   help="don't-care band: a group is a defect only when its peak exceeds "
                        "tolerance + this (default: 0)")
    p.add_argument("--init-transform", metavar="FILE",
                   help="rough pose, 4 x 4 (text or .npy), scan -> reference; default: found "
                        "automatically (FPFH + RANSAC)")
    p.add_argument("--no-register", action="store_true",
                   help="use --init-transform (or the identity) as is, without ICP")
    from .registration import DEFAULT_METHOD, LIBRARIES, METHODS  # noqa: PLC0415

    p.add_argument("--library", choices=["auto", *LIBRARIES], default="auto",
                   help=f"fine-registration library (default: auto, the first installed of "
                        f"{', '.join(LIBRARIES)})")
    p.add_argument("--method", choices=list(METHODS), default=DEFAULT_METHOD,
                   help=f"fine ICP variant (default: {DEFAULT_METHOD})")
    p.add_argument("--coverage", type=_float, metavar="LENGTH",
                   help="points farther than this from the reference are not covered "
                        "(default: max(10 x tolerance, 10 x reference spacing))")
    p.add_argument("--preset", metavar="NAME",
                   help="miem.detect preset for the agreement with MIEM (default: detect's)")
    p.add_argument("--no-agreement", action="store_true", help="do not run MIEM")
    p.add_argument("--no-plot", action="store_true", help="do not draw the PNG")
    p.add_argument("--seed", type=int, default=0, help="RANSAC seed (default: 0)")
    p.add_argument("--units", default="mm", metavar="NAME",
                   help="name of the length unit, for printing only (default: mm)")
    p.set_defaults(func=_cmd_compare)


class _Error(Exception):
    pass


def _read_transform(path: str) -> np.ndarray:
    try:
        t = np.load(path) if path.endswith(".npy") else np.loadtxt(
            path, delimiter="," if path.endswith(".csv") else None)
    except (OSError, ValueError) as exc:
        raise _Error(f"--init-transform {path}: cannot read a 4 x 4 matrix ({exc})") from None
    if np.shape(t) != (4, 4):
        raise _Error(f"--init-transform {path}: expected a 4 x 4 matrix, got shape "
                     f"{np.shape(t)}")
    return np.asarray(t, dtype=np.float64)


def _scan(path: Path) -> tuple[Any, np.ndarray, np.ndarray | None]:
    """(data, points for the comparison, index: file point -> flat grid cell, or None)."""
    try:
        data = mio.read(path)
    except (OSError, ValueError, ImportError) as exc:
        raise _Error(str(exc)) from None
    if data.organized:
        return data, data.points, None
    try:  # exports on scan lines become a grid (MIEM's organized detector), as for detect
        grid, index, _, _ = mio._rebuild_grid(data.points)
        return data, grid, index
    except ValueError:
        return data, data.points, None


def _jf(v: float) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def _jv(v: Any) -> list:
    return [_jf(x) for x in np.asarray(v, dtype=np.float64).ravel()]


def _cmd_compare(args: argparse.Namespace) -> int:
    from . import __version__, compare  # noqa: PLC0415

    scan_path, ref_path = Path(args.scan), Path(args.reference)
    out_dir = Path(args.out_dir)
    stem = scan_path.name[: -len(scan_path.suffix)] if scan_path.suffix else scan_path.name
    try:
        init = _read_transform(args.init_transform) if args.init_transform else None
        out_dir.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        data, pts, index = _scan(scan_path)
        detection: Any = None
        if not args.no_agreement:
            from . import detect  # noqa: PLC0415

            try:
                detection = detect(pts) if args.preset is None else detect(pts,
                                                                            preset=args.preset)
            except ValueError as exc:
                raise _Error(f"{scan_path}: MIEM detection: {exc}") from None
        res = compare(pts, str(ref_path), tolerance=args.tolerance, dont_care=args.dont_care,
                      init_transform=init, register_scan=not args.no_register,
                      library=args.library, method=args.method, coverage=args.coverage,
                      detection=detection, seed=args.seed)
        seconds = time.perf_counter() - t0
    except _Error as exc:
        print(f"miem: error: {exc}", file=sys.stderr)
        return 1
    except ImportError as exc:
        print(f"miem: error: {exc}", file=sys.stderr)
        return 1
    except (OSError, ValueError) as exc:
        print(f"miem: error: {scan_path} vs {ref_path}: {exc}", file=sys.stderr)
        return 1

    # Map grid cells back to the file's points.
    n_file = int(np.prod(data.points.shape[:-1]))
    dev = np.asarray(res.deviation).reshape(-1)
    lab = np.asarray(res.labels).reshape(-1)
    if index is not None:
        ok = index >= 0
        fdev = np.full(n_file, np.nan)
        flab = np.full(n_file, 3, dtype=np.uint8)
        fdev[ok], flab[ok] = dev[index[ok]], lab[index[ok]]
        inverse = np.full(dev.size, -1, dtype=np.int64)
        inverse[index[ok]] = np.flatnonzero(ok)
    else:
        fdev, flab, inverse = dev, lab, None
    flat = np.asarray(pts).reshape(-1, 3)
    rows = []
    for d in res.defects:
        cells = np.asarray(d.indices)
        k = int(np.argmax(np.abs(dev[cells])))
        idx = cells if inverse is None else inverse[cells]
        rows.append({"id": int(d.id), "kind": "excess" if d.kind == "protrusion" else "missing",
                     "count": int(d.count), "peak_deviation": _jf(d.peak_height),
                     "mean_deviation": _jf(d.mean_height), "extent": _jf(d.extent),
                     "centroid": _jv(d.centroid), "normal": _jv(d.normal),
                     "peak_point": _jv(flat[cells[k]]),
                     "indices": [int(i) for i in np.sort(idx)]})
    reg = res.registration
    ag = res.agreement
    from .comparison import DeviationLabel  # noqa: PLC0415

    per = np.bincount(flab, minlength=4)
    counts = {lab.name: int(per[lab]) for lab in DeviationLabel}  # the file's points
    doc = {
        "miem_version": __version__, "scan": str(scan_path), "reference": str(ref_path),
        "points": n_file, "transform": [_jv(r) for r in res.transform],
        "registration": None if reg is None else {
            "coarse": reg.coarse, "library": reg.library, "method": reg.method,
            "rmse": _jf(reg.rmse), "inlier_fraction": _jf(reg.inlier_fraction),
            "inlier_distance": _jf(reg.inlier_distance), "voxel": _jf(reg.voxel),
            "seconds": {k: round(v, 3) for k, v in reg.seconds.items()}},
        "parameters": {k: (_jf(v) if isinstance(v, float) else v) for k, v in res.params.items()},
        "counts": counts,
        "agreement": None if ag is None else {
            "both": [[c, list(m)] for c, m in ag.both], "compare_only": list(ag.compare_only),
            "miem_only": list(ag.miem_only), "miem_not_covered": list(ag.miem_not_covered),
            "points": ag.points},
        "seconds": round(seconds, 3), "defects": rows,
    }
    cloud_fmt = data.format if mio.FORMATS[data.format]["write"] else "pcd"
    cloud = out_dir / f"{stem}.deviation{mio.FORMATS[cloud_fmt]['suffixes'][0]}"
    json_path = out_dir / f"{stem}.compare.json"
    csv_path = out_dir / f"{stem}.compare.csv"
    tf_path = out_dir / f"{stem}.transform.txt"
    png = out_dir / f"{stem}.deviation.png"
    for out in (cloud, json_path, csv_path, tf_path, png):
        for src in (scan_path, ref_path):
            if out.exists() and src.exists() and out.resolve() == src.resolve():
                print(f"miem: error: refusing to overwrite the input {src}", file=sys.stderr)
                return 2
    try:
        fields = {k: v for k, v in data.fields.items() if k not in ("deviation",
                                                                    "compare_label")}
        fields.update(deviation=fdev.reshape(data.points.shape[:-1]),
                      compare_label=flab.reshape(data.points.shape[:-1]))
        mio.write(cloud, data.points, fields, format=cloud_fmt)
        with mio._atomic(json_path) as tmp:
            tmp.write_text(json.dumps(doc, indent=1, allow_nan=False) + "\n", encoding="utf-8")
        with mio._atomic(csv_path) as tmp, open(tmp, "w", encoding="utf-8", newline="") as fh:
            w = csv.writer(fh, lineterminator="\n")
            w.writerow(["id", "kind", "count", "peak_deviation", "mean_deviation", "extent",
                        "centroid_x", "centroid_y", "centroid_z", "normal_x", "normal_y",
                        "normal_z", "peak_x", "peak_y", "peak_z"])
            for r in rows:
                w.writerow([r["id"], r["kind"], r["count"]] + [
                    "nan" if v is None else f"{v:.10g}" for v in (
                        r["peak_deviation"], r["mean_deviation"], r["extent"], *r["centroid"],
                        *r["normal"], *r["peak_point"])])
        with mio._atomic(tf_path) as tmp:
            np.savetxt(tmp, res.transform, fmt="%.12g")
        drawn = False
        if not args.no_plot:
            try:
                from ._plot_compare import plot_deviation  # noqa: PLC0415

                plot_deviation(flat, dev, res, counts, png, title=f"{scan_path.name} vs "
                               f"{ref_path.name}", units=args.units)
                drawn = True
            except ImportError as exc:
                print(f"miem: note: no plot: {exc}", file=sys.stderr)
    except (OSError, ValueError) as exc:
        print(f"miem: error: cannot write the outputs: {exc}", file=sys.stderr)
        return 1
    _print(args, scan_path, ref_path, n_file, res, counts, rows, seconds)
    outs = [cloud, json_path, csv_path, tf_path] + ([png] if drawn else [])
    print("wrote " + ", ".join(str(o) for o in outs))
    return 0


def _print(args: argparse.Namespace, scan_path: Path, ref_path: Path, n: int, res: Any,
           c: dict, rows: list, seconds: float) -> None:
    u = args.units
    p = res.params
    print(f"{scan_path.name} ({n:,} points) vs {ref_path.name} ({p['reference_kind']}, "
          f"{p['reference_points']:,} points)")
    reg = res.registration
    if reg is not None:
        print(f"registration: {reg.coarse} + {reg.library} {reg.method} in "
              f"{sum(reg.seconds.values()):.1f} s; rmse {reg.rmse:.4f} {u}, "
              f"{100 * reg.inlier_fraction:.1f} % of the scan within {reg.inlier_distance:.3g} "
              f"{u} of the reference")
    else:
        print("registration: none (the transform as given)")
    print("transform scan -> reference:")
    for r in res.transform:
        print("  " + " ".join(f"{v:+12.6f}" for v in r))
    print(f"tolerance {p['tolerance']:g} {u}, don't-care band {p['dont_care']:g} {u}, "
          f"coverage {p['coverage']:.3g} {u}")
    print(f"points: {c['WITHIN']:,} within tolerance, {c['EXCESS']:,} excess, "
          f"{c['MISSING']:,} missing, {c['NOT_COVERED']:,} not covered")
    n_ex = sum(r["kind"] == "excess" for r in rows)
    print(f"defects: {len(rows):,} ({n_ex:,} excess, {len(rows) - n_ex:,} missing)")
    if rows:
        print(f"  {'id':>4} {'kind':<8} {'points':>7} {'peak (' + u + ')':>10} "
              f"{'extent':>8}  centroid")
        for r in rows[:10]:
            cx = " ".join(f"{v:.3f}" for v in r["centroid"])
            print(f"  {r['id']:>4} {r['kind']:<8} {r['count']:>7,} {r['peak_deviation']:>+10.3f} "
                  f"{r['extent']:>8.3f}  {cx}")
    clipped = _at_coverage(rows, p["coverage"])
    if clipped:
        what = "defects peak" if clipped > 1 else "defect peaks"
        print(f"miem: note: {clipped:,} {what} within "
              f"{100 * (1 - _CLIPPED):.0f} % of the coverage ({p['coverage']:.3g} {u}): the "
              f"material may stand further out, where no reference point is within reach; "
              f"measure it with a larger --coverage", file=sys.stderr)
    if res.agreement is not None:
        print(f"agreement with MIEM: {res.agreement.summary()}")
    print(f"total {seconds:.1f} s")


#: A defect whose |peak| reaches this fraction of the coverage is probably cut off by it: a
#: point's deviation never exceeds its distance to the reference, at most the coverage.
_CLIPPED = 0.95


def _at_coverage(rows: list, coverage: float) -> int:
    """How many defects peak at the coverage's edge (their true peak may lie beyond it)."""
    return sum(abs(r["peak_deviation"]) >= _CLIPPED * coverage for r in rows)
