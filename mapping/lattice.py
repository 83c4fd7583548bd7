"""Integer cell lattice helpers shared by the grid and by observation compaction.

A lattice of square cells of side `resolution` is anchored at the world origin: cell
(i, j) covers [i·res, (i+1)·res) × [j·res, (j+1)·res). Everything here is vectorised numpy
on N×2 arrays of points or integer cells; there is no per-point or per-ray Python loop.
"""

from __future__ import annotations

import numpy as np

# Above this many bbox cells per input cell, deduplicate by sorting instead of a bitmap.
_BITMAP_DENSITY_LIMIT = 8


def as_points(a: np.ndarray, name: str = "points") -> np.ndarray:
    """View `a` as an N×2 array of (x, y); raises ValueError for any other shape."""
    a = np.asarray(a)
    if a.ndim != 2 or a.shape[1] != 2:
        raise ValueError(f"{name} must have shape (N, 2) as (x, y), got {a.shape}")
    return a


def cells_of(points: np.ndarray, resolution: float) -> np.ndarray:
    """Lattice cells (N×2 int64, columns i, j) holding the N×2 `points`."""
    return np.floor(as_points(points) / resolution).astype(np.int64)


def cell_centres(cells: np.ndarray, resolution: float) -> np.ndarray:
    """World centres (N×2 float64) of the N×2 integer `cells`."""
    return (np.asarray(cells, dtype=np.float64) + 0.5) * resolution


def cell_bounds(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inclusive bounds (lo, hi) (each (2,) int64) of a non-empty N×2 cell array."""
    # Column-wise: numpy's axis-0 reduction over two columns is an order slower.
    i, j = cells[:, 0], cells[:, 1]
    return np.array([i.min(), j.min()]), np.array([i.max(), j.max()])


def _dedupe(i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct (i, j) pairs of two 1-D integer arrays, ordered by (j, i).

    Uses a bitmap over the bounding box when that box is small compared with the number
    of cells (O(N), the common case for one depth frame) and a sort otherwise.
    """
    if len(i) == 0:
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
    i0, j0 = int(i.min()), int(j.min())
    width, height = int(i.max()) - i0 + 1, int(j.max()) - j0 + 1
    flat = (j - j0) * width + (i - i0)
    if width * height <= _BITMAP_DENSITY_LIMIT * len(i) + 4096:
        seen = np.zeros(width * height, dtype=bool)
        seen[flat] = True
        flat = np.flatnonzero(seen)
    else:
        flat = np.unique(flat)
    return flat % width + i0, flat // width + j0


def unique_cells(cells: np.ndarray) -> np.ndarray:
    """Distinct rows (M×2 int64) of an N×2 integer cell array, ordered by (j, i)."""
    cells = as_points(cells, "cells").astype(np.int64, copy=False)
    return np.column_stack(_dedupe(cells[:, 0], cells[:, 1]))


def quantise_points(points: np.ndarray, quantum: float) -> np.ndarray:
    """Snap N×2 points to the centres of a `quantum`-sized lattice and drop duplicates.

    The result is float32 (M×2, M ≤ N); each point moves by at most quantum/√2.
    """
    points = as_points(points)
    if quantum <= 0:
        raise ValueError(f"quantum must be > 0, got {quantum}")
    i, j = (np.floor(points[:, k] / quantum).astype(np.int64) for k in range(2))
    ui, uj = _dedupe(i, j)
    return np.column_stack([(ui + 0.5) * quantum, (uj + 0.5) * quantum]).astype(np.float32)


def bundle_rays(origin: np.ndarray, ends: np.ndarray, resolution: float) -> np.ndarray:
    """Indices of the rays worth tracing from `origin` to the N×2 `ends`.

    Rays are grouped by bearing into bins no wider than half a cell at the longest range,
    and only the longest ray of each bin is kept: every shorter ray in the bin runs within
    half a cell of it, which is the sampling tolerance of `trace_rays` anyway. A depth
    frame's thousands of distinct end cells thus need only a few hundred traced rays.
    """
    d = as_points(ends, "ends") - np.asarray(origin, dtype=np.float64)
    if len(d) == 0:
        return np.empty(0, dtype=np.int64)
    r = np.hypot(d[:, 0], d[:, 1])
    width = 0.5 * resolution / max(float(r.max()), resolution)
    bins = np.floor((np.arctan2(d[:, 1], d[:, 0]) + np.pi) / width).astype(np.int64)
    order = np.lexsort((r, bins))
    sorted_bins = bins[order]
    last_of_bin = np.append(sorted_bins[1:] != sorted_bins[:-1], True)
    return order[last_of_bin]


def trace_rays(origin: np.ndarray, ends: np.ndarray, resolution: float) -> np.ndarray:
    """Cells (K×2 int64, with repeats) that the segments origin → ends pass through.

    Each segment is sampled at steps of at most half a cell from the origin (included)
    up to its end point (excluded), all segments at once in one ragged numpy array.
    """
    return np.column_stack(trace_rays_ij(origin, ends, resolution))


def trace_rays_ij(
    origin: np.ndarray, ends: np.ndarray, resolution: float
) -> tuple[np.ndarray, np.ndarray]:
    """`trace_rays` as two 1-D arrays (i, j), which is cheaper to index with."""
    o = np.asarray(origin, dtype=np.float64)
    if o.shape != (2,):
        raise ValueError(f"origin must have shape (2,) as (x, y), got {o.shape}")
    ends = as_points(ends, "ends")
    if len(ends) == 0:
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
    # In cell units, so that a sample's cell is the floor of its coordinates.
    dx = (ends[:, 0] - o[0]) / resolution
    dy = (ends[:, 1] - o[1]) / resolution
    steps = np.maximum(np.ceil(2.0 * np.hypot(dx, dy)), 1).astype(np.int64)
    ray = np.repeat(np.arange(len(steps)), steps)
    first = np.cumsum(steps) - steps
    frac = np.arange(len(ray), dtype=np.float64)
    frac -= first[ray]
    frac /= steps[ray]
    x = frac * dx[ray]
    x += o[0] / resolution
    frac *= dy[ray]
    frac += o[1] / resolution
    return np.floor(x).astype(np.int64), np.floor(frac).astype(np.int64)
