"""miem.DetectParams: one configuration, honoured or rejected on every path; presets tied to the
accuracy benchmark and the reference; C++ defaults equal Python's; config files."""

from __future__ import annotations

import dataclasses
import inspect
import json
from pathlib import Path

import miem
import miem._core as core
import miem.reference as ref
import numpy as np
import pytest
from miem.params import dump_config, load_config

ROOT = Path(__file__).resolve().parents[1]


def scan(h: int = 40, w: int = 36, seed: int = 0) -> np.ndarray:
    """A tilted, slightly noisy sheet with spikes, a pit, a wide smooth dome and dropouts."""
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[0:h, 0:w]
    x, y = c * 0.3, r * 0.3
    z = 0.05 * x + 0.02 * y + rng.normal(0.0, 0.002, (h, w))
    z += 0.12 * np.exp(-((x - 2.1) ** 2 + (y - 2.1) ** 2) / 0.5)  # around cell (7, 7)
    g = np.dstack([x, y, z])
    g[h // 2, w // 2, 2] += 1.0
    g[h - 8, 10, 2] -= 0.8
    g[12:14, w - 10:w - 8, 2] += 2.0  # 2 x 2: the paper's scale 1 misses it
    g[rng.random((h, w)) < 0.01] = np.nan
    return g


def cloud() -> np.ndarray:
    """The same kind of surface as an unorganized cloud (rows shuffled, x and y jittered by up
    to a sixth of the 0.3 step: off any scan line, as the cloud path's own data)."""
    pts = scan(30, 30, 1).reshape(-1, 3)
    rng = np.random.default_rng(5)
    pts = pts[rng.permutation(len(pts))]
    pts[:, :2] += rng.uniform(-0.05, 0.05, (len(pts), 2))
    return pts


# --- defaults and presets --------------------------------------------------------------------


def test_default_is_the_recommended_preset_on_every_path() -> None:
    assert miem.DEFAULT_PRESET == "recommended"
    assert miem.DetectParams() == miem.PRESETS["recommended"] == miem.default_params("grid")
    assert miem.default_params("cloud") == miem.PRESETS["recommended"]
    g = scan()
    res = miem.detect(g)
    assert res.params["preset"] == "recommended"
    np.testing.assert_array_equal(res.labels, miem.detect(g, preset="recommended").labels)
    pts = cloud()
    np.testing.assert_array_equal(miem.detect(pts).labels,
                                  miem.detect(pts, preset="recommended").labels)
    assert miem.detect(pts).params["height_tolerance"] == "7rms"
    # the stream: the recommended detector, height and edge tests and min_step="auto"
    # included (in C++ too)
    d = miem.default_params("stream")
    assert d.grid.height_tolerance == "4.5rms" and d.grid.edge_extent == 12
    assert d.grid.edge_tolerance == 4.0 and d.grid.min_step == "auto"
    assert d == miem.PRESETS["recommended"]
    assert miem.ProfileStream(8).params == d
    cs, cd = core.stream_default_params(), core.DetectParams()
    for name in ("theta0_deg", "scales", "height_k", "height_abs", "edge_extent", "window",
                 "max_iterations", "max_gap", "edge_k", "edge_window", "min_step_auto",
                 "min_step", "max_reach", "z_resolution_auto", "z_resolution", "z_noise_auto",
                 "z_noise"):
        assert getattr(cs, name) == getattr(cd, name), name
    assert (cs.min_step_auto, cs.min_step) == (True, -1.0)
    assert (cs.z_resolution_auto, cs.z_resolution) == (True, -1.0)
    assert (cs.z_noise_auto, cs.z_noise) == (True, -1.0)


def test_presets_are_the_accuracy_benchmark_and_the_reference() -> None:
    tuned = json.loads((ROOT / "bench" / "accuracy" / "recommended.json").read_text())
    rec = miem.PRESETS["recommended"].flat("grid")
    for name, value in tuned.items():
        got = rec[name]
        assert (list(got) if isinstance(got, tuple) else got) == value, name
    for name, table in ref._PRESETS.items():
        p = miem.PRESETS[name].flat("grid")
        for k, v in table.items():
            assert p[k] == v, (name, k)
    assert set(ref._PRESETS) == set(miem.PRESETS)
    assert ref._DEFAULT_PRESET == miem.DEFAULT_PRESET
    # the reference's cloud defaults are the recommended cloud values
    sig = inspect.signature(ref.detect_points).parameters
    for k, v in miem.PRESETS["recommended"].flat("cloud").items():
        if k in sig:
            assert sig[k].default == v, k


def test_paper_preset_is_the_paper() -> None:
    p = miem.PRESETS["paper"]
    a, g, c = p.angle, p.grid, p.cloud
    assert (a.theta0, a.scales, a.min_directions, a.max_iterations) == (75.0, (1,), None, 10)
    assert (g.max_gap, g.min_step, g.window, g.height_tolerance, g.edge_extent,
            g.edge_tolerance) == (1, None, 21, None, 0, None)
    assert (c.height_tolerance, c.edge_extent, c.min_group) == (None, 0.0, 0)


def _core_fields(c) -> dict:
    return {k: getattr(c, k) for k in dir(c) if not k.startswith("_") and
            not callable(getattr(c, k))}


def test_cpp_defaults_equal_python_defaults() -> None:
    # the bound C++ DetectParams{} / PointsDetectParams{} are what the Python defaults convert to
    assert _core_fields(core.DetectParams()) == _core_fields(miem.DetectParams()._core_grid(0))
    assert _core_fields(core.recommended_params()) == _core_fields(core.DetectParams())
    assert _core_fields(core.paper_params()) == _core_fields(
        miem.PRESETS["paper"]._core_grid(0))
    assert _core_fields(core.stream_default_params()) == _core_fields(
        miem.default_params("stream")._core_grid(0, "stream"))
    assert _core_fields(core.PointsDetectParams()) == _core_fields(
        miem.DetectParams()._core_cloud(0))
    assert _core_fields(core.paper_points_params()) == _core_fields(
        miem.PRESETS["paper"]._core_cloud(0))


# --- every field honoured or rejected on every path ------------------------------------------

# A valid value per field, different from the default (and from the stream's neutral value).
OTHER = {
    "theta0": 100.0, "scales": (1, 3), "min_directions": 2, "max_iterations": 3,
    "max_gap": 2, "min_step": 0.5, "max_reach": 5, "window": 9, "heights": "abnormal",
    "height_tolerance": 0.05, "edge_extent": 4, "radius": 1.2, "K": 6, "link": 0.9,
    "min_group": 5, "height_radius": 2.0, "merge_distance": 0.01, "spacing": 0.35,
    "edge_tolerance": 8.0, "edge_window": 7, "edge_radius": 2.5, "isolated_tolerance": 2.0,
    "z_resolution": 0.02, "z_noise": 0.03,
}
ALL_FIELDS = {name for path in miem.params.PATHS for name in miem.DetectParams.fields(path)}


def _run(path: str, base: miem.DetectParams, overrides: dict):
    if path == "grid":
        return miem.detect(scan(), params=base, **overrides).params
    if path == "cloud":
        return miem.detect(cloud(), params=base, **overrides).params
    s = miem.ProfileStream(36, params=base, **overrides)
    for row in scan():
        s.push(row)
    s.flush()
    return s.params.flat("stream")


def test_other_values_cover_every_field() -> None:
    assert set(OTHER) == ALL_FIELDS
    for path in miem.params.PATHS:
        for name, meta in miem.DetectParams.fields(path).items():
            assert OTHER[name] != meta["default"], name


@pytest.mark.parametrize("path", miem.params.PATHS)
@pytest.mark.parametrize("name", sorted(ALL_FIELDS))
def test_every_field_is_honoured_or_rejected(path: str, name: str) -> None:
    base = miem.default_params(path)
    fields = miem.DetectParams.fields(path)
    value = OTHER[name]
    meta = fields.get(name, {}) if path == "stream" else {}
    # a stream field with "stream_refuses" takes any value but that one (min_step: not "auto")
    honoured = name in fields and ("stream" not in meta or "stream_refuses" in meta)
    if honoured:
        used = _run(path, base, {name: value})
        assert used[name] == value, (name, used[name])
    else:
        with pytest.raises(ValueError, match=name):
            _run(path, base, {name: value})


def test_grid_fields_change_the_result() -> None:
    """Honoured means used: each grid field gives the reference's result for its value, and the
    main ones visibly change the labels or heights of this scan."""
    g = scan()
    base = miem.detect(g, preset="paper")
    for name in miem.DetectParams.fields("grid"):
        if name in ("heights", "max_reach"):
            continue
        kw = {name: 179.0 if name == "theta0" else OTHER[name]}  # 100 deg changes nothing here
        if name == "height_tolerance":  # a window clear of the other defects' EDGE cells
            kw["window"] = 7
        if name == "edge_extent":  # only with the height test
            kw = {"height_tolerance": 0.05, "edge_extent": 30}
        if name == "edge_window":  # only with the edge test
            kw = {"edge_tolerance": 8.0, "edge_window": 7}
        res, oracle = miem.detect(g, preset="paper", **kw), ref.detect(g, preset="paper", **kw)
        np.testing.assert_array_equal(res.labels, oracle.labels)  # used as the reference does
        np.testing.assert_allclose(res.height, oracle.height, atol=1e-8, equal_nan=True)
        if name in ("theta0", "scales", "window", "height_tolerance", "min_step"):
            changed = (res.labels != base.labels).any() or not np.allclose(
                res.height, base.height, equal_nan=True)
            assert changed, name
    # heights="abnormal": NaN where not ABNORMAL
    res = miem.detect(g, heights="abnormal")
    assert np.isnan(res.height[res.labels != miem.ABNORMAL]).all()
    # max_reach is used with min_step only
    a = miem.detect(g, preset="paper", min_step=1.5, max_reach=1)
    b = miem.detect(g, preset="paper", min_step=1.5, max_reach=8)
    assert not np.array_equal(a.angle, b.angle, equal_nan=True)  # neighbours found or not
    np.testing.assert_array_equal(
        b.labels, ref.detect(g, preset="paper", min_step=1.5, max_reach=8).labels)


def test_cloud_fields_are_the_reference_s() -> None:
    pts = cloud()
    for kw in ({}, {"height_tolerance": None, "min_group": 0}, {"radius": 1.2, "K": 6},
               {"edge_extent": 3.0, "height_radius": 3.0}):
        res = miem.detect(pts, **kw)
        oracle = ref.detect_points(pts, **kw)
        np.testing.assert_array_equal(res.labels, oracle.labels)
    paper = miem.detect(pts, preset="paper")
    oracle = ref.detect_points(pts, theta0=75.0, scales=(1,), height_tolerance=None,
                               edge_extent=0.0, min_group=0, edge_tolerance=None)
    np.testing.assert_array_equal(paper.labels, oracle.labels)


# --- the drift cases of issue 9 -----------------------------------------------------------------


def test_clouds_run_the_preset_s_cloud_values_and_refuse_grid_fields() -> None:
    pts = cloud()
    rec = miem.detect(pts, preset="recommended")
    for k in ("height_tolerance", "edge_extent", "min_group"):
        assert rec.params[k] == miem.CLOUD_PRESETS["recommended"][k]  # not dropped
    with pytest.raises(ValueError, match="theta0='auto'"):
        miem.detect(pts, theta0="auto")
    for name, value in (("window", 9), ("max_gap", 2), ("max_reach", 5)):
        with pytest.raises(ValueError, match=name):
            miem.detect(pts, **{name: value})
        with pytest.raises(ValueError, match=name):
            miem.detect_points(pts, **{name: value})
    with pytest.raises(ValueError, match="radius"):
        miem.detect(scan(), radius=1.0)


def test_stream_refuses_what_it_does_not_implement() -> None:
    for kw, name in (({"theta0": "auto"}, "theta0"), ({"radius": 1.0}, "radius")):
        with pytest.raises(ValueError, match=name):
            miem.ProfileStream(16, **kw)
    # the height test, its compact EDGE groups, heights, the edge test and min_step="auto"
    # (SPEC: the first 256 rows with data) are honoured now
    assert miem.ProfileStream(16, preset="recommended").params == miem.PRESETS["recommended"]
    for kw in ({"height_tolerance": "4rms"}, {"edge_extent": 5}, {"window": 9},
               {"heights": "abnormal"}, {"edge_tolerance": 3.0}, {"edge_window": 7},
               {"min_step": "auto"}):
        (name, value), = kw.items()
        assert getattr(miem.ProfileStream(16, **kw).params.grid, name) == value
    # theta0_auto on the C++ side (the old silent drift: batch EDGE where the stream said NORMAL)
    p = core.stream_default_params()
    p.theta0_auto = True
    code, msg = core.check_stream_params(16, p)
    assert code == 1 and msg.startswith("theta0_auto")
    with pytest.raises(ValueError, match="theta0_auto"):
        core.ProfileStream64(16, p)
    p = core.stream_default_params()
    p.min_step_auto = True
    p.min_step = -1.0
    assert core.check_stream_params(16, p)[0] == 0


@pytest.mark.parametrize("preset", [None, "paper"])
def test_stream_equals_batch_on_its_parameters(preset) -> None:
    g = scan(60, 36, 4)
    s = miem.ProfileStream(36, preset=preset)
    out = np.full(g.shape[:2], 99, np.uint8)
    for row in g:
        done = s.push(row)
        if done is not None:
            out[done.row] = done.labels
    for done in s.flush():
        out[done.row] = done.labels
    want = miem.detect(g, params=s.params).labels
    np.testing.assert_array_equal(out, want)
    assert (want == miem.ABNORMAL).any()
    assert s.params == (miem.PRESETS[preset] if preset else miem.default_params("stream"))


def test_nothrow_names_the_field_for_nan_height_and_negative_edge_extent() -> None:
    for field_, value in (("height_abs", float("nan")), ("edge_extent", -1),
                          ("height_k", float("inf"))):
        p = core.DetectParams()
        setattr(p, field_, value)
        code, msg = p.check()
        assert code == 1 and msg.startswith(field_), msg
        with pytest.raises(ValueError, match=field_):
            core.detect_organized(scan(), p)


# --- the Python API ----------------------------------------------------------------------------


def test_params_preset_and_overrides() -> None:
    g = scan()
    p = miem.PRESETS["paper"].replace(theta0=80.0)
    a = miem.detect(g, params=p)
    b = miem.detect(g, preset="paper", theta0=80.0)
    c = miem.detect(g, params=p.to_dict())
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_array_equal(a.labels, c.labels)
    assert a.params["preset"] == "custom" and b.params["preset"] == "paper"
    assert miem.detect(g, p).params["theta0"] == 80.0  # params may be positional
    with pytest.raises(ValueError, match="params, preset"):
        miem.detect(g, params=p, preset="paper")
    with pytest.raises(ValueError, match="thet0: unknown"):
        miem.detect(g, thet0=80)
    with pytest.raises(ValueError, match="preset"):
        miem.detect(g, preset="fast")
    with pytest.raises(ValueError, match="params"):
        miem.detect(g, params=42)
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.angle.theta0 = 70.0  # type: ignore[misc]
    assert miem.PRESETS["paper"].angle.theta0 == 75.0
    # replace() sets a name in every part that has it; for_path() only in the detector's parts
    q = miem.DetectParams().replace(height_tolerance=None)
    assert q.grid.height_tolerance is None and q.cloud.height_tolerance is None
    q = miem.DetectParams().for_path("cloud", height_tolerance="5rms")
    assert q.cloud.height_tolerance == "5rms" and q.grid.height_tolerance == "4.5rms"


def test_fields_carry_units_help_and_parts() -> None:
    for path in miem.params.PATHS:
        for name, meta in miem.DetectParams.fields(path).items():
            assert meta["help"] and meta["metavar"], name
            assert meta["part"] in ("angle", "grid", "cloud")
    grid = miem.DetectParams.fields("grid")
    assert grid["theta0"]["unit"] == "deg" and grid["window"]["unit"] == "cells"
    assert miem.DetectParams.fields("cloud")["edge_extent"]["unit"] == "spacings"
    assert "radius" not in grid and "window" not in miem.DetectParams.fields("cloud")


def test_bound_types_have_read_write_fields_with_docs() -> None:
    p = core.DetectParams()
    p.theta0_deg = 80.0
    p.scales = [1, 3]
    assert (p.theta0_deg, p.scales) == (80.0, [1, 3])
    assert "degrees" in core.AngleParams.theta0_deg.__doc__
    assert "cells" in core.GridParams.window.__doc__
    assert "length" in core.CloudParams.radius.__doc__
    p.window = 4
    assert p.check() == (1, "window: must be an odd integer >= 3")
    c = core.PointsDetectParams()
    c.min_group = 2
    assert c.check()[1].startswith("min_group")


@pytest.mark.parametrize("fmt", ["json", "toml"])
def test_config_round_trip(tmp_path: Path, fmt: str) -> None:
    for p in (miem.PRESETS["paper"], miem.PRESETS["recommended"],
              miem.DetectParams().replace(theta0="auto", min_step=0.3, radius=2.0)):
        path = tmp_path / f"c.{fmt}"
        path.write_text(dump_config(p, fmt))
        assert load_config(path) == p


def test_config_file_with_a_preset_and_overrides(tmp_path: Path) -> None:
    path = tmp_path / "cell.toml"
    path.write_text('preset = "paper"\ntheta0 = 80.0\n[grid]\nheight_tolerance = "off"\n'
                    'window = 15\n')
    assert load_config(path) == miem.PRESETS["paper"].replace(theta0=80.0).for_path(
        "grid", window=15)
    path = tmp_path / "cell.json"
    path.write_text('{"scales": [1, 2, 3], "grid": {"window": 15}}')
    assert load_config(path) == miem.DetectParams().replace(scales=(1, 2, 3)).for_path(
        "grid", window=15)
    path.write_text('{"windw": 15}')
    with pytest.raises(ValueError, match="windw"):
        load_config(path)
    path.write_text('{"cloud": {"window": 15}}')
    with pytest.raises(ValueError, match="window"):
        load_config(path)
    path.write_text("[1, 2]")
    with pytest.raises(ValueError, match="table"):
        load_config(path)
    path.write_text("{not json")
    with pytest.raises(ValueError, match="JSON"):
        load_config(path)
    with pytest.raises(ValueError, match="cannot read"):
        load_config(tmp_path / "missing.json")
