"""Why the edge test leaves burr cells of the real scan unflagged (a diagnostic, writes nothing).

    python bench/accuracy/real_misses.py            # profiles 70-79 (the wall top)
    python bench/accuracy/real_misses.py 380 390    # any band of profiles [first, last)

For every BURR cell of ``real_truth`` in the band that the recommended preset leaves NORMAL or
EDGE, the reference's edge-test quantities (``miem.reference._side_fits``, SPEC "Edge test"
steps 3-6) are recomputed on the final labels (the last pass's support; one origin for the
band instead of the tile's, which changes round-off only) and the cell is put in one class:

- *fits*: it fits a clean sub-window (printed: which, and how steep those planes are: a plane
  much steeper than the surface around it is a sub-window straddling two levels);
- *no fit, below*: it fits none and lies below a clean sub-window whose opposite is empty or
  falls away (a hanging candidate), with which of the hanging conditions fail (45 degrees
  from the top's last support cell, the shelf beyond);
- *no fit, other*: it fits none and is neither proud nor a hanging candidate.

The real scan is the test split: this tells where the error goes, it must not pick thresholds.
"""

from __future__ import annotations

import collections
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import miem  # noqa: E402
import real_truth as rt  # noqa: E402
from miem import reference as ref  # noqa: E402

SIDES = ("left", "right", "up", "down", "up-left", "up-right", "down-left", "down-right")


def _hanging_parts(grid, labels, cells, r, below, h, nrm):  # noqa: ANN001, ANN202
    """Per cell of ``cells``: some hanging candidate side passes the 45-degree condition / the
    shelf / both (``miem.reference._hang_conditions``, apart)."""
    n = below.shape[1]
    steep_any, shelf_any, both = (np.zeros(n, dtype=bool) for _ in range(3))
    for k in range(len(SIDES)):
        if below[k].any():
            steep, shelf = ref._hang_conditions(grid, labels, cells, r, k, h[k], nrm[k])
            steep_any |= below[k] & steep
            shelf_any |= below[k] & shelf
            both |= below[k] & steep & shelf
    return steep_any, shelf_any, both


def misses(first: int, last: int) -> dict:
    """The classes above, counted over the missed BURR cells of profiles first..last-1."""
    tr = rt.truth()
    g = tr.grid
    p = miem.PRESETS["recommended"].grid
    labels = miem.detect(g).labels
    r, k = p.edge_window // 2, float(p.edge_tolerance)
    cells = np.zeros(labels.shape, dtype=bool)
    band = slice(first, last)
    cells[band] = (tr.classes[band] == rt.BURR) & ((labels[band] == miem.NORMAL)
                                                    | (labels[band] == miem.EDGE))
    fin = np.isfinite(g[first:last, :, 2])
    origin = g[first:last][np.unravel_index(np.argmax(fin), fin.shape)]
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        h, rms, spread, valid, nrm, cen, empty, _ = ref._side_fits(
            g, labels == miem.NORMAL, labels == miem.INVALID, cells, r, origin)
        _, clean, tol = ref._clean_sides(rms, spread, valid, nrm, k)
        fits = clean & ~(np.abs(h) > tol)
        below = np.zeros_like(clean)
        for a, b in ref._EDGE_OPPOSITE:
            for x, y in ((a, b), (b, a)):
                drop = ref._dot3(nrm[x], cen[y] - cen[x]) < -tol[x]
                beyond = empty[y] | (clean[y] & (h[y] > tol[y]) & drop)
                below[x] = clean[x] & (h[x] < -tol[x]) & beyond
        rr, cc = np.nonzero(cells)
        nofit = ~fits.any(axis=0)
        cand = nofit & below.any(axis=0)
        st, sh, both = _hanging_parts(g, labels, cells, r, below, h, nrm)
    tilt = np.degrees(np.arccos(np.clip(nrm[..., 2], -1.0, 1.0)))
    fit_sides = collections.Counter()
    fit_tilt = collections.defaultdict(list)
    for i in np.flatnonzero(~nofit):
        fit_sides[tuple(SIDES[s] for s in range(8) if fits[s, i])] += 1
        for s in np.flatnonzero(fits[:, i]):
            fit_tilt[SIDES[s]].append(tilt[s, i])
    return {
        "missed": int(rr.size), "fits": int((~nofit).sum()),
        "fits_by_sides": fit_sides.most_common(8),
        "fit_tilt_deg_p10_p50_p90": {s: np.round(np.percentile(t, [10, 50, 90]), 1).tolist()
                                     for s, t in fit_tilt.items()},
        "no_fit_below": int(cand.sum()),
        "below_45deg_ok": int((cand & st).sum()), "below_shelf_ok": int((cand & sh).sum()),
        "below_both_ok": int((cand & both).sum()),
        "no_fit_other": int((nofit & ~cand).sum()),
    }


def main(argv: list[str]) -> int:
    first, last = (int(argv[0]), int(argv[1])) if len(argv) >= 2 else (70, 80)
    if not rt.available():
        print("real scan not available (../shared/data/real)")
        return 1
    for key, value in misses(first, last).items():
        print(f"{key}: {value}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
