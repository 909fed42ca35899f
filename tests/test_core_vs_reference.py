"""The C++ core against the independent NumPy reference (the oracle) on organized scans.

Labels and flags must be equal exactly; angles, heights and planes to tight tolerances.
"""

from __future__ import annotations

import numpy as np
import pytest

import miem
from miem import reference as ref


def make_grid(seed: int, shape=(48, 56), dx=0.25, dy=0.4, noise=0.004, nan_frac=0.02,
              dtype=np.float64, offset=(0.0, 0.0, 0.0)) -> np.ndarray:
    """A curved, tilted surface with a crease, spikes, pits, 2x2 clusters, dust and dropouts."""
    rng = np.random.default_rng(seed)
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = xx * dx, yy * dy
    z = 0.05 * x - 0.03 * y + 0.3 * np.exp(-((x - 6.0) ** 2) / 20.0)
    # a crease across the profiles: slope changes by ~20 degrees at column 3w/4
    c0 = (3 * w) // 4
    z += np.where(xx > c0, (xx - c0) * dx * np.tan(np.radians(20)), 0.0)
    z += rng.normal(0.0, noise, z.shape)
    grid = np.dstack([x, y, z])
    for _ in range(6):  # single spikes and pits
        r, c = rng.integers(3, h - 3), rng.integers(3, w - 3)
        grid[r, c, 2] += rng.choice([-1.0, 1.0]) * rng.uniform(0.5, 3.0)
    for _ in range(3):  # 2x2 clusters
        r, c = rng.integers(3, h - 4), rng.integers(3, w - 4)
        grid[r:r + 2, c:c + 2, 2] += rng.uniform(0.8, 2.0)
    r, c = rng.integers(3, h - 3), rng.integers(3, w - 3)
    grid[r, c, 2] += 25.0  # dust far above
    drop = rng.random((h, w)) < nan_frac
    grid[drop] = np.nan
    # a lone return inside a dropout hole
    grid[5:10, 5:10] = np.nan
    grid[7, 7] = (7 * dx, 7 * dy, 0.0)
    grid = grid + np.asarray(offset)
    return grid.astype(dtype)


PARAMS = [
    {},
    {"scales": (1, 2), "max_gap": 2},
    {"min_step": 0.45},
    {"theta0": 120.0, "min_directions": 2, "max_iterations": 3},
    {"theta0": 60.0, "max_gap": 0, "window": 5},
    {"scales": (2,), "min_step": 0.3, "max_reach": 3, "window": 7},
    {"scales": (1, 3), "theta0": 100.0, "max_iterations": 1},
    # beyond the paper
    {"theta0": "auto"},
    {"height_tolerance": "4rms"},
    {"height_tolerance": 0.05, "max_iterations": 2},
    {"theta0": "auto", "scales": (1, 2), "height_tolerance": "3rms"},
    {"preset": "paper", "theta0": 90.0},
    {"theta0": 90.0, "scales": (1, 2), "height_tolerance": "4rms", "edge_extent": 12,
     "window": 15},
    {"theta0": 120.0, "height_tolerance": 0.05, "edge_extent": 3},
]


