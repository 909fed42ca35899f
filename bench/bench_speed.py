"""Speed of the default detector (issue 17): what a user compares first.

Usage: ``python bench/bench_speed.py [--quick] [--build-dir DIR]`` writes
``bench/results_speed.md`` (``run_results.py`` puts it at the top of RESULTS.md) and
``bench/results_speed.json``. Every ratio in it is measured in this one run: earlier builds are
rebuilt from their commits (``git archive``), never read from a file recorded on another machine.

Sections, all measured in this one run:

* miem's default preset (``"recommended"``) against Open3D on the same cloud (the scan grid's
  finite points); PCL where ``bench/run_cpp.py`` found it (``results_cpp.md``).
* Size sweep: organized grids 256^2 .. 4096^2 (1 and 2 threads) and ``fit_plane`` on 1e5 .. 1e7
  points against a NumPy read of the same array: how the cost grows.
* Peak memory of ``detect`` in a fresh process against the input grid.
* With min_step on: the default on a synthetic laser-profiler scan and on the real scan
  ``second_source.pcd`` (when ``../shared`` is present), where ``min_step="auto"`` resolves to a
  length; today's ``miem_bench_stages`` against the commit before the vectorised min_step search.
* Surfaces: the default on 512^2 scans of every ``make_scan`` surface at two noise levels
  (``miem_bench_stages``, one thread): what a part's shape costs, stage by stage.
* Dropouts: the default on the benchmark scan with 0-20 % random dropouts added, today's build
  and ``DROPOUT_BASE``'s (before the quiet rule counted per half sub-window and pass 1 searched
  on to s + 1 a whole word at once).
* Memory layouts: the default on one scan in C order, as coordinate planes, in Fortran order
  and as float32 (the caller's array is read in place).
* Where the time goes: each C++ stage timed alone (``miem_bench_stages``, CPU time, one thread),
  and the stage costs by configuration differences through the Python API (comparable across
  versions: angle test only; + heights at every point; + the height test).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
from common import best_of, cpu_name, interleaved, plane_points, scan_grid  # noqa: E402

OUT = HERE / "results_speed.md"
RAW = HERE / "results_speed.json"
PRESET = "recommended"  # the default preset (issue 9)


def cpu_time(fn, repeats: int) -> float:
    """Smallest process CPU time of `repeats` single-threaded calls (a shared machine steals wall
    time, not CPU time)."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
    return best


def breakdown(side: int, repeats: int) -> dict:
    """Stage costs at side x side, 1 thread, by configuration differences (CPU time)."""
    import miem

    grid = scan_grid(side, side)
    off = dict(preset=PRESET, edge_tolerance=None)
    cfg = {
        "angle": dict(off, height_tolerance=None, heights="abnormal"),
        "angle+heights": dict(off, height_tolerance=None),
        "angle+heights+ht": off,
        "full": dict(preset=PRESET),
    }
    t = {k: cpu_time(lambda kw=kw: miem.detect(grid, num_threads=1, **kw), repeats)
         for k, kw in cfg.items()}
    return {"side": side, "miem": miem.__version__, "angle": t["angle"],
            "heights": t["angle+heights"] - t["angle"],
            "height_test": t["angle+heights+ht"] - t["angle+heights"],
            "edge_test": t["full"] - t["angle+heights+ht"], "full": t["full"]}


def lead(side: int, repeats: int) -> list[dict]:
    """miem default against Open3D on the same points."""
    import miem

    grid = scan_grid(side, side)
    pts = grid.reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    n = grid.shape[0] * grid.shape[1]
    rows = []
    for nt in (1, 2):
        t = best_of(lambda: miem.detect(grid, preset=PRESET, num_threads=nt), repeats)
        res = miem.detect(grid, preset=PRESET, num_threads=nt)
        rows.append({"who": f"miem `detect` (default preset), {nt} thread(s)", "t": t,
                     "flagged": int(res.abnormal.sum()), "mpts": n / t / 1e6})
    try:
        import open3d as o3d
    except ImportError:
        return rows
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    r = 3 * 0.2  # three grid steps
    jobs = [
        ("Open3D `remove_statistical_outlier(20, 2.0)` (all cores)",
         lambda: pcd.remove_statistical_outlier(20, 2.0)),
        (f"Open3D `remove_radius_outlier(8, {r:.1f})` (all cores)",
         lambda: pcd.remove_radius_outlier(8, r)),
        ("Open3D `estimate_normals(KNN 20)` (all cores)",
         lambda: pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))),
    ]
    for who, fn in jobs:
        t = best_of(fn, max(1, repeats - 1))
        out = fn()
        flagged = len(pts) - len(out[1]) if isinstance(out, tuple) else None
        rows.append({"who": who, "t": t, "flagged": flagged, "mpts": n / t / 1e6})
    return rows


def layout_times(side: int, repeats: int) -> list[dict]:
    """The default on the same scan in the memory layouts a user hands over (CPU time, 1
    thread): C order (H, W, 3), a view of (3, H, W) coordinate planes, Fortran order, float32."""
    import miem

    grid = scan_grid(side, side)
    planes = np.moveaxis(np.ascontiguousarray(np.moveaxis(grid, -1, 0)), 0, -1)
    layouts = [("C order (H, W, 3), float64", grid),
               ("coordinate planes: a (3, H, W) array's view", planes),
               ("Fortran order (np.asfortranarray)", np.asfortranarray(grid)),
               ("C order, float32", grid.astype(np.float32))]
    ref = miem.detect(grid, num_threads=1).labels
    rows = []
    for who, g in layouts:
        t = cpu_time(lambda g=g: miem.detect(g, num_threads=1), repeats)
        same = bool(np.array_equal(miem.detect(g, num_threads=1).labels, ref))
        rows.append({"who": who, "strides": list(g.strides), "t": t, "same_labels": same})
    return rows


