"""Which stage of the cloud detector raises each false alarm (and finds each burr) on the
held-out-style clouds: the angle passes with the floating groups, the height test or the edge
test (a point ABNORMAL with the defaults is put to the first stage that flags it when the later
ones are turned off). For diagnosis on the tuning split and the third seed set; the test split is
scored, not diagnosed.

``python bench/accuracy/cloud_alarms.py [--split third] [--kinds edge_crease,edge_flange]``
prints per scene and per kind: TP, FA on normal surface (FAn) and on the designed edge (FAe),
each as angle / height / edge, and the misses (FN).
"""

from __future__ import annotations

import argparse

import numpy as np

from clouds import clouds


def stages(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(ABNORMAL with the defaults, stage per point: 0 angle passes and floating groups,
    1 height test, 2 edge test)."""
    import miem

    a = miem.ABNORMAL
    full = miem.detect_points(points).labels == a
    angle = miem.detect_points(points, edge_tolerance=None, height_tolerance=None).labels == a
    height = miem.detect_points(points, edge_tolerance=None).labels == a
    return full, np.where(angle, 0, np.where(height, 1, 2))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--split", choices=("tune", "third"), default="third")
    ap.add_argument("--kinds", default="", help="comma-separated focus kinds (default: all)")
    args = ap.parse_args(argv)
    kinds = {k for k in args.kinds.split(",") if k} or None
    total: dict[tuple[str, str], np.ndarray] = {}
    for c in clouds(args.split):
        kind = c.scene.spec.group
        if kinds and kind not in kinds:
            continue
        full, stage = stages(c.points)
        cells = []
        for name, value in (("TP", 1), ("FAn", 0), ("FAe", 2)):
            n = np.bincount(stage[full & (c.truth == value)], minlength=3)
            total[(kind, name)] = total.get((kind, name), np.zeros(3, int)) + n
            cells.append(f"{name} {n[0]}/{n[1]}/{n[2]}")
        fn = int(np.count_nonzero(~full & (c.truth == 1)))
        print(f"{c.name} (step {c.step:g}): " + ", ".join(cells) + f", FN {fn}")
    print("per kind (angle / height / edge):")
    for (kind, name), n in total.items():
        print(f"  {kind} {name}: {n[0]}/{n[1]}/{n[2]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
