"""Soak benchmark: build and run ``miem_bench_soak`` (10^6 streamed profiles with random
dropouts, missing profiles, burr tips, pits and part changes) and write bench/results_soak.md
(a fragment of RESULTS.md): latency percentiles and resident memory per window of profiles.

    python bench/run_soak.py [--profiles 1000000] [--width 1280] [--quick]

The stream allocates nothing per profile (cpp/tests/test_stream_alloc.cpp), so the resident
memory must stay flat after the first window and the latency must not drift; the script states
both from the numbers it measured.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from common import cpu_name  # noqa: E402
from run_cpp import ROOT, one_core, sh  # noqa: E402

OUT = HERE / "results_soak.md"
RAW = HERE / "results_soak.json"


def build(build_dir: Path) -> Path:
    cmd = ["cmake", "-S", str(ROOT), "-B", str(build_dir), "-DCMAKE_BUILD_TYPE=Release",
           "-DMIEM_BUILD_BENCH=ON", f"-DPython_EXECUTABLE={sys.executable}"]
    if not (build_dir / "CMakeCache.txt").exists():
        cmd += ["-G", "Ninja"] if subprocess.run(["which", "ninja"],
                                                capture_output=True).returncode == 0 else []
    sh(cmd)
    sh(["cmake", "--build", str(build_dir), "-j", "2", "--target", "miem_bench_soak"])
    return build_dir / "bench" / "miem_bench_soak"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profiles", type=int, default=1_000_000)
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--quick", action="store_true", help="50,000 profiles")
    ap.add_argument("--build-dir", type=Path, default=ROOT / "build" / "bench-cpp")
    args = ap.parse_args()
    n = 50_000 if args.quick else args.profiles
    window = max(1, n // 10)

    exe = build(args.build_dir)
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    out = sh(one_core([str(exe), "--width", str(args.width), "--profiles", str(n),
                       "--window", str(window)]))
    wall = time.perf_counter() - t0
    load1 = os.getloadavg()
    rows = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    RAW.write_text(json.dumps(rows, indent=1))

    last = rows[-1]
    rss = [r["rss_kb"] for r in rows]
    growth = rss[-1] - rss[0]  # after the first window: the buffers are all touched by then
    p99 = [r["p99_us"] for r in rows]
    drift = max(p99[1:] or p99) / min(p99[1:] or p99)
    flat = abs(growth) <= 256  # kB, a page-cache-level wobble
    lines = [
        "## Soak: 10^6 streamed profiles (C++)" if n == 1_000_000
        else f"## Soak: {n:,} streamed profiles (C++)",
        "",
        f"Written by `python bench/run_soak.py` on {time.strftime('%Y-%m-%d')}: {cpu_name()}, "
        f"one core (`taskset -c 1`), shared with other jobs (load average {load0[0]:.1f} at the "
        f"start, {load1[0]:.1f} at the end), {wall:.0f} s in all. One `miem::ProfileStream<double>`"
        f" with the default parameters (lag {last['lag']}), {last['width']} points per profile: "
        "each profile is a noisy row of a curved sheet with fresh random dropouts (up to 5% of "
        "its points, a run of up to 64 in 5% of the profiles), 0-3 burr tips or pits, 0.2% "
        f"missing profiles (all NaN: {last['empty']:,} here) and a new part (flush + reset) "
        f"every 50,000 profiles on average ({last['resets']} here). Latency is one `push`, "
        "wall clock; memory is the process's resident set (`/proc/self/statm`) at the end of "
        "each window.",
        "",
        "| profiles | p50 (us) | p99 (us) | p99.9 (us) | max (us) | RSS (MiB) |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(f"| {r['profiles']:,} | {r['p50_us']:.1f} | {r['p99_us']:.1f} | "
                     f"{r['p999_us']:.1f} | {r['max_us']:.0f} | {r['rss_kb'] / 1024:.2f} |")
    lines += [
        "",
        f"Resident memory from the first window to the last: {rss[0] / 1024:.2f} -> "
        f"{rss[-1] / 1024:.2f} MiB ({growth:+,} kB): {'flat' if flat else 'NOT flat'}. "
        f"p99 per window between {min(p99):.1f} and {max(p99):.1f} us (windows 2-10 within "
        f"{drift:.2f}x of each other; the max column is the scheduler's noise on a shared "
        f"machine). {last['rows_out']:,} rows came out, {last['abnormal']:,} ABNORMAL points, "
        f"{last['bad_status']} unexpected statuses.",
        "",
    ]
    OUT.write_text("\n".join(lines))
    splice_into_results("\n".join(lines))
    print("\n".join(lines))


def splice_into_results(fragment: str) -> None:
    """Put the fragment into RESULTS.md now (bench/run_results.py appends every results_*.md
    when it next runs): replace an earlier soak section, else append."""
    path = HERE / "RESULTS.md"
    if not path.exists():
        return
    text = path.read_text()
    start = text.find("\n## Soak")
    if start < 0:
        path.write_text(text.rstrip() + "\n\n" + fragment.rstrip() + "\n")
        return
    end = text.find("\n## ", start + 1)
    tail = text[end:] if end >= 0 else "\n"
    path.write_text(text[:start] + "\n" + fragment.rstrip() + "\n" + tail)


if __name__ == "__main__":
    main()
