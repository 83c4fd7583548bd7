"""Compiled inner loops of the mapper (numba): per-pixel projection and per-sample ray marks.

Both loops visit tens of thousands of pixels or ray samples per frame, where numpy needs a
dozen full-size passes and temporaries; compiled, each is one pass. They compute every value
that decides a cell in exactly the float operations that the mapper's semantics define
(float32 for depth points, float64 for ray samples; no fused multiply-adds, numba's default),
so the maps equal, cell for cell, those of tests/mapping/reference_mapper.py, a
straightforward numpy re-implementation. Compiled code is cached on disk (numba
`cache=True`): only the first run on a machine pays the compilation (a few seconds).

Cells are flat indices (j − j0)·width + (i − i0) into a row-major box of width × height
cells; a point outside the box raises IndexError (the callers size the boxes so that none
is, but an out-of-box write would corrupt memory).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def depth_pixel_cells(
    depth: np.ndarray,
    rays: np.ndarray,
    t: np.ndarray,
    near: int,
    far: int,
    cut_no_return: bool,
    scale: np.float32,
    floor_clearance: np.float32,
    max_height: np.float32,
    far_m: np.float32,
    quantum: np.float32,
    box: tuple[int, int, int, int],
    cells: np.ndarray,
    obstacle: np.ndarray,
) -> None:
    """Each depth pixel's lattice cell, or −1 when it shows nothing on the floor plane.

    depth (P,) integer readings in depth units, matching `rays` (3, P) float32 (walker-frame
    displacement per metre of z-depth) and `t` (3,) float32 (the camera in the walker
    frame). A reading in near..far (inclusive) is a hit at rays·(d·scale) + t: a ray end if
    its height is at most max_height, and also an obstacle if at least floor_clearance. A
    reading beyond `far` (and, with `cut_no_return`, one <= 0: no return) is cut at far_m:
    a ray end if that point's height is within [0, max_height]. A ray end's cell is
    (⌊x/q⌋, ⌊y/q⌋) on the `quantum` lattice, flat in `box` = (i0, j0, width, height) →
    `cells` (int32), −2 when outside the box; `obstacle` (bool) marks obstacle pixels.
    Everything in float32, as `depth_points.depth_to_observation`; branch-free, so that
    the loop runs on SIMD lanes.
    """
    i0, j0, width, height = box
    zero = np.float32(0.0)
    tx, ty, tz = t[0], t[1], t[2]
    for p in range(depth.shape[0]):
        d = depth[p]
        hit = (d >= near) & (d <= far)
        cut = (d > far) | (cut_no_return & (d <= 0))
        z = np.float32(d) * scale if hit else far_m
        h = rays[2, p] * z + tz
        end = (hit | (cut & (h >= zero))) & (h <= max_height)
        i = np.int32(np.floor((rays[0, p] * z + tx) / quantum)) - np.int32(i0)
        j = np.int32(np.floor((rays[1, p] * z + ty) / quantum)) - np.int32(j0)
        inside = (i >= 0) & (i < width) & (j >= 0) & (j < height)
        cells[p] = (j * np.int32(width) + i) if inside else np.int32(-2)
        if not end:
            cells[p] = np.int32(-1)
        obstacle[p] = hit & end & (h >= floor_clearance)


@njit(cache=True, nogil=True)
def compact_pixel_cells(
    cells: np.ndarray, obstacle: np.ndarray, size: int, centres: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(obstacles, ray ends): the centres (float32, from `centres`, (size, 2)) of the
    distinct cells of `depth_pixel_cells`, ordered by flat index, i.e. by (j, i); the
    obstacles are the end cells that hold an obstacle pixel."""
    is_end = np.zeros(size, dtype=np.uint8)
    for p in range(cells.shape[0]):
        c = cells[p]
        if c >= 0:
            is_end[c] |= np.uint8(1) | (np.uint8(2) if obstacle[p] else np.uint8(0))
        elif c == -2:
            raise IndexError("depth point outside the camera's lattice box")
    words = is_end[: size - size % 8].view(np.uint64)
    n_end = n_obstacle = 0
    ends = np.empty(min(size, cells.shape[0]) + 8, dtype=np.int64)  # ≤ 1 per pixel, + slack
    for w in range(words.shape[0]):
        if words[w] != 0:  # then branch-free over its 8 cells
            for c in range(8 * w, 8 * w + 8):
                ends[n_end] = c
                n_end += is_end[c] != 0
    for c in range(size - size % 8, size):
        ends[n_end] = c
        n_end += is_end[c] != 0
    end_xy = np.empty((n_end, 2), dtype=np.float32)
    for k in range(n_end):
        c = ends[k]
        end_xy[k, 0] = centres[c, 0]
        end_xy[k, 1] = centres[c, 1]
        n_obstacle += is_end[c] >> 1
    obstacle_xy = np.empty((n_obstacle, 2), dtype=np.float32)
    m = 0
    for k in range(n_end):
        if is_end[ends[k]] >> 1:
            obstacle_xy[m, 0] = end_xy[k, 0]
            obstacle_xy[m, 1] = end_xy[k, 1]
            m += 1
    return obstacle_xy, end_xy


