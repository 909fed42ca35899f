"""README.md's examples run as written: the Quickstart, "From Python" and the command-line
session (the C++ snippet is built in test_cpp.py against the installed package).

Each marked block (see readme_snippets.py) runs in a fresh directory, shell blocks with this
interpreter's environment in place of ``.venv/bin/``; a session's commands must print what the
README shows, but for the timing columns.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import readme_snippets as rs  # noqa: E402

BIN = Path(sys.executable).parent


def _env() -> dict:
    env = dict(os.environ)
    env["PATH"] = f"{BIN}{os.pathsep}{env.get('PATH', '')}"
    env["MPLBACKEND"] = "Agg"
    return env


def _shell(code: str, cwd: Path, merged: bool = False) -> subprocess.CompletedProcess:
    """Run shell code; `merged`: a session command, stderr into stdout as a terminal shows it,
    and no -e (a session may show a failing command and its exit status)."""
    code = code.replace(".venv/bin/", f"{BIN}/")
    flags = ["-o", "pipefail"] if merged else ["-euo", "pipefail"]
    return subprocess.run(["bash", *flags, "-c", code], cwd=cwd, env=_env(),
                          stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT if merged else subprocess.PIPE,
                          text=True, timeout=300)


def _python(code: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, env=_env(),
                          capture_output=True, text=True, timeout=300)


def _run_blocks(name: str, cwd: Path) -> list[str]:
    blocks = rs.blocks(name)
    assert blocks, f"README.md has no block marked 'snippet: {name}'"
    outputs = []
    for b in blocks:
        if b.lang in ("sh", "bash"):
            proc = _shell(b.code, cwd)
        elif b.lang == "python":
            proc = _python(b.code, cwd)
        else:
            continue
        assert proc.returncode == 0, (
            f"README.md line {b.line} ({b.lang}) failed:\n{b.code}\n--- stdout\n{proc.stdout}"
            f"\n--- stderr\n{proc.stderr[-3000:]}"
        )
        outputs.append(proc.stdout)
    return outputs


def test_quickstart_runs_as_written(tmp_path: Path) -> None:
    out = _run_blocks("quickstart", tmp_path)
    found = re.search(r"found (\d+) of (\d+) defect points", out[-1])
    assert found, out[-1]
    # the recommended detector finds (nearly) every injected defect point of this scan
    assert int(found.group(1)) >= 0.9 * int(found.group(2)) > 0


def test_from_python_runs_as_written(tmp_path: Path) -> None:
    _run_blocks("from-python", tmp_path)


_TIMING = re.compile(r"\s+\d+\.\d\d\s+\d+\.\d\d$")  # the two seconds columns of miem detect


def _same(shown: str, got: str) -> bool:
    if _TIMING.search(shown):
        return _TIMING.sub("", shown).rstrip() == _TIMING.sub("", got).rstrip()
    return shown.rstrip() == got.rstrip()


def test_cli_session_reproduces(tmp_path: Path) -> None:
    blocks = rs.blocks("cli-session")
    assert blocks, "README.md has no block marked 'snippet: cli-session'"
    for block in blocks:
        assert rs.session(block), f"README.md line {block.line}: the session is empty"
        for command, shown in rs.session(block):
            proc = _shell(command, tmp_path, merged=True)
            # a command shown failing ends with `; echo "exit $?"`, so the shell exits 0
            assert proc.returncode == 0, f"$ {command}\n{proc.stdout[-3000:]}"
            got = [g for g in proc.stdout.splitlines() if g.strip()]
            assert len(got) == len(shown), f"$ {command}\nshown:\n" + "\n".join(shown) + \
                "\ngot:\n" + "\n".join(got)
            for s, g in zip(shown, got):
                assert _same(s, g), f"$ {command}\nshown: {s}\ngot:   {g}"


def test_snippet_markers_are_all_known() -> None:
    names = {b.name for b in rs.blocks()}
    assert {"quickstart", "from-python", "cli-session", "cpp"} <= names, names
