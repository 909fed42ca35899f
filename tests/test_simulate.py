"""Tests of ``miem.simulate``: the generators by geometry, then the paper's claim end to end.

Generator properties are checked against the formulas they state (surface equations, defect
heights, counts, margins), never against an earlier run. The paper's claim (section 3: every
injected abnormal point found, no normal point flagged, the edge strips left alone, and the MIEM
plane equal to the clean plane while least squares and the plain eigenvalue fit drift) is checked
through ``miem.detect`` and ``miem.fit_plane`` (the compiled core).
"""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

import miem
from miem import simulate as sim

N, A, E, INV = sim.NORMAL, sim.ABNORMAL, sim.EDGE, sim.INVALID


def grid_axes(scan: sim.Scan) -> tuple[np.ndarray, np.ndarray]:
    """The x of each column and the y of each row (taken from the clean scan's first cells)."""
    return scan.clean[0, :, 0], scan.clean[:, 0, 1]


def same(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal arrays, NaN equal to NaN (for float arrays)."""
    return bool(np.array_equal(a, b, equal_nan=a.dtype.kind == "f"))


# --------------------------------------------------------------------------------------------
# paper_surface / paper_scan: geometry
# --------------------------------------------------------------------------------------------


def test_paper_surface_formula() -> None:
    x = np.linspace(-50.0, 30.0, 17).reshape(1, 17)
    z = sim.paper_surface(x)
    assert z.shape == x.shape and z.dtype == np.float64
    np.testing.assert_allclose(z, 0.4 * np.exp(-(x**2) / 50.0), rtol=1e-15, atol=0)
    assert sim.paper_surface(0.0) == pytest.approx(0.4, abs=1e-15)
    assert sim.paper_surface(5.0) == pytest.approx(sim.paper_surface(-5.0), abs=0)


def test_paper_scan_grid_and_counts() -> None:
    scan = sim.paper_scan()
    h, w = scan.shape
    assert (h, w) == (201, 161)
    assert scan.points.shape == scan.clean.shape == (h, w, 3)
    assert scan.points.dtype == scan.clean.dtype == np.float64
    assert scan.truth.shape == (h, w) and scan.truth.dtype == np.uint8
    assert scan.kinds.shape == (h, w)
    assert scan.step == 0.5 and scan.surface == "paper"
    x, y = grid_axes(scan)
    np.testing.assert_allclose(x, -50.0 + 0.5 * np.arange(161), rtol=0, atol=1e-12)
    np.testing.assert_allclose(y, -50.0 + 0.5 * np.arange(201), rtol=0, atol=1e-12)
    # rows are profiles at constant y, columns run along x
    assert np.all(scan.clean[..., 1] == y[:, None]) and np.all(scan.clean[..., 0] == x[None, :])
    assert np.count_nonzero(scan.truth == A) == 5
    assert np.count_nonzero(scan.truth == E) == 2 * h - 2  # two strips, two defects on them
    assert np.count_nonzero(scan.truth == INV) == 0
    assert len(scan.defects) == 5 and sum(d.on_edge for d in scan.defects) == 2


def test_paper_scan_points_lie_on_the_surface() -> None:
    scan = sim.paper_scan(seed=3)
    x, z = scan.points[..., 0], scan.points[..., 2]
    normal = scan.truth == N
    np.testing.assert_allclose(z[normal], sim.paper_surface(x[normal]), rtol=0, atol=1e-12)
    # edge strips: one column per strip x, raised by strip_height (3 steps) over the surface
    edge_cols = np.flatnonzero((scan.truth == E).any(axis=0))
    np.testing.assert_allclose(scan.clean[0, edge_cols, 0], [-25.0, 15.0], atol=1e-12)
    strip = np.zeros(scan.shape, dtype=bool)
    strip[:, edge_cols] = True
    cz, cx = scan.clean[..., 2], scan.clean[..., 0]
    np.testing.assert_allclose(cz[strip], sim.paper_surface(cx[strip]) + 1.5, rtol=0, atol=1e-12)
    assert np.all(scan.truth[strip] != N) and np.all(scan.truth[~strip] != E)


def test_paper_scan_defects() -> None:
    scan = sim.paper_scan(seed=1)
    h, w = scan.shape
    moved = np.any(scan.points != scan.clean, axis=-1)
    assert np.array_equal(moved, scan.truth == A)
    assert np.array_equal(scan.points[..., :2], scan.clean[..., :2])
    edge_cols = set(np.flatnonzero((scan.truth == E).any(axis=0)).tolist())
    for d in scan.defects:
        assert len(d.cells) == 1 and d.indices == (d.cells[0][0] * w + d.cells[0][1],)
        r, c = d.cells[0]
        dz = scan.points[r, c, 2] - scan.clean[r, c, 2]
        assert dz == pytest.approx(d.offset, abs=1e-12)
        assert 4.0 * scan.step - 1e-12 <= abs(d.offset) <= 8.0 * scan.step + 1e-12
        assert scan.kinds[r, c] == d.kind
        assert d.kind == ("spike" if d.offset > 0 else "pit")
        assert (c in edge_cols) == d.on_edge
        if d.on_edge:
            assert d.kind == "spike"
    assert np.count_nonzero(scan.kinds != "") == 5
    # margins: 5 cells from the border, from the strips (unless on one) and from each other
    cells = [d.cells[0] for d in scan.defects]
    for r, c in cells:
        assert 5 <= r < h - 5 and 5 <= c < w - 5
    for d in scan.defects:
        if not d.on_edge:
            assert min(abs(d.cells[0][1] - c) for c in edge_cols) > 5
    for i, (r1, c1) in enumerate(cells):
        for r2, c2 in cells[i + 1 :]:
            assert max(abs(r1 - r2), abs(c1 - c2)) > 5


@pytest.mark.parametrize("step", [0.2, 0.25, 0.3, 0.4, 0.5])
def test_paper_scan_steps(step: float) -> None:
    scan = sim.paper_scan(step=step)
    assert scan.shape == (math.floor(100 / step + 1e-9) + 1, math.floor(80 / step + 1e-9) + 1)
    x, y = grid_axes(scan)
    assert x[0] == -50.0 and y[0] == -50.0 and x[-1] <= 30.0 and y[-1] <= 50.0
    assert np.count_nonzero(scan.truth == A) == 5
    assert np.count_nonzero(scan.truth == E) == 2 * scan.shape[0] - 2


def test_paper_scan_options() -> None:
    scan = sim.paper_scan(n_abnormal=7, n_on_edge=3, strips=(0.0,), height=5.0, seed=4)
    assert np.count_nonzero(scan.truth == A) == 7
    assert np.count_nonzero(scan.truth == E) == scan.shape[0] - 3
    assert all(abs(d.offset) == pytest.approx(2.5, abs=1e-12) for d in scan.defects)
    none = sim.paper_scan(n_abnormal=0, n_on_edge=0, strips=())
    assert not none.defects and np.all(none.truth == N)
    assert np.array_equal(none.points, none.clean)


def test_paper_scan_noise_and_dropout() -> None:
    scan = sim.paper_scan(noise=0.05, dropout=0.02, seed=2)
    fin = np.isfinite(scan.points).all(axis=-1)
    assert np.array_equal(~fin, scan.truth == INV)
    assert np.array_equal(np.isnan(scan.points), np.isnan(scan.clean))
    assert np.all(np.isnan(scan.points[~fin]))
    assert np.count_nonzero(~fin) == round(0.02 * scan.truth.size)
    normal = scan.truth == N
    resid = scan.points[..., 2][normal] - sim.paper_surface(scan.points[..., 0][normal])
    assert np.std(resid) == pytest.approx(0.05 * 0.5, rel=0.05)
    assert abs(np.mean(resid)) < 0.01 * 0.5
    # defects sit on top of the same noisy scan
    ok = fin & (scan.truth != A)
    assert np.array_equal(scan.points[ok], scan.clean[ok])
    # dropouts keep 2 cells away from defects and strips
    for r, c in zip(*np.nonzero(scan.truth != N)):
        if scan.truth[r, c] in (A, E):
            window = scan.truth[max(r - 2, 0) : r + 3, max(c - 2, 0) : c + 3]
            assert not np.any(window == INV)


# --------------------------------------------------------------------------------------------
# paper_points
# --------------------------------------------------------------------------------------------


def test_paper_points() -> None:
    cloud = sim.paper_points()
    p, t = cloud.points, cloud.truth
    assert p.shape == cloud.clean.shape == (10_000, 3) and p.dtype == np.float64
    assert t.shape == (10_000,) and t.dtype == np.uint8
    assert np.count_nonzero(t == A) == 5 and len(cloud.defects) == 5
    assert p[:, 0].min() >= -50 and p[:, 0].max() <= 30
    assert p[:, 1].min() >= -50 and p[:, 1].max() <= 50
    # normal points lie on the surface; strip points on surface + triangular bead
    x = p[:, 0]
    normal = t == N
    np.testing.assert_allclose(p[normal, 2], sim.paper_surface(x[normal]), rtol=0, atol=1e-12)
    dist = np.minimum(np.abs(x + 25.0), np.abs(x - 15.0))
    assert np.array_equal(t == E, (dist < 1.0) & (t != A))
    bead = 2.0 * np.clip(1.0 - dist / 1.0, 0.0, None)
    np.testing.assert_allclose(cloud.clean[:, 2], sim.paper_surface(x) + bead, rtol=0, atol=1e-12)
    moved = np.any(p != cloud.clean, axis=1)
    assert np.array_equal(moved, t == A)
    for d in cloud.defects:
        (i,) = d.indices
        assert d.cells == ()
        assert p[i, 2] - cloud.clean[i, 2] == pytest.approx(d.offset, abs=1e-12)
        assert 3.0 <= abs(d.offset) <= 5.0
        assert (dist[i] < 0.1) == d.on_edge  # the on-edge ones are the points nearest a crest
    assert sum(d.on_edge for d in cloud.defects) == 2


# --------------------------------------------------------------------------------------------
# make_scan: geometry
# --------------------------------------------------------------------------------------------


def expected_z(surface: str, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The surfaces make_scan documents, with its default parameters."""
    s = x * math.cos(math.radians(15.0)) - y * math.sin(math.radians(15.0))
    if surface == "plane":
        return np.zeros_like(x)
    if surface == "tilted":
        az = math.radians(30.0)
        return math.tan(math.radians(20.0)) * (x * math.cos(az) + y * math.sin(az))
    if surface == "curved":
        r = 2.0 * max(np.abs(x).max(), np.abs(y).max())
        return x**2 / (2 * r) + y**2 / (4 * r)
    if surface == "crease":
        return -math.tan(math.radians(10.0)) * np.abs(s)
    return math.tan(math.radians(60.0)) * np.maximum(s, 0.0)


@pytest.mark.parametrize("surface", sim.SURFACES)
def test_make_scan_surfaces(surface: str) -> None:
    scan = sim.make_scan(surface=surface, defects={})
    assert scan.points.shape == (128, 128, 3) and scan.truth.dtype == np.uint8
    x, y = grid_axes(scan)
    np.testing.assert_allclose(x, (np.arange(128) - 63.5) * 0.3, rtol=0, atol=1e-12)
    np.testing.assert_allclose(y, (np.arange(128) - 63.5) * 0.3, rtol=0, atol=1e-12)
    xx, yy = scan.points[..., 0], scan.points[..., 1]
    np.testing.assert_allclose(scan.points[..., 2], expected_z(surface, xx, yy), rtol=0, atol=1e-12)
    band = scan.truth == E
    if surface in ("crease", "flange"):
        s = xx * math.cos(math.radians(15.0)) - yy * math.sin(math.radians(15.0))
        assert np.array_equal(band, np.abs(s) <= 1.5 * 0.3)
        assert np.all(band.any(axis=1))  # the line crosses every profile
    else:
        assert not band.any()
    assert np.array_equal(scan.points, scan.clean)


DEFECT_HEIGHTS = {"spike": 6.0, "pit": -6.0, "dust": 40.0, "cluster": 6.0}


@pytest.mark.parametrize("surface", sim.SURFACES)
def test_make_scan_defects(surface: str) -> None:
    defects = {"spike": 2, "pit": 2, "dust": 1, "cluster": 2}
    scan = sim.make_scan(surface=surface, defects=defects, seed=5)
    assert np.count_nonzero(scan.truth == A) == 2 + 2 + 1 + 4 * 2
    assert [d.kind for d in scan.defects] == ["spike"] * 2 + ["pit"] * 2 + ["dust"] + [
        "cluster"
    ] * 2
    moved = np.any(scan.points != scan.clean, axis=-1)
    assert np.array_equal(moved, scan.truth == A)
    w = scan.shape[1]
    for d in scan.defects:
        want = DEFECT_HEIGHTS[d.kind] * scan.step
        assert d.offset == pytest.approx(want, abs=1e-12)
        assert d.indices == tuple(sorted(r * w + c for r, c in d.cells))
        for r, c in d.cells:
            assert scan.points[r, c, 2] - scan.clean[r, c, 2] == pytest.approx(want, abs=1e-12)
            assert scan.kinds[r, c] == d.kind and scan.truth[r, c] == A
        if d.kind == "cluster":
            (r0, c0) = d.cells[0]
            assert set(d.cells) == {(r0, c0), (r0, c0 + 1), (r0 + 1, c0), (r0 + 1, c0 + 1)}
        else:
            assert len(d.cells) == 1
    # margins: 5 cells from the border, the EDGE band and each other
    edge = np.argwhere(scan.truth == E)
    all_cells = [(d, rc) for d in scan.defects for rc in d.cells]
    for d, (r, c) in all_cells:
        assert 5 <= r < scan.shape[0] - 5 and 5 <= c < w - 5
        if edge.size:
            assert np.abs(edge - [r, c]).max(axis=1).min() > 5
        for e, (r2, c2) in all_cells:
            if e is not d:
                assert max(abs(r - r2), abs(c - c2)) > 5


def test_make_scan_defect_spec_forms() -> None:
    a = sim.make_scan(defects=["spike", "pit", "spike"], seed=3)
    assert [d.kind for d in a.defects] == ["spike", "pit", "spike"]
    b = sim.make_scan(defects={"spike": 2, "pit": 1}, seed=3)
    assert sorted(d.kind for d in b.defects) == ["pit", "spike", "spike"]
    default = sim.make_scan()
    assert sorted(d.kind for d in default.defects) == ["dust", "pit", "pit", "spike", "spike"]
    assert not sim.make_scan(defects={}).defects


def test_make_scan_noise_dropout_origin() -> None:
    scan = sim.make_scan(noise=0.1, dropout=0.05, seed=7)
    nan = ~np.isfinite(scan.points).all(axis=-1)
    assert np.array_equal(nan, scan.truth == INV)
    assert np.all(np.isnan(scan.points[nan])) and np.all(np.isnan(scan.clean[nan]))
    assert np.count_nonzero(nan) == round(0.05 * 128 * 128)
    z = scan.points[..., 2][scan.truth == N]
    assert np.std(z) == pytest.approx(0.1 * 0.3, rel=0.05)
    base = sim.make_scan(surface="tilted", seed=2)
    far = sim.make_scan(surface="tilted", seed=2, origin=(1.0e4, -2.0e4, 500.0))
    np.testing.assert_allclose(
        far.points - base.points,
        np.broadcast_to([1.0e4, -2.0e4, 500.0], base.points.shape),
        rtol=0,
        atol=1e-8,
    )
    assert np.array_equal(far.truth, base.truth)


# --------------------------------------------------------------------------------------------
# Determinism
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "make",
    [
        lambda seed: sim.paper_scan(seed=seed, noise=0.02, dropout=0.01),
        lambda seed: sim.make_scan(
            surface="crease",
            noise=0.05,
            dropout=0.02,
            seed=seed,
            defects={"spike": 2, "cluster": 1},
        ),
        lambda seed: sim.make_scan(surface="curved", seed=seed),
    ],
    ids=["paper_scan", "make_scan-noisy", "make_scan-clean"],
)
def test_scan_seeded(make) -> None:
    a, b, c = make(11), make(11), make(12)
    for name in ("points", "clean", "truth", "kinds"):
        assert same(getattr(a, name), getattr(b, name)), name
    assert a.defects == b.defects
    assert not same(a.points, c.points)
    assert not same(a.truth, c.truth)


