"""Grinding-target planning: miem.plan_targets (C++ core) against the NumPy reference (issue 12).

Script: ``python bench/bench_targets.py [--repeats R]`` prints a markdown table and writes it to
``bench/results_targets.md`` (``run_results.py`` appends the fragment to RESULTS.md).

Inputs: the real scan ``../shared/data/real/second_source.pcd`` (when present) and seeded
synthetic grids (``common.scan_grid``) with a growing number of defects. Every contender gets the
same detection result, transform and options (the defaults a user gets, protrusions and pits,
tool radius 1 mm, a start point): the table checks that both return the same targets before
timing them. Detection time is shown for scale: planning is a small step after it.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import best_of, cpu_name, scan_grid  # noqa: E402

HERE = Path(__file__).resolve().parent
OUT = HERE / "results_targets.md"
README = HERE.parent / "README.md"
MARKERS = ("<!-- targets-results:start -->", "<!-- targets-results:end -->")
REAL = HERE.parents[1] / "shared" / "data" / "real" / "second_source.pcd"


def _transform() -> np.ndarray:
    a = np.radians(30.0)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    T[:3, 3] = [850.0, -120.0, 310.0]
    return T


def cases():
    from miem import io as mio

    if REAL.exists():
        data = mio.read(REAL)
        grid = mio.grid_from_scanlines(data.points)
        yield "second_source.pcd (real)", grid, "recommended"
    for h, n in ((300, 100), (600, 400), (1000, 1200)):
        yield f"synthetic {h}x{h}, {n} injected", scan_grid(h, h, seed=1, n_defects=n), "paper"


def run(repeats: int) -> tuple:
    import miem
    from miem import reference_targets as ref

    T = _transform()
    opts = dict(kinds=("protrusion", "pit"))
    rows = []
    for name, grid, preset in cases():
        t0 = time.perf_counter()
        res = miem.detect(grid, preset=preset)
        t_detect = time.perf_counter() - t0
        start = T[:3, 3] + [0.0, 0.0, 200.0]
        tool = miem.Tool(radius=1.0)

        def core():
            return miem.plan_targets(res, grid, T, tool=tool, start=start, **opts)

        def numpy_ref():
            return ref.plan_targets(grid, res.labels, res.height, res.defects, T,
                                    tool_radius=1.0, start=start, **opts)

        a, b = core(), numpy_ref()
        same = ([t.defect_ids for t in a.targets] == [o["defect_ids"] for o in b["targets"]]
                and np.allclose([t.position for t in a.targets],
                                [o["position"] for o in b["targets"]], atol=1e-8))
        if not same:
            raise SystemExit(f"{name}: core and reference disagree; not timing")
        t_core = best_of(core, repeats)
        t_ref = best_of(numpy_ref, max(1, repeats // 3))
        rows.append((name, len(res.defects), len(a.targets), a.path_length, t_detect, t_core,
                     t_ref))
    lines = [
        "## Grinding targets (plan_targets)",
        "",
        f"`bench/bench_targets.py`, best of {repeats} (reference: of {max(1, repeats // 3)}), "
        f"{cpu_name()}. Same detection, transform and options for both; identical targets "
        "checked before timing. Protrusions and pits, tool radius 1 mm, path from a start point.",
        "",
        "| scan | defects | targets | path (mm) | detect (s) | miem plan (ms) | NumPy reference "
        "(ms) | reference / miem |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, nd, nt, length, td, tc, tr in rows:
        lines.append(f"| {name} | {nd:,} | {nt:,} | {length:,.1f} | {td:.2f} | {tc * 1e3:.2f} | "
                     f"{tr * 1e3:,.1f} | {tr / tc:,.0f}x |")
    real = [r for r in rows if "real" in r[0]]
    big = max(rows, key=lambda r: r[1])
    parts = [f"{r[5] * 1e3:.0f} ms for the {r[1]:,} defects of {r[0].split()[0]} (detection "
             f"{r[4]:.2f} s)" for r in real]
    parts.append(f"{big[5] * 1e3:.0f} ms for {big[1]:,} defects on a {big[0].split()[1].rstrip(',')} grid")
    ratios = [r[6] / r[5] for r in rows]
    summary = (f"`plan_targets`: {'; '.join(parts)}; {min(ratios):,.0f}-{max(ratios):,.0f}x "
               "faster than the NumPy reference.")
    return "\n".join(lines) + "\n", summary


def _write_readme(summary: str) -> None:
    if not README.exists():
        return
    text = README.read_text(encoding="utf-8")
    if MARKERS[0] not in text or MARKERS[1] not in text:
        return
    head, rest = text.split(MARKERS[0], 1)
    _, tail = rest.split(MARKERS[1], 1)
    README.write_text(f"{head}{MARKERS[0]}\n{summary}\n{MARKERS[1]}{tail}", encoding="utf-8")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    text, summary = run(args.repeats)
    print(text)
    print(summary)
    OUT.write_text(text, encoding="utf-8")
    _write_readme(summary)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
