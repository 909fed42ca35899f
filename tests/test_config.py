"""Issue 9, "a new parameter touches its type, its check, SPEC and README": the C++ field tables
(``visit_fields``, bound as ``miem._core.*Params.fields()``) are the one list of fields. Every
bound field is a field of miem.DetectParams (as it is, or spelled by one of the few documented
Python spellings), with the C++ default; every field is a command-line option, a line of
``miem config`` and a row of SPEC's table; miem.dask knows it; no module keeps its own list of
plain field names."""

from __future__ import annotations

import ast
import dataclasses
import functools
import importlib.util
import re
from pathlib import Path

import miem
import miem._core as core
import miem.params as mp
import numpy as np
import pytest
from miem import cli

ROOT = Path(__file__).resolve().parents[1]
PARTS = ("angle", "grid", "cloud")


def bound(part: str) -> list[tuple[str, str, str]]:
    return [tuple(f) for f in mp._CORE_PART[part].fields()]


def py_fields(part: str) -> dict[str, dataclasses.Field]:
    return {f.name: f for f in dataclasses.fields(mp._PART_TYPES[part])}


SPELLED = {s.name for part in PARTS for s in mp._SPELLED[part]}


def test_bound_fields_are_read_write_with_unit_and_help() -> None:
    for part in PARTS:
        names = [n for n, _, _ in bound(part)]
        assert len(names) == len(set(names)) and names, part
        obj = mp._CORE_PART[part]()
        for name, unit, help_ in bound(part):
            assert help_, name
            doc = getattr(mp._CORE_PART[part], name).__doc__
            assert help_ in doc and (not unit or f"[{unit}]" in doc), name
            setattr(obj, name, getattr(obj, name))  # writable
    # the combined types add num_threads only (a call argument, not a detection parameter)
    assert [n for n, _, _ in core.DetectParams.fields()] == ["num_threads"]
    assert [n for n, _, _ in core.PointsDetectParams.fields()] == ["num_threads"]


def test_every_bound_field_is_a_python_field_with_the_cpp_default() -> None:
    for part in PARTS:
        fields = py_fields(part)
        covered = {c: name for name, f in fields.items() for c in f.metadata["core"]}
        assert set(covered) == {n for n, _, _ in bound(part)}, part  # each C++ field, once
        for name, f in fields.items():
            if name not in SPELLED:  # a plain field: the C++ field as it is
                assert f.metadata["core"] == (name,), name
                unit, help_ = next((u, h) for n, u, h in bound(part) if n == name)
                assert (f.metadata["unit"], f.metadata["help"]) == (unit, help_), name
        # defaults: the Python default converts to exactly the default-constructed C++ value
        whole = mp._CORE_WHOLE[part]
        converted = whole()
        mp._to_core(mp._PART_TYPES[part](), converted)
        for c in covered:
            assert getattr(converted, c) == getattr(whole(), c), (part, c)
    # and every C++ preset round-trips through its Python spelling
    for preset, grid, cloud in (("paper", core.paper_params(), core.paper_points_params()),
                                ("recommended", core.DetectParams(), core.PointsDetectParams())):
        p = miem.PRESETS[preset]
        assert p == miem.DetectParams._from_core(grid, cloud)
        g, c = p._core_grid(0), p._core_cloud(0)
        for part, want, got in (("angle", grid, g), ("grid", grid, g), ("cloud", cloud, c)):
            for n, _, _ in bound(part):
                assert getattr(got, n) == getattr(want, n), (preset, part, n)
    # the paper's angle part is the same on grids and clouds
    for n, _, _ in bound("angle"):
        assert getattr(core.paper_params(), n) == getattr(core.paper_points_params(), n), n


