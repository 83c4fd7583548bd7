"""Open-loop braking (thesis eq 5.13) and the manual baseline (`none`).

Brake the wheel on the side of the chosen turn with a torque proportional to how far
the nearest obstacle ahead is inside [d_min, d_max]; release both when nothing is ahead
or the walker is not moving forward.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from control.base import ControlInput, Controller
from control.perception import distance_ahead, turn_direction
from hardware.calibration import WalkerCalibration
from hardware.geometry import to_walker_frame
from hardware.messages import BrakeCommand
from hardware.registry import Spec


@dataclass(frozen=True)
class OpenLoopConfig:
    """Open-loop braking parameters (thesis values).

    d_min_m / d_max_m: full brake below d_min, none beyond d_max, linear between (5.13);
    half_width_m: half-width of the band ahead searched for obstacles (walker 0.69 m);
    arc_half_deg / n_arcs: the turn-decision fan (±45°, 32 sub-arcs);
    unseen_free_radius_m: free radius of arcs outside the view with no obstacle (0 in the
    thesis); min_speed_mps: brakes act only while moving forward faster than this;
    latch_turn: keep the side chosen when a braking episode starts until it ends (nothing
    within d_max, or not moving forward). False decides every tick, as the thesis did; in
    simulation that decision flips back and forth while turning at a wall, because the arcs
    the walker turns toward leave the camera's view and then count as blocked.
    """

    d_min_m: float = 0.5
    d_max_m: float = 1.25
    half_width_m: float = 0.345
    arc_half_deg: float = 45.0
    n_arcs: int = 32
    unseen_free_radius_m: float = 0.0
    min_speed_mps: float = 0.05
    latch_turn: bool = True

    def __post_init__(self) -> None:
        if not 0 <= self.d_min_m < self.d_max_m:
            raise ValueError(f"need 0 <= d_min < d_max, got {self.d_min_m}, {self.d_max_m}")


def open_loop_level(d: float, d_min: float, d_max: float) -> float:
    """Brake level in [0, 1] from the front distance (eq 5.13 divided by 12 V)."""
    if d >= d_max:
        return 0.0
    if d <= d_min:
        return 1.0
    return (d_max - d) / (d_max - d_min)


class OpenLoop(Controller):
    def __init__(self, config: OpenLoopConfig, calibration: WalkerCalibration) -> None:
        self.config = config
        self.cal = calibration
        self.last_distance = math.inf
        self.last_direction = 0

    def command(self, inp: ControlInput) -> BrakeCommand:
        cfg, brake = self.config, self.cal.brake
        off = brake.torque_off_nm
        pts = to_walker_frame(inp.occupied_xy, inp.pose)
        d = distance_ahead(pts, self.cal, cfg.half_width_m)
        self.last_distance = d
        level = open_loop_level(d, cfg.d_min_m, cfg.d_max_m)
        if level == 0.0 or inp.v <= cfg.min_speed_mps:
            self.last_direction = 0
            return BrakeCommand(inp.t, off, off, "open-loop")
        self.last_direction = turn_direction(pts, self.cal, cfg, self.last_direction)
        torque = off + (brake.torque_max_nm - off) * level
        if self.last_direction > 0:  # turn left: brake the left wheel
            return BrakeCommand(inp.t, torque, off, "open-loop")
        return BrakeCommand(inp.t, off, torque, "open-loop")


@dataclass(frozen=True)
class ManualConfig:
    """The manual baseline has no parameters: both brakes stay at their residual torque."""


class Manual(Controller):
    def __init__(self, config: ManualConfig, calibration: WalkerCalibration) -> None:
        self.off = calibration.brake.torque_off_nm

    def command(self, inp: ControlInput) -> BrakeCommand:
        return BrakeCommand(inp.t, self.off, self.off, "none")


OPEN_LOOP = Spec(
    "open-loop",
    OpenLoopConfig,
    OpenLoop,
    "brake torque from front distance, eq 5.13",
)
NONE = Spec(
    "none",
    ManualConfig,
    Manual,
    "manual baseline: brakes released",
)
