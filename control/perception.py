"""What the braking controllers read from the map: distance ahead and free space per side.

Both work on occupied cell centres in the world frame (N×2) and the walker's pose;
the reference point is the depth camera (the thesis measured from its camera pose).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def front_distance(
    points_walker: np.ndarray, reference_x: float, half_width: float, max_range: float
) -> float:
    """Distance ahead of x = reference_x to the nearest point inside the walker-width band.

    Returns inf when nothing lies in the band within max_range.
    """
    p = points_walker
    ahead = p[:, 0] - reference_x
    inside = (ahead > 0.0) & (np.abs(p[:, 1]) <= half_width) & (ahead <= max_range)
    return float(ahead[inside].min()) if np.any(inside) else math.inf


@dataclass(frozen=True)
class TurnDecision:
    direction: int  # +1 turn left, -1 turn right
    area_left: float
    area_right: float
    radii: np.ndarray  # per sub-arc, right to left


def choose_turn(
    points_walker: np.ndarray,
    reference_x: float,
    half_arc_rad: float,
    n_arcs: int,
    half_fov_rad: float,
    range_limit: float,
    unseen_free_radius: float,
) -> TurnDecision:
    """Compare polar integrals of free space, A = Σ ½ r_i² Δθ, left and right (thesis §5.2).

    Sub-arcs span [−half_arc, +half_arc] around the heading. In each, r_i is the range
    to the nearest occupied point; arcs with no obstacle get `range_limit` when inside
    the camera's view and `unseen_free_radius` when outside it (the thesis used 0 in
    the open loop: an unseen arc might be blocked).
    """
    p = points_walker
    rel = p - np.array([reference_x, 0.0])
    r = np.hypot(rel[:, 0], rel[:, 1])
    ang = np.arctan2(rel[:, 1], rel[:, 0])
    edges = np.linspace(-half_arc_rad, half_arc_rad, n_arcs + 1)
    dtheta = edges[1] - edges[0]
    centres = 0.5 * (edges[:-1] + edges[1:])
    radii = np.where(np.abs(centres) <= half_fov_rad, range_limit, unseen_free_radius)
    keep = (ang >= -half_arc_rad) & (ang < half_arc_rad) & (r <= range_limit)
    idx = np.clip(np.searchsorted(edges, ang[keep], side="right") - 1, 0, n_arcs - 1)
    nearest = np.full(n_arcs, np.inf)
    np.minimum.at(nearest, idx, r[keep])
    radii = np.where(np.isfinite(nearest), nearest, radii)
    area = 0.5 * radii**2 * dtheta
    half = n_arcs // 2
    area_right, area_left = float(area[:half].sum()), float(area[half:].sum())
    return TurnDecision(1 if area_left >= area_right else -1, area_left, area_right, radii)


def distance_ahead(points_walker: np.ndarray, calibration, half_width: float) -> float:
    """`front_distance` from the walker's depth camera, within its range."""
    return front_distance(
        points_walker, calibration.depth_mount.x, half_width, calibration.depth_range_m[1]
    )


def turn_direction(points_walker: np.ndarray, calibration, config, previous: int) -> int:
    """The side to turn to (+1 left, −1 right) for a controller config with arc_half_deg,
    n_arcs, unseen_free_radius_m and latch_turn: `previous` (the side of the braking
    episode under way, 0 if none) when latched, else `choose_turn` from the depth camera
    (its field of view and range)."""
    if config.latch_turn and previous:
        return previous
    intr = calibration.depth_intrinsics
    return choose_turn(
        points_walker,
        calibration.depth_mount.x,
        math.radians(config.arc_half_deg),
        config.n_arcs,
        math.atan(intr.width / 2 / intr.fx),
        calibration.depth_range_m[1],
        config.unseen_free_radius_m,
    ).direction
