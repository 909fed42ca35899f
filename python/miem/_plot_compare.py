"""Deviation colour map of a comparison (``miem compare``): a top view of the scan coloured by
signed deviation from the reference (not covered grey, the largest defects numbered) and the
deviation histogram with the tolerance band."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ._plot import _matplotlib

_MAX_POINTS = 400_000


def plot_deviation(points: np.ndarray, deviation: np.ndarray, result: Any, counts: dict,
                   path: Path, *, title: str = "", units: str = "mm", max_labels: int = 10,
                   size: tuple = (12.0, 6.0), dpi: int = 100) -> None:
    """Write a PNG of a comparison. ``points`` (N, 3) in the scan's frame, ``deviation`` (N,)
    as in ``result`` (a :class:`miem.CompareResult`), ``counts`` points per label name."""
    Figure, FigureCanvasAgg = _matplotlib()
    tol = float(result.params["tolerance"])
    fig = Figure(figsize=size, dpi=dpi)
    FigureCanvasAgg(fig)
    gs = fig.add_gridspec(1, 2, width_ratios=[1.4, 1.0])
    ax = fig.add_subplot(gs[0])
    finite = np.isfinite(points).all(axis=1)
    step = max(1, int(finite.sum()) // _MAX_POINTS)
    idx = np.flatnonzero(finite)[::step]
    cov = idx[np.isfinite(deviation[idx])]
    unc = idx[~np.isfinite(deviation[idx])]
    lim = 3.0 * tol
    ax.scatter(points[unc, 0], points[unc, 1], s=0.3, c="0.8", linewidths=0, rasterized=True,
               label="not covered")
    order = cov[np.argsort(np.abs(deviation[cov]))]  # largest on top
    sc = ax.scatter(points[order, 0], points[order, 1], s=0.3, c=deviation[order],
                    cmap="RdBu_r", vmin=-lim, vmax=lim, linewidths=0, rasterized=True)
    cb = fig.colorbar(sc, ax=ax, fraction=0.04, pad=0.02, extend="both")
    cb.set_label(f"deviation ({units}): > 0 excess, < 0 missing")
    for v in (-tol, tol):
        cb.ax.axhline(v, color="k", lw=0.8)
    for d in result.defects[:max_labels]:
        c = d.centroid
        r = max(float(d.extent) / 2.0, 3.0 * float(result.params["scan_spacing"]))
        ax.add_patch(_circle(fig, (c[0], c[1]), r))
        ax.annotate(str(d.id), (c[0], c[1]), xytext=(4, 4), textcoords="offset points",
                    fontsize=8, bbox={"boxstyle": "round,pad=0.1", "fc": "white", "ec": "none",
                                      "alpha": 0.7})
    ax.set_aspect("equal")
    ax.set_xlabel(f"x ({units})")
    ax.set_ylabel(f"y ({units})")
    ax.set_title(title or "deviation from the reference")

    ax2 = fig.add_subplot(gs[1])
    vals = deviation[np.isfinite(deviation)]
    if vals.size:
        hi = max(lim, float(np.percentile(np.abs(vals), 99.5)))
        ax2.hist(np.clip(vals, -hi, hi), bins=120, range=(-hi, hi), color="0.4")
        ax2.set_yscale("log")
    for v in (-tol, tol):
        ax2.axvline(v, color="r", lw=0.8, ls="--")
    c = counts
    reg = result.registration
    text = [f"within {c['WITHIN']:,}", f"excess {c['EXCESS']:,}", f"missing {c['MISSING']:,}",
            f"not covered {c['NOT_COVERED']:,}", f"defects {len(result.defects):,}"]
    if reg is not None:
        text.append(f"fit rmse {reg.rmse:.3f} {units}, inliers {100 * reg.inlier_fraction:.1f} %")
    ax2.text(0.02, 0.98, "\n".join(text), transform=ax2.transAxes, va="top", fontsize=8,
             bbox={"fc": "white", "ec": "0.7"})
    ax2.set_xlabel(f"deviation ({units}); tolerance +/-{tol:g}")
    ax2.set_ylabel("points")
    fig.tight_layout()
    fig.savefig(str(path))


def _circle(fig: Any, center: tuple, radius: float) -> Any:
    from matplotlib.patches import Circle  # noqa: PLC0415

    return Circle(center, radius, fill=False, ec="k", lw=0.8)
