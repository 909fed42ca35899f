"""NumPy reference of grinding-target planning, written from docs/SPEC.md "Grinding targets".

The oracle for ``miem.plan_targets`` (the C++ core): the same selection, merging, poses and
order, computed with plain NumPy. Used by the tests (core == reference) and as the NumPy
contender of ``bench/bench_targets.py``.
"""

from __future__ import annotations

from typing import Any, Dict, List, Optional, Sequence

import numpy as np

__all__ = ["plan_targets", "abc_from_rotation", "quaternion_from_rotation", "order_path"]

ABNORMAL, EDGE = 1, 2


def quaternion_from_rotation(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0: the eigenvector of the largest eigenvalue of the
    symmetric 4x4 matrix of Bar-Itzhack's method (robust for any rotation)."""
    (a, b, c), (d, e, f), (g, h, i) = R
    K = np.array([[a - e - i, d + b, g + c, h - f],
                  [d + b, e - a - i, h + f, c - g],
                  [g + c, h + f, i - a - e, d - b],
                  [h - f, c - g, d - b, a + e + i]]) / 3.0
    w, v = np.linalg.eigh(K)
    x, y, z, qw = v[:, np.argmax(w)]
    q = np.array([qw, x, y, z])
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def abc_from_rotation(R: np.ndarray) -> np.ndarray:
    """KUKA A, B, C in degrees with R = Rz(A) Ry(B) Rx(C); A = 0 at B = +-90."""
    cb = np.hypot(R[0, 0], R[1, 0])
    b = np.arctan2(-R[2, 0], cb)
    if cb > 1e-9:
        a, c = np.arctan2(R[1, 0], R[0, 0]), np.arctan2(R[2, 1], R[2, 2])
    else:
        a, c = 0.0, np.arctan2(-R[1, 2], R[1, 1])
    return np.degrees([a, b, c])


def _length(nodes: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(nodes, axis=0), axis=1).sum()) if len(nodes) > 1 else 0.0