@njit(cache=True, nogil=True)
def place_points(
    points: np.ndarray, x: float, y: float, c: float, s: float, out: np.ndarray
) -> None:
    """World (x', y') of the walker-frame float32 `points` (N×2) at the pose (x, y) with
    heading cos c, sin s, into `out` (N×2 float64): x' = (x + c·px) − s·py and
    y' = (y + s·px) + c·py, operation for operation as `hardware.geometry.transform_points`."""
    for k in range(points.shape[0]):
        px = np.float64(points[k, 0])
        py = np.float64(points[k, 1])
        out[k, 0] = (x + c * px) - s * py
        out[k, 1] = (y + s * px) + c * py


@njit(cache=True, nogil=True)
def update_log_odds(
    log_odds: np.ndarray,
    occupied: np.ndarray,
    crossed: np.ndarray,
    l_occ: np.float32,
    l_free: np.float32,
    l_min: np.float32,
    l_max: np.float32,
) -> None:
    """One frame's log-odds update of a (h, w) window: + l_occ (clamped to l_max) where
    `occupied`, else + l_free (clamped to l_min) where `crossed`; float32."""
    h, w = log_odds.shape
    for r in range(h):
        for c in range(w):
            if occupied[r, c]:
                log_odds[r, c] = min(log_odds[r, c] + l_occ, l_max)
            elif crossed[r, c]:
                log_odds[r, c] = max(log_odds[r, c] + l_free, l_min)


@njit(cache=True, nogil=True)
def mark_ray_samples(
    ox: float,
    oy: float,
    dx: np.ndarray,
    dy: np.ndarray,
    steps: np.ndarray,
    box: tuple[int, int, int, int],
    marks: np.ndarray,
) -> None:
    """Mark the cells of the samples of rays from the origin (ox, oy) along (dx, dy), all in
    cell units: ray r has n = steps[r] samples at fractions k/n, k = 0..n−1, each at
    (k/n·dx + ox, k/n·dy + oy), in cell (⌊x⌋, ⌊y⌋), flat in `box` = (i0, j0, width, height)
    of the bitmap `marks`."""
    i0, j0, width, height = box
    n_max = 0
    for r in range(len(steps)):
        n_max = max(n_max, steps[r])
    ii = np.empty(n_max, dtype=np.int64)
    jj = np.empty(n_max, dtype=np.int64)
    for r in range(len(steps)):
        n = steps[r]
        nf = float(n)
        ax, ay = dx[r], dy[r]
        for k in range(n):  # no branches or stores but these: runs on SIMD lanes
            f = float(k) / nf
            ii[k] = np.int64(math.floor(f * ax + ox)) - i0
            jj[k] = np.int64(math.floor(f * ay + oy)) - j0
        for k in range(n):
            i, j = ii[k], jj[k]
            if not (0 <= i < width and 0 <= j < height):
                raise IndexError("ray sample outside the marked box")
            marks[j * width + i] = True


@njit(cache=True, nogil=True)
def _widen(points, resolution, bounds):
    """`bounds` widened to the cells ⌊p/resolution⌋ of the points: from the points'
    extremes, as a correctly rounded division by a positive number and the floor are
    both monotonic (the same cells as dividing every point, four divisions instead)."""
    i0, j0, i1, j1 = bounds
    if points.shape[0] == 0:
        return i0, j0, i1, j1
    x0 = x1 = points[0, 0]
    y0 = y1 = points[0, 1]
    for k in range(1, points.shape[0]):
        x, y = points[k, 0], points[k, 1]
        x0, x1 = min(x0, x), max(x1, x)
        y0, y1 = min(y0, y), max(y1, y)
    i0, i1 = min(i0, math.floor(x0 / resolution)), max(i1, math.floor(x1 / resolution))
    j0, j1 = min(j0, math.floor(y0 / resolution)), max(j1, math.floor(y1 / resolution))
    return i0, j0, i1, j1


