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

from mapping.distance import capped_squared_distances
from slam.kernel_math import copy_into, copy_vector, wrap
from slam.scan_proposal import fit_one


@njit(cache=True, nogil=True, inline="always")
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
    for j in range(max(cj - kernel, j0), min(cj + kernel + 1, j0 + ny)):
        r = j - j0
        dy0 = (j + 0.5) * resolution - y
        for i in range(max(ci - kernel, i0), min(ci + kernel + 1, i0 + nx)):
            c = i - i0
            if log_odds[r, c] <= occupied_log_odds:
                continue
            dx = (i + 0.5) * resolution - x
            dy = dy0
            if centroids:
                h = hits[r, c]
                if h > 0:
                    dx += hit_x[r, c] / h
                    dy += hit_y[r, c] / h
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
def log_likelihood_field(targets: np.ndarray, table: np.ndarray, cap: int) -> np.ndarray:
    """The flat log p of a likelihood field over the (H, W) bool `targets` (the cells a
    point is expected on), for `field_log_likelihood`: table[d²] at each cell, d² its
    squared distance [cells²] to the nearest target measured up to cap
    (mapping.distance.capped_squared_distances), and table[cap²] — the field's floor,
    which the table must equal for every d ≥ cap — in the last entry, for points
    outside."""
    ny, nx = targets.shape
    d2 = capped_squared_distances(targets, cap)
    out = np.empty(ny * nx + 1)
    for i in range(ny):
        cells = out[i * nx : (i + 1) * nx]
        for x in range(nx):
            cells[x] = table[d2[i, x]]
    out[ny * nx] = table[cap * cap]
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
    back = -1  # the move that would undo the last one: its pose scored below this one's
    while halvings <= refinements:
        c, s = math.cos(pose[2]), math.sin(pose[2])
        improved = False
        best_score = best
        best_matched = matched
        taken = -1
        for move in range(6):
            if move == back:
                continue
            copy_vector(trial, pose)
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
                copy_vector(best_pose, trial)
                taken = move
        if improved:
            copy_vector(pose, best_pose)
            best, matched = best_score, best_matched
            back = taken ^ 1  # forward <-> back, left <-> right, turn left <-> right
        else:
            back = -1
            step_xy *= 0.5
            step_theta *= 0.5
            halvings += 1
    return pose, best, matched


@njit(cache=True, nogil=True)
def propose(
    grid: tuple,
    points: np.ndarray,
    start: np.ndarray,
    prior_cov: np.ndarray,
    turns: np.ndarray,
    match: tuple,
    fit_steps: np.ndarray,
    min_points: int,
    e: np.ndarray,
) -> tuple[np.ndarray, float, bool, int]:
    """One particle's improved proposal against its own map (slam.grid_rbpf, steps 1-2):
    the hill climb from the odometry pose `start` and from it turned by each of `turns`
    (rad), the best of the climbs kept; when at least `min_points` points matched, the
    Gaussian fit of likelihood × prior on the 3×3×3 lattice of `fit_steps` around the
    match (slam.scan_proposal.fit_one), the pose drawn from it with the standard normals
    e (3,), log η plus the lattice cell's log volume; otherwise the pose drawn from the
    prior N(start, prior_cov) and the frame's log-likelihood there.

    match = (step_m, step_rad, refinements, kernel_cells, sigma_m, z_hit, z_rand,
    beam_weight). Returns (pose, log weight, matched, the winning start: k when the climb
    turned by turns[k − 1] found a better optimum more than a first step away from the
    straight climb's, else 0)."""
    step_m, step_rad, refinements, kernel, sigma, z_hit, z_rand, beam_weight = match
    best_pose, best_score, best_matched = hill_climb(
        grid, points, start, step_m, step_rad, refinements, kernel, sigma, z_hit, z_rand
    )
    straight = best_pose
    winner = 0
    for k in range(turns.shape[0]):
        s = start.copy()
        s[2] += turns[k]
        pose, score, matched = hill_climb(
            grid, points, s, step_m, step_rad, refinements, kernel, sigma, z_hit, z_rand
        )
        if score > best_score:
            best_pose, best_score, best_matched = pose, score, matched
            # a win only if it found another optimum, not the straight climb's
            moved = math.hypot(pose[0] - straight[0], pose[1] - straight[1])
            far = abs(wrap(pose[2] - straight[2])) > step_rad or moved > step_m
            winner = k + 1 if far else 0
    mean = np.empty(3)
    cov = np.empty((3, 3))
    if best_matched >= min_points:
        fit = np.empty((27, 3))
        ll = np.empty(27)
        g = 0
        for i in range(-1, 2):
            for j in range(-1, 2):
                for k in range(-1, 2):
                    fit[g, 0] = best_pose[0] + i * fit_steps[0]
                    fit[g, 1] = best_pose[1] + j * fit_steps[1]
                    fit[g, 2] = best_pose[2] + k * fit_steps[2]
                    ll[g] = (
                        beam_weight
                        * frame_log_likelihood(grid, points, fit[g], kernel, sigma, z_hit, z_rand)[
                            0
                        ]
                    )
                    g += 1
        log_w = fit_one(fit, ll, start, prior_cov, fit_steps, mean, cov)
        log_w += math.log(fit_steps[0] * fit_steps[1] * fit_steps[2]) - 1.5 * math.log(
            2.0 * math.pi
        )
    else:
        copy_vector(mean, start)
        copy_into(cov, prior_cov)
    pose = draw(mean, cov, e)
    if best_matched < min_points:
        log_w = (
            beam_weight * frame_log_likelihood(grid, points, pose, kernel, sigma, z_hit, z_rand)[0]
        )
    return pose, log_w, best_matched >= min_points, winner


@njit(cache=True, nogil=True)
def draw(mean: np.ndarray, cov: np.ndarray, e: np.ndarray) -> np.ndarray:
    """mean + L e, L the lower Cholesky factor of the positive definite cov; θ wrapped."""
    l00 = math.sqrt(cov[0, 0])
    l10 = cov[1, 0] / l00
    l20 = cov[2, 0] / l00
    l11 = math.sqrt(cov[1, 1] - l10 * l10)
    l21 = (cov[2, 1] - l20 * l10) / l11
    l22 = math.sqrt(cov[2, 2] - l20 * l20 - l21 * l21)
    out = np.empty(3)
    out[0] = mean[0] + l00 * e[0]
    out[1] = mean[1] + l10 * e[0] + l11 * e[1]
    theta = mean[2] + l20 * e[0] + l21 * e[1] + l22 * e[2]
    out[2] = wrap(theta)
    return out
