"""End-to-end tests of the ``miem`` command line, run as ``python -m miem`` in a subprocess.

Expected numbers come from the Python API (``miem.detect``, ``miem.fit_plane``,
``miem.simulate``) on the same data, from the files decoded independently, or from the PNG
format itself; never from an earlier run of the command line.
"""

from __future__ import annotations

import csv
import io
import json
import struct
import subprocess
import sys
from pathlib import Path

import miem
import miem.io as mio
import numpy as np
import pytest
from miem import cli, simulate

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"


def run(*args: str | Path, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "miem", *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, timeout=300, check=False)


@pytest.fixture(scope="module")
def scans(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Generated scans in several formats, written through the API."""
    d = tmp_path_factory.mktemp("scans")
    paper = simulate.paper_scan()
    crease = simulate.make_scan(shape=(60, 80), surface="crease", noise=0.02, dropout=0.02,
                                defects={"spike": 2, "pit": 1, "cluster": 1, "dust": 1}, seed=4)
    mio.write(d / "paper.pcd", paper.points, {"truth": paper.truth})
    mio.write(d / "crease.ply", crease.points, {"truth": crease.truth})
    # A profiler export: unorganized, profile after profile, dropouts left out.
    flat = crease.points.reshape(-1, 3)
    mio.write(d / "lines.xyz", flat[np.isfinite(flat).all(axis=1)])
    return {"paper": d / "paper.pcd", "crease": d / "crease.ply", "lines": d / "lines.xyz"}


# ---------------------------------------------------------------------------------------------
# help and usage


def test_help_explains_every_option_with_default() -> None:
    top = run("--help")
    assert top.returncode == 0
    for cmd in ("detect", "fit", "simulate", "plot"):
        assert cmd in top.stdout
    out = run("detect", "--help").stdout
    # the defaults are the recommended preset's (miem.DetectParams)
    for opt, default in (("--theta0 DEG", "(default: 90)"), ("--scales N", "(default: 1 2)"),
                         ("--height-tolerance LENGTH|Krms", "(default: 4.5rms)"),
                         ("--edge-extent CELLS", "(default: 12)"), ("--config FILE", "TOML"),
                         ("--max-gap CELLS", "(default: 1)"), ("--min-step LENGTH", "off"),
                         ("--window CELLS", "21"), ("--max-iterations N", "10"),
                         ("--min-directions N", "all available"), ("--threads N", "all cores"),
                         ("--preset", "paper"), ("--format", "same as the"),
                         ("-o DIR", "current directory"), ("--line-step LENGTH", "estimated")):
        entry = "\n  " + opt  # the option's own help entry, not the usage line
        assert entry in out, opt
        text = " ".join(out.split(entry, 1)[1].split()[:60])
        assert default in text, (opt, text)
    assert "degrees" in out and "mm" in out
    for cmd in ("fit", "simulate", "plot"):
        res = run(cmd, "--help")
        assert res.returncode == 0 and "default" in res.stdout


def test_version_and_usage_errors(tmp_path: Path, scans: dict[str, Path]) -> None:
    res = run("--version")
    assert res.returncode == 0 and res.stdout.strip() == f"miem {miem.__version__}"
    assert run().returncode == 2
    assert run("detect").returncode == 2  # no SCAN
    res = run("detect", scans["paper"], "--theta0", "wide")
    assert res.returncode == 2 and "--theta0" in res.stderr
    res = run("detect", scans["paper"], "--theta0", "200", "-o", tmp_path)
    assert res.returncode == 2 and "theta0" in res.stderr
    res = run("detect", scans["paper"], "--window", "4", "-o", tmp_path)
    assert res.returncode == 2 and "window" in res.stderr and "odd" in res.stderr
    res = run("detect", scans["paper"], "--preset", "fast", "-o", tmp_path)
    assert res.returncode == 2 and "paper" in res.stderr
    assert list(tmp_path.iterdir()) == []


def test_presets_are_the_detectors(tmp_path: Path, scans: dict[str, Path]) -> None:
    out = run("detect", "--help").stdout
    choices = out.split("--preset {", 1)[1].split("}", 1)[0].split(",")
    assert sorted(choices) == sorted(miem.PRESETS)
    # An explicit option overrides the preset; the others keep the preset's values.
    res = run("detect", scans["crease"], "-o", tmp_path, "--preset", miem.DEFAULT_PRESET,
              "--theta0", "100", "--height-tolerance", "4rms")
    assert res.returncode == 0, res.stderr
    doc, _ = read_report(tmp_path, "crease")
    api = miem.detect(mio.read(scans["crease"]).points, preset=miem.DEFAULT_PRESET,
                      theta0=100.0, height_tolerance="4rms")
    assert doc["parameters"]["theta0"] == 100.0
    assert doc["parameters"]["window"] == miem.PRESETS[miem.DEFAULT_PRESET].grid.window
    assert doc["counts"] == api.counts() and len(doc["defects"]) == len(api.defects)
    res = run("detect", scans["crease"], "-o", tmp_path, "--theta0", "auto")
    assert res.returncode == 0, res.stderr
    doc, _ = read_report(tmp_path, "crease")
    api = miem.detect(mio.read(scans["crease"]).points, theta0="auto")
    assert doc["parameters"]["theta0_auto"] is True
    assert doc["parameters"]["theta0"] == api.params["theta0"]
    assert doc["counts"] == api.counts()


def test_every_grid_field_is_an_option_with_unit_and_default() -> None:
    out = run("detect", "--help").stdout
    grid = miem.DetectParams.fields("grid")
    for name, meta in grid.items():
        opt = "\n  --" + name.replace("_", "-")
        assert opt in out, name
        text = " ".join(out.split(opt, 1)[1].split()[:80])
        assert "(default:" in text, name
        if meta["unit"]:
            assert f"[{meta['unit']}]" in text, name


def test_config_file_and_miem_config(tmp_path: Path, scans: dict[str, Path]) -> None:
    from miem.params import load_config

    res = run("config", "--preset", "paper", "--format", "json")
    assert res.returncode == 0, res.stderr
    assert miem.DetectParams.from_dict(json.loads(res.stdout)) == miem.PRESETS["paper"]
    toml = run("config").stdout  # the default preset, TOML, every field with its unit
    for path in ("grid", "cloud"):
        for name in miem.DetectParams.fields(path):
            assert f"\n{name} = " in toml, name
    assert "[angle]" in toml and "[grid]" in toml and "[cloud]" in toml
    cfg = tmp_path / "cell.toml"
    cfg.write_text(toml)
    assert load_config(cfg) == miem.PRESETS["recommended"]
    cfg.write_text(toml.replace("edge_extent = 12", "edge_extent = 4"))
    out = tmp_path / "out"
    res = run("detect", scans["crease"], "-o", out, "--config", cfg, "--theta0", "100")
    assert res.returncode == 0, res.stderr
    doc, _ = read_report(out, "crease")
    points = mio.read(scans["crease"]).points
    api = miem.detect(points, theta0=100.0, edge_extent=4)
    assert (doc["parameters"]["theta0"], doc["parameters"]["edge_extent"]) == (100.0, 4)
    assert doc["counts"] == api.counts()
    # --edge-extent, and 'off' for an optional parameter
    res = run("detect", scans["crease"], "-o", out, "--edge-extent", "3",
              "--height-tolerance", "off", "--preset", "paper")
    assert res.returncode == 0, res.stderr
    doc, _ = read_report(out, "crease")
    assert doc["parameters"]["edge_extent"] == 3 and doc["parameters"]["height_tolerance"] is None
    assert doc["parameters"]["preset"] == "paper"
    assert doc["counts"] == miem.detect(points, preset="paper", edge_extent=3).counts()
    # a bad file is a usage error naming the field
    cfg.write_text('windw = 15\n')
    res = run("detect", scans["crease"], "-o", out, "--config", cfg)
    assert res.returncode == 2 and "windw" in res.stderr
    res = run("config", "--preset", "paper", "-o", tmp_path / "p.json", "--format", "json")
    assert res.returncode == 0
    assert load_config(tmp_path / "p.json") == miem.PRESETS["paper"]


# ---------------------------------------------------------------------------------------------
# simulate


def test_simulate_paper_and_scan(tmp_path: Path) -> None:
    res = run("simulate", "paper", "-o", tmp_path / "paper.pcd")
    assert res.returncode == 0, res.stderr
    assert "201 x 161" in res.stdout
    back = mio.read(tmp_path / "paper.pcd")
    want = simulate.paper_scan()
    assert back.organized
    np.testing.assert_array_equal(back.points, want.points)
    np.testing.assert_array_equal(back.fields["truth"], want.truth)

    res = run("simulate", "scan", "-o", tmp_path / "s.npz", "--shape", "40", "50", "--surface",
              "tilted", "--defects", "spike=3,pit=1", "--noise", "0.01", "--dropout", "0.05",
              "--seed", "7", "--step", "0.25", "--origin", "1000", "-500", "20")
    assert res.returncode == 0, res.stderr
    want = simulate.make_scan(shape=(40, 50), step=0.25, surface="tilted", noise=0.01,
                              defects={"spike": 3, "pit": 1}, dropout=0.05, seed=7,
                              origin=(1000.0, -500.0, 20.0))
    back = mio.read(tmp_path / "s.npz")
    np.testing.assert_array_equal(back.points, want.points)
    np.testing.assert_array_equal(back.fields["truth"], want.truth)

    res = run("simulate", "scan", "-o", tmp_path / "bad.pcd", "--defects", "burr=2")
    assert res.returncode == 1 and "burr" in res.stderr
    assert not (tmp_path / "bad.pcd").exists()


# ---------------------------------------------------------------------------------------------
# detect


def read_report(out: Path, stem: str) -> tuple[dict, list[dict]]:
    doc = json.loads((out / f"{stem}.defects.json").read_text())
    with open(out / f"{stem}.defects.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    return doc, rows


def test_detect_batch_matches_the_api(tmp_path: Path, scans: dict[str, Path]) -> None:
    out = tmp_path / "out"
    res = run("detect", scans["paper"], scans["crease"], "-o", out, "--scales", "1", "2")
    assert res.returncode == 0, res.stderr
    for key, stem, ext in (("paper", "paper", ".pcd"), ("crease", "crease", ".ply")):
        grid = mio.read(scans[key]).points
        api = miem.detect(grid, scales=(1, 2))
        doc, rows = read_report(out, stem)
        assert len(doc["defects"]) == len(rows) == len(api.defects)
        assert doc["counts"] == api.counts()
        assert doc["grid"] == list(grid.shape[:2]) and doc["parameters"]["scales"] == [1, 2]
        for got, want, row in zip(doc["defects"], api.defects, rows):
            assert got["id"] == want.id and got["count"] == want.count == int(row["count"])
            assert got["kind"] == want.kind == row["kind"]
            assert got["indices"] == want.indices.tolist()
            assert got["peak_height"] == pytest.approx(want.peak_height, rel=1e-12)
            assert float(row["peak_height"]) == pytest.approx(want.peak_height, rel=1e-9)
            np.testing.assert_allclose(got["centroid"], want.centroid, rtol=1e-12)
            np.testing.assert_allclose(got["normal"], want.normal, rtol=1e-12, atol=1e-15)
            # The peak point is a point of the defect with the peak height.
            cells = want.indices
            k = int(np.argmax(np.abs(api.height.ravel()[cells])))
            np.testing.assert_array_equal(got["peak_point"], grid.reshape(-1, 3)[cells[k]])
        cloud = mio.read(out / f"{stem}.labels{ext}")
        assert cloud.organized and cloud.points.shape == grid.shape
        np.testing.assert_array_equal(cloud.fields["label"], api.labels)
        np.testing.assert_array_equal(cloud.fields["height"], api.height)
        np.testing.assert_array_equal(cloud.fields["angle"], api.angle)
        np.testing.assert_array_equal(cloud.fields["flags"], api.flags)
        np.testing.assert_array_equal(cloud.fields["truth"], mio.read(scans[key]).fields["truth"])
    # Every injected paper defect was found (the paper's claim) and reported.
    doc, _ = read_report(out, "paper")
    assert doc["counts"]["ABNORMAL"] == 5
    # Summary table: one line per scan with its defect count.
    lines = res.stdout.splitlines()
    assert lines[0].split()[:3] == ["scan", "points", "grid"]
    paper_line = next(ln for ln in lines if ln.startswith("paper.pcd"))
    assert paper_line.split()[1:6] == ["32,361", "201x161", "5", "400", "5"]
    assert "2 of 2 scans done" in res.stdout


def test_detect_unorganized_scanlines_maps_back_to_input_order(
        tmp_path: Path, scans: dict[str, Path]) -> None:
    out = tmp_path / "o"
    res = run("detect", scans["lines"], "-o", out, "--format", "csv")
    assert res.returncode == 0, res.stderr
    pts = mio.read(scans["lines"]).points
    grid, index = mio.grid_from_scanlines(pts, return_index=True)
    api = miem.detect(grid)
    cloud = mio.read(out / "lines.labels.csv")
    assert not cloud.organized
    np.testing.assert_array_equal(cloud.points, pts)  # same points, same order
    np.testing.assert_array_equal(cloud.fields["label"], api.labels.ravel()[index])
    doc, _ = read_report(out, "lines")
    assert len(doc["defects"]) == len(api.defects) and doc["organized"] is False
    inverse = {int(c): i for i, c in enumerate(index)}
    for got, want in zip(doc["defects"], api.defects):
        assert got["indices"] == sorted(inverse[int(c)] for c in want.indices)
        assert all(cloud.fields["label"][i] == miem.ABNORMAL for i in got["indices"])


def test_failed_inputs_give_exit_1_and_the_rest_is_done(
        tmp_path: Path, scans: dict[str, Path]) -> None:
    bad = tmp_path / "bad.pcd"
    bad.write_bytes(b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
                    b"WIDTH 100\nHEIGHT 1\nPOINTS 100\nDATA binary\n" + bytes(40))
    empty = tmp_path / "empty.ply"
    empty.write_bytes(b"")
    out = tmp_path / "out"
    res = run("detect", bad, scans["paper"], empty, tmp_path / "missing.xyz", "-o", out)
    assert res.returncode == 1
    assert "bad.pcd" in res.stderr and "truncated" in res.stderr
    assert "empty.ply" in res.stderr and "empty" in res.stderr
    assert "missing.xyz" in res.stderr
    assert "1 of 4 scans done, 3 failed" in res.stdout
    assert sorted(p.name for p in out.iterdir()) == [
        "paper.defects.csv", "paper.defects.json", "paper.labels.pcd"]


def test_detect_never_overwrites_an_input(tmp_path: Path, scans: dict[str, Path]) -> None:
    grid = mio.read(scans["paper"]).points
    mio.write(tmp_path / "a.pcd", grid)
    mio.write(tmp_path / "a.labels.pcd", grid[:50])  # looks like an earlier output
    before = (tmp_path / "a.labels.pcd").read_bytes()
    res = run("detect", "a.pcd", "a.labels.pcd", cwd=tmp_path)
    assert res.returncode == 1
    assert "refusing to overwrite the input" in res.stderr
    assert (tmp_path / "a.labels.pcd").read_bytes() == before
    assert (tmp_path / "a.labels.labels.pcd").exists()  # the other input was processed
    # Two inputs with one name would write the same outputs: a usage error, nothing written.
    (tmp_path / "x").mkdir()
    mio.write(tmp_path / "x" / "a.pcd", grid)
    res = run("detect", "a.pcd", "x/a.pcd", "-o", "o2", cwd=tmp_path)
    assert res.returncode == 2 and "same outputs" in res.stderr
    assert not (tmp_path / "o2").exists()


@pytest.mark.parametrize("fmt", ["ply", "las", "npz", "txt"])
def test_detect_output_formats(tmp_path: Path, scans: dict[str, Path], fmt: str) -> None:
    res = run("detect", scans["paper"], "-o", tmp_path, "--format", fmt, "-q")
    assert res.returncode == 0, res.stderr
    assert res.stdout == ""
    cloud = mio.read(tmp_path / f"paper.labels.{fmt}")
    api = miem.detect(mio.read(scans["paper"]).points)
    np.testing.assert_array_equal(cloud.fields["label"], api.labels)


def test_no_progress_bar_when_not_a_terminal(tmp_path: Path, scans: dict[str, Path]) -> None:
    res = run("detect", scans["paper"], "-o", tmp_path)
    assert res.returncode == 0 and "[" not in res.stderr and "\r" not in res.stderr


def test_progress_bar_on_a_terminal() -> None:
    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    stream = Tty()
    bar = cli._Progress(4, True, stream)
    bar.show(2, "b.pcd: detecting")
    assert stream.getvalue() == "\r[" + "#" * 12 + " " * 12 + "] 2/4 b.pcd: detecting"
    bar.close()
    assert stream.getvalue().endswith("\r")
    quiet = Tty()
    cli._Progress(4, False, quiet).show(1, "x")
    assert quiet.getvalue() == ""


@pytest.mark.skipif(not (REAL / "second_source.pcd").exists(), reason="no shared/data/real")
def test_detect_real_profiler_scan(tmp_path: Path) -> None:
    src = REAL / "second_source.pcd"
    res = run("detect", src, "-o", tmp_path)
    assert res.returncode == 0, res.stderr
    pts = mio.read(src).points
    api = miem.detect(mio.grid_from_scanlines(pts))
    doc, rows = read_report(tmp_path, "second_source")
    assert doc["grid"] == [426, 724]
    assert len(doc["defects"]) == len(rows) == len(api.defects)
    assert doc["counts"] == api.counts()
    cloud = mio.read(tmp_path / "second_source.labels.pcd")
    assert cloud.points.shape == (250_681, 3)
    np.testing.assert_array_equal(cloud.points, pts)


@pytest.mark.skipif(not (REAL / "target.pcd").exists(), reason="no shared/data/real")
def test_detect_explains_a_cloud_without_scan_lines(tmp_path: Path) -> None:
    # forced onto the scan-line path, the refusal explains itself and writes nothing
    res = run("detect", REAL / "target.pcd", "-o", tmp_path, "--layout", "scanlines")
    assert res.returncode == 1
    assert "target.pcd" in res.stderr and "unorganized" in res.stderr
    assert "--layout cloud" in res.stderr
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------------------------------
# fit


def test_fit_prints_three_planes(scans: dict[str, Path]) -> None:
    res = run("fit", scans["paper"])
    assert res.returncode == 0, res.stderr
    grid = mio.read(scans["paper"]).points
    api = miem.detect(grid)
    want = {"least squares": miem.fit_plane(grid, "lstsq"), "eigenvalue": miem.fit_plane(grid),
            "MIEM": api.plane}
    got = {}
    for line in res.stdout.splitlines():
        for name in want:
            if line.startswith(name + " "):
                got[name] = line[len(name):].split()
    assert set(got) == set(want)
    for name, plane in want.items():
        cols = got[name]
        np.testing.assert_allclose([float(c) for c in cols[:3]], plane.normal, atol=1e-6)
        assert float(cols[3]) == pytest.approx(plane.d, abs=1e-6)
        assert float(cols[4]) == pytest.approx(plane.rms, rel=1e-5)
        assert int(cols[5].replace(",", "")) == plane.n_points
    assert int(got["eigenvalue"][5].replace(",", "")) - int(got["MIEM"][5].replace(",", "")) \
        == api.counts()["ABNORMAL"] == 5


# ---------------------------------------------------------------------------------------------
# plot


def png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    assert data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


@pytest.mark.parametrize("view", ["3d", "top"])
def test_plot_writes_a_png_of_the_requested_size(tmp_path: Path, scans: dict[str, Path],
                                                 view: str) -> None:
    import matplotlib.image as mpimg

    out = tmp_path / "p.png"
    res = run("plot", scans["crease"], "-o", out, "--view", view, "--size", "8", "3.5",
              "--dpi", "80", "--scales", "1", "2")
    assert res.returncode == 0, res.stderr
    assert png_size(out) == (640, 280)
    img = mpimg.imread(out)
    assert img.shape[:2] == (280, 640)
    # Not a blank canvas: red (ABNORMAL / circles) and the colour map are there.
    rgb = img[..., :3]
    red = (rgb[..., 0] > 0.7) & (rgb[..., 1] < 0.3) & (rgb[..., 2] < 0.3)
    assert red.sum() > 20
    assert len(np.unique(rgb.reshape(-1, 3).round(2), axis=0)) > 50
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.png"]


def test_plot_default_name_and_failure(tmp_path: Path, scans: dict[str, Path]) -> None:
    res = run("plot", scans["paper"], cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert png_size(tmp_path / "paper.png") == (1600, 600)
    bad = tmp_path / "bad.npy"
    bad.write_bytes(b"\x93NUMPY junk")
    res = run("plot", bad, "-o", tmp_path / "bad.png")
    assert res.returncode == 1 and "bad.npy" in res.stderr
    assert not (tmp_path / "bad.png").exists()