@njit(cache=True, nogil=True)
def floor_bounds(a: np.ndarray, b: np.ndarray, resolution: float) -> tuple[int, int, int, int]:
    """(i0, j0, i1, j1): the inclusive bounds of the cells ⌊p/resolution⌋ of the rows of
    two N×2 float64 point arrays (not both empty)."""
    big = np.iinfo(np.int64).max
    bounds = (big, big, -big, -big)
    return _widen(b, resolution, _widen(a, resolution, bounds))


@njit(cache=True, nogil=True)
def mark_cells(
    points: np.ndarray, resolution: float, box: tuple[int, int, int, int], marks: np.ndarray
) -> None:
    """Mark the cells ⌊p/resolution⌋ of the N×2 float64 `points` in the flat bitmap of
    `box` = (i0, j0, width, height)."""
    i0, j0, width, height = box
    for k in range(points.shape[0]):
        i = math.floor(points[k, 0] / resolution) - i0
        j = math.floor(points[k, 1] / resolution) - j0
        if not (0 <= i < width and 0 <= j < height):
            raise IndexError("point outside the marked box")
        marks[j * width + i] = True


@njit(cache=True, nogil=True)
def mark_end_rays(
    ends: np.ndarray,
    ox: float,
    oy: float,
    resolution: float,
    bundle: bool,
    box: tuple[int, int, int, int],
    marks: np.ndarray,
) -> int:
    """Mark the cells crossed by the rays from the sensor (ox, oy) [m] to the centres of
    the cells set in the flat bitmap `ends` of `box` = (i0, j0, width, height), in `marks`
    (same box); returns the number of rays traced.

    With `bundle`, only the longest ray of each bearing bin is traced (the last of equally
    long ones in (j, i) order), as `lattice.bundle_rays`: bins of width
    0.5·resolution / max(r_max, resolution) over the bearing atan2(dy, dx) + π. Rays are
    sampled as `mark_ray_samples`, from the origin in cell units (ox/res, oy/res)."""
    i0, j0, width, _ = box
    n = 0
    for c in range(ends.shape[0]):
        n += ends[c]
    tx = np.empty(n)
    ty = np.empty(n)
    k = 0
    for c in range(ends.shape[0]):
        if ends[c]:
            j, i = divmod(c, width)
            tx[k] = (i + (i0 + 0.5)) * resolution
            ty[k] = (j + (j0 + 0.5)) * resolution
            k += 1
    dx = np.empty(n)
    dy = np.empty(n)
    for k in range(n):
        dx[k] = tx[k] - ox
        dy[k] = ty[k] - oy
    pick = np.arange(n)
    if bundle and n > 0:
        r = np.empty(n)
        r_max = 0.0
        for k in range(n):
            r[k] = math.hypot(dx[k], dy[k])
            r_max = max(r_max, r[k])
        bin_width = 0.5 * resolution / max(r_max, resolution)
        bins = np.empty(n, dtype=np.int64)
        n_bins = 0
        for k in range(n):
            bins[k] = math.floor((math.atan2(dy[k], dx[k]) + math.pi) / bin_width)
            n_bins = max(n_bins, bins[k] + 1)
        longest = np.full(n_bins, -np.inf)
        best = np.full(n_bins, -1, dtype=np.int64)
        for k in range(n):
            b = bins[k]
            if r[k] >= longest[b]:
                longest[b] = r[k]
                best[b] = k
        m = 0
        for b in range(n_bins):
            if best[b] >= 0:
                pick[m] = best[b]
                m += 1
        pick = pick[:m]
    cx = np.empty(len(pick))
    cy = np.empty(len(pick))
    steps = np.empty(len(pick), dtype=np.int64)
    for q in range(len(pick)):
        cx[q] = dx[pick[q]] / resolution
        cy[q] = dy[pick[q]] / resolution
        steps[q] = max(math.ceil(2.0 * math.hypot(cx[q], cy[q])), 1)
    mark_ray_samples(ox / resolution, oy / resolution, cx, cy, steps, box, marks)
    return len(pick)


