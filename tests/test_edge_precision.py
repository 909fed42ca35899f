"""The edge test's precision floor (SPEC "Edge test" step 3): float32 coordinates are rounded to
its epsilon, so a noise-free face stored as float32 (a CAD model sampled to a PCD file) lies a
few ulps off its sub-windows' planes; without the floor every such cell stood proud of a plane
whose rms is round-off. The core equals the reference and the stream equals batch."""

from __future__ import annotations

import miem
import numpy as np
import pytest
from miem import reference as ref
from miem.simulate import make_scan
from miem.stream import ProfileStream


def _stream(grid: np.ndarray) -> np.ndarray:
    st = ProfileStream(grid.shape[1], dtype=grid.dtype)
    out = np.full(grid.shape[:2], 99, dtype=np.uint8)
    for r in range(grid.shape[0]):
        done = st.push(grid[r])
        if done is not None:
            out[done.row] = done.labels
    for done in st.flush():
        out[done.row] = done.labels
    return out


@pytest.mark.parametrize("surface", ["fillet", "tilted", "crease"])
def test_noise_free_float32_faces_keep_their_cells(surface: str) -> None:
    """A noise-free scan as float32: the labels flag the simulated defects and nothing else, as
    in float64 (the fillet's 60-degree web, 15 mm high, lies 1-2e-6 mm off its planes in
    float32: 15,300 of its 48,000 cells were ABNORMAL before the floor)."""
    scan = make_scan((200, 240), step=0.2, surface=surface, noise=0.0, seed=0,
                     defects={"spike": 3, "pit": 3, "dust": 1, "cluster": 2})
    truth = scan.truth == miem.ABNORMAL
    for dt in (np.float32, np.float64):
        labels = miem.detect(scan.points.astype(dt)).labels
        np.testing.assert_array_equal(labels == miem.ABNORMAL, truth)


def test_core_reference_and_stream_agree_in_float32() -> None:
    """Where the floor decides (the fillet's web as float32), the core on 1 and 2 threads, the
    stream and the reference give the same labels."""
    scan = make_scan((200, 240), step=0.2, surface="fillet", noise=0.0, seed=0,
                     defects={"spike": 3, "pit": 3})
    for dt in (np.float32, np.float64):
        g = scan.points.astype(dt)
        oracle = ref.detect(g).labels
        for nt in (1, 2):
            np.testing.assert_array_equal(miem.detect(g, num_threads=nt).labels, oracle)
        np.testing.assert_array_equal(_stream(g), oracle)
    # the reference's floor decides: without it (edge_test's float64 default on the float32
    # values) the web's cells stand proud
    g = scan.points.astype(np.float32).astype(np.float64)
    before = miem.detect(g, edge_tolerance=None).labels
    p = miem.detect(g).params
    kw = {"window": 15, "tolerance": 4.0, "max_iterations": 10, "z_noise": p["z_noise"],
          "z_resolution": p["z_resolution"]}
    loose = ref.edge_test(g, before, **kw)[0]
    tight = ref.edge_test(g, before, precision=4.0 * 2.0**-23, **kw)[0]
    assert (loose == miem.ABNORMAL).sum() > 100 * (tight == miem.ABNORMAL).sum() > 0


def test_the_floor_scales_with_the_coordinates_only_so_far() -> None:
    """Far from the origin float32 is coarse (at 1000 mm its step is 6e-5 mm): the floor, 4
    epsilons of the cell's largest coordinate (4.8e-4 mm there), keeps the rounding quiet and a
    0.05 mm bump found, by geometry the bump's cells and no other."""
    h, w = 60, 70
    x, y = np.meshgrid(np.arange(w) * 0.2, np.arange(h) * 0.2)
    z = 0.3 * x + 0.2 * y
    bump = (np.abs(np.arange(h)[:, None] - 30) <= 1) & (np.abs(np.arange(w)[None, :] - 35) <= 1)
    z = z + 0.05 * bump
    g = (np.stack([x, y, z], axis=-1) + 1000.0).astype(np.float32)
    labels = miem.detect(g).labels
    assert (labels[bump] == miem.ABNORMAL).all()
    assert (labels[~bump] != miem.ABNORMAL).all()
    np.testing.assert_array_equal(labels, ref.detect(g).labels)


def test_clouds_have_the_floor_too() -> None:
    """The cloud edge test's sectors (SPEC "Unorganized clouds: edge test" step 3) take the same
    floor: a noise-free fillet as a float32 cloud, shuffled, flags its defects and nothing else
    (623 of 48,000 points at 200 x 240 before the floor), on 1 and 2 threads; the core equals
    the reference on a smaller one."""
    scan = make_scan((200, 240), step=0.2, surface="fillet", noise=0.0, seed=0,
                     defects={"spike": 3, "pit": 3, "dust": 1, "cluster": 2})
    order = np.random.default_rng(0).permutation(scan.points.shape[0] * scan.points.shape[1])
    cloud = scan.points.reshape(-1, 3)[order].astype(np.float32)
    truth = (scan.truth.reshape(-1) == miem.ABNORMAL)[order]
    for nt in (1, 2):
        np.testing.assert_array_equal(miem.detect(cloud, num_threads=nt, layout="cloud").labels
                                      == miem.ABNORMAL, truth)
    small = make_scan((120, 140), step=0.2, surface="fillet", noise=0.0, seed=0,
                      defects={"spike": 3, "pit": 3}).points.reshape(-1, 3).astype(np.float32)
    np.testing.assert_array_equal(miem.detect(small, layout="cloud").labels,
                                  ref.detect_points(small).labels)
