"""Potential-field braking in the style of the RT Walker (Hirata et al.).

Every occupied map cell within `radius_m` of a reference point on the walker (on its
centre line, `origin_x_m` ahead of the rear axle) and within ±`half_fov_deg` of the
heading pushes the walker away from it with a magnitude

    m_i = cell_size_m · gain_per_cell · (1 / r_i^k − 1 / radius^k),  r_i ≥ min_distance_m,

which grows as 1/r^k near the obstacle and falls to zero at the influence radius (so a
cell entering the radius does not make the brakes jump). Weighting each cell by the map's
cell size makes the field a line integral along an obstacle's outline, independent of the
map resolution. The summed repulsion F = Σ −m_i u_i (u_i the unit vector to the cell,
walker frame: x forward, y left) becomes brake torques above the residual torque:

- turning: the lateral component F_y pushes the walker sideways; a braked walker turns
  toward its braked wheel, so F_y > 0 (pushed left, obstacles on the right) brakes the
  left wheel by gain_turn_nm · F_y, and F_y < 0 the right wheel;
- slowing: cells straight ahead (inside the walker-width band, |y| ≤ brake_half_width_m)
  contribute their backward push −F_x,band to *both* brakes, gain_slow_nm · (−F_x,band):
  an obstacle dead ahead gives no side to turn to but should slow the walker.

Both torques are clamped to the brake limits; nothing brakes while the walker is not
moving forward. A pure potential field has the usual local minima (a symmetric dead end
only slows the walker); the user still chooses where to go.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from control.base import ControlInput, Controller
from hardware.calibration import WalkerCalibration
from hardware.geometry import to_walker_frame
from hardware.messages import BrakeCommand
from hardware.registry import Spec


@dataclass(frozen=True)
class PotentialFieldConfig:
    """Potential-field parameters.

    radius_m: influence radius of an occupied cell [m] (1.2);
    k: exponent of the 1/r^k repulsion (2);
    gain_per_cell: scale of each cell's repulsion (1; the field is then in m^(1−k));
    cell_size_m: weight of one occupied cell, the map's cell size [m] (0.05);
    gain_turn_nm: brake torque per unit lateral field [N·m] (1.5: a long wall alongside,
    0.5 m from the centre line, gives about 1.8 N·m on the wheel away from it);
    gain_slow_nm: torque on both brakes per unit backward field from the band ahead [N·m]
    (0.8: a wall across the path 0.5 m ahead of the reference point gives about 1.4 N·m
    each);
    origin_x_m: the reference point on the centre line, ahead of the rear axle [m] (0.3,
    the middle of the frame);
    half_fov_deg: only cells within ±this of the heading, seen from the reference point,
    count (90: everything ahead of it);
    brake_half_width_m: half-width of the band ahead whose push slows the walker [m]
    (0.345, half the walker);
    min_distance_m: distances are floored at this to bound the field [m] (0.1);
    min_speed_mps: brakes act only while moving forward faster than this [m/s] (0.05).
    """

    radius_m: float = 1.2
    k: float = 2.0
    gain_per_cell: float = 1.0
    cell_size_m: float = 0.05
    gain_turn_nm: float = 1.5
    gain_slow_nm: float = 0.8
    origin_x_m: float = 0.3
    half_fov_deg: float = 90.0
    brake_half_width_m: float = 0.345
    min_distance_m: float = 0.1
    min_speed_mps: float = 0.05

    def __post_init__(self) -> None:
        if not 0 < self.min_distance_m < self.radius_m:
            raise ValueError(
                f"need 0 < min_distance_m < radius_m, got {self.min_distance_m}, {self.radius_m}"
            )
        if not self.k > 0:
            raise ValueError(f"k must be > 0, got {self.k}")
        if not 0 < self.half_fov_deg <= 180:
            raise ValueError(f"half_fov_deg must be in (0, 180], got {self.half_fov_deg}")


@dataclass(frozen=True)
class Field:
    """Summed repulsion in the walker frame: total (fx, fy) and the band-ahead fx_band."""

    fx: float
    fy: float
    fx_band: float
    n_cells: int


def repulsion(points_walker: np.ndarray, config: PotentialFieldConfig) -> Field:
    """The summed repulsive field of occupied cells given in the walker frame."""
    c = config
    rel = np.asarray(points_walker, dtype=float).reshape(-1, 2) - np.array([c.origin_x_m, 0.0])
    r = np.hypot(rel[:, 0], rel[:, 1])
    ang = np.arctan2(rel[:, 1], rel[:, 0])
    keep = (r < c.radius_m) & (np.abs(ang) <= math.radians(c.half_fov_deg))
    if not np.any(keep):
        return Field(0.0, 0.0, 0.0, 0)
    rel, r = rel[keep], r[keep]
    rc = np.maximum(r, c.min_distance_m)
    mag = c.cell_size_m * c.gain_per_cell * (rc**-c.k - c.radius_m**-c.k)
    unit = rel / np.maximum(r, 1e-12)[:, None]
    push = -mag[:, None] * unit
    band = (np.abs(rel[:, 1]) <= c.brake_half_width_m) & (rel[:, 0] > 0)
    return Field(
        float(push[:, 0].sum()),
        float(push[:, 1].sum()),
        float(push[band, 0].sum()),
        int(keep.sum()),
    )


class PotentialField(Controller):
    """See the module docstring; last_field holds the last tick's Field."""

    def __init__(self, config: PotentialFieldConfig, calibration: WalkerCalibration) -> None:
        self.config = config
        self.cal = calibration
        self.last_field = Field(0.0, 0.0, 0.0, 0)

    def command(self, inp: ControlInput) -> BrakeCommand:
        cfg, brake = self.config, self.cal.brake
        off = brake.torque_off_nm
        if inp.v <= cfg.min_speed_mps:
            self.last_field = Field(0.0, 0.0, 0.0, 0)
            return BrakeCommand(inp.t, off, off, "potential-field")
        f = repulsion(to_walker_frame(inp.occupied_xy, inp.pose), cfg)
        self.last_field = f
        slow = cfg.gain_slow_nm * max(-f.fx_band, 0.0)
        left = off + cfg.gain_turn_nm * max(f.fy, 0.0) + slow
        right = off + cfg.gain_turn_nm * max(-f.fy, 0.0) + slow
        return BrakeCommand(inp.t, brake.clamp(left), brake.clamp(right), "potential-field")


SPEC = Spec(
    "potential-field",
    PotentialFieldConfig,
    PotentialField,
    "RT Walker style: brake away from the summed 1/r^k repulsion of nearby cells",
)
