"""Write the expectation files of the C++ tests from the NumPy reference (``miem.reference``).

Run from anywhere (needs only NumPy; the reference is loaded from its file, so the compiled
extension is not needed):

    python cpp/tests/data/make_expectations.py

Each case is a small organized scan (micrometre-quantised coordinates, so the text is short and
round-trips exactly), the parameters, and what the reference returns for it: labels, flags,
angles, heights, the MIEM plane, the pass count and the defects. ``test_organized.cpp`` reads
them. The files are committed; rerun this script only when the spec or the cases change.
"""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REFERENCE = HERE.parents[2] / "python" / "miem" / "reference.py"


def load_reference():
    spec = importlib.util.spec_from_file_location("miem_reference", REFERENCE)
    mod = importlib.util.module_from_spec(spec)
    assert spec.loader is not None
    sys.modules[spec.name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


def surface(h: int, w: int, dx: float, dy: float, rng: np.random.Generator,
            noise: float = 0.002) -> np.ndarray:
    """A gently curved sheet with scanner noise, z quantised to a micrometre."""
    r, c = np.mgrid[0:h, 0:w]
    x = np.round(c * dx, 3)
    y = np.round(r * dy, 3)
    z = 0.4 * np.exp(-((x - 0.5 * w * dx) ** 2) / 50.0) + 0.01 * y
    z = np.round(z + rng.normal(0.0, noise, z.shape), 3)
    return np.dstack([x, y, z]).astype(np.float64)


def case_spikes(rng):
    g = surface(18, 24, 0.25, 0.3, rng)
    g[4, 5, 2] += 0.8                       # burr tip
    g[9, 15, 2] -= 0.6                      # pit
    g[12:14, 8:10, 2] += 0.5                # 2x2 spatter
    g[15, 20, 2] += 1.2                     # spike near the border
    return g, dict(theta0=75.0, scales=(1,), max_gap=1, min_step=None, min_directions=None,
                   max_iterations=10, window=5, max_reach=32)


def case_dropouts(rng):
    g = surface(18, 24, 0.25, 0.3, rng)
    g[6, 6, 2] += 0.9
    g[6, 7] = np.nan                        # dropout next to the spike
    g[10, :] = np.nan                       # a whole profile lost
    g[13:15, 16:18, 2] += 0.6
    g[rng.random(g.shape[:2]) < 0.03] = np.nan
    g[2, 20] = [g[2, 20, 0], g[2, 20, 1], 5.0]  # dust far above
    return g, dict(theta0=75.0, scales=(1, 2), max_gap=2, min_step=None, min_directions=None,
                   max_iterations=10, window=7, max_reach=32)


def case_edges(rng):
    g = surface(16, 22, 0.25, 0.3, rng)
    g[:, 11, 2] += 0.4                      # a designed ridge across the profiles: EDGE
    g[:, 15:, 2] += 0.7                     # a step: not sharp enough to flag
    g[5, 4, 2] += 0.7
    g[11, 18, 2] -= 0.5
    return g, dict(theta0=75.0, scales=(1,), max_gap=1, min_step=None, min_directions=None,
                   max_iterations=10, window=5, max_reach=32)


def case_min_step(rng):
    g = surface(16, 28, 0.05, 0.3, rng, noise=0.001)
    g[7, 12:14, 2] += 0.4
    g[3, 20, 2] -= 0.3
    g[12, 5, 2] += 0.3
    return g, dict(theta0=75.0, scales=(1,), max_gap=1, min_step=0.2, min_directions=None,
                   max_iterations=10, window=5, max_reach=8)


def case_cascade(rng):
    g = surface(18, 20, 0.25, 0.25, rng, noise=0.0005)
    # A wedge burr: each pass removes its highest cell, which exposes the next one (7 passes
    # to settle); max_iterations=4 cuts it short.
    for i, hgt in enumerate([2.4, 1.8, 1.3, 0.9, 0.6, 0.35]):
        g[8, 5 + i, 2] += hgt
        g[9, 5 + i, 2] += 0.9 * hgt
    # The same wedge across the profiles.
    for i, hgt in enumerate([2.4, 1.8, 1.3, 0.9]):
        g[3 + i, 15, 2] += hgt
        g[3 + i, 16, 2] += 0.9 * hgt
    return g, dict(theta0=75.0, scales=(1,), max_gap=1, min_step=None, min_directions=None,
                   max_iterations=4, window=5, max_reach=32)


def case_float32(rng):
    g = surface(14, 20, 0.25, 0.3, rng).astype(np.float32).astype(np.float64)
    g[5, 9, 2] += np.float32(0.75)
    g[9, 3, 2] -= np.float32(0.5)
    g = g.astype(np.float32).astype(np.float64)
    return g, dict(theta0=60.0, scales=(1, 2), max_gap=1, min_step=None, min_directions=2,
                   max_iterations=10, window=5, max_reach=32)


CASES = {
    "spikes": (case_spikes, "float64"),
    "dropouts": (case_dropouts, "float64"),
    "edges": (case_edges, "float64"),
    "min_step": (case_min_step, "float64"),
    "cascade": (case_cascade, "float64"),
    "float32": (case_float32, "float32"),
}


def num(v: float) -> str:
    """Shortest text that reads back as the same double ('nan' for NaN)."""
    return "nan" if math.isnan(v) else repr(float(v))


def approx(v: float) -> str:
    return "nan" if math.isnan(v) else f"{float(v):.12g}"


def write_case(ref, name: str, make, dtype: str, rng: np.random.Generator) -> Path:
    grid, params = make(rng)
    res = ref.detect(grid, **params)
    h, w, _ = grid.shape
    lines = [
        "miem-expectation 1",
        "# generated by make_expectations.py from miem.reference; do not edit by hand",
        f"name {name}",
        f"dtype {dtype}",
        f"rows {h}",
        f"cols {w}",
        f"theta0 {num(params['theta0'])}",
        "scales " + " ".join([str(len(params["scales"]))] + [str(s) for s in params["scales"]]),
        f"max_gap {params['max_gap']}",
        f"min_step {num(-1.0 if params['min_step'] is None else params['min_step'])}",
        f"max_reach {params['max_reach']}",
        f"min_directions {0 if params['min_directions'] is None else params['min_directions']}",
        f"max_iterations {params['max_iterations']}",
        f"window {params['window']}",
        "grid",
    ]
    for r in range(h):
        lines.append(" ".join(num(v) for v in grid[r].ravel()))
    lines.append("labels")
    lines += ["".join(str(int(v)) for v in res.labels[r]) for r in range(h)]
    lines.append("flags")
    lines += [" ".join(str(int(v)) for v in res.flags[r]) for r in range(h)]
    lines.append("angle")
    lines += [" ".join(approx(v) for v in res.angle[r]) for r in range(h)]
    lines.append("height")
    lines += [" ".join(approx(v) for v in res.height[r]) for r in range(h)]
    lines.append(f"iterations {res.iterations}")
    if res.plane is None:
        lines.append("plane 0")
    else:
        p = res.plane
        lines.append("plane 1 " + " ".join(num(v) for v in (*p.normal, p.d, p.rms)) +
                     f" {p.n_points}")
    lines.append(f"defects {len(res.defects)}")
    for d in res.defects:
        lines.append(f"defect {d.kind} {approx(d.peak_height)} {d.count} " +
                     " ".join(str(int(i)) for i in d.indices))
    lines.append("end")
    path = HERE / f"{name}.txt"
    path.write_text("\n".join(lines) + "\n")
    counts = np.bincount(res.labels.ravel(), minlength=4)
    print(f"{path.name}: {h}x{w}, labels N/A/E/I = {counts.tolist()}, "
          f"{res.iterations} passes, {len(res.defects)} defects")
    return path


def main() -> None:
    ref = load_reference()
    for i, (name, (make, dtype)) in enumerate(CASES.items()):
        write_case(ref, name, make, dtype, np.random.default_rng(1000 + i))


if __name__ == "__main__":
    main()
