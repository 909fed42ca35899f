"""Build and run the C++ tests (ctest): once plain, once with AddressSanitizer and UBSan, and
the consumer test (the installed package used by ``cpp/examples`` through ``find_package``).

Each build goes to a temporary directory with ``-DMIEM_BUILD_TESTS=ON``; any failure fails here
with the end of the build or test log. Skipped only when GoogleTest is not installed.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
JOBS = "2"
SANITIZE = "-fsanitize=address,undefined -fno-sanitize-recover=all -fno-omit-frame-pointer"
# -O0 for the sanitizer build: it compiles several times faster than -O1 (Eigen, GoogleTest), and
# the tests' data are small.

pytestmark = pytest.mark.skipif(shutil.which("cmake") is None, reason="cmake not installed")


def _run(cmd: list[str], env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, text=True)


def _check(proc: subprocess.CompletedProcess, what: str) -> str:
    if proc.returncode != 0:
        tail = "\n".join(proc.stdout.splitlines()[-150:])
        pytest.fail(f"{what} failed (exit {proc.returncode}):\n{tail}", pytrace=False)
    return proc.stdout


def _configure_and_build(build: Path, extra: list[str]) -> None:
    cmd = ["cmake", "-S", str(ROOT), "-B", str(build), "-DMIEM_BUILD_TESTS=ON",
           f"-DPython_EXECUTABLE={sys.executable}", *extra]
    if shutil.which("ninja"):
        cmd += ["-G", "Ninja"]
    proc = _run(cmd)
    if proc.returncode != 0 and "GTest" in proc.stdout:
        pytest.skip("GoogleTest (libgtest-dev) not installed")
    _check(proc, "cmake configure")
    _check(_run(["cmake", "--build", str(build), "-j", JOBS]), "cmake --build")


def _ctest(build: Path, args: list[str], env: dict | None = None) -> str:
    out = _check(_run(["ctest", "--test-dir", str(build), "--output-on-failure", "-j", JOBS,
                       "--timeout", "600", *args], env=env), "ctest")
    assert "tests passed" in out, out[-2000:]
    return out


@pytest.fixture(scope="module")
def plain_build(tmp_path_factory: pytest.TempPathFactory) -> Path:
    build = tmp_path_factory.mktemp("cpp-plain")
    _configure_and_build(build, ["-DCMAKE_BUILD_TYPE=Release"])
    return build


def test_ctest(plain_build: Path) -> None:
    out = _ctest(plain_build, ["-LE", "consumer"])
    print(out.splitlines()[-3])


def test_ctest_with_sanitizers(tmp_path: Path) -> None:
    build = tmp_path / "cpp-asan"
    _configure_and_build(build, ["-DCMAKE_BUILD_TYPE=", f"-DCMAKE_CXX_FLAGS=-O0 {SANITIZE}",
                                 f"-DCMAKE_EXE_LINKER_FLAGS={SANITIZE}",
                                 "-DMIEM_USE_OPENMP=OFF"])
    env = dict(os.environ)
    env["ASAN_OPTIONS"] = "abort_on_error=1:detect_leaks=1:strict_string_checks=1"
    env["UBSAN_OPTIONS"] = "print_stacktrace=1:halt_on_error=1"
    out = _ctest(build, [], env=env)
    print(out.splitlines()[-3])


def test_consumer_of_installed_package(plain_build: Path) -> None:
    out = _ctest(plain_build, ["-L", "consumer", "-V"])
    assert "consumer test passed" in out, out[-3000:]


def _cached_build_type(build: Path, extra: list[str]) -> str:
    cmd = ["cmake", "-S", str(ROOT), "-B", str(build), f"-DPython_EXECUTABLE={sys.executable}",
           *extra]
    _check(_run(cmd), "cmake configure")
    for line in (build / "CMakeCache.txt").read_text().splitlines():
        if line.startswith("CMAKE_BUILD_TYPE:"):
            return line.split("=", 1)[1]
    return "<unset>"


def test_plain_build_is_release_and_explicit_choice_kept(tmp_path: Path) -> None:
    # A plain `cmake -S . -B build` (the README's command) must not give an unoptimised library;
    # an explicit build type, even an empty one, is the user's choice.
    env_type = os.environ.pop("CMAKE_BUILD_TYPE", None)
    try:
        assert _cached_build_type(tmp_path / "plain", []) == "Release"
        assert _cached_build_type(tmp_path / "debug", ["-DCMAKE_BUILD_TYPE=Debug"]) == "Debug"
        assert _cached_build_type(tmp_path / "empty", ["-DCMAKE_BUILD_TYPE="]) == ""
    finally:
        if env_type is not None:
            os.environ["CMAKE_BUILD_TYPE"] = env_type


def test_readme_cpp_snippet_builds_and_runs(plain_build: Path, tmp_path: Path) -> None:
    """README.md's C++ example, as written, against the installed package (find_package)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import readme_snippets as rs

    blocks = rs.blocks("cpp")
    assert blocks, "README.md has no block marked 'snippet: cpp'"
    prefix, src, build = tmp_path / "prefix", tmp_path / "src", tmp_path / "build"
    src.mkdir()
    _check(_run(["cmake", "--install", str(plain_build), "--prefix", str(prefix),
                 "--component", "cpp"]), "cmake --install")
    (src / "main.cpp").write_text("".join(b.code for b in blocks if b.lang == "cpp"))
    cmake_blocks = [b.code for b in rs.blocks("cpp-cmake")]
    (src / "CMakeLists.txt").write_text(
        "cmake_minimum_required(VERSION 3.16)\nproject(readme_snippet CXX)\n"
        "add_executable(controller main.cpp)\n" + "".join(cmake_blocks))
    cache = (plain_build / "CMakeCache.txt").read_text()
    eigen = [ln.split("=", 1)[1] for ln in cache.splitlines() if ln.startswith("Eigen3_DIR:")]
    cmd = ["cmake", "-S", str(src), "-B", str(build), "-DCMAKE_BUILD_TYPE=Release",
           f"-DCMAKE_PREFIX_PATH={prefix}"] + ([f"-DEigen3_DIR={eigen[0]}"] if eigen else [])
    _check(_run(cmd), "configure the README snippet")
    _check(_run(["cmake", "--build", str(build)]), "build the README snippet")
    out = _check(_run([str(build / "controller")]), "run the README snippet")
    assert "defects" in out, out
    m = re.search(r"ABNORMAL points: batch (\d+), stream (\d+)", out)
    assert m and m.group(1) == m.group(2) and int(m.group(1)) > 0, out  # the same detector
