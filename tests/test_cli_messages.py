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
    code, err = _run(capsys, ["detect", str(f), "-o", str(tmp_path / "out")])
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
