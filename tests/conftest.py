"""Shared fixtures: run a snippet in a fresh interpreter under a memory cap and a time limit."""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import textwrap

import pytest

# The child runs the snippet and reports how it ended and its peak resident memory on its last
# line; a crash (abort, segfault, libgomp's "out of memory") leaves no report and fails the test.
_WRAPPER = """
import json, resource, sys
ns = {"__name__": "__case__"}
try:
    exec(compile(sys.stdin.read(), "<case>", "exec"), ns)
    out = {"ok": True, "result": ns.get("result")}
except BaseException as exc:
    out = {"ok": False, "type": type(exc).__name__, "message": str(exc),
           "mro": [c.__name__ for c in type(exc).__mro__]}
# VmHWM: this interpreter's own peak; ru_maxrss would keep the forking parent's size (Linux
# carries it across exec).
try:
    with open("/proc/self/status") as fh:
        hwm = [ln for ln in fh if ln.startswith("VmHWM:")][0]
    out["peak_mb"] = int(hwm.split()[1]) / 1024
except (OSError, IndexError):
    out["peak_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
sys.stdout.flush()
print("\\n@@REPORT@@" + json.dumps(out))
"""


class Isolated:
    """``isolated(code)`` runs `code` in a subprocess with an address-space cap (so that a
    memory bomb fails fast instead of swapping the machine) and a timeout, and returns the
    report: ``ok``, ``result`` (the snippet's global ``result``, JSON), ``type``, ``message``,
    ``mro`` (exception class names), ``peak_mb`` (peak RSS of the whole child), ``stdout``,
    ``stderr``, ``returncode``."""

    CASES = ""  # set below: defines run_cases({name: callable}) inside the child

    def __init__(self, tmp_path):
        self.cwd = tmp_path

    def __call__(self, code: str, *, cap_mb: int = 2048, timeout: float = 60.0) -> dict:
        def limit() -> None:
            resource.setrlimit(resource.RLIMIT_AS, (cap_mb << 20, cap_mb << 20))

        proc = subprocess.run(
            [sys.executable, "-c", _WRAPPER], input=textwrap.dedent(code), capture_output=True,
            text=True, timeout=timeout, preexec_fn=limit, cwd=self.cwd,
        )
        marker = proc.stdout.rfind("@@REPORT@@")
        if marker < 0:
            raise AssertionError(
                f"the child died without a report (exit {proc.returncode}):\n"
                f"{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")
        report = json.loads(proc.stdout[marker + len("@@REPORT@@"):])
        report.update(stdout=proc.stdout[:marker], stderr=proc.stderr,
                      returncode=proc.returncode)
        return report


@pytest.fixture(scope="session")
def isolated(tmp_path_factory) -> Isolated:
    return Isolated(tmp_path_factory.mktemp("isolated"))


# Runs inside the child: call each case, record how it ended and how long it took.
CASES = """
import time
def run_cases(cases):
    out = {}
    for name, fn in cases.items():
        t0 = time.perf_counter()
        try:
            fn()
            rec = {"ok": True}
        except BaseException as exc:
            rec = {"ok": False, "type": type(exc).__name__, "message": str(exc),
                   "mro": [c.__name__ for c in type(exc).__mro__]}
        rec["seconds"] = time.perf_counter() - t0
        out[name] = rec
    return out
"""
Isolated.CASES = CASES


# Under README's ``pytest -n auto --dist loadfile --no-loadscope-reorder`` (pytest-xdist) each
# file runs whole on one worker (its module-scoped fixtures are made once), files in collection
# order: the files here go first so that the longest one does not start last and hold up the run.
XDIST_FIRST = ("tests/test_cpp.py",)  # two C++ builds (plain and sanitized) and their ctest runs


def pytest_collection_modifyitems(config, items):
    if not hasattr(config, "workerinput"):  # not an xdist worker: collection order unchanged
        return
    first = {name: i for i, name in enumerate(XDIST_FIRST)}
    items.sort(key=lambda item: first.get(item.nodeid.split("::")[0], len(first)))
