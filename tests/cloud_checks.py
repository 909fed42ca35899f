"""Core == reference on an unorganized cloud, as the cloud tests compare them: labels, flags,
heights, passes, the edge radius and the defects' members."""

from __future__ import annotations

import numpy as np
import pytest

import miem
from miem import reference as ref


def assert_same_cloud_result(core: miem.DetectResult, oracle: ref.RefPointsResult) -> None:
    np.testing.assert_array_equal(core.labels, oracle.labels)
    np.testing.assert_array_equal(core.flags, oracle.flags)
    np.testing.assert_allclose(core.height, oracle.height, atol=1e-9, equal_nan=True)
    assert core.iterations == oracle.iterations
    assert core.params["edge_radius"] == pytest.approx(oracle.params["edge_radius"], rel=1e-12)
    assert [d.indices.tolist() for d in core.defects] == [
        d.indices.tolist() for d in oracle.defects]


def assert_core_is_reference_everywhere(pts: np.ndarray) -> None:
    """Core == reference with the defaults on ``pts`` and on its float32 copy 1e3 mm away, and
    the same labels on 1 and 2 threads."""
    assert_same_cloud_result(miem.detect_points(pts), ref.detect_points(pts))
    p32 = (pts + 1e3).astype(np.float32)
    assert_same_cloud_result(miem.detect_points(p32), ref.detect_points(p32))
    base = miem.detect_points(pts).labels
    for nt in (1, 2):
        np.testing.assert_array_equal(miem.detect_points(pts, num_threads=nt).labels, base)
