"""A synthetic run for the absolute-observation tests: a walker on a circle whose velocity
odometry over-reports its turn (as a slipping wheel does), with seeded noisy position
fixes and compass headings along the true path."""

from __future__ import annotations

import numpy as np

from hardware.geometry import wrap_angle
from hardware.messages import CompassHeading, PositionFix, VelocityOdometry
from slam.motion import apply_increment
from slam.trajectory import Trajectory

V_MPS, OMEGA_RADPS, DT_S = 0.5, 0.1, 0.1
ODOMETRY_TURN_GAIN, ODOMETRY_TURN_BIAS = 1.2, 0.02  # what the odometry reports of ω


def drifting_run(
    seed: int = 0,
    steps: int = 600,
    every: int = 10,
    sigma_fix_m: float = 0.3,
    sigma_compass_rad: float = 0.1,
    start: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> tuple[list, Trajectory]:
    """(messages in time order, the true trajectory): velocity odometry every DT_S that
    turns 1.2·ω + 0.02 rad/s where the walker turns ω, and every `every` steps a fix and
    a heading with the given noise (seeded)."""
    rng = np.random.default_rng(seed)
    t = DT_S * np.arange(steps + 1)
    poses = [np.array(start, dtype=float)]
    for _ in range(steps):
        poses.append(apply_increment(poses[-1], V_MPS * DT_S, OMEGA_RADPS * DT_S))
    truth = np.array(poses)
    messages: list = []
    odometry_omega = ODOMETRY_TURN_GAIN * OMEGA_RADPS + ODOMETRY_TURN_BIAS
    for k, tk in enumerate(t.tolist()):
        messages.append(VelocityOdometry(tk, V_MPS, odometry_omega))
        if k > 0 and k % every == 0:
            x, y = truth[k, :2] + rng.normal(0.0, sigma_fix_m, 2)
            heading = float(wrap_angle(truth[k, 2] + rng.normal(0.0, sigma_compass_rad)))
            messages.append(PositionFix(tk, float(x), float(y), sigma_fix_m))
            messages.append(CompassHeading(tk, heading, sigma_compass_rad))
    return messages, Trajectory(t, truth)


def position_rmse(est: Trajectory, truth: Trajectory) -> float:
    """Unaligned position RMSE of `est` at the true times."""
    p = est.interpolate(truth.t)
    return float(np.sqrt(np.mean(np.sum((p[:, :2] - truth.poses[:, :2]) ** 2, axis=1))))
