"""Planar collision geometry: convex polygons, separating-axis penetration and contacts.

Polygons are (K, 2) arrays of vertices in counter-clockwise order (world metres).
`penetration` is the separating-axis test returning the minimum translation that pushes
one polygon out of another; `PolygonSet` holds a fixed set of obstacle polygons with
precomputed edge normals and bounding circles so that checking a few walker parts
against ~100 obstacles each physics step costs tens of microseconds.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit


@dataclass(frozen=True, slots=True, eq=False)
class Contact:
    """An overlap between a walker part and an obstacle.

    depth [m] and normal (unit, 2-vector) form the minimum translation that pushes the
    part out of the obstacle; point is an approximate contact point (the centroid of the
    overlap region).
    """

    part: str
    obstacle: str
    depth: float
    normal: np.ndarray
    point: np.ndarray


def rectangle(cx: float, cy: float, yaw: float, sx: float, sy: float) -> np.ndarray:
    """Corners (4×2, CCW) of a rectangle with centre (cx, cy), heading yaw and sides sx, sy."""
    c, s = np.cos(yaw), np.sin(yaw)
    hx, hy = 0.5 * sx, 0.5 * sy
    local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    rot = np.array([[c, -s], [s, c]])
    return local @ rot.T + np.array([cx, cy])


def body_rectangle(
    pose: Sequence[float], x_min: float, x_max: float, y_min: float, y_max: float
) -> np.ndarray:
    """Corners (4×2, CCW, world) of the body-frame rectangle [x_min, x_max]×[y_min, y_max]
    of a robot at planar pose (x, y, θ)."""
    x, y, th = (float(v) for v in pose)
    c, s = np.cos(th), np.sin(th)
    local = np.array([[x_min, y_min], [x_max, y_min], [x_max, y_max], [x_min, y_max]])
    return local @ np.array([[c, -s], [s, c]]).T + np.array([x, y])


def _check_polygon(p: np.ndarray, name: str) -> np.ndarray:
    p = np.asarray(p, dtype=float)
    if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] < 3:
        raise ValueError(f"{name} must be a (K>=3, 2) array of vertices, got shape {p.shape}")
    return p


def _check_parts(parts: np.ndarray) -> np.ndarray:
    parts = np.asarray(parts, dtype=float)
    if parts.ndim != 3 or parts.shape[2] != 2 or parts.shape[1] < 3:
        raise ValueError(f"parts must be a (P, K>=3, 2) array, got shape {parts.shape}")
    return parts


def edge_normals(p: np.ndarray) -> np.ndarray:
    """Outward unit normals (K×2) of the edges p[i] → p[i+1] of a CCW polygon (K×2), or
    of each polygon of a stack (..., K, 2) of them."""
    p = np.asarray(p, dtype=float)
    e = p[..., [*range(1, p.shape[-2]), 0], :] - p
    n = np.stack([e[..., 1], -e[..., 0]], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _separated(plo: np.ndarray, phi: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(P, M) whether the axis-aligned box [plo, phi] of each part (P, 2) is apart from
    (or touches) the box [lo, hi] of each polygon (M, 2)."""
    return ((lo[None] >= phi[:, None]) | (hi[None] <= plo[:, None])).any(axis=2)


