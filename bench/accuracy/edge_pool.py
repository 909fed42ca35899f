"""A pool of generated edge scenes outside every split, for choosing between a rule's variants.

    python bench/accuracy/edge_pool.py [--base 9000] [--per-kind 40] [--clouds]
        [--set FIELD=VALUE ...] [--cloud-set FIELD=VALUE ...]

The suite's edge kinds (``edge_scenes``) at seeds ``base + 100 i + j`` (kind ``i`` in
``EDGE_KINDS`` order, ``j < per_kind``), the step cycling 0.05 / 0.1 / 0.2 / 0.5 mm with ``j``,
the line curved when ``j // 4`` is odd, the noise cycling 0.005 / 0.01 / 0.02 mm: every step
meets both line shapes and every noise. The tuning split has 2 edge scenes per kind and the
diagnosis set ``third`` 4, too few to tell a rule's variants apart. The pool's seeds (9000-9439
for the bases 9000 and 9100) are apart from the splits' edge seeds (``suite``: tuning
1300-1331, test 2300-2339, third 7300-7333) and the dev set's (from 8000). It never takes the
test split's role: nothing it scores is reported in the tables. ``--clouds`` scores the scenes
as held-out-style clouds too (``clouds.to_cloud``). Prints per kind F1, burr cells found, and
false alarms on the designed edge and on normal surface (counts, then rates of the designed
edge's and the normal surface's cells), then F1 per step. ``--set`` passes a parameter override
to the grid detector and ``--cloud-set`` to the cloud detector (``miem.detect`` keywords; the
value read as a Python literal, else a string: ``--set edge_tolerance=3.5``), for scoring a
setting's variants on the pool; a field a path does not honour is refused there, as
``miem.detect`` refuses it. Writes nothing.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from edge_scenes import EDGE_KINDS  # noqa: E402
from suite import Scene, SceneSpec, build  # noqa: E402

__all__ = ["pool", "pool_specs"]

STEPS = (0.05, 0.1, 0.2, 0.5)
NOISES = (0.005, 0.01, 0.02)


def pool_specs(base: int = 9000, per_kind: int = 40) -> list[SceneSpec]:
    """The pool's scene specs (see the module doc)."""
    if per_kind < 1 or per_kind > 100:
        raise ValueError(f"per_kind: expected 1..100 (seeds 100 apart per kind), got {per_kind}")
    out = []
    for i, kind in enumerate(EDGE_KINDS):
        for j in range(per_kind):
            seed = base + 100 * i + j
            params = {"kind": kind, "seed": seed, "step": STEPS[j % 4],
                      "curved": bool((j // 4) % 2), "noise": NOISES[j % 3]}
            out.append(SceneSpec(f"pool-{kind}-{seed}", "pool", kind, "edge", params))
    return out


def pool(base: int = 9000, per_kind: int = 40) -> Iterator[Scene]:
    """The pool's scenes, built one after the other."""
    for spec in pool_specs(base, per_kind):
        yield build(spec)


def overrides(items: list[str] | None) -> dict:
    """``FIELD=VALUE`` strings as ``miem.detect`` keywords: each value a Python literal
    (``3.5``, ``None``, ``(1, 2)``), else the string itself (``4.5rms``)."""
    import ast

    out = {}
    for item in items or ():
        field, sep, text = item.partition("=")
        if not sep or not field.isidentifier():
            raise ValueError(f"override: expected FIELD=VALUE, got {item!r}")
        try:
            out[field] = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            out[field] = text
    return out


def main(argv: list[str] | None = None) -> int:
    """Print the pool's scores (see the module doc)."""
    import argparse

    import miem
    from clouds import to_cloud
    from score import Counts, confusion

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", type=int, default=9000)
    ap.add_argument("--per-kind", type=int, default=40)
    ap.add_argument("--clouds", action="store_true", help="also as held-out-style clouds")
    ap.add_argument("--set", action="append", metavar="FIELD=VALUE",
                    help="a grid detector override (repeatable)")
    ap.add_argument("--cloud-set", action="append", metavar="FIELD=VALUE",
                    help="a cloud detector override (repeatable; with --clouds)")
    args = ap.parse_args(argv)
    if args.cloud_set and not args.clouds:
        ap.error("--cloud-set: the clouds are scored only with --clouds")
    grid_kw, cloud_kw = overrides(args.set), overrides(args.cloud_set)
    paths = ("grid", "cloud") if args.clouds else ("grid",)
    per: dict = {}
    for sc in pool(args.base, args.per_kind):
        for path in paths:
            if path == "grid":
                points, truth, kw = sc.points, sc.truth, grid_kw
            else:
                cl = to_cloud(sc)
                points, truth, kw = cl.points, cl.truth, cloud_kw
            c = confusion(miem.detect(points, **kw).labels == miem.ABNORMAL, truth)
            for key in ((path, sc.spec.group, None), (path, sc.spec.group, sc.step)):
                per[key] = per.get(key, Counts()) + c
    print(f"pool base {args.base}, {args.per_kind} scenes per kind: F1, burr cells found, "
          "false alarms on the designed edge + on normal surface (counts; rates)"
          + (f"; grid overrides {grid_kw}" if grid_kw else "")
          + (f"; cloud overrides {cloud_kw}" if cloud_kw else ""))
    for path in paths:
        for kind in EDGE_KINDS:
            c = per[(path, kind, None)]
            steps = "  ".join(f"{s:g} mm {per[(path, kind, s)].f1:.3f}" for s in STEPS
                              if (path, kind, s) in per)
            print(f"{path:5s} {kind:11s} F1 {c.f1:.3f}  found {c.tp}/{c.tp + c.fn}  "
                  f"FA {c.fp_edge}+{c.fp_normal} ({c.edge_fa:.2%}; {c.normal_fa:.3%})  | {steps}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
