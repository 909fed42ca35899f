"""Unorganized clouds: miem's normals and detection against Open3D, and accuracy on
held-out-style clouds (issues 3 and 11).

Two modes:

- pytest-benchmark: ``python -m pytest bench/bench_unorganized.py --benchmark-only``
  (``MIEM_BENCH_N`` sets the cloud size, default 1,000,000).
- script: ``python bench/bench_unorganized.py [--n N] [--repeats R]`` prints a markdown table of
  times and ratios and writes it to ``bench/results_unorganized.md`` (``run_results.py`` appends
  that fragment to RESULTS.md), with peak memory measured in fresh subprocesses.

The cloud is scan-like and truly unorganized: a curved sheet from ``miem.simulate.make_scan``
(0.3 mm steps, z noise, spikes, pits, dust, 2x2 clusters), x / y jittered by +-0.075 mm, rows in
random order, dropouts removed (Open3D has no NaN handling). Every contender gets the same array.
The same points in scan order (profile by profile, as a scanner writes them) are timed too:
Open3D's k-d tree queries run several times faster on them (memory locality), miem's hardly
change (its neighbour grid sorts the points), so the ratios are given for both orders. With
the shared data beside the repository (``../shared/data/real``), the real unorganized files are
timed as well, in their file order. Open3D uses every core; miem runs with ``num_threads=2`` (this
machine's cores) for the ratios and is also reported on 1 thread. Open3D's outlier filters are
different methods, shown for scale: what a user would otherwise run on such a cloud.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import cpu_name, interleaved  # noqa: E402


def best_of(fn, repeats: int) -> tuple:
    """(smallest wall time, smallest process CPU time) of `repeats` calls of fn(), seconds. On a
    shared machine the CPU time (every thread of this process) is the steadier measure."""
    return interleaved([fn], repeats)[0]


HERE = Path(__file__).resolve().parent
OUT = HERE / "results_unorganized.md"
#: The shared real scans (absent in a user's clone: their table is then left out).
REAL_DIR = HERE.parents[1] / "shared" / "data" / "real"
#: Real files below this size are left out of the real-cloud table (timings of a few ms).
REAL_MIN_POINTS = 10_000
#: The stage profile of the build before the #11 speed work (main at fbc6d8f with the stage clock
#: added), written by ``--save-profile`` run against that build.
PROFILE_BEFORE = HERE / "results_unorganized_profile_before.json"
DEFAULT_N = 1_000_000
#: The default without the cloud edge test (SPEC "Unorganized clouds: edge test"; on by
#: default since issue 11's third session): its cost and its accuracy gain are measured here.
EDGE_OFF = {"edge_tolerance": None}


def scan_cloud(n: int = DEFAULT_N, seed: int = 1, shuffle: bool = True) -> np.ndarray:
    """About `n` points of a jittered, shuffled curved-sheet scan with defects, float64 (N, 3);
    `shuffle` false: the same points in scan order (row by row)."""
    from miem.simulate import make_scan

    side = max(16, round(float(np.sqrt(n))))
    k = max(1, n // 50_000)
    scan = make_scan(
        (side, side), step=0.3, surface="curved", noise=0.02,
        defects={"spike": k, "pit": k, "dust": max(1, k // 2), "cluster": max(1, k // 2)},
        dropout=0.001, seed=seed,
    )
    rng = np.random.default_rng(seed)
    pts = scan.points.reshape(-1, 3).copy()
    pts[:, :2] += rng.uniform(-0.075, 0.075, (len(pts), 2))
    if shuffle:
        pts = pts[rng.permutation(len(pts))]
    return np.ascontiguousarray(pts[np.isfinite(pts).all(axis=1)])


def _o3d():
    try:
        import open3d as o3d
    except ImportError:  # pragma: no cover - optional
        return None
    return o3d


def _o3d_cloud(o3d, pts: np.ndarray):
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))


def check_normals_parity(pts: np.ndarray, radius: float, o3d) -> float:
    """Median |cos| between miem's and Open3D's normals at the same radius (sign-free)."""
    import miem._unorganized as mu

    ours = mu.estimate_normals(pts, radius)
    pc = _o3d_cloud(o3d, pts)
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamRadius(radius))
    theirs = np.asarray(pc.normals)
    ok = ours.valid
    cos = np.abs(np.einsum("ij,ij->i", ours.normals[ok], theirs[ok]))
    return float(np.median(cos))


# --------------------------------------------------------------------------------------------
# memory: peak RSS growth of one call, in a fresh interpreter

_MEM_CHILD = r"""
import json, sys, numpy as np
import miem, miem._unorganized as mu
def status(key):
    for line in open('/proc/self/status'):
        if line.startswith(key):
            return int(line.split()[1]) * 1024
