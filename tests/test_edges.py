"""Burrs on edges: the edge scenes of the accuracy suite, the real-scan burr truth and its
scoring, and the reference's edge test on hand-built steps, creases and lips.

Fast: small grids only; the real-scan tests skip without ``../shared/data``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

ACCURACY = Path(__file__).resolve().parents[1] / "bench" / "accuracy"
sys.path.insert(0, str(ACCURACY))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import edge_pool  # noqa: E402
import edge_scenes  # noqa: E402
import real_truth as rt  # noqa: E402
import suite  # noqa: E402
from stream_batch import stream_labels  # noqa: E402
import miem  # noqa: E402
from miem import _core  # noqa: E402
from miem import reference as ref  # noqa: E402
from miem import simulate  # noqa: E402

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
    assert len(test) == 10 * len(suite.EDGE_KINDS) and len(tune) == 2 * len(suite.EDGE_KINDS)
    assert not {s.params["seed"] for s in test} & {s.params["seed"] for s in tune}
    sc = suite.build(test[0])
    assert sc.region is not None and sc.n_defects == len(sc.region_height)


def test_dev_set_is_apart_from_every_split() -> None:
    """The dev set (suite.dev_specs, where the valley rule's bounds were chosen) shares no
    seed with the tuning, test or third split, and holds every non-edge kind and the paper."""
    dev = suite.dev_specs()
    seeds = {(s.source, s.params["seed"]) for s in dev}
    for split in ("tune", "test", "third"):
        assert not seeds & {(s.source, s.params["seed"]) for s in suite.specs(split, real=False)}
    assert {s.group for s in dev} == set(suite.KINDS) | {"paper"}
    assert len(dev) == 24 * (len(suite.KINDS) + 1)


def test_edge_pool_is_apart_from_every_split_and_covers_every_step() -> None:
    """The pool of generated edge scenes (edge_pool.py, where rule variants are compared beyond
    the tuning split's 2 scenes per kind) shares no edge seed with the tuning, test or third
    split or the dev set; each kind meets every step on both line shapes and every noise; the
    specs build the scenes edge_scenes makes from the same arguments."""
    specs = edge_pool.pool_specs(9000, 40) + edge_pool.pool_specs(9100, 40)
    seeds = {(s.group, s.params["seed"]) for s in specs}
    assert len(seeds) == len(specs) == 2 * 40 * len(suite.EDGE_KINDS)
    for split in ("tune", "test", "third"):
        assert not seeds & {(s.group, s.params["seed"]) for s in suite.specs(split, real=False)}
    assert not {s.params["seed"] for s in specs} & {s.params["seed"] for s in suite.dev_specs()}
    for kind in suite.EDGE_KINDS:
        mine = [s.params for s in specs if s.group == kind]
        assert {(p["step"], p["curved"]) for p in mine} == {
            (st, cv) for st in (0.05, 0.1, 0.2, 0.5) for cv in (False, True)}
        assert {p["noise"] for p in mine} == {0.005, 0.01, 0.02}
    spec = specs[5]
    sc = suite.build(spec)
    e = edge_scenes.make_edge_scene(**spec.params)
    np.testing.assert_array_equal(sc.truth, e.truth)
    assert sc.step == spec.params["step"] == 0.1 and spec.params["curved"] is True
    with pytest.raises(ValueError, match="per_kind"):
        edge_pool.pool_specs(9000, 101)


def test_edge_pool_overrides_reach_the_detector(capsys) -> None:
    """edge_pool.py --set / --cloud-set: FIELD=VALUE read as literals (else strings), refused
    without '=', and passed to the detector: the printed found count for one scene per kind
    is the one miem.detect gives with that override, counted here from the truth; so are the
    false alarms, which the override changes on the wall scene (so a dropped override fails)."""
    assert edge_pool.overrides(["edge_tolerance=3.5", "height_tolerance=4.5rms",
                                "scales=(1, 2)", "min_step=None"]) == {
        "edge_tolerance": 3.5, "height_tolerance": "4.5rms", "scales": (1, 2), "min_step": None}
    assert edge_pool.overrides(None) == {}
    with pytest.raises(ValueError, match="FIELD=VALUE"):
        edge_pool.overrides(["edge_tolerance"])
    with pytest.raises(SystemExit):  # clouds' overrides without the clouds: refused
        edge_pool.main(["--per-kind", "1", "--cloud-set", "edge_tolerance=2.0"])
    assert "--cloud-set" in capsys.readouterr().err
    edge_pool.main(["--per-kind", "1", "--set", "edge_tolerance=2.0"])
    out = capsys.readouterr().out
    assert "grid overrides {'edge_tolerance': 2.0}" in out
    for spec in edge_pool.pool_specs(9000, 1):
        sc = suite.build(spec)
        burr = sc.truth == 1
        flagged = miem.detect(sc.points, edge_tolerance=2.0).labels == miem.ABNORMAL
        fa_edge, fa_normal = int((flagged & (sc.truth == 2)).sum()), int(
            (flagged & (sc.truth == 0)).sum())
        line = next(ln for ln in out.splitlines() if ln.split()[1] == spec.group)
        assert f"found {int((burr & flagged).sum())}/{int(burr.sum())} " in line
        assert f" FA {fa_edge}+{fa_normal} " in line
        if spec.group == "edge_wall":
            default = miem.detect(sc.points).labels == miem.ABNORMAL
            assert int((default & (sc.truth != 1)).sum()) != fa_edge + fa_normal


# --------------------------------------------------------------------------------------------
# real truth scoring


def test_score_mask_hand_counts() -> None:
    cls = np.array([[0, 1, 1, 4], [0, 1, 5, 3], [0, 0, 1, 1]], dtype=np.uint8)
    dev = np.where(cls == 1, 0.5, 0.0)
    dev[2, 3] = 0.25
    regions = [np.array([1, 2, 5]), np.array([10, 11])]
    tr = rt.RealTruth(np.zeros((3, 4, 3)), dev, cls, regions, np.array([0.5, 0.25]), 0.1,
                      cls == 0)
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


def test_truth_classes_and_regions_by_hand() -> None:
    """real_truth step 4 on a hand-made deviation row: CLEAN below 0.15, BURR above 0.25 up to
    FOREIGN (5 mm), don't-care between and beyond (material 6 mm out is not this part's), NaN
    on a finite cell uncovered, on a missing cell a dropout; the burr regions hold the cells
    with 0.2 < dev <= 5 only, so two burrs parted by a foreign cell are two regions."""
    dev = np.array([[0.0, 0.1, 0.18, 0.3, 6.0, 0.4, -0.3, 5.0, np.nan, np.nan]])
    fin = np.array([[True] * 9 + [False]])
    cls = rt._classes(dev, fin)
    c, b, d, u, o = rt.CLEAN, rt.BURR, rt.DONTCARE, rt.UNCOVERED, rt.DROPOUT
    assert cls.tolist() == [[c, c, d, b, d, b, d, b, u, o]]
    assert [r.tolist() for r in rt._burr_regions(dev)] == [[3], [5], [7]]


def test_error_bands_hand_counts() -> None:
    """edges.py's "where the error goes" table: misses (and their EDGE share) and false alarms
    per band of profiles, counted by hand on a 25 x 3 truth with bands of 10 rows."""
    import edges

    cls = np.zeros((25, 3), dtype=np.uint8)  # CLEAN
    cls[12, 0] = cls[13, 0] = cls[22, 1] = rt.BURR
    cls[5, 0] = rt.DONTCARE
    labels = np.full((25, 3), miem.NORMAL, dtype=np.uint8)
    labels[12, 0] = miem.EDGE  # missed, EDGE
    labels[22, 1] = miem.ABNORMAL  # found
    labels[1, 1] = labels[2, 2] = labels[21, 0] = miem.ABNORMAL  # false alarms (bands 0, 0, 2)
    labels[5, 0] = miem.ABNORMAL  # don't care: not a false alarm
    tr = rt.RealTruth(np.zeros((25, 3, 3)), np.zeros((25, 3)), cls, [], np.zeros(0), 0.1,
                      cls == rt.CLEAN)
    rows = edges.error_bands({"recommended": (None, 0.0, 0.0, labels)}, tr, band=10, top=2)
    assert "Missed BURR cells 2 (1 of them EDGE, the rest NORMAL); false alarms 3." in rows[2]
    assert rows[-2:] == ["| 10-19 | 2 (1) | | 0-9 | 2 |", "| 0-9 | 0 (0) | | 20-24 | 1 |"]


def test_local_offset_by_hand() -> None:
    """real_truth step 5 on a hand-built deviation field (0.05 x 0.1 mm grid, 20 x 20 mm): the
    left half lies 0.1 mm under the golden, the right half 0.04 mm over it (+-0.01 mm in a
    checkerboard). A 4 mm band of wall-case cells (dev +0.04) in the left half and a 4 mm band
    of burr cells (dev 0.3) in the right half cover most of the 4 mm disc of the cells in and
    next to them: counted as reference cells they would carry the median; they are not, so
    every cell 4.4 mm or more from the seam (x = 10 mm) gets its own half's offset, to the 2 um
    step. A corner with no reference cell within 4 mm has none (NaN)."""
    h, w = 200, 400
    x, y = np.meshgrid(np.arange(w) * 0.05, np.arange(h) * 0.1)
    grid = np.stack([x, y, np.zeros_like(x)], axis=-1)
    dev = np.where(x < 10.0, -0.1, 0.04)
    dev = dev + np.where((np.arange(h)[:, None] + np.arange(w)[None, :]) % 2 == 0, 0.01, -0.01)
    wall = (x >= 2.0) & (x < 6.0)
    dev[wall] = 0.04
    burr = (x >= 14.0) & (x < 18.0)
    dev[burr] = 0.3
    corner = (x >= 10.0) & (y >= 15.0)
    wall |= corner  # no reference cell there
    off = rt.local_offset(grid, dev, wall)
    left = (x < 10.0 - 4.4) & (y < 20.0)
    right = (x > 10.0 + 4.4) & (y < 15.0 - 4.4)
    # the median of an even mix of -0.11 and -0.09 lies between them (either is a median)
    assert np.all((off[left] >= -0.11 - 1e-9) & (off[left] <= -0.09 + 1e-9))
    assert np.all((off[right] >= 0.03 - 1e-9) & (off[right] <= 0.05 + 1e-9))
    assert (left & wall).sum() > 5_000 and (right & burr).sum() > 5_000
    deep = (x > 10.0 + 4.4) & (y > 15.0 + 4.4)
    assert deep.any() and np.isnan(off[deep]).all()


@pytest.mark.skipif(not rt.available(), reason="shared/data/real not present")
def test_real_truth_registration_lip_layer_and_outline_returns() -> None:
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
    # Returns from below the lower outline (profiles 382-387): more than 5 mm below the top
    # of profiles 375-379 next to them, they are no burr, whatever their distance to the golden
    # sample's wall: not one is BURR, nor in a burr region.
    top = np.nanmedian(z[375:380])
    deep = np.zeros(z.shape, dtype=bool)
    deep[382:388] = np.nan_to_num(z[382:388], nan=np.inf) < top - 5.0
    assert (deep & covered).sum() > 100
    assert not (tr.classes[deep] == rt.BURR).any()
    assert not np.isin(np.flatnonzero(deep), np.concatenate(tr.regions)).any()


@pytest.mark.skipif(not rt.available(), reason="shared/data/real not present")
def test_real_scan_min_step_auto_and_flat_surface() -> None:
    """On the real scan (uneven profile spacing, 1 um z steps): the core's automatic min_step is
    the reference's rule to the last bit, and flat surface (real_truth's mask, derived from the
    golden sample) is EDGE on under 1 % of its cells with it, against several % without."""
    tr = rt.truth(local=False)
    g = tr.grid
    res = miem.detect(g, heights="abnormal")
    fin = np.isfinite(g).all(axis=-1)
    assert res.params["min_step"] == ref._auto_min_step(g.astype(np.float64), fin)
    assert res.params["min_step"] is not None and res.params["min_step"] > 0.1
    off = miem.detect(g, min_step=None, edge_tolerance=None, heights="abnormal")
    share = (res.labels[tr.flat] == miem.EDGE).mean()
    share_off = (off.labels[tr.flat] == miem.EDGE).mean()
    assert share < 0.01 < share_off


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


@pytest.mark.parametrize("kind", ["step", "crease", "outline", "valley", "fillet", "bead", "strip",
                                  "rib", "roof", "ledge", "chamfer", "round"])
def test_clean_features_stay_clean(kind: str) -> None:
    h, w = 40, 40
    cols = np.arange(w)[None, :].repeat(h, 0)
    z = _noise((h, w))
    if kind == "strip":  # the paper's edge strip: one sample wide, 3 steps tall (a feature line)
        z[:, 20] += 0.3
    elif kind == "rib":  # a designed rib 2 mm tall, wider (12 cells) than the half-window (5)
        z = z + 2.0 * ((cols >= 14) & (cols < 26))
        g = _grid(z)  # the height passes flag its crest (a 21-cell window): the edge test adds none
        base = ref.detect(g, preset="recommended").labels
        np.testing.assert_array_equal(_edge_labels(g), base)
        return
    elif kind == "roof":  # a convex ridge, flanks of 40 degrees: less steep than 45, no fin
        z = z - np.tan(np.radians(40)) * np.abs(cols - 20) * 0.1
    elif kind == "ledge":  # a terrace 4 cells wide between two drops (a staircase going down)
        z = z - 1.0 * (cols >= 18) - 1.0 * (cols >= 22)
    elif kind == "chamfer":  # a 40-degree chamfer 3 cells wide, then a wall 2 mm down: below
        # the top's plane, above the floor's, but less steep than 45 degrees (not hanging)
        x = np.clip(cols - 19, 0, 3) * 0.1
        z = z - np.tan(np.radians(40)) * x - 2.0 * (cols >= 23)
    elif kind == "round":  # a rounded edge (radius 0.5 mm, a quarter circle), then 2 mm down
        x = np.clip(cols - 19, 0, 4) * 0.1
        z = z - (0.5 - np.sqrt(0.25 - x * x)) - 2.0 * (cols >= 24)
    elif kind == "step":
        z = z - 2.0 * (cols >= 20)
    elif kind == "crease":
        z = z - np.tan(np.radians(30)) * np.maximum(cols - 20, 0) * 0.1  # convex: falls away
    elif kind == "valley":  # a concave crease (30 degrees)
        z = z + np.tan(np.radians(30)) * np.maximum(cols - 20, 0) * 0.1
    elif kind == "fillet":  # a concave crease rounded over about 1 mm: above both faces' planes
        # (0.2 mm at the line), but rising all the way: no lip (SPEC "Edge test" step 6)
        x = (cols - 20) * 0.1
        z = z + np.tan(np.radians(30)) * 0.3 * np.logaddexp(0.0, x / 0.3)
    elif kind == "bead":  # a designed bead across every profile: the same plane on both sides
        z[:, 20] += 0.3
    else:
        z[:, 20:] = np.nan
    labels = _edge_labels(_grid(z))
    assert not (labels == ref.ABNORMAL).any()


@pytest.mark.parametrize("kind", ["step", "outline", "crease", "valley"])
def test_lip_before_the_feature_is_abnormal(kind: str) -> None:
    h, w = 40, 40
    cols = np.arange(w)[None, :].repeat(h, 0)
    z = _noise((h, w))
    if kind == "step":
        z = z - 2.0 * (cols >= 20)
    elif kind == "crease":
        z = z - np.tan(np.radians(30)) * np.maximum(cols - 20, 0) * 0.1  # convex: falls away
    elif kind == "valley":  # concave: the face beyond rises (step 6, lips at a concave feature)
        z = z + np.tan(np.radians(30)) * np.maximum(cols - 20, 0) * 0.1
    else:
        z[:, 20:] = np.nan
    lip = np.zeros((h, w), bool)
    lip[12:28, 18:20] = True  # the last two points before the feature, 16 profiles long
    z = z + 0.1 * lip
    labels = _edge_labels(_grid(z))
    flagged = labels == ref.ABNORMAL
    assert flagged[lip].all()  # 0.1 mm = 50 noise sigmas above the top surface
    assert not (flagged & ~lip).any()


def _valley_lip_z(fold: float, h: int = 40, w: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """A concave crease at column 20 (the face beyond rises at ``fold`` degrees) with a lip
    0.1 mm tall on the last two columns before it, rows 12-27; returns z and the lip mask."""
    cols = np.arange(w)[None, :].repeat(h, 0)
    z = _noise((h, w)) + np.tan(np.radians(fold)) * np.maximum(cols - 20, 0) * 0.1
    lip = np.zeros((h, w), bool)
    lip[12:28, 18:20] = True
    return z + 0.1 * lip, lip


def test_lip_at_a_concave_feature_needs_a_dip_then_a_rise() -> None:
    """SPEC "Edge test" step 6, lips at a concave feature, on NORMAL labels (11-cell
    sub-windows, 8 rms, so D = max(16 rms, half the lip's height) = 0.05 mm): before a
    30-degree valley the lip's inner rows fire, column 18 at the first pass (its left side is
    clean, z = 0; beyond it the crease cell at column 20 lies 0.1 mm lower: the dip; then the
    face rises 0.17 mm above z = 0 at column 23), column 19 at the second (with column 18 out
    of the support its left side is clean). Must not fire (in the lip's inner rows) when the
    same lip stands on a plane (no rise beyond the dip: a bead, which the height test judges)
    nor when the cells beyond the lip rise at once (a ramp up from the lip's height: no dip, as
    on a fillet)."""
    rows = slice(17, 23)  # whose sub-windows lie within the lip's rows 12-27 (r = 5)
    for case, fires in (("valley", True), ("plane", False), ("ramp", False)):
        z, lip = _valley_lip_z(0.0 if case == "plane" else 30.0)
        if case == "ramp":  # beyond the lip the face starts at the lip's height
            z[:, 20:] += 0.1
        g = _grid(z)
        labels = np.zeros(lip.shape, np.uint8)
        for passes, cols in ((1, [18]), (10, [18, 19])):
            out = ref.edge_test(g, labels, window=11, tolerance=8.0, max_iterations=passes)[0]
            new = out == ref.ABNORMAL
            assert new[rows][:, cols].all() == fires and new[rows].any() == fires, case
            assert not (new & ~lip).any(), case
            if case == "valley" and passes == 1:
                assert not new[rows, 19].any(), case
    # by hand, at the first pass: row 20, column 18 over the left side's plane (z = 0, within
    # noise): the crease cell 2 columns on lies 0.1 lower, column 23 rises 0.3 tan(30) = 0.17
    # above z = 0: both more than D = 0.05
    z, _ = _valley_lip_z(30.0)
    assert z[20, 18] - z[20, 20] > 0.05 and z[20, 23] > 0.05


def _steep_valley_lip_z(beyond: float, h: int = 40, w: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """Sheet (z = 0) up to a 45-degree concave crease whose first cell, column 20, lies
    ``beyond`` mm up (the crease line between the columns); a lip 0.12 mm tall on column 19,
    rows 12-27, the last cell before it; returns z and the lip mask."""
    cols = np.arange(w)[None, :].repeat(h, 0)
    z = _noise((h, w)) + np.where(cols >= 20, beyond + (cols - 20) * 0.1, 0.0)
    lip = np.zeros((h, w), bool)
    lip[12:28, 19] = True
    return z + 0.12 * lip, lip


def test_lip_dips_at_itself_before_a_steep_valley(monkeypatch: pytest.MonkeyPatch) -> None:
    """SPEC "Edge test" step 6, lips at a concave feature, the dip at P itself: on a coarse
    scan of a steep concave crease the first cell beyond the lip has climbed already, so no
    cell beyond lies D lower than the lip, but the lip stands above the chord between its
    neighbours. By hand (11-cell sub-windows, 8 rms ~ 0.016 = t: D = max(2 t, half the lip's
    height) = 0.06 mm; P = column 19 over its left side's plane z = 0): the first cell beyond,
    column 20, lies 0.12 - 0.07 = 0.05 below P (not D: from there the surface rises, so no
    cell beyond dips by D; but more than 2 t), the chord from column 18 (0.12 below P) to
    column 20 passes 0.085 below P (> D); the last cell beyond, column 24, lies 0.47 above the
    left side's plane (the rise). The lip rule must not fire when the first cell beyond lies
    level with the lip (0.12: no dip at P, as at a terrace's edge or on a fillet); there the
    valley rule (step 6, valleys) does: P steps up 0.12 from the sheet, more than it rises
    onto that cell (0) plus 1.5 t, and the face beyond climbs, as a one-cell burr before a
    coarsely sampled concave crease does."""
    z, lip = _steep_valley_lip_z(0.07)
    t = 8 * 0.002
    assert 0.12 - 0.07 < 0.06 < (0.12 + 0.05) / 2 and 0.05 > 2 * t * 1.4
    rows = slice(17, 23)  # whose sub-windows lie within the lip's rows 12-27 (r = 5)
    labels = np.zeros(lip.shape, np.uint8)
    level = _grid(_steep_valley_lip_z(0.12)[0])
    for valleys in (True, False):  # the level case: the valley rule's, not the lip rule's
        if not valleys:
            monkeypatch.setattr(ref, "_VALLEY_HEIGHT", np.inf)
        out = ref.edge_test(level, labels, window=11, tolerance=8.0, max_iterations=1)[0]
        new = out == ref.ABNORMAL
        assert new[rows, 19].all() == valleys and not (new & ~lip).any(), valleys
    for beyond, fires in ((0.07, True), (0.12, False)):  # the lip rule alone
        g = _grid(_steep_valley_lip_z(beyond)[0])
        out = ref.edge_test(g, labels, window=11, tolerance=8.0, max_iterations=1)[0]
        new = out == ref.ABNORMAL
        assert new[rows, 19].all() == fires and new[rows].any() == fires, beyond
        assert not (new & ~lip).any(), beyond
    monkeypatch.undo()
    # the detector, core and reference, batch and stream: the lip and nothing else
    g = _grid(z)
    kw = {"preset": "recommended", "edge_tolerance": 8.0, "edge_window": 11}
    want = ref.detect(g, **kw).labels
    flagged = want == ref.ABNORMAL
    assert flagged[rows, 19].all() and not (flagged & ~lip).any()
    np.testing.assert_array_equal(miem.detect(g, **kw).labels, want)
    p = miem.default_params("stream").replace(edge_tolerance=8.0, edge_window=11)
    np.testing.assert_array_equal(stream_labels(g, p), miem.detect(g, params=p).labels)


def _outline_crop(resume: bool) -> tuple[np.ndarray, np.ndarray]:
    """A 48 x 64 crop of a generated cut scene (seed 9003, outside every split: 0.5 mm steps,
    0.02 mm noise, a curved outline with burr runs along it) and its burr mask. With
    ``resume`` the part's plane (fitted to its clean cells) returns 3 cells beyond the
    outline: a band of dropouts, not an outline."""
    e = edge_scenes.make_edge_scene("edge_cut", 9003, step=0.5, noise=0.02, curved=True)
    pts = np.ascontiguousarray(e.points[30:78, 50:114]).copy()
    burr = e.truth[30:78, 50:114] == suite.DEFECT
    if resume:
        z = pts[..., 2]
        fin = np.isfinite(z)
        clean = fin & ~burr
        a = np.c_[pts[clean][:, :2], np.ones(int(clean.sum()))]
        coef = np.linalg.lstsq(a, z[clean], rcond=None)[0]
        # the NaN cells more than 3 steps (4-connected) from a return
        far = ndimage.binary_erosion(~fin, iterations=3, border_value=1)
        x = (50 + np.arange(64))[None, :].repeat(48, 0) * 0.5  # the scene's columns
        y = np.nanmean(pts[..., 1], axis=1)[:, None].repeat(64, 1)
        noise = np.random.default_rng(1).normal(0.0, 0.02, int(far.sum()))
        pts[far] = np.c_[x[far], y[far], coef[0] * x[far] + coef[1] * y[far] + coef[2] + noise]
    return pts, burr


def test_lip_before_an_outline_that_its_run_fits(monkeypatch: pytest.MonkeyPatch) -> None:
    """SPEC "Edge test" step 5, outlines: burr runs along a cut whose sub-windows along the cut
    (they hold the run itself) fit them. With the rule the reference flags burr cells it
    misses without it (a tolerance bound of infinity), and nothing else; the core and the
    stream agree. Where the part's surface resumes 3 cells beyond the cut (a band of
    dropouts: no sub-window there is 90 % without returns), the rule adds nothing."""
    pts, burr = _outline_crop(resume=False)
    on = ref.detect(pts).labels == ref.ABNORMAL
    np.testing.assert_array_equal(miem.detect(pts).labels == miem.ABNORMAL, on)
    p = miem.default_params("stream")
    np.testing.assert_array_equal(stream_labels(pts, p) == miem.ABNORMAL, on)
    gap = _outline_crop(resume=True)[0]
    assert np.isfinite(gap[..., 2]).sum() > np.isfinite(pts[..., 2]).sum() + 100
    gap_on = ref.detect(gap).labels == ref.ABNORMAL
    monkeypatch.setattr(ref, "_OUTLINE_HEIGHT", np.inf)
    off = ref.detect(pts).labels == ref.ABNORMAL
    gained = on & ~off
    assert gained.sum() >= 10 and not (gained & ~burr).any() and not (on & ~burr).any()
    np.testing.assert_array_equal(ref.detect(gap).labels == ref.ABNORMAL, gap_on)


def _coarse_valley_z(kind: str, h: int = 40, w: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """Sheet (z = 0) sampled at 0.5 mm up to a 30-degree concave crease between columns 19 and
    20 (``"crease"``; ``"burr"``: with a burr 0.1 mm tall on column 19, rows 12-27, the last
    cell before the line; ``"fillet"``: the crease rounded over 0.3 mm); returns z and the
    burr mask."""
    cols = np.arange(w)[None, :].repeat(h, 0)
    x = (cols - 19.5) * 0.5
    t30 = np.tan(np.radians(30))
    face = t30 * 0.3 * np.logaddexp(0.0, x / 0.3) if kind == "fillet" else t30 * np.maximum(x, 0.0)
    burr = np.zeros((h, w), bool)
    if kind == "burr":
        burr[12:28, 19] = True
    return _noise((h, w)) + face + 0.1 * burr, burr


def test_valley_burr_before_a_coarse_concave_crease(monkeypatch: pytest.MonkeyPatch) -> None:
    """SPEC "Edge test" step 6, valleys. At 0.5 mm steps the face beyond a 30-degree concave
    crease climbs 0.14 mm by its first cell, so a 0.1 mm burr on the last cell before the line
    has no dip beyond it and stands only 0.028 above the chord of its neighbours (the lip's D
    is 0.05): no lip. By hand (11-cell sub-windows, 8 rms ~ 0.016 = t): P lies 0.1 above the
    left side's plane (z = 0) and 0.1 + 0.14 above the face's plane extended back (both more
    than 1.75 t); the face's centroid lies far above the left plane (more than 2 t); towards
    the left P steps up 0.1 from column 18 (on the plane), more than the rise from P onto
    column 20 (0.044) plus 1.5 t. The same crease without the burr, and rounded into a fillet
    (its last cell before the line 0.06 above the sheet's plane and 0.2 above the face's, but
    stepping up only 0.05 from column 18 while the surface beyond climbs 0.14 in one step),
    stay clean. Without the rule (a height bound of infinity) the burr is missed."""
    z, burr = _coarse_valley_z("burr")
    assert 0.1 > 1.75 * 0.016 and 0.1 > 0.044 + 1.5 * 0.016
    f = _coarse_valley_z("fillet")[0] - _noise((40, 40))  # the fillet's own profile, by hand
    assert abs(f[20, 19] - 0.0625) < 1e-3 and abs(f[20, 20] - f[20, 19] - 0.145) < 1e-3
    assert f[20, 19] - f[20, 18] < 0.145 + 1.5 * 0.016
    assert z[20, 20] - z[20, 19] > -0.05 and z[20, 19] - (z[20, 18] + z[20, 20]) / 2 < 0.05
    labels = np.zeros(burr.shape, np.uint8)
    for kind in ("burr", "crease", "fillet"):
        g = _grid(_coarse_valley_z(kind)[0], step=0.5)
        out = ref.edge_test(g, labels, window=11, tolerance=8.0, max_iterations=10)[0]
        np.testing.assert_array_equal(out == ref.ABNORMAL,
                                      burr if kind == "burr" else np.zeros_like(burr))
    g = _grid(z, step=0.5)
    kw = {"preset": "recommended", "edge_tolerance": 8.0, "edge_window": 11}
    want = ref.detect(g, **kw).labels
    np.testing.assert_array_equal(want == ref.ABNORMAL, burr)
    np.testing.assert_array_equal(miem.detect(g, **kw).labels, want)
    p = miem.default_params("stream").replace(edge_tolerance=8.0, edge_window=11)
    np.testing.assert_array_equal(stream_labels(g, p), miem.detect(g, params=p).labels)
    monkeypatch.setattr(ref, "_VALLEY_HEIGHT", np.inf)
    assert not (ref.edge_test(g, labels, window=11, tolerance=8.0, max_iterations=10)[0]
                == ref.ABNORMAL).any()


def test_valley_rule_leaves_a_curved_sheet_clean(monkeypatch: pytest.MonkeyPatch) -> None:
    """SPEC "Edge test" step 6, valleys, the guards chosen on scenes outside the test split: a
    curved sheet of the dev set at 0.5 mm steps (noise 0.01 mm, six 3 x 3 clusters; seed 8123,
    outside every split) has noise peaks that lie above the planes on both sides of them,
    extrapolated over a concave curve. With a height bound of 1.5 t, the far side's centroid
    over 1 t, a step up of 1 t and no bound on the angle between the planes (the first form
    of the rule) 14 of its clean cells were flagged; with the rule's bounds (1.75 t, 2 t, 1.5 t,
    more than 4 degrees) none is, and the core agrees."""
    spec = next(s for s in suite.dev_specs() if s.name == "dev-cluster3-3-curved")
    assert spec.params["step"] == 0.5 and spec.params["seed"] == 8123
    sc = suite.build(spec)
    clean = sc.truth != suite.DEFECT
    labels = ref.detect(sc.points).labels
    assert not ((labels == ref.ABNORMAL) & clean).any()
    assert (labels[~clean] == ref.ABNORMAL).all()
    np.testing.assert_array_equal(miem.detect(sc.points).labels, labels)
    for name, value in (("_VALLEY_HEIGHT", 1.5), ("_VALLEY_CENTROID", 1.0), ("_VALLEY_JUMP", 1.0),
                        ("_VALLEY_COS", 1.0 + 1e-9)):
        monkeypatch.setattr(ref, name, value)
    # (step 4's smooth-curved-surface rule, which came later, clears 4 of them by itself)
    assert ((ref.detect(sc.points).labels == ref.ABNORMAL) & clean).sum() == 10
    monkeypatch.setattr(ref, "_curved", lambda h, *a, **k: np.zeros(h.shape[1], dtype=bool))
    assert ((ref.detect(sc.points).labels == ref.ABNORMAL) & clean).sum() == 14


def _crease_crop(seed: int, noise: float, crop: tuple[slice, slice], n_burr: int,
                 at_least: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A crop of generated crease scene ``seed`` (0.5 mm steps): its points, burr cells and the
    reference's ABNORMAL cells, after checking that it holds ``n_burr`` burr cells, that the
    reference finds at least ``at_least`` of them and no other cell, and that the core (float64
    and float32) and the stream give the same cells."""
    e = edge_scenes.make_edge_scene("edge_crease", seed, step=0.5, noise=noise)
    pts = np.ascontiguousarray(e.points[crop]).copy()
    burr = e.truth[crop] == suite.DEFECT
    assert burr.sum() == n_burr
    on = ref.detect(pts).labels == ref.ABNORMAL
    assert (on & burr).sum() >= at_least and not (on & ~burr).any()
    for p in (pts, pts.astype(np.float32)):
        np.testing.assert_array_equal(miem.detect(p).labels == miem.ABNORMAL, on)
    stream = stream_labels(pts, miem.default_params("stream"))
    np.testing.assert_array_equal(stream == miem.ABNORMAL, on)
    return pts, burr, on


def test_valley_beside_a_far_side_that_is_not_clean(monkeypatch: pytest.MonkeyPatch) -> None:
    """SPEC "Edge test" step 6, valleys, level sub-windows: a 32 x 40 crop of a generated crease
    scene (seed 9017, outside every split: 0.5 mm steps, 0.01 mm noise, a straight concave
    crease of 21 degrees at 128 degrees across the scan, burr runs 1-4 cells wide before it).
    Beyond a burr cell the far sub-window holds the run's other cells or straddles the line,
    so it is not clean. Asking for two clean sub-windows (the rule's first form) the reference
    finds 20 of the crop's 128 burr cells; with two level ones at least 75, and no other cell;
    the core (float64 and float32) and the stream agree."""
    pts, burr, on = _crease_crop(9017, 0.01, np.s_[12:44, 0:40], 128, 75)
    # the first form: the valley rule given the clean sub-windows instead of the level ones
    clean_sides, valleys, seen = ref._clean_sides, ref._valleys, []

    def keep_clean(*args: object, **kw: object) -> tuple[np.ndarray, ...]:
        level, clean, tol = clean_sides(*args, **kw)
        seen.append(clean)
        return level, clean, tol

    monkeypatch.setattr(ref, "_clean_sides", keep_clean)
    monkeypatch.setattr(ref, "_valleys", lambda g, lab, cells, r, level, *rest: valleys(
        g, lab, cells, r, seen[-1], *rest))
    first = ref.detect(pts).labels == ref.ABNORMAL
    assert (first & burr).sum() <= 25 and not (first & ~on).any()


def test_valley_needs_a_crease_not_a_curved_surface(monkeypatch: pytest.MonkeyPatch) -> None:
    """SPEC "Edge test" step 6, valleys: the two planes meet at more than 4 degrees. The paper
    scan is noise-free and gently curved, with beads one sample wide and 1.5 mm tall (designed
    EDGE). A bead cell stands far above the level planes on both sides, and on a noise-free
    surface the tolerances are so small that the curvature alone puts one side's centroid more
    than 2 t above the other side's plane; but the two planes there meet at under a degree. With
    the bound, default detection flags exactly the 5 injected defects (core and reference);
    without it the reference flags bead cells too."""
    scan = simulate.paper_scan()
    pts, truth = scan.points, scan.truth
    want = truth == simulate.ABNORMAL
    assert want.sum() == 5
    on = ref.detect(pts).labels == ref.ABNORMAL
    np.testing.assert_array_equal(on, want)
    np.testing.assert_array_equal(miem.detect(pts).labels == miem.ABNORMAL, on)
    # a bead cell's left and right sub-windows (r = 7): planes less than a degree apart
    r, c = 100, 130
    assert truth[r, c] == simulate.EDGE
    sel = np.zeros(truth.shape, bool)
    sel[r, c] = True
    support = np.isfinite(pts[..., 2]) & (truth != simulate.EDGE)
    nrm = ref._side_fits(pts, support, ~np.isfinite(pts[..., 2]), sel, 7, pts[0, 0])[4]
    assert np.degrees(np.arccos(min(1.0, float(nrm[0, 0] @ nrm[1, 0])))) < 1.0
    monkeypatch.setattr(ref, "_VALLEY_COS", 1.0 + 1e-9)
    beads = (ref.detect(pts).labels == ref.ABNORMAL) & (truth == simulate.EDGE)
    assert beads.sum() >= 100


def test_lip_across_a_convex_crease(monkeypatch: pytest.MonkeyPatch) -> None:
    """SPEC "Edge test" step 6, crossings: a 28 x 32 crop of a generated crease scene (seed
    9007, outside every split: 0.5 mm steps, 0.02 mm noise, a straight convex fold of 19.5
    degrees, burr runs 1-4 cells wide along it). The far face's plane, extended over a burr
    cell on the near face, lies above the surface there: the cell fits that sub-window, so no
    other rule of step 6 flags it. With the rule the reference finds at least 75 of the
    crop's 80 burr cells and no other cell; without it at most 65 (and nothing the rule's form
    does not); the core (float64 and float32), whose shortcut must not settle a cell that fits,
    and the stream agree."""
    pts, burr, on = _crease_crop(9007, 0.02, np.s_[36:64, 54:86], 80, 75)
    monkeypatch.setattr(ref, "_crossings",
                        lambda proud_of, *rest: np.zeros(proud_of.shape[1], bool))
    first = ref.detect(pts).labels == ref.ABNORMAL
    assert (first & burr).sum() <= 65 and not (first & ~on).any()


def _flange_9318() -> tuple[np.ndarray, np.ndarray]:
    """Generated flange scene 9318 (outside every split: 0.2 mm steps, 0.005 mm noise, a
    straight rounded bend, burr runs on its last 1-4 points before the bend): points, burr
    cells."""
    e = edge_scenes.make_edge_scene("edge_flange", 9318, step=0.2, noise=0.005)
    return e.points, e.truth == suite.DEFECT


def test_lip_across_a_rounded_bend(monkeypatch: pytest.MonkeyPatch) -> None:
    """SPEC "Edge test" step 6, crossings, on a flange (_flange_9318). Beyond a burr cell the
    far sub-window spans the rounded bend: its centroid lies below the near face's plane, but
    it is rarely clean, so a rule asking for two clean faces (the lower envelope this rule
    replaced) left the cell to the far face's tangent plane, which it fits. With the rule the
    reference finds at least 50 of the scene's 114 burr cells and no other cell; without it
    at most 20; the core (float64 and float32) and the stream agree."""
    pts, burr = _flange_9318()
    assert burr.sum() == 114
    on = ref.detect(pts).labels == ref.ABNORMAL
    assert (on & burr).sum() >= 50 and not (on & ~burr).any()
    for p in (pts, pts.astype(np.float32)):
        np.testing.assert_array_equal(miem.detect(p).labels == miem.ABNORMAL, on)
    stream = stream_labels(pts, miem.default_params("stream"))
    np.testing.assert_array_equal(stream == miem.ABNORMAL, on)
    monkeypatch.setattr(ref, "_crossings",
                        lambda proud_of, *rest: np.zeros(proud_of.shape[1], bool))
    without = ref.detect(pts).labels == ref.ABNORMAL
    assert (without & burr).sum() <= 20 and not (without & ~on).any()


def test_lip_across_a_feature_clears_the_floor(monkeypatch: pytest.MonkeyPatch) -> None:
    """SPEC "Edge test" step 6, crossings: P must stand more than 2.5 floors above the near
    face (the floor: min_step / 2 here, 0.03 mm with min_step 0.06), where a scanner's
    resolution, not its noise, sets the tolerance. _flange_9318 with min_step 0.06: the core
    (float64 and float32) equals the reference, which finds at least 30 burr cells and no
    other cell; without the floor's bound at least 50, no other cell either (the bound only
    withholds flags, and the core's shortcut bounds the floor's part by it)."""
    pts, burr = _flange_9318()
    on = ref.detect(pts, min_step=0.06).labels == ref.ABNORMAL
    assert (on & burr).sum() >= 30 and not (on & ~burr).any()
    for p in (pts, pts.astype(np.float32)):
        np.testing.assert_array_equal(miem.detect(p, min_step=0.06).labels == miem.ABNORMAL, on)
    monkeypatch.setattr(ref, "_CROSSING_FLOOR", 0.0)
    loose = ref.detect(pts, min_step=0.06).labels == ref.ABNORMAL
    assert (loose & burr).sum() >= 50 and not (loose & ~burr).any() and (on <= loose).all()


def _fin_z(h: int = 40, w: int = 40, diagonal: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Sheet with a fin 1.5 mm tall and 4 cells (0.4 mm) wide standing on it, along the rows
    (or along a diagonal); returns z and the fin mask."""
    rows, cols = np.mgrid[0:h, 0:w]
    fin = (np.abs(cols - rows) < 2) if diagonal else ((cols >= 18) & (cols < 22))
    fin &= (rows >= 6) & (rows < h - 6)
    return _noise((h, w)) + 1.5 * fin, fin


@pytest.mark.parametrize("diagonal", [False, True])
def test_fin_is_abnormal(diagonal: bool) -> None:
    z, fin = _fin_z(diagonal=diagonal)
    if not diagonal:  # a step down beyond it: ground at two levels
        z = z - 1.0 * (np.arange(40)[None, :] >= 24)
    g = _grid(z)
    inner = fin.copy()  # a fin's two end cells of each line do not go on both ways
    inner[[6, 33], :] = False
    # the rule alone, on NORMAL labels, by hand: a fin cell has ground within r = 5 on both
    # sides at most ~0.5 mm (0.7 diagonally) apart, 1.5 mm or more below it; off the fin no
    # cell stands above ground on both sides
    labels = np.zeros(fin.shape, np.uint8)
    assert ref._fins(g, labels, fin, 5)[inner].all()
    assert not ref._fins(g, labels, ~fin, 5).any()
    # the edge test on NORMAL labels, the fin on flat sheet: the fin and nothing else (with the
    # step its cells next to it fit sub-windows that straddle fin, ground and step: a cell that
    # fits a clean sub-window stays as it is)
    g = _grid(_fin_z(diagonal=diagonal)[0])
    out = ref.edge_test(g, labels, window=11, tolerance=8.0, max_iterations=10)[0]
    assert (out == ref.ABNORMAL)[inner].all()
    assert not ((out == ref.ABNORMAL) & ~fin).any()
    # the detector: every inner fin cell (the ends too when the height passes flag them), no other
    flagged = _edge_labels(g) == ref.ABNORMAL
    assert flagged[inner].all() and not (flagged & ~fin).any()


def _hanging_z(h: int = 40, w: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """Sheet ending in a wall 2 mm down at column 20, with a burr hanging beyond it: column 20
    of rows 12-27 at 0.5 mm below the top (a shelf between top and floor); returns z and the
    burr mask."""
    cols = np.arange(w)[None, :].repeat(h, 0)
    z = _noise((h, w)) - 2.0 * (cols >= 20)
    burr = np.zeros((h, w), bool)
    burr[12:28, 20] = True
    z[burr] = _noise((h, w), seed=4)[burr] - 0.5
    return z, burr


def test_hanging_burr_is_abnormal() -> None:
    """A burr hanging 0.5 mm below the top beyond a wall 2 mm tall (SPEC "Edge test" step 6):
    below the top's plane (whose last support cell is 1-2 cells = 0.1-0.2 mm away: steeper than
    45 degrees), above the floor's (the sub-window beyond it holds only floor: clean), and the
    floor lies 1.5 mm further down (more than twice 0.5). The edge test on NORMAL labels flags
    the burr and nothing else; so does the detector. The same shelf 1 mm down (a staircase of
    two equal steps) is not hanging; the chamfer and the rounded edge before a wall are in
    test_clean_features_stay_clean."""
    z, burr = _hanging_z()
    g = _grid(z)
    labels = np.zeros(burr.shape, np.uint8)
    out = ref.edge_test(g, labels, window=11, tolerance=8.0, max_iterations=10)[0]
    assert (out == ref.ABNORMAL)[burr].all()
    assert not ((out == ref.ABNORMAL) & ~burr).any()
    flagged = _edge_labels(g) == ref.ABNORMAL
    assert flagged[burr].all() and not (flagged & ~burr).any()
    z[burr] -= 0.5  # 1 mm below the top, 1 mm above the floor: a ledge
    out = ref.edge_test(_grid(z), labels, window=11, tolerance=8.0, max_iterations=10)[0]
    assert not (out == ref.ABNORMAL).any()


def test_hanging_is_measured_from_the_tops_last_sample() -> None:
    """SPEC "Edge test" step 6, 45 degrees: measured from the nearest *ground* cell towards the
    top (NORMAL or EDGE), the top's last sample, which the angle passes often label EDGE.
    Sheet ending in a wall 2 mm down at column 20, its last two samples (columns 18-19) EDGE,
    column 20 of rows 12-27 hanging ``depth`` below the top (0.1 mm grid). Must fire at
    depth 0.25: 0.1 mm from the EDGE sample at column 19, 0.25^2 > 0.1^2 (steeper than 45
    degrees), floor 1.75 mm further down (> 2 x 0.25); measured from the nearest NORMAL cell
    (column 17, 0.3 mm away) it would not be (0.25^2 < 0.3^2). Must not fire at depth 0.09:
    0.09^2 < 0.1^2 (gentler than 45 degrees from the last sample: a chamfer or a rounded
    edge)."""
    h, w = 40, 40
    labels = np.zeros((h, w), np.uint8)
    labels[:, 18:20] = ref.EDGE
    for depth, fires in ((0.25, True), (0.09, False)):
        z, burr = _hanging_z(h, w)
        z[burr] = _noise((h, w), seed=4)[burr] - depth
        g = _grid(z)
        out = ref.edge_test(g, labels, window=11, tolerance=8.0, max_iterations=10)[0]
        flagged = out == ref.ABNORMAL
        assert flagged[burr].all() == fires and (flagged[burr].any() == fires), depth
        assert not (flagged & ~burr).any(), depth
        # the geometry the test rests on, by hand: below the top's plane (z ~ 0) by depth
        # (> 8 tolerances of 0.002 mm noise), 0.1 mm from column 19's sample, 0.3 from 17's
        p, q19, q17 = g[20, 20], g[20, 19], g[20, 17]
        assert (depth ** 2 > np.hypot(*(q19 - p)[:2]) ** 2) == fires
        assert depth ** 2 < np.hypot(*(q17 - p)[:2]) ** 2


def test_hanging_ledge_goes_on_from_its_drop() -> None:
    """SPEC "Edge test" step 6, the path of ABNORMAL cells: a ledge hanging 0.25 mm below the
    top beyond a wall 2 mm tall at column 20 (0.1 mm grid), columns 20-24 of rows 4-35.
    Columns 20-23 are ABNORMAL already (earlier passes); column 24 lies 0.5 mm from the top's
    last sample (column 19), farther than it lies deep (0.25^2 < 0.5^2: gentler than 45 degrees
    from there), but the path 19 -> 20 drops 0.25 mm over 0.1 mm (steeper than 45 degrees) and
    runs over ABNORMAL cells to it: column 24 hangs. Must not fire when the path is broken by a
    dropout (column 22 INVALID), nor when the path descends gently (columns 20-23 going down
    0.05 mm per 0.1 mm: a chamfer, whose cells another rule flagged). Checked on rows 11-28,
    whose 15-cell sub-windows lie within the ledge's rows (nearer its ends the top's
    sub-window takes in floor beyond the ledge and is not clean; there, seen diagonally, the
    ledge's end cells stand above the floor around them with the top rising beyond: lips at a
    concave feature, whatever the path)."""
    h, w = 40, 40
    cols = np.arange(w)[None, :].repeat(h, 0)
    rows, inner = slice(4, 36), slice(11, 29)
    for case, fires in (("ledge", True), ("dropout", False), ("chamfer", False)):
        z = _noise((h, w)) - 2.0 * (cols >= 25)
        z[:, 20:25] = -2.0 + _noise((h, w), seed=5)[:, 20:25]  # the wall: floor under the ledge
        z[rows, 20:25] = _noise((h, w), seed=4)[rows, 20:25] - 0.25
        if case == "chamfer":
            z[rows, 20:24] = -0.05 * (cols[rows, 20:24] - 19) + _noise((h, w), 6)[rows, 20:24]
        labels = np.zeros((h, w), np.uint8)
        labels[rows, 20:24] = ref.ABNORMAL
        if case == "dropout":
            z[rows, 22] = np.nan
            labels[rows, 22] = ref.INVALID
        g = _grid(z)
        out = ref.edge_test(g, labels, window=15, tolerance=8.0, max_iterations=1)[0]
        new = (out == ref.ABNORMAL) & (labels != ref.ABNORMAL)
        assert new[inner, 24].all() == fires and new[inner, 24].any() == fires, case
        assert not new[:, :24].any() and not new[:, 25:].any(), case
        # by hand: 0.5 mm from column 19's sample, 0.25 deep; the drop 19 -> 20 is steep
        p, q, first = g[20, 24], g[20, 19], g[20, 20]
        assert 0.25 ** 2 < np.hypot(*(q - p)[:2]) ** 2
        assert ((q - first)[2] > np.hypot(*(q - first)[:2])) == (case != "chamfer")


def _ledge_z(width: int, h: int = 40, w: int = 40, droop: float = 0.08,
             floor: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Sheet ending in a wall ``floor`` mm down at column 20 (0.1 mm grid), with material bent
    out level beyond it: columns 20 .. 20 + width - 1 of rows 4 .. h - 5 ``droop`` below the
    top; returns z and the ledge mask."""
    cols = np.arange(w)[None, :].repeat(h, 0)
    z = _noise((h, w)) - floor * (cols >= 20)
    ledge = np.zeros((h, w), bool)
    ledge[4:h - 4, 20:20 + width] = True
    z[ledge] = _noise((h, w), seed=4)[ledge] - droop
    return z, ledge


def _without_ledges(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ref, "_ledges", lambda grid, labels, cells, r, below, *a:
                        np.zeros(below.shape[1], dtype=bool))


def test_ledge_hanging_gently_is_abnormal(monkeypatch: pytest.MonkeyPatch) -> None:
    """SPEC "Edge test" step 6, ledges: material bent out level 0.08 mm below a wall top
    (floor 2 mm down), 3 cells wide. Gentler than 45 degrees from the top's last sample
    (0.08 < 0.1 mm away), so the hanging rule leaves it; the ledge rule flags it: its cells lie
    level (0.002 mm noise), the top steps down onto them by 0.08 (more than the ledge's
    steps plus a tolerance), and beyond them the wall drops steeply, 1.9 mm further (more than
    twice 0.08). Must not fire: one cell wide (a chamfer's single sample), a level band 6
    cells wide (wider than a burr: a surface of the part), a ledge whose floor lies only
    1.5 x 0.08 further down (a staircase), nor, in the reference without the rule, on most of
    the ledge. Core == reference, batch == stream."""
    g3 = None
    for width, fires in ((3, True), (1, False), (6, False)):
        z, ledge = _ledge_z(width)
        g = _grid(z)
        core = miem.detect(g).labels == miem.ABNORMAL
        oracle = ref.detect(g).labels == miem.ABNORMAL
        np.testing.assert_array_equal(core, oracle, err_msg=str(width))
        inner = ledge.copy()
        inner[:11] = inner[29:] = False  # rows whose sub-windows lie within the ledge's rows
        # (a cell whose neighbours along the row differ by the noise's 4 rms is no ledge: 1 of 57)
        assert core[inner].mean() >= 0.95 if fires else not core[inner].any(), width
        assert not (core & ~ledge).any(), width
        if width == 3:
            g3 = g
    # by hand: 0.08 deep, 0.1 mm from the top's last sample (gentler than 45 degrees)
    p, q = g3[20, 20], g3[20, 19]
    assert (q - p)[2] < np.hypot(*(q - p)[:2])
    p = miem.default_params("stream")
    np.testing.assert_array_equal(stream_labels(g3, p), miem.detect(g3, params=p).labels)
    z, _ = _ledge_z(3, floor=0.2)  # a staircase: 0.08, then 0.12 further down
    stairs = ref.detect(_grid(z)).labels
    _without_ledges(monkeypatch)
    np.testing.assert_array_equal(ref.detect(_grid(z)).labels, stairs)  # (its ends: other rules)
    _, ledge = _ledge_z(3)
    assert (ref.detect(g3).labels == miem.ABNORMAL)[ledge].sum() <= 6


def _wall_burr_z(h: int = 50, w: int = 60, row: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """A wall top at ``row`` (floor 3 mm down) with material hanging over it, as on the real
    scan's first wall: three profiles 0.5, 1.0 and 1.5 mm below the top, then two profiles
    without a return; returns z and the burr mask (profiles 0.1 mm apart, points 0.05 mm)."""
    rng = np.random.default_rng(3)
    rows = np.arange(h)[:, None].repeat(w, 1)
    z = rng.normal(0.0, 0.002, (h, w)) - 3.0 * (rows >= row)
    burr = (rows >= row) & (rows < row + 3)
    z[burr] = -0.5 * (rows[burr] - row + 1) + rng.normal(0.0, 0.002, int(burr.sum()))
    z[row + 3:row + 5] = np.nan
    return z, burr


def _plane_normal_z(pts: np.ndarray) -> float:
    """|u_z| of the eigen plane of ``pts`` (N, 3), by NumPy directly."""
    q = pts - pts.mean(axis=0)
    return float(abs(np.linalg.eigh(q.T @ q)[1][2, 0]))


def test_steep_sub_window_is_never_clean() -> None:
    """SPEC "Edge test" step 4: a sub-window whose plane is steeper than 70 degrees is never
    clean (P is not tested against it). Must fire: at the middle profile of material hanging
    over a wall top, the left half-window (15 profiles x 7 points of 0.05 mm) holds top, burr
    and floor; its plane (NumPy, by hand) is within 20 degrees of vertical, and it "fits" the
    cell. Without the rule the cells stay as they are; with it every inner cell of that profile
    is ABNORMAL and no cell off the burr. Must not fire: designed faces tilted 60 degrees keep all 8 sub-windows valid
    and nothing is flagged; at 75 degrees every sub-window is steep."""
    z, burr = _wall_burr_z()
    g = _grid(z)
    g[..., 0] *= 0.5  # points 0.05 mm apart along the profile
    labels = np.where(np.isfinite(z), ref.NORMAL, ref.INVALID).astype(np.uint8)
    r, c = 21, 30
    left = g[r - 7:r + 8, c - 7:c].reshape(-1, 3)
    left = left[np.isfinite(left).all(axis=1)]
    assert _plane_normal_z(left) < np.cos(np.radians(70.0))
    cells = np.zeros(z.shape, bool)
    cells[r, c] = True
    fits = ref._side_fits(g, labels == ref.NORMAL, labels == ref.INVALID, cells, 7, g[0, 0])
    steep = fits[3] & (fits[4][..., 2] < ref._EDGE_STEEP_COS)
    assert steep[0, 0] and steep[1, 0]  # left and right
    out = ref.edge_test(g, labels, window=15, tolerance=4.0, max_iterations=10)[0]
    flagged = out == ref.ABNORMAL
    assert flagged[r, 7:53].all() and not (flagged & ~burr).any()
    saved = ref._EDGE_STEEP_COS
    try:
        ref._EDGE_STEEP_COS = -1.0  # the rule off
        off = ref.edge_test(g, labels, window=15, tolerance=4.0, max_iterations=10)[0]
    finally:
        ref._EDGE_STEEP_COS = saved
    assert (off[r, 7:53] != ref.ABNORMAL).sum() > 20
    for deg, steep in ((60.0, False), (75.0, True)):
        rows = np.arange(40)[:, None].repeat(40, 1)
        g = _grid(_noise((40, 40)) - np.tan(np.radians(deg)) * rows * 0.1)
        lab = np.zeros((40, 40), np.uint8)
        inner = np.zeros((40, 40), bool)
        inner[8:32, 8:32] = True
        fits = ref._side_fits(g, lab == ref.NORMAL, lab == ref.INVALID, inner, 7, g[0, 0])
        assert fits[3].all()
        uz = fits[4][..., 2]  # cos of the tilt, by geometry
        np.testing.assert_allclose(uz, np.cos(np.radians(deg)), atol=0.02)
        assert (uz < ref._EDGE_STEEP_COS).all() if steep else (uz >= ref._EDGE_STEEP_COS).all()
        if not steep:
            out = ref.edge_test(g, lab, window=15, tolerance=4.0, max_iterations=10)[0]
            assert not (out == ref.ABNORMAL).any()


# --------------------------------------------------------------------------------------------
# the C++ edge test (opt-in: edge_tolerance / edge_window): core == reference on edge scenes
# (float64 and float32, 1 and 2 threads), field checks, and the paths that cannot honour it
# (ProfileStream, clouds, miem.dask) refusing it when it is on


def _lip_scene() -> np.ndarray:
    """Sheet ending in an outline (no return beyond column 20), a 0.1 lip on its last 2 columns."""
    z = _noise((40, 40))
    z[:, 20:] = np.nan
    z[12:28, 18:20] += 0.1
    return _grid(z)


def _core_scenes() -> list:
    """Crops (48 x 64 cells) of two tuning edge scenes around their burrs, and the lip scene."""
    specs = [s for s in suite.specs("tune", real=False) if s.group in suite.EDGE_KINDS]
    out = [("lip", _lip_scene())]
    for spec in specs[:4:3]:
        sc = suite.build(spec)
        r, c = np.argwhere(sc.truth == suite.DEFECT)[0]
        r0 = int(np.clip(r - 24, 0, sc.shape[0] - 48))
        c0 = int(np.clip(c - 32, 0, sc.shape[1] - 64))
        out.append((spec.name, np.ascontiguousarray(sc.points[r0:r0 + 48, c0:c0 + 64])))
    # taller than wide (not transposed), 200 rows: the core's ring of integral-image rows wraps
    # (bands of 64 rows); lips across the band borders
    z = _noise((200, 40), seed=8)
    z[:, 21:] = np.nan
    for r0 in (5, 55, 120, 185):
        z[r0:r0 + 14, 19:21] += 0.1
    out.append(("tall lip", _grid(z)))
    out.append(("tall crop", np.ascontiguousarray(out[1][1].transpose(1, 0, 2))))
    for diagonal in (False, True):  # fins (SPEC "Edge test" step 6), across tile borders
        z, _ = _fin_z(140, 150, diagonal)
        z[60:70, :] -= 0.8  # a lower terrace under part of it
        out.append((f"fin {diagonal}", _grid(z)))
    z, _ = _hanging_z(140, 150)  # a burr hanging beyond a wall (step 6), across tile borders
    z[60:70, :20] += 0.3
    out.append(("hanging", _grid(z)))
    z, burr = _hanging_z(140, 150)  # hanging 0.25 mm, 45 degrees from the top's last sample
    z[burr] = _noise((140, 150), seed=4)[burr] - 0.25
    z[:, 18:20] += 0.02  # a rounded-up rim: the angle passes label the last samples EDGE
    out.append(("hanging shallow", _grid(z)))
    z, _ = _ledge_z(3, 140, 150)  # a ledge bent out level (step 6), across tile borders
    z[60:70, :20] += 0.3
    out.append(("ledge", _grid(z)))
    z, _ = _wall_burr_z(140, 150, row=62)  # steep sub-windows (step 3), across tile borders
    out.append(("steep", _grid(z)))
    z, _ = _valley_lip_z(30.0, 140, 150)  # a lip at a concave crease (step 6), across tiles
    z[60:75, 17:20] += 0.05
    out.append(("valley lip", _grid(z.T.copy())))
    z, _ = _steep_valley_lip_z(0.07, 140, 150)  # a lip whose dip is at itself (step 6)
    out.append(("steep valley lip", _grid(z)))
    return out


@pytest.mark.parametrize("k, window", [(8.0, 11), (5.0, 7)])
def test_core_equals_reference(k: float, window: int) -> None:
    kw = {"preset": "recommended", "edge_tolerance": k, "edge_window": window}
    changed = 0
    for name, pts in _core_scenes():
        oracle = ref.detect(pts, **kw)
        for nt in (1, 2):
            core = miem.detect(pts, num_threads=nt, **kw)
            np.testing.assert_array_equal(core.labels, oracle.labels, err_msg=f"{name} {nt}")
            assert core.iterations == oracle.iterations, name
            np.testing.assert_allclose(core.height, oracle.height, atol=1e-7, equal_nan=True)
        f32 = pts.astype(np.float32)
        oracle32 = ref.detect(f32, **kw)
        for nt in (1, 2):
            np.testing.assert_array_equal(miem.detect(f32, num_threads=nt, **kw).labels,
                                          oracle32.labels, err_msg=f"{name} float32 {nt}")
        off = ref.detect(pts, preset="recommended")
        changed += int((oracle.labels != off.labels).sum())
    assert changed > 0  # the edge test did something on these scenes
    assert core.params["edge_tolerance"] == k and core.params["edge_window"] == window


def test_exactly_flat_sides_do_not_decide_by_round_off() -> None:
    """SPEC "Edge test" step 3: a side with l0 <= 1e-12 l2 has rms 0. On a noise-free grid every
    side within one face is exactly flat, its l0 round-off that the core's solver and NumPy's
    make differently; *clean* (rms <= 2 best) compared those specks, so the core and the
    reference chose different clean sides. This grid (a crease, a spike one column past it;
    hypothesis found it) gave core ABNORMAL, reference EDGE at the spike."""
    yy, xx = np.mgrid[0:20, 0:20].astype(np.float64)
    z = 0.125 * (xx + yy) + np.where(xx > 2, (xx - 2) * np.tan(np.radians(11.0)), 0.0)
    z[9, 3] += 2.9
    pts = np.dstack([xx, yy, z])
    kw = {"theta0": 40.0, "scales": (1,), "max_gap": 0, "max_iterations": 1, "window": 3,
          "height_tolerance": None, "edge_extent": 0}
    oracle = ref.detect(pts, **kw)
    for nt in (1, 2):
        np.testing.assert_array_equal(miem.detect(pts, num_threads=nt, **kw).labels,
                                      oracle.labels)
    # a spike 2.9 above a noise-free face is a defect, and nothing else is
    assert oracle.labels[9, 3] == miem.ABNORMAL
    assert np.count_nonzero(oracle.labels == miem.ABNORMAL) == 1


def _sliver_scene(gap: int) -> np.ndarray:
    """Sheet (columns 0..19), `gap` columns without return, then a sliver of 2 columns 2 mm
    above the sheet (a wall top seen across its shadow) and no return beyond."""
    z = _noise((40, 40))
    z[:, 20:20 + gap] = np.nan
    z[:, 20 + gap:22 + gap] += 2.0
    z[:, 22 + gap:] = np.nan
    return _grid(z)


@pytest.mark.parametrize("walk, attached", [
    ("P", True), ("IIP", False), ("IHIP", True), ("HIIP", False), ("PII", True), ("HHO", True),
    ("HIH", True), ("HII", False), ("", True), ("AIIP", True), ("HIIA", False),
])
def test_attached_walks_by_hand(walk: str, attached: bool) -> None:
    """SPEC "Edge test" step 5: P is attached to a side unless 2 INVALID cells in a row come
    before the first cell on the side's plane on its way there. Walk from P (0.3 above the
    plane z = 0, tolerance 0.1): P a cell on the plane, H one 0.3 above it, A ABNORMAL on the
    plane, I no return, O the grid ends."""
    cells = walk.split("O")[0]
    z = {"P": 0.0, "H": 0.3, "A": 0.0, "I": np.nan}
    code = {"P": miem.NORMAL, "H": miem.NORMAL, "A": miem.ABNORMAL, "I": miem.INVALID}
    # P at the right end of a row; the left side (0) lies along the walk, the right one (1)
    # beyond the grid at once
    row = list(reversed(cells))
    zz = np.array([[z[c] for c in row] + [0.3]])
    grid = _grid(zz)
    labels = np.array([[code[c] for c in row] + [miem.NORMAL]], dtype=np.uint8)
    sel = np.zeros(labels.shape, dtype=bool)
    sel[0, -1] = True
    nrm = np.tile([0.0, 0.0, 1.0], (8, 1, 1))
    cen = np.zeros((8, 1, 3))
    tol = np.full((8, 1), 0.1)
    out = ref._attached(grid, labels, sel, 7, np.zeros(3), nrm, cen, tol)
    assert out.shape == (8, 1)
    assert out[0, 0] == attached and out[1, 0]


@pytest.mark.parametrize("gap", [1, 2, 3])
def test_sliver_beyond_a_dropout_band_is_no_lip(gap: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """A sliver beyond a band of dropouts stands proud of the sheet with nothing beyond it, as a
    lip before an outline does; across more than one dropout in a row it is not attached to
    the sheet (SPEC "Edge test" step 5) and stays as the angle and height tests leave it."""
    pts = _sliver_scene(gap)
    sliver = np.zeros(pts.shape[:2], dtype=bool)
    sliver[:, 20 + gap:22 + gap] = True
    oracle = ref.detect(pts)
    for nt in (1, 2):
        np.testing.assert_array_equal(miem.detect(pts, num_threads=nt).labels, oracle.labels)
    before = miem.detect(pts, edge_tolerance=None).labels
    assert not (before[sliver] == miem.ABNORMAL).any()
    if gap == 1:  # one dropout: attached, a lip 2 mm tall at the outline
        assert (oracle.labels[sliver] == miem.ABNORMAL).all()
    else:
        np.testing.assert_array_equal(oracle.labels, before)
        # without the condition the outline rule flags the whole sliver
        monkeypatch.setattr(ref, "_attached", lambda grid, labels, cells, *a: np.ones(
            (8, int(cells.sum())), dtype=bool))
        assert (ref.detect(pts).labels[sliver] == miem.ABNORMAL).all()


def test_stream_leaves_slivers_as_batch() -> None:
    """The stream reads the same walk (the labels at the start of the pass, rows within r)."""
    grid = _sliver_scene(3).transpose(1, 0, 2).copy()  # the sliver along the profiles
    p = miem.default_params("stream")
    want = miem.detect(grid, params=p)
    np.testing.assert_array_equal(want.labels, ref.detect(grid).labels)
    assert not (want.labels[23:25] == miem.ABNORMAL).any()
    np.testing.assert_array_equal(stream_labels(grid, p), want.labels)


def test_lip_before_the_outline_and_only_abnormal_added() -> None:
    pts = _lip_scene()
    base = miem.detect(pts, preset="recommended", edge_tolerance=None)
    res = miem.detect(pts, preset="recommended", edge_tolerance=8.0)
    changed = res.labels != base.labels
    assert changed.any() and (res.labels[changed] == miem.ABNORMAL).all()
    # by construction: only lip cells (rows 12..27, columns 18..19) are raised
    rows, cols = np.nonzero(changed)
    assert rows.min() >= 12 and rows.max() <= 27 and cols.min() >= 18 and cols.max() <= 19
    assert base.params["edge_tolerance"] is None


def test_on_by_default_on_grids_off_where_not_implemented() -> None:
    rec = miem.DetectParams().grid
    assert (rec.edge_tolerance, rec.edge_window, rec.min_step) == (4.0, 15, "auto")
    c = _core.DetectParams()
    assert (c.edge_k, c.edge_window, c.min_step_auto, c.min_step) == (4.0, 15, True, -1.0)
    assert c.edge_test()
    pts = _lip_scene()
    res = miem.detect(pts)
    np.testing.assert_array_equal(
        res.labels, miem.detect(pts, edge_tolerance=4.0, edge_window=15, min_step="auto").labels)
    np.testing.assert_array_equal(res.labels, ref.detect(pts).labels)  # the reference default
    assert (res.labels != miem.detect(pts, edge_tolerance=None).labels).any()  # it runs
    # the paper's method has neither
    p = _core.paper_params()
    assert p.edge_k == 0.0 and not p.min_step_auto
    # the stream's default has both (C++ and Python; tests/test_stream.py: stream == batch)
    s = _core.stream_default_params()
    assert s.edge_k == _core.DetectParams().edge_k > 0 and s.min_step_auto
    assert miem.ProfileStream(10).params.grid.min_step == "auto"


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf"), "8", True])
def test_edge_tolerance_rejected(bad: object) -> None:
    g = _grid(_noise((12, 12)))
    with pytest.raises(ValueError, match="edge_tolerance"):
        miem.detect(g, edge_tolerance=bad)
    if not isinstance(bad, str):
        with pytest.raises(ValueError, match="edge_tolerance"):
            ref.detect(g, edge_tolerance=bad)


@pytest.mark.parametrize("bad", [2, 4, 1])
def test_edge_window_rejected(bad: int) -> None:
    g = _grid(_noise((12, 12)))
    with pytest.raises(ValueError, match="edge_window"):
        miem.detect(g, edge_tolerance=8.0, edge_window=bad)
    with pytest.raises(ValueError, match="edge_window"):
        ref.detect(g, edge_tolerance=8.0, edge_window=bad)


def test_cpp_check_names_the_field() -> None:
    p = _core.DetectParams()
    p.edge_k = float("nan")
    code, msg = p.check()
    assert code != 0 and msg.startswith("edge_k")
    p.edge_k, p.edge_window = 4.0, 10
    code, msg = p.check()
    assert code != 0 and msg.startswith("edge_window")
    p.edge_window = 9
    assert p.check()[0] == 0 and p.edge_test()


def test_cloud_path_has_its_own_edge_test_not_the_grid_window() -> None:
    pts = _grid(_noise((12, 12))).reshape(-1, 3)
    pts = pts[np.random.default_rng(1).permutation(len(pts))]  # a cloud, not scan-line order
    res = miem.detect(pts, edge_tolerance=8.0)  # the cloud edge test (SPEC "Unorganized clouds")
    assert res.params["edge_tolerance"] == 8.0
    with pytest.raises(ValueError, match="edge_window"):
        miem.detect(pts, edge_window=15)


def test_stream_runs_the_edge_test() -> None:
    # the stream honours the edge test, any odd window (tests/test_stream.py: stream == batch)
    s = miem.ProfileStream(10, edge_tolerance=8.0, edge_window=9)
    assert (s.params.grid.edge_tolerance, s.params.grid.edge_window) == (8.0, 9)
    p = _core.DetectParams()
    p.height_abs = p.height_k = 0.0
    p.edge_extent = 0
    p.edge_k = 8.0
    p.min_step_auto = False
    assert _core.ProfileStream64(10, p).lag > _core.stream_lag(_core.paper_params())


def test_stream_hangs_ledges_as_batch() -> None:
    """The hanging rule's path of ABNORMAL cells (SPEC "Edge test" step 6) reads the labels of
    earlier passes: the stream (its labels at the start of each pass, kept per cell) equals
    batch on the tuning edge scene whose ledges need it (hanging runs beside raised lips)."""
    spec = next(s for s in suite.specs("tune", real=False) if s.name == "tune-edge_wall-1")
    grid = suite.build(spec).points
    p = miem.default_params("stream")
    want = miem.detect(grid, params=p)
    assert (want.labels != miem.detect(grid, params=p, edge_tolerance=None).labels).sum() > 50
    np.testing.assert_array_equal(stream_labels(grid, p), want.labels)


def _jittered_profiles(seed: int, rows: int = 100,
                       cols: int = 240) -> tuple[np.ndarray, np.ndarray]:
    """A profiler's scan of a gently curved sheet (0.05 mm along, 0.1 mm across), noise 0.002 mm,
    every profile offset in z by N(0, 0.02 mm) (profile-to-profile jitter, ten times the noise),
    1 um z steps, with spikes and pits 0.3-1.3 mm (the truth: those cells)."""
    rng = np.random.default_rng(seed)
    c = np.arange(cols) * 0.05
    off = 0.02 * rng.standard_normal(rows)
    g = np.empty((rows, cols, 3))
    for r in range(rows):
        z = (2.0 * np.exp(-(c - 0.025 * cols) ** 2 / 2000.0) + 0.05 * np.sin(2 * np.pi * r / 1024)
             + rng.normal(0.0, 0.002, cols) + off[r])
        g[r, :, 0], g[r, :, 1], g[r, :, 2] = c, r * 0.1, np.round(z * 1000.0) / 1000.0
    truth = np.zeros((rows, cols), dtype=bool)
    for sign, rate in ((1.0, 0.0002), (-1.0, 0.0001)):
        m = rng.random((rows, cols)) < rate
        g[..., 2][m] += sign * (0.3 + rng.random(int(m.sum())))
        truth |= m
    return g, truth


def test_edge_tolerance_floor_from_min_step() -> None:
    """SPEC "Edge test" step 3: with a min_step in use, no sub-window's tolerance is below
    min_step / 2. On profiles jittered by ten times their noise, an up or down sub-window (a
    few profiles, not P's) that happens to fit its profiles closely had an rms far below the
    scan's noise across profiles, and whole profiles offset by a few jitter sigmas stood
    "proud" of it: 346 false alarms on this scan without the floor, none with it, every spike
    and pit still found; core == reference (1 and 2 threads, float32), stream == batch."""
    g, truth = _jittered_profiles(22)
    pre = miem.detect(g, edge_tolerance=None)
    ms = pre.params["min_step"]
    assert ms is not None and 0.05 < ms < 0.12  # "auto": 4 x the jitter's sigma (about 0.08)
    kw = {"window": 15, "tolerance": 4.0, "max_iterations": 10}
    without = ref.edge_test(g, pre.labels, min_step=None, **kw)[0]
    with_floor = ref.edge_test(g, pre.labels, min_step=ms, **kw)[0]
    assert ((without == miem.ABNORMAL) & ~truth).sum() > 100  # the profiles that stood proud
    res = miem.detect(g)
    assert res.params["min_step"] == ms and res.params["edge_tolerance"] == 4.0
    np.testing.assert_array_equal(res.labels, with_floor)
    abnormal = res.labels == miem.ABNORMAL
    assert not (abnormal & ~truth).any() and abnormal[truth].all()
    oracle = ref.detect(g, preset="recommended")
    np.testing.assert_array_equal(res.labels, oracle.labels)
    np.testing.assert_array_equal(miem.detect(g, num_threads=2).labels, oracle.labels)
    f32 = g.astype(np.float32)
    np.testing.assert_array_equal(miem.detect(f32).labels,
                                  ref.detect(f32, preset="recommended").labels)
    np.testing.assert_array_equal(stream_labels(g, miem.default_params("stream")), res.labels)
    # a min_step given as a length sets the floor alike (miem.dask gives its blocks one)
    np.testing.assert_array_equal(miem.detect(g, min_step=ms).labels, res.labels)


def test_feature_line_cells_back_at_a_wall_foot() -> None:
    """SPEC "Edge test" step 9: at the foot of a wall (a 1-3 mm drop at 0.05 mm steps, at an
    angle to the grid) the angle test sees a floor cell whose return lies a little low as a pit
    (every direction crossing the wall gives just under 90 degrees, theta0 = 90): 79
    designed-edge cells ABNORMAL without step 9. They lie on the floor's plane, beside the
    wall's feature line: step 9 gives them back (EDGE), no burr cell among them, every burr cell
    found before still found. Core == reference (1 and 2 threads, float32), stream == batch."""
    sc = edge_scenes.make_edge_scene("edge_wall", 9012, step=0.05, noise=0.005)
    g = sc.points
    pre = ref.detect(g, preset="recommended", edge_tolerance=None)  # after the height passes
    kw = {"window": 15, "tolerance": 4.0, "max_iterations": 10,
          "min_step": pre.params["min_step"], "z_resolution": pre.params["z_resolution"]}
    before = ref.edge_test(g, pre.labels, **kw)[0]  # lines=None: no step 9
    oracle = ref.detect(g, preset="recommended")
    edge, burr = sc.truth == edge_scenes.EDGE, sc.truth == edge_scenes.DEFECT
    was, now = before == miem.ABNORMAL, oracle.labels == miem.ABNORMAL
    assert (was & edge).sum() > 50 and (now & edge).sum() <= 2
    back = was & ~now
    assert back.sum() > 50 and not (back & burr).any()
    assert (oracle.labels[back] == miem.EDGE).all() and not (now & ~was).any()
    assert (now & burr).sum() == (was & burr).sum() > 0
    for nt in (1, 2):
        np.testing.assert_array_equal(miem.detect(g, num_threads=nt).labels, oracle.labels)
    f32 = g.astype(np.float32)
    np.testing.assert_array_equal(miem.detect(f32).labels,
                                  ref.detect(f32, preset="recommended").labels)
    np.testing.assert_array_equal(stream_labels(g, miem.default_params("stream")), oracle.labels)
    # without the height test every EDGE cell is a feature line for step 9: batch == stream
    off = miem.default_params("stream").replace(height_tolerance=None)
    got = miem.detect(g, params=off)
    np.testing.assert_array_equal(got.labels, ref.detect(g, preset="recommended",
                                                         height_tolerance=None).labels)
    np.testing.assert_array_equal(stream_labels(g, off), got.labels)


def _stacked_edge_scan(n_rows: int, n_cols: int) -> np.ndarray:
    """Edge scenes (220 x 256 cells each) side by side and stacked into one continuous tall scan,
    far from the scanner's origin (x + 300 mm): its moments, summed over the whole grid, would
    reach 1e10 and more."""
    rows, y0 = [], 0.0
    for i in range(n_rows):
        part = []
        for j in range(n_cols):
            sc = edge_scenes.make_edge_scene(edge_scenes.EDGE_KINDS[(i + j) % 4], 100 * i + j,
                                             shape=(220, 256))
            g = sc.points.copy()
            g[..., 0] += j * 25.6 + 300.0
            part.append(g)
        band = np.concatenate(part, axis=1)
        band[..., 1] += y0 - np.nanmin(band[..., 1]) + 200.0
        y0 = np.nanmax(band[..., 1]) + 0.1
        rows.append(band)
    return np.concatenate(rows, axis=0)


def test_edge_sums_do_not_depend_on_the_rows_above() -> None:
    """The edge test's sums are per 64 x 128 tile (SPEC step 3): the last rows of a tall scan get
    the labels they get when the scan starts 640 rows (a tile multiple) above them, beyond the
    detector's reach. With sums over the whole grid (before) the last 1280 rows of this scan
    had 8,952 ABNORMAL cells against 1,733 when detected alone (l0 lost in differences of
    ~1e11 sums)."""
    g = _stacked_edge_scan(24, 4)  # 5280 x 1024 cells
    whole = miem.detect(g)
    assert whole.params["edge_tolerance"] is not None  # the default runs the edge test
    start = g.shape[0] - 1280
    part = miem.detect(g[start - 640:], min_step=whole.params["min_step"])
    np.testing.assert_array_equal(whole.labels[start:], part.labels[640:])
    assert (whole.labels[start:] == miem.ABNORMAL).sum() > 100


def test_dask_runs_the_edge_test_as_one_machine() -> None:
    mdask = pytest.importorskip("miem.dask")
    import dask
    import dask.array as da

    g = _stacked_edge_scan(6, 1)
    want = miem.detect(g)
    with dask.config.set(scheduler="sync"):
        res = mdask.detect(da.from_array(g, chunks=(384, 256, 3)))
        defects, labels, height = res.defects(res.labels, res.height)
    assert res.params["edge_tolerance"] == want.params["edge_tolerance"]
    np.testing.assert_array_equal(labels, want.labels)
    np.testing.assert_array_equal(height, want.height)
    assert [d.indices.tolist() for d in defects] == [d.indices.tolist() for d in want.defects]


# --------------------------------------------------------------------------------------------
# min_step="auto"


def test_auto_min_step_from_profile_jitter() -> None:
    import miem

    rng = np.random.default_rng(5)
    h, w = 60, 80
    x, y = np.meshgrid(np.arange(w) * 0.05, np.arange(h) * 0.1)
    jitter = rng.normal(0.0, 0.06, (h, 1))  # whole profiles offset: sigma 0.06 mm across
    g = np.stack([x, y, 0.1 * x + jitter + 0.0 * y], axis=-1)
    res = miem.detect(g, preset="recommended", min_step="auto")
    oracle = ref.detect(g, preset="recommended", min_step="auto")
    assert res.params["min_step_auto"] and oracle.params["min_step_auto"]
    assert res.params["min_step"] == pytest.approx(oracle.params["min_step"], rel=1e-12)
    # across: second differences of iid offsets have sigma sqrt(6) * 0.05; along: none
    assert 0.15 < res.params["min_step"] < 0.4
    np.testing.assert_array_equal(res.labels, oracle.labels)
    plain = miem.detect(g, preset="recommended", min_step=None)
    assert (plain.labels == miem.EDGE).sum() > 0
    assert (res.labels == miem.EDGE).sum() < (plain.labels == miem.EDGE).sum()
    # a quiet grid: 4 sigma below the spacing, min_step stays off
    quiet = g.copy()
    quiet[..., 2] = 0.1 * x + rng.normal(0.0, 0.001, (h, w))
    assert miem.detect(quiet, min_step="auto").params["min_step"] is None
    assert ref.detect(quiet, min_step="auto").params["min_step"] is None
    with pytest.raises(ValueError, match="min_step"):
        miem.detect(g, min_step="often")


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_auto_min_step_core_equals_reference(dtype: type) -> None:
    """The core's auto_min_step (C++) gives the reference's value to the last bit, with
    dropouts, on unevenly spaced profiles with 1 um z steps; labels equal for 1 and 2 threads."""
    rng = np.random.default_rng(11)
    h, w = 50, 61
    y = np.cumsum(rng.choice([0.1, 0.2, 1.0], size=h))  # uneven profile spacing
    x = np.arange(w) * 0.05
    xx, yy = np.meshgrid(x, y)
    z = np.round(0.02 * xx + rng.normal(0.0, 0.02, (h, 1)) + rng.normal(0, 0.002, (h, w)), 3)
    g = np.stack([xx, yy, z], axis=-1).astype(dtype)
    g[rng.random((h, w)) < 0.05] = np.nan
    oracle = ref.detect(g)
    assert oracle.params["min_step_auto"] and oracle.params["min_step"] is not None
    for nt in (1, 2):
        res = miem.detect(g, num_threads=nt)
        assert res.params["min_step"] == oracle.params["min_step"]  # same arithmetic
        np.testing.assert_array_equal(res.labels, oracle.labels)
    # hand check of the rule on this grid (float64 of the stored values)
    g64 = g.astype(np.float64)
    fin = np.isfinite(g64).all(axis=-1)
    spacing, noise = [], []
    for a in (g64, g64.transpose(1, 0, 2)):
        f = np.isfinite(a).all(axis=-1)
        pair = f[:, :-1] & f[:, 1:]
        spacing.append(np.median(np.linalg.norm(a[:, 1:] - a[:, :-1], axis=-1)[pair]))
        tri = f[:, :-2] & f[:, 1:-1] & f[:, 2:]
        d2 = np.abs(a[:, :-2, 2] - 2 * a[:, 1:-1, 2] + a[:, 2:, 2])[tri]
        noise.append(1.4826 * np.median(d2) / np.sqrt(6.0))
    assert fin.sum() > 0
    assert 4 * max(noise) > min(spacing)
    assert res.params["min_step"] == pytest.approx(4 * max(noise), rel=1e-12)


def test_auto_min_step_core_equals_reference_on_random_grids() -> None:
    """The core selects its four medians without sorting all values (a band from a sample, or
    float32 key histograms; under 65,536 sample cells by selection among all values, as the
    small grids here): the reference's value to the last bit on grids with ties
    (quantised z), runs of equal values, dropouts, odd and even counts, 1-row and 1-column
    grids, float32, and a grid big enough for 2 threads to split it."""
    rng = np.random.default_rng(23)
    grids = []
    for trial in range(40):
        h, w = (1, 30) if trial == 0 else ((30, 1) if trial == 1 else tuple(rng.integers(2, 25, 2)))
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
        z = rng.normal(0.0, 1.0, (h, w)) * 10.0 ** rng.uniform(-3, 1)
        if trial % 3 == 0:
            z = np.round(z, 1)  # many equal values
        g = np.dstack([xx * 1e-3, yy * rng.choice([1e-3, 5e-3]), z])
        g[rng.random((h, w)) < rng.uniform(0.0, 0.3)] = np.nan
        grids.append(g)
    yy, xx = np.mgrid[0:300, 0:260].astype(np.float64)
    big = np.dstack([xx * 0.1, yy * 0.2, np.round(rng.normal(0.0, 0.15, xx.shape), 2)])
    big[rng.random(xx.shape) < 0.05] = np.nan
    grids.append(big)
    n_on = 0
    for g in grids:
        fin = np.isfinite(g).all(axis=-1)
        if fin.sum() < 3:
            continue
        for dtype in (np.float64, np.float32):
            gg = g.astype(dtype)
            want = ref._auto_min_step(gg.astype(np.float64), np.isfinite(gg).all(axis=-1))
            n_on += want is not None
            for nt in (1, 2):
                assert miem.detect(gg, num_threads=nt).params["min_step"] == want
    assert n_on > 40  # the medians decide (min_step on), not only the "off" branch
    # the core's fast path takes a band from a sample of every 31st cell (row-major) and falls
    # back to the exact histograms when a middle rank is outside it: spikes on exactly those
    # cells put the sample's band far above the true middle
    g = big.copy()
    g.reshape(-1, 3)[::31, 2] += 50.0
    want = ref._auto_min_step(g, np.isfinite(g).all(axis=-1))
    assert want is not None
    for nt in (1, 2):
        assert miem.detect(g, num_threads=nt).params["min_step"] == want


def test_auto_min_step_core_equals_reference_on_a_wide_scan() -> None:
    """A scan wide enough that the core's sample of every 31st cell of its first 256 rows
    holds over 8,192 values: the sample's band edges and the middle ranks within the band are
    both selected through histograms of the values' bit patterns (then among the few values
    of the ranks' bins). The reference's value to the last bit, with quantised z (runs of
    equal values at the middle ranks) and without (the two middle values apart: odd and even
    counts), jittered x, dropouts, float32, 1 and 2 threads."""
    rng = np.random.default_rng(29)
    yy, xx = np.mgrid[0:300, 0:1200].astype(np.float64)
    z = 0.01 * xx + rng.normal(0.0, 0.05, xx.shape) + rng.normal(0, 0.1, (300, 1))
    g = np.dstack([xx * 0.05 + rng.uniform(-0.01, 0.01, xx.shape), yy * 0.1, z])
    clean = g.copy()
    g[rng.random(xx.shape) < 0.03] = np.nan
    g[98:103, 600] = clean[98:103, 600]
    other = g.copy()
    other[100, 600] = np.nan  # three triples across the profiles fewer: the other parity
    quantised = g.copy()
    quantised[..., 2] = np.round(quantised[..., 2], 2)
    for gg in (g, other, quantised, g.astype(np.float32), other.astype(np.float32)):
        want = ref._auto_min_step(gg.astype(np.float64), np.isfinite(gg).all(axis=-1))
        assert want is not None
        for nt in (1, 2):
            assert miem.detect(gg, num_threads=nt).params["min_step"] == want


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_auto_min_step_reads_256_rows_from_the_first_with_data(dtype: type) -> None:
    """SPEC "min_step='auto'": the medians are those of the 256 rows from the first row with a
    finite cell (rows of dropouts before it, one inside); the noise doubles after them, so the
    whole grid's medians differ. Core (1 and 2 threads) == reference == NumPy by hand."""
    rng = np.random.default_rng(17)
    h, w, lead = 600, 45, 50
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    y = np.cumsum(rng.choice([0.1, 0.2, 0.5], h))[:, None] + 0 * xx
    sd = np.where(np.arange(h) < lead + 256, 0.05, 0.1)[:, None]
    z = np.round(0.01 * xx + rng.normal(0.0, 1.0, (h, 1)) * sd + rng.normal(0, 0.002, (h, w)), 3)
    g = np.dstack([xx * 0.05, y, z]).astype(dtype)
    g[:lead] = np.nan
    g[lead + 100] = np.nan
    g[rng.random((h, w)) < 0.03] = np.nan
    g64 = g.astype(np.float64)

    def by_hand(a: np.ndarray) -> float:
        spacing, noise = [], []
        for b in (a, a.transpose(1, 0, 2)):
            f = np.isfinite(b).all(axis=-1)
            pair = f[:, :-1] & f[:, 1:]
            spacing.append(np.median(np.linalg.norm(b[:, 1:] - b[:, :-1], axis=-1)[pair]))
            tri = f[:, :-2] & f[:, 1:-1] & f[:, 2:]
            d2 = np.abs(b[:, :-2, 2] - 2 * b[:, 1:-1, 2] + b[:, 2:, 2])[tri]
            noise.append(1.4826 * np.median(d2) / np.sqrt(6.0))
        assert 4 * max(noise) > min(spacing)
        return 4 * max(noise)

    want = ref._auto_min_step(g64, np.isfinite(g64).all(axis=-1))
    assert want == pytest.approx(by_hand(g64[lead:lead + 256]), rel=1e-12)
    assert by_hand(g64[lead:]) > 1.2 * want  # the whole grid would give another value
    for nt in (1, 2):
        assert miem.detect(g, num_threads=nt).params["min_step"] == want
    # fewer than 256 rows after the first with data: all of them
    short = g[: lead + 120]
    s64 = short.astype(np.float64)
    assert miem.detect(short).params["min_step"] == ref._auto_min_step(
        s64, np.isfinite(s64).all(axis=-1)) == pytest.approx(by_hand(s64[lead:]), rel=1e-12)


def test_cpp_min_step_auto_and_a_length_is_an_error() -> None:
    p = _core.DetectParams()
    p.min_step = 0.2  # with min_step_auto still on: refused, not silently ignored
    code, msg = p.check()
    assert code != 0 and msg.startswith("min_step")
    p.min_step_auto = False
    assert p.check()[0] == 0
    with pytest.raises(ValueError, match="min_step"):
        miem.detect(_grid(_noise((12, 12))), min_step="sometimes")
