"""miem.stream.ProfileStream: labels equal miem.detect on the same rows; bad input."""

from __future__ import annotations

import miem
import numpy as np
import pytest
from miem.stream import ProfileStream, StreamRow


def make_scan(h: int, w: int, seed: int) -> np.ndarray:
    """A curved sheet with noise, burr tips, pits, a wedge burr across the profiles (removals
    cascade over several passes), dropouts and a lost profile."""
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[0:h, 0:w]
    g = np.zeros((h, w, 3))
    g[..., 0] = c * 0.25
    g[..., 1] = r * 0.3
    g[..., 2] = (0.4 * np.exp(-((c * 0.25 - 0.125 * w) ** 2) / 50.0) + 0.01 * r * 0.3 +
                 rng.normal(0.0, 0.002, (h, w))).round(3)
    for _ in range(6):
        g[rng.integers(1, h - 1), rng.integers(1, w - 1), 2] += rng.uniform(0.5, 1.5)
    for _ in range(3):
        g[rng.integers(1, h - 1), rng.integers(1, w - 1), 2] -= rng.uniform(0.4, 1.4)
    r0, c0 = rng.integers(1, h - 7), rng.integers(1, w - 2)
    for k, hgt in enumerate([2.4, 1.8, 1.3, 0.9, 0.6, 0.35]):
        g[r0 + k, c0, 2] += hgt
        g[r0 + k, c0 + 1, 2] += 0.9 * hgt
    g[rng.random((h, w)) < 0.01] = np.nan
    g[h // 3] = np.nan
    return g


def stream_all(stream: ProfileStream, grid: np.ndarray) -> np.ndarray:
    out = np.full(grid.shape[:2], 99, dtype=np.uint8)
    expected = 0
    for r in range(grid.shape[0]):
        done = stream.push(grid[r])
        if r < stream.lag:
            assert done is None
        else:
            assert isinstance(done, StreamRow) and done.row == r - stream.lag == expected
            out[done.row] = done.labels
            expected += 1
    for done in stream.flush():
        assert done.row == expected
        out[done.row] = done.labels
        expected += 1
    assert expected == grid.shape[0]
    return out


@pytest.mark.parametrize(
    "params",
    [{}, {"scales": (1, 2), "max_gap": 2}, {"max_iterations": 3}, {"min_directions": 2},
     {"theta0": 100.0}, {"min_step": 0.2, "max_reach": 4}],
)
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_stream_equals_detect(params: dict, dtype) -> None:
    grid = make_scan(80, 60, 3).astype(dtype)
    want = miem.detect(grid, preset="paper", **params).labels
    got = stream_all(ProfileStream(60, preset="paper", dtype=dtype, **params), grid)
    np.testing.assert_array_equal(got, want)
    assert (want == miem.ABNORMAL).sum() > 0


def test_lag_and_properties() -> None:
    s = ProfileStream(10, preset="paper")
    assert (s.lag, s.width, s.dtype, s.rows_pushed, s.finished) == (20, 10, np.float64, 0, False)
    assert ProfileStream(10, scales=(1, 2), max_gap=2, max_iterations=3).lag == 12
    assert "lag=20" in repr(s)
    assert ProfileStream(10).lag == 10 * (2 + 1)  # the default: scales (1, 2), max_gap 1


def test_any_strides_and_dtypes_are_read() -> None:
    grid = make_scan(40, 30, 4)
    want = stream_all(ProfileStream(30), grid)
    fortran = np.asfortranarray(grid.transpose(1, 0, 2)).transpose(1, 0, 2)  # strided rows
    got = stream_all(ProfileStream(30), fortran)
    np.testing.assert_array_equal(got, want)
    ints = np.nan_to_num(grid * 1000).astype(np.int64)  # integers are converted
    ProfileStream(30).push(ints[0])


def test_all_nan_profile_is_a_row_of_dropouts() -> None:
    s = ProfileStream(8, max_iterations=1)
    rows = []
    for r in range(5):
        p = np.zeros((8, 3))
        p[:, 0] = np.arange(8)
        p[:, 1] = r
        done = s.push(np.full((8, 3), np.nan) if r == 0 else p)
        rows += [] if done is None else [done]
    rows += s.flush()
    assert [d.row for d in rows] == list(range(5))
    assert (rows[0].labels == miem.INVALID).all()
    assert (rows[2].labels == miem.NORMAL).all()


def test_bad_input_raises_and_leaves_the_stream_unchanged() -> None:
    s = ProfileStream(16)
    with pytest.raises(ValueError, match="profile: expected shape"):
        s.push(np.zeros((15, 3)))
    with pytest.raises(ValueError, match="profile: expected shape"):
        s.push(np.zeros((16, 2)))
    with pytest.raises(ValueError, match="profile"):
        s.push(np.array(["a"] * 48).reshape(16, 3))
    assert s.rows_pushed == 0
    s.push(np.zeros((16, 3)))
    s.flush()
    assert s.finished
    with pytest.raises(ValueError, match="reset"):
        s.push(np.zeros((16, 3)))
    s.reset()
    assert s.rows_pushed == 0 and not s.finished


@pytest.mark.parametrize(
    "kwargs, match",
    [({"width": 0}, "width"), ({"theta0": 180.0}, "theta0"), ({"scales": ()}, "scales"),
     ({"scales": (0,)}, "scales"), ({"max_gap": -1}, "max_gap"), ({"min_step": -1.0}, "min_step"),
     ({"min_directions": 5}, "min_directions"), ({"max_iterations": 255}, "max_iterations"),
     ({"max_reach": 0}, "max_reach"), ({"dtype": np.int32}, "dtype")],
)
def test_bad_parameters(kwargs: dict, match: str) -> None:
    args = {"width": 10, **kwargs}
    width = args.pop("width")
    with pytest.raises(ValueError, match=match):
        ProfileStream(width, **args)