def fmt_layouts(rows: list[dict], side: int) -> list[str]:
    if not rows:
        return []
    base = rows[0]["t"]
    L = ["", f"### Memory layouts ({side}x{side}, default preset, 1 thread, CPU time)", "",
         "`miem.detect` reads the caller's array in place, except a column-major grid "
         "(Fortran order: its row neighbours lie a column apart), which it copies into C "
         "order once (the copy is in its time). "
         "Float32 labels may differ from float64 in a few cells near a threshold (SPEC "
         "\"Numbers\").", "",
         "| layout | strides (bytes) | CPU ms | / C order | labels as C order float64 |",
         "|---|---|---:|---:|---|"]
    for r in rows:
        L.append(f"| {r['who']} | {tuple(r['strides'])} | {r['t'] * 1e3:.0f} | "
                 f"{r['t'] / base:.2f}x | {'same' if r['same_labels'] else 'differ'} |")
    return L


def pcl_rows(build_dir: Path, side: int, repeats: int) -> list[dict]:
    """PCL's counterparts of the Open3D jobs of :func:`lead` on the same scan (its finite points,
    one thread): ``miem_bench_pcl --grid``, built here where PCL is installed; [] without it."""
    if build_stages(ROOT, build_dir) is None:
        return []
    done = subprocess.run(["cmake", "--build", str(build_dir), "-j", "2", "--target",
                           "miem_bench_pcl"], capture_output=True, text=True)
    binary = build_dir / "bench" / "miem_bench_pcl"
    if done.returncode != 0 or not binary.exists():
        return []
    grid_file = build_dir / f"lead_{side}.f64"
    np.ascontiguousarray(scan_grid(side, side), dtype=np.float64).tofile(grid_file)
    out = subprocess.run([str(binary), "--grid", str(grid_file), str(side), str(side),
                          "--repeats", str(repeats)], capture_output=True, text=True, check=True)
    n = side * side
    return [{"who": r["method"], "t": r["median_ms"] / 1e3, "mpts": n / r["median_ms"] / 1e3,
             "flagged": None if r["flagged"] < 0 else int(r["flagged"])}
            for r in json.loads(out.stdout)]


#: The size sweep's defect density: the lead scan's (200 defects in 2048^2 points) at every size,
#: so that the cost per point compares scans of one kind (a fixed 200 made 256^2 64x as dense
#: in defects as 2048^2, and each defect brings its own edge-test and height work).
SWEEP_DEFECTS_PER_POINT = 200 / 2048**2


def sweep_defects(n: int) -> int:
    """The defects injected into a sweep grid of n points (at least 1)."""
    return max(1, round(SWEEP_DEFECTS_PER_POINT * n))


def sweep(sides: list[int], repeats: int) -> list[dict]:
    import miem

    rows = []
    for side in sides:
        n = side * side
        grid = scan_grid(side, side, n_defects=sweep_defects(n))
        reps = repeats if side < 4096 else max(1, repeats - 1)
        # CPU time in a block of 1-thread calls of its own: after a 2-thread call the idle
        # OpenMP worker spins on, and its CPU time would count in the next 1-thread call
        t1 = cpu_time(lambda: miem.detect(grid, preset=PRESET, num_threads=1), reps)
        # the speed-up is a ratio: its two timings alternate, so a burst of load on the shared
        # machine hits both alike; two more rounds than the CPU timing, as a 2-thread call's
        # fresh output pages (first touched in parallel) vary most from run to run
        (w1, _), (w2, _) = interleaved([lambda nt=nt: miem.detect(grid, preset=PRESET,
                                                                  num_threads=nt)
                                        for nt in (1, 2)], reps + 2)
        rows.append({"side": side, "n": n, "cpu1": t1, "wall1": w1, "wall2": w2})
        del grid
    return rows


def fit_sweep(sizes: list[int], repeats: int) -> list[dict]:
    import miem

    rows = []
    for n in sizes:
        pts = plane_points(n)
        t = best_of(lambda: miem.fit_plane(pts, num_threads=1), repeats)
        t_sum = best_of(lambda: pts.sum(axis=0), repeats)
        rows.append({"n": n, "t": t, "gbs": pts.nbytes / t / 1e9, "sum_gbs": pts.nbytes / t_sum / 1e9})
    return rows


_MEM_CHILD = textwrap.dedent("""
    import sys, json
    sys.path.insert(0, {here!r})
    import numpy as np, miem
    from common import scan_grid
    def hwm():
        for line in open('/proc/self/status'):
            if line.startswith('VmHWM'):
                return int(line.split()[1]) * 1024
    def rss():
        for line in open('/proc/self/status'):
            if line.startswith('VmRSS'):
                return int(line.split()[1]) * 1024
    grid = scan_grid({side}, {side})
    miem.detect(scan_grid(64, 64), preset={preset!r})  # load everything first
    # Reset the high-water mark to the current RSS (Linux >= 4.0), then measure the call.
    open('/proc/self/clear_refs', 'w').write('5')
    before = rss()
    res = miem.detect(grid, preset={preset!r}, num_threads=1)
    out = sum(a.nbytes for a in (res.labels, res.flags, res.angle, res.height))
    print(json.dumps({{"grid": grid.nbytes, "growth": hwm() - before, "outputs": out}}))
""")


