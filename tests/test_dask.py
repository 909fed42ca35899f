"""miem.dask on a LocalCluster with 2 worker processes: labels, flags, angles, heights and
defects equal miem.detect on the whole grid, for every preset, with defects straddling block
borders; a killed worker is retried without wrong output."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest

import miem

da = pytest.importorskip("dask.array", reason="miem[dask] not installed")
distributed = pytest.importorskip("distributed", reason="miem[dask] not installed")
import dask  # noqa: E402

import miem.dask as mdask  # noqa: E402


@pytest.fixture(scope="module")
def client():
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=":0") as cluster:
        with distributed.Client(cluster) as c:
            yield c


def scene(h: int, w: int, borders_r=(), borders_c=(), seed: int = 0) -> np.ndarray:
    """A curved noisy sheet (0.25 mm steps) with spikes, pits, a bead line (a designed EDGE
    feature the whole height long), dropouts, a lost profile, and, on every given block border,
    defects cut by it: 3x3 spike clusters, a wedge burr whose removal cascades over passes, a
    smooth spatter dome (caught by the height test only) and a pit."""
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = c * 0.25, r * 0.25
    z = 0.3 * np.exp(-((x - 0.3 * w * 0.25) ** 2) / 60.0) + 0.002 * y
    z = z + rng.normal(0.0, 0.003, (h, w))
    bead = w // 5
    z[:, bead] += 0.75
    for _ in range(h * w // 800):
        z[rng.integers(1, h - 1), rng.integers(1, w - 1)] += rng.choice([-1, 1]) * rng.uniform(
            0.3, 1.5)

    def dome(r0: int, c0: int, rad: float = 3.5, hgt: float = 0.06) -> None:
        d2 = (r - r0) ** 2 + (c - c0) ** 2
        z[...] += hgt * np.clip(1 - d2 / rad**2, 0, None) ** 2

    def wedge(r0: int, c0: int, along_rows: bool) -> None:
        for k, hh in enumerate([2.4, 1.8, 1.3, 0.9, 0.6, 0.35]):
            rr, cc = (r0 + k - 3, c0) if along_rows else (r0, c0 + k - 3)
            z[rr, cc] += hh
            z[rr + (0 if along_rows else 1), cc + (1 if along_rows else 0)] += 0.9 * hh

    def pair(r0: int, c0: int, dr: int, dc: int) -> None:  # removed over two passes
        z[r0, c0] += 2.0
        z[r0 + dr, c0 + dc] += 1.0

    for b in borders_r:
        for cc in (w // 7, 3 * w // 7, 5 * w // 7):
            z[b - 1:b + 2, cc - 1:cc + 2] += rng.uniform(0.3, 2.0, (3, 3))
            pair(b - 1, cc + 3, 1, 1)
            pair(b, cc - 4, -1, 0)
        wedge(b, 2 * w // 7, along_rows=True)
        dome(b, 4 * w // 7)
        z[b, 6 * w // 7] -= 0.8
    for b in borders_c:
        for rr in (h // 7, 3 * h // 7, 5 * h // 7):
            z[rr - 1:rr + 2, b - 1:b + 2] += rng.uniform(0.3, 2.0, (3, 3))
            pair(rr + 3, b - 1, 1, 1)
            pair(rr - 4, b, 0, -1)
        wedge(2 * h // 7, b, along_rows=False)
        dome(4 * h // 7, b)
        z[6 * h // 7, b] -= 0.8
    for br in borders_r:  # corners
        for bc in borders_c:
            z[br - 1:br + 1, bc - 1:bc + 1] += 1.2
    g = np.dstack([x, y, z])
    g[rng.random((h, w)) < 0.01] = np.nan
    g[h // 3] = np.nan
    return g


def _defects_equal(got: list, want: list) -> None:
    assert len(got) == len(want)
    for a, b in zip(got, want):
        assert (a.id, a.count, a.kind) == (b.id, b.count, b.kind)
        np.testing.assert_array_equal(a.indices, b.indices)
        np.testing.assert_array_equal(a.cells, b.cells)
        for f in ("centroid", "normal", "peak_height", "mean_height", "extent"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)


def check_equal(grid: np.ndarray, chunks, **kw) -> list:
    """miem.dask on `grid` in `chunks` against miem.detect on the whole grid; returns the
    defects (for the caller's own checks). Both run the same parameters, edge test included."""
    want = miem.detect(grid, **{k: v for k, v in kw.items() if k != "strict"})
    res = mdask.detect(da.from_array(grid, chunks=chunks + (3,)), **kw)
    defects, labels, flags, angle, height = res.defects(res.labels, res.flags, res.angle,
                                                        res.height)
    np.testing.assert_array_equal(labels, want.labels)
    np.testing.assert_array_equal(flags, want.flags)
    np.testing.assert_array_equal(angle, want.angle)
    np.testing.assert_array_equal(height, want.height)
    _defects_equal(defects, want.defects)
    return want.defects


def _straddling(defects: list, borders_r=(), borders_c=()) -> int:
    """Number of defects with cells on both sides of some block border."""
    n = 0
    for d in defects:
        rows, cols = d.cells[:, 0], d.cells[:, 1]
        n += any((rows < b).any() and (rows >= b).any() for b in borders_r) or any(
            (cols < b).any() and (cols >= b).any() for b in borders_c)
    return n


@pytest.mark.parametrize("preset", list(miem.PRESETS))
def test_row_blocks_equal_whole_grid_for_every_preset(client, preset: str) -> None:
    halo = mdask.grid_halo(miem.detect(scene(8, 8), preset=preset).params)
    rows = max(64, halo // 2)  # blocks much smaller than the scan: edge blocks see part of it
    h = 6 * rows
    borders = tuple(rows * k for k in range(1, 6))
    g = scene(h, 120, borders_r=borders, seed=1)
    defects = check_equal(g, (rows, 120), preset=preset)
    assert _straddling(defects, borders_r=borders) >= 10
    assert h > rows + 2 * halo or preset == "paper"


@pytest.mark.parametrize("preset", list(miem.PRESETS))
def test_tiles_equal_whole_grid_for_every_preset(client, preset: str) -> None:
    br, bc = (80, 160), (70, 140)
    g = scene(240, 200, borders_r=br, borders_c=bc, seed=2).astype(np.float32)
    defects = check_equal(g, (80, 70), preset=preset)
    assert _straddling(defects, br, bc) >= 10


@pytest.mark.parametrize("kw", [
    {"scales": (1, 2, 3), "max_gap": 2, "max_iterations": 4},
    {"min_step": 0.2, "max_reach": 3, "max_iterations": 3},
    {"preset": "recommended", "max_iterations": 2, "window": 9, "edge_extent": 5},
    {"preset": "recommended", "height_tolerance": 0.05, "heights": "abnormal"},
    {"min_directions": 3, "theta0": 100.0},
])
def test_overrides_equal_whole_grid(client, kw: dict) -> None:
    br, bc = (40, 80), (45, 90)
    g = scene(120, 135, borders_r=br, borders_c=bc, seed=3)
    defects = check_equal(g, (40, 45), **kw)
    assert _straddling(defects, br, bc) >= 4


def test_halo_is_needed(client) -> None:
    # The same scene with a halo far below grid_halo: some labels differ, so the equality above
    # rests on the halo, not on luck.
    g = scene(256, 120, borders_r=(64, 128, 192), seed=4)
    want = miem.detect(g, preset="recommended")
    params = dict(want.params)
    res = mdask._build(da.from_array(g, chunks=(64, 120, 3)),
                       {"preset": "recommended", "num_threads": 1}, params, 0, 0)
    assert not np.array_equal(res.labels.compute(), want.labels)


def test_blocks_without_points_and_numpy_input(client) -> None:
    g = scene(200, 60, seed=5)
    g[:120] = np.nan  # the first blocks and their halos hold no finite point
    defects = check_equal(g, (20, 30), preset="paper")
    assert len(defects) > 0
    res = mdask.detect(g, preset="paper")  # a NumPy array: one block
    np.testing.assert_array_equal(res.labels.compute(), miem.detect(g, preset="paper").labels)


@pytest.mark.parametrize("kw", [{"theta0": "auto"},
                                {"theta0": "auto", "preset": "recommended", "max_iterations": 3}])
def test_auto_theta0_equals_whole_grid(client, kw: dict) -> None:
    br, bc = (50, 100), (45, 90)
    g = scene(150, 135, borders_r=br, borders_c=bc, seed=8)
    g[:, :, 2] *= 3.0  # steeper noise: theta0 inside (75, 170), not at a bound
    want = miem.detect(g, **kw)
    assert 75.0 < want.params["theta0"] < 170.0
    got = mdask.auto_theta0(da.from_array(g, chunks=(50, 45, 3)), kw)
    assert got == want.params["theta0"]
    check_equal(g, (50, 45), **kw)
    g[...] = np.nan  # no finite angle: 75
    g[0, [0, 5, 10]] = [[0, 0, 0], [5, 0, 0], [10, 0, 0]]  # too far apart for an angle
    assert mdask.auto_theta0(da.from_array(g, chunks=(50, 45, 3)), kw) == 75.0 == miem.detect(
        g, **kw).params["theta0"]


def test_strict_halo_and_pickled_blocks(client) -> None:
    params = miem.detect(scene(8, 8), preset="recommended").params
    # angle passes, height passes (window 21, edge_extent 12), edge passes and their step 9
    # (edge_window 15)
    assert mdask.grid_halo(params, strict=True) == 10 * 3 + 10 * (127 + 10) + 11 * (127 + 7) + 10
    assert mdask.grid_halo(params) == 10 * 3 + 10 * (10 + 12 + 1) + 11 * 7 + 10
    assert mdask.grid_halo(miem.detect(scene(8, 8), preset="paper").params, strict=True) == 30
    g = scene(150, 90, borders_r=(50, 100), seed=7)
    check_equal(g, (50, 90), preset="recommended", strict=True)
    # blocks reach the workers pickled: the core takes such arrays as they are
    import pickle

    copy = pickle.loads(pickle.dumps(g.astype(np.float32)))
    np.testing.assert_array_equal(miem.detect(copy).labels, miem.detect(g.astype(np.float32)).labels)


def test_bad_input_is_rejected() -> None:
    g = da.from_array(scene(30, 30), chunks=(10, 10, 3))
    with pytest.raises(ValueError, match="theta0"):
        mdask.detect(g, theta0="sometimes")
    with pytest.raises(ValueError, match="window"):
        mdask.detect(g, window=4)
    with pytest.raises(ValueError, match="grid"):
        mdask.detect(da.zeros((10, 4), chunks=5))
    with pytest.raises(ValueError, match="points: fewer than 3 distinct"):  # a cloud
        mdask.detect(da.zeros((10, 3), chunks=5))
    empty = mdask.detect(da.full((20, 20, 3), np.nan, chunks=(10, 10, 3)))
    with pytest.raises(ValueError, match="fewer than 3 finite points"):
        empty.defects()


def _slow_read(block: np.ndarray) -> np.ndarray:
    time.sleep(0.05)  # a slow disk: the run lasts long enough to kill a worker in it
    return block


@pytest.mark.slow
def test_killed_worker_is_retried(client) -> None:
    g = scene(1200, 100, borders_r=tuple(range(40, 1200, 40)), seed=6)
    want = miem.detect(g, preset="paper")
    grid = da.from_array(g, chunks=(40, 100, 3)).map_blocks(_slow_read)
    res = mdask.detect(grid, preset="paper")
    future = client.compute(res.labels)
    # mid-run: kill a worker process that holds finished blocks and is computing another one
    deadline = time.time() + 60
    victim = None
    while victim is None and time.time() < deadline and not future.done():
        held, busy = client.has_what(), client.processing()
        for addr in busy:
            if busy[addr] and held.get(addr):
                victim = addr
                break
        time.sleep(0.005)
    assert victim is not None, "the run ended before a worker could be killed"
    pid = client.run(os.getpid, workers=[victim])[victim]
    os.kill(pid, signal.SIGKILL)
    assert not future.done()
    np.testing.assert_array_equal(future.result(timeout=120), want.labels)


# --- unorganized clouds -----------------------------------------------------------------------


def cloud(n_side: int, seed: int = 0, tile: float = 0.0) -> np.ndarray:
    """A jittered lattice (1 mm) on a gentle bump, with spikes, 3-point burrs, a floating
    cluster, dropouts (NaN rows) and, with `tile`, burr pairs cut by the tile borders (x or y
    = min + k tile); in a shuffled order (chunks are not spatial)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:n_side, 0:n_side].astype(np.float64)
    x = x.ravel() + rng.uniform(-0.3, 0.3, x.size)
    y = y.ravel() + rng.uniform(-0.3, 0.3, y.size)
    z = 2.0 * np.exp(-((x - n_side / 2) ** 2 + (y - n_side / 3) ** 2) / (n_side**2 / 4))
    pts = np.column_stack([x, y, z + rng.normal(0, 0.01, x.size)])
    for k in rng.choice(x.size, x.size // 150, replace=False):
        pts[k, 2] += rng.uniform(1.0, 3.0)
    for c in rng.choice(x.size, 8, replace=False):  # burrs of 3 neighbouring points
        near = np.argsort(np.hypot(x - x[c], y - y[c]))[:3]
        pts[near, 2] += 2.5
    pts[rng.random(len(pts)) < 0.01] = np.nan
    if tile:
        fin = np.isfinite(pts).all(axis=1)
        for axis in (0, 1):
            lo = pts[fin, axis].min()
            for b in np.arange(lo + tile, pts[fin, axis].max(), tile):
                for other in np.linspace(5, n_side - 5, 6):
                    d = np.where(fin, np.abs(pts[:, 1 - axis] - other), np.inf)
                    left = np.where(pts[:, axis] < b, d + np.abs(pts[:, axis] - b), np.inf)
                    right = np.where(pts[:, axis] >= b, d + np.abs(pts[:, axis] - b), np.inf)
                    pts[np.argmin(left), 2] += 3.0  # a burr of two points, cut by it
                    pts[np.argmin(right), 2] += 3.2
    pts = np.concatenate([pts, [[n_side / 2, n_side / 2, 30.0], [n_side / 2 + 0.5,
                                                                   n_side / 2, 30.2]]])
    return pts[rng.permutation(len(pts))]


def check_points_equal(pts: np.ndarray, chunk: int, **kw) -> tuple:
    spacing = miem.point_spacing(pts)
    kw = dict(radius=4 * spacing, min_step=0.5 * spacing, **kw)
    want = miem.detect(pts, **{k: v for k, v in kw.items() if k != "tile"})
    res = mdask.detect_points(da.from_array(pts, chunks=(chunk, 3)), **kw)
    defects, *arrays = res.defects(res.labels, res.flags, res.angle, res.height, res.degenerate)
    for k, a in zip(("labels", "flags", "angle", "height", "degenerate"), arrays):
        np.testing.assert_array_equal(a, getattr(want, k), err_msg=k)
    _defects_equal(defects, want.defects)
    return want, res


@pytest.mark.parametrize("preset", list(miem.PRESETS))
def test_cloud_tiles_equal_whole_cloud(client, preset: str) -> None:
    pts = cloud(120, seed=1, tile=40.0)
    kw = {"preset": preset, "max_iterations": 2, "tile": 40.0}
    cloud_cfg = miem.CLOUD_PRESETS.get(preset, {})
    if cloud_cfg.get("height_tolerance") is not None and cloud_cfg.get("edge_extent"):
        kw["edge_extent"] = 3  # compact EDGE groups, in the whole cloud's spacings
    if cloud_cfg.get("min_group"):
        kw["min_group"] = 3  # groups of 40 would make the halo cover the whole test cloud
    want, res = check_points_equal(pts, 2000, **kw)
    assert res.params["tiles"] == (3, 3)
    if cloud_cfg.get("height_tolerance") is None:
        assert 40.0 + 2 * res.params["halo"] < 120  # each tile sees part of the cloud only
    lo = np.nanmin(pts[np.isfinite(pts).all(axis=1)], axis=0)
    cut = [d for d in want.defects if any(
        len(np.unique(np.floor((pts[d.indices, a] - lo[a]) / 40.0))) > 1 for a in (0, 1))]
    assert len(cut) >= 10


def test_cloud_small_tiles_full_iterations(client) -> None:
    pts = cloud(60, seed=2)
    spacing = miem.point_spacing(pts)
    check_points_equal(pts, 900, preset="paper")
    # the paper's method with radius and min_step given, on small tiles (8 or more a side)
    kw = {"preset": "paper", "radius": 4 * spacing, "min_step": 0.5 * spacing}
    res = mdask.detect_points(pts, tile=7.0, **kw)
    assert res.params["tiles"][0] >= 8
    want = miem.detect(pts, **kw)
    defects, labels = res.defects(res.labels)
    np.testing.assert_array_equal(labels, want.labels)
    _defects_equal(defects, want.defects)


def test_cloud_refusals() -> None:
    pts = da.from_array(cloud(20), chunks=(100, 3))
    with pytest.raises(ValueError, match="window"):
        mdask.detect_points(pts, radius=3.0, min_step=0.5, window=5)
    with pytest.raises(ValueError, match="tile"):
        mdask.detect_points(pts, radius=3.0, min_step=0.5, tile=-1.0)
    with pytest.raises(ValueError, match="spacing"):
        mdask.detect_points(pts, spacing=-1.0)
    with pytest.raises(ValueError, match="new_rule: miem.dask does not know"):
        mdask._refuse_unknown({"new_rule": 2, "off_rule": 0, "radius": 1.0}, {"radius"})
    # miem.detect's layout= and shape=: named, with what to do instead (no rebuild in miem.dask)
    grid = da.from_array(np.zeros((8, 9, 3)), chunks=(4, 9, 3))
    for f, data in ((mdask.detect, pts), (mdask.detect, grid), (mdask.detect_points, pts)):
        for kw in ({"layout": "auto"}, {"shape": (20, 20)}):
            name = next(iter(kw))
            with pytest.raises(ValueError, match=rf"^{name}: miem.dask.detect(_points)? does "
                                                 r"not take it: .*miem.io.grid_from_scanlines"):
                f(data, **kw)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_cloud_spacing_from_tiles_equals_the_whole_clouds(dtype) -> None:
    pts = cloud(70, seed=4).astype(dtype)
    dup = pts[np.isfinite(pts).all(axis=1)][:900] + dtype(1e-3)  # near duplicates, shuffled in
    pts = np.concatenate([pts, dup])[np.random.default_rng(0).permutation(len(pts) + 900)]
    arr = da.from_array(pts, chunks=(400, 3))
    fin = np.isfinite(pts).all(axis=1)
    lo, hi = pts[fin].min(axis=0), pts[fin].max(axis=0)
    with dask.config.set(scheduler="sync"):
        got = mdask._cloud_spacing(arr, lo, hi, 0.0)
        merged = mdask._cloud_spacing(arr, lo, hi, 0.01)
    assert got == miem.point_spacing(pts)  # every finite row counts
    assert merged == miem.detect(pts, merge_distance=0.01).params["spacing"]  # distinct ones
    assert merged != got


def test_cloud_default_preset_without_lengths(client) -> None:
    """A call on a cloud without lengths: the whole cloud's spacing (found from the tiles) sets
    radius, min_step, link, height_radius and the compact-EDGE span, as miem.detect on the
    whole; the default's cloud edge test runs with the whole cloud's median (found from the
    tiles too: tests/test_dask_cloud_edge.py)."""
    pts = cloud(90, seed=5)
    want = miem.detect(pts)
    assert want.params["edge_tolerance"] is not None
    res = mdask.detect_points(da.from_array(pts, chunks=(700, 3)))
    assert res.params["spacing"] == want.params["spacing"]
    defects, labels, height = res.defects(res.labels, res.height)
    np.testing.assert_array_equal(labels, want.labels)
    np.testing.assert_array_equal(height, want.height)
    _defects_equal(defects, want.defects)


def _spec_min_step(g: np.ndarray):
    """min_step="auto" straight from docs/SPEC.md, with NumPy medians over all rows of `g` (the
    sample rows when `g` has fewer than 256 rows from its first with data)."""
    fin = np.isfinite(g).all(axis=-1)
    spacing = noise = None
    for dr, dc in ((0, 1), (1, 0)):
        H, W = g.shape[0] - dr, g.shape[1] - dc
        ok = fin[:H, :W] & fin[dr:dr + H, dc:dc + W]
        d = g[dr:dr + H, dc:dc + W][ok] - g[:H, :W][ok]
        H2, W2 = g.shape[0] - 2 * dr, g.shape[1] - 2 * dc
        ok3 = fin[:H2, :W2] & fin[dr:dr + H2, dc:dc + W2] & fin[2 * dr:2 * dr + H2,
                                                                 2 * dc:2 * dc + W2]
        if not ok.any() or not ok3.any():
            continue
        z = g[..., 2]
        sec = np.abs(z[:H2, :W2] - 2 * z[dr:dr + H2, dc:dc + W2]
                     + z[2 * dr:2 * dr + H2, 2 * dc:2 * dc + W2])[ok3]
        dist = float(np.median(np.sqrt((d ** 2).sum(axis=1))))
        sigma = 1.4826 * float(np.median(sec)) / np.sqrt(6.0)
        spacing = dist if spacing is None else min(spacing, dist)
        noise = sigma if noise is None else max(noise, sigma)
    return None if noise is None or not 4 * noise > spacing else 4 * noise


@pytest.mark.parametrize("chunks", [(17, 23), (40, 61), (100, 100)])
def test_min_step_auto_medians_from_blocks(chunks) -> None:
    rng = np.random.default_rng(7)
    yy, xx = np.mgrid[0:80, 0:61].astype(np.float64)
    y = np.cumsum(rng.choice([0.1, 0.2, 1.0], 80))[:, None] + 0 * xx  # uneven profiles
    g = np.dstack([xx * 0.05, y, np.round(rng.normal(0, 0.04, xx.shape), 3)])
    g[rng.random(xx.shape) < 0.05] = np.nan
    for grid in (g, g.astype(np.float32)):
        want = _spec_min_step(grid.astype(np.float64))
        assert want is not None  # the noise exceeds the along-profile spacing here
        with dask.config.set(scheduler="sync"):
            got = mdask.auto_min_step(da.from_array(grid, chunks=(*chunks, 3)))
        assert got == want
        assert got == miem.detect(grid).params["min_step"]  # the core's own
        res = mdask.detect(da.from_array(grid, chunks=(*chunks, 3)), preset="recommended",
                           edge_tolerance=None)
        assert res.params["min_step"] == got and res.params["min_step_auto"]
        with dask.config.set(scheduler="sync"):
            labels = res.labels.compute()
        np.testing.assert_array_equal(labels, miem.detect(grid, edge_tolerance=None).labels)
    flat = np.dstack([xx, yy, 0 * xx])  # no noise: off
    assert mdask.auto_min_step(da.from_array(flat, chunks=(30, 30, 3))) is None


def test_min_step_auto_reads_the_256_rows_from_the_first_with_data() -> None:
    """SPEC: the 256 rows from the first row with a finite cell, found over the blocks (rows of
    dropouts first, in another block); the noise doubles after them."""
    rng = np.random.default_rng(9)
    yy, xx = np.mgrid[0:420, 0:31].astype(np.float64)
    sd = np.where(np.arange(420) < 40 + 256, 0.04, 0.08)[:, None]
    g = np.dstack([xx * 0.05, yy * 0.1, np.round(rng.normal(0, 1, (420, 1)) * sd, 3) + 0 * xx])
    g[:40] = np.nan
    want = _spec_min_step(g[40:296])
    assert want is not None and want != _spec_min_step(g[40:])
    with dask.config.set(scheduler="sync"):
        got = mdask.auto_min_step(da.from_array(g, chunks=(37, 17, 3)))
    assert got == miem.detect(g).params["min_step"]
    assert got == pytest.approx(want, rel=1e-12)
    assert mdask.auto_min_step(da.from_array(np.full((50, 8, 3), np.nan), chunks=(20, 8, 3))) \
        is None