def test_paper_points_seeded() -> None:
    a, b, c = sim.paper_points(seed=4), sim.paper_points(seed=4), sim.paper_points(seed=5)
    assert same(a.points, b.points) and same(a.truth, b.truth) and a.defects == b.defects
    assert not same(a.points, c.points)


# --------------------------------------------------------------------------------------------
# Bad arguments
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("func", "kwargs", "match"),
    [
        (sim.paper_scan, {"step": 0.0}, "step"),
        (sim.paper_scan, {"step": float("nan")}, "step"),
        (sim.paper_scan, {"n_abnormal": -1}, "n_abnormal"),
        (sim.paper_scan, {"n_abnormal": 2.5}, "n_abnormal"),
        (sim.paper_scan, {"n_abnormal": 2, "n_on_edge": 3}, "n_on_edge"),
        (sim.paper_scan, {"noise": -0.1}, "noise"),
        (sim.paper_scan, {"seed": -1}, "seed"),
        (sim.paper_scan, {"strips": (100.0,)}, "strips"),
        (sim.paper_scan, {"strips": ()}, "edge strip"),
        (sim.paper_scan, {"strips": (0.0, 0.5)}, "3 columns"),
        (sim.paper_scan, {"height": (8.0, 4.0)}, "height"),
        (sim.paper_scan, {"height": 0.0}, "height"),
        (sim.paper_scan, {"dropout": 0.9}, "dropout"),
        (sim.paper_scan, {"n_abnormal": 500}, "cannot place"),
        (sim.paper_points, {"n": 10}, "n must"),
        (sim.paper_points, {"n_on_edge": 6}, "n_on_edge"),
        (sim.paper_points, {"strip_half_width": 0.0}, "strip_half_width"),
        (sim.make_scan, {"shape": (4, 128)}, r"shape\[0\]"),
        (sim.make_scan, {"shape": 128}, "shape"),
        (sim.make_scan, {"step": -0.3}, "step"),
        (sim.make_scan, {"surface": "sphere"}, "surface"),
        (sim.make_scan, {"defects": {"burr": 1}}, "unknown defect kind"),
        (sim.make_scan, {"defects": "spike"}, "defects"),
        (sim.make_scan, {"defects": {"spike": -1}}, "defects"),
        (sim.make_scan, {"dropout": -0.1}, "dropout"),
        (sim.make_scan, {"noise": float("inf")}, "noise"),
        (sim.make_scan, {"fold_deg": 90.0}, "fold_deg"),
        (sim.make_scan, {"flange_deg": 0.0}, "flange_deg"),
        (sim.make_scan, {"line_angle_deg": 80.0}, "line_angle_deg"),
        (sim.make_scan, {"surface": "crease", "line_offset": 1e3}, "off the grid"),
        (sim.make_scan, {"surface": "tilted", "tilt_deg": 60.0}, "max_slope_deg"),
        (sim.make_scan, {"origin": (0.0, 0.0)}, "origin"),
        (sim.make_scan, {"shape": (16, 16), "defects": {"spike": 20}}, "cannot place"),
    ],
)
def test_bad_arguments(func, kwargs, match) -> None:
    with pytest.raises(ValueError, match=match):
        func(**kwargs)


