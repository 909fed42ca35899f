"""Edge test step 7, isolated spikes (docs/SPEC.md "Edge test"): a single-cell pit or burr near a
bend that no feature line marks is ABNORMAL; a rounded bend or fillet, whose cells every clean
sub-window misses too but whose neighbours lie as far off as they do, stays clean. The
premises are checked by geometry (plain SVD plane fits of the 8 sub-windows), not by the code
under test; core == reference (float32/64, 1 and 2 threads) and stream == batch."""

from __future__ import annotations

import sys
from pathlib import Path

import miem
import numpy as np
import pytest
from miem import reference as ref

sys.path.insert(0, str(Path(__file__).resolve().parent))
from stream_batch import assert_stream_equals_batch  # noqa: E402

R = 7  # the edge test's sub-window half-size at the default edge_window 15
SIDES = ((-R, R, -R, -1), (-R, R, 1, R), (-R, -1, -R, R), (1, R, -R, R),
         (-R, -1, -R, -1), (-R, -1, 1, R), (1, R, -R, -1), (1, R, 1, R))


def _grid(z: np.ndarray, step: float = 0.1) -> np.ndarray:
    h, w = z.shape
    x, y = np.meshgrid(np.arange(w) * step, np.arange(h) * step)
    return np.stack([x, y, z], axis=-1)


def _premise(g: np.ndarray, p: tuple[int, int]) -> tuple[bool, bool]:
    """(P lies more than 8 rms off every clean sub-window, its neighbours' median distance to
    the cleanest one's plane is below 0.2 x P's), by total-least-squares fits of every cell of
    each sub-window (the scenes below have no ABNORMAL support cell to leave out)."""
    r0, c0 = p
    fits = []
    for a0, a1, b0, b1 in SIDES:
        q = g[max(r0 + a0, 0):r0 + a1 + 1, max(c0 + b0, 0):c0 + b1 + 1].reshape(-1, 3)
        m = q.mean(axis=0)
        _, s, vt = np.linalg.svd(q - m, full_matrices=False)
        fits.append((s[2] / np.sqrt(len(q)), vt[2], m))
    best = min(f[0] for f in fits)
    far = all(abs(u @ (g[p] - m)) > 8 * rms for rms, u, m in fits if rms <= 2 * best)
    _, u, m = min(fits, key=lambda f: f[0])
    nb = [abs(u @ (g[r0 + a, c0 + b] - m)) for a in (-1, 0, 1) for b in (-1, 0, 1) if a or b]
    return far, bool(np.median(nb) < 0.2 * abs(u @ (g[p] - m)))


def _fold(h: int = 40, w: int = 40, convex: bool = True, seed: int = 5) -> np.ndarray:
    """A plane folded 25 degrees at column 20 (no feature line: not EDGE), noise 0.002."""
    cols = np.arange(w)[None, :].repeat(h, 0)
    z = np.random.default_rng(seed).normal(0.0, 0.002, (h, w))
    return z - (1 if convex else -1) * np.tan(np.radians(25)) * np.maximum(cols - 20, 0) * 0.1


def _bend(kind: str, h: int = 40, w: int = 40) -> np.ndarray:
    """A 40-degree bend rounded with radius 1 mm from column 20 (a fillet: rising), noise 0.002."""
    x = (np.arange(w)[None, :].repeat(h, 0) - 20) * 0.1
    rad, ang = 1.0, np.radians(40)
    xs = rad * np.sin(ang)
    prof = np.where(x <= 0, 0.0, np.where(
        x <= xs, rad - np.sqrt(np.maximum(rad * rad - x * x, 0.0)),
        rad * (1 - np.cos(ang)) + np.tan(ang) * (x - xs)))
    z = np.random.default_rng(5).normal(0.0, 0.002, (h, w))
    return z + (prof if kind == "fillet" else -prof)


@pytest.mark.parametrize("convex, amp", [(True, -0.08), (False, 0.08), (True, 0.04)])
def test_spike_near_an_unmarked_fold_is_abnormal(convex: bool, amp: float) -> None:
    z = _fold(convex=convex)
    p = (20, 16)  # 4 cells before the fold: the height test's window straddles it
    z[p] += amp
    g = _grid(z)
    assert _premise(g, p) == (True, True)
    without = miem.detect(g, preset="recommended", edge_tolerance=None).labels
    assert not (without == miem.ABNORMAL).any()  # the height test misses it
    labels = miem.detect(g, preset="recommended").labels
    assert np.argwhere(labels == miem.ABNORMAL).tolist() == [list(p)]


@pytest.mark.parametrize("kind", ["fillet", "bend"])
def test_rounded_bend_stays_clean(kind: str) -> None:
    g = _grid(_bend(kind))
    premises = [_premise(g, (r, c)) for r in range(8, 32) for c in range(8, 32)]
    assert sum(far for far, _ in premises) >= 10  # cells off every clean plane by > 8 rms ...
    assert not any(far and iso for far, iso in premises)  # ... none of them alone
    labels = miem.detect(g, preset="recommended").labels
    assert not (labels == miem.ABNORMAL).any()