@njit(cache=True, nogil=True)
def accumulate_hits(
    points: np.ndarray,
    resolution: float,
    box: tuple[int, int, int, int],
    hit_x: np.ndarray,
    hit_y: np.ndarray,
    hits: np.ndarray,
) -> None:
    """Add each world point (N×2) to its cell ⌊p/resolution⌋ of the (height, width)
    layers covering `box` = (i0, j0, width, height): its offset from the cell's centre to
    hit_x, hit_y and 1 to hits (float32). Points outside the box are skipped (a grid that
    rolled holds only part of a frame)."""
    i0, j0, width, height = box
    for k in range(points.shape[0]):
        x, y = points[k, 0], points[k, 1]
        i = math.floor(x / resolution)
        j = math.floor(y / resolution)
        c, r = i - i0, j - j0
        if 0 <= c < width and 0 <= r < height:
            hit_x[r, c] += x - (i + 0.5) * resolution
            hit_y[r, c] += y - (j + 0.5) * resolution
            hits[r, c] += 1.0


@njit(cache=True, nogil=True)
def place_frame(
    points: np.ndarray,
    x: float,
    y: float,
    c: float,
    s: float,
    sensor_x: float,
    sensor_y: float,
    resolution: float,
    out: np.ndarray,
) -> tuple[float, float, int, int, int, int]:
    """A walker-frame frame placed at the pose (x, y) with heading cos c, sin s: its
    float32 points (N×2) into `out` (N×2 float64) as `place_points`, and (sx, sy, i0, j0,
    i1, j1): the sensor's world position (the same operations) and the inclusive bounds
    of the cells ⌊p/resolution⌋ of the sensor and the points, as
    `mapping.grid.GridExtent.integrate` takes them from a `WorldObservation`."""
    place_points(points, x, y, c, s, out)
    sx = (x + c * sensor_x) - s * sensor_y
    sy = (y + s * sensor_x) + c * sensor_y
    i = math.floor(sx / resolution)
    j = math.floor(sy / resolution)
    i0, j0, i1, j1 = _widen(out, resolution, (i, j, i, j))
    return sx, sy, i0, j0, i1, j1


@njit(cache=True, nogil=True)
def integrate_log_odds(
    world: np.ndarray,
    n_obstacles: int,
    sx: float,
    sy: float,
    resolution: float,
    bundle: bool,
    box: tuple[int, int, int, int],
    window: tuple[int, int, int, int],
    grid_lo: tuple[int, int],
    log_odds: np.ndarray,
    l_occ: np.float32,
    l_free: np.float32,
    l_min: np.float32,
    l_max: np.float32,
    hit_x: np.ndarray,
    hit_y: np.ndarray,
    hits: np.ndarray,
) -> None:
    """One frame into a log-odds grid in one call, as `mapping.grid.OccupancyGrid`'s
    update does it in several: `world` (N×2 float64) its obstacle points (the first
    n_obstacles) and ray ends, the sensor at (sx, sy); the cells marked over the frame's
    `box` (i0, j0, width, height), the rays traced (`mark_end_rays`), and the cells of
    `window` (the part of the box the grid holds, same form) updated as
    `update_log_odds` in the (ny, nx) layers whose cell [0, 0] is the lattice cell
    `grid_lo`; with hit layers (not empty, as `HitCentroidGrid`'s) the obstacle points
    are added to them as `accumulate_hits`."""
    i0, j0, width, height = box
    ends = np.zeros(width * height, dtype=np.bool_)
    mark_cells(world[n_obstacles:], resolution, box, ends)
    occupied = np.zeros(width * height, dtype=np.bool_)
    mark_cells(world[:n_obstacles], resolution, box, occupied)
    crossed = ends.copy()
    mark_end_rays(ends, sx, sy, resolution, bundle, box, crossed)
    wi0, wj0, w_width, w_height = window
    crop = (slice(wj0 - j0, wj0 - j0 + w_height), slice(wi0 - i0, wi0 - i0 + w_width))
    row0, col0 = wj0 - grid_lo[1], wi0 - grid_lo[0]
    rows, cols = slice(row0, row0 + w_height), slice(col0, col0 + w_width)
    update_log_odds(
        log_odds[rows, cols],
        occupied.reshape(height, width)[crop],
        crossed.reshape(height, width)[crop],
        l_occ, l_free, l_min, l_max,
    )  # fmt: skip
    if hits.size:
        accumulate_hits(
            world[:n_obstacles], resolution, window, hit_x[rows, cols], hit_y[rows, cols],
            hits[rows, cols],
        )  # fmt: skip
