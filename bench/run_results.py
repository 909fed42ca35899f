"""Measure the core against the NumPy reference and write bench/RESULTS.md.

Usage: ``python bench/run_results.py [--quick] [--all]``. Every ratio is measured in this one run
on this machine (best of several repeats; the machine is shared, so read ratios, not seconds).
The README's results table (between the ``results:start`` / ``results:end`` markers) is rewritten
from the same numbers. Fragments written by other benchmark scripts (``results_*.md`` beside this
file) are included as they are: ``results_speed.md`` (bench_speed.py: the default detector against
Open3D and PCL, size sweep, memory, threads, where the time goes) first, the others after.
``--all`` first reruns those scripts (bench_speed.py, run_cpp.py, bench_unorganized.py,
bench_edges.py, bench_rebuild.py), so one
command regenerates every table.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import os
import platform
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

import miem  # noqa: E402
from miem import reference as ref  # noqa: E402

from common import best_of, cpu_name, plane_points, scan_grid  # noqa: E402


def bench_fit(n: int, repeats: int) -> list[dict]:
    pts = plane_points(n)
    a, b = miem.fit_plane(pts), ref.fit_plane(pts)
    np.testing.assert_allclose(a.normal, b.normal, atol=1e-12)  # parity before timing
    t_ref = best_of(lambda: ref.fit_plane(pts), repeats)
    t_sum = best_of(lambda: pts.sum(axis=0), repeats)  # one NumPy read pass: a bandwidth yardstick
    rows = []
    for nt in (1, 2):
        t = best_of(lambda: miem.fit_plane(pts, num_threads=nt), repeats)
        rows.append({"what": f"fit_plane, {n / 1e6:.0f}M points, {nt} thread(s)", "core": t,
                     "ref": t_ref, "gbs": pts.nbytes / t / 1e9,
                     "sum_gbs": pts.nbytes / t_sum / 1e9})
    return rows


def bench_detect(sides_ref: list[int], sides_core: list[int], repeats: int) -> list[dict]:
    rows = []
    for side in sorted(set(sides_ref) | set(sides_core)):
        grid = scan_grid(side, side)
        n = side * side
        t_ref = None
        if side in sides_ref:
            oracle = ref.detect(grid)
            np.testing.assert_array_equal(miem.detect(grid).labels, oracle.labels)
            t_ref = best_of(lambda: ref.detect(grid), 1 if side > 256 else repeats)
        for label, kw in (("1 thread", {"num_threads": 1}), ("2 threads", {"num_threads": 2}),
                          ("1 thread, heights='abnormal'",
                           {"num_threads": 1, "heights": "abnormal"})):
            t = best_of(lambda: miem.detect(grid, **kw), repeats)
            rows.append({"what": f"detect {side}x{side}, {label}", "core": t, "ref": t_ref,
                         "mpts": n / t / 1e6})
    return rows


def default_grid_settings() -> str:
    """The organized detector's default settings, read from the preset (not written by hand)."""
    p = miem.PRESETS[miem.DEFAULT_PRESET]
    fields = {**vars(p.angle), **vars(p.grid)}
    return ", ".join(f"{k} {v!r}" for k, v in fields.items() if v is not None)


def fmt_ratio(ref_t, core_t) -> str:
    return "n/a" if ref_t is None else f"{ref_t / core_t:.1f}x"


