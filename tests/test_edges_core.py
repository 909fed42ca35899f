"""The C++ edge test (SPEC "Edge test", opt-in: edge_tolerance / edge_window): core == reference
on edge scenes (float64 and float32, 1 and 2 threads), field checks, and the paths that cannot
honour it (ProfileStream, clouds, miem.dask) refusing it when it is on.

Fast: small crops only (the reference height and edge tests are slow).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

import miem
from miem import _core
from miem import reference as ref

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench" / "accuracy"))

import suite  # noqa: E402


def _grid(z: np.ndarray, step: float = 0.1) -> np.ndarray:
    h, w = z.shape
    x, y = np.meshgrid(np.arange(w) * step, np.arange(h) * step)
    return np.stack([x, y, z], axis=-1)


def _noise(shape: tuple[int, int], seed: int = 3, sigma: float = 0.002) -> np.ndarray:
    return np.random.default_rng(seed).normal(0.0, sigma, shape)


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


def test_lip_before_the_outline_and_only_abnormal_added() -> None:
    pts = _lip_scene()
    base = miem.detect(pts, preset="recommended")
    res = miem.detect(pts, preset="recommended", edge_tolerance=8.0)
    changed = res.labels != base.labels
    assert changed.any() and (res.labels[changed] == miem.ABNORMAL).all()
    # by construction: only lip cells (rows 12..27, columns 18..19) are raised
    rows, cols = np.nonzero(changed)
    assert rows.min() >= 12 and rows.max() <= 27 and cols.min() >= 18 and cols.max() <= 19
    assert base.params["edge_tolerance"] is None  # off by default


def test_off_by_default_everywhere() -> None:
    assert miem.DetectParams().grid.edge_tolerance is None
    assert _core.DetectParams().edge_k == 0.0 and not _core.DetectParams().edge_test()
    pts = _lip_scene()
    np.testing.assert_array_equal(miem.detect(pts).labels,
                                  miem.detect(pts, edge_tolerance=None).labels)


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


def test_cloud_path_rejects_the_edge_test() -> None:
    pts = _grid(_noise((12, 12))).reshape(-1, 3)
    pts = pts[np.random.default_rng(1).permutation(len(pts))]  # a cloud, not scan-line order
    with pytest.raises(ValueError, match="edge_tolerance"):
        miem.detect(pts, edge_tolerance=8.0)


def test_stream_rejects_the_edge_test() -> None:
    with pytest.raises(ValueError, match="edge_tolerance"):
        miem.ProfileStream(10, edge_tolerance=8.0)
    p = _core.DetectParams()
    p.height_abs = p.height_k = 0.0
    p.edge_extent = 0
    p.edge_k = 8.0
    with pytest.raises(ValueError, match="edge_k"):
        _core.ProfileStream64(10, p)


def test_dask_rejects_the_edge_test() -> None:
    mdask = pytest.importorskip("miem.dask")
    g = _lip_scene()
    with pytest.raises(ValueError, match="edge_tolerance"):
        mdask.detect(g, edge_tolerance=8.0)
    # off (the default): accepted, equal to miem.detect
    np.testing.assert_array_equal(mdask.detect(g).labels, miem.detect(g).labels)
