"""miem.DetectParams: one configuration, honoured or rejected on every path; presets tied to the
accuracy benchmark and the reference; C++ defaults equal Python's; config files."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import miem
import miem._core as core
import miem.reference as ref
import numpy as np
import pytest
from miem.params import dump_config, load_config

ROOT = Path(__file__).resolve().parents[1]
FIELDS = miem.DetectParams.fields()


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
    return scan(30, 30, 1).reshape(-1, 3)


# --- defaults and presets --------------------------------------------------------------------


def test_default_is_the_recommended_preset_on_every_path() -> None:
    assert miem.DEFAULT_PRESET == "recommended"
    assert miem.DetectParams() == miem.PRESETS["recommended"] == miem.default_params("grid")
    g = scan()
    res = miem.detect(g)
    assert res.params["preset"] == "recommended"
    want = miem.detect(g, preset="recommended")
    np.testing.assert_array_equal(res.labels, want.labels)
    # stream and clouds: the recommended angle test; the height test they do not implement is off
    for path in ("stream", "cloud"):
        d = miem.default_params(path)
        assert (d.theta0, d.scales) == (90.0, (1, 2))
        assert d.height_tolerance is None and d.edge_extent == 0
    assert miem.ProfileStream(8).params == miem.default_params("stream")
    assert miem.detect(cloud()).params["theta0"] == 90.0


def test_presets_are_the_accuracy_benchmark_and_the_reference() -> None:
    tuned = json.loads((ROOT / "bench" / "accuracy" / "recommended.json").read_text())
    rec = miem.PRESETS["recommended"]
    for name, value in tuned.items():
        got = getattr(rec, name)
        assert (list(got) if isinstance(got, tuple) else got) == value, name
    for name, table in ref._PRESETS.items():
        p = miem.PRESETS[name]
        for k, v in table.items():
            assert getattr(p, k) == v, (name, k)
    assert set(ref._PRESETS) == set(miem.PRESETS)
    assert ref._DEFAULT_PRESET == miem.DEFAULT_PRESET


def test_paper_preset_is_the_paper() -> None:
    p = miem.PRESETS["paper"]
    assert (p.theta0, p.scales, p.max_gap, p.min_step, p.min_directions, p.max_iterations,
            p.window, p.height_tolerance, p.edge_extent) == (75.0, (1,), 1, None, None, 10, 21,
                                                             None, 0)


def _core_fields(c) -> dict:
    return {k: getattr(c, k) for k in dir(c) if not k.startswith("_") and
            not callable(getattr(c, k))}


def test_cpp_defaults_equal_python_defaults() -> None:
    # grid: the bound C++ DetectParams{} is what the Python defaults convert to
    assert _core_fields(core.DetectParams()) == _core_fields(miem.DetectParams()._core_grid(0))
    assert _core_fields(core.recommended_params()) == _core_fields(core.DetectParams())
    assert _core_fields(core.paper_params()) == _core_fields(
        miem.PRESETS["paper"]._core_grid(0))
    assert _core_fields(core.stream_default_params()) == _core_fields(
        miem.default_params("stream")._core_grid(0, "stream"))
    assert _core_fields(core.PointsDetectParams()) == _core_fields(
        miem.default_params("cloud")._core_cloud(0))


# --- every field honoured or rejected on every path ------------------------------------------

# A valid non-neutral value per field (different from the default, too).
OTHER = {
    "theta0": 100.0, "scales": (1, 3), "max_gap": 2, "min_step": 0.5, "min_directions": 2,
    "max_iterations": 3, "window": 9, "heights": "abnormal", "height_tolerance": 0.05,
    "edge_extent": 4, "max_reach": 5, "radius": 1.2, "K": 6, "link": 0.9,
}


def _run(path: str, params: miem.DetectParams):
    if path == "grid":
        return miem.detect(scan(), params=params).params
    if path == "cloud":
        return miem.detect(cloud(), params=params).params
    s = miem.ProfileStream(36, params=params)
    for row in scan():
        s.push(row)
    s.flush()
    return dataclasses.asdict(s.params)


def test_other_values_cover_every_field() -> None:
    assert set(OTHER) == set(FIELDS)
    for name, value in OTHER.items():
        assert value != FIELDS[name]["default"] and value != FIELDS[name]["neutral"], name


@pytest.mark.parametrize("path", miem.params.PATHS)
@pytest.mark.parametrize("name", list(FIELDS))
def test_every_field_is_honoured_or_rejected(path: str, name: str) -> None:
    base = miem.default_params(path)
    params = base.replace(**{name: OTHER[name]})
    if name == "edge_extent" and path == "grid":
        params = params.replace(height_tolerance=0.05)
    if path in FIELDS[name]["paths"]:
        used = _run(path, params)
        assert used[name] == OTHER[name] or (name == "scales" and tuple(used[name]) == OTHER[name])
    else:
        with pytest.raises(ValueError, match=name):
            _run(path, params)


def test_grid_fields_change_the_result() -> None:
    """Honoured means used: each grid field gives the reference's result for its value, and the
    main ones visibly change the labels or heights of this scan."""
    g = scan()
    base = miem.detect(g, preset="paper")
    for name, value in OTHER.items():
        if "grid" not in FIELDS[name]["paths"] or name in ("heights", "max_reach"):
            continue
        kw = {name: 179.0 if name == "theta0" else value}  # 100 deg changes nothing here
        if name == "height_tolerance":  # a window clear of the other defects' EDGE cells
            kw["window"] = 7
        if name == "edge_extent":  # only with the height test
            other = miem.detect(g, preset="paper", height_tolerance=0.05, edge_extent=30)
            oracle = ref.detect(g, preset="paper", height_tolerance=0.05, edge_extent=30)
            np.testing.assert_array_equal(other.labels, oracle.labels)
            continue
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


# --- the drift cases of issue 9 -----------------------------------------------------------------


def test_cloud_refuses_the_grid_only_height_test_instead_of_dropping_it() -> None:
    pts = cloud()
    with pytest.raises(ValueError, match="height_tolerance.*edge_extent.*unorganized"):
        miem.detect(pts, preset="recommended")
    with pytest.raises(ValueError, match="theta0='auto'"):
        miem.detect(pts, theta0="auto")
    with pytest.raises(ValueError, match="height_tolerance"):
        miem.detect_points(pts, height_tolerance="4rms")
    # with the height test switched off it runs: the recommended angle test
    res = miem.detect(pts, preset="recommended", height_tolerance=None, edge_extent=0)
    np.testing.assert_array_equal(res.labels, miem.detect(pts).labels)
    oracle = ref.detect_points(pts, theta0=90.0, scales=(1, 2))
    np.testing.assert_array_equal(res.labels, oracle.labels)


def test_stream_refuses_what_it_does_not_implement() -> None:
    for kw, name in (({"theta0": "auto"}, "theta0"), ({"height_tolerance": "4rms"},
                                                       "height_tolerance"),
                     ({"edge_extent": 12}, "edge_extent"), ({"window": 9}, "window"),
                     ({"heights": "abnormal"}, "heights"), ({"radius": 1.0}, "radius")):
        with pytest.raises(ValueError, match=name):
            miem.ProfileStream(16, **kw)
    with pytest.raises(ValueError, match="height_tolerance"):
        miem.ProfileStream(16, preset="recommended")
    # theta0_auto on the C++ side (the old silent drift: batch EDGE where the stream said NORMAL)
    p = core.stream_default_params()
    p.theta0_auto = True
    code, msg = core.check_stream_params(16, p)
    assert code == 1 and msg.startswith("theta0_auto")
    with pytest.raises(ValueError, match="theta0_auto"):
        core.ProfileStream64(16, p)


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
        p.theta0 = 70.0  # type: ignore[misc]
    assert miem.PRESETS["paper"].theta0 == 75.0


def test_fields_carry_units_help_and_paths() -> None:
    for name, meta in FIELDS.items():
        assert meta["help"] and meta["metavar"], name
        assert set(meta["paths"]) <= set(miem.params.PATHS) and meta["paths"], name
    assert FIELDS["theta0"]["unit"] == "deg"
    assert FIELDS["window"]["unit"] == "cells"
    assert FIELDS["radius"]["paths"] == ("cloud",)


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


@pytest.mark.parametrize("fmt", ["json", "toml"])
def test_config_round_trip(tmp_path: Path, fmt: str) -> None:
    for p in (miem.PRESETS["paper"], miem.PRESETS["recommended"],
              miem.DetectParams(theta0="auto", min_step=0.3, radius=2.0)):
        path = tmp_path / f"c.{fmt}"
        path.write_text(dump_config(p, fmt))
        assert load_config(path) == p


def test_config_file_with_a_preset_and_overrides(tmp_path: Path) -> None:
    path = tmp_path / "cell.toml"
    path.write_text('preset = "paper"\ntheta0 = 80.0\nheight_tolerance = "off"\n')
    assert load_config(path) == miem.PRESETS["paper"].replace(theta0=80.0)
    path = tmp_path / "cell.json"
    path.write_text('{"scales": [1, 2, 3], "window": 15}')
    assert load_config(path) == miem.DetectParams(scales=(1, 2, 3), window=15)
    path.write_text('{"windw": 15}')
    with pytest.raises(ValueError, match="windw"):
        load_config(path)
    path.write_text("[1, 2]")
    with pytest.raises(ValueError, match="table"):
        load_config(path)
    path.write_text("{not json")
    with pytest.raises(ValueError, match="JSON"):
        load_config(path)
    with pytest.raises(ValueError, match="cannot read"):
        load_config(tmp_path / "missing.json")
