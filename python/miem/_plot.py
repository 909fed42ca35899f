"""Pictures of a labelled scan for people at the cell: labels in 3-D, height map, defect list.

Drawn with matplotlib's object API on an Agg canvas: no pyplot, no global backend switch, so it
is safe inside an interactive session and on a headless controller. Installed with
``pip install "miem[plot]"``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Literal

import numpy as np

from .io import LABEL_COLORS, MissingDependencyError

__all__ = ["plot_scan"]

_NORMAL, _ABNORMAL, _EDGE = 0, 1, 2
_MAX_3D_NORMAL = 60_000  # NORMAL points drawn in the 3-D view (a random subset beyond that)
_MAX_3D_EDGE = 30_000
_LABEL_BOX = {"boxstyle": "round,pad=0.12", "fc": "white", "ec": "none", "alpha": 0.75}


def _matplotlib() -> Any:
    try:
        import matplotlib  # noqa: F401
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as exc:
        raise MissingDependencyError(
            'plotting needs the optional package matplotlib, which is not installed: '
            'pip install "miem[plot]"'
        ) from exc
    return Figure, FigureCanvasAgg


def _fmt_len(v: float) -> str:
    return f"{v:+.3f}" if np.isfinite(v) else "n/a"


def _marker_size(n: int, width_in: float, height_in: float, lo: float, hi: float) -> float:
    """Marker area (points^2) that roughly tiles an axes of the given size with n points."""
    area_pt2 = width_in * height_in * 72.0 * 72.0
    return float(np.clip(area_pt2 / max(n, 1) * 1.3, lo, hi))


def _spacing(points: np.ndarray) -> float:
    """Typical distance between neighbouring points in the x-y plane (for marker sizes)."""
    if points.ndim == 3:
        meds = []
        for d in (np.diff(points[..., :2], axis=0), np.diff(points[..., :2], axis=1)):
            n = np.hypot(d[..., 0], d[..., 1]).ravel()
            n = n[np.isfinite(n) & (n > 0)]
            if n.size:
                meds.append(float(np.median(n)))
        if meds:
            return max(meds)
    flat = points.reshape(-1, 3)
    flat = flat[np.isfinite(flat).all(axis=1)]
    area = float(np.ptp(flat[:, 0]) * np.ptp(flat[:, 1])) if flat.shape[0] > 1 else 0.0
    return float(np.sqrt(area / max(flat.shape[0], 1))) if area > 0 else 1.0


def _fit_markers(fig: Any, ax: Any, collection: Any, spacing: float, dpi: int) -> None:
    """Size square markers so that they tile the axes at the scan's point spacing."""
    fig.canvas.draw()
    bbox = ax.get_window_extent()
    x0, x1 = ax.get_xlim()
    px_per_unit = bbox.width / max(abs(x1 - x0), 1e-300)
    side_pt = 1.15 * spacing * px_per_unit * 72.0 / dpi  # overlap a little: no seams
    collection.set_sizes([float(np.clip(side_pt, 0.3, 30.0)) ** 2])


