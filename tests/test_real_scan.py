"""A real laser-profiler scan of a burred workpiece (shared/data/real/second_source.pcd).

The file is unorganized on paper but stored in scan-line order (SOURCES.md): one profile per y
value, x in steps of exactly 0.05 mm. The grid is rebuilt here independently of miem.io.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pypcd4  # a test dependency (the [test] extra)
import pytest

import miem
from miem import reference as ref

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "second_source.pcd"


@pytest.fixture(scope="module")
def scan() -> tuple[np.ndarray, np.ndarray]:
    if not DATA.exists():
        pytest.skip(f"shared data not beside the repository: {DATA} (a user's clone has none)")
    pts = pypcd4.PointCloud.from_path(DATA).numpy(("x", "y", "z")).astype(np.float64)
    # profiles: runs of equal y in file order
    line = np.concatenate([[0], np.cumsum(np.diff(pts[:, 1]) != 0)])
    col = np.round((pts[:, 0] - pts[:, 0].min()) / 0.05).astype(np.int64)
    grid = np.full((line.max() + 1, col.max() + 1, 3), np.nan)
    grid[line, col] = pts
    return pts, grid


def test_grid_rebuild_keeps_every_point(scan) -> None:
    pts, grid = scan
    assert pts.shape == (250_681, 3)  # SOURCES.md: POINTS 250681
    assert grid.shape[0] == 426  # 426 profiles
    assert np.isfinite(grid[..., 2]).sum() == pts.shape[0]  # no two points in one cell


def test_detect_runs_on_the_real_scan(scan) -> None:
    _, grid = scan
    res = miem.detect(grid, preset="paper", scales=(1, 2))
    finite = np.isfinite(grid).all(axis=2)
    assert ((res.labels == miem.INVALID) == ~finite).all()
    counts = res.counts()
    # a burred, cut part: some abnormal points and feature edges, but the surface dominates
    assert counts["ABNORMAL"] > 0 and counts["EDGE"] > 0
    assert counts["NORMAL"] > 0.9 * finite.sum()
    assert res.plane is not None and res.plane.n_points == finite.sum() - counts["ABNORMAL"]
    for d in res.defects[:20]:
        assert d.kind in ("protrusion", "pit", "isolated")
        assert (res.labels.reshape(-1)[d.indices] == miem.ABNORMAL).all()
    # the same labels whatever the thread count
    one = miem.detect(grid, preset="paper", scales=(1, 2), num_threads=1)
    np.testing.assert_array_equal(one.labels, res.labels)


def test_real_patch_matches_reference(scan) -> None:
    _, grid = scan
    patch = grid[150:230, 200:320]  # 80 profiles x 120 points of the measured surface
    assert np.isfinite(patch).all(axis=2).mean() > 0.5
    for kw in ({}, {"scales": (1, 2), "min_step": 0.1}):
        core, oracle = miem.detect(patch, **kw), ref.detect(patch, **kw)
        np.testing.assert_array_equal(core.labels, oracle.labels)
        np.testing.assert_array_equal(core.flags, oracle.flags)
        np.testing.assert_allclose(core.height, oracle.height, atol=1e-7, equal_nan=True)
