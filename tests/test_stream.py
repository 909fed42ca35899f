"""miem.stream.ProfileStream: labels and heights equal miem.detect on the same rows; bad input."""

from __future__ import annotations

import sys
from pathlib import Path

import miem
import numpy as np
import pytest
from miem import reference as ref
from miem.stream import ProfileStream, StreamRow

sys.path.insert(0, str(Path(__file__).resolve().parent))
from quiet_removed import detect_seeing_removed  # noqa: E402


def make_scan(h: int, w: int, seed: int) -> np.ndarray:
    """A curved sheet with noise, burr tips, pits, a wedge burr across the profiles (removals
    cascade over several passes), dropouts and a lost profile."""
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[0:h, 0:w]
    g = np.zeros((h, w, 3))
    g[..., 0] = c * 0.25
    g[..., 1] = r * 0.3
    g[..., 2] = (0.4 * np.exp(-((c * 0.25 - 0.125 * w) ** 2) / 50.0) + 0.01 * r * 0.3 +
                 rng.normal(0.0, 0.002, (h, w))).round(3)
    for _ in range(6):
        g[rng.integers(1, h - 1), rng.integers(1, w - 1), 2] += rng.uniform(0.5, 1.5)
    for _ in range(3):
        g[rng.integers(1, h - 1), rng.integers(1, w - 1), 2] -= rng.uniform(0.4, 1.4)
    r0, c0 = rng.integers(1, h - 7), rng.integers(1, w - 2)
    for k, hgt in enumerate([2.4, 1.8, 1.3, 0.9, 0.6, 0.35]):
        g[r0 + k, c0, 2] += hgt
        g[r0 + k, c0 + 1, 2] += 0.9 * hgt
    g[rng.random((h, w)) < 0.01] = np.nan
    g[h // 3] = np.nan
    return g


def make_full_scan(h, w, seed):
    """Creases (long EDGE lines along and across the profiles), low bumps and bump clusters
    the height test finds over several passes, burr tips, pits, dropouts, a lost profile."""
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[0:h, 0:w]
    x, y = c * 0.25, r * 0.3
    z = 0.002 * x + 0.01 * y
    z = z + 0.15 * np.abs(x - 0.13 * w) + 0.1 * np.maximum(0, y - 0.2 * h)  # creases
    z = z + 0.8 * (x > 0.6 * w * 0.25) + 0.6 * (y > 0.7 * h * 0.3)  # steps: EDGE lines
    z[:, w // 4] += 0.6          # a fin along the scan: a long EDGE line
    z[h // 2, :] += 0.5          # one across the profiles
    for _ in range(max(2, h * w // 4000)):  # short fins: compact EDGE groups
        r0, c0 = rng.integers(2, h - 8), rng.integers(2, w - 8)
        if rng.random() < 0.5:
            z[r0:r0 + rng.integers(3, 7), c0] += 0.4
        else:
            z[r0, c0:c0 + rng.integers(3, 7)] += 0.4
    z = z + rng.normal(0.0, 0.003, (h, w))
    for _ in range(max(3, h * w // 1500)):  # low bumps, some in clusters
        r0, c0 = rng.integers(0, h), rng.integers(0, w)
        for _ in range(rng.integers(1, 4)):
            rr = np.clip(r0 + rng.integers(-3, 4), 0, h - 1)
            cc = np.clip(c0 + rng.integers(-3, 4), 0, w - 1)
            s = rng.uniform(0.4, 1.2)
            z += rng.uniform(0.02, 0.2) * np.exp(-((r - rr) ** 2 + (c - cc) ** 2) / (2 * s * s))
    for _ in range(max(2, h * w // 3000)):
        z[rng.integers(0, h), rng.integers(0, w)] += rng.uniform(-1.0, 1.5)
    g = np.stack([x, y, z.round(4)], axis=-1)
    g[rng.random((h, w)) < 0.01] = np.nan
    g[h // 3] = np.nan
    return g


def stream_both(stream: ProfileStream, grid: np.ndarray, defects: list | None = None) -> tuple:
    """Labels and heights of every row, each taken when the stream hands it back (and, into
    `defects`, the defects each row made final)."""
    out = np.full(grid.shape[:2], 99, dtype=np.uint8)
    heights = np.full(grid.shape[:2], -1e300)
    expected = 0
    for r in range(grid.shape[0]):
        done = stream.push(grid[r])
        if r < stream.lag:
            assert done is None
        else:
            assert isinstance(done, StreamRow) and done.row == r - stream.lag == expected
            out[done.row], heights[done.row] = done.labels, done.heights
            expected += 1
            if defects is not None:
                defects.extend(_final(done, grid.shape[0]))
    for done in stream.flush():
        assert done.row == expected
        out[done.row], heights[done.row] = done.labels, done.heights
        expected += 1
        if defects is not None:
            defects.extend(_final(done, grid.shape[0]))
    assert expected == grid.shape[0]
    return out, heights


def _final(done: StreamRow, rows: int) -> list:
    """A row's defects, each reported by the first row after its last one (or the scan's last
    row): no later profile could have changed it."""
    for d in done.defects:
        assert d.cells[:, 0].max() == done.row - 1 or done.row == rows - 1
    return done.defects


def assert_same_defects(got: list, want: list, labels: np.ndarray) -> None:
    """The stream's defects are detect's, as a set (the stream numbers them as reported): the
    same points and kind, summaries equal up to the heights' rounding."""
    assert len(want) > 0
    assert sorted(d.id for d in got) == list(range(len(got)))
    got = sorted(got, key=lambda d: d.indices[0])
    want = sorted(want, key=lambda d: d.indices[0])
    assert [d.indices.tolist() for d in got] == [d.indices.tolist() for d in want]
    for a, b in zip(got, want):
        assert a.kind == b.kind and a.count == b.count
        np.testing.assert_array_equal(a.cells, b.cells)
        np.testing.assert_array_equal(a.centroid, b.centroid)
        np.testing.assert_allclose([a.peak_height, a.mean_height, a.extent, *a.normal],
                                   [b.peak_height, b.mean_height, b.extent, *b.normal],
                                   rtol=1e-9, atol=1e-9, equal_nan=True)
    assert sum(d.count for d in want) == (labels == miem.ABNORMAL).sum()


def stream_all(stream: ProfileStream, grid: np.ndarray) -> np.ndarray:
    return stream_both(stream, grid)[0]


def assert_heights_equal(got: np.ndarray, want: np.ndarray, signed: bool = True,
                         atol: float = 1e-9) -> None:
    """Equal up to rounding (the same window planes, summed in another order): NaN at the same
    cells, values within 1e-9 of the scan's few-unit heights."""
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    if not signed:  # a window whose NORMAL points are collinear: the orientation is ill-posed
        got, want = np.abs(got), np.abs(want)
    np.testing.assert_allclose(got[~np.isnan(want)], want[~np.isnan(want)], rtol=0, atol=atol)


# Every preset, and variants that change each stage's lag (window, edge_extent, iterations),
# heights of ABNORMAL points only, an absolute height tolerance, min_step, a wider gap.
STAGE_VARIANTS = [
    {}, {"heights": "abnormal"}, {"max_iterations": 3, "window": 7, "edge_extent": 4},
    {"window": 5, "edge_extent": 30}, {"edge_extent": 0}, {"height_tolerance": "3rms"},
    {"scales": (1, 2), "max_gap": 2, "min_step": 0.2, "max_reach": 4},
]


@pytest.mark.parametrize("preset", sorted(miem.PRESETS))
@pytest.mark.parametrize("variant", range(len(STAGE_VARIANTS)))
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_stream_equals_detect_full_detector(preset: str, variant: int, dtype) -> None:
    grid = make_full_scan(160, 70, 11 + variant).astype(dtype)
    kw = STAGE_VARIANTS[variant]
    want = miem.detect(grid, params=miem.PRESETS[preset], **kw)
    stream = ProfileStream(70, params=miem.PRESETS[preset], dtype=dtype, **kw)
    defects: list = []
    got, heights = stream_both(stream, grid, defects)
    np.testing.assert_array_equal(got, want.labels)
    assert_heights_equal(heights, want.height)
    assert (want.labels == miem.ABNORMAL).sum() > 0
    assert_same_defects(defects, want.defects, want.labels)


# Pass 1 runs batch detection's row kernel (cpp/src/pass1_row.hpp) on the stream's own ring of
# converted rows, CellJudge for what it cannot settle, with min_step. Without it, a filter: with
# max_gap >= 1 and the smallest scale at most max_gap it takes the cell one step further for a
# dropout (CellJudge where that one is missing too); otherwise CellJudge next to each dropout,
# and the row kernel where more than 0.5 % of the rows around are dropouts. Spacing 0.25 mm
# along the profiles: min_step 1.6 mm puts the scale-2 and -3 neighbours 13 and 20 steps out,
# past the kernel's 16 (CellJudge's), scale 1 within it; theta0 above 90 flags the flat surface
# (with neighbours that far, 150 degrees flags a few percent).
PASS1_VARIANTS = [
    {"min_step": 0.3}, {"min_step": 0.3, "theta0": 60.0}, {"min_step": 0.3, "theta0": 120.0},
    {"min_step": 1.6, "scales": (1, 2, 3), "theta0": 150.0},
    {"min_step": 0.6, "max_gap": 2, "scales": (2, 3), "theta0": 150.0},
    {"min_step": 0.3, "max_reach": 2}, {"min_step": None},
    {"min_step": None, "max_gap": 2, "scales": (1, 3), "theta0": 120.0},
]


@pytest.mark.parametrize("variant", range(len(PASS1_VARIANTS)))
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_stream_pass1_kernel_equals_detect(variant: int, dtype) -> None:
    """The stream's pass 1 against batch detection on a scan whose first 90 profiles have 6 %
    dropouts, runs of them along and across the profiles and a lost profile, and whose last 50
    have none (the filter's rows without min_step): the angle passes' labels alone (pass 1
    alone: no later pass re-judges a cell; all passes) and the default detector."""
    h, w = 150, 90
    grid = make_full_scan(h, w, 40 + variant).astype(dtype)
    for r in range(100, h):  # the last rows without dropouts
        bad = np.isnan(grid[r, :, 2])
        grid[r, :, 0] = np.arange(w) * 0.25
        grid[r, :, 1] = r * 0.3
        grid[r, bad, 2] = np.interp(np.flatnonzero(bad), np.flatnonzero(~bad), grid[r, ~bad, 2])
    rng = np.random.default_rng(variant)
    grid[:90][rng.random((90, w)) < 0.05] = np.nan
    grid[20:60, 30] = np.nan  # a run across the profiles
    grid[70, 10:40] = np.nan  # and one along a profile
    assert np.isfinite(grid[100:]).all()
    angles = {"heights": "abnormal", "height_tolerance": None, "edge_tolerance": None}
    for base in ({**angles, "max_iterations": 1}, angles, {}):
        p = miem.default_params("stream").replace(**base, **PASS1_VARIANTS[variant])
        want = miem.detect(grid, params=p)
        assert want.params["min_step"] == PASS1_VARIANTS[variant]["min_step"]
        assert np.isin(want.labels, (miem.ABNORMAL, miem.EDGE)).sum() > 20
        got = stream_all(ProfileStream(w, params=p, dtype=dtype), grid)
        np.testing.assert_array_equal(got, want.labels)


def hand_min_step(g: np.ndarray) -> float:
    """SPEC "min_step='auto'" over all rows of `g` by hand (NumPy medians): 4 max(sigma) where
    sigma = 1.4826 median|second difference of z| / sqrt(6) along and across (it exceeds the
    spacing on the scans below)."""
    noise = []
    for a in (g, g.transpose(1, 0, 2)):
        f = np.isfinite(a).all(axis=-1)
        tri = f[:, :-2] & f[:, 1:-1] & f[:, 2:]
        noise.append(1.4826 * np.median(np.abs(a[:, :-2, 2] - 2 * a[:, 1:-1, 2] + a[:, 2:, 2])[tri])
                     / np.sqrt(6.0))
    return 4.0 * max(noise)


def jittered(grid: np.ndarray, sd: float, lead: int, seed: int) -> np.ndarray:
    """Whole profiles offset in z (sd `sd`: a profiler's profile-to-profile jitter, which turns
    min_step "auto" on) and `lead` profiles of dropouts first (the scanner before the part)."""
    g = grid.copy()
    g[..., 2] += np.random.default_rng(seed).normal(0.0, sd, (g.shape[0], 1))
    g[:lead] = np.nan
    return g


@pytest.mark.parametrize("preset", sorted(miem.PRESETS))
@pytest.mark.parametrize("rows, lead", [(700, 0), (650, 300), (200, 12), (290, 4), (420, 0)])
def test_stream_runs_min_step_auto_as_batch(preset: str, rows: int, lead: int) -> None:
    """min_step="auto" (SPEC: the first 256 rows from the first row with a finite cell) in the
    stream, under every preset: decided over the pushes after lead + 255 (the stages then catch
    up), after rows of dropouts handed back while it waits, or at the flush (fewer than 256
    rows; or while rounds 1-3 run, 290 rows; or while the stages catch up, 420 rows); labels,
    heights and defects equal batch's, and the value differs from the whole grid's (the noise
    changes after the rows it reads)."""
    grid = jittered(make_full_scan(rows, 70, 31), 0.1, lead, 5)
    grid[lead + 256:, :, 2] += np.random.default_rng(6).normal(0.0, 0.1, (max(rows - lead - 256,
                                                                              0), 1))
    p = miem.PRESETS[preset].replace(min_step="auto")
    want = miem.detect(grid, params=p)
    step = want.params["min_step"]
    assert isinstance(step, float) and step > 0
    assert step == pytest.approx(hand_min_step(grid[lead:lead + 256]), rel=1e-12)
    if rows > lead + 256:
        assert hand_min_step(grid[lead:]) != pytest.approx(step, rel=1e-3)
    stream = ProfileStream(70, params=p)
    assert stream.lag >= 256 and stream.min_step is None  # not decided yet
    defects: list = []
    got, heights = stream_both(stream, grid, defects)
    assert stream.min_step == step  # the value batch resolved
    np.testing.assert_array_equal(got, want.labels)
    assert_heights_equal(heights, want.height)
    assert_same_defects(defects, want.defects, want.labels)
    # with that value given as a length, batch gives the same labels (the rule is the value)
    np.testing.assert_array_equal(miem.detect(grid, params=p, min_step=step).labels, want.labels)


def test_stream_parts_switch_the_pass1_kernel_depth() -> None:
    """One stream, min_step "auto", parts reset in turn: jittered profiles (auto on: pass 1's
    row kernel searches 16 steps deep), then twice a steady scanner (auto off: the filter, and
    the kernel 3 steps deep on the rows next to the part's 4 % dropouts; the second part finds
    the kernel's ring as the first left it), then jittered again. Each part's labels equal batch
    detection of that part alone."""
    modes = (True, False, False, True)
    parts = []
    for k, on in enumerate(modes):
        g = make_full_scan(420, 60, 51 + k)
        if on:
            g = jittered(g, 0.1, 0, 60 + k)
        g[np.random.default_rng(70 + k).random(g.shape[:2]) < 0.04] = np.nan
        parts.append(g)
    p = miem.default_params("stream").replace(min_step="auto")
    stream = ProfileStream(60, params=p)
    for g, on in zip(parts, modes):
        want = miem.detect(g, params=p)
        assert (want.params["min_step"] is not None) == on
        np.testing.assert_array_equal(stream_all(stream, g), want.labels)
        stream.reset()


@pytest.mark.parametrize("lead, kw", [(40, {}), (5, {"preset": "paper", "max_iterations": 1,
                                                    "max_reach": 4})])
def test_stream_spreads_the_min_step_decision(lead: int, kw: dict) -> None:
    """min_step="auto" ON (jittered profiles): the stream decides it over several pushes
    (SPEC "Streaming": rounds 1-3 of the selection 16 rows a push after row F + 255, so with
    the default lag of 550 the value is known at push F + 255 + 47, not before), and it is the
    value batch detection resolves (``res.params["min_step"]``); with a lag of 256 (no pushes
    to spare) the push of row F + 255 decides it. Labels and heights equal batch's."""
    grid = jittered(make_full_scan(lead + 620, 60, 41), 0.1, lead, 9)
    p = miem.default_params("stream").replace(min_step="auto")
    if kw:
        p = miem.PRESETS[kw.pop("preset")].replace(min_step="auto", **kw)
    want = miem.detect(grid, params=p)
    step = want.params["min_step"]
    assert isinstance(step, float) and step > 0  # auto min_step is on here
    stream = ProfileStream(60, params=p)
    rounds = 3 * 256 // 16 if stream.lag == 550 else 1  # pushes rounds 1-3 take
    assert stream.lag in (550, 256)
    got = np.full(grid.shape[:2], 99, dtype=np.uint8)
    heights = np.full(grid.shape[:2], -1e300)
    for r in range(grid.shape[0]):
        done = stream.push(grid[r])
        decided = r >= lead + 255 + rounds - 1
        assert (stream.min_step is not None) == decided, r
        if decided:
            assert stream.min_step == step
        if done is not None:
            got[done.row], heights[done.row] = done.labels, done.heights
    for done in stream.flush():
        got[done.row], heights[done.row] = done.labels, done.heights
    np.testing.assert_array_equal(got, want.labels)
    assert_heights_equal(heights, want.height)


def make_outline_scan(h: int, w: int, seed: int) -> np.ndarray:
    """make_full_scan whose profiles end at 2/3 of the width (an outline) with lips raised
    along it (burrs on a cut edge): the edge test has work."""
    g = make_full_scan(h, w, seed)
    rng = np.random.default_rng(seed + 100)
    end = 2 * w // 3
    g[:, end:] = np.nan
    r0 = 3
    while r0 + 10 < h:
        n = int(rng.integers(2, 9))
        g[r0:r0 + n, end - 1, 2] += rng.uniform(0.03, 0.1)
        r0 += int(rng.integers(15, 40))
    return g


@pytest.mark.parametrize("kw", [{}, {"edge_window": 9, "max_iterations": 4},
                                {"edge_tolerance": 2.5, "edge_window": 5, "window": 9},
                                # pass 1's quiet cells read further than 2 r (q = h = 10 > 6);
                                # no "auto" length: the lag is not 256
                                {"edge_window": 7, "max_iterations": 3, "min_step": None,
                                 "z_resolution": None, "z_noise": 0.003}])
def test_stream_runs_the_edge_test_as_batch(kw: dict) -> None:
    """The edge test in the stream (lag max(H + max(2 r, q), h) + (P - 1) r + h): labels, heights
    and defects equal batch detection's on a scan whose outline carries burrs the edge test
    finds."""
    grid = make_outline_scan(420, 60, 3)
    p = miem.default_params("stream").replace(**kw)
    want = miem.detect(grid, params=p)
    without = miem.detect(grid, params=p, edge_tolerance=None)
    assert (want.labels == miem.ABNORMAL).sum() > (without.labels == miem.ABNORMAL).sum()
    stream = ProfileStream(60, params=p)
    r, P, h = p.grid.edge_window // 2, p.angle.max_iterations, p.grid.window // 2
    auto = p.grid.min_step == "auto"
    R = max(p.angle.scales) + p.grid.max_gap + (p.grid.max_reach if auto else 0)
    lag_h = P * R + p.grid.edge_extent + p.grid.max_gap + P * h
    lag = max(lag_h + max(2 * r, r, h), h) + (P - 1) * r + h
    assert stream.lag == (max(lag, 256) if auto or p.grid.z_noise == "auto" else lag)
    defects: list = []
    got, heights = stream_both(stream, grid, defects)
    np.testing.assert_array_equal(got, want.labels)
    assert_heights_equal(heights, want.height)
    assert_same_defects(defects, want.defects, want.labels)


def _not_quiet(grid: np.ndarray, p: miem.DetectParams, quiet_share: float = 0.2,
               **kw: object) -> int:
    """The NORMAL and EDGE cells after step 9 that the reference finds not quiet (SPEC "Edge
    test" step 1; every one without the height test): the cells edge pass 1 judges (`kw`: the
    keywords that made `p` from the stream's defaults, for the reference). With the height
    test, more than `quiet_share` of them are quiet (the scene exercises the rule)."""
    res = miem.detect(grid, params=p, edge_tolerance=None)  # labels after the height passes
    q = res.params
    r, window = p.grid.edge_window // 2, p.grid.window
    floor = max(0.5 * (q["min_step"] or 0.0), 1.5 * (q["z_resolution"] or 0.0),
                2.0 * (q["z_noise"] or 0.0))
    g = np.asarray(grid, dtype=np.float64)
    lines = res.labels == miem.EDGE
    if q["height_tolerance"] is not None:
        lines &= ~ref._compact_edges(lines, q["edge_extent"],
                                     ~np.isfinite(g).all(-1) | (res.labels == miem.ABNORMAL),
                                     q["max_gap"])
    after9 = ref.edge_test(g, res.labels, window=2 * r + 1, tolerance=p.grid.edge_tolerance,
                           max_iterations=0, min_step=q["min_step"],
                           z_resolution=q["z_resolution"], z_noise=q["z_noise"], lines=lines)[0]
    cand = (after9 == miem.NORMAL) | (after9 == miem.EDGE)
    if q["height_tolerance"] is not None:
        angle = miem.detect(grid, params=p, height_tolerance=None, edge_tolerance=None).labels
        # the height test removed cells: the windows around them were fitted again
        assert ((res.labels == miem.ABNORMAL) & (angle != miem.ABNORMAL)).sum() > 0
        removed = detect_seeing_removed(g, **kw)[1]
        quiet = ref._quiet_cells(g, after9, r, window, floor, removed)
        assert quiet.sum() > quiet_share * cand.sum()
        cand &= ~quiet
    return int(cand.sum())


@pytest.mark.parametrize("kw,noise", [
    ({}, 0.003), ({"edge_window": 7, "max_iterations": 3, "min_step": None,
                  "z_resolution": None, "z_noise": 0.003}, 0.003),
    ({"edge_window": 7, "height_tolerance": None}, 0.003),
    # noise-free, no tolerance floor: the flat planes' cells are quiet
    ({"min_step": None, "z_resolution": None, "z_noise": None}, 0.0)])
def test_stream_judges_the_cells_that_are_not_quiet(kw: dict, noise: float) -> None:
    """Edge pass 1 of the stream judges exactly the NORMAL and EDGE cells the reference finds
    not quiet (SPEC "Edge test" step 1) on the labels after step 9, also where the height
    passes' removals a quiet cell must not have within h = 10 lie beyond the 2 r rows step 9
    and pass 1 read; none is quiet without the height test."""
    rng = np.random.default_rng(8)
    h, w = 300, 120
    r_, c_ = np.mgrid[0:h, 0:w]
    z = 0.01 * r_ * 0.2 + 0.5 * (r_ > 200)  # a sheet, a step
    z = z + rng.normal(0.0, noise, (h, w)) if noise > 0 else z
    z[rng.integers(0, h, 12), rng.integers(0, 80, 12)] += 0.2  # spikes
    for _ in range(12):  # low bump clusters: the height passes peel them over several passes
        r0, c0 = rng.integers(0, h), rng.integers(0, 80)
        for _ in range(rng.integers(1, 4)):
            rr, cc = r0 + rng.integers(-3, 4), c0 + rng.integers(-3, 4)
            s = rng.uniform(0.4, 1.2)
            z += rng.uniform(0.02, 0.2) * np.exp(-((r_ - rr) ** 2 + (c_ - cc) ** 2) / (2 * s * s))
    g = np.stack([c_ * 0.25, r_ * 0.2, z], axis=-1)
    g[:, 80:] = np.nan  # an outline with burrs on it
    for r0 in (20, 90, 150, 240):
        g[r0:r0 + 5, 79, 2] += 0.08
    g[rng.random((h, w)) < 0.03] = np.nan  # dropouts: some windows hold n_min of them
    grid = g
    p = miem.default_params("stream").replace(**kw)
    stream = ProfileStream(w, params=p)
    stream_all(stream, grid)
    assert stream.edge_candidates == _not_quiet(grid, p, **kw)


def test_stream_quiet_cells_among_scattered_dropouts() -> None:
    """At 12 % scattered dropouts a 15 x 15 window often holds n_min = 24 of them while no half
    does (SPEC "Edge test" step 1 counts per half): the stream leaves out the cells the
    reference finds quiet, and its labels equal batch detection's."""
    from miem.simulate import make_scan
    scan = make_scan((260, 90), step=0.2, surface="tilted", noise=0.003, seed=6,
                     defects={"spike": 4, "pit": 4, "cluster": 2}, dropout=0.12)
    g = scan.points.copy()
    r_, c_ = np.mgrid[0:260, 0:90]
    for r0, c0 in ((40, 20), (130, 60), (200, 30)):  # low bumps: the height passes find them
        g[..., 2] += 0.04 * np.exp(-((r_ - r0) ** 2 + (c_ - c0) ** 2) / 0.8)
    p = miem.default_params("stream")
    stream = ProfileStream(90, params=p)
    got = stream_all(stream, g)
    np.testing.assert_array_equal(got, miem.detect(g, params=p).labels)
    assert stream.edge_candidates == _not_quiet(g, p, quiet_share=0.5)


def test_stream_quiet_planes_of_a_sparse_strip() -> None:
    """A strip of columns mostly without return (a 26-column sheet, a lone column of specks at
    the far side): height pass 1 fits those rows cell by cell (few cells in the span), and a
    removal above a row marks its planes stale before that row's pass 1 (kHStale). The cells
    it marks stay candidates, as the reference counts them (the one-cell path once dropped
    the mark, and the stream judged 94 cells fewer)."""
    rng = np.random.default_rng(8)
    h, w, keep = 300, 120, 26
    r_, c_ = np.mgrid[0:h, 0:w]
    z = 0.002 * r_ + rng.normal(0.0, 0.003, (h, w))
    for _ in range(25):  # low bumps: the height passes find them
        r0, c0 = rng.integers(0, h), rng.integers(2, keep - 2)
        z += rng.uniform(0.02, 0.05) * np.exp(-((r_ - r0) ** 2 + (c_ - c0) ** 2) / 0.5)
    g = np.stack([c_ * 0.25, r_ * 0.2, z], axis=-1)
    g[:, keep:w - 1] = np.nan
    g[1::3, w - 1] = np.nan  # the specks: every third row
    g[2::3, w - 1] = np.nan
    p = miem.default_params("stream")
    stream = ProfileStream(w, params=p)
    got = stream_all(stream, g)
    np.testing.assert_array_equal(got, miem.detect(g, params=p).labels)
    assert stream.edge_candidates == _not_quiet(g, p, quiet_share=0.05)


@pytest.mark.parametrize("num_threads", [1, 2, 3])
def test_stream_splits_a_push_among_threads_with_batch_results(num_threads: int) -> None:
    """num_threads splits a push's column work (the angle passes, edge-test tiles and height
    strips) among threads: labels, heights and defects still equal batch detection's."""
    grid = make_outline_scan(420, 300, 5)  # 3 tile columns, the outline in the third
    want = miem.detect(grid)
    assert (want.labels != miem.detect(grid, edge_tolerance=None).labels).any()
    defects: list = []
    got, heights = stream_both(ProfileStream(300, num_threads=num_threads), grid, defects)
    np.testing.assert_array_equal(got, want.labels)
    assert_heights_equal(heights, want.height)
    assert_same_defects(defects, want.defects, want.labels)


REAL_SCAN = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "second_source.pcd"


@pytest.mark.skipif(not REAL_SCAN.exists(), reason="no shared/data/real")
def test_stream_equals_batch_on_the_real_profiler_scan() -> None:
    """The real burred profiler scan (426 profiles of 724 points: six edge-test tiles across,
    dropouts, an outline): the default stream, and with min_step resolved on it, equals batch
    detection; the edge test changes its labels."""
    import miem.io as mio

    grid = np.asarray(mio.grid_from_scanlines(np.asarray(mio.read(REAL_SCAN).points)))
    assert grid.shape[1] > 5 * 128
    p = miem.default_params("stream")
    step = miem.detect(grid).params["min_step"]
    for kw in ({}, {"min_step": step}):
        want = miem.detect(grid, params=p, **kw)
        without = miem.detect(grid, params=p, edge_tolerance=None, **kw)
        assert (want.labels != without.labels).sum() > 100
        got, heights = stream_both(ProfileStream(grid.shape[1], params=p, **kw), grid)
        np.testing.assert_array_equal(got, want.labels)
        assert_heights_equal(heights, want.height, atol=1e-8)  # coordinates of ~100 mm


def test_stream_finds_fins_as_batch() -> None:
    """The edge test's fins (SPEC "Edge test" step 6: thin material standing above ground on
    both sides; the rule reads the cells within r of the judged one) across the stream's tile
    borders: a fin along the profiles over rows 40-250 (tile bands at 64, 128, 192) straddling
    the tile column border at 128, and a diagonal one; the stream equals batch, which flags them."""
    h, w = 300, 200
    rng = np.random.default_rng(4)
    rows, cols = np.mgrid[0:h, 0:w]
    fin = (cols >= 126) & (cols < 130) & (rows >= 40) & (rows < 250)
    fin |= (np.abs(cols - 30 - (rows - 150)) < 2) & (rows >= 150) & (rows < 260)
    grid = np.stack([cols * 0.1, rows * 0.1, rng.normal(0.0, 0.002, (h, w)) + 1.5 * fin], -1)
    p = miem.default_params("stream")
    want = miem.detect(grid, params=p)
    without = miem.detect(grid, params=p, edge_tolerance=None)
    flagged = want.labels == miem.ABNORMAL
    assert flagged[fin].mean() > 0.9 and (flagged & ~(without.labels == miem.ABNORMAL))[fin].any()
    got, heights = stream_both(ProfileStream(w, params=p), grid)
    np.testing.assert_array_equal(got, want.labels)
    assert_heights_equal(heights, want.height)


def test_stream_runs_the_whole_default_detector() -> None:
    """The default stream is the default batch detector (min_step "auto" included): the height
    test finds what the angle test alone does not, over several passes, with compact EDGE
    groups; the stream agrees."""
    grid = make_full_scan(300, 120, 5)
    base = miem.PRESETS["recommended"]
    full = miem.detect(grid, params=base)
    angle_only = miem.detect(grid, params=base, height_tolerance=None, edge_tolerance=None)
    one_pass = miem.detect(grid, params=base, max_iterations=1)
    no_compact = miem.detect(grid, params=base, edge_extent=0)
    n = lambda r: int((r.labels == miem.ABNORMAL).sum())  # noqa: E731
    assert n(full) > 3 * n(angle_only) and n(full) > n(one_pass) and n(full) > n(no_compact)
    stream = ProfileStream(120)
    assert stream.params == base == miem.default_params("stream")
    got, heights = stream_both(stream, grid)
    np.testing.assert_array_equal(got, full.labels)
    assert_heights_equal(heights, full.height)


def test_min_step_resolved_on_a_first_scan_then_given_to_the_stream() -> None:
    """min_step given as a length (e.g. the value "auto" resolved on a first scan of the part,
    ``result.params["min_step"]``): the stream equals batch with it, with a shorter lag."""
    first, grid = make_full_scan(200, 80, 21), make_full_scan(200, 80, 22)
    rng = np.random.default_rng(0)  # profile noise comparable to the spacing: "auto" turns on
    first[..., 2] += rng.normal(0.0, 0.1, first.shape[:2])
    grid[..., 2] += rng.normal(0.0, 0.1, grid.shape[:2])
    step = miem.detect(first).params["min_step"]
    assert isinstance(step, float) and step > 0
    want = miem.detect(grid, min_step=step)
    stream = ProfileStream(80, min_step=step)
    assert stream.lag == ProfileStream(80).lag  # R has max_reach either way
    got, heights = stream_both(stream, grid)
    np.testing.assert_array_equal(got, want.labels)
    assert_heights_equal(heights, want.height)
    assert ProfileStream(80, min_step=None).lag < stream.lag


def test_extreme_height_tolerance_labels_equal_and_heights_up_to_orientation() -> None:
    """An absolute tolerance below the features removes most of the scan: windows left with a
    line of NORMAL points have an ill-posed orientation (SPEC "Height"), where batch and stream
    may differ in the sign, and the values by the rounding such a window amplifies."""
    grid = make_full_scan(120, 90, 1)
    want = miem.detect(grid, height_tolerance=0.03)
    got, heights = stream_both(ProfileStream(90, height_tolerance=0.03), grid)
    np.testing.assert_array_equal(got, want.labels)
    assert_heights_equal(heights, want.height, signed=False, atol=1e-6)


def test_lag_formula() -> None:
    """L = P R + E + (P + 1) h with the height test (E = edge_extent + max_gap), P R + h without; with the edge test
    max(H + max(2 r, q), h) + (P - 1) r + h, H = P R + E + P h, q = max(r, h) (docs/SPEC.md:
    step 9 r rows behind the height passes, pass 1 r rows behind step 9 and q behind the height
    passes: its quiet cells' windows)."""
    # the default: min_step "auto", so R = 1 + 2 (scales, max_gap) + 32 (max_reach)
    assert ProfileStream(10).lag == (10 * 35 + 12 + 1 + 10 * 10 + 2 * 7) + 9 * 7 + 10 == 550
    assert ProfileStream(10, edge_tolerance=None).lag == 10 * 35 + 12 + 1 + 11 * 10 == 473
    off = {"min_step": None, "z_resolution": None, "z_noise": None}  # none waits for its rows
    assert ProfileStream(10, **off).lag == (10 * 3 + 12 + 1 + 10 * 10 + 2 * 7) + 9 * 7 + 10 == 230
    assert ProfileStream(10, preset="paper").lag == 10 * 2 + 10
    assert ProfileStream(10, max_iterations=3, window=7, edge_extent=4, edge_window=9,
                         **off).lag == (3 * 3 + 4 + 1 + 3 * 3 + 2 * 4) + 2 * 4 + 3
    # a height window wider than 2 r: pass 1 waits for the quiet cells' windows (q = h = 10)
    assert ProfileStream(10, max_iterations=3, window=21, edge_extent=4, edge_window=7,
                         **off).lag == (3 * 3 + 4 + 1 + 3 * 10) + 10 + 2 * 3 + 10 == 70
    # without the height test no cell is quiet: 2 r
    assert ProfileStream(10, max_iterations=3, window=21, height_tolerance=None, edge_window=7,
                         **off).lag == max(3 * 3 + 2 * 3, 10) + 2 * 3 + 10
    assert ProfileStream(10, height_tolerance=None, edge_tolerance=None, window=9,
                         **off).lag == 10 * 3 + 4
    # min_step "auto": at least the 256 rows it reads
    assert ProfileStream(10, max_iterations=3, window=7, edge_extent=4, edge_window=9).lag == \
        max((3 * 35 + 4 + 3 * 3 + 2 * 4) + 2 * 4 + 3, 256) == 256
    assert ProfileStream(10, preset="paper", min_step="auto").lag == max(10 * 34 + 10, 256)
    # z_resolution and z_noise "auto" (measured on the same rows) too
    assert ProfileStream(10, min_step=None).lag == max(230, 256)
    assert ProfileStream(10, min_step=None, z_resolution=None).lag == 256
    assert ProfileStream(10, preset="paper", z_noise="auto").lag == 256
    assert ProfileStream(10, preset="paper", z_resolution="auto").lag == 256


@pytest.mark.parametrize(
    "params",
    [{}, {"scales": (1, 2), "max_gap": 2}, {"max_iterations": 3}, {"min_directions": 2},
     {"theta0": 100.0}, {"min_step": 0.2, "max_reach": 4}],
)
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_stream_equals_detect(params: dict, dtype) -> None:
    grid = make_scan(80, 60, 3).astype(dtype)
    want = miem.detect(grid, preset="paper", **params).labels
    got = stream_all(ProfileStream(60, preset="paper", dtype=dtype, **params), grid)
    np.testing.assert_array_equal(got, want)
    assert (want == miem.ABNORMAL).sum() > 0


def test_lag_and_properties() -> None:
    s = ProfileStream(10, preset="paper")
    assert (s.lag, s.width, s.dtype, s.rows_pushed, s.finished) == (30, 10, np.float64, 0, False)
    assert ProfileStream(10, preset="paper", scales=(1, 2), max_gap=2, max_iterations=3).lag == 22
    assert "lag=30" in repr(s)


def test_any_strides_and_dtypes_are_read() -> None:
    grid = make_scan(40, 30, 4)
    want = stream_all(ProfileStream(30), grid)
    fortran = np.asfortranarray(grid.transpose(1, 0, 2)).transpose(1, 0, 2)  # strided rows
    got = stream_all(ProfileStream(30), fortran)
    np.testing.assert_array_equal(got, want)
    ints = np.nan_to_num(grid * 1000).astype(np.int64)  # integers are converted
    ProfileStream(30).push(ints[0])


def test_all_nan_profile_is_a_row_of_dropouts() -> None:
    s = ProfileStream(8, max_iterations=1)
    rows = []
    for r in range(5):
        p = np.zeros((8, 3))
        p[:, 0] = np.arange(8)
        p[:, 1] = r
        done = s.push(np.full((8, 3), np.nan) if r == 0 else p)
        rows += [] if done is None else [done]
    rows += s.flush()
    assert [d.row for d in rows] == list(range(5))
    assert (rows[0].labels == miem.INVALID).all()
    assert (rows[2].labels == miem.NORMAL).all()


def test_bad_input_raises_and_leaves_the_stream_unchanged() -> None:
    s = ProfileStream(16)
    with pytest.raises(ValueError, match="profile: expected shape"):
        s.push(np.zeros((15, 3)))
    with pytest.raises(ValueError, match="profile: expected shape"):
        s.push(np.zeros((16, 2)))
    with pytest.raises(ValueError, match="profile"):
        s.push(np.array(["a"] * 48).reshape(16, 3))
    assert s.rows_pushed == 0
    s.push(np.zeros((16, 3)))
    s.flush()
    assert s.finished
    with pytest.raises(ValueError, match="reset"):
        s.push(np.zeros((16, 3)))
    s.reset()
    assert s.rows_pushed == 0 and not s.finished


@pytest.mark.parametrize(
    "kwargs, match",
    [({"width": 0}, "width"), ({"theta0": 180.0}, "theta0"), ({"scales": ()}, "scales"),
     ({"scales": (0,)}, "scales"), ({"max_gap": -1}, "max_gap"), ({"min_step": -1.0}, "min_step"),
     ({"min_directions": 5}, "min_directions"), ({"max_iterations": 255}, "max_iterations"),
     ({"max_reach": 0}, "max_reach"), ({"dtype": np.int32}, "dtype"),
     ({"theta0": "auto"}, "theta0"), ({"edge_tolerance": -3.0}, "edge_tolerance"),
     ({"min_step": "often"}, "min_step"),
     ({"edge_window": 4}, "edge_window"),
     ({"window": 4}, "window"), ({"edge_extent": -1}, "edge_extent"),
     ({"num_threads": 0}, "num_threads"), ({"num_threads": 1.5}, "num_threads")],
)
def test_bad_parameters(kwargs: dict, match: str) -> None:
    args = {"width": 10, **kwargs}
    width = args.pop("width")
    with pytest.raises(ValueError, match=match):
        ProfileStream(width, **args)


@pytest.mark.parametrize("num_threads", [1, 2])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_stream_builds_a_band_late_where_pass_1_had_no_candidate(num_threads: int, dtype) -> None:
    """Edge pass 1 builds a tile band's integral images ahead (over the 2 r rows before it) only
    in the tile columns where it had a candidate within the last r rows; the others catch up
    from the band's first image row when they first have one. Low bumps the height passes flag
    (each makes the cells within h = 10 rows not quiet: candidates) sit where a tile column's
    first candidate of a band comes before, inside and after that window, in four tile columns
    of a smooth sheet: labels, heights and defects equal batch detection's."""
    rng = np.random.default_rng(12)
    h, w = 330, 400  # bands of 64 rows, tile columns of 128 (the last one 16 wide)
    r_, c_ = np.mgrid[0:h, 0:w]
    z = 0.001 * r_ + rng.normal(0.0, 0.003, (h, w))
    k = 0
    for band in (1, 2, 3, 4):
        for t, off in enumerate((-16, -8, -2, 0, 3, 9)):  # first candidate row - band start
            row = 64 * band + off + 10  # the bump's candidates reach 10 rows above it
            col = 128 * (k % 3) + 20 + 17 * t
            k += 1
            z += 0.05 * np.exp(-((r_ - row) ** 2 + (c_ - col) ** 2) / 2.0)
    g = np.stack([c_ * 0.05, r_ * 0.1, z], axis=-1).astype(dtype)
    p = miem.default_params("stream")
    want = miem.detect(g, params=p)
    assert (want.labels == miem.ABNORMAL).sum() >= 20
    stream = ProfileStream(w, params=p, num_threads=num_threads)
    defects: list = []
    got, heights = stream_both(stream, g, defects)
    np.testing.assert_array_equal(got, want.labels)
    assert_heights_equal(heights, want.height)
    assert_same_defects(defects, want.defects, want.labels)
    assert stream.edge_candidates == _not_quiet(np.asarray(g, dtype=np.float64), p, 0.5)