def memory(side: int) -> dict | None:
    code = _MEM_CHILD.format(here=str(HERE), side=side, preset=PRESET)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    if proc.returncode != 0:
        return None
    return json.loads(proc.stdout.strip().splitlines()[-1])


STAGES = ("min_step_auto", "angle_passes", "height_test", "edge_test", "miem_plane", "heights",
          "defects")
# Earlier commits timed in the same run (C++ stages, 1 thread): (commit, what it is, preset the
# old binary runs, preset the current binary runs for the same configuration).
BASES = [
    ("fbc6d8f", "the default before issue 10 (no edge test, no min_step 'auto')", "recommended",
     "recommended-no-edge"),
    ("67252b8", "2026-12-02, before the min_step row kernel, the fin rule and the "
     "edge test's branch-free judge", "recommended", "recommended"),
    ("cd0cfef", "2026-12-02, before the vectorised window sums, the masked MIEM-plane "
     "moments and the min_step row skip", "recommended", "recommended"),
    ("c5b2e81", "2026-12-05, before the edge test's quiet cells", "recommended", "recommended"),
    ("9503cd4", "2026-12-05, before the quiet cells from the height test's planes",
     "recommended", "recommended"),
    ("ed7b889", "2026-12-05, before the finiteness pass fused into pass 1 (and the edge "
     "test's attached condition)", "recommended", "recommended"),
    ("c212da6", "2026-12-06, before quiet cells count removed cells as missing ones",
     "recommended", "recommended"),
    ("a2bad9d", "2026-12-07, before pass 1 took its rest lanes from packed usable bits and "
     "loaded its rows in vector code",
     "recommended", "recommended"),
    ("cdeec00", "2026-12-07, before the edge images' row loads in vector code and the "
     "masked window planes", "recommended", "recommended"),
    ("1d3f0ed", "2026-12-07, before box_sums' three chains side by side and the height "
     "verdicts without masked loads", "recommended", "recommended"),
    ("e46544c", "2026-12-07, before the fused AVX-512 pass-1 kernel, the MIEM plane's lane "
     "sums and pass 1's finiteness and row loads in AVX-512", "recommended", "recommended"),
    ("5c0cd2e", "2026-12-07, before the window fits found each tile's wanted cells band by "
     "band", "recommended", "recommended"),
    ("4f7d1ea", "2026-12-07, before min_step / z_resolution 'auto' selected their medians "
     "through bit-pattern histograms and loaded their rows in AVX-512", "recommended",
     "recommended"),
    ("760e4da", "2026-12-07, before the edge test's quiet cells at the grid border and by "
     "the height test's last planes", "recommended", "recommended"),
]


def build_stages(src: Path, build_dir: Path) -> Path | None:
    """Configure and build miem_bench_stages of the tree `src` in `build_dir`."""
    cmd = ["cmake", "-S", str(src), "-B", str(build_dir), "-DCMAKE_BUILD_TYPE=Release",
           "-DMIEM_BUILD_BENCH=ON"]
    if shutil.which("ninja") and not (build_dir / "CMakeCache.txt").exists():
        cmd += ["-G", "Ninja"]
    for c in (cmd, ["cmake", "--build", str(build_dir), "-j", "2", "--target", "miem_bench_stages"]):
        proc = subprocess.run(c, capture_output=True, text=True)
        if proc.returncode != 0:
            print(proc.stdout[-2000:], proc.stderr[-2000:], file=sys.stderr)
            return None
    # the schedule probe (bench/cpp/schedule_probe.cpp; OpenMP builds only): optional
    subprocess.run(["cmake", "--build", str(build_dir), "-j", "2", "--target",
                    "miem_schedule_probe"], capture_output=True, text=True)
    return build_dir / "bench" / "miem_bench_stages"


def schedule_probe(binary: Path) -> Path | None:
    """libmiem_schedule_probe.so beside a miem_bench_stages binary, if it was built."""
    so = binary.parent / "libmiem_schedule_probe.so"
    return so if so.exists() else None


def base_binary(commit: str, build: bool = True) -> Path | None:
    """miem_bench_stages built from an earlier commit (git archive into build/base-COMMIT);
    with build=False only one built before."""
    root = ROOT / "build" / f"base-{commit}"
    if not build:
        done = root / "build" / "bench" / "miem_bench_stages"
        return done if done.exists() else None
    src = root / "src"
    if not (src / "CMakeLists.txt").exists():
        src.mkdir(parents=True, exist_ok=True)
        arch = subprocess.run(["git", "-C", str(ROOT), "archive", commit], capture_output=True)
        if arch.returncode != 0:
            return None
        subprocess.run(["tar", "-x", "-C", str(src)], input=arch.stdout, check=True)
    return build_stages(src, root / "build")


def run_stages(binary: Path, grid_file: Path, side: int, nt: int, repeats: int,
               preset: str, cols: int | None = None) -> dict:
    """miem_bench_stages on a side x side grid (side x cols with `cols`); with more than one
    thread under the schedule probe when it was built (the row's "schedule": CPU work and
    critical path per stage)."""
    env = dict(os.environ)
    probe = schedule_probe(binary)
    if nt > 1 and probe is not None:
        env["LD_PRELOAD"] = str(probe)
    out = subprocess.run([str(binary), str(grid_file), str(side), str(cols or side), str(nt),
                          str(repeats), preset], capture_output=True, text=True, check=True,
                         env=env).stdout
    row = json.loads(out)
    for k in STAGES:
        row.setdefault(k, 0.0)  # older binaries time fewer stages
    return row


