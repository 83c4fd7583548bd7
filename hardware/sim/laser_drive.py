"""A robot with a 2-D laser driving laps of a closed route among walls: noisy velocity
odometry and laser scans, the PICO maze robot's setting (EMC 2016: a small robot, a
270° laser, corners as landmarks), for tests and benchmarks of the laser features
(mapping.scan_features) and the localizers that use them — with none of the walker's
physics.

`laser_drive(walls, route, ...)` steers along the closed polyline `route` (pure pursuit
on the true pose, a look-ahead of `lookahead_m`) at speed `v` and gives the steps (each
the messages of one time: a VelocityOdometry, and a LaserScan every `scan_every` steps)
and the true path. The walls are upright boxes (hardware.sim.raycast rows [cx, cy, yaw,
sx, sy, z0, z1]) hit by level rays at `laser_height_m`. The truth moves along the same
Euler step as hardware.sim.landmark_drive; the odometry is the true (v, ω) plus white
noise.

`PICO_MAZE` is a 6 × 4 m room with a 2 × 1 m block in its middle and the route a
rectangle around the block, 1 m from every wall: four concave room corners and four
convex block corners, two to six in view at a time.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hardware.messages import LaserScan, Message, VelocityOdometry
from hardware.sim.raycast import BoxRayCaster

__all__ = ["PICO_MAZE", "PICO_ROUTE", "LaserNoise", "laser_drive"]


def _wall(x0: float, y0: float, x1: float, y1: float, thick: float = 0.1) -> list[float]:
    """An axis-aligned wall from (x0, y0) to (x1, y1) as a box row."""
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    return [cx, cy, 0.0, abs(x1 - x0) + thick, abs(y1 - y0) + thick, 0.0, 1.0]


PICO_MAZE = np.array(
    [
        _wall(-3.0, -2.0, 3.0, -2.0),
        _wall(-3.0, 2.0, 3.0, 2.0),
        _wall(-3.0, -2.0, -3.0, 2.0),
        _wall(3.0, -2.0, 3.0, 2.0),
        [0.0, 0.0, 0.0, 2.0, 1.0, 0.0, 1.0],  # the block
    ]
)
PICO_ROUTE = ((-2.0, -1.0), (2.0, -1.0), (2.0, 1.0), (-2.0, 1.0))


@dataclass(frozen=True)
class LaserNoise:
    """Standard deviations of the simulated sensors (per sample)."""

    v_frac: float = 0.05  # of the speed
    omega: float = math.radians(3.0)  # rad/s
    range_m: float = 0.01


def laser_drive(
    walls: np.ndarray,
    route: Sequence[tuple[float, float]],
    steps: int,
    dt: float = 0.1,
    v: float = 0.5,
    noise: LaserNoise = LaserNoise(),
    scan_every: int = 2,
    fov_rad: float = math.radians(270.0),
    beams: int = 541,
    max_range_m: float = 10.0,
    laser_height_m: float = 0.3,
    lookahead_m: float = 0.5,
    seed: int = 0,
) -> tuple[list[list[Message]], np.ndarray]:
    """The steps (messages of one time each) and the true path (steps + 1, 4: t, x, y,
    θ), starting at the route's first point facing its second."""
    rng = np.random.default_rng(seed)
    caster = BoxRayCaster(walls)
    pts = np.asarray(route, dtype=float)
    x = np.array([*pts[0], math.atan2(*(pts[1] - pts[0])[::-1])])
    angles = -0.5 * fov_rad + fov_rad / (beams - 1) * np.arange(beams)
    target = 1
    out: list[list[Message]] = []
    truth = [(0.0, *x)]
    for k in range(steps):
        t = k * dt
        while math.hypot(*(pts[target] - x[:2])) < lookahead_m:
            target = (target + 1) % len(pts)
        heading = math.atan2(pts[target][1] - x[1], pts[target][0] - x[0])
        turn = math.remainder(heading - x[2], 2 * math.pi)
        omega = 2.0 * v * math.sin(turn) / lookahead_m  # pure pursuit's curvature × v
        msgs: list[Message] = [
            VelocityOdometry(
                t,
                v * (1.0 + noise.v_frac * rng.standard_normal()),
                omega + noise.omega * rng.standard_normal(),
            )
        ]
        if k % scan_every == 0:
            a = x[2] + angles
            dirs = np.column_stack([np.cos(a), np.sin(a), np.zeros(beams)])
            hit, _ = caster.cast(np.array([x[0], x[1], laser_height_m]), dirs, max_range_m)
            ranges = hit + noise.range_m * rng.standard_normal(beams)
            ranges[~np.isfinite(hit)] = np.inf
            msgs.append(LaserScan(t, float(angles[0]), float(angles[1] - angles[0]), ranges,
                                  max_range_m))  # fmt: skip
        out.append(msgs)
        x = x + dt * np.array([v * math.cos(x[2]), v * math.sin(x[2]), omega])
        truth.append((t + dt, *x))
    return out, np.array(truth)
