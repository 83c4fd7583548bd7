"""Exact Euclidean distance transform of a grid, compiled (numba).

The likelihood fields that score scans against maps (the particle filter's, the scan
matcher's) need, for every cell, the distance to the nearest occupied cell. This is
Felzenszwalb & Huttenlocher's two passes ("Distance Transforms of Sampled Functions",
2012): the distance to the nearest target within each column, then along each row the
lower envelope of the parabolas (x − q)² + g(q). It returns the squared distance in
cells as an integer, exactly, so that the callers choose the arithmetic after it: the
square root in float64 equals scipy's `distance_transform_edt`, in float32 OpenCV's
`distanceTransform(DIST_L2, DIST_MASK_PRECISE)`, and a field that depends on the
distance alone can be a table indexed by the squared distance.

A field that stops changing a few σ from a surface (the particle filter's reaches its
floor to the last bit ~19 cells out) needs distances only up to there:
`capped_squared_distances` finds them with (2·cap − 1) additions per cell in runs along
memory (vector code), 2–3× faster than the full transform's data-dependent branch per
cell at such caps.
"""

from __future__ import annotations

import numpy as np
from numba import njit


def no_target(shape: tuple[int, int]) -> int:
    """The value `squared_distances` gives where a grid of `shape` has no target: more
    than any squared distance within it."""
    return shape[0] * shape[0] + shape[1] * shape[1]


@njit(cache=True, nogil=True)
def squared_distances(targets: np.ndarray) -> np.ndarray:
    """(H, W) int64 squared Euclidean distance [cells²] from each cell of the (H, W) bool
    `targets` to the nearest True cell (0 on one); `no_target(shape)` everywhere when
    there is none."""
    ny, nx = targets.shape
    inf = ny * ny + nx * nx
    g = np.empty((ny, nx), np.int64)
    # pass 1: the squared distance to the nearest target in the same column, swept row by
    # row (down, then up) so that every access runs along memory
    last = np.full(nx, -1, np.int64)
    for i in range(ny):
        for j in range(nx):
            if targets[i, j]:
                last[j] = i
            d = i - last[j]
            g[i, j] = d * d if last[j] >= 0 else inf
    last[:] = -1
    for i in range(ny - 1, -1, -1):
        for j in range(nx):
            if targets[i, j]:
                last[j] = i
            if last[j] >= 0:
                d = last[j] - i
                if d * d < g[i, j]:
                    g[i, j] = d * d
    # pass 2: along each row, the lower envelope of the parabolas (x − q)² + g[q]; the
    # breakpoints are ratios of integers below 2·(H² + W²) over denominators below 2·W,
    # so float64 orders them exactly
    out = np.empty((ny, nx), np.int64)
    v = np.empty(nx, np.int64)  # the envelope's parabolas (their columns)
    z = np.empty(nx + 1, np.float64)  # where each one starts
    for i in range(ny):
        k = -1
        for q in range(nx):
            fq = g[i, q]
            if fq >= inf:
                continue
            if k < 0:
                k = 0
                v[0] = q
                z[0] = -np.inf
                z[1] = np.inf
                continue
            while True:
                p = v[k]
                s = ((fq + q * q) - (g[i, p] + p * p)) / (2.0 * (q - p))
                if s <= z[k]:
                    k -= 1  # z[0] is −inf: k stays ≥ 0
                else:
                    break
            k += 1
            v[k] = q
            z[k] = s
            z[k + 1] = np.inf
        if k < 0:
            out[i, :] = inf
            continue
        k = 0
        for x in range(nx):
            while z[k + 1] < x:
                k += 1
            p = v[k]
            out[i, x] = (x - p) * (x - p) + g[i, p]
    return out


@njit(cache=True, nogil=True)
def capped_squared_distances(targets: np.ndarray, cap: int) -> np.ndarray:
    """(H, W) int32 squared Euclidean distance [cells²] from each cell of the (H, W) bool
    `targets` to the nearest True cell where that is below cap², and cap² elsewhere."""
    ny, nx = targets.shape
    floor_d2 = cap * cap
    # the squared distance to the nearest target in the same column, up to cap, swept
    # down and then up one row at a time, in rows padded by cap cells of cap²
    col = np.empty((ny, nx + 2 * cap), np.int32)
    col[:, :cap] = floor_d2
    col[:, cap + nx :] = floor_d2
    run = np.empty(nx, np.int32)
    run[:] = cap
    for i in range(ny):
        here = col[i, cap : cap + nx]
        for j in range(nx):
            d = 0 if targets[i, j] else min(run[j] + 1, cap)
            run[j] = d
            here[j] = d * d
    run[:] = cap
    for i in range(ny - 1, -1, -1):
        here = col[i, cap : cap + nx]
        for j in range(nx):
            d = 0 if targets[i, j] else min(run[j] + 1, cap)
            run[j] = d
            here[j] = min(here[j], d * d)
    # along each row, the nearest of the columns within cap − 1 cells (views with
    # indices from 0 up: no negative-index checks, so the loop becomes vector code)
    out = np.empty((ny, nx), np.int32)
    for i in range(ny):
        row = col[i]
        best = out[i]
        for x in range(nx):
            best[x] = row[cap + x]
        for dq in range(1, cap):
            dd = dq * dq
            left = row[cap - dq : cap - dq + nx]
            right = row[cap + dq : cap + dq + nx]
            for x in range(nx):
                best[x] = min(best[x], min(left[x], right[x]) + dd)
        for x in range(nx):
            best[x] = min(best[x], floor_d2)
    return out
