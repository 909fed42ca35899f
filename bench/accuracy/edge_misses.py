"""Where the edge scenes' burr cells are missed: a diagnostic, per scene and per kind x step.

    python bench/accuracy/edge_misses.py              # tuning split (diagnose here)
    python bench/accuracy/edge_misses.py test         # test split (to score, never to tune)

For every edge scene of the split (default preset): burr cells, missed ones, and the label the
detector gave the missed cells (NORMAL or EDGE), the scene's step and whether its line is
curved; then the misses per kind and step. Writes nothing (the tables are edges.py's).
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
from suite import EDGE_KINDS, scenes  # noqa: E402

DEFECT = 1  # suite truth class of a burr cell


def misses(split: str = "tune") -> dict:
    """Per (kind, step): [burr cells, missed, missed NORMAL, missed EDGE]; prints each scene."""
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
    return dict(out)


def main() -> int:
    split = sys.argv[1] if len(sys.argv) > 1 else "tune"
    res = misses(split)
    print("\nkind, step: burr cells, missed (NORMAL, EDGE)")
    for (kind, step), (n, m, mn, me) in sorted(res.items()):
        print(f"{kind:<12} {step}: {n:>5} {m:>5} ({mn}, {me})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
