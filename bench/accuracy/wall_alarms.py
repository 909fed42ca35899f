"""Why designed wall-edge cells become ABNORMAL: a diagnostic (see wall_alarms.md).

    python bench/accuracy/wall_alarms.py              # tuning split (diagnose here)
    python bench/accuracy/wall_alarms.py test         # test split (to score, never to tune)

For every ``edge_wall`` scene of the split, with the benchmark's ``miem`` setting
(``tuned.json`` over the paper's method, the default's edge stage): the designed-edge cells
(truth EDGE) the detector calls ABNORMAL, whether the angle passes alone already do, and for
each such cell the rays of every direction and scale as pass 1 sees them (SPEC "Neighbour":
every finite cell usable): neighbour offset ``k``, its height above the cell ``dz``, its
horizontal distance ``xy`` and the angle (``*`` = flagged). Writes nothing.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))

import miem  # noqa: E402
from contenders import EDGE_STAGE, miem_kwargs  # noqa: E402
from suite import scenes  # noqa: E402

EDGE = 2  # suite truth class of a designed-edge cell
DIRECTIONS = ((0, 1), (1, 0), (1, 1), (1, -1))


def _neighbour(g: np.ndarray, fin: np.ndarray, r: int, c: int, d: tuple[int, int], s: int,
               side: int, max_gap: int, min_step: float | None, max_reach: int):
    """SPEC "Neighbour" with every finite cell usable: ``(row, col, k)`` or None."""
    h, w = fin.shape
    gaps, k = 0, s
    while True:
        if min_step is not None and k > s + max_gap + max_reach:
            return None
        rr, cc = r + side * k * d[0], c + side * k * d[1]
        if not (0 <= rr < h and 0 <= cc < w):
            return None
        if not fin[rr, cc]:
            gaps += 1
            if gaps > max_gap:
                return None
        elif min_step is None or np.linalg.norm(g[rr, cc] - g[r, c]) >= s * min_step:
            return rr, cc, k
        k += 1


def _ray(g: np.ndarray, r: int, c: int, a: tuple, b: tuple, cos0: float) -> str:
    u, v = g[a[0], a[1]] - g[r, c], g[b[0], b[1]] - g[r, c]
    cs = float(np.clip(u @ v / math.sqrt((u @ u) * (v @ v)), -1.0, 1.0))
    arm = " ".join(f"k{n[2]} dz {w[2]:+.2f} xy {math.hypot(w[0], w[1]):.2f}"
                   for n, w in ((a, u), (b, v)))
    return f"{arm} {math.degrees(math.acos(cs)):5.1f}{'*' if cs >= cos0 else ' '}"


def main() -> int:
    split = sys.argv[1] if len(sys.argv) > 1 else "tune"
    tuned = json.loads((HERE / "tuned.json").read_text())["contenders"]["miem"]["params"]
    total = 0
    for sc in scenes(split, real=False):
        if sc.spec.group != "edge_wall":
            continue
        kw = {**EDGE_STAGE, **miem_kwargs(tuned, sc.step)}
        res = miem.detect(sc.points, preset="paper", **kw)
        angle_only = miem.detect(sc.points, preset="paper",
                                 **{**kw, "height_tolerance": None, "edge_tolerance": None})
        alarms = np.argwhere((res.labels == miem.ABNORMAL) & (sc.truth == EDGE))
        n_angle = int(((angle_only.labels == miem.ABNORMAL) & (sc.truth == EDGE)).sum())
        total += len(alarms)
        ms = res.params["min_step"]
        print(f"{sc.spec.name}: {len(alarms)} designed-edge alarms ({n_angle} after the angle "
              f"passes alone), min_step used {ms}, iterations {res.iterations}")
        g, fin = sc.points, np.isfinite(sc.points).all(axis=2)
        p = res.params
        cos0 = math.cos(math.radians(p["theta0"]))
        for r, c in alarms:
            print(f"  cell ({r},{c}) z {g[r, c, 2]:.3f} flags {res.flags[r, c]:>2} "
                  f"angle {res.angle[r, c]:.1f}")
            for d in DIRECTIONS:
                rays = []
                for s in p["scales"]:
                    a, b = (_neighbour(g, fin, r, c, d, s, side, p["max_gap"], ms, p["max_reach"])
                            for side in (-1, 1))
                    rays.append(f"s{s} n/a" if a is None or b is None
                                else f"s{s} {_ray(g, r, c, a, b, cos0)}")
                print(f"    dir {d!s:<8} " + " | ".join(rays))
    print(f"total designed-edge alarms in edge_wall scenes: {total}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
