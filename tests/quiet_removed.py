"""The cells the reference hands its edge test's quiet rule as removed by the height test
(SPEC "Edge test" step 1: the last height pass's removals when max_iterations ended the passes,
none when they ended by themselves), seen by wrapping ``reference._quiet_cells`` for one
``reference.detect``. Shared by test_stream and test_edge_quiet."""

from __future__ import annotations

import numpy as np
from miem import reference as ref


def detect_seeing_removed(grid: np.ndarray, **kw: object) -> tuple[ref.RefResult, np.ndarray]:
    """``ref.detect(grid, **kw)`` and the ``removed`` cells it handed ``_quiet_cells`` (called
    exactly once)."""
    seen = []
    quiet_cells = ref._quiet_cells

    def spy(*args: object) -> np.ndarray:
        seen.append(np.array(args[5], dtype=bool))
        return quiet_cells(*args)

    ref._quiet_cells = spy
    try:
        res = ref.detect(grid, **kw)
    finally:
        ref._quiet_cells = quiet_cells
    assert len(seen) == 1
    return res, seen[0]
