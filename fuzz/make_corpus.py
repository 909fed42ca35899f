"""Write the seed corpus (fuzz/corpus/<harness>/): small valid files of each format written by
miem.io (grids with dropouts, clouds, extra fields, every encoding) plus a Gocator CSV export.
Run once; the files are committed."""

from pathlib import Path

import numpy as np

import miem.io

ROOT = Path(__file__).resolve().parent / "corpus"


def scans():
    y, x = np.mgrid[0:3, 0:4] * 0.5
    grid = np.dstack([x, y, 0.1 * x])
    grid[1, 2] = np.nan
    cloud = np.array([[0.0, 0, 0], [1, 0, 0.5], [0, 1, 0.25], [1, 1, 2]])
    label = np.array([[0, 1, 2, 3], [0, 0, 3, 1], [2, 0, 0, 0]], dtype=np.uint8)
    return [("grid", grid, {"label": label}), ("cloud", cloud, {}),
            ("cloud32", cloud.astype(np.float32), {"height": np.arange(4.0)})]


def main():
    for suffix, encodings in {".pcd": ["ascii", "binary", "binary_compressed"],
                              ".ply": ["ascii", "binary"], ".las": [None], ".laz": [None],
                              ".npy": [None], ".npz": [None], ".xyz": [None], ".csv": [None]}.items():
        d = ROOT / suffix[1:]
        d.mkdir(parents=True, exist_ok=True)
        for name, pts, fields in scans():
            for enc in encodings:
                miem.io.write(d / f"{name}-{enc or 'plain'}{suffix}", pts, fields, encoding=enc)
    (ROOT / "csv" / "gocator.csv").write_text(
        "Info\nVersion,5\n\nPart\nRow Count,Column Count,X Offset,Y Offset\n2,3,0,0\n"
        "Y\\X,0.0,0.5,1.0\n0.0,1.0,1.5,\n0.5,1.0,,2.0\nEnd\n")
    d = ROOT / "stream"
    d.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for i in range(4):
        (d / f"seed{i}").write_bytes(rng.bytes(64 * (i + 1)))


if __name__ == "__main__":
    main()