pts = np.load(sys.argv[1])
what, radius = sys.argv[2], float(sys.argv[3])
if what == 'normals':
    mu.estimate_normals(pts[:1000], radius, num_threads=2)   # warm-up: imports, thread pool
else:
    miem.detect(pts[:1000], num_threads=2)
base = status('VmRSS:')
try:
    open('/proc/self/clear_refs', 'w').write('5')               # reset VmHWM to the current RSS
    reset = True
except OSError:
    reset = False
before_hwm = status('VmHWM:')
res = mu.estimate_normals(pts, radius, num_threads=2) if what == 'normals' else miem.detect(pts, num_threads=2)
peak = status('VmHWM:')
print(json.dumps(dict(base=base, before_hwm=before_hwm, peak=peak, reset=reset)))
"""


def peak_memory(pts: np.ndarray, what: str, radius: float, tmpdir: Path) -> dict:
    """Peak RSS growth (bytes) of one call over the RSS just before it, in a fresh process."""
    path = tmpdir / "miem_bench_cloud.npy"
    np.save(path, pts)
    try:
        out = subprocess.run(
            [sys.executable, "-c", _MEM_CHILD, str(path), what, repr(radius)],
            check=True, capture_output=True, text=True,
        ).stdout
    finally:
        path.unlink(missing_ok=True)
    rec = json.loads(out.strip().splitlines()[-1])
    rec["growth"] = rec["peak"] - (rec["base"] if rec["reset"] else rec["before_hwm"])
    return rec


# --------------------------------------------------------------------------------------------
# script mode


def stage_profile(pts: np.ndarray, repeats: int = 1) -> dict:
    """Where the time of the default ``miem.detect(points)`` goes: per stage, the process CPU
    seconds on 1 thread and the wall seconds on 2 threads (each the run with the least total
    CPU, resp. wall, of `repeats`), from ``PointsDetectResult.stage_seconds``."""
    import miem

    out = {"n": int(len(pts)), "stages": {}}
    for nt, key, idx in ((1, "cpu_1thread", 1), (2, "wall_2threads", 0)):
        best = None
        for _ in range(max(1, repeats)):
            st = miem.detect(pts, num_threads=nt).stage_seconds
            tot = sum(v[idx] for v in st.values())
            if best is None or tot < best[0]:
                best = (tot, st)
        for name, v in best[1].items():
            out["stages"].setdefault(name, {})[key] = float(v[idx])
    return out


def profile_lines(now: dict) -> list[str]:
    """The stage table: before (PROFILE_BEFORE, when present) and now."""
    before = json.loads(PROFILE_BEFORE.read_text()) if PROFILE_BEFORE.exists() else None
    if before is not None and before.get("n") != now["n"]:
        before = None  # another cloud size: not comparable
    lines = [f"### Where the time goes (default detection, {now['n']:,}-point cloud)", "",
             "Per stage of `miem.detect(points)` (`PointsDetectResult.stage_seconds`): process "
             "CPU seconds on 1 thread and wall seconds on 2 threads (shared machine: compare "
             "the CPU column). "
             + ("'before' is main at fbc6d8f (the build before the #11 speed work, with only the "
                f"stage clock added), measured by `--save-profile` on {before['when']} "
                f"(on {before.get('cpu', 'a CPU it did not record')}; now on {cpu_name()})."
                if before else "No 'before' profile of this cloud size "
                "(bench/results_unorganized_profile_before.json, made with the default --n)."), ""]
    names = list(now["stages"])
    if before:
        names += [k for k in before["stages"] if k not in now["stages"]]
        lines += ["| stage | before: CPU s, 1 thread | now: CPU s, 1 thread | now: wall s, "
                  "2 threads |", "|---|---|---|---|"]
    else:
        lines += ["| stage | CPU s, 1 thread | wall s, 2 threads |", "|---|---|---|"]

    def cell(d: dict, name: str, key: str) -> str:
        v = d["stages"].get(name, {}).get(key)
        return "-" if v is None else f"{v:.2f}"

    for name in names:
        row = [name] + ([cell(before, name, "cpu_1thread")] if before else [])
        row += [cell(now, name, "cpu_1thread"), cell(now, name, "wall_2threads")]
        lines.append("| " + " | ".join(row) + " |")
    tot = ["**total**"]
    for d, key in ([(before, "cpu_1thread")] if before else []) + [(now, "cpu_1thread"),
                                                                   (now, "wall_2threads")]:
        tot.append(f"**{sum(v.get(key, 0.0) for v in d['stages'].values()):.2f}**")
    lines += ["| " + " | ".join(tot) + " |", ""]
    return lines


def uneven_cloud(pts: np.ndarray, seed: int = 2) -> np.ndarray:
    """The cloud thinned unevenly: a point at relative x position u in [0, 1] is kept with
    probability 0.25 + 0.75 u (density varies 4x across the part)."""
    rng = np.random.default_rng(seed)
    x = pts[:, 0]
    u = (x - x.min()) / max(float(np.ptp(x)), 1e-300)
    return np.ascontiguousarray(pts[rng.random(len(pts)) < 0.25 + 0.75 * u])


def real_lines(o3d, repeats: int) -> list[str]:
    """miem's default detection against Open3D's statistical outlier removal on the real files
    of REAL_DIR (file order; organized files as grids for miem, their finite points for
    Open3D), with the neighbourhood sizes that set a cloud's cost. Empty without the data."""
    import miem
    import miem._unorganized as mu
    import miem.io as mio

    files = sorted(REAL_DIR.glob("*.pcd")) if REAL_DIR.is_dir() else []
    rows = []
    for f in files:
        data = np.asarray(mio.read(f).points, dtype=np.float64)
        flat = data.reshape(-1, 3)
        finite = np.ascontiguousarray(flat[np.isfinite(flat).all(axis=1)])
        if len(finite) < REAL_MIN_POINTS:
            continue
        grid = data.ndim == 3
        arg = data if grid else finite
        with warnings.catch_warnings():  # a profiler export read as points: advice, not data
            warnings.simplefilter("ignore", UserWarning)
            res = miem.detect(arg, num_threads=2)
            t_m, _ = best_of(lambda: miem.detect(arg, num_threads=2), repeats)
        pc = _o3d_cloud(o3d, finite)
        t_o, _ = best_of(lambda: pc.remove_statistical_outlier(20, 2.0), repeats)
        ball = "" if grid else mu.estimate_normals(finite, res.params["radius"]).count
        t_cli = None if grid else rebuilt_detect(finite, repeats)  # None: as miem detect
        rows.append((f.name, len(finite), "grid" if grid else "cloud", ball, t_m, t_o, t_cli))
    if not rows:
        return []
    lines = ["### Real files (file order)", "",
             f"The real scans of `shared/data/real` with at least {REAL_MIN_POINTS:,} finite "
             "points, as a user loads them (`miem.io.read`): `miem.detect` with the defaults "
             "(2 threads; an organized file as its grid) against Open3D's "
             "`remove_statistical_outlier(20, 2.0)` (all cores) on the same finite points, best "
             f"of {repeats}. A cloud's cost grows with the points in its balls (radius 5 x "
             "spacing, the height and edge tests twice that): 'points per ball' is the count at "
             "`radius`, mean and largest. 'miem detect FILE' is what the command line runs, and "
             "`miem.detect(points, layout=\"auto\")`: the grid rebuilt from the scan lines "
             "where the points lie on them (`miem.io.grid_from_scanlines`; rebuild and grid "
             "detection timed together), else the cloud detector.", "",
             "| file | points | miem path | points per ball: mean / max | miem detect (s) | "
             "Open3D SOR (s) | SOR / miem | miem detect FILE (s) | SOR / that |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, npts, path, ball, t_m, t_o, t_cli in rows:
        b = "" if isinstance(ball, str) else f"{ball.mean():.0f} / {ball.max():,}"
        cli = ("the same", "") if t_cli is None else (f"{t_cli:.3f} (grid rebuilt)",
                                                      f"{t_o / t_cli:.2f}x")
        lines.append(f"| {name} | {npts:,} | {path} | {b} | {t_m:.3f} | {t_o:.3f} | "
                     f"{t_o / t_m:.2f}x | {cli[0]} | {cli[1]} |")
    ratios = [t_o / t_m for *_, t_m, t_o, _ in rows]
    lines += ["", f"SOR / miem over these files: median {np.median(ratios):.2f}x, range "
              f"{min(ratios):.2f}x - {max(ratios):.2f}x.", ""]
    return lines


def rebuilt_detect(points: np.ndarray, repeats: int) -> float | None:
    """Seconds for ``miem.detect(points, layout="auto")`` (2 threads) on an unorganized file
    whose points lie on scan lines: the grid rebuilt (as `miem detect FILE` does) and detected;
    None when the points give no grid (then it runs the cloud detector, as the command line)."""
    import miem
    from miem._layout import rebuild

    if rebuild(points, "auto") is None:  # (the check that detect makes first)
        return None
    return best_of(lambda: miem.detect(points, layout="auto", num_threads=2), repeats)[0]


def accuracy_lines() -> list[str]:
    """Held-out-style clouds (bench/accuracy/clouds.py): F1 per defect kind, both splits, with
    the user's defaults (``miem.detect(points)``) and ``preset="recommended"``."""
    import miem

    sys.path.insert(0, str(HERE / "accuracy"))
    from clouds import clouds
    from score import Counts, confusion
    from suite import KINDS

    presets = [None] if miem.DEFAULT_PRESET == "recommended" else [None, "recommended"]
    presets.append(EDGE_OFF)  # the default without the edge test
    lines = ["### Accuracy on held-out-style clouds", "",
             "The accuracy suite's synthetic and paper scenes (bench/accuracy/suite.py) as "
             "clouds: dropouts removed, x / y jittered uniformly by up to a quarter step, rows "
             "shuffled (bench/accuracy/clouds.py). The cloud values of the presets were chosen "
             "on the tune split; the test split differs in seeds, surfaces, noise and steps. "
             "F1 of the defect class per focus kind (target: >= 0.95 for every kind).", ""]
    splits = {split: list(clouds(split)) for split in ("tune", "test")}
    groups = {c.scene.spec.group for cl in splits.values() for c in cl}
    kinds = [k for k in KINDS if k in groups] + sorted(groups - set(KINDS))
    head = "| split | settings | all | " + " | ".join(kinds) + " |"
    lines += [head, "|" + "---|" * (3 + len(kinds))]
    verdict = []
    for split, cl in splits.items():
        for preset in presets:
            per: dict[str, list] = {}
            for c in cl:
                kw = ({} if preset is None else dict(preset) if isinstance(preset, dict)
                      else {"preset": preset})
                res = miem.detect(c.points, **kw)
                per.setdefault(c.scene.spec.group, []).append(
                    confusion(res.labels == miem.ABNORMAL, c.truth))
            tot = {k: Counts.total(v) for k, v in per.items()}
            allc = Counts.total(tot.values())
            name = (f"default (preset {miem.DEFAULT_PRESET!r})" if preset is None
                    else "default + " + ", ".join(f"{k}={v}" for k, v in preset.items())
                    if isinstance(preset, dict) else f"preset {preset!r}")
            cells = [f"{tot[k].f1:.2f}" if k in tot else "-" for k in kinds]
            lines.append(f"| {split} | {name} | {allc.f1:.3f} | " + " | ".join(cells) + " |")
            if split == "test":
                low = [k for k in kinds if k in tot and not tot[k].f1 >= 0.95]
                verdict.append(f"{name}: " + ("every kind >= 0.95" if not low else
                                              "below 0.95: " + ", ".join(low)))
    lines += ["", "Test split: " + "; ".join(verdict) + ".", ""]
    return lines


def run(n: int, repeats: int, accuracy: bool = True) -> str:
    import miem
    import miem._unorganized as mu

    pts = scan_cloud(n)
    scan = scan_cloud(n, shuffle=False)  # the same points in scan order
    n = len(pts)
    uneven = uneven_cloud(pts)
    spacing = mu.point_spacing(pts)
    res = miem.detect(pts, num_threads=2)  # the user's defaults
    radius = res.params["radius"]
    preset = res.params.get("preset", miem.DEFAULT_PRESET)
    o3d = _o3d()
    rows: list[tuple[str, str, float, float]] = []
    cpu: dict[str, float] = {}

    def add(contender: str, op: str, fn, reps: int = repeats) -> float:
        t, c = best_of(fn, reps)
        rows.append((contender, op, t, c))
        cpu[f"{contender}|{op}"] = c
        return t

    def add_threads(op: str, fn) -> tuple[float, float]:
        # A thread speed-up is a ratio of two timings: fn(1) and fn(2) measured alternately,
        # best of 2 x repeats each, so a burst of load on the shared machine hits both alike.
        pair = interleaved([lambda nt=nt: fn(nt) for nt in (1, 2)], 2 * repeats)
        for nt, (t, c) in zip((1, 2), pair):
            rows.append((f"miem, {nt} thread" + ("s" if nt > 1 else ""), op, t, c))
            cpu[f"{rows[-1][0]}|{op}"] = c
        return pair[0][0], pair[1][0]

    t_n1, t_n2 = add_threads("estimate_normals(radius)",
                             lambda nt: mu.estimate_normals(pts, radius, num_threads=nt))
    t_d1, t_d2 = add_threads(f"detect(points) (defaults: preset {preset!r})",
                             lambda nt: miem.detect(pts, num_threads=nt))
    if preset != "recommended":
        add("miem, 2 threads", "detect(points, preset='recommended')",
            lambda: miem.detect(pts, preset="recommended", num_threads=2))
    t_d2s = add("miem, 2 threads", "detect(points), the same cloud in scan order",
                lambda: miem.detect(scan, num_threads=2))
    t_n2s = add("miem, 2 threads", "estimate_normals(radius), the same cloud in scan order",
                lambda: mu.estimate_normals(scan, radius, num_threads=2))
    add("miem, 2 threads", f"detect(points), uneven density ({len(uneven):,} points)",
        lambda: miem.detect(uneven, num_threads=2))
    add("miem, 1 thread", "detect(points, edge_tolerance=None) (the default without "
               "the cloud edge test)", lambda: miem.detect(pts, num_threads=1, **EDGE_OFF))
    t_e2 = add("miem, 2 threads", "detect(points, edge_tolerance=None) (the default without "
               "the cloud edge test)", lambda: miem.detect(pts, num_threads=2, **EDGE_OFF))
    parity = None
    t_on = t_os = t_or = t_ons = t_oss = None
    if o3d is not None:
        parity = check_normals_parity(pts, radius, o3d)
        o3d_reps = max(1, min(repeats, 2))

        def o3d_normals() -> None:
            pc = _o3d_cloud(o3d, pts)
            pc.estimate_normals(o3d.geometry.KDTreeSearchParamRadius(radius))

        pc_in = _o3d_cloud(o3d, pts)
        t_on = add("Open3D (all cores)", "estimate_normals (same radius)", o3d_normals, o3d_reps)
        t_os = add("Open3D (all cores)", "remove_statistical_outlier(20, 2.0)",
                   lambda: pc_in.remove_statistical_outlier(20, 2.0), o3d_reps)
        t_or = add("Open3D (all cores)", "remove_radius_outlier(3, radius)",
                   lambda: pc_in.remove_radius_outlier(3, radius), o3d_reps)
        _, kept = pc_in.remove_statistical_outlier(20, 2.0)
        o3d_removed = n - len(kept)
        pc_scan = _o3d_cloud(o3d, scan)

        def o3d_normals_scan() -> None:
            pc = _o3d_cloud(o3d, scan)
            pc.estimate_normals(o3d.geometry.KDTreeSearchParamRadius(radius))

        t_ons = add("Open3D (all cores)", "estimate_normals (same radius), the same cloud in scan "
                    "order", o3d_normals_scan, o3d_reps)
        t_oss = add("Open3D (all cores)", "remove_statistical_outlier(20, 2.0), the same cloud "
                    "in scan order", lambda: pc_scan.remove_statistical_outlier(20, 2.0), o3d_reps)

    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        mem_n = peak_memory(pts, "normals", radius, Path(tmp))
        mem_d = peak_memory(pts, "detect", radius, Path(tmp))
    in_bytes = pts.nbytes

    def mb(b: float) -> str:
        return f"{b / 2**20:.0f} MB"

    def met(ok: bool) -> str:
        return "met" if ok else "NOT met"

    header = (
        f"Cloud: {n:,} points, curved sheet scan (0.3 mm steps, x / y jittered by +-0.075 mm, "
        f"rows shuffled; also in scan order where it says so), float64; spacing {spacing:.4f} mm. "
        "Every call uses the defaults a "
        f"user gets: `miem.detect(points)` (preset {preset!r}: radius 5 x spacing = "
        f"{radius:.4f} mm, ~{np.mean(mu.estimate_normals(pts, radius).count):.0f} points per "
        "neighbourhood), normals at that radius for both libraries. "
        f"{cpu_name()}, {os.cpu_count()} cores, shared machine "
        f"(load average {os.getloadavg()[0]:.1f} at the start): read ratios, not seconds. Best "
        f"of {repeats} (miem's normals and its default detect on the shuffled cloud: best of "
        f"{2 * repeats}, 1 and 2 threads alternated; "
        f"Open3D: best of {max(1, min(repeats, 2))})."
    )
    lines = ["## Unorganized clouds (issues 3 and 11)", "", header, "",
             "| contender | operation | time (s) | process CPU (s) |", "|---|---|---|---|"]
    lines += [f"| {c} | {op} | {t:.3f} | {ct:.3f} |" for c, op, t, ct in rows]
    lines += ["", "| ratio | value | target |", "|---|---|---|"]
    lines.append(f"| miem 2 threads normals speed-up over 1 thread | {t_n1 / t_n2:.2f}x | "
                 f">= 1.7: {met(t_n1 / t_n2 >= 1.7)} |")
    lines.append(f"| miem 2 threads detect speed-up over 1 thread | {t_d1 / t_d2:.2f}x | "
                 f">= 1.7: {met(t_d1 / t_d2 >= 1.7)} |")
    if t_on is not None:
        lines.append(f"| Open3D estimate_normals / miem estimate_normals (2 threads), shuffled | "
                     f"{t_on / t_n2:.1f}x | >= 3x: {met(t_on / t_n2 >= 3)} |")
        lines.append(f"| the same, cloud in scan order | {t_ons / t_n2s:.1f}x | "
                     f">= 3x: {met(t_ons / t_n2s >= 3)} |")
        lines.append(f"| Open3D statistical outlier removal / miem detect (2 threads), shuffled | "
                     f"{t_os / t_d2:.2f}x | >= 2x: {met(t_os / t_d2 >= 2)} |")
        lines.append(f"| the same, cloud in scan order | {t_oss / t_d2s:.2f}x | "
                     f">= 2x: {met(t_oss / t_d2s >= 2)} |")
        lines.append(f"| Open3D radius outlier removal / miem detect (2 threads) | "
                     f"{t_or / t_d2:.2f}x | |")
        c_os = cpu["Open3D (all cores)|remove_statistical_outlier(20, 2.0)"]
        c_d1 = cpu[f"miem, 1 thread|detect(points) (defaults: preset {preset!r})"]
        lines.append(f"| process CPU: Open3D statistical outlier removal (all cores) / miem detect "
                     f"(1 thread) | {c_os / c_d1:.2f}x | (the load-independent view) |")
        lines.append(f"| normals parity: median abs(cos) miem vs Open3D | {parity:.9f} | ~1 |")
    c_e1 = cpu["miem, 1 thread|detect(points, edge_tolerance=None) (the default without the "
               "cloud edge test)"]
    c_d1 = cpu[f"miem, 1 thread|detect(points) (defaults: preset {preset!r})"]
    lines.append(f"| speed cost of the cloud edge test: default detect / without it (1 thread, "
                 f"process CPU; 2 threads, wall) | {c_d1 / c_e1:.2f}x; {t_d2 / t_e2:.2f}x | |")
    for op, mem in (("estimate_normals", mem_n), ("detect", mem_d)):
        ratio = mem["growth"] / in_bytes
        lines.append(f"| peak memory growth, {op} (outputs included) | {mb(mem['growth'])} = "
                     f"{ratio:.2f} x input ({mb(in_bytes)}) | < 3 x input: {met(ratio < 3)} |")
    counts = np.bincount(res.labels, minlength=4)
    summary = (f"miem detect (defaults): {counts[1]:,} ABNORMAL, {counts[2]:,} EDGE, "
               f"{len(res.defects)} defects, {res.iterations} passes")
    if o3d is not None:
        summary += f"; Open3D statistical filter removed {o3d_removed:,} points."
    else:
        summary += ". Open3D not installed: its rows are missing."
    lines += ["", summary, "Memory: VmHWM growth over the RSS before the call, in a fresh "
              "process.", ""]
    lines += profile_lines(stage_profile(pts, repeats))
    if o3d is not None:
        lines += real_lines(o3d, max(1, min(repeats, 2)))
    if accuracy:
        lines += accuracy_lines()
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=DEFAULT_N, help="cloud size (default 1e6)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--no-accuracy", action="store_true", help="skip the held-out-style clouds")
    ap.add_argument("--save-profile", type=Path, metavar="JSON",
                    help="only write the stage profile of the importable miem to JSON (how "
                    f"{PROFILE_BEFORE.name} was made, against the earlier build)")
    args = ap.parse_args(argv)
    if args.save_profile:
        import time

        prof = stage_profile(scan_cloud(args.n), args.repeats)
        prof["when"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
        prof["cpu"] = cpu_name()
        args.save_profile.write_text(json.dumps(prof, indent=1) + "\n")
        print(json.dumps(prof, indent=1))
        return 0
    text = run(args.n, args.repeats, not args.no_accuracy)
    print(text)
    args.out.write_text(text)
    return 0


# --------------------------------------------------------------------------------------------
# pytest-benchmark mode

try:
    import pytest
except ImportError:  # pragma: no cover
    pytest = None

if pytest is not None:
    BENCH_N = int(os.environ.get("MIEM_BENCH_N", DEFAULT_N))

    @pytest.fixture(scope="module")
    def cloud():
        import miem._unorganized as mu

        pts = scan_cloud(BENCH_N)
        return pts, 3.0 * mu.point_spacing(pts)

    @pytest.mark.parametrize("threads", [1, 2])
    def test_miem_estimate_normals(benchmark, cloud, threads):
        import miem._unorganized as mu

        pts, radius = cloud
        res = benchmark.pedantic(
            mu.estimate_normals, args=(pts, radius), kwargs={"num_threads": threads}, rounds=3
        )
        assert res.valid.mean() > 0.99

    @pytest.mark.parametrize("threads", [1, 2])
    def test_miem_detect(benchmark, cloud, threads):
        import miem._unorganized as mu

        pts, _ = cloud
        res = benchmark.pedantic(
            mu.detect_points, args=(pts,), kwargs={"num_threads": threads}, rounds=3
        )
        assert (res.labels == 1).mean() < 0.01

    def test_open3d_estimate_normals(benchmark, cloud):
        o3d = pytest.importorskip("open3d")
        pts, radius = cloud
        assert check_normals_parity(pts, radius, o3d) > 0.999

        def run_o3d():
            pc = _o3d_cloud(o3d, pts)
            pc.estimate_normals(o3d.geometry.KDTreeSearchParamRadius(radius))

        benchmark.pedantic(run_o3d, rounds=2)

    def test_open3d_statistical_outlier(benchmark, cloud):
        o3d = pytest.importorskip("open3d")
        pc = _o3d_cloud(o3d, cloud[0])
        benchmark.pedantic(pc.remove_statistical_outlier, args=(20, 2.0), rounds=2)

    def test_open3d_radius_outlier(benchmark, cloud):
        o3d = pytest.importorskip("open3d")
        pc = _o3d_cloud(o3d, cloud[0])
        benchmark.pedantic(pc.remove_radius_outlier, args=(3, cloud[1]), rounds=2)


if __name__ == "__main__":
    sys.exit(main())