def _axis_pushes(axes: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pair q and axis, how far polygon a[q] must move along +axes[q] (first) or
    along −axes[q] (second) to clear b[q]; both positive on every axis: they overlap."""
    pa = np.einsum("qad,qkd->qak", axes, a)
    pb = np.einsum("qad,qkd->qak", axes, b)
    return pb.max(axis=2) - pa.min(axis=2), pa.max(axis=2) - pb.min(axis=2)


def _sat(a: np.ndarray, b: np.ndarray, axes: np.ndarray) -> tuple[float, np.ndarray] | None:
    pa = a @ axes.T  # (Ka, M) projections of a's vertices on every axis
    pb = b @ axes.T
    # Overlap when a is pushed along +axis (b's max − a's min) or along −axis.
    push_pos = pb.max(axis=0) - pa.min(axis=0)
    push_neg = pa.max(axis=0) - pb.min(axis=0)
    if min(push_pos.min(), push_neg.min()) <= 0.0:
        return None
    i_pos, i_neg = int(np.argmin(push_pos)), int(np.argmin(push_neg))
    if push_pos[i_pos] <= push_neg[i_neg]:
        return float(push_pos[i_pos]), axes[i_pos].copy()
    return float(push_neg[i_neg]), -axes[i_neg]


def penetration(a: np.ndarray, b: np.ndarray) -> tuple[float, np.ndarray] | None:
    """Separating-axis test between convex polygons a and b (CCW vertex arrays).

    Returns (depth, normal) — moving a by depth·normal makes the two just touch, and no
    shorter translation does — or None when they do not overlap (touching is no overlap).
    """
    a = _check_polygon(a, "a")
    b = _check_polygon(b, "b")
    return _sat(a, b, np.vstack([edge_normals(a), edge_normals(b)]))


def clip_convex(subject: np.ndarray, clip: np.ndarray) -> np.ndarray:
    """Intersection of two convex CCW polygons (Sutherland–Hodgman); (0, 2) if empty."""
    # Plain floats: for a handful of vertices this is far faster than numpy.
    out = [(float(x), float(y)) for x, y in np.asarray(subject, dtype=float)]
    cl = [(float(x), float(y)) for x, y in np.asarray(clip, dtype=float)]
    for i in range(len(cl)):
        if not out:
            break
        (x0, y0), (x1, y1) = cl[i], cl[(i + 1) % len(cl)]
        ex, ey = x1 - x0, y1 - y0
        # Cross product with the clip edge: >= 0 is on its left, i.e. inside.
        sides = [ex * (py - y0) - ey * (px - x0) for px, py in out]
        pts = []
        for k, (px, py) in enumerate(out):
            sk, sn = sides[k], sides[(k + 1) % len(out)]
            if sk >= 0:
                pts.append((px, py))
            if (sk >= 0) != (sn >= 0):
                qx, qy = out[(k + 1) % len(out)]
                f = sk / (sk - sn)
                pts.append((px + f * (qx - px), py + f * (qy - py)))
        out = pts
    return np.array(out, dtype=float).reshape(-1, 2)


def polygon_centroid(p: np.ndarray) -> np.ndarray:
    """Area centroid of a simple polygon (the vertex mean if it is degenerate)."""
    pts = [(float(x), float(y)) for x, y in np.asarray(p, dtype=float)]
    a = cx = cy = 0.0
    for (x0, y0), (x1, y1) in zip(pts, pts[1:] + pts[:1], strict=True):
        c = x0 * y1 - x1 * y0
        a += c
        cx += (x0 + x1) * c
        cy += (y0 + y1) * c
    if abs(a) < 1e-12:
        return np.asarray(p, dtype=float).mean(axis=0)
    return np.array([cx, cy]) / (3.0 * a)


def contact_point(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Centroid of the overlap of two convex polygons (mean of both centroids if none)."""
    overlap = clip_convex(a, b)
    if len(overlap) < 3:
        return 0.5 * (a.mean(axis=0) + b.mean(axis=0))
    return polygon_centroid(overlap)


def point_polygon_distance(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Signed distance from each point (N×2) to a convex CCW polygon (negative inside)."""
    points = np.atleast_2d(np.asarray(points, dtype=float))
    p0 = poly
    e = np.roll(poly, -1, axis=0) - p0  # (K, 2)
    d = points[:, None, :] - p0[None, :, :]  # (N, K, 2)
    t = np.clip((d * e).sum(-1) / (e * e).sum(-1), 0.0, 1.0)
    closest = p0[None] + t[..., None] * e[None]
    dist = np.linalg.norm(points[:, None, :] - closest, axis=-1).min(axis=1)
    inside = (np.einsum("nkj,kj->nk", d, edge_normals(poly)) <= 0).all(axis=1)
    return np.where(inside, -dist, dist)


def polygon_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Signed distance between convex polygons: the gap if apart, −(penetration depth)
    if they overlap."""
    a = _check_polygon(a, "a")
    b = _check_polygon(b, "b")
    pen = penetration(a, b)
    if pen is not None:
        return -pen[0]
    return float(min(point_polygon_distance(a, b).min(), point_polygon_distance(b, a).min()))


@njit(cache=True, nogil=True)
def _vertex_edge_gap(a: np.ndarray, b: np.ndarray) -> float:
    """The least distance from a vertex of polygon a (K, 2) to an edge of polygon b (L, 2)."""
    best = np.inf
    n = b.shape[0]
    for k in range(a.shape[0]):
        vx, vy = a[k, 0], a[k, 1]
        for j in range(n):
            ax, ay = b[j, 0], b[j, 1]
            ex, ey = b[(j + 1) % n, 0] - ax, b[(j + 1) % n, 1] - ay
            dx, dy = vx - ax, vy - ay
            t = min(max((dx * ex + dy * ey) / (ex * ex + ey * ey), 0.0), 1.0)
            gx, gy = dx - t * ex, dy - t * ey
            best = min(best, math.sqrt(gx * gx + gy * gy))
    return best


@njit(cache=True, nogil=True)
def _vertex_edge_gaps(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per pair q, the least distance from a vertex of a[q] (Q, K, 2) to an edge of b[q]
    (Q, L, 2)."""
    out = np.empty(a.shape[0])
    for q in range(a.shape[0]):
        out[q] = _vertex_edge_gap(a[q], b[q])
    return out


@njit(cache=True, nogil=True)
def _apart(a: np.ndarray, b: np.ndarray, slack: float) -> bool:
    """Whether an edge normal of convex polygon a or b (CCW) separates them by more than
    slack (the separating-axis test)."""
    for poly in (a, b):
        n = poly.shape[0]
        for j in range(n):
            ex, ey = poly[(j + 1) % n, 0] - poly[j, 0], poly[(j + 1) % n, 1] - poly[j, 1]
            norm = math.sqrt(ex * ex + ey * ey)
            nx, ny = ey / norm, -ex / norm
            a_lo, a_hi, b_lo, b_hi = np.inf, -np.inf, np.inf, -np.inf
            for k in range(a.shape[0]):
                d = nx * a[k, 0] + ny * a[k, 1]
                a_lo, a_hi = min(a_lo, d), max(a_hi, d)
            for k in range(b.shape[0]):
                d = nx * b[k, 0] + ny * b[k, 1]
                b_lo, b_hi = min(b_lo, d), max(b_hi, d)
            if min(b_hi - a_lo, a_hi - b_lo) < -slack:
                return True
    return False


@njit(cache=True, nogil=True)
def _least_gap(
    parts: np.ndarray, polys: np.ndarray, lo: np.ndarray, hi: np.ndarray, horizon: float
) -> float:
    """min(horizon, the least vertex-to-edge distance between a part (P, K, 2) and a
    polygon (M, L, 2) whose bounding boxes (lo, hi: (M, 2)) come within horizon); 0 as
    soon as a part and a polygon are not apart by more than a rounding error."""
    best = horizon
    for p in range(parts.shape[0]):
        part = parts[p]
        x0, y0 = part[:, 0].min() - horizon, part[:, 1].min() - horizon
        x1, y1 = part[:, 0].max() + horizon, part[:, 1].max() + horizon
        for m in range(polys.shape[0]):
            if lo[m, 0] >= x1 or hi[m, 0] <= x0 or lo[m, 1] >= y1 or hi[m, 1] <= y0:
                continue
            if not _apart(part, polys[m], 1e-9):
                return 0.0
            best = min(best, _vertex_edge_gap(part, polys[m]), _vertex_edge_gap(polys[m], part))
    return best


_CANDIDATE_MARGIN_M = 0.25


class PolygonSet:
    """A fixed set of named convex polygons with the same vertex count (e.g. rectangles).

    Edge normals, bounding circles and axis-aligned bounding boxes are computed once;
    `contacts` prefilters by bounding boxes (tighter than circles for long walls) and runs
    the separating-axis test, vectorised, only on the few candidate pairs.
    """

    def __init__(self, names: Sequence[str], polygons: np.ndarray) -> None:
        polys = np.asarray(polygons, dtype=float)
        if polys.size == 0:
            polys = np.zeros((0, 4, 2))
        if polys.ndim != 3 or polys.shape[2] != 2 or polys.shape[1] < 3 or len(names) != len(polys):
            raise ValueError(
                f"expected {len(names)} polygons as an (M, K>=3, 2) array, got shape {polys.shape}"
            )
        self.names = tuple(names)
        self.polygons = polys
        self.normals = edge_normals(polys)
        self.centres = polys.mean(axis=1)
        self.radii = np.linalg.norm(polys - self.centres[:, None, :], axis=2).max(
            axis=1, initial=0.0
        )
        self.lo = polys.min(axis=1, initial=np.inf)
        self.hi = polys.max(axis=1, initial=-np.inf)
        self._cache: tuple = (np.inf, np.inf, -np.inf, -np.inf, np.zeros(0, dtype=int))

    def __len__(self) -> int:
        return len(self.polygons)

    def near(self, centre: np.ndarray, radius: float) -> np.ndarray:
        """Indices of polygons whose bounding circle meets the circle (centre, radius)."""
        d = self.centres - centre
        reach = self.radii + radius
        return np.flatnonzero((d * d).sum(axis=1) < reach * reach)

    def clearance(self, part: np.ndarray, max_dist: float = np.inf) -> tuple[float, str]:
        """Signed distance from a convex part to the nearest polygon (negative: the
        deepest penetration) and that polygon's name; (inf, "") if none is within max_dist.
        """
        d, names = self.clearances(_check_polygon(part, "part")[None], max_dist)
        return float(d[0]), names[0]

    def clearances(
        self, parts: np.ndarray, max_dist: float = np.inf
    ) -> tuple[np.ndarray, tuple[str, ...]]:
        """`clearance` for many convex parts at once (P, K, 2): distances (P,) and names."""
        parts = _check_parts(parts)
        n = len(parts)
        best = np.full(n, np.inf)
        who = np.full(n, -1)
        if n == 0 or len(self) == 0:
            return best, ("",) * n
        plo, phi = parts.min(axis=1), parts.max(axis=1)
        m = max_dist if np.isfinite(max_dist) else 1e300
        ip, im = np.nonzero(~_separated(plo, phi, self.lo - m, self.hi + m))
        if len(ip):
            a, b = parts[ip], self.polygons[im]
            axes = np.concatenate([edge_normals(a), self.normals[im]], axis=1)
            push = np.minimum(*_axis_pushes(axes, a, b))
            dist = np.minimum(_vertex_edge_gaps(a, b), _vertex_edge_gaps(b, a))
            dist = np.where((push > 0).all(axis=1), -push.min(axis=1), dist)
            order = np.lexsort((dist, ip))  # by part, nearest first
            first = order[np.r_[True, ip[order][1:] != ip[order][:-1]]]
            best[ip[first]] = dist[first]
            who[ip[first]] = im[first]
        far = best > max_dist
        best[far] = np.inf
        who[far] = -1
        return best, tuple(self.names[i] if i >= 0 else "" for i in who)

    def least_gap(self, parts: np.ndarray, horizon: float) -> float:
        """A lower bound on the distance from the convex parts (P, K, 2) to the polygons,
        capped at `horizon`; 0 when a part may overlap or touch one (then `contacts`
        tells). Compiled: the simulator's broad phase asks it every few physics steps.
        Apart, two convex polygons are as far as a vertex of one from an edge of the
        other; a part counts as apart from a polygon when an edge normal separates them
        by more than 1e-9 m, so that no contact `contacts` finds is missed."""
        parts = _check_parts(parts)
        return float(_least_gap(parts, self.polygons, self.lo, self.hi, float(horizon)))

    def contacts(self, parts: Sequence[tuple[str, np.ndarray]]) -> list[Contact]:
        """Contacts of each named convex part with the polygons; the deepest one per
        (part, polygon name) when several polygons share a name (e.g. table top and legs).

        All parts must have the same vertex count (e.g. rectangles); the separating-axis
        test runs vectorised over every (part, nearby polygon) pair.
        """
        if not parts or len(self) == 0:
            return []
        names = [n for n, _ in parts]
        pp = np.array([p for _, p in parts], dtype=float)  # (P, K, 2)
        if pp.ndim != 3 or pp.shape[2] != 2 or pp.shape[1] < 3:
            raise ValueError(
                f"parts must be convex polygons with the same vertex count, got {pp.shape}"
            )
        ip, im = self._box_pairs(pp)
        if len(ip) == 0:
            return []
        a, b = pp[ip], self.polygons[im]  # (Q, K, 2), (Q, L, 2)
        axes = np.concatenate([edge_normals(pp)[ip], self.normals[im]], axis=1)  # (Q, A, 2)
        push_pos, push_neg = _axis_pushes(axes, a, b)
        best = self._deepest(ip, im, axes, push_pos, push_neg)
        return [
            Contact(names[i], name, depth, normal, contact_point(pp[i], self.polygons[m]))
            for (i, name), (depth, normal, m) in best.items()
        ]

    def _box_pairs(self, pp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(part indices, polygon indices) of the pairs whose axis-aligned bounding boxes
        overlap, for parts pp (P, K, 2): first all parts together against the polygons
        (a cached candidate list), then each part against the candidates."""
        plo, phi = pp.min(axis=1), pp.max(axis=1)  # (P, 2)
        x0, y0 = (float(v) for v in plo.min(axis=0))
        x1, y1 = (float(v) for v in phi.max(axis=0))
        c = self._cache
        if not (c[0] <= x0 and c[1] <= y0 and x1 <= c[2] and y1 <= c[3]):
            # Candidates for a box a little larger than the parts, reused while the parts
            # stay inside it (the walker moves a few millimetres per physics step).
            m = _CANDIDATE_MARGIN_M
            c = (x0 - m, y0 - m, x1 + m, y1 + m)
            blo, bhi = self.lo, self.hi
            cand = np.flatnonzero(
                (blo[:, 0] < c[2]) & (bhi[:, 0] > c[0]) & (blo[:, 1] < c[3]) & (bhi[:, 1] > c[1])
            )
            self._cache = c = (*c, cand)
        cand = c[4]
        if len(cand) == 0:
            return cand, cand
        ip, ic = np.nonzero(~_separated(plo, phi, self.lo[cand], self.hi[cand]))
        return ip, cand[ic]

    def _deepest(
        self,
        ip: np.ndarray,
        im: np.ndarray,
        axes: np.ndarray,
        push_pos: np.ndarray,
        push_neg: np.ndarray,
    ) -> dict[tuple[int, str], tuple[float, np.ndarray, int]]:
        """Per (part index, polygon name), of the pairs (ip, im) that overlap on every
        axis, the deepest: (depth, the unit normal pushing the part out, polygon index)."""
        push = np.minimum(push_pos, push_neg)
        best: dict[tuple[int, str], tuple[float, np.ndarray, int]] = {}
        for q in np.flatnonzero((push > 0.0).all(axis=1)):
            j = int(np.argmin(push[q]))
            depth = float(push[q, j])
            normal = axes[q, j] if push_pos[q, j] <= push_neg[q, j] else -axes[q, j]
            key = (int(ip[q]), self.names[im[q]])
            if key not in best or depth > best[key][0]:
                best[key] = (depth, normal.copy(), int(im[q]))
        return best