def faster_alternated(runs: dict, rounds: int = 2) -> dict:
    """{key: run()} -> {key: the fastest of `rounds` results}, the keys' runs alternated (a
    shared host's bursts of load otherwise land on one build's turn)."""
    best: dict = {}
    for _ in range(rounds):
        for key, run in runs.items():
            got = run()
            if key not in best or got["run"] < best[key]["run"]:
                best[key] = got
    return best


def stage_times(build_dir: Path, side: int, repeats: int, build_bases: bool = True):
    """The C++ stages, timed alone (miem_bench_stages), 1 and 2 threads; and the same scan on
    the BASES commits' binaries (1 thread; built first unless build_bases is false), all in
    this one run."""
    binary = build_stages(ROOT, build_dir)
    if binary is None:
        return [], []
    grid_file = build_dir / f"grid_{side}.f64"
    scan_grid(side, side).astype(np.float64).tofile(grid_file)
    rows = []
    for preset in ("recommended", "recommended-no-edge", "paper"):
        for nt in (1, 2):
            rows.append(run_stages(binary, grid_file, side, nt, repeats, preset))
    before = []
    for commit, what, old_preset, new_preset in BASES:
        old = base_binary(commit, build_bases)
        if old is None:
            continue
        got = faster_alternated({
            "now": lambda: run_stages(binary, grid_file, side, 1, repeats, new_preset),
            "before": lambda: run_stages(old, grid_file, side, 1, repeats, old_preset)})
        a, b = got["now"], got["before"]
        if b["checksum"] != a["checksum"]:
            what += " (labels differ!)"
        before.append({"commit": commit, "what": what, "preset": new_preset, "before": b,
                       "now": a})
    grid_file.unlink()
    return rows, before


#: The surface sweep's scans: make_scan's surfaces at 0.2 mm steps, 1 um (a good profiler's)
#: and 20 um of noise, the same defects on each.
SURFACE_NOISES = (0.001, 0.02)
SURFACE_DEFECTS = {"spike": 5, "pit": 5, "dust": 2, "cluster": 2}


def surface_times(build_dir: Path, side: int, repeats: int) -> list[dict]:
    """miem_bench_stages (default preset, 1 thread) on side x side scans of every make_scan
    surface at each of SURFACE_NOISES."""
    from miem.simulate import EXTRA_SURFACES, SURFACES, make_scan

    binary = build_stages(ROOT, build_dir)
    if binary is None:
        return []
    grid_file = build_dir / f"surface_{side}.f64"
    rows = []
    for surface in SURFACES + EXTRA_SURFACES:
        for noise in SURFACE_NOISES:
            scan = make_scan((side, side), step=0.2, surface=surface, noise=noise, seed=1,
                             defects=SURFACE_DEFECTS)
            np.ascontiguousarray(scan.points, dtype=np.float64).tofile(grid_file)
            row = run_stages(binary, grid_file, side, 1, repeats, PRESET)
            row.update(surface=surface, noise=noise)
            rows.append(row)
    grid_file.unlink()
    return rows


#: The dropout sweep: random dropouts added to the benchmark scan (which has 0.5 % of its own),
#: and the build before the changes that sweep measures.
DROPOUTS = (0.0, 0.02, 0.05, 0.1, 0.2)
DROPOUT_BASE = ("3be50c2", "2026-12-07, before the quiet rule counted support per half and "
                "pass 1 searched on to s + 1 a whole word at once")


def dropout_times(build_dir: Path, side: int, repeats: int, build_bases: bool = True):
    """miem_bench_stages (default preset, 1 thread) on the side x side benchmark scan with each
    of DROPOUTS' shares of its cells made dropouts (seeded), today's build and DROPOUT_BASE's
    (built first unless build_bases is false; skipped when neither is there)."""
    binary = build_stages(ROOT, build_dir)
    if binary is None:
        return []
    old = base_binary(DROPOUT_BASE[0], build_bases)
    grid_file = build_dir / f"dropouts_{side}.f64"
    scan = scan_grid(side, side).astype(np.float64)
    rows = []
    for share in DROPOUTS:
        g = scan.copy()
        g[np.random.default_rng(3).random((side, side)) < share] = np.nan
        g.tofile(grid_file)
        row = {"share": share, "nan": float(np.isnan(g[..., 2]).mean())}
        row.update(faster_alternated({
            key: (lambda exe=exe: run_stages(exe, grid_file, side, 1, repeats, PRESET))
            for key, exe in (("now", binary), ("before", old)) if exe is not None}))
        rows.append(row)
    grid_file.unlink()
    return rows