# --------------------------------------------------------------------------------------------
# The paper's claim, end to end through the compiled core
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("step", "noise", "seed"),
    [(0.5, 0.0, 0), (0.5, 0.0, 1), (0.5, 0.05, 2), (0.4, 0.0, 3), (0.25, 0.1, 4), (0.2, 0.0, 5)],
)
def test_paper_claim(step: float, noise: float, seed: int) -> None:
    scan = sim.paper_scan(step=step, noise=noise, seed=seed)
    res = miem.detect(scan.points, preset="paper")
    labels = res.labels
    assert np.all(labels[scan.truth == A] == A)  # all 5 injected points found
    assert np.count_nonzero(labels[scan.truth == N] == A) == 0  # no normal point flagged
    assert np.count_nonzero(labels[scan.truth == E] == A) == 0  # edge strips stay
    assert np.all(labels[scan.truth == E] == E)  # flagged in some directions only
    if noise <= 0.05:
        # stronger: the labels are the truth, everything but the strips and the defects NORMAL
        assert np.array_equal(labels, scan.truth)
    else:
        # a noisy dip beside a bead may be flagged once (EDGE); never ABNORMAL
        assert np.count_nonzero(labels[scan.truth == N] != N) <= 10
    found = sorted(tuple(int(i) for i in d.indices) for d in res.defects)
    assert found == sorted(d.indices for d in scan.defects)