def test_border_cells_are_not_tested() -> None:
    z = _fold()
    z[0, 10] -= 0.08  # first row: a clipped neighbourhood, not tested
    z[20, 0] -= 0.08  # first column
    z[39, 10] -= 0.08  # last row
    g = _grid(z)
    without = miem.detect(g, preset="recommended", edge_tolerance=None).labels
    labels = miem.detect(g, preset="recommended").labels
    oracle = ref.detect(g, preset="recommended").labels
    np.testing.assert_array_equal(labels, oracle)
    assert not ((labels == miem.ABNORMAL) & (without != miem.ABNORMAL)).any()


def _scenes() -> list[tuple[str, np.ndarray]]:
    out = []
    z = _fold(70, 150, seed=2)  # back to level at column 125 (a concave fold)
    z += np.tan(np.radians(25)) * np.maximum(np.arange(150) - 125, 0)[None, :] * 0.1
    # spikes 4 cells from a fold, across tile borders (64 x 128), near the first and last rows,
    # two adjacent, and one with two neighbours without a return (an even count)
    for p, amp in (((20, 16), -0.08), ((63, 16), -0.06), ((64, 15), -0.06), ((68, 16), -0.08),
                   ((1, 16), -0.08), ((40, 121), 0.06), ((40, 129), -0.06), ((30, 16), -0.08),
                   ((31, 16), -0.08), ((53, 16), -0.08)):
        z[p] += amp
    z[52, 15:17] = np.nan
    out.append(("fold", _grid(z)))
    z = _fold(48, 48, convex=False, seed=4)
    z[10, 17] += 0.08
    out.append(("valley", _grid(z)))
    out.append(("fillet", _grid(_bend("fillet"))))
    return out


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_core_equals_reference(dtype: type) -> None:
    added = 0
    for name, pts in _scenes():
        pts = pts.astype(dtype)
        oracle = ref.detect(pts, preset="recommended")
        for nt in (1, 2):
            core = miem.detect(pts, preset="recommended", num_threads=nt)
            np.testing.assert_array_equal(core.labels, oracle.labels, err_msg=f"{name} {nt}")
        base = ref.detect(pts, preset="recommended", edge_tolerance=None).labels
        added += int(((oracle.labels == miem.ABNORMAL) & (base != miem.ABNORMAL)).sum())
    assert added >= 5  # the rule fired on these scenes


def test_stream_equals_batch() -> None:
    pts = _scenes()[0][1]
    want = assert_stream_equals_batch(pts, miem.PRESETS["recommended"])
    assert want.labels[20, 16] == miem.ABNORMAL and want.labels[68, 16] == miem.ABNORMAL


def _pad(rows: tuple[int, int], cols: tuple[int, int]) -> np.ndarray:
    """A raised patch 0.08 high, 4 cells before a concave 25-degree fold (the edge test's
    "stands proud" does not fire there: beyond it the surface rises; a lip at a concave feature,
    step 6: beyond the patch the surface dips, then rises with the fold)."""
    z = _fold(convex=False)
    z[rows[0]:rows[1], cols[0]:cols[1]] += 0.08
    return _grid(z)


@pytest.mark.parametrize("rows, cols", [((18, 20), (14, 17)), ((19, 21), (15, 17)),
                                        ((18, 21), (14, 16))])
def test_corner_of_a_raised_pad_is_no_spike(rows: tuple[int, int], cols: tuple[int, int],
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    g = _pad(rows, cols)
    pad = np.zeros(g.shape[:2], bool)
    pad[rows[0]:rows[1], cols[0]:cols[1]] = True
    corners = sorted([r, c] for r in (rows[0], rows[1] - 1) for c in (cols[0], cols[1] - 1))
    for dtype in (np.float64, np.float32):
        pts = g.astype(dtype)
        core = miem.detect(pts, preset="recommended").labels
        np.testing.assert_array_equal(core, ref.detect(pts, preset="recommended").labels)
        np.testing.assert_array_equal(core == miem.ABNORMAL, pad)  # the whole pad: a lip
    # the spike rule alone (the lip rule off) flags none of it: without the corner condition
    # the 4 corners (3 of 8 neighbours raised, in a row and a column direction) pass step 7's
    # other conditions
    monkeypatch.setattr(ref, "_lips", lambda *a: np.zeros(a[4].shape[1], dtype=bool))
    assert not (ref.detect(g, preset="recommended").labels == miem.ABNORMAL).any()
    monkeypatch.setattr(ref, "_spike_corner", lambda res, h: False)
    assert np.argwhere(ref.detect(g, preset="recommended").labels == miem.ABNORMAL).tolist() \
        == corners


@pytest.mark.parametrize("rows", [(20, 21), (20, 22)])
def test_spike_raised_one_way_stays_a_spike(rows: tuple[int, int]) -> None:
    g = _pad(rows, (16, 17))  # one cell, or two in a column: raised in one direction at most
    labels = miem.detect(g, preset="recommended").labels
    np.testing.assert_array_equal(labels, ref.detect(g, preset="recommended").labels)
    assert np.argwhere(labels == miem.ABNORMAL).tolist() == [[r, 16] for r in range(*rows)]


def test_pad_stream_equals_batch() -> None:
    want = assert_stream_equals_batch(_pad((18, 20), (14, 17)), miem.PRESETS["recommended"])
    assert np.argwhere(want.labels == miem.ABNORMAL).tolist() == [
        [r, c] for r in (18, 19) for c in (14, 15, 16)]
