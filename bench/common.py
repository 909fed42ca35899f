"""Inputs shared by the benchmark suites and the results script (seeded, reproducible)."""

from __future__ import annotations

import platform
import time
from pathlib import Path

import numpy as np


def best_of(fn, repeats: int) -> float:
    """Smallest wall time of `repeats` calls of fn(), seconds."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def interleaved(fns: list, repeats: int) -> list[tuple]:
    """best_of for each of fns, their calls alternated (fns[0], fns[1], fns[0], ...)."""
    walls: list[list[float]] = [[] for _ in fns]
    cpus: list[list[float]] = [[] for _ in fns]
    for _ in range(max(1, repeats)):
        for i, fn in enumerate(fns):
            c0, t0 = time.process_time(), time.perf_counter()
            fn()
            walls[i].append(time.perf_counter() - t0)
            cpus[i].append(time.process_time() - c0)
    return [(min(w), min(c)) for w, c in zip(walls, cpus)]


def cpu_name() -> str:
    """The CPU model from /proc/cpuinfo (or platform's guess) and the widest vector unit miem's
    kernels can use on it (the core carries AVX2 and AVX-512 clones: timings taken on machines
    with different units do not compare)."""
    model, flags = "", set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name") and not model:
                model = line.split(":", 1)[1].strip()
            elif line.startswith("flags") and not flags:
                flags = set(line.split(":", 1)[1].split())
    except OSError:
        pass
    model = model or platform.processor() or "unknown"
    if not flags:
        return model
    simd = ("AVX-512" if "avx512f" in flags
            else "AVX2, no AVX-512" if "avx2" in flags else "no AVX2")
    return f"{model} ({simd})"


def scan_grid(h: int, w: int, seed: int = 0, n_defects: int = 200) -> np.ndarray:
    """A laser-scan-like organized grid: 0.2 mm steps, a gentle bump, 2 um noise, spikes, pits,
    2x2 clusters and 0.5% dropouts."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    x, y = xx * 0.2, yy * 0.2
    z = 0.4 * np.exp(-((x - 0.1 * w) ** 2) / 5000.0) + 0.01 * y / max(h, 1)
    z = z + rng.normal(0.0, 0.002, z.shape)
    grid = np.dstack([x, y, z])
    flat = grid.reshape(-1, 3)
    idx = rng.choice(h * w, size=min(n_defects, h * w // 10), replace=False)
    flat[idx, 2] += rng.choice([-1.0, 1.0], idx.size) * rng.uniform(0.5, 3.0, idx.size)
    flat[rng.random(h * w) < 0.005] = np.nan
    return grid


def plane_points(n: int, seed: int = 0) -> np.ndarray:
    """n points near a tilted plane far from the origin (robot base frame)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-50.0, 50.0, size=(n, 2))
    z = 0.1 * xy[:, 0] - 0.05 * xy[:, 1] + rng.normal(0.0, 0.01, n)
    return np.column_stack([xy, z]) + np.array([1200.0, -300.0, 450.0])