def rel_err(plane, ref) -> tuple[float, float]:
    dn = float(np.abs(np.asarray(plane.normal) - np.asarray(ref.normal)).max())
    return dn, abs(plane.d - ref.d) / abs(ref.d)


def test_paper_table() -> None:
    scan = sim.paper_scan()
    rows = sim.paper_table(scan)
    assert [(r.case, r.method) for r in rows] == [
        (case, method)
        for case in ("without outliers", "with outliers")
        for method in ("least squares", "eigenvalue", "MIEM")
    ]
    for r in rows:
        assert r.normal.shape == (3,) and np.linalg.norm(r.normal) == pytest.approx(1, abs=1e-14)
        assert r.normal[2] > 0 and r.rms > 0
    ls0, eig0, miem0, ls1, eig1, miem1 = rows
    # without outliers the three agree; MIEM keeps every point, so it is the eigenvalue fit
    assert miem0.n_points == eig0.n_points == scan.truth.size
    assert max(rel_err(miem0, eig0)) < 1e-12
    assert max(rel_err(ls0, eig0)) < 1e-3
    # with outliers MIEM drops exactly the 5 injected points and returns the clean plane
    assert miem1.n_points == scan.truth.size - 5
    clean = miem.fit_plane(scan.clean[scan.truth != A], method="eigen")
    dn, dd = rel_err(miem1, clean)
    assert dn < 1e-9 and dd < 1e-9
    assert miem1.rms == pytest.approx(clean.rms, rel=1e-9)
    # ... while least squares and the plain eigenvalue fit drift by far more
    for drifted in (ls1, eig1):
        dn, dd = rel_err(drifted, clean)
        assert dn > 1e-6 and dd > 1e-4
        assert drifted.rms > 1.01 * clean.rms