def order_path(points: np.ndarray, start: Optional[np.ndarray]) -> List[int]:
    """Nearest neighbour from `start` (else from point 0), then 2-opt with the first node fixed."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(pts)
    if n == 0:
        return []
    left = np.ones(n, bool)
    if start is not None:
        seq, cur = [-1], np.asarray(start, dtype=np.float64)
    else:
        seq, cur = [0], pts[0]
        left[0] = False
    while left.any():
        d2 = ((pts - cur) ** 2).sum(axis=1)
        d2[~left] = np.inf
        k = int(np.argmin(d2))  # first of equal distances
        seq.append(k)
        left[k] = False
        cur = pts[k]
    nodes = np.array([start if k < 0 else pts[k] for k in seq], dtype=np.float64)
    order = np.arange(len(seq))
    m = len(order)

    def dist(a: int, b: int) -> float:
        return float(np.linalg.norm(nodes[order[a]] - nodes[order[b]]))

    for _ in range(1000):
        changed = False
        for i in range(1, m - 1):
            for j in range(i + 1, m):
                delta = dist(i - 1, j) - dist(i - 1, i)
                if j + 1 < m:
                    delta += dist(i, j + 1) - dist(j, j + 1)
                if delta < -1e-9 * (1.0 + dist(i - 1, i)):
                    order[i:j + 1] = order[i:j + 1][::-1].copy()
                    changed = True
        if not changed:
            break
    out = [seq[k] for k in order]
    return out[1:] if start is not None else out


def _inside(poly: np.ndarray, x: float, y: float) -> bool:
    inside = False
    j = len(poly) - 1
    for i in range(len(poly)):
        (xi, yi), (xj, yj) = poly[i], poly[j]
        if (yi > y) != (yj > y) and x < (xj - xi) * (y - yi) / (yj - yi) + xi:
            inside = not inside
        j = i
    return inside


def _deeper_key(depth: float, ident: int) -> tuple:
    return (1, 0.0, ident) if np.isnan(depth) else (0, -abs(depth), ident)


def plan_targets(
    grid: np.ndarray,
    labels: np.ndarray,
    height: np.ndarray,
    defects: Sequence[Any],
    T_base_sensor: np.ndarray,
    *,
    at: str = "peak",
    kinds: Sequence[str] = ("protrusion",),
    min_height: float = 0.0,
    min_area: float = 0.0,
    min_count: int = 1,
    tool_radius: float = 0.0,
    edge_clearance: float = 0.0,
    standoff: float = 0.0,
    approach: float = 20.0,
    retract: float = 20.0,
    toward_sensor: Sequence[float] = (0.0, 0.0, 1.0),
    x_axis: Optional[Sequence[float]] = None,
    start: Optional[Sequence[float]] = None,
    order: bool = True,
    point_area: float = 0.0,
    roi_mask: Optional[np.ndarray] = None,
    roi_polygon: Optional[np.ndarray] = None,
) -> Dict[str, Any]:
    """Targets as dicts in path order, plus ``path_length`` and ``rejected`` (SPEC.md)."""
    g = np.asarray(grid, dtype=np.float64)
    if g.ndim == 2:
        g = g[None]
    H, W, _ = g.shape
    T = np.asarray(T_base_sensor, dtype=np.float64).reshape(-1, 4, 4)
    rows = np.arange(H) if len(T) == H and len(T) > 1 else np.zeros(H, int)
    R_rows, t_rows = T[rows, :3, :3], T[rows, :3, 3]
    base = np.einsum("rij,rcj->rci", R_rows, g) + t_rows[:, None, :]
    finite = np.isfinite(g).all(axis=2)
    lab = np.asarray(labels).reshape(H, W)
    hgt = np.asarray(height, dtype=np.float64).reshape(-1)
    toward = np.asarray(toward_sensor, dtype=np.float64)
    toward = toward / np.linalg.norm(toward)
    edge_pts = base[(lab == EDGE) & finite] if edge_clearance > 0 else np.zeros((0, 3))
    rejected = dict(kind=0, height=0, size=0, roi=0, edge=0)
    cands = []
    for d in defects:
        if d.kind not in kinds:
            rejected["kind"] += 1
            continue
        if min_height > 0 and not abs(d.peak_height) >= min_height:
            rejected["height"] += 1
            continue
        idx = np.asarray(d.indices, dtype=np.int64)
        r, c = idx // W, idx % W
        keep = (lab[r, c] == ABNORMAL) & finite[r, c]
        idx, r, c = idx[keep], r[keep], c[keep]
        if idx.size == 0 or idx.size < min_count:
            rejected["size"] += 1
            continue
        h = hgt[idx]
        fin = np.isfinite(h)
        peak = int(idx[np.flatnonzero(fin)[np.argmax(np.abs(h[fin]))]]) if fin.any() else int(idx[0])
        pr, pc = divmod(peak, W)
        n = np.asarray(d.normal, dtype=np.float64)
        n = n / np.linalg.norm(n) if np.isfinite(n).all() else toward
        if n @ toward < 0:
            n = -n
        n = R_rows[pr] @ n
        n = n / np.linalg.norm(n)
        if point_area > 0:
            areas = np.full(idx.size, point_area)
        else:
            def diff(r0, c0, r1, c1, rr, cc):
                a = (r0 >= 0) & (r0 < H) & (c0 >= 0) & (c0 < W)
                b = (r1 >= 0) & (r1 < H) & (c1 >= 0) & (c1 < W)
                a[a] = finite[r0[a], c0[a]]
                b[b] = finite[r1[b], c1[b]]
                p0 = base[np.clip(r0, 0, H - 1), np.clip(c0, 0, W - 1)]
                p1 = base[np.clip(r1, 0, H - 1), np.clip(c1, 0, W - 1)]
                here = base[rr, cc]
                out = np.where((a & b)[:, None], 0.5 * (p1 - p0),
                               np.where(a[:, None], here - p0, p1 - here))
                return out, a | b

            du, ok_u = diff(r, c - 1, r, c + 1, r, c)
            dv, ok_v = diff(r - 1, c, r + 1, c, r, c)
            areas = np.abs(np.cross(du, dv) @ n)
            ok = ok_u & ok_v
            fill = areas[ok].mean() if ok.any() else 0.0
            areas = np.where(ok, areas, fill)
        area = float(areas.sum())
        same = np.isfinite(h) & (h != 0) & ((h > 0) == (d.peak_height > 0))
        volume = float((np.abs(h[same]) * areas[same]).sum()) if np.isfinite(d.peak_height) else 0.0
        if area < min_area:
            rejected["size"] += 1
            continue
        ps = g[pr, pc]
        if (roi_mask is not None and not np.asarray(roi_mask).reshape(-1)[peak]) or (
                roi_polygon is not None and not _inside(np.asarray(roi_polygon), ps[0], ps[1])):
            rejected["roi"] += 1
            continue
        pts_b, pts_s = base[r, c], g[r, c]
        anchor = base[pr, pc] if at == "peak" else pts_b.mean(axis=0)
        anchor_s = ps if at == "peak" else pts_s.mean(axis=0)
        if edge_clearance > 0 and len(edge_pts) and \
                (((edge_pts - anchor) ** 2).sum(axis=1) < edge_clearance ** 2).any():
            rejected["edge"] += 1
            continue
        cands.append(dict(id=int(d.id), depth=float(d.peak_height), peak=peak, row=pr, normal=n,
                          anchor=anchor, anchor_scan=anchor_s, area=area, volume=volume,
                          count=int(idx.size), sum_b=pts_b.sum(axis=0), sum_s=pts_s.sum(axis=0)))

    # single-linkage components of "anchors closer than tool_radius"
    m = len(cands)
    comp = list(range(m))
    if tool_radius > 0 and m:
        A = np.array([cd["anchor"] for cd in cands])
        close = ((A[:, None] - A[None]) ** 2).sum(axis=2) < tool_radius ** 2
        changed = True  # propagate the smallest index through each component
        lab_c = np.arange(m)
        while changed:
            new = np.array([lab_c[close[i]].min() for i in range(m)])
            changed = bool((new != lab_c).any())
            lab_c = new
        comp = list(lab_c)
    groups: Dict[int, List[int]] = {}
    for i, k in enumerate(comp):
        groups.setdefault(int(k), []).append(i)
    targets = []
    for members in groups.values():
        cs = [cands[i] for i in members]
        head = min(cs, key=lambda cd: _deeper_key(cd["depth"], cd["id"]))
        count = sum(cd["count"] for cd in cs)
        if at == "peak":
            point, point_s = head["anchor"], head["anchor_scan"]
        else:
            point = sum(cd["sum_b"] for cd in cs) / count
            point_s = sum(cd["sum_s"] for cd in cs) / count
        n = head["normal"]
        z = -n
        Rh = R_rows[head["row"]]
        ref = np.asarray(x_axis, dtype=np.float64) if x_axis is not None else Rh[:, 1]
        x = ref - (ref @ z) * z
        if np.linalg.norm(x) <= 1e-9 * np.linalg.norm(ref):
            x = Rh[:, 0] - (Rh[:, 0] @ z) * z
        if np.linalg.norm(x) <= 1e-9:
            e = np.eye(3)[int(np.argmin(np.abs(z)))]
            x = e - (e @ z) * z
        x = x / np.linalg.norm(x)
        rot = np.column_stack([x, np.cross(z, x), z])
        pos = point + standoff * n
        targets.append(dict(
            point=point, point_scan=point_s, normal=n, rotation=rot, position=pos,
            approach_point=pos + approach * n, retract_point=pos + retract * n,
            quaternion=quaternion_from_rotation(rot), abc=abc_from_rotation(rot),
            depth=head["depth"], area=sum(cd["area"] for cd in cs),
            volume=sum(cd["volume"] for cd in cs), count=count,
            defect_ids=tuple(sorted(cd["id"] for cd in cs)), peak_index=head["peak"],
            _key=_deeper_key(head["depth"], head["id"])))
    targets.sort(key=lambda t: t["_key"])
    start_v = None if start is None else np.asarray(start, dtype=np.float64)
    pts = np.array([t["point"] for t in targets]).reshape(-1, 3)
    seq = order_path(pts, start_v) if order else list(range(len(targets)))
    ordered = [targets[k] for k in seq]
    nodes = pts[seq] if start_v is None else np.vstack([start_v, pts[seq]])
    return dict(targets=ordered, path_length=_length(nodes), rejected=rejected,
                defects_used=m)