def assert_same(core: miem.DetectResult, oracle, atol_h=1e-8) -> None:
    np.testing.assert_array_equal(core.labels, oracle.labels)
    np.testing.assert_array_equal(core.flags, oracle.flags)
    np.testing.assert_allclose(core.angle, oracle.angle, rtol=0, atol=1e-9, equal_nan=True)
    np.testing.assert_allclose(core.height, oracle.height, rtol=0, atol=atol_h, equal_nan=True)
    assert core.iterations == oracle.iterations
    if oracle.plane is None:
        assert core.plane is None
    else:
        np.testing.assert_allclose(core.plane.normal, oracle.plane.normal, atol=1e-10)
        assert core.plane.d == pytest.approx(oracle.plane.d, rel=1e-9, abs=1e-9)
        assert core.plane.rms == pytest.approx(oracle.plane.rms, rel=1e-7, abs=1e-12)
        assert core.plane.n_points == oracle.plane.n_points
    assert len(core.defects) == len(oracle.defects)
    for a, b in zip(core.defects, oracle.defects):
        assert a.id == b.id
        np.testing.assert_array_equal(a.indices, b.indices)
        assert a.count == b.count
        assert a.kind == b.kind
        np.testing.assert_allclose(a.centroid, b.centroid, rtol=1e-12)
        np.testing.assert_allclose(a.peak_height, b.peak_height, atol=atol_h, equal_nan=True)
        np.testing.assert_allclose(a.mean_height, b.mean_height, atol=atol_h, equal_nan=True)
        np.testing.assert_allclose(a.normal, b.normal, atol=1e-9, equal_nan=True)
        np.testing.assert_allclose(a.extent, b.extent, atol=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("params", PARAMS, ids=lambda p: ",".join(f"{k}={v}" for k, v in p.items())
                         or "defaults")
def test_detect_matches_reference(seed: int, params: dict) -> None:
    grid = make_grid(seed)
    kw = {"preset": "paper", **params}  # the paper's method, then the overrides
    core, oracle = miem.detect(grid, **kw), ref.detect(grid, **kw)
    assert core.params["theta0"] == pytest.approx(oracle.params["theta0"], abs=1e-9)
    # the scene must exercise the rules: abnormal and invalid cells present (edges with defaults)
    present = set(np.unique(oracle.labels).tolist())
    assert {0, 1, 3} <= present
    if params.get("theta0") == "auto":  # a quiet scan: the automatic threshold is well above 75
        assert core.params["theta0"] > 120.0
    if not params:
        assert 2 in present
    assert_same(core, oracle)


@pytest.mark.parametrize("nan_frac", [0.12, 0.3])
@pytest.mark.parametrize("params", [{}, {"preset": "paper"}, {"max_gap": 2}, {"max_gap": 0}],
                         ids=lambda p: ",".join(f"{k}={v}" for k, v in p.items()) or "defaults")
def test_dense_dropouts_match_reference(nan_frac: float, params: dict) -> None:
    """Scattered dropouts at 12 and 30 %: most 64-cell words of pass 1's row kernel then hold
    many cells whose neighbour at s is a dropout, which it searches on to s + 1 for the whole
    word at once (kernel_rest_all); labels, flags and angles as the reference's."""
    grid = make_grid(7, shape=(60, 150), nan_frac=nan_frac)
    core, oracle = miem.detect(grid, **params), ref.detect(grid, **params)
    assert {0, 1, 3} <= set(np.unique(oracle.labels).tolist())
    assert_same(core, oracle)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_default_is_the_recommended_preset_and_matches_reference(seed: int) -> None:
    grid = make_grid(seed)
    core, oracle = miem.detect(grid), ref.detect(grid)
    assert core.params["preset"] == "recommended"
    assert_same(core, oracle)
    assert_same(miem.detect(grid, preset="recommended"), oracle)
    assert_same(miem.detect(grid, params=miem.PRESETS["recommended"]), oracle)
    assert {0, 1, 3} <= set(np.unique(oracle.labels).tolist())


def test_height_test_finds_a_smooth_dome_like_the_reference() -> None:
    rng = np.random.default_rng(21)
    yy, xx = np.mgrid[0:60, 0:60] * 0.3
    z = rng.normal(0.0, 0.003, xx.shape) + 0.1 * np.exp(-((xx - 9) ** 2 + (yy - 9) ** 2) / 0.4)
    z += np.where(xx > 12, (xx - 12) * np.tan(np.radians(25)), 0.0)  # a designed crease
    grid = np.dstack([xx, yy, z])
    dome = ((xx - 9) ** 2 + (yy - 9) ** 2) < 0.5
    plain = miem.detect(grid, preset="paper")
    assert not plain.abnormal[dome].any()  # the angle test cannot see it
    for tol in ("4rms", 0.04):
        # theta0='auto' marks the crease EDGE; the height test abstains near designed edges
        kw = {"preset": "paper", "theta0": "auto", "height_tolerance": tol}
        core, oracle = miem.detect(grid, **kw), ref.detect(grid, **kw)
        assert_same(core, oracle)
        assert (core.labels[:, 40] == miem.EDGE).sum() > 50
        assert core.abnormal[dome].any()
        assert not core.abnormal[(xx > 11) & (xx < 13)].any()  # the crease is not flagged


def test_float32_matches_reference_on_the_same_values() -> None:
    grid = make_grid(5, dtype=np.float32)
    core = miem.detect(grid, scales=(1, 2))
    oracle = ref.detect(grid.astype(np.float64), scales=(1, 2))
    assert_same(core, oracle, atol_h=1e-7)


def test_far_from_origin_matches_reference() -> None:
    grid = make_grid(7, offset=(1.0e5, -2.0e5, 3.0e4))
    core = miem.detect(grid)
    oracle = ref.detect(grid)
    # heights of a 0.004-noise surface far from the origin: agree to 1e-7 of a unit
    assert_same(core, oracle, atol_h=1e-7)


@pytest.mark.parametrize("heights", ["all", "abnormal"])
def test_same_results_for_any_thread_count(heights: str) -> None:
    grid = make_grid(11, shape=(300, 320), nan_frac=0.05)  # large enough to run in parallel
    one = miem.detect(grid, scales=(1, 2), num_threads=1, heights=heights)
    two = miem.detect(grid, scales=(1, 2), num_threads=2, heights=heights)
    for name in ("labels", "flags", "angle", "height"):
        np.testing.assert_array_equal(getattr(one, name), getattr(two, name))
    assert one.plane is not None and two.plane is not None
    assert one.plane.normal.tolist() == two.plane.normal.tolist()
    assert one.plane.d == two.plane.d
    assert [d.indices.tolist() for d in one.defects] == [d.indices.tolist() for d in two.defects]


def test_abnormal_only_heights_equal_full_heights_on_abnormal_cells() -> None:
    grid = make_grid(3)
    full = miem.detect(grid)
    fast = miem.detect(grid, heights="abnormal")
    np.testing.assert_array_equal(full.labels, fast.labels)
    ab = full.labels == miem.ABNORMAL
    np.testing.assert_allclose(fast.height[ab], full.height[ab], atol=1e-9, equal_nan=True)
    assert np.isnan(fast.height[~ab]).all()


@pytest.mark.parametrize("seed", [0, 4])
def test_plane_fits_match_reference(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(5000, 3)) * (10.0, 4.0, 0.05) + (1e4, -3e3, 50.0)
    pts[rng.random(5000) < 0.01] = np.nan
    for method in ("eigen", "lstsq"):
        a, b = miem.fit_plane(pts, method), ref.fit_plane(pts, method)
        np.testing.assert_allclose(a.normal, b.normal, atol=1e-12)
        np.testing.assert_allclose(a.centroid, b.centroid, rtol=1e-14)
        assert a.d == pytest.approx(b.d, rel=1e-11)
        assert a.rms == pytest.approx(b.rms, rel=1e-9)
        assert a.n_points == b.n_points


def test_vertical_planes_are_oriented_by_geometry_not_rounding() -> None:
    # Points on a plane y = const: the unit normal is (0, +-1, 0) up to rounding, and its n_z
    # is a residue of either sign. SPEC "Plane fit" counts |n_z| <= 1e-6 as zero, so both
    # fits orient by n_y > 0 (before that rule 70 of these 300 core fits and 32 reference fits
    # came out with n_y < 0).
    rng = np.random.default_rng(1)
    for _ in range(300):
        n = int(rng.integers(3, 9))
        y = float(rng.choice([0.4, 1.2, 0.7, 3.3]))
        p = np.column_stack([rng.uniform(0, 2, n), np.full(n, y), rng.normal(0, 1e-2, n)])
        for fit in (miem.fit_plane(p), ref.fit_plane(p)):
            assert abs(fit.normal[1]) == pytest.approx(1.0, abs=1e-9)
            assert fit.normal[1] > 0


_ONE_ROW_WINDOWS = [
    # CI failures (hypothesis, theta0="auto", window 3): defects leave only three NORMAL cells on
    # one row in the window of cell `cell`, so its plane is the vertical plane y = that row's y
    # and the height of the cell is its y offset, +-dy, by the SPEC's orientation (n_y > 0),
    # whatever sign the solver's n_z residue has (up to 1e-11 here in the core's window solver).
    (0.4, [[-1.60386285e-03, -2.64871799e-03, -4.96723244e-04, 8.40890476e-04, 2.27209306e-03],
           [2.19412799e-04, -1.10529464e-03, -1.56956071e-03, 1.49749154e-03, 3.26956609e-03],
           [5.45537552e-04, -2.46665733e-03, -1.91653041e-03, 3.20003818e-03, 4.05764881e-04],
           [-3.46426968e-03, -1.67392386e-04, 1.99976735e01, -1.25857619e-03, -9.76011647e-04]],
     (2, 2), 0.4),  # window rows 1..3: NORMAL cells only on row 1, the cell on row 2: +dy
    (0.25, [[2.51460442e-04, -2.64209727e-04, 1.28084530e-03, 2.09800234e-04, -1.07133875e-03,
             1.83495494e00, 1.83683975e00, 1.89416193e-03, -1.40747047e-03, -2.53084294e-03,
             -1.24654893e-03, 8.26519587e-05],
            [-4.65006155e-03, -4.37583328e-04, -2.49182189e-03, -1.46453471e-03, -1.08851797e-03,
             1.83359915e00, 1.83505501e00, 2.08502674e-03, -2.57069326e-04, 2.73292694e-03,
             -1.33038935e-03, 7.03020140e-04],
            [1.80694036e-03, 1.88024596e-04, -1.48699850e-03, -1.84345075e-03, -9.15451651e-04,
             4.40390247e-04, -2.01923637e-03, -4.18351150e-04, -3.18450020e-04, 1.08169117e-03,
             4.29318245e-04, 7.10745418e-04]],
     (1, 5), -0.25),  # window rows 0..2: NORMAL cells only on row 2, the cell on row 1: -dy
]


@pytest.mark.parametrize("dy, z, cell, height", _ONE_ROW_WINDOWS)
def test_height_over_a_single_row_window_is_by_geometry(dy, z, cell, height) -> None:
    z = np.asarray(z)
    yy, xx = np.mgrid[0:z.shape[0], 0:z.shape[1]].astype(float)
    grid = np.dstack([xx * 0.25, yy * dy, z])
    p = dict(theta0="auto", scales=(1,), max_gap=0, min_step=None, min_directions=None,
             max_iterations=1, window=3, height_tolerance=None, edge_extent=0)
    for res in (miem.detect(grid, **p), ref.detect(grid, **p)):
        assert res.labels[cell] in (miem.ABNORMAL, miem.EDGE)
        assert res.height[cell] == pytest.approx(height, abs=1e-9)


# A hypothesis draw (seed 15, 1,500 examples): a noise-free sloped plane with four spikes. Its
# 30 finite angles have an even count whose middle pair is a straight triple (cell (1, 11)) and
# 2.39 degrees. That cell has two straight pairs, cosines -1 and -1 + 1 ulp: the core kept the
# first (180 - angle = 0), NumPy the larger (8.5e-7), so theta0 differed by 3.8e-6 degrees.
STRAIGHT_MEDIAN_Z = [
    [0.0, 3.8168448431082913e-02, 9.8209062743646824e-02, 1.5824967705621074e-01,
     2.1829029136877465e-01, 2.7833090568133856e-01, 3.3837151999390247e-01,
     3.9841213430646638e-01, 4.5845274861903029e-01, 5.1849336293159420e-01,
     5.7853397724415812e-01, 6.3857459155672203e-01, 6.9861520586928594e-01],
    [-5.2666062463138187e-02, -1.4497614032055274e-02, 4.5543000280508644e-02,
     1.0558361459307256e-01, 1.6562422890563649e-01, 2.2566484321820041e-01,
     -1.5812910279916137e+00, 3.4574607184332823e-01, 4.0578668615589208e-01,
     4.6582730046845600e-01, 2.0525867914781021e+01, 5.8590852909358382e-01,
     6.4594914340614773e-01],
    [-1.6479348079865703e+00, -6.7163676495193461e-02, -7.1230621826295464e-03,
     -1.0664468675202234e+00, 1.1295816644249829e-01, 1.7299878075506220e-01,
     2.3303939506762611e-01, 2.9308000938019008e-01, 3.5312062369275399e-01,
     4.1316123800531790e-01, 4.7320185231788181e-01, 5.3324246663044572e-01,
     5.9328308094300963e-01]]
STRAIGHT_MEDIAN_PARAMS = dict(scales=(1,), max_gap=0, min_step=0.45, min_directions=None,
                              max_iterations=1, max_reach=1, window=3, height_tolerance=None,
                              edge_extent=0)


def straight_median_grid() -> np.ndarray:
    """STRAIGHT_MEDIAN_Z on columns 0.25 apart and rows 0.4 apart."""
    z = np.asarray(STRAIGHT_MEDIAN_Z)
    yy, xx = np.mgrid[0:z.shape[0], 0:z.shape[1]].astype(float)
    return np.dstack([xx * 0.25, yy * 0.4, z])


def test_theta0_auto_reads_straight_triples_as_straight() -> None:
    grid = straight_median_grid()
    core = miem.detect(grid, theta0="auto", **STRAIGHT_MEDIAN_PARAMS)
    oracle = ref.detect(grid, theta0="auto", **STRAIGHT_MEDIAN_PARAMS)
    assert core.params["theta0"] == pytest.approx(oracle.params["theta0"], abs=1e-9)
    # by hand: 30 angles, 15 of them straight (180 - angle below 1e-3: round-off), so the
    # median is half the smallest bent one, whatever round-off the straight ones carry
    dev = 180.0 - ref.detect(grid, theta0=90.0, **STRAIGHT_MEDIAN_PARAMS).angle
    dev = np.sort(dev[np.isfinite(dev)])
    assert dev.size == 30 and (dev[:15] < 1e-5).all() and dev[15] > 1.0
    assert core.params["theta0"] == pytest.approx(180.0 - 6.0 * (dev[15] / 2.0) / 0.6745,
                                                  abs=1e-9)


def test_dask_auto_theta0_reads_straight_triples_as_straight() -> None:
    da = pytest.importorskip("dask.array", reason="miem[dask] not installed")
    import miem.dask as mdask

    grid = straight_median_grid()
    kw = dict(STRAIGHT_MEDIAN_PARAMS, theta0="auto")
    got = mdask.auto_theta0(da.from_array(grid, chunks=(2, 7, 3)), kw)
    assert got == miem.detect(grid, **kw).params["theta0"]


def test_scan_line_functions_match_reference() -> None:
    rng = np.random.default_rng(9)
    x = np.linspace(0, 10, 400)
    line = np.stack([x, np.zeros_like(x), 0.1 * np.sin(x)], axis=1)
    line[rng.integers(0, 400, 20), 2] += 1.0
    line[rng.integers(0, 400, 10)] = np.nan
    line[50] = line[51]  # a duplicate point: no angle at 50 or 51
    for step in (1, 2, 5):
        np.testing.assert_allclose(miem.scan_line_angles(line, step),
                                   ref.scan_line_angles(line, step), atol=1e-9, equal_nan=True)
        np.testing.assert_allclose(miem.scan_line_heights(line, step),
                                   ref.scan_line_heights(line, step), atol=1e-12, equal_nan=True)


@pytest.mark.parametrize("seed", [0, 1])
def test_recommended_preset_matches_reference(seed: int) -> None:
    grid = make_grid(seed)
    core, oracle = miem.detect(grid, preset="recommended"), ref.detect(grid, preset="recommended")
    assert core.params["height_tolerance"] == "4.5rms" and core.params["edge_extent"] == 12
    assert_same(core, oracle)
    # explicit arguments override the preset
    over = miem.detect(grid, preset="recommended", height_tolerance=None)
    assert over.params["height_tolerance"] is None and over.params["theta0"] == 90.0


def _border_cluster_grid() -> np.ndarray:
    """A noisy plane (0.25 spacing), a 2 x 2 cluster at the left border between missing
    profiles, spikes, a pit and dust: the window (5) of the cluster's cells holds NORMAL cells of
    one profile only, three cells nearly on a line, so the window plane is nearly vertical."""
    rng = np.random.default_rng(2)
    yy, xx = np.mgrid[0:19, 0:15] * 0.25
    z = 0.002 * rng.standard_normal(xx.shape)
    z[15:17, 0:2] += 1.14
    z[2, 10] += 1.8
    z[8, 2] -= 0.72
    z[8, 5] += 2.25
    z[10, 0] += 20.0
    g = np.dstack([xx, yy, z])
    g[[1, 4, 7, 11]] = np.nan
    return g


def test_window_planes_the_sums_lose_are_fitted_directly() -> None:
    """The core's window sums hold moments about a point of the tile; for a support nearly on a
    line their round-off exceeds the plane's l1 and the plane tilted by ~1e-5: a height of
    -0.4999911 against the reference's -0.5 on this grid (hypothesis found 4 of 40 seeds of
    test_core_equals_reference_on_grids failing so). Such windows are fitted directly."""
    g = _border_cluster_grid()
    kw = {"theta0": "auto", "scales": (1,), "max_gap": 0, "max_iterations": 1, "window": 5,
          "height_tolerance": None, "edge_extent": 0}
    oracle = ref.detect(g, **kw)
    for nt in (1, 2):
        core = miem.detect(g, num_threads=nt, **kw)
        np.testing.assert_array_equal(core.labels, oracle.labels)
        np.testing.assert_allclose(core.height, oracle.height, rtol=0, atol=1e-12,
                                   equal_nan=True)
    # the stream's running sums: the same heights
    stream = miem.ProfileStream(g.shape[1], **dict(kw, theta0=core.params["theta0"]))
    rows = [r for p in g if (r := stream.push(p)) is not None] + list(stream.flush())
    np.testing.assert_allclose(np.stack([r.heights for r in rows]), oracle.height, rtol=0,
                               atol=1e-12, equal_nan=True)


def test_a_window_plane_without_a_unique_normal_does_not_exist() -> None:
    """SPEC "Height": a window plane exists only where l1 - l0 > 1e-6 l2. A noise-free 3 x 3
    window (equal steps in x and y) around a pit the angle test leaves NORMAL has l0 = l1 by
    symmetry: any vertical plane through the pit fits it equally, and the core and NumPy
    picked different ones (heights 0.25 against -0.25; hypothesis found it)."""
    yy, xx = np.mgrid[0:12, 0:3] * 0.25
    z = np.zeros(xx.shape)
    z[5, 1], z[10, 1] = 2.82, -1.84
    g = np.dstack([xx, yy, z])
    kw = {"theta0": 40.0, "scales": (2,), "max_gap": 0, "max_iterations": 1, "window": 5,
          "height_tolerance": None, "edge_extent": 0}
    oracle = ref.detect(g, **kw)
    assert oracle.labels[10, 1] == miem.NORMAL  # the pit is in the window planes
    assert np.isnan(oracle.height[11]).all()  # the 3 x 3 window at the grid's end: l0 = l1
    for nt in (1, 2):
        core = miem.detect(g, num_threads=nt, **kw)
        np.testing.assert_array_equal(core.labels, oracle.labels)
        np.testing.assert_allclose(core.height, oracle.height, rtol=0, atol=1e-12,
                                   equal_nan=True)
