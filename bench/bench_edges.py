"""Speed cost of the edge test and of min_step="auto" (the default since #10); writes
bench/results_edges.md (included in bench/RESULTS.md by run_results.py).

    python bench/bench_edges.py

One ``miem.detect`` call per setting, best of 3, all threads, measured in this one run; wall and
CPU time (the machine may be shared: read the ratios). ``before``: the default without the edge
test and without ``min_step="auto"`` (``min_step=None, edge_tolerance=None``); ``+auto``: with
``min_step="auto"`` only; ``default``: both (what a user gets). The NumPy reference
(``miem.reference.detect``, the oracle) runs the default on the small scene for the core /
reference ratio. Grids: the real burred scan (when ``../shared/data/real`` is present) and a
synthetic wall scene of the accuracy suite.
"""

from __future__ import annotations

import platform
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE / "accuracy"))

import miem  # noqa: E402
from miem import reference as ref  # noqa: E402

from common import cpu_name  # noqa: E402

OUT = HERE / "results_edges.md"
SETTINGS = {
    "before": {"min_step": None, "edge_tolerance": None},
    "+auto": {"edge_tolerance": None},
    "default": {},
}


def timed(fn, repeats: int = 3) -> tuple[float, float]:
    """(best wall s, CPU s of that call) over ``repeats`` calls."""
    best = (np.inf, np.inf)
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        w, c = time.perf_counter() - w0, time.process_time() - c0
        best = min(best, (w, c))
    return best


def grids() -> list[tuple[str, np.ndarray]]:
    import real_truth as rt
    from suite import scenes

    out = []
    if rt.available():
        out.append(("real scan 426 x 724", rt.truth().grid))
    sc = next(s for s in scenes("test", real=False) if s.spec.group == "edge_wall")
    out.append((f"edge wall scene {sc.shape[0]} x {sc.shape[1]}", np.asarray(sc.points)))
    return out


def main() -> int:
    rows = []
    small = None
    for name, g in grids():
        t = {k: timed(lambda kw=kw: miem.detect(g, **kw)) for k, kw in SETTINGS.items()}
        rows.append((name, t))
        small = g
    t_ref = timed(lambda: ref.detect(small), 1)
    t_core = timed(lambda: miem.detect(small, num_threads=1))
    lines = [
        "## Edge test and min_step='auto': speed cost (`bench/bench_edges.py`)",
        "",
        f"Written by `python bench/bench_edges.py` on {cpu_name()} ({platform.machine()}), "
        f"miem {miem.__version__}: one `miem.detect` call, best of 3, all threads, wall ms "
        "(CPU ms). `before`: the default without the edge test and without `min_step='auto'`; "
        "`+auto`: with `min_step='auto'`; `default`: both (the recommended preset).",
        "",
        "| grid | before | +auto | default | default / before (wall) | default / before (CPU) |",
        "|---|---|---|---|---|---|",
    ]
    for name, t in rows:
        cells = " | ".join(f"{1e3 * t[k][0]:.0f} ({1e3 * t[k][1]:.0f})" for k in SETTINGS)
        lines.append(f"| {name} | {cells} | {t['default'][0] / t['before'][0]:.1f}x | "
                     f"{t['default'][1] / t['before'][1]:.1f}x |")
    lines += [
        "",
        f"NumPy reference (`miem.reference.detect`, the default) on the {rows[-1][0]}: "
        f"{1e3 * t_ref[0]:.0f} ms; the core on one thread {1e3 * t_core[0]:.1f} ms "
        f"(core {t_ref[0] / t_core[0]:.0f}x faster). Open3D and PCL have no counterpart of the "
        "edge test. Accuracy: `bench/accuracy/results_edges.md`.",
    ]
    OUT.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
