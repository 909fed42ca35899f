"""Grid search of every contender's parameters on the tuning split.

Each setting is scored by its confusion counts summed over all tuning scenes (micro average).
The rule, the same for every contender: among the settings that meet the false-alarm targets on
the tuning split (designed-edge cells flagged <= 0.1 %, normal cells flagged <= 0.01 %), take
the highest F1; when no setting meets them, the highest F1 overall. Ties go to fewer false
alarms, then to the earlier setting in the grid.

miem is searched in three stages: (1) ``theta0 x scales x max_gap x height_tolerance``;
(2) around the stage-1 winner, ``min_directions x min_step x max_iterations x window`` (and
``edge_extent`` once the core has it, see ``prototype.py``);
(3) ``theta0`` and the height tolerance refined around the stage-2 winner. Settings that give
lengths in sampling steps (``min_step_steps``, ``height_tolerance_steps``) cannot be a fixed
preset (the preset does not know the scan's step), so the recommended setting is the best
*scale-free* one; the best step-scaled one is reported beside it.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from contenders import Contender, miem_supports
from score import Counts, confusion
from suite import Scene

__all__ = ["EDGE_FA_MAX", "NORMAL_FA_MAX", "Trial", "best", "evaluate", "tune_miem"]

#: False-alarm targets (fractions) used by the selection rule.
EDGE_FA_MAX = 0.001
NORMAL_FA_MAX = 0.0001


@dataclass(frozen=True)
class Trial:
    """One setting and its counts summed over the tuning scenes."""

    params: dict
    counts: Counts

    @property
    def feasible(self) -> bool:
        """Meets both false-alarm targets (no edge cells counts as meeting that one)."""
        efa = self.counts.edge_fa
        return (math.isnan(efa) or efa <= EDGE_FA_MAX) and self.counts.normal_fa <= NORMAL_FA_MAX

    @property
    def scale_free(self) -> bool:
        """No length given in sampling steps (usable as a fixed preset)."""
        return not any(
            k.endswith("_steps") and v is not None for k, v in self.params.items()
        )


def _f1(t: Trial) -> float:
    f = t.counts.f1
    return -1.0 if math.isnan(f) else f


def best(trials: Sequence[Trial]) -> Trial:
    """The winner by the selection rule (module docstring)."""
    pool = [t for t in trials if t.feasible] or list(trials)
    order = {id(t): i for i, t in enumerate(trials)}
    return max(pool, key=lambda t: (round(_f1(t), 9), -t.counts.fp, -order[id(t)]))


def evaluate(
    contender: Contender, scenes: Sequence[Scene], settings: Sequence[dict] | None = None
) -> list[Trial]:
    """Counts of every setting summed over the scenes.

    Parameters
    ----------
    contender : Contender
        The detector.
    scenes : sequence of Scene
        The tuning scenes.
    settings : sequence of dict, optional
        Full settings to try (structural and threshold keys together); default: the product
        of the contender's structural and threshold grids.

    Returns
    -------
    list of Trial
        In the order of `settings`.
    """
    if settings is None:
        settings = [{**s, **t} for s in contender.structural for t in contender.thresholds]
    groups: dict[str, tuple[dict, list[tuple[int, dict]]]] = {}
    for i, p in enumerate(settings):
        s, t = contender.split(p)
        key = repr(sorted(s.items(), key=lambda kv: kv[0]))
        groups.setdefault(key, (s, []))[1].append((i, t))
    totals = [Counts()] * len(settings)
    for scene in scenes:
        for s, items in groups.values():
            t0 = time.perf_counter()
            state, finite = contender.state(scene.points, scene.step, s)
            dt = time.perf_counter() - t0
            for i, t in items:
                mask = contender.mask(state, finite, scene.step, t)
                totals[i] = totals[i] + confusion(mask, scene.truth, dt)
    return [Trial(dict(p), c) for p, c in zip(settings, totals)]


def _near(values: Sequence[Any], center: Any) -> list[Any]:
    return [center] + [v for v in values if v != center]


def tune_miem(contender: Contender, scenes: Sequence[Scene]) -> dict[str, Any]:
    """The three-stage search of miem's settings (module docstring).

    Returns
    -------
    dict
        ``trials`` (every Trial, in search order), ``winner`` (the best scale-free Trial),
        ``winner_steps`` (the best Trial that gives a length in steps, or None) and ``stages``
        (the winner after each stage).
    """
    trials: list[Trial] = []
    seen: set[str] = set()

    def run(settings: list[dict]) -> list[Trial]:
        fresh = []
        for p in settings:
            key = repr(sorted(p.items(), key=lambda kv: kv[0]))
            if key not in seen:
                seen.add(key)
                fresh.append(p)
        got = evaluate(contender, scenes, fresh)
        trials.extend(got)
        return got

    stages = []
    run(list(contender.structural))
    stages.append(best([t for t in trials if t.scale_free]))
    # Stage 2: the remaining switches, around both the scale-free and the step-scaled leader.
    leaders = [stages[-1]] + [best([t for t in trials if not t.scale_free])] * any(
        not t.scale_free for t in trials
    )
    for lead in leaders:
        base = dict(lead.params)
        stage2 = []
        extents = (None, 8, 12, 20) if miem_supports("edge_extent") else (None,)
        for md, ms, it, win, ext in itertools.product(
            (None, 3), (None, 1.5), (10, 30), (11, 21, 31), extents
        ):
            p = dict(base)
            p.update(min_directions=md, max_iterations=it, window=win)
            p["min_step_steps"] = ms
            if ext is not None or "edge_extent" in base:
                p["edge_extent"] = ext
            stage2.append(p)
        run(stage2)
    stages.append(best([t for t in trials if t.scale_free]))
    # Stage 3: theta0 and the height tolerance refined.
    base = dict(stages[-1].params)
    thetas = [base["theta0"]]
    if isinstance(base["theta0"], float):
        thetas = [base["theta0"] + d for d in (-10.0, -5.0, 0.0, 5.0, 10.0)]
        thetas = [t for t in thetas if 0.0 < t < 180.0]
        if miem_supports("height_tolerance"):
            thetas.append("auto")
    tols = [base.get("height_tolerance")]
    tol = base.get("height_tolerance")
    if isinstance(tol, str):
        k = float(tol[:-3])
        tols = [f"{v:g}rms" for v in (k - 1.0, k - 0.5, k, k + 0.5, k + 1.0) if v > 0]
    stage3 = []
    for t in thetas:
        for h in tols:
            p = dict(base)
            p["theta0"] = t
            if miem_supports("height_tolerance"):
                p["height_tolerance"] = h
            stage3.append(p)
    run(stage3)
    stages.append(best([t for t in trials if t.scale_free]))
    stepped = [t for t in trials if not t.scale_free]
    return {
        "trials": trials,
        "winner": stages[-1],
        "winner_steps": best(stepped) if stepped else None,
        "stages": stages,
    }
