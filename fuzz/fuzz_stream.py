"""Fuzz miem.ProfileStream's input: width, parameters and profiles (NaN, inf, huge, tiny and
repeated values) from the fuzzer's bytes. Every push must return None or a StreamRow of labels
0..3, rows must come out numbered 0, 1, 2, ... and, when the rows hold 3 finite points, equal
miem.detect's labels on the same rows; a profile beyond the coordinate range (SPEC "Numbers") is
refused by both (see fuzz/README.md)."""

import sys

import atheris

with atheris.instrument_imports(include=["miem"]):
    import miem
    import numpy as np

_SPECIAL = [np.nan, np.inf, -np.inf, 0.0, -0.0, 1e300, -1e300, 1e-310, 5e-324, 1.0, 0.5]


def test_one_input(data: bytes) -> None:
    fdp = atheris.FuzzedDataProvider(data)
    width = fdp.ConsumeIntInRange(1, 24)
    rows = fdp.ConsumeIntInRange(1, 24)
    params = {
        "theta0": fdp.ConsumeFloatInRange(1.0, 179.0),
        "scales": sorted({fdp.ConsumeIntInRange(1, 3) for _ in range(fdp.ConsumeIntInRange(1, 2))}),
        "max_gap": fdp.ConsumeIntInRange(0, 2),
        "min_directions": fdp.PickValueInList([None, 1, 2, 3, 4]),
        "max_iterations": fdp.ConsumeIntInRange(1, 4),
    }
    if fdp.ConsumeBool():
        params["min_step"] = fdp.ConsumeFloatInRange(0.0, 2.0)
        params["max_reach"] = fdp.ConsumeIntInRange(1, 4)
    dtype = fdp.PickValueInList([np.float64, np.float32])
    # a plane with fuzzed cells: raw doubles or special values
    yy, xx = np.mgrid[0:rows, 0:width].astype(np.float64)
    grid = np.dstack([xx, yy, np.zeros_like(xx)])
    for _ in range(fdp.ConsumeIntInRange(0, 3 * rows)):
        r, c, k = (fdp.ConsumeIntInRange(0, rows - 1), fdp.ConsumeIntInRange(0, width - 1),
                   fdp.ConsumeIntInRange(0, 2))
        grid[r, c, k] = (fdp.PickValueInList(_SPECIAL) if fdp.ConsumeBool()
                         else fdp.ConsumeRegularFloat())
    with np.errstate(over="ignore"):
        grid = grid.astype(dtype)  # float32: huge values become inf (dropouts)
    stream = miem.ProfileStream(width, dtype=dtype, **params)
    out = {}
    for profile in grid:
        try:
            done = stream.push(profile)
        except ValueError as exc:  # coordinates beyond the SPEC range: refused, not mislabelled
            assert "rescale" in str(exc), exc
            try:
                miem.detect(grid, stream.params)
            except ValueError as batch:
                assert "rescale" in str(batch), batch
                return
            raise AssertionError("the stream refused a profile that detect accepts") from exc
        if done is not None:
            out[done.row] = done.labels
    out.update({r.row: r.labels for r in stream.flush()})
    assert sorted(out) == list(range(rows)), sorted(out)
    labels = np.stack([out[r] for r in range(rows)])
    assert labels.shape == (rows, width) and labels.max() <= 3
    if np.isfinite(grid).all(axis=2).sum() >= 3:
        try:
            batch = miem.detect(grid, stream.params).labels  # the parameters the stream used
        except ValueError as exc:  # all coordinates below 1e-18: only the batch can tell
            assert "rescale" in str(exc), exc
            return
        np.testing.assert_array_equal(labels, batch)


if __name__ == "__main__":
    atheris.Setup(sys.argv, test_one_input)
    atheris.Fuzz()
