"""Compiled inner loop of the scan matcher's correlative search (numba).

`grid_scores` scores every translation of a rotated query on the likelihood field: for
each point and each (row, column) offset one lookup. numpy does it as one gather into a
(points × rows × columns) temporary and a mean over the points, tens of MB for a wide
window; here the sum runs point by point into the (rows × columns) result, in the same
order as numpy's reduction over the first axis, so the scores are the same to the bit
(but for a single offset, where numpy sums the one column pairwise: within 1e-16).

`icp_steps` is the point-to-line ICP of slam.scan_matching.icp, every iteration in one
loop: each query point placed, its nearest reference point found in `buckets` (the
reference points sorted by a grid of cells as wide as the correspondence gate, so the
nearest within the gate is in the 3 × 3 cells around it: the k-d tree's answer), its
residual rows weighted and added to JᵀWJ and JᵀWr, then the 3 × 3 solve. numpy took ~25
calls per iteration on a few hundred points, and their overhead was most of the cost.
The sums run in the query's point order, one operation at a time (no BLAS, no SIMD
reassociation: numba does not reorder floating-point sums), so the result is the same on
any CPU.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from slam.kernel_math import inverse, wrap


@njit(cache=True, nogil=True)
def grid_scores(
    flat: np.ndarray,
    height: int,
    width: int,
    cells: np.ndarray,
    x_offs: np.ndarray,
    y_offs: np.ndarray,
) -> np.ndarray:
    """Mean over the points of a flattened field (height × width) at their cells (n, 2:
    column, row) shifted by every (y, x) cell offset: (len(y_offs), len(x_offs));
    lookups outside the field are clipped to its border."""
    n = cells.shape[0]
    ny, nx = len(y_offs), len(x_offs)
    out = np.zeros((ny, nx))
    cols = np.empty(nx, np.int64)
    for k in range(n):
        for b in range(nx):
            cols[b] = min(max(cells[k, 0] + x_offs[b], 0), width - 1)
        for a in range(ny):
            base = min(max(cells[k, 1] + y_offs[a], 0), height - 1) * width
            row = out[a]
            for b in range(nx):
                row[b] += flat[base + cols[b]]
    return out / n


def buckets(points: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The points (M, 2) sorted by the grid cell (of side `cell`) they fall in, for
    `nearest`: (order (M,): point indices by cell, starts (H·W + 1,): where each cell's
    run begins in order, (x0, y0, cell, W, H) as floats: the grid). The cells are made
    wider when the points' extent would need more than 1024 of them a side (a small
    gate over a building): `nearest` only needs them at least as wide as the gate."""
    cell = max(cell, float(np.ptp(points, axis=0).max()) / 1024.0)
    lo = points.min(axis=0) - cell
    ij = np.floor((points - lo) / cell).astype(np.int64)
    w, h = int(ij[:, 0].max()) + 2, int(ij[:, 1].max()) + 2
    flat = ij[:, 1] * w + ij[:, 0]
    order = np.argsort(flat, kind="stable")
    starts = np.searchsorted(flat[order], np.arange(w * h + 1))
    return order, starts, np.array([lo[0], lo[1], cell, w, h])


@njit(cache=True, nogil=True)
def nearest(points, order, starts, grid, x, y, gate2):
    """Index of the reference point nearest (x, y) with squared distance below gate2
    (the lowest index among equals), or −1; grid's cell must be at least the gate."""
    w, h = int(grid[3]), int(grid[4])
    ci = math.floor((x - grid[0]) / grid[2])
    cj = math.floor((y - grid[1]) / grid[2])
    best, best_d2 = -1, gate2
    for j in range(max(cj - 1, 0), min(cj + 2, h)):
        for i in range(max(ci - 1, 0), min(ci + 2, w)):
            c = j * w + i
            for k in range(starts[c], starts[c + 1]):
                p = order[k]
                dx = x - points[p, 0]
                dy = y - points[p, 1]
                d2 = dx * dx + dy * dy
                if d2 < best_d2 or (d2 == best_d2 and best >= 0 and p < best):
                    best, best_d2 = p, d2
    return best


@njit(cache=True, nogil=True)
def icp_steps(
    points, normals, has_normal, order, starts, grid, query, x, gate, huber, iterations,
    tol_xy, tol_theta, min_points,
):  # fmt: skip
    """Gauss-Newton ICP of `query` (N, 2) from pose x (3,, updated in place) against the
    reference points with their normals: point-to-line rows where has_normal, else two
    point-to-point rows; Huber weights. Returns (iterations run, converged)."""
    gate2 = gate * gate
    h = np.empty((3, 3))
    h_inv = np.empty((3, 3))
    g = np.empty(3)
    it = 0
    for it in range(1, iterations + 1):
        c, s = math.cos(x[2]), math.sin(x[2])
        for a in range(3):
            g[a] = 0.0
            for b in range(3):
                h[a, b] = 0.0
        count = 0
        for k in range(query.shape[0]):
            qx = (c * query[k, 0] - s * query[k, 1]) + x[0]
            qy = (s * query[k, 0] + c * query[k, 1]) + x[1]
            p = nearest(points, order, starts, grid, qx, qy, gate2)
            if p < 0:
                continue
            count += 1
            dqx, dqy = -(qy - x[1]), qx - x[0]  # ∂q/∂θ
            ex, ey = qx - points[p, 0], qy - points[p, 1]
            if has_normal[p]:
                nx, ny = normals[p, 0], normals[p, 1]
                _add_row(h, g, nx, ny, nx * dqx + ny * dqy, nx * ex + ny * ey, huber)
            else:
                _add_row(h, g, 1.0, 0.0, dqx, ex, huber)
                _add_row(h, g, 0.0, 1.0, dqy, ey, huber)
        if count < min_points:
            break
        for a in range(3):
            h[a, a] += 1e-9
        det = inverse(h, 3, h_inv)
        if det == 0.0 or not math.isfinite(det):
            break
        step0 = -(h_inv[0, 0] * g[0] + h_inv[0, 1] * g[1] + h_inv[0, 2] * g[2])
        step1 = -(h_inv[1, 0] * g[0] + h_inv[1, 1] * g[1] + h_inv[1, 2] * g[2])
        step2 = -(h_inv[2, 0] * g[0] + h_inv[2, 1] * g[1] + h_inv[2, 2] * g[2])
        x[0] += step0
        x[1] += step1
        x[2] = wrap(x[2] + step2)
        if math.hypot(step0, step1) < tol_xy and abs(step2) < tol_theta:
            return it, True
    return it, False


@njit(cache=True, nogil=True, inline="always")
def _add_row(h, g, j0, j1, j2, r, huber) -> None:
    """One Huber-weighted residual row r with Jacobian (j0, j1, j2) into JᵀWJ and JᵀWr."""
    a = abs(r)
    w = 1.0 if a <= huber else huber / max(a, 1e-12)
    j = (j0, j1, j2)
    for u in range(3):
        wu = w * j[u]
        g[u] += wu * r
        for v in range(3):
            h[u, v] += wu * j[v]
