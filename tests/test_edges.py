"""Burrs on edges: the edge scenes of the accuracy suite, the real-scan burr truth and its
scoring, and the reference's edge test on hand-built steps, creases and lips.

Fast: small grids only; the real-scan tests skip without ``../shared/data``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

ACCURACY = Path(__file__).resolve().parents[1] / "bench" / "accuracy"
sys.path.insert(0, str(ACCURACY))

import edge_scenes  # noqa: E402
import real_truth as rt  # noqa: E402
import suite  # noqa: E402
from miem import reference as ref  # noqa: E402

# --------------------------------------------------------------------------------------------
# synthetic edge scenes


@pytest.mark.parametrize("kind", edge_scenes.EDGE_KINDS)
def test_edge_scene_truth(kind: str) -> None:
    a = edge_scenes.make_edge_scene(kind, 7, step=0.1, noise=0.01)
    b = edge_scenes.make_edge_scene(kind, 7, step=0.1, noise=0.01)
    assert np.array_equal(a.points, b.points, equal_nan=True)
    t = a.truth
    finite = np.isfinite(a.points).all(-1)
    assert np.array_equal(~finite, t == edge_scenes.DROPOUT)
    assert np.array_equal(a.region >= 0, t == edge_scenes.DEFECT)
    assert (t == edge_scenes.EDGE).any() and (t == edge_scenes.DEFECT).any()
    assert set(np.unique(a.region[a.region >= 0])) <= set(range(len(a.region_height)))
    assert ((a.region_height >= 0.05) & (a.region_height <= 0.5)).all()
    z = a.points[..., 2][finite]
    assert np.allclose(z, np.round(z / 0.001) * 0.001, atol=1e-9)  # 1 um quantisation
    dy = np.diff(a.points[:, :, 1], axis=0)
    rows = np.nanmedian(dy, axis=1)
    assert rows.min() > 0 and rows.max() >= 2 * rows.min() - 1e-12  # uneven profile spacing
    if kind == "edge_cut":
        assert (~finite).mean() > 0.2  # the part ends: no return beyond the outline


def test_edge_specs_split() -> None:
    test = [s for s in suite.specs("test", real=False) if s.group in suite.EDGE_KINDS]
    tune = [s for s in suite.specs("tune", real=False) if s.group in suite.EDGE_KINDS]
    assert len(test) == 4 * len(suite.EDGE_KINDS) and len(tune) == 2 * len(suite.EDGE_KINDS)
    assert not {s.params["seed"] for s in test} & {s.params["seed"] for s in tune}
    sc = suite.build(test[0])
    assert sc.region is not None and sc.n_defects == len(sc.region_height)


# --------------------------------------------------------------------------------------------
# real truth scoring


def test_score_mask_hand_counts() -> None:
    cls = np.array([[0, 1, 1, 4], [0, 1, 5, 3], [0, 0, 1, 1]], dtype=np.uint8)
    dev = np.where(cls == 1, 0.5, 0.0)
    dev[2, 3] = 0.25
    regions = [np.array([1, 2, 5]), np.array([10, 11])]
    tr = rt.RealTruth(np.zeros((3, 4, 3)), dev, cls, regions, np.array([0.5, 0.25]), 0.1)
    flagged = np.zeros((3, 4), bool)
    flagged[0, 1] = flagged[0, 0] = flagged[0, 3] = flagged[1, 2] = True
    s = rt.score_mask(flagged, tr)
    # BURR cells (0,1) (0,2) (1,1) (2,2) (2,3): one flagged; CLEAN (0,0) flagged; the
    # don't-care (0,3) and uncovered (1,2) cells are not scored.
    assert (s.tp, s.fn, s.fp) == (1, 4, 1)
    assert s.precision == pytest.approx(0.5) and s.recall == pytest.approx(0.2)
    assert (s.regions, s.regions_found, s.regions_tall, s.regions_tall_found) == (2, 1, 1, 1)
    with pytest.raises(ValueError, match="shape"):
        rt.score_mask(np.zeros((2, 2), bool), tr)


@pytest.mark.skipif(not rt.available(), reason="shared/data/real not present")
def test_real_truth_registration_and_the_lip_layer() -> None:
    tr = rt.truth()
    assert tr.grid.shape == (426, 724, 3)
    assert tr.nn_median < 0.15  # the golden sample lies on the scan (registration)
    covered = np.isfinite(tr.dev)
    clean = tr.classes == rt.CLEAN
    assert clean.sum() > 0.8 * covered.sum()
    # Geometry, not the code's output: in profiles 310-314 a layer stands about 2 mm above the
    # wall top of profile 309 next to it; every covered point of it is a burr.
    z = tr.grid[..., 2]
    top = np.nanmedian(z[305:310, 250:350])
    layer = (z[310:315, 250:350] > top + 1.5) & covered[310:315, 250:350]
    assert layer.sum() > 100
    assert (tr.classes[310:315, 250:350][layer] == rt.BURR).all()


# --------------------------------------------------------------------------------------------
# the reference's edge test on hand-built scans


def _grid(z: np.ndarray, step: float = 0.1) -> np.ndarray:
    h, w = z.shape
    x, y = np.meshgrid(np.arange(w) * step, np.arange(h) * step)
    return np.stack([x, y, z], axis=-1)


def _noise(shape: tuple[int, int], seed: int = 3, sigma: float = 0.002) -> np.ndarray:
    return np.random.default_rng(seed).normal(0.0, sigma, shape)


def _edge_labels(g: np.ndarray) -> np.ndarray:
    res = ref.detect(g, preset="recommended")
    return ref.edge_test(g, res.labels, window=11, tolerance=8.0, max_iterations=10)[0]


@pytest.mark.parametrize("kind", ["step", "crease", "outline", "valley", "bead"])
def test_clean_features_stay_clean(kind: str) -> None:
    h, w = 40, 40
    cols = np.arange(w)[None, :].repeat(h, 0)
    z = _noise((h, w))
    if kind == "step":
        z = z - 2.0 * (cols >= 20)
    elif kind == "crease":
        z = z - np.tan(np.radians(30)) * np.maximum(cols - 20, 0) * 0.1  # convex: falls away
    elif kind == "valley":  # concave crease with a lip: not tested (a designed fillet looks so)
        z = z + np.tan(np.radians(30)) * np.maximum(cols - 20, 0) * 0.1
        z[12:28, 18:20] += 0.1
    elif kind == "bead":  # a designed bead across every profile: the same plane on both sides
        z[:, 20] += 0.3
    else:
        z[:, 20:] = np.nan
    labels = _edge_labels(_grid(z))
    assert not (labels == ref.ABNORMAL).any()


@pytest.mark.parametrize("kind", ["step", "outline", "crease"])
def test_lip_before_the_feature_is_abnormal(kind: str) -> None:
    h, w = 40, 40
    cols = np.arange(w)[None, :].repeat(h, 0)
    z = _noise((h, w))
    if kind == "step":
        z = z - 2.0 * (cols >= 20)
    elif kind == "crease":
        z = z - np.tan(np.radians(30)) * np.maximum(cols - 20, 0) * 0.1  # convex: falls away
    else:
        z[:, 20:] = np.nan
    lip = np.zeros((h, w), bool)
    lip[12:28, 18:20] = True  # the last two points before the feature, 16 profiles long
    z = z + 0.1 * lip
    labels = _edge_labels(_grid(z))
    flagged = labels == ref.ABNORMAL
    assert flagged[lip].all()  # 0.1 mm = 50 noise sigmas above the top surface
    assert not (flagged & ~lip).any()
