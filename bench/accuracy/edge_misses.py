"""Where the edge scenes' burr cells are missed: a diagnostic, per scene and per kind x step.

    python bench/accuracy/edge_misses.py              # tuning split (diagnose here)
    python bench/accuracy/edge_misses.py test         # test split (to score, never to tune)

For every edge scene of the split (default preset): burr cells, missed ones, and the label the
detector gave the missed cells (NORMAL or EDGE), the scene's step and whether its line is
curved; then the misses per kind and step; then, per kind, where the missed cells stand against
the edge test's sub-windows on the final labels (``miem.reference._side_fits``, SPEC "Edge
test" steps 3-4): *fits* a clean sub-window (within ``edge_tolerance`` rms of its plane: no
rule of the edge test flags such a cell but the outline rule of step 5, where the sub-windows
along an outline may fit it, so outside outlines the kind's recall cannot exceed the
*ceiling* printed beside it), *above* a clean sub-window (proud, but the opposite side does not fall
away: a concave feature, where only a lip, dipping then rising beyond, or a valley burr,
stepping up from one side's plane and above the other's, is flagged; or a burr
hanging less steeply than 45 degrees below a top, seen from the floor), *below* one, or *no
clean* sub-window.
Writes nothing (the tables are edges.py's).
"""

from __future__ import annotations

import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))

import miem  # noqa: E402
from miem import reference as ref  # noqa: E402
from suite import EDGE_KINDS, scenes  # noqa: E402

DEFECT = 1  # suite truth class of a burr cell


CLASSES = ("fits", "above", "below", "no clean")


def standing(points: np.ndarray, labels: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Per cell of ``cells`` (row-major): its index in CLASSES (see the module doc)."""
    p = miem.PRESETS["recommended"].grid
    r, k = p.edge_window // 2, float(p.edge_tolerance)
    fin = np.isfinite(points[..., 2])
    origin = points[np.unravel_index(np.argmax(fin), fin.shape)]
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        h, rms, spread, valid, nrm, _, _, _ = ref._side_fits(
            points, labels == miem.NORMAL, labels == miem.INVALID, cells, r, origin)
        _, clean, tol = ref._clean_sides(rms, spread, valid, nrm, k)
        fits = (clean & ~(np.abs(h) > tol)).any(axis=0)
        above = (clean & (h > tol)).any(axis=0)
        below = (clean & (h < -tol)).any(axis=0)
    return np.select([fits, above, below], [0, 1, 2], default=3)


def misses(split: str = "tune", where: dict | None = None) -> dict:
    """Per (kind, step): [burr cells, missed, missed NORMAL, missed EDGE]; prints each scene.
    ``where`` (if given) gets per kind the counts of the missed cells per CLASSES."""
    out: dict = defaultdict(lambda: [0, 0, 0, 0])
    for sc in scenes(split, real=False):
        if sc.spec.group not in EDGE_KINDS:
            continue
        labels = miem.detect(sc.points, preset="recommended").labels
        burr = sc.truth == DEFECT
        missed = burr & (labels != miem.ABNORMAL)
        row = [int(burr.sum()), int(missed.sum()), int((missed & (labels == miem.NORMAL)).sum()),
               int((missed & (labels == miem.EDGE)).sum())]
        step = sc.spec.params.get("step")
        print(f"{sc.spec.name:<22} step {step} curved {sc.spec.params.get('curved')!s:<5} "
              f"burr {row[0]:>4} missed {row[1]:>4} (NORMAL {row[2]}, EDGE {row[3]})", flush=True)
        acc = out[(sc.spec.group, step)]
        for i, v in enumerate(row):
            acc[i] += v
        if where is not None and missed.any():
            counts = np.bincount(standing(sc.points, labels, missed), minlength=len(CLASSES))
            where[sc.spec.group] = where.get(sc.spec.group, 0) + counts
    return dict(out)


def main() -> int:
    split = sys.argv[1] if len(sys.argv) > 1 else "tune"
    where: dict = {}
    res = misses(split, where)
    print("\nkind, step: burr cells, missed (NORMAL, EDGE)")
    for (kind, step), (n, m, mn, me) in sorted(res.items()):
        print(f"{kind:<12} {step}: {n:>5} {m:>5} ({mn}, {me})")
    print("\nkind: missed cells that " + " / ".join(CLASSES) + "; recall; ceiling")
    for kind in sorted(where):
        n = sum(v[0] for (kd, _), v in res.items() if kd == kind)
        m = sum(v[1] for (kd, _), v in res.items() if kd == kind)
        c = where[kind]
        print(f"{kind:<12} {' / '.join(str(int(x)) for x in c)}; {(n - m) / n:.3f}; "
              f"{(n - c[0]) / n:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
