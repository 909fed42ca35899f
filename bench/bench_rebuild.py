"""Unorganized exports read as grids: the cost of ``miem.io.grid_from_scanlines`` (issue 11).

Script: ``python bench/bench_rebuild.py [--repeats R] [--quick]`` prints a markdown table and
writes it to ``bench/results_rebuild.md`` (``run_results.py`` appends the fragment to RESULTS.md).

What ``miem detect`` does with an ``(N, 3)`` file (``miem.io._rebuild_grid``): a grid from the
points' scan lines in file order, else sorted by line position, else the cloud detector. Timed
for the real scan ``../shared/data/real/second_source.pcd`` (when present) and a seeded synthetic
profiler scan (2000 profiles of 3000 points, 0.05 mm along, profiles 0.1/0.2/1.0 mm apart, 1 %
dropouts), each in file order and shuffled, and a random cloud of the same size (refused: the
time before the cloud detector takes over). Each rebuilt grid is checked equal to the scan's
own grid before timing. For scale: ``miem.detect`` on the grid (defaults, all threads), and on
the real scan the cloud detector on the shuffled points (what the file got before).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import best_of, cpu_name  # noqa: E402

import miem  # noqa: E402
import miem.io as mio  # noqa: E402

HERE = Path(__file__).resolve().parent
OUT = HERE / "results_rebuild.md"
REAL = HERE.parents[1] / "shared" / "data" / "real" / "second_source.pcd"


def profiler_scan(rows: int, cols: int, seed: int = 0) -> np.ndarray:
    """A tilted, wavy sheet scanned in profiles: x = 0.05 mm steps along, y with uneven profile
    spacing, z quantised to 1 um, 1 % dropouts (NaN). float32, as profiler exports are."""
    rng = np.random.default_rng(seed)
    y = np.cumsum(rng.choice([0.1, 0.2, 1.0], size=rows, p=[0.8, 0.15, 0.05]))
    x = np.arange(cols) * 0.05
    xx, yy = np.meshgrid(x, y)
    z = np.round(0.02 * xx + 0.3 * np.sin(yy / 7.0) + rng.normal(0, 0.005, xx.shape), 3)
    g = np.stack([xx, yy, z], axis=-1).astype(np.float32)
    g[rng.random((rows, cols)) < 0.01] = np.nan
    return g


def _finite(grid: np.ndarray) -> np.ndarray:
    flat = grid.reshape(-1, 3)
    return flat[np.isfinite(flat).all(axis=1)]


def cases(quick: bool):
    """(name, grid, points in file order)."""
    if REAL.exists():
        pts = mio.read(REAL).points
        yield "second_source.pcd (real)", mio.grid_from_scanlines(pts), pts
    rows, cols = (400, 600) if quick else (2000, 3000)
    g = profiler_scan(rows, cols)
    yield f"synthetic profiler scan {rows} x {cols}", g, _finite(g)


def measure(repeats: int, quick: bool) -> list[dict]:
    out = []
    for name, grid, pts in cases(quick):
        n = pts.shape[0]
        shuffled = pts[np.random.default_rng(1).permutation(n)]
        t_det = best_of(lambda: miem.detect(grid), max(1, repeats - 1))
        for order, p in (("file order", pts), ("shuffled", shuffled)):
            got, index, taken, _ = mio._rebuild_grid(p)  # check before timing
            np.testing.assert_array_equal(got, grid)
            np.testing.assert_array_equal(got.reshape(-1, 3)[index], p)
            t = best_of(lambda: mio._rebuild_grid(p), repeats)
            row = {"input": name, "points": n, "order": order, "taken": taken, "t": t,
                   "detect": t_det, "cloud": None}
            if order == "shuffled" and n <= 500_000:
                row["cloud"] = best_of(lambda: miem.detect_points(shuffled), 1)
            out.append(row)
        rng = np.random.default_rng(2)
        lo, hi = np.nanmin(pts, axis=0), np.nanmax(pts, axis=0)
        cloud = (lo + (hi - lo) * rng.random((n, 3))).astype(pts.dtype)

        def refuse() -> None:
            try:
                mio._rebuild_grid(cloud)
            except ValueError:
                return
            raise AssertionError("a random cloud was rebuilt into a grid")

        refuse()
        out.append({"input": name, "points": n, "order": "random cloud, same box",
                    "taken": "refused", "t": best_of(refuse, repeats), "detect": t_det,
                    "cloud": None})
    return out


def table(rows: list[dict], repeats: int) -> str:
    lines = [
        "## Unorganized exports read as grids (`miem.io.grid_from_scanlines`)",
        "",
        f"`bench/bench_rebuild.py`, best of {repeats}, {cpu_name()}. What `miem detect` does "
        "with an `(N, 3)` file: a grid from its scan lines in file order, else sorted by line "
        "position (`order=\"line\"`), else (refused) the cloud detector. Every rebuilt grid is "
        "checked equal to the scan's own grid first. `detect` is `miem.detect` on that grid "
        "(defaults, all threads), for scale; `cloud detector` is `miem.detect_points` on the "
        "shuffled points (what such a file got before it was rebuilt).",
        "",
        "| input | points | order | path taken | rebuild (s) | Mpoints/s | detect (s) | "
        "rebuild / detect | cloud detector (s) |",
        "|---|---:|---|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        cloud = "-" if r["cloud"] is None else f"{r['cloud']:.2f}"
        taken = {"file": "grid, file order", "line": "grid, by line position"}.get(
            r["taken"], r["taken"])
        lines.append(f"| {r['input']} | {r['points']:,} | {r['order']} | {taken} | "
                     f"{r['t']:.3f} | {r['points'] / r['t'] / 1e6:.1f} | {r['detect']:.3f} | "
                     f"{r['t'] / r['detect']:.1f}x | {cloud} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="a smaller synthetic scan")
    args = ap.parse_args(argv)
    text = table(measure(args.repeats, args.quick), args.repeats)
    OUT.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
