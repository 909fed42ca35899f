"""Accuracy benchmark: tune every contender on the tuning split, score it on the test split.

    python bench/accuracy/run.py             # tune, test, write RESULTS.md, plots, JSON
    python bench/accuracy/run.py --no-tune   # reuse tuned.json (tables and plots only)
    python bench/accuracy/run.py --readme    # also put the headline table into README.md

Writes, beside this file: ``tuned.json`` (every contender's chosen parameters and tuning
scores), ``recommended.json`` (the winning ``miem.detect`` keyword arguments: the
``preset="recommended"`` values), ``RESULTS.md`` (the tables) and ``plots/*.png``.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import miem
from contenders import CONTENDERS, EDGE_STAGE, PAPER, miem_supports
from score import Counts, confusion, kind_counts
from suite import EDGE_KINDS, KINDS, TALL_KINDS, Scene, scenes
from tune import EDGE_FA_MAX, NORMAL_FA_MAX, best, evaluate, tune_miem

ROOT = HERE.parents[1]
TUNED = HERE / "tuned.json"
RECOMMENDED = HERE / "recommended.json"
RESULTS = HERE / "RESULTS.md"
PLOTS = HERE / "plots"
README_START, README_END = "<!-- accuracy:start -->", "<!-- accuracy:end -->"

TARGET_F1, TARGET_KIND_F1 = 0.98, 0.95


# --------------------------------------------------------------------------------------------
# JSON


def _jsonable(params: dict) -> dict:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in params.items()}


def _counts_dict(c: Counts) -> dict:
    return {"f1": c.f1, "precision": c.precision, "recall": c.recall, "edge_fa": c.edge_fa,
            "normal_fa": c.normal_fa, "tp": c.tp, "fn": c.fn, "fp_normal": c.fp_normal,
            "fp_edge": c.fp_edge}


def _recommended_kwargs(params: dict) -> dict:
    """Exact ``miem.detect`` keyword arguments of a scale-free miem setting."""
    out = dict(PAPER)
    if miem_supports("height_tolerance"):
        out["height_tolerance"] = None
    out.update(EDGE_STAGE)  # owned by edges.py --tune
    out.update({k: v for k, v in params.items() if not k.endswith("_steps")})
    return _jsonable(out)


def detect_call(rec: dict) -> str:
    """``miem.detect(grid, ...)`` source text with the given keyword arguments."""
    parts = []
    for k, v in rec.items():
        if isinstance(v, list):
            v = tuple(v)
        parts.append(f"{k}={v!r}")
    return "miem.detect(grid, " + ", ".join(parts) + ")"


# --------------------------------------------------------------------------------------------
# tuning


def run_tuning(tune_scenes: Sequence[Scene], log: Any) -> dict:
    """Tune every contender; returns the content of ``tuned.json``."""
    out: dict[str, Any] = {"contenders": {}, "scenes": [s.name for s in tune_scenes]}
    for name, c in CONTENDERS.items():
        t0 = time.perf_counter()
        if c.fixed is not None:
            trials = evaluate(c, tune_scenes, [c.fixed])
            win, extra = trials[0], {}
        elif name == "miem":
            res = tune_miem(c, tune_scenes)
            trials, win = res["trials"], res["winner"]
            ws = res["winner_steps"]
            top = sorted(trials, key=lambda t: (not t.feasible, -_nan0(t.counts.f1)))[:15]
            extra = {
                "stages": [_jsonable(s.params) for s in res["stages"]],
                "winner_steps": None if ws is None else {
                    "params": _jsonable(ws.params), "tuning": _counts_dict(ws.counts)},
                "top": [{"params": _jsonable(t.params), "feasible": t.feasible,
                         "tuning": _counts_dict(t.counts)} for t in top],
            }
        else:
            trials = evaluate(c, tune_scenes)
            win, extra = best(trials), {}
        dt = time.perf_counter() - t0
        out["contenders"][name] = {
            "params": _jsonable(win.params), "feasible": win.feasible,
            "tuning": _counts_dict(win.counts), "n_settings": len(trials),
            "seconds": round(dt, 1), **extra,
        }
        log(f"  tuned {name:12s} {len(trials):4d} settings {dt:6.1f} s  F1 {win.counts.f1:.4f}"
            f"  {win.params}")
    return out


def _nan0(v: float) -> float:
    return 0.0 if math.isnan(v) else v


# --------------------------------------------------------------------------------------------
# testing


def run_test(test_scenes: Sequence[Scene], tuned: dict, log: Any) -> dict:
    """Every contender on every test scene: per-scene counts and per-kind cells found."""
    per_scene: dict[str, dict[str, Counts]] = defaultdict(dict)
    per_kind: dict[str, dict[str, list[int]]] = defaultdict(lambda: defaultdict(lambda: [0, 0]))
    for name, c in CONTENDERS.items():
        params = c.fixed if c.fixed is not None else tuned["contenders"][name]["params"]
        t0 = time.perf_counter()
        for sc in test_scenes:
            mask, dt = c.run(sc.points, sc.step, params)
            per_scene[name][sc.name] = confusion(mask, sc.truth, dt)
            for kind, (found, total) in kind_counts(mask, sc.kinds).items():
                key = kind if sc.spec.source == "synthetic" else f"{sc.spec.group}:{kind}"
                per_kind[name][key][0] += found
                per_kind[name][key][1] += total
        log(f"  tested {name:12s} {time.perf_counter() - t0:6.1f} s")
    return {"scene": per_scene, "kind": per_kind}


# --------------------------------------------------------------------------------------------
# tables


def _pct(v: float, digits: int = 3) -> str:
    return "n/a" if math.isnan(v) else f"{100 * v:.{digits}f} %"


def _f(v: float, digits: int = 3) -> str:
    return "n/a" if math.isnan(v) else f"{v:.{digits}f}"


def _group_counts(per_scene: dict[str, Counts], test_scenes: Sequence[Scene], group: str) -> Counts:
    return Counts.total(per_scene[s.name] for s in test_scenes if s.spec.group == group)


def headline(result: dict, test_scenes: Sequence[Scene]) -> list[str]:
    """Overall table, one row per contender."""
    n_cells = sum(int(np.isfinite(s.points).all(axis=-1).sum()) for s in test_scenes)
    rows = [
        ("| contender | F1 | precision | recall | edge false alarms | normal false alarms "
         "| time (ms / 100k pts) |"),
        "|---|---|---|---|---|---|---|",
    ]
    for name in CONTENDERS:
        tot = Counts.total(result["scene"][name].values())
        ms = 1e3 * tot.seconds / n_cells * 1e5
        label = f"**{name}**" if name == "miem" else name
        rows.append(
            f"| {label} | {_f(tot.f1)} | {_f(tot.precision)} | {_f(tot.recall)} "
            f"| {_pct(tot.edge_fa)} ({tot.fp_edge}) | {_pct(tot.normal_fa, 4)} ({tot.fp_normal}) "
            f"| {ms:.1f} |"
        )
    return rows


def _groups() -> list[str]:
    return [*KINDS, *EDGE_KINDS, "paper", "real"]


def group_f1_table(result: dict, test_scenes: Sequence[Scene]) -> list[str]:
    """F1 per scene group (focus kind, paper, real) and contender."""
    names = list(CONTENDERS)
    rows = ["| scenes | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    for g in _groups():
        cells = []
        vals = {n: _group_counts(result["scene"][n], test_scenes, g).f1 for n in names}
        top = max(_nan0(v) for v in vals.values())
        for n in names:
            s = _f(vals[n])
            cells.append(f"**{s}**" if _nan0(vals[n]) == top and top > 0 else s)
        rows.append(f"| {g} | " + " | ".join(cells) + " |")
    return rows


def detail_table(result: dict, test_scenes: Sequence[Scene], name: str) -> list[str]:
    """Per group: all scores of one contender."""
    rows = [
        "| scenes | defect cells | precision | recall | F1 | edge FA | normal FA |",
        "|---|---|---|---|---|---|---|",
    ]
    for g in _groups():
        c = _group_counts(result["scene"][name], test_scenes, g)
        rows.append(f"| {g} | {c.n_defect} | {_f(c.precision)} | {_f(c.recall)} | {_f(c.f1)} "
                    f"| {_pct(c.edge_fa)} ({c.fp_edge}) | {_pct(c.normal_fa, 4)} "
                    f"({c.fp_normal}) |")
    tot = Counts.total(result["scene"][name].values())
    rows.append(f"| **all** | {tot.n_defect} | {_f(tot.precision)} | {_f(tot.recall)} "
                f"| {_f(tot.f1)} | {_pct(tot.edge_fa)} ({tot.fp_edge}) "
                f"| {_pct(tot.normal_fa, 4)} ({tot.fp_normal}) |")
    return rows


def real_kind_table(result: dict) -> list[str]:
    """Recall per injected kind on the real and paper scenes."""
    names = list(CONTENDERS)
    keys = sorted({k for n in names for k in result["kind"][n] if ":" in k})
    rows = ["| scenes:kind | cells | " + " | ".join(names) + " |",
            "|---" * (len(names) + 2) + "|"]
    for k in keys:
        total = result["kind"][names[0]][k][1]
        vals = [result["kind"][n][k][0] / total for n in names]
        rows.append(f"| {k} | {total} | " + " | ".join(_f(v, 2) for v in vals) + " |")
    return rows


def scene_table(result: dict, test_scenes: Sequence[Scene]) -> list[str]:
    """Per scene: F1 of every contender, and the scores of miem."""
    names = list(CONTENDERS)
    rows = [
        "| scene | step | noise | defect cells | edge cells | miem P / R | miem FA edge / "
        "normal | " + " | ".join(f"F1 {n}" for n in names) + " |",
        "|---" * (7 + len(names)) + "|",
    ]
    for s in test_scenes:
        m = result["scene"]["miem"][s.name]
        noise = s.spec.params.get("noise", "real")
        noise = f"{noise:g}" if isinstance(noise, float) else noise
        f1s = " | ".join(_f(result["scene"][n][s.name].f1, 2) for n in names)
        rows.append(
            f"| {s.name} | {s.step:g} | {noise} | {m.n_defect} | {m.n_edge} "
            f"| {_f(m.precision, 2)} / {_f(m.recall, 2)} | {m.fp_edge} / {m.fp_normal} | {f1s} |"
        )
    return rows


def targets(result: dict, test_scenes: Sequence[Scene], per: dict | None = None) -> list[str]:
    """The issue's targets, met or not, with the measured value.

    For miem's recommended settings, or for the per-scene counts `per` (the prototype).
    """
    per = result["scene"]["miem"] if per is None else per
    tot = Counts.total(per.values())
    lines = []

    def line(ok: bool, text: str) -> None:
        lines.append(f"- {'met' if ok else '**missed**'}: {text}")

    line(tot.f1 >= TARGET_F1, f"overall F1 >= {TARGET_F1}: {tot.f1:.4f}")
    for g in TALL_KINDS:
        c = _group_counts(per, test_scenes, g)
        line(c.f1 >= TARGET_KIND_F1, f"F1 >= {TARGET_KIND_F1} on `{g}`: {c.f1:.4f}")
    line(_nan0(tot.edge_fa) <= EDGE_FA_MAX,
         f"designed-edge false alarms <= {100 * EDGE_FA_MAX:g} %: {_pct(tot.edge_fa)}")
    line(tot.normal_fa <= NORMAL_FA_MAX,
         f"normal-point false alarms <= {100 * NORMAL_FA_MAX:g} %: {_pct(tot.normal_fa, 4)}")
    others = {n: Counts.total(result["scene"][n].values()).f1 for n in CONTENDERS if n != "miem"}
    runner = max(others, key=lambda n: _nan0(others[n]))
    line(tot.f1 > _nan0(others[runner]),
         f"ahead of every other contender on overall F1: {tot.f1:.4f} vs {runner} "
         f"{others[runner]:.4f}")
    return lines


def _grid_text(tuned: dict) -> list[str]:
    lines = []
    for name, c in CONTENDERS.items():
        if c.fixed is not None:
            lines.append(f"- `{name}`: not tuned: `{_jsonable(c.fixed)}`.")
            continue
        if name == "miem":
            stage1 = c.structural
            keys = sorted({k for p in stage1 for k in p})
            axes = {k: sorted({repr(p.get(k)) for p in stage1}) for k in keys}
            ax = "; ".join(f"`{k}` in {{{', '.join(v)}}}" for k, v in axes.items())
            lines.append(
                f"- `miem` ({tuned['contenders'][name]['n_settings']} settings in 3 stages): "
                f"stage 1, {len(stage1)} settings: {ax} (`height_tolerance_steps` is an "
                "absolute tolerance in sampling steps); stage 2 around the stage-1 leaders "
                "(scale-free and step-scaled): `min_directions` in {None, 3}, "
                "`min_step_steps` in {None, 1.5}, `max_iterations` in {10, 30}, `window` in "
                "{11, 21, 31}; stage 3: `theta0` +-5, +-10 deg and `\"auto\"`, the rms "
                "tolerance +-0.5, +-1."
            )
            continue
        axes: dict[str, set] = defaultdict(set)
        for p in c.structural + c.thresholds:
            for k, v in p.items():
                axes[k].add(repr(v))
        ax = "; ".join(f"`{k}` in {{{', '.join(sorted(v))}}}" for k, v in axes.items())
        n = len(c.structural) * len(c.thresholds)
        lines.append(f"- `{name}` ({n} settings): {ax}.")
    return lines


def prototype_section(result: dict, test_scenes: Sequence[Scene], proto: dict) -> list[str]:
    """miem (the core) against the prototype of the proposed height-test rule."""
    per = proto["scene"]
    t = proto["tuning"]
    rows = [
        "## Prototype: a proposed height-test rule (not in miem yet)",
        "",
        ("What limits miem above is its height test: it tests NORMAL cells only and abstains "
         "wherever an EDGE cell lies in the window, and most defects the angle test cannot "
         "take whole (spatter domes, burr ridges, low spikes and pits, 3x3 tops) are EDGE or "
         "sit next to EDGE cells. `bench/accuracy/prototype.py` emulates, on top of the core's "
         "angle passes, a rule that tells defects from designed features by their length: "
         "8-connected EDGE components at most `edge_extent` cells long are compact (a halo, a "
         "short ridge, a dome) and are height-tested like NORMAL cells; the test abstains only "
         "next to longer EDGE components (feature lines). Tuned on the tuning split the same "
         f"way ({proto['n_settings']} settings): `{proto['params']}`, tuning F1 "
         f"{_f(t.f1)}, edge FA {_pct(t.edge_fa)}, normal FA {_pct(t.normal_fa, 4)}."),
        "",
        ("| scenes | miem (core, recommended) F1 | prototype F1 | prototype precision "
         "| prototype recall |"),
        "|---|---|---|---|---|",
    ]
    for g in _groups():
        core = _group_counts(result["scene"]["miem"], test_scenes, g)
        pc = Counts.total(per[s.name] for s in test_scenes if s.spec.group == g)
        rows.append(f"| {g} | {_f(core.f1)} | {_f(pc.f1)} | {_f(pc.precision)} "
                    f"| {_f(pc.recall)} |")
    core = Counts.total(result["scene"]["miem"].values())
    pc = Counts.total(per.values())
    rows += [
        f"| **all** | {_f(core.f1)} | {_f(pc.f1)} | {_f(pc.precision)} | {_f(pc.recall)} |",
        "",
        (f"Prototype on the test split: edge false alarms {_pct(pc.edge_fa)} ({pc.fp_edge}), "
         f"normal false alarms {_pct(pc.normal_fa, 4)} ({pc.fp_normal}). The issue's targets "
         "measured on it:"),
        "",
        *targets(result, test_scenes, per),
    ]
    return rows


def write_results(result: dict, tuned: dict, test_scenes: Sequence[Scene], seconds: float,
                  tune_scenes_n: int, proto: dict | None = None) -> str:
    """RESULTS.md text."""
    rec = json.loads(RECOMMENDED.read_text())
    ctr = tuned["contenders"]
    n_test = len(test_scenes)
    n_real = sum(s.spec.source == "real" for s in test_scenes)
    cells = sum(s.truth.size for s in test_scenes)
    md = [
        "# Detection accuracy: miem against the alternatives",
        "",
        (f"Generated by `python bench/accuracy/run.py` in {seconds:.0f} s on "
         f"{platform.machine()} (miem {miem.__version__}, Python {platform.python_version()})."),
        (f"Test split: {n_test} scenes ({n_real} from real scans), {cells:,} cells; tuning "
         f"split: {tune_scenes_n} other scenes. Every contender gets the same scenes."),
        "",
        "## Headline (test split, all scenes)",
        "",
        ("Scores of the class ABNORMAL against injected defects. Edge false alarms: designed-edge "
         "cells (creases, flanges, fillets, edge strips) flagged; normal false alarms: good "
         "surface cells flagged (counts in brackets). Time: wall time per 100k points on a "
         "shared 2-core machine (miem: the compiled core with `heights=\"abnormal\"`)."),
        "",
        *headline(result, test_scenes),
        "",
        "Recommended settings (`bench/accuracy/recommended.json`, chosen on the tuning split):",
        "",
        "```python",
        detect_call(rec),
        "```",
        "",
        "## Targets (recommended settings, test split)",
        "",
        *targets(result, test_scenes),
        "",
        "## F1 per scene group",
        "",
        ("Synthetic scenes are grouped by their defect kind (each scene holds one kind); "
         "`*_low` kinds are not taller than one sampling step. `paper`: the paper's simulated "
         "surface with its edge strips (defects on the strips too); `real`: real scans with "
         "injected defects. Best per row in bold."),
        "",
        *group_f1_table(result, test_scenes),
        "",
        "![F1 per defect kind](plots/f1_per_kind.png)",
        "",
        "![False alarms](plots/false_alarms.png)",
        "",
        *(prototype_section(result, test_scenes, proto) + [""] if proto else []),
        "## miem, recommended settings, per group",
        "",
        *detail_table(result, test_scenes, "miem"),
        "",
        "## miem, paper settings, per group",
        "",
        *detail_table(result, test_scenes, "miem_paper"),
        "",
        "## Recall per injected kind on the real and paper scenes",
        "",
        *real_kind_table(result),
        "",
        "## Per scene",
        "",
        *scene_table(result, test_scenes),
        "",
        "## The suite",
        "",
        ("`bench/accuracy/suite.py` builds every scene from `miem.simulate` with seeds fixed in "
         "the scene specs (`specs(\"tune\")`, `specs(\"test\")`), so one command regenerates it."),
        "",
        ("- Surfaces: tilted plane (10-30 deg), gently curved sheet, doubly curved shell (sphere "
         "cap), saddle, crease (fold 10-30 deg), bent flange (30-60 deg), edge strip (a bead one "
         "cell wide, 3 steps high, across every profile), fillet (arc of 8 steps between a web "
         "and a 30-60 deg face); the paper's surface with two edge strips."),
        ("- Defects (heights along z in sampling steps): single spikes and pits 1-10 steps "
         "(`spike`, `pit`) and 0.5-1 step (`spike_low`, `pit_low`), dust 10-60 steps above the "
         "surface, 2x2 and 3x3 clusters 1-10 steps, burr ridges one cell wide and 4-10 cells "
         "long along a profile (`ridge_along`) or across profiles (`ridge_across`) 1-6 steps "
         "high, smooth weld-spatter domes 2-4 cells wide 1-4 steps high (spherical caps)."),
        ("- Noise 1, 3, 5, 10 % of the step; steps 0.2, 0.3, 0.4, 0.5 mm; dropouts 0-2 %; "
         "120-160 x 120-160 cells. The tuning split pairs kinds with other surfaces, noise levels "
         "and steps, and uses other seeds."),
        ("- Truth: defect (the injected cells), designed edge (the crease/flange/fillet band, "
         "the strip's bead), normal, dropout (not scored)."),
        ("- Real scans (`shared/data/real`, see its SOURCES.md): `second_source.pcd` (a laser "
         "profiler scan of a burred workpiece; grid rebuilt from its scan lines with "
         "`miem.io.grid_from_scanlines`, every other column kept: 0.1 mm x 0.1 mm cells) and "
         "the Gocator height map (0.3 mm). Crops of 150 x 150 cells get 23 injected defects "
         "each (spikes, pits, dust, 2x2/3x3 clusters, ridges, spatter; 1-6 steps). "
         "**Truth on real scans, honestly:** what is already on a real scan is not known. Cells "
         "are *unknown* (not scored) when the paper-settings detector labels them ABNORMAL or "
         "EDGE on the crop before injection, or when they are rough (rms of the 5 x 5 local "
         "plane above 3 times the crop's median), and within 2 cells of those. Defects are "
         "injected only on normal cells 3 cells or more from unknown cells and dropouts. The "
         "rule uses the paper settings, so it favours `miem_paper` on the real scenes' false "
         "alarms; every other contender's flags on the remaining real surface count as false "
         "alarms, real burrs among them if the rule missed any."),
        "",
        "## Tuning",
        "",
        ("Every contender's parameters, miem's included, are chosen on the tuning split only, "
         "by a grid search of the summed (micro) counts over all tuning scenes. Rule, the same "
         f"for every contender: among the settings that meet the false-alarm targets on the "
         f"tuning split (edge <= {100 * EDGE_FA_MAX:g} %, normal <= {100 * NORMAL_FA_MAX:g} %), "
         "the highest F1; when none does, the highest F1. Lengths are in sampling steps (the "
         "step of a scan is known). Grids:"),
        "",
        *_grid_text(tuned),
        "",
        ("| contender | chosen parameters | tuning F1 | tuning edge FA | tuning normal FA "
         "| meets FA targets |"),
        "|---|---|---|---|---|---|",
    ]
    for name in CONTENDERS:
        c = ctr[name]
        t = c["tuning"]
        md.append(f"| {name} | `{c['params']}` | {_f(t['f1'])} | {_pct(t['edge_fa'])} "
                  f"| {_pct(t['normal_fa'], 4)} | {'yes' if c['feasible'] else 'no'} |")
    m = ctr["miem"]
    md += ["", "miem's best settings on the tuning split (feasible first):", "",
           "| settings | F1 | precision | recall | edge FA | normal FA | feasible |",
           "|---|---|---|---|---|---|---|"]
    for t in m.get("top", []):
        s = t["tuning"]
        md.append(f"| `{t['params']}` | {_f(s['f1'])} | {_f(s['precision'])} "
                  f"| {_f(s['recall'])} | {_pct(s['edge_fa'])} | {_pct(s['normal_fa'], 4)} "
                  f"| {'yes' if t['feasible'] else 'no'} |")
    ws = m.get("winner_steps")
    if ws:
        s = ws["tuning"]
        md += ["", (f"Best setting with a length in sampling steps (not usable as a fixed "
                    f"preset): `{ws['params']}`: tuning F1 {_f(s['f1'])}, edge FA "
                    f"{_pct(s['edge_fa'])}, normal FA {_pct(s['normal_fa'], 4)}.")]
    md += ["", "Stage winners: " + "; ".join(f"`{p}`" for p in m.get("stages", [])), ""]
    return "\n".join(md)


# --------------------------------------------------------------------------------------------
# plots


def plots(result: dict, test_scenes: Sequence[Scene], proto: dict | None = None) -> None:
    """Per-kind F1 bars (with the prototype's, hatched, when given) and false-alarm bars, PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    PLOTS.mkdir(exist_ok=True)
    names = list(CONTENDERS)
    groups = _groups()
    colors = plt.get_cmap("tab10")
    fig, ax = plt.subplots(figsize=(13, 5.2))
    series = [(n, result["scene"][n]) for n in names]
    if proto:
        series.append(("prototype (proposed height test, not in miem)", proto["scene"]))
    width = 0.8 / len(series)
    x = np.arange(len(groups))
    for i, (n, per) in enumerate(series):
        vals = [_nan0(_group_counts(per, test_scenes, g).f1) for g in groups]
        is_proto = n.startswith("prototype")
        ax.bar(x + (i - (len(series) - 1) / 2) * width, vals, width, label=n,
               color="white" if is_proto else colors(i), hatch="////" if is_proto else None,
               edgecolor="black" if n == "miem" or is_proto else "none", linewidth=0.8)
    ax.axhline(TARGET_KIND_F1, color="gray", ls="--", lw=0.8)
    ax.text(len(groups) - 0.5, TARGET_KIND_F1 + 0.01, "target 0.95", ha="right", fontsize=8,
            color="gray")
    ax.set_xticks(x, groups, rotation=25, ha="right")
    ax.set_ylabel("F1 of ABNORMAL (test split)")
    ax.set_ylim(0, 1.05)
    ax.set_title("F1 per scene group (one defect kind per synthetic scene)")
    ax.legend(ncol=5, fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.2))
    fig.tight_layout()
    fig.savefig(PLOTS / "f1_per_kind.png", dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    tots = {n: Counts.total(result["scene"][n].values()) for n in names}
    for ax, attr, title, target in (
        (axes[0], "edge_fa", "designed-edge cells flagged", EDGE_FA_MAX),
        (axes[1], "normal_fa", "normal cells flagged", NORMAL_FA_MAX),
    ):
        vals = [100 * _nan0(getattr(tots[n], attr)) for n in names]
        floor = 1e-4
        bars = ax.bar(names, [max(v, floor) for v in vals],
                      color=[colors(i) for i in range(len(names))])
        for b, v in zip(bars, vals):
            ax.text(b.get_x() + b.get_width() / 2, max(v, floor) * 1.15,
                    "0" if v == 0 else f"{v:.3g}", ha="center", fontsize=8)
        ax.axhline(100 * target, color="gray", ls="--", lw=0.8)
        ax.text(len(names) - 0.5, 100 * target * 1.15, f"target {100 * target:g} %", ha="right",
                fontsize=8, color="gray")
        ax.set_yscale("log")
        ax.set_ylim(floor, 200)
        ax.set_ylabel("% of cells (log; 0 drawn at the floor)")
        ax.set_title(f"False alarms: {title} (test split)")
        ax.tick_params(axis="x", rotation=30)
    fig.tight_layout()
    fig.savefig(PLOTS / "false_alarms.png", dpi=110)
    plt.close(fig)


# --------------------------------------------------------------------------------------------
# README


def update_readme(result: dict, test_scenes: Sequence[Scene]) -> bool:
    """Put the headline table between the accuracy markers of README.md (if present)."""
    path = ROOT / "README.md"
    text = path.read_text()
    if README_START not in text or README_END not in text:
        return False
    head, rest = text.split(README_START, 1)
    _, tail = rest.split(README_END, 1)
    rec = json.loads(RECOMMENDED.read_text())
    block = [README_START, "", *headline(result, test_scenes), "",
             "Targets of the recommended settings on the test split:", "",
             *targets(result, test_scenes), "",
             (f"Recommended settings: `{detect_call(rec)}`; details in "
              "[`bench/accuracy/RESULTS.md`](bench/accuracy/RESULTS.md)."), "", README_END]
    path.write_text(head + "\n".join(block) + tail)
    return True


# --------------------------------------------------------------------------------------------


def main(argv: Sequence[str] | None = None) -> int:
    """Command line (module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--no-tune", action="store_true", help="reuse tuned.json")
    ap.add_argument("--readme", action="store_true", help="update README.md's headline table")
    ap.add_argument("--no-real", action="store_true", help="leave the real scans out")
    ap.add_argument("--no-prototype", action="store_true",
                    help="skip the prototype of the proposed height test (prototype.py)")
    args = ap.parse_args(argv)
    t_start = time.perf_counter()

    def log(msg: str) -> None:
        print(f"[{time.perf_counter() - t_start:6.1f} s] {msg}", flush=True)

    real = False if args.no_real else None
    tune_scenes = list(scenes("tune", real=real))
    test_scenes = list(scenes("test", real=real))
    log(f"suite: {len(tune_scenes)} tuning scenes, {len(test_scenes)} test scenes")
    if args.no_tune and TUNED.exists():
        tuned = json.loads(TUNED.read_text())
    else:
        tuned = run_tuning(tune_scenes, log)
        TUNED.write_text(json.dumps(tuned, indent=1) + "\n")
        rec = _recommended_kwargs(tuned["contenders"]["miem"]["params"])
        RECOMMENDED.write_text(json.dumps(rec, indent=1) + "\n")
    result = run_test(test_scenes, tuned, log)
    if args.no_prototype:
        proto = None
    else:
        from prototype import GRID, test_prototype, tune_prototype

        p_best, p_tune, p_ok = tune_prototype(tune_scenes)
        proto = {"params": p_best, "tuning": p_tune, "feasible": p_ok, "n_settings": len(GRID),
                 "scene": test_prototype(test_scenes, p_best)}
        log(f"  prototype (proposed height test) tuned and tested: {p_best}")
    plots(result, test_scenes, proto)
    seconds = time.perf_counter() - t_start
    RESULTS.write_text(
        write_results(result, tuned, test_scenes, seconds, len(tune_scenes), proto)
    )
    log(f"wrote {RESULTS.relative_to(ROOT)}")
    if args.readme:
        log("README.md updated" if update_readme(result, test_scenes)
            else "README.md has no accuracy markers; not updated")
    for line in headline(result, test_scenes):
        print(line)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

