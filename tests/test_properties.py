"""Property-based tests (hypothesis): the C++ core equals the NumPy reference on generated grids
and clouds, the stream equals the batch detector, labels are invariant under the symmetries of
the method, and no call modifies its input.

Scenes are drawn from parameters (shape, spacing, tilt, a crease, spikes, 2x2 clusters, dust, NaN
patterns: random dropouts, missing rows and columns, a cut edge) plus a seed for the noise, so a
failing example shrinks to a small readable scene. The example budget is fixed and the run is
derandomized, so CI runs the same few examples every time in seconds; set
``MIEM_HYPOTHESIS_EXAMPLES=2000`` (and optionally ``MIEM_HYPOTHESIS_SEED``) for a longer search.
"""

from __future__ import annotations

import os
import warnings

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

import miem  # noqa: E402
from miem import reference as ref  # noqa: E402

_EXAMPLES = int(os.environ.get("MIEM_HYPOTHESIS_EXAMPLES", "25"))
_SEED = os.environ.get("MIEM_HYPOTHESIS_SEED")
CI = settings(
    max_examples=_EXAMPLES,
    derandomize=_SEED is None,
    database=None,
    deadline=None,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


def _seeded(test):
    return hypothesis.seed(int(_SEED))(test) if _SEED is not None else test


# ---------------------------------------------------------------------------------------------
# scenes


@st.composite
def grids(draw, max_side=22):
    h = draw(st.integers(3, max_side))
    w = draw(st.integers(3, max_side))
    dx = draw(st.sampled_from([0.25, 0.5, 1.0]))
    dy = draw(st.sampled_from([0.25, 0.4, 1.0]))
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = xx * dx, yy * dy
    z = draw(st.floats(-0.3, 0.3)) * x + draw(st.floats(-0.3, 0.3)) * y
    if draw(st.booleans()):  # a designed crease across the profiles
        c0 = draw(st.integers(1, w - 1))
        z = z + np.where(xx > c0, (xx - c0) * dx * np.tan(np.radians(draw(st.floats(5, 40)))), 0)
    z = z + rng.normal(0.0, draw(st.sampled_from([0.0, 0.002, 0.01])), z.shape)
    q = draw(st.sampled_from([None, None, 0.001, 0.01]))  # z stored in steps (z_resolution)
    if q is not None:
        z = np.round(z / q) * q
    g = np.dstack([x, y, z])
    for _ in range(draw(st.integers(0, 4))):  # spikes and pits
        g[rng.integers(0, h), rng.integers(0, w), 2] += rng.choice([-1, 1]) * rng.uniform(0.3, 3)
    if draw(st.booleans()) and h > 2 and w > 2:  # a 2x2 cluster
        r, c = rng.integers(0, h - 1), rng.integers(0, w - 1)
        g[r:r + 2, c:c + 2, 2] += rng.uniform(0.5, 2.0)
    if draw(st.booleans()):  # dust far above
        g[rng.integers(0, h), rng.integers(0, w), 2] += 20.0
    nan = draw(st.sampled_from(["none", "random", "rows", "cols", "cut", "block"]))
    if nan == "random":
        g[rng.random((h, w)) < draw(st.sampled_from([0.05, 0.2, 0.5]))] = np.nan
    elif nan == "rows":
        g[rng.integers(0, h, max(1, h // 4))] = np.nan
    elif nan == "cols":
        g[:, rng.integers(0, w, max(1, w // 4))] = np.nan
    elif nan == "cut":  # a cut edge: everything right of a slanted line is missing
        g[xx > (w * 0.6 + 0.3 * yy)] = np.nan
    elif nan == "block":
        r, c = rng.integers(0, h), rng.integers(0, w)
        g[r:r + 4, c:c + 4] = np.nan
    g = g + np.array([draw(st.sampled_from([0.0, 1e3, -5e4])), 0.0, 0.0])
    if np.count_nonzero(np.isfinite(g).all(axis=2)) < 3:
        g[0, :3] = [[0, 0, 0], [dx, 0, 0], [0, dy, 0]]
    return g


@st.composite
def grid_params(draw, stream=False):
    p = {
        "theta0": draw(st.floats(40.0, 170.0) if stream
                       else st.one_of(st.floats(40.0, 170.0), st.just("auto"))),
        "scales": tuple(sorted(draw(st.sets(st.integers(1, 3), min_size=1, max_size=2)))),
        "max_gap": draw(st.integers(0, 2)),
        "min_step": draw(st.one_of(st.none(), st.sampled_from([0.2, 0.45, 1.1]))),
        "min_directions": draw(st.one_of(st.none(), st.integers(1, 4))),
        "max_iterations": draw(st.integers(1, 4)),
    }
    if p["min_step"] is not None:
        p["max_reach"] = draw(st.integers(1, 4))
    if not stream:
        p["window"] = draw(st.sampled_from([3, 5, 7, 11]))
        p["height_tolerance"] = draw(st.sampled_from([None, None, "3rms", "4.5rms", 0.05]))
        p["edge_extent"] = draw(st.integers(0, 12))
    return p


@st.composite
def clouds(draw):
    n = draw(st.integers(40, 400))
    rng = np.random.default_rng(draw(st.integers(0, 2**31 - 1)))
    side = draw(st.sampled_from([4.0, 10.0]))
    xy = rng.uniform(0.0, side, size=(n, 2))
    z = draw(st.floats(-0.3, 0.3)) * xy[:, 1]
    if draw(st.booleans()):
        z = z + np.where(xy[:, 0] > side / 2, (xy[:, 0] - side / 2) * np.tan(np.radians(25)), 0)
    pts = np.column_stack([xy, z + rng.normal(0.0, draw(st.sampled_from([0.0, 0.01])), n)])
    k = draw(st.integers(0, 5))
    if k:
        pts[rng.choice(n, k, replace=False), 2] += rng.choice([-1, 1], k) * rng.uniform(0.5, 2, k)
    if draw(st.booleans()):
        pts = np.vstack([pts, [[side / 2, side / 2, 8.0]]])  # dust
    pts[rng.random(pts.shape[0]) < draw(st.sampled_from([0.0, 0.05]))] = np.nan
    return pts


@st.composite
def cloud_params(draw):
    return {
        "theta0": draw(st.floats(50.0, 150.0)),
        "scales": tuple(sorted(draw(st.sets(st.integers(1, 2), min_size=1, max_size=2)))),
        "K": draw(st.integers(2, 8)),
        "min_directions": draw(st.one_of(st.none(), st.integers(1, 2))),
        "max_iterations": draw(st.integers(1, 3)),
        "radius": draw(st.one_of(st.none(), st.sampled_from([0.8, 1.5]))),
    }


def _scale_lengths(p: dict, s: float) -> dict:
    out = dict(p)
    for key in ("min_step", "radius", "link"):
        if out.get(key) is not None:
            out[key] = out[key] * s
    if isinstance(out.get("height_tolerance"), float):
        out["height_tolerance"] *= s
    return out


# ---------------------------------------------------------------------------------------------
# core == reference


def _assert_like_reference(core, oracle):
    np.testing.assert_array_equal(core.labels, oracle.labels)
    np.testing.assert_array_equal(core.flags, oracle.flags)
    # Compared as cosines: acos is ill-conditioned near 180 degrees, where one rounding of the
    # cosine moves the angle by 1e-6 degrees.
    np.testing.assert_array_equal(np.isnan(core.angle), np.isnan(oracle.angle))
    np.testing.assert_allclose(np.cos(np.radians(core.angle)), np.cos(np.radians(oracle.angle)),
                               rtol=0, atol=1e-12, equal_nan=True)
    scale = max(1.0, float(np.nanmax(np.abs(np.nan_to_num(core.height, nan=0.0)))))
    np.testing.assert_allclose(core.height, oracle.height, rtol=0, atol=1e-7 * scale,
                               equal_nan=True)
    assert core.iterations == oracle.iterations
    _assert_defects_alike(core.defects, oracle.defects, 1e-7 * scale, oracle.height.ravel())


def _assert_defects_alike(core, oracle, tol, heights):
    """Same groups with the same peaks; the peak (the member height of largest magnitude), the
    rank (by |peak|) and the kind (by the sign of the peak) are compared where they are decided,
    not by rounding of a tie: members whose |height| agree within `tol` with the largest may
    each be the peak (a +h and a -h of one group make its kind a tie), two defects whose |peak|
    agree within `tol` may come in either order, a zero-height group may be either."""
    def key(d):
        return tuple(d.indices.tolist())

    a, b = {key(d): d for d in core}, {key(d): d for d in oracle}
    assert len(a) == len(core) and a.keys() == b.keys()
    for k, d in a.items():
        if np.isnan(b[k].peak_height):
            assert np.isnan(d.peak_height), k
            continue
        h = heights[list(k)]
        h = h[np.isfinite(h)]
        tied = h[np.abs(h) >= np.abs(b[k].peak_height) - tol]  # the oracle's peak among them
        assert np.min(np.abs(tied - d.peak_height)) <= tol, (k, d.peak_height, tied)
        if abs(b[k].peak_height) > tol and len(set(np.sign(tied))) == 1:
            assert d.kind == b[k].kind, k
        else:  # pit or protrusion by the tie's rounding, but 'isolated' is decided
            assert (d.kind == "isolated") == (b[k].kind == "isolated"), k
    peaks = [abs(b[key(d)].peak_height) for d in core]  # the oracle's |peak| in the core's order
    peaks = [-1.0 if np.isnan(p) else p for p in peaks]
    assert all(x >= y - tol for x, y in zip(peaks, peaks[1:])), peaks


@CI
@_seeded
@given(grids(), grid_params())
def test_core_equals_reference_on_grids(grid, params):
    before = grid.copy()
    core = miem.detect(grid, **params)
    oracle = ref.detect(grid, **params)
    np.testing.assert_array_equal(grid, before)
    assert core.params["theta0"] == pytest.approx(oracle.params["theta0"], abs=1e-9)
    _assert_like_reference(core, oracle)


@CI
@_seeded
@given(clouds(), cloud_params())
def test_core_equals_reference_on_clouds(points, params):
    before = points.copy()
    core = miem.detect(points, **params)
    oracle = ref.detect_points(points, **params)
    np.testing.assert_array_equal(points, before)
    np.testing.assert_array_equal(core.degenerate, oracle.degenerate)
    _assert_like_reference(core, oracle)


# ---------------------------------------------------------------------------------------------
# stream == batch


@CI
@_seeded
@given(grids(), grid_params(stream=True), st.sampled_from([np.float64, np.float32]))
def test_stream_equals_batch(grid, params, dtype):
    grid = grid.astype(dtype)
    stream = miem.ProfileStream(grid.shape[1], dtype=dtype, **params)
    # batch detection with the stream's parameters (the default preset, height test included)
    batch = miem.detect(grid, params=stream.params).labels
    rows = {}
    for profile in grid:
        done = stream.push(profile)
        if done is not None:
            rows[done.row] = done.labels
    rows.update({r.row: r.labels for r in stream.flush()})
    assert sorted(rows) == list(range(grid.shape[0]))
    np.testing.assert_array_equal(np.stack([rows[r] for r in sorted(rows)]), batch)


# ---------------------------------------------------------------------------------------------
# invariances


def _swap_bits(flags, a, b):
    fa, fb = (flags >> a) & 1, (flags >> b) & 1
    out = flags & ~np.uint8((1 << a) | (1 << b))
    return (out | (fa << b) | (fb << a)).astype(np.uint8)


@CI
@_seeded
@given(grids(), grid_params(), st.sampled_from(["rows", "cols", "transpose"]))
def test_labels_invariant_under_the_grid_symmetries(grid, params, how):
    """Reversing the profile order or the points along each profile, or swapping the roles of
    rows and columns, permutes the cells and the direction bits, never the labels (the angle
    test is symmetric in a point's two neighbours; the height and edge tests are left out: their
    planes are fitted from sums in an order-dependent order, equal only to rounding)."""
    params = dict(params, height_tolerance=None, edge_tolerance=None)
    res = miem.detect(grid, **params)
    if how == "rows":  # (1, 1) <-> (1, -1)
        moved, back, bits = grid[::-1], lambda a: a[::-1], (2, 3)
    elif how == "cols":
        moved, back, bits = grid[:, ::-1], lambda a: a[:, ::-1], (2, 3)
    else:  # along <-> across; the diagonals keep their axes
        moved, back, bits = grid.transpose(1, 0, 2), lambda a: a.T, (0, 1)
    other = miem.detect(np.ascontiguousarray(moved), **params)
    np.testing.assert_array_equal(back(other.labels), res.labels)
    np.testing.assert_array_equal(_swap_bits(back(other.flags), *bits), res.flags)


@CI
@_seeded
@given(grids(), grid_params(), st.sampled_from([2.0**-30, 0.125, 8.0, 2.0**40]))
def test_power_of_two_scaling_scales_heights_exactly(grid, params, s):
    """Multiplying coordinates and lengths by a power of two is exact in floating point, so the
    labels are identical and every height is multiplied by exactly that factor. Not where a
    product underflows: coordinates as small as 1e-308 (a slope hypothesis drew) have
    subnormal squares and scaled heights, which round."""
    mag = np.abs(grid[np.isfinite(grid)])
    hypothesis.assume(np.all((mag == 0.0) | (mag >= 1e-100)))
    res = miem.detect(grid, **params)
    other = miem.detect(grid * s, **_scale_lengths(params, s))
    np.testing.assert_array_equal(other.labels, res.labels)
    np.testing.assert_array_equal(other.flags, res.flags)
    np.testing.assert_array_equal(other.height, res.height * s)


@CI
@_seeded
@given(grids(), grid_params())
def test_float32_input_equals_its_float64_values(grid, params):
    """float32 coordinates are widened per value: the result is that of the same values in
    float64."""
    g32 = grid.astype(np.float32)
    a = miem.detect(g32, **params)
    b = miem.detect(g32.astype(np.float64), **params)
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_array_equal(a.height, b.height)


@CI
@_seeded
@given(clouds(), cloud_params(), st.integers(0, 2**31 - 1))
def test_cloud_labels_follow_a_permutation_of_the_points(points, params, seed):
    perm = np.random.default_rng(seed).permutation(points.shape[0])
    a = miem.detect(points, **params)
    b = miem.detect(points[perm], **params)
    np.testing.assert_array_equal(b.labels, a.labels[perm])


# ---------------------------------------------------------------------------------------------
# inputs are never modified (read-only arrays are accepted, so nothing writes to them)


@CI
@_seeded
@given(grids(max_side=12), st.sampled_from([np.float64, np.float32, ">f8"]))
def test_no_function_writes_to_its_input(grid, dtype):
    g = grid.astype(dtype)
    g.flags.writeable = False
    pts = g.reshape(-1, 3)
    line = g[0]
    cloud = np.ascontiguousarray(pts[np.isfinite(pts).all(axis=1)])
    cloud.flags.writeable = False
    before = [a.copy() for a in (g, cloud)]
    miem.detect(g)
    miem.detect(g, preset="recommended", heights="abnormal")
    if cloud.shape[0] >= 3:
        with warnings.catch_warnings():  # (a flattened grid's advice is not what this checks;
            warnings.simplefilter("ignore", UserWarning)  # which examples give one varies)
            miem.detect(cloud)
        miem.estimate_normals(cloud, 1.0)
        miem.point_spacing(cloud)
        miem.NeighborGrid(cloud, 1.0).radius_query(0, 1.0)
    miem.scan_line_angles(line)
    miem.scan_line_heights(line, 2)
    try:
        miem.fit_plane(pts).distance(pts)
    except ValueError:
        pass  # collinear finite points: no plane
    s = miem.ProfileStream(g.shape[1])
    for row in g:
        s.push(row)
    np.testing.assert_array_equal(g, before[0])
    np.testing.assert_array_equal(cloud, before[1])


@st.composite
def profiler_scans(draw):
    """An organized profiler scan: `h` profiles at uneven positions along y (steps of 0.06 to
    2 mm, above half the 0.05 mm point spacing), points 0.05 mm apart along x from an offset,
    noisy z, NaN holes (one profile complete: with holes everywhere neither the grid's width
    nor the point spacing can be told; a point in every profile), in float64 or float32."""
    h, w = draw(st.integers(2, 12)), draw(st.integers(3, 20))
    seed = draw(st.integers(0, 2**31 - 1))
    x0 = draw(st.sampled_from([0.0, -3.7, 125.0]))
    dtype = draw(st.sampled_from([np.float64, np.float32]))
    rng = np.random.default_rng(seed)
    ys = x0 + np.cumsum(rng.uniform(0.06, 2.0, h))
    c = np.mgrid[0:h, 0:w][1]
    g = np.stack([x0 + c * 0.05, np.broadcast_to(ys[:, None], (h, w)),
                  rng.normal(0, 0.02, (h, w))], axis=-1)
    holes = rng.random((h, w)) < draw(st.sampled_from([0.0, 0.1, 0.4]))
    holes[rng.integers(h)] = False  # one whole profile: the width and the step are known
    holes[np.arange(h), rng.integers(w, size=h)] = False  # (a profile without points is none)
    g[holes] = np.nan
    return g.astype(dtype)


@CI
@_seeded
@given(profiler_scans(), st.integers(0, 2**31 - 1))
def test_shuffled_profiler_scan_rebuilds_its_grid(grid, seed):
    # grid_from_scanlines: in file order and, shuffled, by line position, the very grid, each
    # point at its cell; the caller's points unchanged
    import miem.io as mio

    flat = grid.reshape(-1, 3)
    cells = np.flatnonzero(np.isfinite(flat).all(axis=1))
    pts = flat[cells]
    np.testing.assert_array_equal(mio.grid_from_scanlines(pts), grid)
    perm = np.random.default_rng(seed).permutation(len(pts))
    shuffled = pts[perm]
    before = shuffled.copy()
    out, index = mio.grid_from_scanlines(shuffled, order="line", return_index=True)
    np.testing.assert_array_equal(out, grid)
    np.testing.assert_array_equal(index, cells[perm])
    np.testing.assert_array_equal(shuffled, before)
