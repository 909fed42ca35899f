"""miem.dask on a distributed.LocalCluster (worker processes): a generated organized scan of
about 1e8 points, throughput per worker, scaling from 1 to 2 workers, peak memory per worker
against the chunk size, exactness against miem.detect on a part, and a paper calculation for a
1e10-point skin. Writes bench/results_dask.md.

    python bench/bench_dask.py                 # 16384 x 6144 = 1.0e8 points
    python bench/bench_dask.py --rows 4096     # a quicker run
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

import dask
import dask.array as da
import distributed
from dask import delayed

import miem
import miem.dask as mdask
from miem.chunked_io import NpyWriter

HERE = Path(__file__).resolve().parent


def block(r0: int, r1: int, width: int, seed: int) -> np.ndarray:
    """Rows r0..r1 of a skin-like scan: 0.2 mm steps, a gentle wave, 3 um noise, spikes, pits,
    spatter domes and 0.3% dropouts; float32. Each row band has its own seeded generator."""
    rng = np.random.default_rng([seed, r0])
    h = r1 - r0
    r = np.arange(r0, r1, dtype=np.float64)[:, None]
    c = np.arange(width, dtype=np.float64)[None, :]
    x, y = np.broadcast_to(c * 0.2, (h, width)), np.broadcast_to(r * 0.2, (h, width))
    z = 0.5 * np.sin(x / 40.0) * np.cos(y / 55.0) + rng.normal(0.0, 0.003, (h, width))
    n = h * width // 20000
    rr, cc = rng.integers(0, h, n), rng.integers(0, width, n)
    z[rr, cc] += rng.choice([-1.0, 1.0], n) * rng.uniform(0.1, 1.5, n)
    for _ in range(h * width // 400000):  # spatter domes, 7 cells wide
        a, b = rng.integers(4, h - 4), rng.integers(4, width - 4)
        d2 = (np.arange(-3, 4)[:, None] ** 2 + np.arange(-3, 4)[None, :] ** 2) / 12.0
        z[a - 3:a + 4, b - 3:b + 4] += 0.05 * np.clip(1.0 - d2, 0.0, None)
    g = np.dstack([x, y, z]).astype(np.float32)
    g[rng.random((h, width)) < 0.003] = np.nan
    return g


def scan(rows: int, width: int, chunk: int, seed: int = 0) -> "da.Array":
    parts = [da.from_delayed(delayed(block, pure=True)(r0, min(rows, r0 + chunk), width, seed),
                             (min(rows, r0 + chunk) - r0, width, 3), np.float32)
             for r0 in range(0, rows, chunk)]
    return da.concatenate(parts)


def _status_mb(field: str) -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return float(line.split()[1]) / 1024.0
    raise RuntimeError(f"{field} not in /proc/self/status")


def reset_peak_mb() -> float:
    """The worker's resident memory now, its peak reset to it (Linux: clear_refs 5), so that
    the peak measured afterwards is this run's, not inherited from the process it was forked
    from or from imports (ru_maxrss cannot be reset)."""
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    return _status_mb("VmRSS")


def peak_rss_mb() -> float:
    return _status_mb("VmHWM")


def run(rows: int, width: int, chunk: int, workers: int, preset: str, out_dir: Path) -> dict:
    """One detection of the generated scan on a fresh cluster: labels and heights streamed to
    .npy files, defects joined; wall time and each worker's peak memory."""
    with distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                  dashboard_address=":0", memory_limit="10GiB") as cluster:
        with distributed.Client(cluster) as client:
            client.run(lambda: __import__("miem.dask"))  # imports are not detection time
            base = max(client.run(reset_peak_mb).values())
            grid = scan(rows, width, chunk)
            t0 = time.perf_counter()
            res = mdask.detect(grid, preset=preset)
            labels = NpyWriter(out_dir / "labels.npy", res.labels.shape, np.uint8)
            height = NpyWriter(out_dir / "height.npy", res.height.shape, np.float64)
            defects, _ = res.defects(da.store([res.labels, res.height], [labels, height],
                                              lock=False, compute=False))
            wall = time.perf_counter() - t0
            rss = list(client.run(peak_rss_mb).values())
    return {"wall": wall, "rss": rss, "base": base, "defects": len(defects), "halo": res.halo,
            "points": rows * width}