def test_cpp_check_names_the_field_as_the_user_wrote_it() -> None:
    g = np.dstack(np.mgrid[0:8, 0:8].astype(float) + (np.zeros((8, 8)),))
    g = np.dstack([g[..., 0], g[..., 1], 0.01 * g[..., 0] ** 2])
    for kw, name in (({"window": 4}, "window"), ({"edge_window": 2}, "edge_window"),
                     ({"max_gap": -1}, "max_gap"), ({"max_reach": 0}, "max_reach"),
                     ({"edge_extent": -2}, "edge_extent"), ({"max_iterations": 0},
                                                            "max_iterations"),
                     ({"scales": (0,)}, "scales"), ({"min_directions": 5}, "min_directions"),
                     ({"window": 2**40}, "window"), ({"window": 5.0}, "window"),
                     ({"theta0": 180.0}, "theta0"), ({"edge_tolerance": 0}, "edge_tolerance")):
        with pytest.raises(ValueError, match=rf"^{name}\b"):
            miem.detect(g, **kw)
    pts = g.reshape(-1, 3)
    for kw, name in (({"K": 9}, "K"), ({"radius": 0.0}, "radius"), ({"link": -1.0}, "link"),
                     ({"min_group": 2}, "min_group"), ({"merge_distance": -1.0},
                                                       "merge_distance"),
                     ({"height_radius": float("nan")}, "height_radius"),
                     ({"isolated_tolerance": -1.0}, "isolated_tolerance"),
                     ({"edge_extent": -1.0}, "edge_extent"), ({"spacing": 0.0}, "spacing")):
        with pytest.raises(ValueError, match=rf"^{name}\b"):
            miem.detect(pts, **kw)
    # a C++ message about a spelled field names the Python field (and the C++ one)
    p = core.PointsDetectParams()
    p.isolated_k = -1.0
    with pytest.raises(ValueError, match=r"^isolated_tolerance \(C\+\+ isolated_k\): must be"):
        mp._check(p, ("angle", "cloud"))


def test_every_field_is_an_option_a_config_line_and_a_spec_row() -> None:
    parser = cli._build_parser()
    sub = next(a for a in parser._actions if isinstance(a, cli.argparse._SubParsersAction))
    detect = sub.choices["detect"]
    options = {o: a.dest for a in detect._actions for o in a.option_strings}
    spec = (ROOT / "docs" / "SPEC.md").read_text()
    section = spec.split("## Parameters", 1)[1].split("\n## ", 1)[0]
    rows = {}
    for m in re.finditer(r"^\| (\w+) \| `(\w+)` \|(.*)$", section, re.M):
        rows[(m.group(1), m.group(2))] = m.group(3)
    for preset in miem.PRESETS:
        text = mp.dump_config(miem.PRESETS[preset])
        for part in PARTS:
            table = text.split(f"[{part}]", 1)[1].split("\n[", 1)[0]
            for name in py_fields(part):
                assert f"\n{name} = " in table, (preset, part, name)
    for part in PARTS:
        for name, f in py_fields(part).items():
            assert options.get(cli._option(name)) == name, name  # --edge-extent, --k
            assert (part, name) in rows, (part, name)
            for c in f.metadata["core"]:  # a spelled field's row names its C++ fields
                assert c == name or f"`{c}`" in rows[(part, name)], (part, name, c)
    # and nothing else: SPEC's table has no field that does not exist
    assert set(rows) == {(part, n) for part in PARTS for n in py_fields(part)}


def test_dask_knows_every_field() -> None:
    import miem.dask as mdask

    assert set(miem.DetectParams.fields("grid")) <= mdask._GRID_KNOWN
    assert set(miem.DetectParams.fields("cloud")) <= mdask._POINT_KNOWN


