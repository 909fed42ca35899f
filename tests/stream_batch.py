"""The stream == batch check shared by the tests: push every profile of a grid through a
ProfileStream, flush it, and compare the stacked rows with batch `miem.detect` on the grid."""

from __future__ import annotations

import miem
import numpy as np
from miem.stream import ProfileStream


def stream_labels(grid: np.ndarray, params: miem.DetectParams) -> np.ndarray:
    """The (H, W) labels of every row, in the order the stream hands them back."""
    stream = ProfileStream(grid.shape[1], params=params)
    rows = [r for prof in grid if (r := stream.push(prof)) is not None] + list(stream.flush())
    assert [r.row for r in rows] == list(range(grid.shape[0]))
    return np.stack([r.labels for r in rows])


def assert_stream_equals_batch(grid: np.ndarray, params: miem.DetectParams):
    """Batch detection of `grid` (returned), after asserting the stream's labels equal it."""
    want = miem.detect(grid, params=params)
    np.testing.assert_array_equal(stream_labels(grid, params), want.labels)
    return want
