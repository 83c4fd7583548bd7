"""Integer cell lattice helpers shared by the grid and by observation compaction.

A lattice of square cells of side `resolution` is anchored at the world origin: cell
(i, j) covers [i·res, (i+1)·res) × [j·res, (j+1)·res). Everything here is vectorised numpy
on N×2 arrays of points or integer cells; there is no per-point or per-ray Python loop.
"""

from __future__ import annotations

from functools import lru_cache

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
    """Cells (K×2 int64, with repeats) that the segments origin → ends pass through.

    Each segment is sampled at steps of at most half a cell from the origin (included)
    up to its end point (excluded); see `_ray_samples`.
    """
    return np.column_stack(trace_rays_ij(origin, ends, resolution))


def trace_rays_ij(
    origin: np.ndarray, ends: np.ndarray, resolution: float
) -> tuple[np.ndarray, np.ndarray]:
    """`trace_rays` as two 1-D arrays (i, j), which is cheaper to index with."""
    x, y = _ray_samples(origin, ends, resolution)
    return np.floor(x).astype(np.int64).ravel(), np.floor(y).astype(np.int64).ravel()


def trace_rays_flat(
    origin: np.ndarray, ends: np.ndarray, resolution: float, lo: tuple[int, int], width: int
) -> np.ndarray:
    """`trace_rays` as flat indices (j − lo_j)·width + (i − lo_i) into a row-major box.

    The box's lower-left cell is `lo` = (lo_i, lo_j); rows are `width` cells long. The
    index arithmetic stays in float64 (exact on integers) and is converted once, which
    halves the passes over the samples compared with integer (i, j).
    """
    x, y = _ray_samples(origin, ends, resolution)
    np.floor(x, out=x)
    np.floor(y, out=y)
    y *= width
    y += x
    y -= float(lo[1]) * width + float(lo[0])
    return y.astype(np.intp).ravel()


@lru_cache(maxsize=8)
def _fraction_table(rows: int) -> np.ndarray:
    """(rows, rows) float64: row n−1 holds min(k, n−1)/n for k = 0..rows−1."""
    n = np.arange(1.0, rows + 1.0)[:, None]
    table = np.minimum(np.arange(float(rows)), n - 1.0) / n
    table.setflags(write=False)
    return table


def _fractions(n_max: int) -> np.ndarray:
    """(n_max, n_max) view of the sample fractions of rays of n = 1..n_max samples: row n−1
    holds k/n for k < n and then repeats (n−1)/n, the ray's last sample.

    Tables are cached by n_max rounded up to 32: ~200 kB for a depth frame's rays, which
    stays in cache, unlike one large table. Longer rays (> 25 m at 5 cm) are uncached."""
    if n_max > 512:
        return _fraction_table.__wrapped__(n_max)
    return _fraction_table(-(-n_max // 32) * 32)[:n_max, :n_max]


def _ray_samples(
    origin: np.ndarray, ends: np.ndarray, resolution: float
) -> tuple[np.ndarray, np.ndarray]:
    """Sample points (x, y), in cell units, of the segments origin → ends (same shape).

    A segment L cells long gets n = max(⌈2L⌉, 1) samples at fractions k/n, k = 0..n−1,
    of the way from the origin: the origin included, the end excluded, steps of at most
    half a cell. A sample's cell is the floor of its coordinates.

    When the rays have similar lengths (a depth frame's bundled rays) the samples form an
    (R, n_max) block in which a short ray repeats its last sample: broadcasting the
    per-ray values is cheaper than gathering them per sample. Otherwise the samples
    form one ragged 1-D array. Either way each sample is computed as k/n·d + o in the
    same float64 operations, so the cells do not depend on the layout.
    """
    o = np.asarray(origin, dtype=np.float64)
    if o.shape != (2,):
        raise ValueError(f"origin must have shape (2,) as (x, y), got {o.shape}")
    ends = as_points(ends, "ends")
    if len(ends) == 0:
        return np.empty(0), np.empty(0)
    dx = (ends[:, 0] - o[0]) / resolution
    dy = (ends[:, 1] - o[1]) / resolution
    steps = np.maximum(np.ceil(2.0 * np.hypot(dx, dy)), 1.0)  # integral float64
    n_max, total = int(steps.max()), int(steps.sum())
    if len(steps) * n_max <= 2 * total:
        frac = _fractions(n_max)[steps.astype(np.intp) - 1]  # not .take: it copies the view
        dx, dy = dx[:, None], dy[:, None]
    else:
        counts = steps.astype(np.int64)
        ray = np.repeat(np.arange(len(counts)), counts)
        frac = np.arange(total, dtype=np.float64)
        frac -= (np.cumsum(counts) - counts)[ray]
        frac /= steps[ray]
        dx, dy = dx[ray], dy[ray]
    x = frac * dx
    x += o[0] / resolution
    frac *= dy
    frac += o[1] / resolution
    return x, frac
