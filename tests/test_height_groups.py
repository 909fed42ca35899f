"""EDGE groups of the height test link across dropouts (docs/SPEC.md "height_tolerance" step 1).

A feature line crossed by a dropout is one feature line: without the link, a bead cut by a
dropout 10 rows from the grid's end leaves a 10-cell piece that reads as compact, and its end
cell, whose window no longer reaches the long piece, was tested against the plane beside the bead
and flagged (the suite's pit_low strip scene: 3 designed-edge false alarms)."""

from __future__ import annotations

import sys
from pathlib import Path

import miem
import miem.reference as ref
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from stream_batch import assert_stream_equals_batch  # noqa: E402


def _groups_compact(edge_cells, invalid_cells, shape, extent, gap) -> np.ndarray:
    edge = np.zeros(shape, bool)
    inv = np.zeros(shape, bool)
    for rc in edge_cells:
        edge[rc] = True
    for rc in invalid_cells:
        inv[rc] = True
    return ref._compact_edges(edge, extent, inv, gap)


def test_link_rule_by_hand() -> None:
    # extent 1: a lone EDGE cell is compact (box 1), two linked cells are not (box >= 2)
    shape = (5, 7)
    # one INVALID cell between them along a row, a column and a diagonal: linked with gap 1
    for a, mid, b in (((2, 1), (2, 2), (2, 3)), ((0, 3), (1, 3), (2, 3)), ((0, 0), (1, 1), (2, 2))):
        assert not _groups_compact([a, b], [mid], shape, 1, 1).any()
        assert _groups_compact([a, b], [mid], shape, 1, 0)[a]  # gap 0: the paper's 8-neighbours
    # the cell between them finite (NORMAL): not linked
    assert _groups_compact([(2, 1), (2, 3)], [], shape, 1, 1)[(2, 1)]
    # two INVALID cells between them: linked with gap 2, not with gap 1
    assert _groups_compact([(2, 0), (2, 3)], [(2, 1), (2, 2)], shape, 1, 1)[(2, 0)]
    assert not _groups_compact([(2, 0), (2, 3)], [(2, 1), (2, 2)], shape, 1, 2)[(2, 0)]
    # a knight's move over an INVALID cell is not along a direction: not linked
    assert _groups_compact([(2, 1), (3, 3)], [(2, 2)], shape, 1, 1)[(2, 1)]


def _bead_scene() -> tuple[np.ndarray, np.ndarray]:
    """A 1-sample bead 3 mm tall (column 20) on a noisy plane, cut by dropouts at rows 10 and 49
    of 60: pieces of rows 0-9, 11-48 and 50-59."""
    h, w = 60, 40
    rng = np.random.default_rng(3)
    rows, cols = np.mgrid[0:h, 0:w]
    z = 0.02 * cols + rng.normal(0.0, 0.01, (h, w))
    z[:, 20] += 3.0
    grid = np.stack([cols * 1.0, rows * 1.0, z], -1)
    grid[10, 20] = np.nan
    grid[49, 20] = np.nan
    bead = np.zeros((h, w), bool)
    bead[:, 20] = True
    bead[[10, 49], 20] = False
    return grid, bead


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_bead_cut_by_dropouts_stays_edge(dtype) -> None:
    grid, bead = _bead_scene()
    grid = grid.astype(dtype)
    core = miem.detect(grid, min_step=None)
    want = ref.detect(grid, min_step=None)
    np.testing.assert_array_equal(core.labels, want.labels)
    # the rule fires: the bead is one feature line, every bead cell stays EDGE
    assert (core.labels[bead] == miem.EDGE).all()
    assert not (core.labels == miem.ABNORMAL).any()
    # without the link (grouping as 8-neighbours only) the end pieces are compact and the two
    # end cells whose window misses the long piece (rows 0 and 59) are 3 mm off the plane
    angle = ref.detect(grid, min_step=None, height_tolerance=None, edge_tolerance=None).labels
    edge = angle == miem.EDGE
    old = ref._compact_edges(edge, 12)
    assert old[bead].sum() == 20 and not ref._compact_edges(edge, 12, ~bead & np.isnan(
        grid[..., 2]), 1)[bead].any()
    # stays quiet where it must: a spike next to the bead is still found
    spiky = grid.copy()
    spiky[30, 5, 2] += 1.0
    res = miem.detect(spiky, min_step=None)
    np.testing.assert_array_equal(res.labels, ref.detect(spiky, min_step=None).labels)
    assert res.labels[30, 5] == miem.ABNORMAL and (res.labels[bead] == miem.EDGE).all()


def test_stream_equals_batch_on_the_cut_bead() -> None:
    grid, _ = _bead_scene()
    assert_stream_equals_batch(grid, miem.default_params("stream"))


def _bead_with_defect_scene() -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """A 1-sample bead 3 units tall (column 20) on a noisy plane, no dropout, with a 2-unit spike
    on it at row 49 of 60: the angle passes take the spike (ABNORMAL), which leaves a 10-row
    piece of the bead beyond it (rows 50-59)."""
    h, w = 60, 40
    rng = np.random.default_rng(3)
    rows, cols = np.mgrid[0:h, 0:w]
    z = 0.02 * cols + rng.normal(0.0, 0.01, (h, w))
    z[:, 20] += 3.0
    z[49, 20] += 2.0
    bead = np.zeros((h, w), bool)
    bead[:, 20] = True
    return np.stack([cols * 1.0, rows * 1.0, z], -1), bead, (49, 20)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_defect_on_a_feature_line_does_not_cut_it(dtype) -> None:
    grid, bead, spike = _bead_with_defect_scene()
    grid = grid.astype(dtype)
    core = miem.detect(grid, min_step=None)
    want = ref.detect(grid, min_step=None)
    np.testing.assert_array_equal(core.labels, want.labels)
    # the angle passes take the spike; the piece beyond it is one feature line with the rest
    angle = ref.detect(grid, min_step=None, height_tolerance=None, edge_tolerance=None).labels
    assert angle[spike] == miem.ABNORMAL
    edge, inv = angle == miem.EDGE, ~np.isfinite(grid).all(axis=-1)
    piece = np.zeros_like(bead)
    piece[50:, 20] = True
    assert ref._compact_edges(edge, 12, inv, 1)[piece].all()  # dropouts only: a compact piece
    assert not ref._compact_edges(edge, 12, inv | (angle == miem.ABNORMAL), 1).any()
    # so the piece, 3 units above the plane beside it, stays EDGE (the rms height test runs next
    # to feature lines: as a compact group it was flagged)
    others = bead.copy()
    others[spike] = False
    assert core.labels[spike] == miem.ABNORMAL and (core.labels[others] == miem.EDGE).all()
    assert np.count_nonzero(core.labels == miem.ABNORMAL) == 1


def test_stream_equals_batch_on_the_bead_with_a_defect() -> None:
    grid, _, spike = _bead_with_defect_scene()
    want = assert_stream_equals_batch(grid, miem.default_params("stream"))
    assert want.labels[spike] == miem.ABNORMAL
