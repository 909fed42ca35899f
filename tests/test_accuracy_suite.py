"""Fast tests of the accuracy benchmark's building blocks (``bench/accuracy``).

Scoring against hand-computed confusion counts, scene determinism, and the consistency of the
generated truth labels (injected defect counts, codes, splits). No contender is run here.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

ACCURACY = Path(__file__).resolve().parents[1] / "bench" / "accuracy"
sys.path.insert(0, str(ACCURACY))

import score
import suite
from miem import simulate as sim

# --------------------------------------------------------------------------------------------
# scoring


def test_confusion_hand_counts() -> None:
    truth = np.array(
        [
            [0, 0, 1, 1],
            [2, 2, 1, 0],
            [3, 4, 0, 0],
        ],
        dtype=np.uint8,
    )
    flagged = np.array(
        [
            [1, 0, 1, 0],
            [1, 0, 1, 0],
            [1, 1, 0, 0],
        ],
        dtype=bool,
    )
    c = score.confusion(flagged, truth, seconds=0.5)
    # defects at (0,2), (0,3), (1,2): two flagged; normal (0,0) flagged; edge (1,0) flagged;
    # the dropout (2,0) and the unknown (2,1) cells are flagged but not scored.
    assert (c.tp, c.fn, c.fp_normal, c.fp_edge) == (2, 1, 1, 1)
    assert (c.n_normal, c.n_edge, c.n_defect, c.fp) == (5, 2, 3, 2)
    assert c.precision == pytest.approx(2 / 4)
    assert c.recall == pytest.approx(2 / 3)
    assert c.f1 == pytest.approx(2 * 2 / (2 * 2 + 2 + 1))
    assert c.edge_fa == pytest.approx(1 / 2)
    assert c.normal_fa == pytest.approx(1 / 5)
    assert c.seconds == 0.5


def test_counts_add_and_empty_ratios() -> None:
    a = score.Counts(tp=3, fn=1, fp_normal=2, fp_edge=0, n_normal=100, n_edge=0, seconds=1.0)
    b = score.Counts(tp=1, fn=3, fp_normal=0, fp_edge=4, n_normal=50, n_edge=40, seconds=2.0)
    t = score.Counts.total([a, b])
    assert t == a + b
    assert (t.tp, t.fn, t.fp, t.n_normal, t.n_edge, t.seconds) == (4, 4, 6, 150, 40, 3.0)
    assert t.f1 == pytest.approx(8 / (8 + 6 + 4))  # micro average, not the mean of the F1s
    assert math.isnan(a.edge_fa)  # no edge cells
    empty = score.Counts()
    assert math.isnan(empty.precision) and math.isnan(empty.recall) and math.isnan(empty.f1)
    assert score.Counts.total([]) == empty


def test_confusion_perfect_and_shape_check() -> None:
    truth = np.zeros((4, 5), dtype=np.uint8)
    truth[1, 1] = 1
    truth[:, 4] = 2
    c = score.confusion(truth == 1, truth)
    assert (c.precision, c.recall, c.f1, c.edge_fa, c.normal_fa) == (1.0, 1.0, 1.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="shape"):
        score.confusion(np.zeros((4, 4), bool), truth)


def test_kind_counts() -> None:
    kinds = np.array([["", "spike", "spike"], ["ridge", "ridge", ""]])
    flagged = np.array([[1, 1, 0], [1, 1, 1]], dtype=bool)
    assert score.kind_counts(flagged, kinds) == {"spike": (1, 2), "ridge": (2, 2)}


# --------------------------------------------------------------------------------------------
# suite


def test_specs_splits_are_disjoint_and_cover_every_kind() -> None:
    test = suite.specs("test", real=False)
    tune = suite.specs("tune", real=False)
    assert len({s.name for s in test + tune}) == len(test) + len(tune)
    seeds = {s.params["seed"] for s in test} & {s.params["seed"] for s in tune}
    assert not seeds
    for split in (test, tune):
        groups = [s.group for s in split]
        assert set(suite.KINDS) <= set(groups)
        assert "paper" in groups
    assert sum(s.group == "spike" for s in test) == 4
    assert sum(s.group == "spike" for s in tune) == 2
    with pytest.raises(ValueError, match="split"):
        suite.specs("train")


def test_scene_is_deterministic() -> None:
    spec = next(s for s in suite.specs("test", real=False) if s.group == "spatter")
    a, b = suite.build(spec), suite.build(spec)
    assert np.array_equal(a.points, b.points, equal_nan=True)
    assert np.array_equal(a.truth, b.truth)
    assert np.array_equal(a.kinds, b.kinds)


@pytest.mark.parametrize("split", ["test", "tune"])
def test_synthetic_truth_is_consistent(split: str) -> None:
    for spec in suite.specs(split, real=False):
        sc = suite.build(spec)
        t = sc.truth
        assert set(np.unique(t)) <= {suite.NORMAL, suite.DEFECT, suite.EDGE, suite.DROPOUT}
        finite = np.isfinite(sc.points).all(axis=-1)
        assert np.array_equal(~finite, t == suite.DROPOUT), spec.name
        assert np.array_equal(sc.kinds != "", t == suite.DEFECT), spec.name
        if spec.source != "synthetic":
            continue
        _, count, (lo, hi) = suite._KIND_SPECS[spec.group]
        assert sc.n_defects == count, spec.name
        scan = sim.make_scan(**spec.params)
        cells = sum(len(d.cells) for d in scan.defects)
        assert cells == int(np.count_nonzero(t == suite.DEFECT)), spec.name
        for d in scan.defects:
            peak = abs(d.offset) / sc.step
            assert lo - 1e-9 <= peak <= hi + 1e-9, (spec.name, d)
        assert 0.2 <= sc.step <= 0.5
        assert 120 <= sc.shape[0] <= 160 and 120 <= sc.shape[1] <= 160
        edge_surface = spec.params["surface"] in ("crease", "flange", "fillet", "strip")
        assert bool((t == suite.EDGE).any()) == edge_surface, spec.name


@pytest.mark.skipif(not suite.real_available(), reason="shared/data/real not present")
def test_real_scene_truth() -> None:
    spec = next(s for s in suite.specs("test") if s.source == "real")
    sc = suite.build(spec)
    t = sc.truth
    assert set(np.unique(t)) <= {suite.NORMAL, suite.DEFECT, suite.DROPOUT, suite.UNKNOWN}
    assert sc.n_defects == sum(spec.params["defects"].values())
    # defects sit on normal surface, at least 3 cells from unknown cells and dropouts
    defect = t == suite.DEFECT
    near_bad = sim._dilate((t == suite.UNKNOWN) | (t == suite.DROPOUT), 3)
    assert not (defect & near_bad).any()
    assert (t == suite.UNKNOWN).any() and (t == suite.NORMAL).sum() > 5000