def fmt_dropouts(rows: list[dict]) -> list[str]:
    if not rows:
        return []
    side = rows[0]["now"]["rows"]
    has_before = all("before" in r for r in rows)
    L = ["", f"### Dropouts (default preset, {side}x{side}, 1 thread)", "",
         "The benchmark scan with random dropouts added (`miem_bench_stages`, CPU time, best of "
         "the repeats" + (f"; `before`: {DROPOUT_BASE[0]} ({DROPOUT_BASE[1]}), built from its "
                          "commit in this run, the two builds alternated twice and the faster "
                          "run of each kept" if has_before else "") + ").", "",
         "| dropouts | run() ms | ns / point | angle passes ms | height test ms | edge test ms |"
         + (" before: edge test ms | before: run() ms | speed-up | same labels |"
            if has_before else ""),
         "|---:|---:|---:|---:|---:|---:|" + ("---:|---:|---:|---|" if has_before else "")]
    for r in rows:
        a = r["now"]
        n = a["rows"] * a["cols"]
        line = (f"| {r['nan'] * 100:.1f} % | {a['run'] * 1e3:.0f} | {a['run'] / n * 1e9:.0f} | "
                f"{a['angle_passes'] * 1e3:.0f} | {a['height_test'] * 1e3:.0f} | "
                f"{a['edge_test'] * 1e3:.0f} |")
        if has_before:
            b = r["before"]
            same = "yes" if b["checksum"] == a["checksum"] else "NO"
            line += (f" {b['edge_test'] * 1e3:.0f} | {b['run'] * 1e3:.0f} | "
                     f"{b['run'] / a['run']:.2f}x | {same} |")
        L.append(line)
    first, last = rows[0]["now"], rows[-1]["now"]
    L += ["", f"From {rows[0]['nan'] * 100:.1f} % to {rows[-1]['nan'] * 100:.1f} % dropouts the "
          f"angle passes grow {last['angle_passes'] / first['angle_passes']:.1f}x: a cell "
          "whose neighbour at `s` cells is a dropout searches on to the one at `s + 1` outside "
          "pass 1's vectorised loop (`kernel_rest`, cpp/src/pass1_row.cpp: one cell at a time, "
          "or a whole 64-cell word at once where many of its cells need it). The edge test "
          "skips quiet cells (SPEC \"Edge test\" step 1), which need fewer than `n_min` "
          "missing returns in each half of their sub-window square (24 of 105 cells at the "
          "default): up to about 10 % of scattered dropouts most cells stay quiet; at 20 % a "
          "half often holds 24 of them, and those cells are judged."]
    return L


def quadric_fit(r: int, a: float, b: float) -> float:
    """How well P = (0, 0) fits the edge test's clean one-sided sub-windows (SPEC "Edge test"
    steps 2-4, half-size r; clean: rms at most twice the least) on the noise-free quadratic
    surface z = a x^2 + b y^2: the least |h| / rms among them, whatever the curvature's radius
    (P fits a side when it is at most the tolerance's k)."""
    from miem.reference import _EDGE_CLEAN_RATIO, _edge_sides

    fits = []
    for r0, r1, c0, c1 in _edge_sides(r):
        y, x = np.meshgrid(np.arange(r0, r1 + 1.0), np.arange(c0, c1 + 1.0), indexing="ij")
        z = a * x * x + b * y * y
        m = np.c_[x.ravel(), y.ravel(), np.ones(x.size)]
        coef = np.linalg.lstsq(m, z.ravel(), rcond=None)[0]
        rms = float(np.sqrt(np.mean((m @ coef - z.ravel()) ** 2)))
        fits.append((rms, abs(float(coef[2]))))  # the plane at P: coef[2]; P's z is 0
    best = min(f[0] for f in fits)
    return min(h / rms for rms, h in fits if rms <= _EDGE_CLEAN_RATIO * best)


