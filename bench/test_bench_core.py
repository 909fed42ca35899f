"""pytest-benchmark: the C++ core against the NumPy reference (issue 2).

Run: ``python -m pytest bench/test_bench_core.py --benchmark-only``. Parity is checked before
timing. Ratios for bench/RESULTS.md come from ``python bench/run_results.py``.
"""

from __future__ import annotations

import numpy as np
import pytest

import miem
from miem import reference as ref

from common import plane_points, scan_grid

FIT_N = 10_000_000
DETECT_SIDES = [256, 1024, 2048]
REF_MAX_SIDE = 256  # the reference takes ~2 s at 256 x 256


@pytest.fixture(scope="module")
def points() -> np.ndarray:
    return plane_points(FIT_N)


@pytest.mark.parametrize("impl", ["core", "reference"])
def test_fit_plane(benchmark, points, impl) -> None:
    fn = miem.fit_plane if impl == "core" else ref.fit_plane
    a, b = miem.fit_plane(points), ref.fit_plane(points)
    np.testing.assert_allclose(a.normal, b.normal, atol=1e-12)
    benchmark.extra_info["points"] = FIT_N
    plane = benchmark.pedantic(fn, args=(points,), rounds=3, iterations=1)
    assert plane.n_points == FIT_N


CASES = [
    (side, impl)
    for side in DETECT_SIDES
    for impl in ("core-1thread", "core-2threads", "core-abnormal-heights", "reference")
    if impl != "reference" or side <= REF_MAX_SIDE  # the reference takes minutes beyond
]


@pytest.mark.parametrize("side, impl", CASES)
def test_detect(benchmark, side, impl) -> None:
    grid = scan_grid(side, side)
    if side <= REF_MAX_SIDE:  # parity before timing
        np.testing.assert_array_equal(miem.detect(grid).labels, ref.detect(grid).labels)
    kwargs = {
        "core-1thread": {"num_threads": 1},
        "core-2threads": {"num_threads": 2},
        "core-abnormal-heights": {"num_threads": 1, "heights": "abnormal"},
        "reference": {},
    }[impl]
    fn = ref.detect if impl == "reference" else miem.detect
    benchmark.extra_info["points"] = side * side
    res = benchmark.pedantic(fn, args=(grid,), kwargs=kwargs, rounds=3, iterations=1)
    assert res.labels.shape == (side, side)
