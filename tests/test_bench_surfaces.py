"""bench/bench_speed.py's surface sweep explains the edge test's cost on curved surfaces with
quadric_fit: how far P misses the planes of its clean one-sided sub-windows on a noise-free
quadratic surface, in their rms. Checked against the least-squares line worked by hand."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

from bench_speed import quadric_fit  # noqa: E402


def test_quadric_fit_is_the_hand_worked_least_squares_line() -> None:
    # z = x^2 over x = 1..7 (a quadrant's or a half's columns; y plays no part): mean x 4, var x
    # 4, mean x^2 20, mean x^3 112, mean x^4 668; slope cov / var = (112 - 80) / 4 = 8, plane
    # at P 20 - 8 * 4 = -12, residual variance (668 - 400) - 32^2 / 4 = 12: |h| / rms = sqrt(12)
    assert quadric_fit(7, 1.0, 0.0) == pytest.approx(math.sqrt(12.0), rel=1e-9)
    # x^2 + y^2 on a quadrant (the clean sides: a half's rms is larger by the full range of its
    # other coordinate): both terms add, |h| = 24, residual variance 24: sqrt(24)
    assert quadric_fit(7, 1.0, 1.0) == pytest.approx(math.sqrt(24.0), rel=1e-9)
    # x^2 - y^2: the terms cancel at P, which lies on every quadrant's plane
    assert quadric_fit(7, 1.0, -1.0) == pytest.approx(0.0, abs=1e-9)
    # the radius does not matter
    assert quadric_fit(7, 0.01, 0.01) == pytest.approx(math.sqrt(24.0), rel=1e-9)