def test_paper_experiment_report() -> None:
    rep = sim.paper_experiment()
    assert rep.claim_holds
    assert (rep.n_found, rep.n_injected, rep.n_false) == (5, 5, 0)
    assert rep.edge_labels == {"NORMAL": 0, "ABNORMAL": 0, "EDGE": 400}
    assert rep.result.iterations == 2  # one pass finds the 5, the second confirms
    angle, _, rel = sim.plane_deviation(rep.rows[5], rep.reference)
    assert angle < 1e-9 and rel < 1e-9
    angle, _, rel = sim.plane_deviation(rep.rows[4], rep.reference)
    assert angle > 1e-5 and rel > 1e-4


def test_main_prints_summary(capsys) -> None:
    assert sim.main(["paper"]) == 0
    out = capsys.readouterr().out
    assert "5 / 5" in out and "0 / 31,956" in out and "0 / 400" in out
    assert "REPRODUCED" in out and "NOT REPRODUCED" not in out
    assert max(len(line) for line in out.splitlines()) <= 100
    for method in ("least squares", "eigenvalue", "MIEM"):
        assert out.count(method) >= 3


def test_main_as_module() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "miem.simulate", "paper", "--seed", "1"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    assert "REPRODUCED" in proc.stdout


def test_main_bad_argument(capsys) -> None:
    with pytest.raises(SystemExit) as info:
        sim.main(["paper", "--step", "-1"])
    assert info.value.code == 2
    assert "step" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# make_scan through the detector: the truth is what MIEM should find
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("surface", sim.SURFACES)
@pytest.mark.parametrize(("noise", "dropout", "seed"), [(0.0, 0.0, 0), (0.05, 0.02, 1)])
def test_make_scan_detect(surface: str, noise: float, dropout: float, seed: int) -> None:
    singles = sim.make_scan(surface=surface, noise=noise, dropout=dropout, seed=seed)
    res = miem.detect(singles.points, preset="paper")  # the paper's settings find single-point defects
    assert np.all(res.labels[singles.truth == A] == A)
    assert not np.any(res.labels[singles.truth != A] == A)
    assert np.array_equal(res.labels == INV, singles.truth == INV)

    clusters = sim.make_scan(
        surface=surface,
        noise=noise,
        dropout=dropout,
        seed=seed,
        defects={"cluster": 3, "spike": 1, "pit": 1, "dust": 1},
    )
    res = miem.detect(clusters.points, preset="paper", scales=(1, 2))  # 2 x 2 clusters need scale 2
    assert np.all(res.labels[clusters.truth == A] == A)
    assert not np.any(res.labels[clusters.truth != A] == A)