def exact_part(rows: int, width: int, chunk: int, preset: str) -> tuple:
    """miem.dask on a part of the scan (synchronous) against miem.detect on it, and the time of
    miem.detect on it (one thread and all threads)."""
    grid = scan(rows, width, chunk)
    g = grid.compute()
    t0 = time.perf_counter()
    want = miem.detect(g, preset=preset, num_threads=1)
    t1 = time.perf_counter() - t0
    t0 = time.perf_counter()
    miem.detect(g, preset=preset)
    tall = time.perf_counter() - t0
    with dask.config.set(scheduler="sync"):
        res = mdask.detect(grid, preset=preset)
        defects, labels, height = res.defects(res.labels, res.height)
    same = (np.array_equal(labels, want.labels)
            and np.array_equal(height, want.height, equal_nan=True)
            and [d.indices.tolist() for d in defects] == [d.indices.tolist() for d in want.defects]
            and np.array_equal([d.peak_height for d in defects],
                               [d.peak_height for d in want.defects], equal_nan=True))
    return same, t1, tall, len(want.defects)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=16384)
    ap.add_argument("--width", type=int, default=6144)
    ap.add_argument("--chunk", type=int, default=2048, help="rows per block")
    ap.add_argument("--preset", default="recommended")
    ap.add_argument("--out", type=Path, default=HERE / "results_dask.md")
    a = ap.parse_args()

    tmp = Path(tempfile.mkdtemp(prefix="miem-bench-dask-"))
    load0 = os.getloadavg()[0]
    same, t1, tall, n_def = exact_part(2 * a.chunk, a.width, a.chunk, a.preset)
    part = 2 * a.chunk * a.width
    small = run(2 * a.chunk, a.width, a.chunk, 1, a.preset, tmp)
    one = run(a.rows, a.width, a.chunk, 1, a.preset, tmp)
    two = run(a.rows, a.width, a.chunk, 2, a.preset, tmp)
    load1 = os.getloadavg()[0]
    n = one["points"]
    tp1, tp2 = n / one["wall"], n / two["wall"] / 2
    eff = tp2 / tp1
    chunk_pts = a.chunk * a.width
    halo = one["halo"]
    ext_rows = a.chunk + 2 * (halo + 16) + 64  # an inner block with its halo (and tile slack)
    overhead = ext_rows / a.chunk
    # bytes per point of a block with its halo, above an idle worker (imports)
    per_point = (max(one["rss"]) - one["base"]) * 1e6 / (min(ext_rows, a.rows) * a.width)
    tile_mem = (one["base"] * 1e6 + per_point * (8192 + 2 * (halo + 48)) ** 2) / 1e6

    lines = [
        "# miem.dask: distributed detection (generated by bench/bench_dask.py)",
        "",
        f"Machine: {platform.machine()}, {os.cpu_count()} cores (shared: load average "
        f"{load0:.1f} before, {load1:.1f} after), Python {platform.python_version()}, "
        f"dask {dask.__version__}, distributed {distributed.__version__}. "
        "`distributed.LocalCluster` of worker processes, 1 thread each; "
        f"preset `{a.preset}` (halo {halo} cells); float32 scan generated block by block "
        "(0.2 mm steps, noise, spikes, pits, spatter domes, dropouts); labels and heights "
        "streamed to .npy files with `NpyWriter`, defects joined (`res.defects(...)`).",
        "",
        f"## Scan of {n:.3g} points ({a.rows} x {a.width}), blocks of {a.chunk} whole rows",
        "",
        "| workers | wall (s) | points/s per worker | peak memory per worker (MB) | defects |",
        "|---|---|---|---|---|",
        f"| 1 | {one['wall']:.1f} | {tp1 / 1e6:.2f} M | {max(one['rss']):.0f} | "
        f"{one['defects']} |",
        f"| 2 | {two['wall']:.1f} | {tp2 / 1e6:.2f} M | {max(two['rss']):.0f} | "
        f"{two['defects']} |",
        "",
        f"Scaling 1 -> 2 workers: {eff:.2f} per worker (target >= 0.8; speed-up "
        f"{one['wall'] / two['wall']:.2f} on 2 cores shared with other jobs).",
        "",
        f"Memory follows the block, not the scan: a scan of {small['points']:.3g} points "
        f"(the same blocks) peaks at {max(small['rss']):.0f} MB per worker, the "
        f"{n:.3g}-point scan at {max(one['rss']):.0f} MB. A block is {chunk_pts:.3g} points "
        f"({chunk_pts * 12 / 1e6:.0f} MB of float32 input); with its halo it is "
        f"~{ext_rows} rows ({overhead:.2f}x the work of its own rows); an idle worker holds "
        f"{one['base']:.0f} MB, a detection ~{per_point:.0f} bytes per point of the block "
        "with its halo.",
        "",
        f"Exactness, measured in this run: on {part:.3g} points (2 blocks) miem.dask gives "
        f"labels, heights and defects {'identical to' if same else 'DIFFERENT FROM'} "
        f"`miem.detect` ({n_def} defects). `miem.detect` on those points: "
        f"{part / t1 / 1e6:.2f} M points/s on 1 thread, {part / tall / 1e6:.2f} M points/s on "
        f"all threads; miem.dask with 1 worker: {tp1 / 1e6:.2f} M points/s "
        f"({tp1 / (part / t1):.2f}x one thread of `miem.detect`, the halo overlap and the "
        "file writes included).",
        "",
        "## Paper calculation: a 1e10-point skin",
        "",
        "From the measured throughput per worker and the halo overlap of this run (whole-row "
        "blocks; for a skin 1e5 points wide use square tiles of about 8192 x 8192, whose "
        f"overlap ((8192 + 2 x {halo + 16 + 32}) / 8192)^2 = "
        f"{((8192 + 2 * (halo + 48)) / 8192) ** 2:.2f} is close to this run's "
        f"{overhead:.2f}), scaling as measured ({eff:.2f} per worker) and reading 12 bytes "
        "(float32 x, y, z) and writing 9 bytes (labels, float64 height) per point:",
        "",
        "| workers | time | input read per worker | peak memory per worker |",
        "|---|---|---|---|",
    ]
    for w in (8, 32, 128, 512):
        t = 1e10 / (tp1 * eff * w)
        lines.append(f"| {w} | {t / 3600:.2f} h ({t / 60:.0f} min) | "
                     f"{1e10 * 12 / w / 1e9:.1f} GB | ~{tile_mem / 1024:.1f} GB (8192^2 tile) |")
    lines += [
        "",
        f"One worker alone would take {1e10 / tp1 / 3600:.1f} h. Time is inversely "
        "proportional to the workers while each has whole blocks to do (1e10 points are "
        f"{1e10 / (8192 * 8192):.0f} tiles of 8192^2); the joined defects are a few per block "
        "and are re-detected on their bounding boxes only when they are larger than the "
        "16-cell margin.",
        "",
    ]
    a.out.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