@functools.lru_cache(maxsize=None)
def _other() -> dict:
    spec = importlib.util.spec_from_file_location("_params_values", ROOT / "tests" /
                                                  "test_params.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.OTHER


def grid_value(name: str):
    """tests/test_params.py's non-default value of a grid field (one table for every test)."""
    return _other()[name]


@pytest.mark.parametrize("name", sorted(miem.DetectParams.fields("grid")))
def test_dask_blocks_equal_the_whole_grid_for_every_field(name: str) -> None:
    """Every grid field runs on blocks, equal to the whole grid. (Blocks see whole 64 x 128-cell
    tiles of context, so this cannot see a halo that is short by less than a tile: a new field
    that reaches farther than grid_halo's formula must still be added to it.)"""
    da = pytest.importorskip("dask.array")
    import dask
    import miem.dask as mdask

    rng = np.random.default_rng(7)
    r, c = np.mgrid[0:320, 0:120].astype(float)  # row blocks of one 64-row tile each
    z = 0.3 * np.exp(-((c - 40.0) ** 2) / 300.0) + rng.normal(0, 0.003, r.shape)
    z[:, 70] += 0.5  # a feature line
    for k in range(60):  # spikes, pits and burr pairs across the block borders
        rr, cc = 64 * (1 + k % 4) + (k % 7) - 3, (k * 37) % 118 + 1
        z[rr, cc] += (-1) ** k * (0.2 + 0.05 * k)
        z[rr + 1, cc] += 0.5 * (-1) ** k * (0.2 + 0.05 * k)
    g = np.dstack([c * 0.25, r * 0.25, z])
    g[rng.random(r.shape) < 0.01] = np.nan
    kw = {"preset": "paper", "max_iterations": 3, name: grid_value(name)}
    if name in ("edge_extent", "window", "heights"):
        kw["height_tolerance"] = 0.05
    if name == "edge_window":
        kw["edge_tolerance"] = 3.0
    if name == "max_reach":
        kw["min_step"] = 0.4
    halo = mdask.grid_halo(miem.detect(g[:8], **kw).params)
    assert 64 + 2 * halo < 320, halo  # a block sees part of the grid only
    want = miem.detect(g, **kw)
    with dask.config.set(scheduler="synchronous"):
        res = mdask.detect(da.from_array(g, chunks=(64, 120, 3)), **kw)
        labels, height = dask.compute(res.labels, res.height)
    np.testing.assert_array_equal(labels, want.labels)
    np.testing.assert_array_equal(height, want.height)


# Where a plain field's name may still be written out, and why (everything else is generated).
ALLOWED = {
    # the spellings (and the C++ fields they stand for) are the documented exceptions
    "params.py": SPELLED | {c for part in PARTS for s in mp._SPELLED[part] for c in s.core},
    # what points_halo reads (the cloud edge test's too); the lengths a cloud's spacing derives
    "dask.py": {"edge_tolerance", "edge_radius", "radius", "min_step", "link", "height_radius",
                "spacing", "edge_extent", "height_tolerance", "min_step_auto", "theta0_auto",
                "scales", "max_gap", "max_reach", "window", "max_iterations", "edge_window",
                "theta0", "min_group", "merge_distance",
                # the other lengths resolved on the driver, as min_step
                "z_resolution", "z_resolution_auto", "z_noise", "z_noise_auto"},
    "cli.py": set(),
}


@pytest.mark.parametrize("module", sorted(ALLOWED))
def test_no_hand_written_list_of_field_names(module: str) -> None:
    """String constants naming a field in params.py, cli.py and dask.py: only the allowed ones
    (the spellings; what dask's halo formulas read). A new plain field needs none of them."""
    names = {n for part in PARTS for n in py_fields(part)} | {
        n for part in PARTS for n, _, _ in bound(part)}
    tree = ast.parse((ROOT / "python" / "miem" / module).read_text())
    docstrings = {id(n.value) for n in ast.walk(tree) if isinstance(n, ast.Expr)}
    found = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant)
             and isinstance(n.value, str) and id(n) not in docstrings and n.value in names}
    assert found <= ALLOWED[module], sorted(found - ALLOWED[module])


def test_a_new_cpp_field_becomes_a_python_field(monkeypatch) -> None:
    """The generator, fed a C++ table with one more plain field: it becomes a field with the
    C++ default, unit and help, converted to the core by its C++ type, with no other change."""

    class Core:
        def __init__(self) -> None:
            self.__dict__.update({n: getattr(core.DetectParams(), n)
                                  for n, _, _ in core.GridParams.fields()}, new_reach=7)

        @staticmethod
        def fields():
            return core.GridParams.fields() + [("new_reach", "cells", "a new reach (>= 0)")]

    monkeypatch.setitem(mp._CORE_PART, "grid", Core)
    monkeypatch.setitem(mp._CORE_WHOLE, "grid", Core)
    Grid = mp._make_part("grid", "test")
    f = {x.name: x for x in dataclasses.fields(Grid)}["new_reach"]
    assert (f.default, f.metadata["unit"], f.metadata["metavar"]) == (7, "cells", "CELLS")
    target = Core()
    mp._to_core(Grid(new_reach=3), target)
    assert target.new_reach == 3
    with pytest.raises(ValueError, match="new_reach: expected an integer"):
        mp._to_core(Grid(new_reach=2.5), Core())


@pytest.mark.parametrize("name", sorted({n for p in ("grid", "cloud")
                                         for n in miem.DetectParams.fields(p)}))
def test_every_option_reaches_detect(name: str) -> None:
    """``miem detect --<field> VALUE`` hands the value to miem.detect on the path that reads it
    (grids, and for cloud scans the cloud kwargs), parsed from its text."""
    value = _other()[name]
    text = [str(v) for v in value] if isinstance(value, tuple) else [str(value)]
    args = cli._build_parser().parse_args(["detect", "scan.pcd", cli._option(name), *text])
    kwargs = cli._detect_kwargs(args)
    if name in miem.DetectParams.fields("grid"):
        assert kwargs[name] == value, (name, kwargs)
    points = cli._Loaded(None, np.zeros((3, 3)), None, "mm", "cloud")
    cloud = cli._cloud_kwargs(points, kwargs, args, Path("scan.pcd"))
    if name in miem.DetectParams.fields("cloud"):
        assert cloud[name] == value, (name, cloud)