@pytest.mark.parametrize("surface", ["plane", "tilted"])
def test_make_scan_heights_seen_by_detector(surface: str) -> None:
    # On a plane the detector's height (along the local normal) is the z offset times n_z.
    scan = sim.make_scan(surface=surface, defects={"spike": 2, "pit": 2, "dust": 1}, seed=8)
    res = miem.detect(scan.points, preset="paper")
    n_z = math.cos(math.radians(20.0)) if surface == "tilted" else 1.0
    by_index = {tuple(int(i) for i in d.indices): d for d in res.defects}
    assert set(by_index) == {d.indices for d in scan.defects}
    for d in scan.defects:
        assert by_index[d.indices].peak_height == pytest.approx(d.offset * n_z, abs=1e-9)
        assert by_index[d.indices].kind == ("pit" if d.offset < 0 else "protrusion")


@pytest.mark.slow
def test_paper_claim_with_reference() -> None:
    """The NumPy oracle reproduces the claim too (and agrees with the core)."""
    from miem import reference

    rep = sim.paper_experiment(backend=reference)
    assert rep.claim_holds
    core = sim.paper_experiment(rep.scan)
    assert np.array_equal(np.asarray(core.result.labels), rep.result.labels)
    for a, b in zip(core.rows, rep.rows):
        assert max(rel_err(a, b)) < 1e-9
