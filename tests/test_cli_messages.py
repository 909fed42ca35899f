"""The command line's messages name its own options, never the library's keywords."""

from __future__ import annotations

import re

import numpy as np
import pytest

from miem.cli import main

_PY_KEYWORD = re.compile(r"\b(format|step|line_tol|line_axis|along_axis|duplicates)=")


def _run(capsys, argv):
    code = main(argv)
    captured = capsys.readouterr()
    return code, captured.err


def test_unknown_suffix_names_input_format(tmp_path, capsys):
    f = tmp_path / "scan.dat"
    f.write_text("0 0 0\n1 0 0\n0 1 0\n")
    code, err = _run(capsys, ["detect", str(f), "-o", str(tmp_path / "out")])
    assert code == 1
    assert "--input-format" in err and not _PY_KEYWORD.search(err), err


def test_directory_is_named_as_a_directory(tmp_path, capsys):
    code, err = _run(capsys, ["detect", str(tmp_path), "-o", str(tmp_path / "out")])
    assert code == 1
    assert "is a directory" in err and "suffix" not in err, err


def test_duplicate_points_name_the_duplicates_option(tmp_path, capsys):
    # two profiles (y = 0, 1), x every 1.0, the second profile has one point twice
    x = np.arange(10.0)
    pts = [np.c_[x, np.zeros(10), np.zeros(10)], np.c_[x, np.ones(10), np.zeros(10)]]
    pts = np.vstack(pts + [[[3.0, 1.0, 0.0]]])
    f = tmp_path / "dup.xyz"
    np.savetxt(f, pts)
    # (with --layout auto the cloud detector would take it and merge the duplicate)
    code, err = _run(capsys, ["detect", str(f), "-o", str(tmp_path / "out"),
                              "--layout", "scanlines"])
    assert code == 1
    assert not _PY_KEYWORD.search(err), err
    assert "--duplicates first or last" in err or "--line-step" in err, err


@pytest.mark.parametrize("text,want", [
    ("pass format= (one of pcd, ply)", "use --input-format (one of pcd, ply)"),
    ("overlap; pass step= and line_tol=", "overlap; use --line-step and --line-tol"),
    ("pass duplicates='first' or 'last' to keep one", "use --duplicates first or last to keep one"),
    ("off its column; check step and along_axis, or", "off its column; check --line-step and "
                                                       "--along-axis, or"),
    ("already --line-step", "already --line-step"),
])
def test_keyword_translation(text, want):
    from miem.cli import _cli_words

    assert _cli_words(text) == want


def _grid_file(tmp_path, scale: float, name: str):
    import miem.io as mio
    from miem import simulate as sim

    scan = sim.make_scan(shape=(40, 60), step=0.5, defects={"spike": 2}, seed=4)
    f = tmp_path / name
    mio.write(f, scan.points * scale)
    return f


def test_units_are_guessed_per_scan_and_reported(tmp_path, capsys):
    import json

    mm = _grid_file(tmp_path, 1.0, "part_mm.npy")      # 0.5 mm steps, 30 mm wide
    m = _grid_file(tmp_path, 1e-3, "part_m.npy")       # the same part in metres
    code = main(["detect", str(mm), str(m), "-o", str(tmp_path / "out")])
    out = capsys.readouterr().out
    assert code == 0
    rows = {line.split()[0]: line for line in out.splitlines() if line.startswith("part_")}
    assert rows["part_mm.npy"].split()[7] == "mm" and rows["part_m.npy"].split()[7] == "m"
    doc = json.loads((tmp_path / "out" / "part_m.defects.json").read_text())
    assert doc["units"] == "m"


def test_unit_mismatch_and_absurd_lengths_are_warned_about(tmp_path, capsys):
    m = _grid_file(tmp_path, 1e-3, "part_m.npy")
    code = main(["detect", str(m), "--units", "mm", "--min-step", "0.5", "-o",
                 str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 0
    assert "looks like m, not the --units mm given" in err
    assert "--min-step=0.5 is larger than the scan itself" in err


def test_guess_units_on_clouds():
    from miem.units import guess_units

    rng = np.random.default_rng(1)
    room = np.c_[rng.uniform(0, 4, 30000), rng.uniform(0, 3, 30000), np.zeros(30000)]  # metres
    g = guess_units(room)
    assert g.unit == "m" and 3.8 < g.extent < 4.0
    assert guess_units(room * 1000).unit == "mm"
    assert guess_units(np.full((5, 3), np.nan)).unit == "mm"  # nothing to go by: the default
