"""Compiled (numba) scan scoring against one particle's occupancy grid, and hill climbing.

The Rao-Blackwellized particle filter (slam.grid_rbpf) scores every particle's frame
against that particle's own map many times per frame, so the score is a compiled loop
over the frame's points instead of a likelihood field (a distance transform per map and
frame would cost more than the whole update). It is the endpoint model of GMapping
(Grisetti et al. 2007): each point, placed at the pose, looks for the occupied cell
nearest to it within ± `kernel` cells of its own cell; at distance d (point to cell
centre, or to the mean of the points the cell was mapped from when the grid keeps them:
mapping.grid.HitCentroidGrid, GMapping's cell model) it scores
log(z_hit·exp(−d²/2σ²) + z_rand), and log(z_rand) when there is none. A cell is occupied
when its log-odds exceed `occupied_log_odds`.

A grid is passed as `grid` = (log_odds, hit_x, hit_y, hits, i0, j0, resolution,
occupied_log_odds): the layers of mapping.grid.OccupancyGrid / HitCentroidGrid, indexed
[iy, ix] with cell (i, j) of the world lattice at [j − j0, i − i0]; hits has shape (0, 0)
for a grid without hit centroids.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def point_log_likelihood(
    grid: tuple,
    x: float,
    y: float,
    kernel: int,
    sigma: float,
    z_hit: float,
    z_rand: float,
) -> tuple[float, bool]:
    """(log-likelihood, matched) of one world point (module docstring)."""
    log_odds, hit_x, hit_y, hits, i0, j0, resolution, occupied_log_odds = grid
    centroids = hits.shape[0] > 0
    ny, nx = log_odds.shape
    ci = math.floor(x / resolution)
    cj = math.floor(y / resolution)
    best = math.inf
    for j in range(cj - kernel, cj + kernel + 1):
        r = j - j0
        if r < 0 or r >= ny:
            continue
        for i in range(ci - kernel, ci + kernel + 1):
            c = i - i0
            if c < 0 or c >= nx or log_odds[r, c] <= occupied_log_odds:
                continue
            dx = (i + 0.5) * resolution - x
            dy = (j + 0.5) * resolution - y
            if centroids and hits[r, c] > 0:
                dx += hit_x[r, c] / hits[r, c]
                dy += hit_y[r, c] / hits[r, c]
            best = min(best, dx * dx + dy * dy)
    if best == math.inf:
        return math.log(z_rand), False
    return math.log(z_hit * math.exp(-0.5 * best / (sigma * sigma)) + z_rand), True


@njit(cache=True, nogil=True)
def frame_log_likelihood(
    grid: tuple,
    points: np.ndarray,
    pose: np.ndarray,
    kernel: int,
    sigma: float,
    z_hit: float,
    z_rand: float,
) -> tuple[float, int]:
    """(Σ log-likelihood, number of matched points) of walker-frame points (K, 2) at the
    pose (x, y, θ)."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    total = 0.0
    matched = 0
    for k in range(points.shape[0]):
        px, py = points[k, 0], points[k, 1]
        ll, ok = point_log_likelihood(
            grid,
            pose[0] + c * px - s * py,
            pose[1] + s * px + c * py,
            kernel,
            sigma,
            z_hit,
            z_rand,
        )
        total += ll
        matched += ok
    return total, matched


@njit(cache=True, nogil=True)
def poses_log_likelihood(
    grid: tuple,
    points: np.ndarray,
    poses: np.ndarray,
    kernel: int,
    sigma: float,
    z_hit: float,
    z_rand: float,
) -> np.ndarray:
    """`frame_log_likelihood` at each of the poses (M, 3) → (M,)."""
    out = np.empty(poses.shape[0])
    for m in range(poses.shape[0]):
        out[m] = frame_log_likelihood(
            grid,
            points,
            poses[m],
            kernel,
            sigma,
            z_hit,
            z_rand,
        )[0]
    return out


@njit(cache=True, nogil=True)
def field_log_likelihood(
    log_p: np.ndarray,
    origin_x: float,
    origin_y: float,
    inv_resolution: float,
    nx: int,
    ny: int,
    points: np.ndarray,
    poses: np.ndarray,
) -> np.ndarray:
    """Σ over walker-frame points (K, 2), placed at each of the poses (M, 3), of a
    likelihood field's log p (flat, row-major ny × nx, and one last entry for points
    outside it) → (M,). The particle filter's scan likelihood against the shared map
    (slam.particle_filter), in one pass instead of numpy's (M, K) temporaries."""
    out = np.empty(poses.shape[0])
    outside = ny * nx
    for m in range(poses.shape[0]):
        x, y = poses[m, 0], poses[m, 1]
        c, s = math.cos(poses[m, 2]), math.sin(poses[m, 2])
        total = 0.0
        for k in range(points.shape[0]):
            px, py = points[k, 0], points[k, 1]
            ix = math.floor((x + c * px - s * py - origin_x) * inv_resolution)
            iy = math.floor((y + s * px + c * py - origin_y) * inv_resolution)
            if 0 <= ix < nx and 0 <= iy < ny:
                total += log_p[iy * nx + ix]
            else:
                total += log_p[outside]
        out[m] = total
    return out


@njit(cache=True, nogil=True)
def hill_climb(
    grid: tuple,
    points: np.ndarray,
    start: np.ndarray,
    step_xy: float,
    step_theta: float,
    refinements: int,
    kernel: int,
    sigma: float,
    z_hit: float,
    z_rand: float,
) -> tuple[np.ndarray, float, int]:
    """The pose of locally best log-likelihood from `start` (GMapping's scan matcher):
    move forward, back, left, right (in the pose's own frame) by step_xy or turn by
    ±step_theta while that improves the score; when nothing does, halve both steps, at
    most `refinements` times. Returns (pose, Σ log-likelihood, matched points).

    (One compiled loop, kept whole for numba.)"""
    pose = start.copy()
    best, matched = frame_log_likelihood(
        grid,
        points,
        pose,
        kernel,
        sigma,
        z_hit,
        z_rand,
    )
    trial = np.empty(3)
    best_pose = np.empty(3)
    halvings = 0
    while halvings <= refinements:
        c, s = math.cos(pose[2]), math.sin(pose[2])
        improved = False
        best_score = best
        best_matched = matched
        for move in range(6):
            trial[:] = pose
            if move == 0:
                trial[0] += c * step_xy
                trial[1] += s * step_xy
            elif move == 1:
                trial[0] -= c * step_xy
                trial[1] -= s * step_xy
            elif move == 2:
                trial[0] -= s * step_xy
                trial[1] += c * step_xy
            elif move == 3:
                trial[0] += s * step_xy
                trial[1] -= c * step_xy
            elif move == 4:
                trial[2] += step_theta
            else:
                trial[2] -= step_theta
            score, m = frame_log_likelihood(
                grid,
                points,
                trial,
                kernel,
                sigma,
                z_hit,
                z_rand,
            )
            if score > best_score:
                best_score, best_matched, improved = score, m, True
                best_pose[:] = trial
        if improved:
            pose[:] = best_pose
            best, matched = best_score, best_matched
        else:
            step_xy *= 0.5
            step_theta *= 0.5
            halvings += 1
    return pose, best, matched
