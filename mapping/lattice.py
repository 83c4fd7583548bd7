"""Integer cell lattice helpers shared by the grid and by observation compaction.

A lattice of square cells of side `resolution` is anchored at the world origin: cell
(i, j) covers [i·res, (i+1)·res) × [j·res, (j+1)·res). Everything here is vectorised numpy
on N×2 arrays of points or integer cells, with no per-point or per-ray Python loop; ray
samples are marked by a compiled loop (`mapping.kernels`).
"""

from __future__ import annotations

import numpy as np

from mapping.kernels import mark_ray_samples

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
    """Indices of the rays worth tracing from `origin` to the N×2 `ends`, by bearing bin.

    Rays are grouped by bearing into bins no wider than half a cell at the longest range,
    and only the longest ray of each bin is kept (of equally long ones, the last): every
    shorter ray in the bin runs within half a cell of it, which is the sampling tolerance
    of `trace_rays` anyway. A depth frame's thousands of distinct end cells thus need only
    a few hundred traced rays.
    """
    ends = as_points(ends, "ends")
    if len(ends) == 0:
        return np.empty(0, dtype=np.int64)
    o = np.asarray(origin, dtype=np.float64)
    # Column by column: 5× cheaper than broadcasting over the N×2 array.
    dx, dy = ends[:, 0] - o[0], ends[:, 1] - o[1]
    r = np.hypot(dx, dy)
    width = 0.5 * resolution / max(float(r.max()), resolution)
    bins = np.arctan2(dy, dx)
    bins += np.pi
    bins /= width
    return _longest_per_bin(np.floor(bins, out=bins).astype(np.int64), r)


def _longest_per_bin(bins: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Per distinct bin (ascending), the index of its largest r (the last one of ties).

    Bins are a bearing's fraction of a full turn, so there are only a few times more of
    them than rays: per-bin maxima by `np.maximum.at` cost O(N + bins), a third of a sort
    of a depth frame's ~1000 end cells (a sort wins for a few dozen).
    """
    n_bins = int(bins.max()) + 1  # bins >= 0
    if len(bins) < 64 or n_bins > _BITMAP_DENSITY_LIMIT * len(bins) + 4096:
        order = np.lexsort((r, bins))
        sorted_bins = bins[order]
        return order[np.append(sorted_bins[1:] != sorted_bins[:-1], True)]
    longest = np.full(n_bins, -np.inf)
    np.maximum.at(longest, bins, r)
    candidates = np.flatnonzero(r == longest[bins])
    pick = np.full(n_bins, -1, dtype=np.int64)
    np.maximum.at(pick, bins[candidates], candidates)
    return pick[pick >= 0]


def trace_rays(origin: np.ndarray, ends: np.ndarray, resolution: float) -> np.ndarray:
    """Distinct cells (K×2 int64, ordered by (j, i)) that the segments origin → ends pass
    through.

    Each segment is sampled at steps of at most half a cell from the origin (included)
    up to its end point (excluded); see `mark_rays`.
    """
    o = np.asarray(origin, dtype=np.float64)
    ends = as_points(ends, "ends")
    if len(ends) == 0:
        return np.empty((0, 2), dtype=np.int64)
    cells = cells_of(np.vstack([o[None], ends]), resolution)
    (i0, j0), (i1, j1) = cell_bounds(cells)
    width, height = int(i1 - i0 + 1), int(j1 - j0 + 1)
    marks = np.zeros(width * height, dtype=bool)
    mark_rays(o, ends, resolution, (int(i0), int(j0)), width, marks)
    j, i = np.divmod(np.flatnonzero(marks), width)
    return np.column_stack([i + i0, j + j0])


def mark_rays(
    origin: np.ndarray,
    ends: np.ndarray,
    resolution: float,
    lo: tuple[int, int],
    width: int,
    marks: np.ndarray,
) -> None:
    """Set the cells the segments origin → ends pass through in `marks`, a flat row-major
    bitmap of a box whose lower-left cell is `lo` = (lo_i, lo_j) and whose rows are
    `width` cells long; the box must hold every cell the segments touch (IndexError).

    A segment L cells long gets n = max(⌈2L⌉, 1) samples at fractions k/n, k = 0..n−1,
    of the way from the origin: the origin included, the end excluded, steps of at most
    half a cell. A sample's cell is the floor of its coordinates (in cell units); the
    samples are marked by one compiled loop (`mapping.kernels.mark_ray_samples`).
    """
    o = np.asarray(origin, dtype=np.float64)
    if o.shape != (2,):
        raise ValueError(f"origin must have shape (2,) as (x, y), got {o.shape}")
    ends = as_points(ends, "ends")
    if len(ends) == 0:
        return
    dx = (ends[:, 0] - o[0]) / resolution
    dy = (ends[:, 1] - o[1]) / resolution
    steps = np.maximum(np.ceil(2.0 * np.hypot(dx, dy)), 1.0).astype(np.int64)
    height = len(marks) // width
    box = (int(lo[0]), int(lo[1]), int(width), int(height))
    mark_ray_samples(o[0] / resolution, o[1] / resolution, dx, dy, steps, box, marks)