def paper_demo() -> str:
    out = subprocess.run([sys.executable, "-m", "miem.simulate", "paper"], capture_output=True,
                         text=True, check=False)
    return out.stdout.rstrip()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller sizes, fewer repeats")
    ap.add_argument("--all", action="store_true", help="rerun the fragment scripts first")
    args = ap.parse_args(argv)
    if args.all:
        quick = {"bench_speed.py": ["--quick"], "run_cpp.py": ["--quick"],
                 "bench_unorganized.py": ["--n", "100000"], "bench_edges.py": [],
                 "bench_rebuild.py": ["--quick"]}
        for script, small in quick.items():
            cmd = [sys.executable, str(HERE / script)] + (small if args.quick else [])
            subprocess.run(cmd, check=True)
    repeats = 2 if args.quick else 3
    fit_n = 1_000_000 if args.quick else 10_000_000
    sides_ref = [128, 256] if args.quick else [256, 512]
    sides_core = [512] if args.quick else [1024, 2048]

    fit_rows = bench_fit(fit_n, repeats)
    det_rows = bench_detect(sides_ref, sides_core, repeats)

    lines = [
        "# Benchmark results",
        "",
        f"Written by `python bench/run_results.py` on {_dt.date.today().isoformat()}: "
        f"miem {miem.__version__}, NumPy {np.__version__}, Python {platform.python_version()}, "
        f"{cpu_name()}, {os.cpu_count()} cores (a shared, noisy machine: compare ratios, "
        "not seconds). Best of "
        f"{repeats} runs. The reference is `miem.reference` (vectorised NumPy, written from "
        "METHOD.md); parity (equal labels / normals) is checked before timing.",
        "",
        *([(HERE / "results_speed.md").read_text().rstrip(), ""]
          if (HERE / "results_speed.md").exists() else []),
        "## Plane fit (eigenvalue method)",
        "",
        "| case | core | reference | speed-up | core GB/s | NumPy `sum` GB/s |",
        "|---|---|---|---|---|---|",
    ]
    for r in fit_rows:
        lines.append(f"| {r['what']} | {r['core'] * 1e3:.1f} ms | {r['ref'] * 1e3:.0f} ms | "
                     f"{fmt_ratio(r['ref'], r['core'])} | {r['gbs']:.1f} | {r['sum_gbs']:.1f} |")
    lines += [
        "",
        "`NumPy sum` is one read pass over the same array: the memory-bandwidth yardstick.",
        "",
        f"## Organized detection (the default preset, `{miem.DEFAULT_PRESET}`: "
        f"{default_grid_settings()})",
        "",
        "| case | core | reference | speed-up | core Mpoints/s |",
        "|---|---|---|---|---|",
    ]
    for r in det_rows:
        ref_s = "-" if r["ref"] is None else f"{r['ref']:.2f} s"
        lines.append(f"| {r['what']} | {r['core'] * 1e3:.1f} ms | {ref_s} | "
                     f"{fmt_ratio(r['ref'], r['core'])} | {r['mpts']:.1f} |")
    lines += [
        "",
        "The reference is timed only up to "
        f"{max(sides_ref)}x{max(sides_ref)} (it needs minutes beyond). `heights='abnormal'` "
        "computes the local-plane height only at ABNORMAL points (the grinding depth); the "
        "default computes it at every point.",
        "",
        "## The paper's simulation (`python -m miem.simulate paper`)",
        "",
        "```",
        paper_demo(),
        "```",
    ]
    for frag in sorted(HERE.glob("results_*.md")):
        if frag.name != "results_speed.md":
            lines += ["", frag.read_text().rstrip()]
    (HERE / "RESULTS.md").write_text("\n".join(lines) + "\n")

    # README table
    readme = ROOT / "README.md"
    if readme.exists():
        big = max(sides_core)
        pick = {r["what"]: r for r in det_rows}
        cmp_side = max(sides_ref)
        table = [
            "| what | miem | vs NumPy reference |",
            "|---|---|---|",
            f"| `fit_plane`, {fit_n / 1e6:.0f}M points, 1 thread | "
            f"{fit_rows[0]['core'] * 1e3:.0f} ms ({fit_rows[0]['gbs']:.1f} GB/s) | "
            f"{fmt_ratio(fit_rows[0]['ref'], fit_rows[0]['core'])} |",
        ]
        for label in ("1 thread", "2 threads", "1 thread, heights='abnormal'"):
            r = pick[f"detect {big}x{big}, {label}"]
            c = pick[f"detect {cmp_side}x{cmp_side}, {label}"]
            table.append(f"| `detect` {big}x{big}, {label} | {r['mpts']:.1f} Mpoints/s | "
                         f"{fmt_ratio(c['ref'], c['core'])} (at {cmp_side}x{cmp_side}) |")
        text = readme.read_text()
        new = re.sub(r"(<!-- results:start -->\n).*?(<!-- results:end -->)",
                     lambda m: m.group(1) + "\n".join(table) + "\n" + m.group(2), text,
                     flags=re.S)
        readme.write_text(new)
    print((HERE / "RESULTS.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
