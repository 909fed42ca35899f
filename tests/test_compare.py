"""miem.compare: registration onto a reference, deviation, labels and defects.

A synthetic part (an analytic height field with a dome, a step and a groove, so that all six
degrees of freedom are constrained) is the reference; the scan samples it on another grid with
noise and known burrs, and the reference is moved by a known rigid motion (the golden sample is
in another frame), so the transform to recover is known exactly.
"""

from __future__ import annotations

import numpy as np
import pytest

import miem
from miem import comparison as cmp
from miem import reference_deviation as refdev

pytest.importorskip("scipy")


def surface(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return (2.0 * np.exp(-((x - 8.0) ** 2 + (y - 6.0) ** 2) / 8.0)
            + 1.5 * np.tanh((x - 20.0) / 1.5) + 0.3 * np.cos(y / 2.5) * (1 + np.tanh((x - 12.0) / 0.8)) + 0.03 * y)


def surface_normal(x: np.ndarray, y: np.ndarray, h: float = 1e-5) -> np.ndarray:
    fx = (surface(x + h, y) - surface(x - h, y)) / (2 * h)
    fy = (surface(x, y + h) - surface(x, y - h)) / (2 * h)
    n = np.stack([-fx, -fy, np.ones_like(fx)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def grid_points(step: float, offset: float = 0.0, size=(30.0, 20.0)) -> np.ndarray:
    xs = np.arange(offset, size[0], step)
    ys = np.arange(offset, size[1], step)
    x, y = np.meshgrid(xs, ys)
    return np.stack([x, y, surface(x, y)], axis=-1)  # (H, W, 3): rows along y


BURRS = [(4.0, 3.0), (14.5, 4.0), (25.0, 15.0), (9.0, 16.0), (27.0, 4.5), (17.0, 12.0),
         (3.5, 12.0), (22.5, 8.0)]


def rotation(axis, deg: float) -> np.ndarray:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = np.radians(deg)
    return np.eye(3) + np.sin(t) * k + (1 - np.cos(t)) * k @ k


MOTION = np.eye(4)
MOTION[:3, :3] = rotation((1.0, 2.0, 3.0), 25.0)
MOTION[:3, 3] = (40.0, -15.0, 7.0)


def make_scan(seed: int = 0, step: float = 0.15, noise: float = 0.01):
    """Scan (H, W, 3) with burrs added along the surface normal, and the true normal deviation."""
    rng = np.random.default_rng(seed)
    g = grid_points(step, offset=0.07)
    x, y = g[..., 0], g[..., 1]
    n = surface_normal(x, y)
    height = np.zeros(x.shape)
    for k, (bx, by) in enumerate(BURRS):
        r = np.hypot(x - bx, y - by)
        peak, rad = 0.5 + 0.07 * k, 0.6
        height = np.maximum(height, np.where(r < rad, peak * (1 - (r / rad) ** 2), 0.0))
    scan = g + height[..., None] * n + noise * rng.standard_normal(g.shape)
    return scan, height


def make_reference(step: float = 0.1) -> np.ndarray:
    pts = grid_points(step).reshape(-1, 3)
    return pts @ MOTION[:3, :3].T + MOTION[:3, 3]


def rotation_error_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = (np.trace(a[:3, :3] @ b[:3, :3].T) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))


def f1(pred: np.ndarray, truth: np.ndarray) -> float:
    tp = np.sum(pred & truth)
    return float(2 * tp / max(1, pred.sum() + truth.sum()))


# ---------------------------------------------------------------------------------------------
# core == reference


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_core_deviation_equals_reference(dtype) -> None:
    rng = np.random.default_rng(1)
    ref = rng.uniform(0, 5, (4000, 3))
    ref[:, 2] = 0.3 * np.sin(ref[:, 0])
    nrm = rng.standard_normal((4000, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    nrm[::97] = np.nan  # rows without a plane are not part of the surface
    ref[::131] = np.nan
    scan = rng.uniform(-1, 6, (3000, 3)).astype(dtype)
    scan[:, 2] = rng.uniform(-0.8, 0.8, 3000)
    scan[::50] = np.nan
    before = scan.copy()
    for lateral in (np.inf, 0.05):
        surf = miem._core.ReferenceSurface(ref, nrm, 0.1, 0)
        dev, dist, near, cov = surf.deviation(scan, 0.4, lateral, 0)
        want = refdev.deviation(scan, ref, nrm, 0.4, lateral)
        np.testing.assert_array_equal(near, want.nearest)
        np.testing.assert_array_equal(cov, want.covered)
        np.testing.assert_allclose(dev, want.deviation, rtol=0, atol=1e-12)
        np.testing.assert_allclose(dist, want.distance, rtol=1e-12, atol=1e-12)
        assert (0.2 < cov.mean() < 0.9) if lateral == np.inf else (0.01 < cov.mean() < 0.2)
    np.testing.assert_array_equal(scan, before)  # the caller's array is untouched
    # Thread count does not change anything.
    one = miem._core.ReferenceSurface(ref, nrm, 0.1, 1).deviation(scan, 0.4, np.inf, 1)
    np.testing.assert_array_equal(one[2], want.nearest)


def test_core_labels_equal_reference() -> None:
    rng = np.random.default_rng(2)
    pts = rng.uniform(0, 10, (5000, 3))
    pts[:, 2] = 0
    dev = 0.01 * rng.standard_normal(5000)
    for cx, cy, h in ((2, 2, 0.6), (7, 3, -0.5), (5, 8, 0.26), (8, 8, 0.9)):
        r = np.hypot(pts[:, 0] - cx, pts[:, 1] - cy)
        dev += np.where(r < 0.8, h * (1 - (r / 0.8) ** 2), 0)
    covered = rng.uniform(size=5000) > 0.05
    dev[~covered] = np.nan
    labels, raw = miem._core.label_deviation(pts, dev, covered, None, 0.2, 0.1, 0.25)
    want_labels, want = refdev.label_deviation(pts, dev, covered, 0.2, 0.1, 0.25)
    np.testing.assert_array_equal(labels, want_labels)
    assert [tuple(d[1]) for d in raw] == [tuple(d.indices) for d in want]
    assert [d[4] for d in raw] == [d.peak_height for d in want]
    assert [d[7] for d in raw] == [d.kind for d in want]
    # The 0.26 dome peaks inside the don't-care band (0.2 + 0.1): no defect, WITHIN.
    near = np.hypot(pts[:, 0] - 5, pts[:, 1] - 8) < 0.2
    assert np.all(labels[near & covered] == cmp.WITHIN)
    assert {d[7] for d in raw} >= {"protrusion", "pit"}


# ---------------------------------------------------------------------------------------------
# registration and burrs


@pytest.fixture(scope="module")
def synthetic():
    pytest.importorskip("open3d")
    scan, height = make_scan()
    ref = make_reference()
    res = miem.compare(scan, ref, tolerance=0.2, detection="auto")
    return scan, height, ref, res


def test_synthetic_part_registered_back_without_initial_pose(synthetic) -> None:
    scan, height, ref, res = synthetic
    reg = res.registration
    assert reg.coarse == "fpfh_ransac"
    rot_err = rotation_error_deg(reg.transform, MOTION)
    trans_err = float(np.linalg.norm(reg.transform[:3, 3] - MOTION[:3, 3]))
    # The motion is 25 deg and 44 mm; it is recovered to within 0.03 deg and 0.03 mm
    # (bench/results_compare.md: about 0.003 deg and 0.002 mm with the defaults).
    assert rot_err < 0.03, rot_err
    assert trans_err < 0.03, trans_err
    assert reg.inlier_fraction > 0.95
    # Noise 0.01; the burr points within inlier_distance count too.
    assert reg.rmse < 0.08


def test_synthetic_burrs_found(synthetic) -> None:
    scan, height, ref, res = synthetic
    truth = height > 0.2  # burrs are added along the normal: their height is the deviation
    pred = res.labels == cmp.EXCESS
    assert f1(pred, truth) >= 0.95, f1(pred, truth)
    # One defect per burr, each at its burr, with the burr's height as peak deviation.
    burr_defects = [d for d in res.defects if d.kind == "protrusion"]
    assert len(burr_defects) == len(BURRS)
    found = []
    for d in burr_defects:
        dist = [np.hypot(d.centroid[0] - bx, d.centroid[1] - by) for bx, by in BURRS]
        k = int(np.argmin(dist))
        assert dist[k] < 0.3
        assert abs(d.peak_height - (0.5 + 0.07 * k)) < 0.06
        found.append(k)
    assert sorted(found) == list(range(len(BURRS)))
    assert res.counts()["MISSING"] == 0
    # Defects in the same form as detect: grid cells and flat indices.
    d = res.defects[0]
    assert isinstance(d, miem.Defect)
    np.testing.assert_array_equal(d.cells[:, 0] * scan.shape[1] + d.cells[:, 1], d.indices)
    assert res.labels.shape == scan.shape[:2]


def test_agreement_with_miem(synthetic) -> None:
    scan, height, ref, res = synthetic
    ag = res.agreement
    det = miem.detect(scan)
    assert ag is not None
    # Every MIEM defect is accounted for once.
    seen = {m for _, ms in ag.both for m in ms}
    assert seen | set(ag.miem_only) | set(ag.miem_not_covered) == {d.id for d in det.defects}
    assert not seen & set(ag.miem_only)
    assert {c for c, _ in ag.both} | set(ag.compare_only) == {d.id for d in res.defects}
    abn = det.labels == miem.ABNORMAL
    out = res.labels == cmp.EXCESS
    assert ag.points["both"] == int(np.sum(abn & out))
    assert "seen by both" in ag.summary()


@pytest.mark.parametrize("library, method", [("open3d", "point_to_plane"), ("open3d", "gicp"),
                                             ("small_gicp", "gicp")])
def test_each_library_from_a_rough_pose(library, method) -> None:
    pytest.importorskip(library)
    scan, height = make_scan(seed=3, step=0.25)
    ref = make_reference(step=0.15)
    rough = MOTION.copy()
    rough[:3, :3] = rough[:3, :3] @ rotation((0, 1, 0), 2.0)
    rough[:3, 3] += (0.4, -0.3, 0.2)
    res = miem.compare(scan, ref, init_transform=rough, library=library, method=method,
                       detection=None)
    assert (res.registration.library, res.registration.method) == (library, method)
    assert res.registration.coarse == "given"
    assert rotation_error_deg(res.transform, MOTION) < 0.05
    assert np.linalg.norm(res.transform[:3, 3] - MOTION[:3, 3]) < 0.02


def test_partial_overlap_and_outliers() -> None:
    pytest.importorskip("open3d")
    rng = np.random.default_rng(4)
    scan, height = make_scan(seed=4, step=0.2)
    part = scan[:, : scan.shape[1] // 2].reshape(-1, 3)  # x < 15: half the part
    lo, hi = part.min(axis=0), part.max(axis=0)
    outliers = rng.uniform(lo - 2, hi + 2, (len(part) // 20, 3))  # 5 % floating returns
    pts = np.concatenate([part, outliers])
    res = miem.compare(pts, make_reference(), detection=None)
    assert rotation_error_deg(res.transform, MOTION) < 0.05
    assert np.linalg.norm(res.transform[:3, 3] - MOTION[:3, 3]) < 0.02
    # Outliers far from the surface are not covered, not defects.
    far = np.abs(outliers[:, 2] - surface(outliers[:, 0], outliers[:, 1])) > 2.5
    assert np.all(res.labels[len(part):][far] == cmp.NOT_COVERED)


def test_points_beyond_the_reference_are_not_covered() -> None:
    scan, _ = make_scan(step=0.3, noise=0.0)
    ref = grid_points(0.1, size=(15.0, 20.0)).reshape(-1, 3)  # the reference has x < 15 only
    res = miem.compare(scan, ref, register_scan=False, detection=None)
    x = scan[..., 0]
    assert np.all(~res.covered[x > 15.5])
    assert res.covered[x < 14.5].mean() > 0.99
    assert res.counts()["NOT_COVERED"] == int(np.sum(~res.covered))


# ---------------------------------------------------------------------------------------------
# mesh references


def heightfield_mesh(step: float):
    trimesh = pytest.importorskip("trimesh")
    g = grid_points(step)
    h, w = g.shape[:2]
    idx = np.arange(h * w).reshape(h, w)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3),
                            np.stack([a, d, c], -1).reshape(-1, 3)])
    return trimesh.Trimesh(vertices=g.reshape(-1, 3), faces=faces, process=False)


def test_mesh_reference_equals_its_dense_sampling() -> None:
    mesh = heightfield_mesh(0.2)
    assert np.all(mesh.face_normals[:, 2] > 0)  # upward: outward for this part
    scan, height = make_scan(step=0.3)
    a = miem.compare(scan, mesh, register_scan=False, detection=None)
    # The same surface as dense points (vertices of a 2x finer triangulation of the mesh).
    fine = mesh.subdivide()
    b = miem.compare(scan, np.asarray(fine.vertices), register_scan=False, detection=None)
    both = a.covered & b.covered
    inner = (scan[..., 0] > 1) & (scan[..., 0] < 29) & (scan[..., 1] > 1) & (scan[..., 1] < 19)
    assert both[inner].mean() > 0.99
    diff = np.abs(a.deviation - b.deviation)[both & inner]
    assert np.percentile(diff, 99) < 0.01 and diff.max() < 0.05
    assert np.mean(a.labels[inner] == b.labels[inner]) > 0.99
    assert a.params["reference_kind"] == "mesh" and b.params["reference_kind"] == "points"


def test_mesh_file_reference(tmp_path) -> None:
    mesh = heightfield_mesh(0.5)
    path = tmp_path / "part.stl"
    mesh.export(path)
    ref = miem.load_reference(path, spacing=0.1)
    assert ref.kind == "mesh" and ref.oriented
    assert abs(len(ref.points) - mesh.area / 0.01) < 2
    np.testing.assert_allclose(np.linalg.norm(ref.normals, axis=1), 1.0, atol=1e-9)


# ---------------------------------------------------------------------------------------------
# bad input


def test_no_overlap_is_a_clear_error() -> None:
    pytest.importorskip("open3d")
    scan, _ = make_scan(step=0.3)
    far = MOTION.copy()
    far[:3, 3] += 500.0
    with pytest.raises(ValueError, match="do not overlap"):
        miem.compare(scan, make_reference(0.2), init_transform=far, detection=None)


def test_degenerate_reference() -> None:
    line = np.stack([np.linspace(0, 10, 100), np.zeros(100), np.zeros(100)], axis=1)
    with pytest.raises(ValueError, match="degenerate"):
        miem.load_reference(line)
    same = np.ones((100, 3))
    with pytest.raises(ValueError, match="degenerate|coincide"):
        miem.load_reference(same)
    with pytest.raises(ValueError, match="at least 10"):
        miem.load_reference(np.zeros((3, 3)) + np.arange(3)[:, None])


@pytest.mark.parametrize("kwargs, match", [
    (dict(tolerance=0), "tolerance"),
    (dict(tolerance=float("nan")), "tolerance"),
    (dict(dont_care=-1), "dont_care"),
    (dict(coverage=-1), "coverage"),
    (dict(init_transform=np.eye(3)), "init_transform"),
    (dict(init_transform=np.diag([2.0, 1, 1, 1])), "init_transform"),
    (dict(scan_up=(0, 0, 0)), "scan_up"),
    (dict(detection="yes"), "detection"),
    (dict(register_scan="no"), "register_scan"),
])
def test_bad_arguments(kwargs, match) -> None:
    scan, _ = make_scan(step=0.5)
    kwargs.setdefault("register_scan", False)
    with pytest.raises(ValueError, match=match):
        miem.compare(scan, make_reference(0.5), **kwargs)


def test_wrong_shapes() -> None:
    good = grid_points(0.5).reshape(-1, 3)
    with pytest.raises(ValueError, match="scan: expected shape"):
        miem.compare(good[:, :2], good, register_scan=False)
    with pytest.raises(ValueError, match="reference: expected shape"):
        miem.compare(good, np.zeros((100, 4)), register_scan=False)
    with pytest.raises(ValueError, match="normals: expected shape"):
        miem.load_reference(good, normals=np.zeros((5, 3)))
    with pytest.raises(ValueError, match="scan"):
        miem.compare(np.full((50, 3), np.nan), good, register_scan=False)
    with pytest.raises(ValueError, match="reference: no such file"):
        miem.load_reference("/nonexistent/part.stl")


def test_float32_scan_huge_coverage_and_inputs_untouched() -> None:
    scan, _ = make_scan(step=0.4, noise=0.0)
    scan32 = scan.astype(np.float32)
    scan32[0, 0] = np.nan  # a dropout
    ref = grid_points(0.2).reshape(-1, 3)
    before_s, before_r = scan32.copy(), ref.copy()
    a = miem.compare(scan32, ref, register_scan=False, detection=None, coverage=1e6,
                     max_lateral=1e6)
    np.testing.assert_array_equal(scan32, before_s)
    np.testing.assert_array_equal(ref, before_r)
    assert a.labels[0, 0] == cmp.NOT_COVERED and a.covered[1:].all()
    # Every finite point is covered; the deviation is the oracle's on the same normals.
    refobj = miem.load_reference(ref)
    want = refdev.deviation(scan32.reshape(-1, 3), refobj.points, refobj.normals, 1e6, 1e6)
    np.testing.assert_allclose(a.deviation.reshape(-1), want.deviation, atol=1e-9)


def test_agreement_spike_seen_by_both(synthetic) -> None:
    scan, height, ref, res = synthetic
    spiked = scan.copy()
    r, c = 40, 60  # a 2 mm single-point spike on a flat, burr-free spot
    assert height[r - 3:r + 4, c - 3:c + 4].max() == 0
    spiked[r, c, 2] += 2.0
    out = miem.compare(spiked, ref, init_transform=res.transform, register_scan=False)
    det = miem.detect(spiked)
    spike_c = [d.id for d in out.defects if r * scan.shape[1] + c in d.indices]
    spike_m = [d.id for d in det.defects if r * scan.shape[1] + c in d.indices]
    assert len(spike_c) == 1 and len(spike_m) == 1
    assert (spike_c[0], (spike_m[0],)) in out.agreement.both
    assert spike_m[0] not in out.agreement.miem_only
