"""A short coverage-guided fuzz run of every harness in fuzz/ (atheris/libFuzzer), seeded from
the committed corpus: a fixed number of runs each (``-runs``, seed 1, so that CI explores the same
inputs on a fast or a slow machine; ``MIEM_FUZZ_RUNS`` to change it), about a minute in all.
Any crash, uncaught exception,
hang (``-timeout``) or memory past ``-rss_limit_mb`` fails the test with libFuzzer's report; the
input that did it is left in the test's temporary directory. fuzz/README.md has the longer run."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("atheris")

ROOT = Path(__file__).resolve().parents[1]
FUZZ = ROOT / "fuzz"
HARNESSES = sorted(p.stem.removeprefix("fuzz_") for p in FUZZ.glob("fuzz_*.py"))
SECONDS = 60  # a wall-clock bound only; the run ends after RUNS inputs
RUNS = int(os.environ.get("MIEM_FUZZ_RUNS", "3000"))


def test_every_reader_and_the_stream_have_a_harness_and_a_corpus():
    assert set(HARNESSES) >= {"pcd", "ply", "las", "laz", "npy", "npz", "xyz", "csv", "stream"}
    for name in HARNESSES:
        assert any((FUZZ / "corpus" / name).iterdir()), name


@pytest.mark.slow
@pytest.mark.parametrize("name", HARNESSES)
def test_fuzz_harness_short_run(name, tmp_path):
    new = tmp_path / "new"  # libFuzzer adds inputs to the first directory: keep the corpus clean
    new.mkdir()
    cmd = [sys.executable, str(FUZZ / f"fuzz_{name}.py"), str(new), str(FUZZ / "corpus" / name),
           f"-runs={RUNS}", f"-max_total_time={SECONDS}", "-rss_limit_mb=1024", "-timeout=10",
           "-seed=1",
           f"-artifact_prefix={tmp_path}/", "-print_final_stats=1"]
    env = dict(os.environ, PYTHONHASHSEED="0")
    # Through sh, which forks the harness: libFuzzer's -rss_limit_mb reads the peak RSS
    # (ru_maxrss), and a child started straight from this process inherits this process's peak
    # across exec (a pytest worker that ran a big test earlier: "out-of-memory (used: 6702Mb)"
    # at the harness's first input); a grandchild forked by a small shell starts from its own.
    proc = subprocess.run(["/bin/sh", "-c", '"$@"; exit $?', "sh", *cmd], capture_output=True,
                          text=True, timeout=SECONDS + 120, env=env, cwd=tmp_path)
    tail = "\n".join(proc.stderr.splitlines()[-40:])
    assert proc.returncode == 0, f"fuzz_{name} found a problem:\n{tail}"
    assert "Done" in proc.stderr, tail
