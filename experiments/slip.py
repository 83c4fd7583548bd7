"""The slip experiment of thesis Fig 6.1: push the walker straight with brakes engaged.

The walker is pushed along the same straight line with neither, the left, the right or
both brakes at a fixed level; the true path stays straight while the dead-reckoned path
curves toward the braked wheel, whose encoder under-reports while it slips.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from hardware.errors import ConfigError
from hardware.geometry import between
from hardware.messages import BrakeCommand, GroundTruthPose
from hardware.sim.simulator import SimConfig, Simulator
from hardware.sim.user import UserParams
from hardware.sim.world import World
from slam.base import create
from slam.trajectory import Trajectory

BRAKE_SETTINGS = ("none", "left", "right", "both")

# Someone walking a line on the floor and forcing the walker along it (the thesis pushed
# it along the same path every time): strong steering, no drift of their sense of heading.
STRAIGHT_PUSHER = UserParams(
    speed_mps=0.6,
    max_push_n=120.0,
    max_steer_n=120.0,
    yaw_gain=150.0,
    speed_integral_gain=60.0,
    heading_drift_rad_per_sqrt_m=0.0,
)


@dataclass(frozen=True, eq=False)
class PushResult:
    brakes: str
    surface: str | float
    truth: Trajectory
    dead_reckoning: Trajectory

    def end_in_start_frame(self, traj: Trajectory) -> np.ndarray:
        """Final pose relative to the start pose: x ahead, y to the left, θ."""
        return between(traj.poses[0], traj.poses[-1])

    @property
    def lateral_drift_m(self) -> float:
        """Dead-reckoned minus true sideways offset at the end (+ = curved left)."""
        return float(
            self.end_in_start_frame(self.dead_reckoning)[1] - self.end_in_start_frame(self.truth)[1]
        )


def straight_push(
    surface: str | float,
    brakes: str,
    level: float = 0.6,
    length_m: float = 6.0,
    seed: int = 0,
) -> PushResult:
    """Push the walker `length_m` straight ahead with `brakes` held at `level` of full PWM."""
    if brakes not in BRAKE_SETTINGS:
        raise ConfigError(f"unknown brake setting '{brakes}'; valid: {', '.join(BRAKE_SETTINGS)}")
    route = np.column_stack([np.linspace(0.0, length_m + 0.5, 30), np.zeros(30)])
    world = World("straight", (-1.0, length_m + 2.0, -3.0, 3.0), (), (), route, (0.0, 0.0, 0.0))
    cfg = SimConfig(surface=surface, seed=seed, duration_s=4 * length_m / STRAIGHT_PUSHER.speed_mps)
    sim = Simulator(world, replace(cfg, user=STRAIGHT_PUSHER))
    cal = sim.calibration
    on = cal.brake.torque(level * cal.brake.pwm_max)
    off = cal.brake.torque_off_nm
    left = on if brakes in ("left", "both") else off
    right = on if brakes in ("right", "both") else off
    sim.send(BrakeCommand(0.0, left, right, "slip-push"))
    dr = create("dead-reckoning", cal, initial_pose=world.start_pose)
    t_truth, truth = [], []
    while not sim.done and sim.state.x < length_m:
        for msg in sim.poll(sim.t + 0.1):
            dr.process(msg)
            if isinstance(msg, GroundTruthPose):
                t_truth.append(msg.t)
                truth.append((msg.x, msg.y, msg.theta))
    return PushResult(
        brakes, surface, Trajectory(np.array(t_truth), np.array(truth)), dr.trajectory()
    )
