"""Public functions survive what the bad-input sweep threw at them (issue 16): absurd thread
counts (item 1), big-endian and misaligned arrays (items 5, 8) and a stream pushed from two
threads (item 9). Expected values come from the same call on a clean input (native, aligned,
one thread), which other tests check against the NumPy reference."""

from __future__ import annotations

import os
import threading

import numpy as np
import pytest

import miem
from miem import _core

PEAK_MB = 200


def _grid(h=32, w=32, seed=0):
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w] * 0.5
    g = np.dstack([x, y, 0.01 * rng.standard_normal((h, w))])
    g[h // 3, w // 3, 2] = 3.0
    g[h // 2, w // 4] = np.nan
    return g


def _misaligned(a):
    """A C-contiguous copy of `a` whose data pointer is one byte off its item alignment."""
    buf = np.zeros(a.nbytes + a.itemsize, np.uint8)
    out = np.frombuffer(buf[1:1 + a.nbytes].data, dtype=a.dtype).reshape(a.shape)
    out[...] = a
    assert not out.flags.aligned and out.flags.c_contiguous
    return out


# ---------------------------------------------------------------------------------------------
# item 1: thread counts


def test_max_threads_is_a_small_multiple_of_the_processors():
    procs = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    m = _core.max_threads()
    if _core.openmp:
        assert m == min(256, 4 * procs)
    else:
        assert m == 1


def test_huge_thread_counts_are_clamped_not_fatal(isolated, tmp_path):
    """Each call of the sweep that killed the interpreter (libgomp out of memory on 2**30
    threads) or started 10,000 OS threads, on >= 65,536 points, in one capped child."""
    np.save(tmp_path / "grid.npy", _grid(256, 256))
    code = isolated.CASES + f"""
import numpy as np, miem
g = np.load({str(tmp_path / "grid.npy")!r})
pts = g.reshape(-1, 3)
cloud = pts[np.isfinite(pts).all(axis=1)]
ref = {{
    "detect": miem.detect(g, num_threads=1).labels,
    "cloud": miem.detect(cloud, num_threads=1).labels,
    "plane": miem.fit_plane(pts, num_threads=1).normal,
    "normals": miem.estimate_normals(cloud, 1.0, num_threads=1).normals,
}}
def same(key, value):
    np.testing.assert_array_equal(value, ref[key])
cases = {{}}
for n in (2**30, 10000, 2**31 - 1, 2**40):
    cases[f"detect-{{n}}"] = lambda n=n: same("detect", miem.detect(g, num_threads=n).labels)
    cases[f"cloud-{{n}}"] = lambda n=n: same("cloud", miem.detect(cloud, num_threads=n).labels)
    cases[f"plane-{{n}}"] = lambda n=n: same("plane", miem.fit_plane(pts, num_threads=n).normal)
    cases[f"grid-{{n}}"] = lambda n=n: miem.NeighborGrid(cloud, 0.5, num_threads=n)
    cases[f"normals-{{n}}"] = lambda n=n: same(
        "normals", miem.estimate_normals(cloud, 1.0, num_threads=n).normals)
    cases[f"spacing-{{n}}"] = lambda n=n: miem.point_spacing(cloud, num_threads=n)
result = run_cases(cases)
"""
    rep = isolated(code, timeout=120)
    assert rep["ok"], rep
    for name, rec in rep["result"].items():
        assert rec["ok"], (name, rec)
        assert rec["seconds"] < 10, (name, rec)
    assert rep["peak_mb"] < PEAK_MB


def test_cli_huge_thread_count(isolated, tmp_path):
    np.save(tmp_path / "grid.npy", _grid(256, 256))
    code = f"""
import miem.cli
rc = miem.cli.main(["detect", {str(tmp_path / "grid.npy")!r}, "--threads", "1073741824",
                    "-q", "--out-dir", {str(tmp_path / "out")!r}])
result = rc
"""
    rep = isolated(code, timeout=120)
    assert rep["ok"] and rep["result"] == 0, rep
    assert (tmp_path / "out" / "grid.labels.npy").exists()
    assert rep["peak_mb"] < PEAK_MB


def test_bad_thread_counts_still_raise():
    g = _grid()
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(ValueError, match="num_threads"):
            miem.detect(g, num_threads=bad)


# ---------------------------------------------------------------------------------------------
# items 5 and 8: byte order and alignment, one conversion in the Python layer


def _entry_points():
    g = _grid()
    pts = g.reshape(-1, 3)
    cloud = pts[np.isfinite(pts).all(axis=1)]
    return {
        "detect": (g, lambda a: miem.detect(a).labels),
        "detect-cloud": (cloud, lambda a: miem.detect_points(a).labels),  # raster order: no warning
        "fit_plane": (pts, lambda a: miem.fit_plane(a).normal),
        "fit_plane-lstsq": (pts, lambda a: miem.fit_plane(a, "lstsq").normal),
        "scan_line_angles": (g[5], lambda a: miem.scan_line_angles(a)),
        "scan_line_heights": (g[5], lambda a: miem.scan_line_heights(a)),
        "NeighborGrid": (cloud, lambda a: miem.NeighborGrid(a, 0.5).radius_query(7, 1.0)),
        "estimate_normals": (cloud, lambda a: miem.estimate_normals(a, 1.0).normals),
        "point_spacing": (cloud, lambda a: miem.point_spacing(a)),
        "distance": (pts, lambda a: miem.fit_plane(pts).distance(a)),
    }


@pytest.mark.parametrize("name", sorted(_entry_points()))
@pytest.mark.parametrize("dtype", ["f8", "f4"])
def test_big_endian_input_gives_the_native_result(name, dtype):
    arr, fn = _entry_points()[name]
    native = arr.astype("=" + dtype)
    swapped = arr.astype(">" + dtype)
    before = swapped.copy()
    np.testing.assert_array_equal(fn(swapped), fn(native))
    np.testing.assert_array_equal(swapped, before)  # input never modified


@pytest.mark.parametrize("name", sorted(_entry_points()))
def test_misaligned_input_gives_the_aligned_result(name):
    arr, fn = _entry_points()[name]
    mis = _misaligned(arr)
    np.testing.assert_array_equal(fn(mis), fn(np.ascontiguousarray(arr)))


def test_the_core_refuses_misaligned_data():
    """Defence in depth: a misaligned buffer that reaches the binding is rejected, never read."""
    mis = _misaligned(_grid())
    with pytest.raises(ValueError, match="aligned"):
        _core.fit_plane(mis.reshape(-1, 3), "eigen", 1)


def test_stream_takes_big_endian_and_misaligned_profiles():
    g = _grid(40, 24)
    ref = miem.ProfileStream(24)
    be = miem.ProfileStream(24)
    mis = miem.ProfileStream(24)
    for row in g:
        a, b, c = ref.push(row), be.push(row.astype(">f8")), mis.push(_misaligned(row))
        assert (a is None) == (b is None) == (c is None)
        if a is not None:
            np.testing.assert_array_equal(a.labels, b.labels)
            np.testing.assert_array_equal(a.labels, c.labels)


# ---------------------------------------------------------------------------------------------
# item 9: one stream, two threads


def test_stream_from_two_threads_is_refused_never_corrupted():
    width = 200_000  # long enough pushes (GIL released) that two threads overlap
    stream = miem.ProfileStream(width, max_iterations=1)
    row = np.zeros((width, 3))
    row[:, 0] = np.arange(width)
    ok = [0, 0]
    refused = [0, 0]
    stop = threading.Event()

    def worker(k):
        while not stop.is_set():
            try:
                stream.push(row)
                ok[k] += 1
            except RuntimeError as exc:
                assert "two threads" in str(exc)
                refused[k] += 1

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(2)]
    for t in threads:
        t.start()
    deadline = threading.Event()
    for _ in range(100):  # up to 5 s, until both threads have been refused at least once
        if deadline.wait(0.05) or (sum(refused) and sum(ok) > 10):
            break
    stop.set()
    for t in threads:
        t.join()
    assert sum(refused) > 0, "no overlap in 5 s"
    # a refused push leaves the stream unchanged: every accepted row was counted once, and the
    # rows come out numbered 0, 1, 2, ... with none lost or repeated
    assert stream.rows_pushed == sum(ok)
    rows = [r.row for r in stream.flush()]
    assert rows == list(range(sum(ok) - len(rows), sum(ok)))


# ---------------------------------------------------------------------------------------------
# item 6: scratch sized by the grid, not by the window


def test_huge_window_on_a_small_grid_costs_the_grid(isolated):
    code = isolated.CASES + """
import numpy as np, miem
y, x = np.mgrid[0:20, 0:20] * 0.5
g = np.dstack([x, y, np.zeros_like(x)]); g[7, 9, 2] = 2.0
ref = miem.detect(g, window=41)  # already covers the whole grid
def same(w):
    r = miem.detect(g, window=w)
    np.testing.assert_array_equal(r.labels, ref.labels)
    np.testing.assert_array_equal(r.height, ref.height)
result = run_cases({str(w): (lambda w=w: same(w)) for w in (6001, 2**30 - 1)})
"""
    rep = isolated(code, timeout=60)
    assert rep["ok"], rep
    for w, rec in rep["result"].items():
        assert rec["ok"] and rec["seconds"] < 5, (w, rec)
    assert rep["peak_mb"] < PEAK_MB


# ---------------------------------------------------------------------------------------------
# item 10: overflow and non-finite results are reported


@pytest.mark.parametrize("scale", [1e154, 1e300, 1e-310, 1e-30, 1e19])
def test_coordinates_beyond_the_range_are_refused_by_core_and_reference(scale):
    from miem import reference as ref

    g = _grid() * scale
    pts = g.reshape(-1, 3)
    for call in (lambda: miem.detect(g), lambda: miem.fit_plane(pts, "lstsq"),
                 lambda: miem.detect(pts[np.isfinite(pts).all(axis=1)]),
                 lambda: miem.scan_line_angles(g[3]), lambda: ref.detect(g),
                 lambda: ref.fit_plane(pts, "lstsq")):
        with pytest.raises(ValueError, match="rescale"):
            call()


def test_the_range_edges_still_compute_like_unit_scale():
    """Inside the range the answer is the unit-scale answer (power-of-two factors are exact)."""
    g = _grid()
    base = miem.detect(g)
    for s in (2.0**54, 2.0**-50):  # grid coordinates up to 15.5: 2**54 x 15.5 < 1e18
        res = miem.detect(g * s)
        np.testing.assert_array_equal(res.labels, base.labels)
        np.testing.assert_array_equal(res.height, base.height * s)
        plane = miem.fit_plane(g.reshape(-1, 3) * s, "lstsq")
        np.testing.assert_allclose(plane.normal, miem.fit_plane(g.reshape(-1, 3), "lstsq").normal,
                                   atol=1e-12)


def test_stream_refuses_profiles_beyond_the_range():
    """The core's push refuses the profile (as it copies it); the message names the magnitude,
    for a profile of the stream's dtype and one converted to it."""
    for dtype in (np.float64, np.float32):
        s = miem.ProfileStream(4, dtype=dtype)
        s.push(np.zeros((4, 3)))
        with pytest.raises(ValueError, match=r"profile: .*magnitude of 1e\+300.*rescale"):
            s.push(np.full((4, 3), 1e300))
        with pytest.raises(ValueError, match=r"magnitude of 3e\+18.*rescale"):
            s.push(np.array([[0, 0, 0], [0, 0, 0], [0, np.nan, -3e18], [0, 0, 0]], dtype))
        assert s.rows_pushed == 1  # refused, not half-taken


def test_a_grid_is_range_checked_by_the_core_in_its_first_pass(monkeypatch):
    """detect reads an (H, W, 3) grid once for the range (SPEC "Numbers"): in angle pass 1, not
    in a separate Python-side pass; a cloud is still checked before it is detected."""
    from miem import _api

    calls = []
    real = _api._core.finite_extent
    monkeypatch.setattr(_api._core, "finite_extent", lambda a, n: calls.append(n) or real(a, n))
    g = _grid()
    miem.detect(g)
    assert calls == []
    g[3, 4, 0] = 2e18
    with pytest.raises(ValueError, match=r"grid: .*magnitude of 2e\+18.*rescale"):
        miem.detect(g)
    assert calls == []
    with pytest.raises(ValueError, match="rescale"):
        miem.detect(g.reshape(-1, 3)[np.isfinite(g.reshape(-1, 3)).all(axis=1)])
    assert calls[0] == "grid"


@pytest.mark.parametrize("case", ["one point", "four coordinates", "bad parameter", "threads"])
def test_the_range_error_comes_first_whatever_else_is_wrong(case):
    """A grid beyond the range that is also wrong in another way says the range (as it did when
    Python checked every grid first; the fuzzed stream found the 1 x 1 case)."""
    g = {"one point": np.zeros((1, 1, 3)), "four coordinates": np.zeros((4, 5, 4))}.get(
        case, np.zeros((4, 5, 3)))
    g[0, 0, 0] = 1e300
    kw = {"bad parameter": {"theta0": -5}, "threads": {"num_threads": 0}}.get(case, {})
    with pytest.raises(ValueError, match=r"grid: .*magnitude of 1e\+300.*rescale") as err:
        miem.detect(g, **kw)
    assert err.value.__suppress_context__  # the range error alone, not chained to the other


@pytest.mark.parametrize("layout", ["c", "strided", "reversed", "fortran", "float32"])
def test_the_range_check_reads_every_value_of_any_layout(layout):
    """One value out of range at the last position of a view (inf and NaN elsewhere do not
    count): refused, with its magnitude in the message; lifting the largest magnitude of a tiny
    grid into the range there makes it computable."""
    g = _grid()
    g[1, 2] = [np.inf, np.nan, -np.inf]
    views = {"c": lambda a: a, "strided": lambda a: a[:, ::2],
             "reversed": lambda a: a[::-1, ::-1, ::-1], "fortran": np.asfortranarray,
             "float32": lambda a: a.astype(np.float32)[:, 1:]}
    arr = views[layout](g)
    miem.detect(arr)  # in range: computes
    last = tuple(n - 1 for n in arr.shape)
    keep = arr[last]
    arr[last] = -3e18
    with pytest.raises(ValueError, match=r"magnitude of 3e\+18.*rescale"):
        miem.detect(arr)
    arr[last] = keep
    arr *= 1e-20  # largest magnitude below 1e-18: refused ...
    with pytest.raises(ValueError, match="rescale"):
        miem.detect(arr)
    arr[last] = 1.0  # ... unless the last value lifts it
    miem.detect(arr)


def test_plane_distance_of_non_finite_points_is_nan():
    plane = miem.fit_plane(_grid().reshape(-1, 3))
    d = plane.distance(np.array([[np.inf, 0, 0], [0, 0, -np.inf], [np.nan, 0, 0], [0, 0, 1.0]]))
    assert np.isnan(d[:3]).all() and np.isfinite(d[3])


# ---------------------------------------------------------------------------------------------
# item 11: messages name the argument the caller gave


def test_theta0_text_on_a_cloud_names_theta0():
    cloud = np.random.default_rng(0).random((200, 3))
    with pytest.raises(ValueError, match=r"^theta0.*'abc'.*degrees"):
        miem.detect(cloud, theta0="abc")


@pytest.mark.parametrize("width", [2**30, 2**40])
def test_huge_stream_width_names_width(width, isolated):
    code = f"""
import miem
try:
    miem.ProfileStream({width})
    result = "constructed"
except ValueError as exc:
    result = str(exc)
"""
    rep = isolated(code, timeout=30)
    assert rep["ok"] and rep["result"].startswith("width:"), rep
    assert rep["peak_mb"] < PEAK_MB


def test_functions_and_a_shared_neighbor_grid_from_several_threads():
    """The core releases the GIL; concurrent calls give the sequential results."""
    from concurrent.futures import ThreadPoolExecutor

    grids = [_grid(64, 64, seed=s) for s in range(6)]
    cloud = grids[0].reshape(-1, 3)
    cloud = cloud[np.isfinite(cloud).all(axis=1)]
    ng = miem.NeighborGrid(cloud, 0.5)
    seq = [miem.detect(g).labels for g in grids]
    seq_q = [ng.radius_query(i, 1.0) for i in range(0, 400, 7)]
    with ThreadPoolExecutor(4) as pool:
        par = list(pool.map(lambda g: miem.detect(g).labels, grids))
        par_q = list(pool.map(lambda i: ng.radius_query(i, 1.0), range(0, 400, 7)))
    for a, b in zip(seq + seq_q, par + par_q):
        np.testing.assert_array_equal(a, b)


# ---------------------------------------------------------------------------------------------
# item 7: long thin grids cost what square ones do


def _surface(h, w, seed=0):
    rng = np.random.default_rng(seed)
    g = np.empty((h, w, 3))
    g[..., 0] = np.arange(w)[None, :] * 0.5
    g[..., 1] = np.arange(h)[:, None] * 0.5
    g[..., 2] = 0.01 * rng.standard_normal((h, w))
    flat = g.reshape(-1, 3)
    flat[rng.integers(0, h * w, 40), 2] += 2.0
    flat[rng.integers(0, h * w, 40)] = np.nan
    return g


@pytest.mark.parametrize("shape", [(1, 20000), (2, 9000), (20000, 1), (3, 7000)])
def test_thin_grids_match_the_reference(shape):
    from miem import reference as ref

    g = _surface(*shape)
    core, oracle = miem.detect(g, scales=(1, 2)), ref.detect(g, scales=(1, 2))
    np.testing.assert_array_equal(core.labels, oracle.labels)
    np.testing.assert_array_equal(core.flags, oracle.flags)
    np.testing.assert_allclose(core.height, oracle.height, atol=1e-9, equal_nan=True)
    assert len(np.unique(core.labels)) >= 2


def test_thin_grid_memory_in_line_with_a_square_one(isolated):
    code = isolated.CASES + """
import resource, numpy as np, miem
def grow(h, w, nt):
    rng = np.random.default_rng(0)
    g = np.empty((h, w, 3)); g[..., 0] = np.arange(w)[None, :]; g[..., 1] = np.arange(h)[:, None]
    g[..., 2] = 0.01 * rng.standard_normal((h, w))
    miem.detect(g[:4, :4] if h > 4 else g[:, :8], num_threads=nt)  # load everything first
    before = hwm()
    miem.detect(g, num_threads=nt)
    return (hwm() - before) / 1024
def hwm():  # this interpreter's peak RSS in kB (ru_maxrss keeps the forking parent's)
    with open("/proc/self/status") as fh:
        return int([ln for ln in fh if ln.startswith("VmHWM:")][0].split()[1])
result = {f"{h}x{w}": grow(h, w, 2) for h, w in [(1, 2_000_000), (1414, 1414), (2_000_000, 1)]}
"""
    rep = isolated(code, timeout=120)
    assert rep["ok"], rep
    grow = rep["result"]
    # the thin grids run first: each figure is the growth of the process's peak from that call
    assert grow["1x2000000"] < 150 and grow["2000000x1"] < 150, grow