def fmt_surfaces(rows: list[dict]) -> list[str]:
    if not rows:
        return []
    side = rows[0]["rows"]
    L = ["", f"### Surfaces (default preset, {side}x{side}, 1 thread)", "",
         f"`make_scan((side, side), step=0.2, surface=S, noise=N, seed=1, defects="
         f"{SURFACE_DEFECTS})` for every surface, timed stage by stage by `miem_bench_stages` "
         "(CPU time, best of the repeats).", "",
         "| surface | noise (mm) | run() ms | ns / point | angle passes ms | height test ms | "
         "edge test ms | edge test share | x the plane's |",
         "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    plane = {r["noise"]: r["run"] for r in rows if r["surface"] == "plane"}
    for r in rows:
        n = r["rows"] * r["cols"]
        L.append(f"| {r['surface']} | {r['noise']:g} | {r['run'] * 1e3:.1f} | "
                 f"{r['run'] / n * 1e9:.0f} | {r['angle_passes'] * 1e3:.1f} | "
                 f"{r['height_test'] * 1e3:.1f} | {r['edge_test'] * 1e3:.1f} | "
                 f"{r['edge_test'] / r['run'] * 100:.0f} % | "
                 f"{r['run'] / plane[r['noise']]:.1f}x |")
    import miem

    grid = miem.DetectParams().grid  # the default's edge test: half-size r, tolerance k rms
    r, k = grid.edge_window // 2, grid.edge_tolerance
    worst = max(rows, key=lambda r: r["run"] / plane[r["noise"]])
    curved = [r for r in rows if r["surface"] in ("curved", "shell")]
    hi = [f"`{r['surface']}` {r['run'] / plane[r['noise']]:.1f}x" for r in curved
          if r["noise"] == max(SURFACE_NOISES)]
    L += ["", f"The slowest: `{worst['surface']}` at noise {worst['noise']:g} mm, "
          f"{worst['run'] / plane[worst['noise']]:.1f}x the plane's time at that noise, "
          f"{worst['edge_test'] / worst['run'] * 100:.0f} % of it in the edge test. Where the "
          "time goes on a smoothly curved surface: the edge test's quiet rule (SPEC \"Edge "
          "test\" step 1) skips a cell whose height-window plane is smooth against the noise "
          "floor, and curvature makes that plane's rms exceed it, so every cell is judged. Its "
          "one-sided sub-window planes, fitted to a quadratic surface and extended to the cell "
          "at their border, miss it by a multiple of their rms that depends on the shape, not "
          f"on the radius; the least over the clean sides ({2 * r + 1}-cell sub-windows, "
          f"noise-free): {quadric_fit(r, 1.0, 1.0):.2f} on a sphere's cap (z = x^2 + y^2), "
          f"{quadric_fit(r, 1.0, 0.5):.2f} on the `curved` sheet (x^2 + y^2 / 2), "
          f"{quadric_fit(r, 1.0, 0.0):.2f} on a cylinder, {quadric_fit(r, 1.0, -1.0):.2f} on "
          f"a saddle, against a tolerance of {k:g} rms. So on a bowl or a dome no clean side fits "
          "a cell (the judge's shortcut settles none): each pays its four quadrant planes and "
          "the test whether it lies on the quadratic surface they bend as (SPEC \"Edge test\" "
          "step 4), and those that do not the other four sub-window planes and the rules' "
          "walks too (fins, lips, hanging cells). Noise of the order of the curvature's "
          "residual lets more "
          f"cells fit (at {max(SURFACE_NOISES) * 1e3:g} um: " + ", ".join(hi)
          + " the plane's time)."]
    return L


def profiler_grid(h: int, w: int, seed: int = 0) -> np.ndarray:
    """A laser-profiler-like grid where ``min_step="auto"`` resolves to a length (as on real
    profiler scans): 0.05 mm along a profile, uneven profile spacing (0.1, 0.2, 1.0 mm
    repeating), a tilted surface with a bump, 2 um noise, z quantised to 1 um, 200 spikes and
    pits, 0.5% dropouts."""
    rng = np.random.default_rng(seed)
    dy = np.resize([0.1, 0.2, 1.0], h - 1)
    y = np.concatenate([[0.0], np.cumsum(dy)])[:, None] * np.ones((1, w))
    x = np.arange(w)[None, :] * 0.05 * np.ones((h, 1))
    z = 0.1 * y + 0.4 * np.exp(-((x - 0.3 * x.max()) ** 2) / 50.0)
    z = z + rng.normal(0.0, 0.002, (h, w))
    grid = np.dstack([x, y, z])
    flat = grid.reshape(-1, 3)
    idx = rng.choice(h * w, size=min(200, h * w // 10), replace=False)
    flat[idx, 2] += rng.choice([-1.0, 1.0], idx.size) * rng.uniform(0.5, 3.0, idx.size)
    flat[:, 2] = np.round(flat[:, 2] * 1000.0) / 1000.0
    flat[rng.random(h * w) < 0.005] = np.nan
    return grid


# The previous landed main (stop 41): its binary runs the min_step scans in the same run as
# today's (the min_step searches 64 lanes at a time since; the labels are the same).
MIN_STEP_BASE = ("5dc5f9e", "2026-12-05, before the min_step searches ran 64 lanes at a time")


def min_step_times(build_dir: Path, side: int, repeats: int, build_bases: bool = True):
    """The default on scans where min_step='auto' resolves to a length: the synthetic profiler
    scan (side x side) and the real scan second_source.pcd when ../shared is present; today's
    binary and MIN_STEP_BASE's, 1 thread, CPU time, in this one run."""
    binary = build_stages(ROOT, build_dir)
    if binary is None:
        return []
    scenes = [(f"synthetic profiler scan {side}x{side}", profiler_grid(side, side))]
    sys.path.insert(0, str(HERE / "accuracy"))
    try:
        import real_truth as rt

        if rt.available():
            scenes.append(("real scan second_source.pcd (426x724)", rt.source_grid()))
    except ImportError:
        pass
    old = base_binary(MIN_STEP_BASE[0], build_bases)
    rows = []
    for name, grid in scenes:
        h, w = grid.shape[:2]
        f = build_dir / "min_step_grid.f64"
        np.ascontiguousarray(grid, dtype=np.float64).tofile(f)
        now = run_stages(binary, f, h, 1, repeats, "recommended", cols=w)
        before = (run_stages(old, f, h, 1, repeats, "recommended", cols=w)
                  if old is not None else None)
        f.unlink()
        rows.append({"scene": name, "n": h * w, "now": now, "before": before})
    return rows


def fmt_min_step(rows: list[dict]) -> list[str]:
    if not rows:
        return []
    L = ["", "### With min_step on (profiler scans)", "",
         "On laser-profiler scans `min_step=\"auto\"` resolves to a length (uneven profile "
         "spacing and z quantisation make the noise estimate exceed the spacing along a profile), "
         "and every neighbour search must walk to the first cell at least `s * min_step` away. "
         "The scan above never turns it on. Each stage timed alone (`miem_bench_stages`, 1 "
         f"thread, CPU ms), today's build against {MIN_STEP_BASE[0]} "
         f"({MIN_STEP_BASE[1]}) in this same run:", "",
         "| scan | min_step | build | " + " | ".join(STAGES) + " | run() | Mpoints/s | "
         "speed-up | same labels, flags, heights |",
         "|---|---:|---|" + "---:|" * (len(STAGES) + 3) + "---|"]
    for r in rows:
        b, a = r["before"], r["now"]
        same = "-"
        if b is not None:
            same = "yes" if all(b.get(k) == a.get(k) for k in ("checksum", "height_bits")) and (
                "flags_checksum" not in b or b["flags_checksum"] == a["flags_checksum"]) else \
                "**no**"
        for label, s in (([(MIN_STEP_BASE[0], b)] if b is not None else []) + [("now", a)]):
            up = f"{b['run'] / a['run']:.2f}x" if (label == "now" and b is not None) else ""
            L.append(f"| {r['scene']} | {a.get('min_step', -1):.3f} mm | {label} | "
                     + " | ".join(f"{s[k] * 1e3:.0f}" for k in STAGES + ("run",))
                     + f" | {r['n'] / s['run'] / 1e6:.1f} | {up} | "
                     + f"{same if label == 'now' else ''} |")
    if any(r["before"] is not None and r["before"].get("checksum") != r["now"].get("checksum")
           for r in rows):
        L += ["", "**no**: the labels differ because a rule added since that commit fires on "
              "that scan (SPEC \"Edge test\" step 6: the hanging ledge's path, lips at a concave "
              "feature); its speed-up then compares slightly different work."]
    return L


def fmt(rows_lead, rows_sweep, rows_fit, mem, stages, before, now_bd, meta,
        min_step_rows=(), surface_rows=(), dropout_rows=(), layout_rows=()) -> str:
    L = ["## Speed of the default detector (`python bench/bench_speed.py`)", ""]
    L.append(f"Written on {meta['date']}: miem {meta['miem']}, {meta['cpu']}, {os.cpu_count()} "
             f"cores, shared with other jobs (load average {meta['load0']:.1f} at the start, "
             f"{meta['load1']:.1f} at the end): read ratios and CPU-time figures before wall "
             "seconds. Default preset = `\"recommended\"` (theta0 90, scales (1, 2), min_step "
             "'auto', window 21, height test 4.5 rms, edge_extent 12, edge test 4 rms in 15-cell "
             "windows), heights at every point, defects.")
    if max(meta["load0"], meta.get("load1", 0.0)) > (os.cpu_count() or 1):
        L[-1] += (" **The load exceeded the core count during this run: the wall-time and "
                  "2-thread figures (and the wall-time comparison with Open3D / PCL) measure "
                  "the other jobs as much as miem; the 1-thread CPU-time columns and the "
                  "same-run before/after ratios are the ones to read.**")
    L += ["", f"### miem's default against Open3D and PCL, the same {meta['lead_side']}x"
          f"{meta['lead_side']} scan", "",
          "| method | time | Mpoints/s | points flagged / removed |", "|---|---:|---:|---:|"]
    for r in rows_lead:
        fl = "-" if r["flagged"] is None else f"{r['flagged']:,}"
        L.append(f"| {r['who']} | {r['t'] * 1e3:.0f} ms | {r['mpts']:.1f} | {fl} |")
    L += ["", "The scan has 200 injected spikes and pits (plus their 2x2 clusters) and 0.5% "
          "dropouts; Open3D's and PCL's filters get its finite points as an unorganized cloud "
          "(they are other methods: what a user would run instead; PCL 1.13 from Debian's "
          "`libpcl-dev`, `bench/cpp/bench_pcl.cpp --grid`, kd-tree search, its rows only where "
          "PCL is installed). PCL's organized-cloud filters on a depth-camera cloud: see "
          "\"Organized detection against PCL\" below.", ""]
    L += ["### Size sweep (default preset)", "",
          "| grid | points | CPU ms, 1 thread | Mpoints/s, 1 thread (CPU) | ns / point | "
          "wall ms, 1 thread | wall ms, 2 threads | 2 threads / 1 thread |",
          "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows_sweep:
        L.append(f"| {r['side']}x{r['side']} | {r['n']:,} | {r['cpu1'] * 1e3:.0f} | "
                 f"{r['n'] / r['cpu1'] / 1e6:.1f} | {r['cpu1'] / r['n'] * 1e9:.0f} | "
                 f"{r['wall1'] * 1e3:.0f} | {r['wall2'] * 1e3:.0f} | {r['wall1'] / r['wall2']:.2f}x |")
    if rows_sweep:
        ns = [r["cpu1"] / r["n"] * 1e9 for r in rows_sweep if r["side"] >= 512]
        if ns:
            L += ["", f"Cost per point from 512^2 up: {min(ns):.0f} to {max(ns):.0f} ns "
                  f"(max / min {max(ns) / min(ns):.2f}: linear when close to 1). Every grid "
                  "has the 2048^2 scan's defect density (200 defects per 2048^2 points: "
                  f"{sweep_defects(512 * 512)} at 512^2, {sweep_defects(4096 * 4096)} at "
                  "4096^2). A fixed cost remains: `min_step` / `z_noise` \"auto\" read the "
                  "first 256 rows whatever the grid's height (SPEC), half of a 512^2 grid and "
                  "1/16 of a 4096^2 one. The wall columns are `miem.detect` through Python, "
                  "best of the repeats, the 1-thread and 2-thread calls alternated."]
    L += ["", "| `fit_plane`, 1 thread | time | GB/s | NumPy `sum` GB/s | share of the yardstick |",
          "|---|---:|---:|---:|---:|"]
    for r in rows_fit:
        L.append(f"| {r['n']:,} points | {r['t'] * 1e3:.1f} ms | {r['gbs']:.1f} | "
                 f"{r['sum_gbs']:.1f} | {r['gbs'] / r['sum_gbs'] * 100:.0f} % |")
    if mem:
        L += ["", "### Memory", "",
              f"`detect` on a {meta['mem_side']}x{meta['mem_side']} float64 grid "
              f"({mem['grid'] / 1e6:.0f} MB) in a fresh process: peak resident growth during the "
              f"call {mem['growth'] / 1e6:.0f} MB = {mem['growth'] / mem['grid']:.2f}x the input "
              f"grid (the four per-point outputs are {mem['outputs'] / 1e6:.0f} MB of it; "
              "target <= 2x)."]
    if stages:
        n_side = meta["stage_side"]
        L += ["", "### Where the time goes", "",
              f"Each stage of `OrganizedDetector::run` (cpp/src/stages.hpp, organized.cpp) timed "
              f"alone by `miem_bench_stages` on the {n_side}x{n_side} scan (C++, no Python; 1 "
              "thread: CPU time, 2 threads: wall time). `recommended` is today's default "
              "(min_step 'auto', edge test); `recommended-no-edge` the default before issue 10. "
              "run(): one detector reused (its workspace warm); fresh: a new detector and new "
              "outputs per call, as `miem.detect` runs (the size sweep's way). *Schedule "
              "allows*: the speed-up the thread schedule permits, CPU work / critical path of "
              "run() (critical path = serial CPU + the busiest thread's CPU in each parallel "
              "region, bench/cpp/schedule_probe.cpp; per-thread CPU time, so other processes "
              "do not change it); below it the machine (memory, wake-ups, load).",
              "", "| preset | threads | " + " | ".join(STAGES)
              + " | run() | fresh | Mpoints/s | schedule allows |",
              "|---|---:|" + "---:|" * (len(STAGES) + 4)]
        for s in stages:
            n = s["rows"] * s["cols"]
            sch = s.get("schedule", {}).get("run")
            allows = f"{sch['work'] / sch['critical']:.2f}x" if sch else "-"
            fresh = f"{s['run_fresh'] * 1e3:.0f} ms" if "run_fresh" in s else "-"
            L.append(f"| {s['preset']} | {s['threads']} | "
                     + " | ".join(f"{s[k] * 1e3:.0f} ms" for k in STAGES + ("run",))
                     + f" | {fresh} | {n / s['run'] / 1e6:.1f} | {allows} |")
    if before:
        n_side = meta["stage_side"]
        L += ["", f"Before and after, in this same run ({n_side}x{n_side}, 1 thread, CPU ms; "
              "the earlier commits built from `git archive` into `build/base-COMMIT`; same "
              "configuration and the same labels; each pair alternated twice, the faster run of "
              "each kept):", "",
              "| build | preset | " + " | ".join(STAGES) + " | run() | Mpoints/s | speed-up |",
              "|---|---|" + "---:|" * (len(STAGES) + 3)]
        for b in before:
            for label, s in ((f"{b['commit']}: {b['what']}", b["before"]), ("now", b["now"])):
                n = s["rows"] * s["cols"]
                up = f"{b['before']['run'] / s['run']:.2f}x" if label == "now" else ""
                L.append(f"| {label} | {b['preset']} | "
                         + " | ".join(f"{s[k] * 1e3:.0f}" for k in STAGES + ("run",))
                         + f" | {n / s['run'] / 1e6:.1f} | {up} |")
    L += fmt_min_step(list(min_step_rows))
    L += fmt_surfaces(list(surface_rows))
    L += fmt_dropouts(list(dropout_rows))
    L += fmt_layouts(list(layout_rows), meta.get("layout_side", 0))
    L += ["", "By configuration differences through the Python API (CPU time, 1 thread, "
          f"{meta['bd_side']}x{meta['bd_side']}; the builds before are compared stage by stage "
          "above):", "",
          "| build | angle test | + heights at every point | + height test | + edge test | "
          "full default | Mpoints/s |", "|---|---:|---:|---:|---:|---:|---:|"]
    for label, bd in [("now", now_bd)]:
        n = bd["side"] ** 2
        et = f"{bd['edge_test'] * 1e3:.0f} ms" if "edge_test" in bd else "- (none)"
        L.append(f"| {label} | {bd['angle'] * 1e3:.0f} ms | {bd['heights'] * 1e3:.0f} ms | "
                 f"{bd['height_test'] * 1e3:.0f} ms | {et} | {bd['full'] * 1e3:.0f} ms | "
                 f"{n / bd['full'] / 1e6:.1f} |")
    return "\n".join(L) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--build-dir", type=Path, default=ROOT / "build" / "bench")
    args = ap.parse_args(argv)
    import datetime as dt

    import miem

    q = args.quick
    bd_side = 512 if q else 2048
    load0 = os.getloadavg()[0]
    meta = {"date": dt.date.today().isoformat(), "miem": miem.__version__, "cpu": cpu_name(),
            "load0": load0, "lead_side": 512 if q else 1024, "mem_side": 512 if q else 2048,
            "stage_side": 512 if q else 2048, "bd_side": bd_side}
    reps = 2 if q else 3
    rows_lead = lead(meta["lead_side"], reps) + pcl_rows(args.build_dir, meta["lead_side"], reps)
    rows_sweep = sweep([256, 512] if q else [256, 512, 1024, 2048, 4096], reps)
    rows_fit = fit_sweep([100_000, 1_000_000] if q else [100_000, 1_000_000, 10_000_000], reps)
    mem = memory(meta["mem_side"])
    # --quick uses only the earlier commits' binaries built before (building them takes minutes)
    stages, before = stage_times(args.build_dir, meta["stage_side"], reps, build_bases=not q)
    min_step_rows = min_step_times(args.build_dir, meta["stage_side"], reps, build_bases=not q)
    surface_rows = surface_times(args.build_dir, 512, reps)
    dropout_rows = dropout_times(args.build_dir, meta["stage_side"], reps, build_bases=not q)
    meta["layout_side"] = 512 if q else 1024
    layout_rows = layout_times(meta["layout_side"], reps)
    now_bd = breakdown(bd_side, reps)
    meta["load1"] = os.getloadavg()[0]
    RAW.write_text(json.dumps({"lead": rows_lead, "sweep": rows_sweep, "fit": rows_fit,
                               "memory": mem, "stages": stages, "before": before, "breakdown": now_bd,
                               "min_step": min_step_rows, "surfaces": surface_rows,
                               "dropouts": dropout_rows, "layouts": layout_rows,
                               "meta": meta}, indent=1) + "\n")
    OUT.write_text(fmt(rows_lead, rows_sweep, rows_fit, mem, stages, before, now_bd, meta,
                       min_step_rows, surface_rows, dropout_rows, layout_rows))
    print(OUT.read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
