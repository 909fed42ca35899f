"""Quiet cells of the edge test (SPEC "Edge test" step 1): the reference's rule against a direct
fit of each cell's height window, and the core against the reference where the rule decides."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

import miem
from miem import reference as ref

sys.path.insert(0, str(Path(__file__).resolve().parent))
from quiet_removed import detect_seeing_removed  # noqa: E402

R = 3  # the edge test's half-size: a 7 x 7 sub-window square
WINDOW = 9  # the height test's window: q = max(3, 4) = 4
FLOOR = 0.01


def _scene(noise: float = 0.002) -> tuple[np.ndarray, np.ndarray]:
    """A sheet (0.1 mm cells, 2 um noise; `noise` 0: a plane to round-off) with a bend, a low
    bump, a dropout patch, one EDGE cell, one ABNORMAL cell the height test flagged, one the
    angle test flagged and a 2 x 2 block of them; the labels set by hand (NORMAL elsewhere)."""
    h, w = 40, 60
    rng = np.random.default_rng(5)
    x, y = np.meshgrid(np.arange(w) * 0.1, np.arange(h) * 0.1)
    z = 0.02 * x + rng.normal(0.0, noise, (h, w)) if noise > 0 else 0.02 * x + 0.01 * y
    z += np.where(x > 4.0, 0.5 * (x - 4.0) ** 2, 0.0)  # a bend from column 40 on
    z[20, 10] += 0.012  # a low bump: 6 sigma of the noise
    g = np.stack([x, y, z], axis=-1)
    labels = np.zeros((h, w), dtype=np.uint8)
    g[8:14, 25:31] = np.nan  # 36 dropouts: >= n_min (4 at r = 3) in the windows around it
    labels[8:14, 25:31] = miem.INVALID
    labels[30, 20] = miem.EDGE
    labels[30, 32] = miem.ABNORMAL  # (removed: the height test's)
    labels[15, 12] = miem.ABNORMAL  # the angle test's: a missing support cell, like a dropout
    labels[33:35, 6:8] = miem.ABNORMAL  # 4 of them: n_min at r = 3
    return g, labels


def _direct(g: np.ndarray, labels: np.ndarray, r: int, window: int, floor: float,
            removed: np.ndarray) -> tuple:
    """Each NORMAL cell: quiet per SPEC step 1 by a plane fitted to its height window's NORMAL
    cells one at a time (np.linalg.eigh of the centred scatter); and how close it is to a
    threshold."""
    h, w = labels.shape
    hw = window // 2
    n_min = max(3, r * r // 2)
    quiet = np.zeros((h, w), dtype=bool)
    margin = np.full((h, w), np.inf)
    for a in range(h):
        for b in range(w):
            if labels[a, b] != miem.NORMAL:
                continue
            r0, c0 = max(0, a - r), max(0, b - r)  # the window clipped at the grid border
            win = labels[r0:a + r + 1, c0:b + r + 1]
            if np.any(win == miem.EDGE):
                continue
            gone = (win == miem.INVALID) | (win == miem.ABNORMAL)
            i, j = a - r0, b - c0  # the cell in it
            halves = (gone[:, :j], gone[:, j + 1:], gone[:i], gone[i + 1:])  # left right up down
            if max(int(half.sum()) for half in halves) >= n_min:
                continue
            if removed[max(0, a - hw):a + hw + 1, max(0, b - hw):b + hw + 1].any():
                continue
            rows, cols = slice(max(0, a - hw), a + hw + 1), slice(max(0, b - hw), b + hw + 1)
            sel = labels[rows, cols] == miem.NORMAL  # the cell too
            p = g[rows, cols][sel]
            m = p.mean(axis=0)
            ev, vec = np.linalg.eigh((p - m).T @ (p - m))
            if not (ev[2] > 0 and ev[1] - ev[0] > 1e-6 * ev[2]):  # a unique normal
                continue
            rms = np.sqrt(max(ev[0], 0.0) / len(p))
            dist = abs((g[a, b] - m) @ vec[:, 0])
            near = dist <= 4.0 * rms or dist <= 1e-6 * np.sqrt((ev[1] + ev[2]) / len(p))
            flat = ev[0] <= 1e-12 * ev[2]  # a plane to round-off
            quiet[a, b] = near and (rms <= 0.75 * floor or flat)
            margin[a, b] = min(abs(dist - 4.0 * rms), abs(rms - 0.75 * floor) + flat)
    return quiet, margin


def test_quiet_cells_are_a_direct_window_fit() -> None:
    g, labels = _scene()
    removed = np.zeros(labels.shape, dtype=bool)
    removed[30, 32] = True  # the ABNORMAL cell, as if the height test had flagged it
    got = ref._quiet_cells(g, labels, R, WINDOW, FLOOR, removed)
    quiet, margin = _direct(g, labels, R, WINDOW, FLOOR, removed)
    sure = margin > 1e-9
    np.testing.assert_array_equal(got[sure], quiet[sure])
    assert (~sure).sum() < 5
    # by geometry: the flat sheet's interior is mostly quiet; the bump (6 sigma off the plane),
    # the bend (its curvature 1 / mm: a 0.9 mm window's plane misses it by more than the
    # floor), the cells within r = 3 of the EDGE cell, within h = 4 of the cell the height test
    # flagged, near the dropouts and the border are not
    assert quiet[5:25, 5:22].mean() > 0.9
    # the angle test's ABNORMAL cell is not, but its neighbours are: to their sub-windows it is
    # a missing cell; the 2 x 2 block's neighbours whose r-square holds all 4 (n_min) are not,
    # those that hold 2 of them are
    assert not got[15, 12] and got[12:19, 9:16].sum() == quiet[12:19, 9:16].sum() >= 40
    assert not got[31:37, 4:10].any()  # rows 31-36, columns 4-9: all 4 within r
    beside = np.zeros_like(got)
    beside[31:37, 3] = beside[31:37, 10] = True  # 2 of them within r
    assert got[beside].sum() == quiet[beside].sum() >= 10
    assert not got[20, 10]
    assert not got[10:30, 45:56].any()
    near = np.zeros_like(got)
    near[27:34, 17:24] = near[26:35, 28:37] = True
    assert not got[near].any()
    # the EDGE cell's ring 4 away is quiet (an angle-test flag there is not within r), the
    # flagged cell's is not (its removal is within h)
    ring = np.zeros_like(got)
    ring[26:35, 16:25] = True
    ring[27:34, 17:24] = False
    assert quiet[ring].mean() > 0.7 and not got[25:36, 27:38][1:-1, 1:-1].any()
    pad = np.pad(labels == miem.INVALID, R)
    holes = np.lib.stride_tricks.sliding_window_view(pad, (2 * R + 1, 2 * R + 1)).sum((2, 3))
    assert (holes >= 4).sum() > 36 and not got[holes >= 4].any()  # 4+ dropouts within r
    # but dropouts within q and not within r leave a cell quiet (columns 21 and 34: 4 from
    # the patch, which the q = 4 square reaches, the r = 3 one not)
    assert quiet[6:16, 21].mean() > 0.7 and quiet[6:16, 34].mean() > 0.7
    # the border too: its windows are clipped (the sheet's top rows and left columns are quiet;
    # on the bend, the last columns' height windows, clipped to 5 columns, fit it within the
    # floor as the direct fit does)
    assert got[:R, 5:22].mean() > 0.7 and quiet[:R, 5:22].mean() > 0.7
    assert got[5:25, :R].mean() > 0.7 and not got[:, 41:-R].any()
    # no floor: nothing on a noisy sheet is quiet
    assert not ref._quiet_cells(g, labels, R, WINDOW, 0.0, removed).any()


def test_noise_free_planes_are_quiet_without_a_floor() -> None:
    """A plane to round-off (a simulated or CAD-sampled face, whose tolerance floor is often 0)
    is flat (l0 <= 1e-12 l2): its cells are quiet with no floor at all, as on a noisy sheet
    within the floor, and the bend beside it (a curved window: not flat) and the bump are
    not. The core judges exactly the cells the reference does: the same labels as the
    reference judging every cell."""
    g, labels = _scene(noise=0.0)
    removed = np.zeros(labels.shape, dtype=bool)
    removed[30, 32] = True
    got = ref._quiet_cells(g, labels, R, WINDOW, 0.0, removed)
    quiet, margin = _direct(g, labels, R, WINDOW, 0.0, removed)
    np.testing.assert_array_equal(got[margin > 1e-9], quiet[margin > 1e-9])
    # by geometry: the plane's interior is quiet (the angle test's cell at row 15, column 12 is
    # a missing support cell), but not where the window holds the bump (row 20, column 10,
    # 0.012 mm high: within h = 4) or the bend (x > 4 mm: column 41 on; l0 of its curvature)
    a, b = np.mgrid[0:40, 0:60]
    bump = (abs(a - 20) <= 4) & (abs(b - 10) <= 4)
    plain = (a >= 5) & (a < 25) & (b >= 5) & (b < 22)
    plain[15, 12] = False  # (the angle test's cell itself: not NORMAL)
    assert got[plain & ~bump].all() and not got[bump].any()
    assert got[3:26, 36].all() and not got[:, 37:].any()  # column 37's window reaches column 41
    assert not got[10:30, 45:56].any() and not got[20, 10]
    assert not got[31:37, 4:10].any()  # the 2 x 2 block
    assert got[:R, 5:22].all() and got[5:15, :R].all()  # the border: clipped windows, flat
    # a detection on a noise-free scan: the core and the reference agree on every label, and
    # the quiet cells change nothing (the reference judging every cell gives the same)
    from miem.simulate import make_scan
    scan = make_scan((90, 100), step=0.2, surface="tilted", noise=0.0, seed=3,
                     defects={"spike": 2, "pit": 2, "dust": 1, "cluster": 1}, dropout=0.002)
    kw = {"z_resolution": None, "z_noise": None}  # no floor (min_step "auto" finds none)
    oracle = ref.detect(scan.points, **kw)
    assert oracle.params["min_step"] is None
    for nt in (1, 2):
        np.testing.assert_array_equal(miem.detect(scan.points, num_threads=nt, **kw).labels,
                                      oracle.labels)
    truth = scan.truth == miem.ABNORMAL
    assert (oracle.labels[truth] == miem.ABNORMAL).all() and truth.sum() > 0
    before = miem.detect(scan.points, edge_tolerance=None, **kw).labels
    every = ref.edge_test(scan.points, before, window=15, tolerance=4.0, max_iterations=10)[0]
    np.testing.assert_array_equal(every, oracle.labels)
    # and the quiet cells are most of them: the core's stream judges the others only
    removed = (before == miem.ABNORMAL) & (miem.detect(
        scan.points, height_tolerance=None, edge_tolerance=None, **kw).labels != miem.ABNORMAL)
    assert ref._quiet_cells(scan.points, before, 7, 21, 0.0, removed).mean() > 0.5


def test_core_judges_what_the_reference_judges() -> None:
    """A low pit on a flat sheet that only step 7 finds (the height test leaves it: under a
    loose tolerance) is not quiet (off its window's plane); nor are a burr on a bend that the
    angle test leaves NORMAL (a rough window). The core and the reference agree on every label,
    and the quiet cells change nothing: the reference judging every cell gives the same."""
    h, w = 60, 70
    rng = np.random.default_rng(11)
    x, y = np.meshgrid(np.arange(w) * 0.1, np.arange(h) * 0.1)
    z = rng.normal(0.0, 0.002, (h, w))
    z[20, 20] -= 0.03  # a low pit
    bend = x > 4.0
    z += np.where(bend, 0.25 * (x - 4.0) ** 2, 0.0)
    z[40:46, 55] += 0.04  # a low burr across the bend
    g = np.stack([x, y, z], axis=-1)
    kw = {"preset": "recommended", "height_tolerance": "12rms"}
    oracle = ref.detect(g, **kw)
    assert oracle.labels[20, 20] == miem.ABNORMAL
    for nt in (1, 2):
        core = miem.detect(g, num_threads=nt, **kw)
        np.testing.assert_array_equal(core.labels, oracle.labels)
    no_edge = ref.detect(g, edge_tolerance=None, **kw)
    assert no_edge.labels[20, 20] != miem.ABNORMAL  # the edge test found it
    # the quiet cells: most of the sheet; judging them too changes no label
    p = oracle.params
    before = no_edge.labels
    assert not (before == miem.EDGE).any()  # (no feature line: step 9 has nothing to do)
    lengths = {k: p[k] for k in ("min_step", "z_resolution", "z_noise")}
    floor = max(0.5 * (p["min_step"] or 0.0), 1.5 * (p["z_resolution"] or 0.0),
                2.0 * (p["z_noise"] or 0.0))
    removed = np.zeros(g.shape[:2], dtype=bool)  # (nothing the height test flagged: 12 rms)
    assert (before == miem.ABNORMAL).sum() == (miem.detect(
        g, height_tolerance=None, edge_tolerance=None, preset="recommended").labels
        == miem.ABNORMAL).sum()
    quiet = ref._quiet_cells(g, before, 7, 21, floor, removed)
    assert quiet[31:50, 10:30].mean() > 0.9  # the flat sheet away from the pit
    assert not quiet[20, 20] and not quiet[40:46, 55].any()
    every = ref.edge_test(g, before, window=15, tolerance=4.0, max_iterations=10, **lengths)[0]
    some = ref.edge_test(g, before, window=15, tolerance=4.0, max_iterations=10,
                         height_window=21, height_removed=removed, **lengths)[0]
    np.testing.assert_array_equal(some, every)
    np.testing.assert_array_equal(some, oracle.labels)


def test_scattered_dropouts_are_counted_per_half() -> None:
    """The support condition is asked of each half sub-window (SPEC "Edge test" step 1): four
    dropouts on the diagonals around a cell (n_min of them in its window, two in each half)
    leave it quiet, four in one half do not. At 12 % scattered dropouts most of a noisy sheet
    stays quiet (a window of 15 x 15 cells holds n_min = 24 of them for 40 % of its cells, a
    half of 15 x 7 almost never), and the core, the reference judging every cell and the
    reference leaving the quiet ones out give the same labels."""
    g, labels = _scene()
    for dr, dc in ((-2, -2), (-2, 2), (2, -2), (2, 2)):  # around (20, 18): 2 per half
        g[20 + dr, 18 + dc] = np.nan
        labels[20 + dr, 18 + dc] = miem.INVALID
    g[17:21, 33] = np.nan  # a column of 4: in the right half of (17..20, 30)
    labels[17:21, 33] = miem.INVALID
    removed = np.zeros(labels.shape, dtype=bool)
    got = ref._quiet_cells(g, labels, R, WINDOW, FLOOR, removed)
    quiet, margin = _direct(g, labels, R, WINDOW, FLOOR, removed)
    sure = margin > 1e-9
    np.testing.assert_array_equal(got[sure], quiet[sure])
    window = ref._box_count(labels == miem.INVALID, 2 * R + 1)
    assert window[20, 18] == 4 == max(3, R * R // 2) and got[20, 18]  # n_min in the window
    assert ref._half_counts(labels == miem.INVALID, R)[19, 30] == 4 == window[19, 30]
    assert not got[17:21, 30].any() and got[17:21, 26].all()  # 3 columns to its left: quiet
    # a detection among scattered dropouts
    from miem.simulate import make_scan
    scan = make_scan((110, 120), step=0.2, surface="tilted", noise=0.003, seed=4,
                     defects={"spike": 3, "pit": 3, "cluster": 2}, dropout=0.12)
    oracle = ref.detect(scan.points)
    for nt in (1, 2):
        np.testing.assert_array_equal(miem.detect(scan.points, num_threads=nt).labels,
                                      oracle.labels)
    truth = scan.truth == miem.ABNORMAL
    assert (oracle.labels[truth] == miem.ABNORMAL).mean() > 0.9
    p = oracle.params
    before = ref.detect(scan.points, edge_tolerance=None).labels
    lengths = {k: p[k] for k in ("min_step", "z_resolution", "z_noise")}
    floor = max(0.5 * (p["min_step"] or 0.0), 1.5 * (p["z_resolution"] or 0.0),
                2.0 * (p["z_noise"] or 0.0))
    removed = (before == miem.ABNORMAL) & (ref.detect(
        scan.points, height_tolerance=None, edge_tolerance=None).labels != miem.ABNORMAL)
    quiet = ref._quiet_cells(scan.points, before, 7, 21, floor, removed)
    gone = (before == miem.INVALID) | (before == miem.ABNORMAL)
    crowded = ref._box_count(gone, 15) >= max(3, 7 * 7 // 2)
    assert crowded.mean() > 0.2 and quiet[crowded].mean() > 0.5
    every = ref.edge_test(scan.points, before, window=15, tolerance=4.0, max_iterations=10,
                          **lengths)[0]
    some = ref.edge_test(scan.points, before, window=15, tolerance=4.0, max_iterations=10,
                         height_window=21, height_removed=removed, **lengths)[0]
    np.testing.assert_array_equal(some, every)
    np.testing.assert_array_equal(some, oracle.labels)


def test_the_last_planes_decide_around_height_removals() -> None:
    """SPEC "Edge test" step 1: the cells around a cell the height test removed are judged by
    their planes over the labels after the height passes (a later pass re-fitted them), so
    the reference hands the quiet rule no removed cell when the passes ended by themselves, and
    the last pass's removals when max_iterations ended them (no pass re-fitted those
    windows). The core, the reference and the reference judging every cell agree either way."""
    from miem.simulate import make_scan
    scan = make_scan((90, 100), step=0.2, surface="tilted", noise=0.003, seed=6,
                     defects={"spike": 3, "pit": 3, "cluster": 2}, dropout=0.002)
    g = scan.points.copy()
    r_, c_ = np.mgrid[0:90, 0:100]
    for r0, c0 in ((25, 20), (60, 70)):  # low bumps: the height passes peel them
        g[..., 2] += 0.04 * np.exp(-((r_ - r0) ** 2 + (c_ - c0) ** 2) / 0.8)
    for iters in (10, 1):
        oracle, removed = detect_seeing_removed(g, max_iterations=iters)
        no_height = ref.detect(g, max_iterations=iters, height_tolerance=None,
                               edge_tolerance=None).labels
        before = ref.detect(g, max_iterations=iters, edge_tolerance=None).labels
        flagged = (before == miem.ABNORMAL) & (no_height != miem.ABNORMAL)
        assert flagged.sum() >= 3  # the height test removed cells
        if iters == 1:  # one pass: its removals' windows were not fitted again
            np.testing.assert_array_equal(removed, flagged)
        else:
            assert not removed.any()
        for nt in (1, 2):
            np.testing.assert_array_equal(
                miem.detect(g, max_iterations=iters, num_threads=nt).labels,
                oracle.labels)