def plot_scan(
    points: np.ndarray,
    result: Any,
    path: str | os.PathLike[str],
    *,
    title: str | None = None,
    units: str = "mm",
    view: Literal["3d", "top"] = "3d",
    max_labels: int = 10,
    size: tuple[float, float] = (16.0, 6.0),
    dpi: int = 100,
    seed: int = 0,
    plan: Any = None,
) -> Path:
    """Draw a labelled scan and save it as a PNG.

    Three panels: the cloud coloured by label (NORMAL grey, EDGE blue, ABNORMAL red; 3-D or
    top view) with the largest defects circled and numbered; a top-view height map of ``z``
    with a colour bar in `units` and the same numbered circles; and a table of those defects
    (kind, peak height over the local surface, point count, centroid).

    Parameters
    ----------
    points : ndarray, shape (H, W, 3) or (N, 3)
        The scan that `result` labels (same number of points, same order).
    result : miem.DetectResult
        Its detection result.
    path : str or os.PathLike
        Output PNG file (written atomically).
    title : str, optional
        Figure title (default: none besides the counts).
    units : str
        Length unit of the coordinates, for the axes and the colour bar.
    view : {"3d", "top"}
        The first panel: a perspective view (the paper's Figures 7, 10, 11) or a top view.
    max_labels : int
        Number of defects, largest ``|peak height|`` first, circled, numbered and listed.
    size : (float, float)
        Figure size in inches (width, height).
    dpi : int
        Pixels per inch: the PNG is ``size * dpi`` pixels.
    seed : int
        Seed of the random subset of NORMAL points drawn in the 3-D view of a large scan.
    plan : miem.TargetPlan, optional
        Grinding targets of this scan (:func:`miem.plan_targets`): drawn on the height map,
        numbered in path order, with the path between them.

    Returns
    -------
    pathlib.Path
        `path`.

    Raises
    ------
    MissingDependencyError
        matplotlib is not installed.
    ValueError
        `points` and `result` do not match, or a bad option.
    """
    from .io import _atomic

    if view not in ("3d", "top"):
        raise ValueError(f"view: expected '3d' or 'top', got {view!r}")
    grid_pts = np.asarray(points, dtype=np.float64)
    if grid_pts.ndim not in (2, 3) or grid_pts.shape[-1] != 3:
        raise ValueError(f"points: expected shape (N, 3) or (H, W, 3), got {grid_pts.shape}")
    pts = grid_pts.reshape(-1, 3)
    labels = np.asarray(result.labels).reshape(-1)
    if labels.size != pts.shape[0]:
        raise ValueError(
            f"result: {labels.size} labels for {pts.shape[0]} points; plot the scan it came from"
        )
    Figure, FigureCanvasAgg = _matplotlib()
    from matplotlib.lines import Line2D
    from matplotlib.patches import Circle
    from matplotlib.ticker import MaxNLocator

    finite = np.isfinite(pts).all(axis=1)
    if not finite.any():
        raise ValueError("points: no finite point to draw")
    height = np.asarray(result.height, dtype=np.float64).reshape(-1)
    defects = list(result.defects)[: max(0, int(max_labels))]
    n_def = len(result.defects)
    counts = {name: int(np.count_nonzero(labels == v))
              for name, v in (("NORMAL", 0), ("ABNORMAL", 1), ("EDGE", 2), ("INVALID", 3))}
    spacing = _spacing(grid_pts)

    fig = Figure(figsize=size, dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    gs = fig.add_gridspec(1, 3, width_ratios=[1.3, 1.1, 0.8])
    sub = (f"{counts['ABNORMAL']:,} abnormal points in {n_def:,} defects, "
           f"{counts['EDGE']:,} edge, {counts['NORMAL']:,} normal, "
           f"{counts['INVALID']:,} missing")
    fig.suptitle(f"{title}\n{sub}" if title else sub, fontsize=11)

    xyz = pts[finite]
    lab = labels[finite]
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    span = np.maximum(hi - lo, 1e-12)
    pad = 0.02 * span
    rng = np.random.default_rng(seed)
    colors = {v: LABEL_COLORS[v] for v in (_NORMAL, _ABNORMAL, _EDGE)}

    # Peak point of each listed defect: where to grind.
    marks = []
    for d in defects:
        idx = np.asarray(d.indices)
        h = height[idx]
        k = int(np.nanargmax(np.abs(h))) if np.isfinite(h).any() else 0
        marks.append((d, pts[idx[k]]))
    ring = 0.035 * float(max(span[0], span[1]))  # circle radius, data units

    def circle_defects(axis: Any, color: str) -> None:
        for k, (d, p) in enumerate(marks):
            axis.add_patch(Circle((p[0], p[1]), ring, fill=False, ec=color, lw=1.2, zorder=4))
            # Turn the number around its circle from one defect to the next, so that the
            # numbers of neighbouring defects do not print on top of each other.
            a = np.deg2rad(45.0 + 90.0 * (k % 4))
            axis.text(p[0] + 1.35 * ring * np.cos(a), p[1] + 1.35 * ring * np.sin(a), f"{d.id}",
                      color=color, fontsize=8, fontweight="bold", ha="center", va="center",
                      zorder=5, bbox=_LABEL_BOX)

    def top_axes(axis: Any) -> None:
        axis.set_aspect("equal")
        axis.set_xlim(lo[0] - pad[0], hi[0] + pad[0])
        axis.set_ylim(lo[1] - pad[1], hi[1] + pad[1])
        axis.set_xlabel(f"x ({units})", fontsize=8)
        axis.set_ylabel(f"y ({units})", fontsize=8)
        axis.tick_params(labelsize=7)

    # Panel 1: labels, 3-D or top view.
    fitted = []  # (axes, collection) whose markers tile the scan
    if view == "3d":
        # Draw in a fixed order (NORMAL, EDGE, ABNORMAL, numbers) rather than by depth, so that
        # abnormal points and their numbers are never hidden behind the surface.
        ax = fig.add_subplot(gs[0, 0], projection="3d", computed_zorder=False)
        abn_size = 10.0 if counts["ABNORMAL"] <= 200 else 4.0
        for v, cap, size_pt, alpha in ((_NORMAL, _MAX_3D_NORMAL, 0.6, 0.35),
                                       (_EDGE, _MAX_3D_EDGE, 1.5, 0.8),
                                       (_ABNORMAL, None, abn_size, 1.0)):
            sel = np.flatnonzero(lab == v)
            if cap is not None and sel.size > cap:
                sel = np.sort(rng.choice(sel, size=cap, replace=False))
            if sel.size:
                ax.scatter(xyz[sel, 0], xyz[sel, 1], xyz[sel, 2], s=size_pt, c=[colors[v]],
                           alpha=alpha, linewidths=0, depthshade=False, rasterized=True,
                           zorder={_NORMAL: 1, _EDGE: 2, _ABNORMAL: 3}[v])
        for d, p in marks:
            ax.text(p[0], p[1], p[2] + 0.05 * span[2], f"{d.id}", color="black", fontsize=8,
                    fontweight="bold", ha="center", va="bottom", bbox=_LABEL_BOX, zorder=5)
        ax.set_box_aspect((span[0], span[1], max(span[2], 0.25 * max(span[0], span[1]))),
                          zoom=1.25)
        ax.zaxis.set_major_locator(MaxNLocator(5))
        ax.set_xlabel(f"x ({units})", fontsize=8, labelpad=-4)
        ax.set_ylabel(f"y ({units})", fontsize=8, labelpad=-4)
        ax.set_zlabel(f"z ({units})", fontsize=8, labelpad=-4)
        ax.tick_params(labelsize=7, pad=-2)
        ax.view_init(elev=35, azim=-60)
    else:
        ax = fig.add_subplot(gs[0, 0])
        for v, order in ((_NORMAL, 1), (_EDGE, 2)):
            sel = lab == v
            if sel.any():
                coll = ax.scatter(xyz[sel, 0], xyz[sel, 1], s=1.0, c=[colors[v]], marker="s",
                                  linewidths=0, rasterized=True, zorder=order)
                fitted.append((ax, coll))
        sel = lab == _ABNORMAL
        if sel.any():
            ax.scatter(xyz[sel, 0], xyz[sel, 1], s=10.0, c=[colors[_ABNORMAL]], linewidths=0,
                       zorder=3)
        circle_defects(ax, "black")
        top_axes(ax)
    ax.set_title("labels", fontsize=10)
    handles = [Line2D([], [], ls="", marker="o", ms=6, mfc=colors[v], mec="none", label=txt)
               for v, txt in ((_ABNORMAL, f"ABNORMAL ({counts['ABNORMAL']:,})"),
                              (_EDGE, f"EDGE ({counts['EDGE']:,})"),
                              (_NORMAL, f"NORMAL ({counts['NORMAL']:,})"))]

    # Panel 2: height map (z), top view, defects circled.
    ax2 = fig.add_subplot(gs[0, 1])
    zlo, zhi = (float(v) for v in np.percentile(xyz[:, 2], [0.5, 99.5]))
    if zhi <= zlo:
        zlo, zhi = float(xyz[:, 2].min()), float(xyz[:, 2].max()) + 1e-9
    order = np.argsort(xyz[:, 2], kind="stable")  # higher points on top
    sc = ax2.scatter(xyz[order, 0], xyz[order, 1], c=xyz[order, 2], s=1.0, marker="s",
                     cmap="viridis", vmin=zlo, vmax=zhi, linewidths=0, rasterized=True)
    fitted.append((ax2, sc))
    circle_defects(ax2, "red")
    top_axes(ax2)
    ax2.set_title("height map", fontsize=10)
    if plan is not None:
        _draw_plan(ax2, plan, ring)
    cb = fig.colorbar(sc, ax=ax2, shrink=0.85, pad=0.02)
    cb.set_label(f"z ({units})", fontsize=8)
    cb.ax.tick_params(labelsize=7)

    # Panel 3: the defect table.
    ax3 = fig.add_subplot(gs[0, 2])
    ax3.axis("off")
    ax3.set_title(f"largest defects ({len(defects)} of {n_def:,})", fontsize=10)
    if defects:
        rows = [[f"{d.id}", d.kind, _fmt_len(d.peak_height), f"{d.count}",
                 f"{p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f}"] for d, p in marks]
        table = ax3.table(cellText=rows,
                          colLabels=["#", "kind", f"peak ({units})", "points",
                                     f"peak point x, y, z ({units})"],
                          loc="upper center", cellLoc="right", colLoc="right")
        table.auto_set_font_size(False)
        table.set_fontsize(7.5)
        table.auto_set_column_width(list(range(5)))
        table.scale(1.0, 1.25)
        for (r, _c), cell in table.get_celld().items():
            cell.set_edgecolor("#cccccc")
            if r == 0:
                cell.set_facecolor("#eeeeee")
    else:
        ax3.text(0.5, 0.9, "no abnormal points", ha="center", va="top", fontsize=9,
                 transform=ax3.transAxes)
    fig.legend(handles=handles, loc="outside lower center", ncol=3, fontsize=8, frameon=False)
    note = ("peak height: signed distance from the local surface\n"
            "(> 0 protrusion, < 0 pit); circles mark the peak points")
    plane = getattr(result, "plane", None)
    if plane is not None:
        n = plane.normal
        note = (f"MIEM plane: n = ({n[0]:+.4f}, {n[1]:+.4f}, {n[2]:+.4f}), "
                f"rms {plane.rms:.4g} {units}\n" + note)
    ax3.text(0.0, 0.02, note, fontsize=7, transform=ax3.transAxes, va="bottom", color="#333333")

    for axis, coll in fitted:
        _fit_markers(fig, axis, coll, spacing, dpi)
    out = Path(path)
    with _atomic(out) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)
    return out


def _draw_plan(axis: Any, plan: Any, ring: float) -> None:
    """Targets (numbered in path order) and the path between them, in scan x-y."""
    xy = np.array([t.point_scan[:2] for t in plan.targets], dtype=np.float64).reshape(-1, 2)
    if xy.shape[0] == 0:
        return
    axis.plot(xy[:, 0], xy[:, 1], "-", color="white", lw=2.4, zorder=6)
    axis.plot(xy[:, 0], xy[:, 1], "-", color="#d62728", lw=1.2, zorder=7)
    axis.scatter(xy[:, 0], xy[:, 1], s=36, marker="v", c="#ff7f0e", edgecolors="black",
                 linewidths=0.6, zorder=8)
    for k, (x, y) in enumerate(xy[:50]):
        axis.text(x, y - 0.9 * ring, f"T{k + 1}", color="black", fontsize=7, ha="center",
                  va="top", zorder=9, bbox=_LABEL_BOX)
    axis.set_title(f"height map, {xy.shape[0]} targets, path {plan.path_length:.1f} "
                   f"{plan.units}", fontsize=10)
