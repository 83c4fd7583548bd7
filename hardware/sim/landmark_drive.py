"""A robot driving at constant speed and turn rate among point landmarks: noisy velocity
odometry and range-bearing sightings, the textbook landmark-SLAM scenario (PythonRobotics'
FastSLAM / EKF-SLAM examples use one like it). For benchmarks and tests of the landmark
localizers, with none of the walker's physics.

`landmark_drive(...)` gives the steps (each the messages of one time: a VelocityOdometry,
then one RangeBearing per landmark within range, the way MRCLAM feeds them) and the true
path; `batched(steps)` turns each step's RangeBearing messages into one RangeBearings.
The odometry holds from its time until the next step's; the truth moves along the same
Euler step (x += dt·v·(cos θ, sin θ), θ += dt·ω) at the true (v, ω).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from hardware.messages import Message, RangeBearing, RangeBearings, VelocityOdometry

__all__ = ["DriveNoise", "batched", "landmark_drive"]


@dataclass(frozen=True)
class DriveNoise:
    """Standard deviations of the simulated sensors (per sample)."""

    v: float = 0.5  # m/s
    omega: float = math.radians(10.0)  # rad/s
    range_m: float = 0.3
    bearing_rad: float = math.radians(2.0)


def landmark_drive(
    landmarks: Mapping[int, tuple[float, float]],
    steps: int,
    dt: float,
    v: float,
    omega: float,
    noise: DriveNoise = DriveNoise(),
    max_range_m: float = 20.0,
    seed: int = 0,
) -> tuple[list[list[Message]], np.ndarray]:
    """The steps (messages of one time each) and the true path (steps + 1, 4: t, x, y, θ),
    from the origin facing +x."""
    rng = np.random.default_rng(seed)
    x = np.zeros(3)
    out: list[list[Message]] = []
    truth = [(0.0, *x)]
    for k in range(steps):
        t = k * dt
        odo = VelocityOdometry(
            t, v + noise.v * rng.standard_normal(), omega + noise.omega * rng.standard_normal()
        )
        msgs: list[Message] = [odo]
        for lid, (lx, ly) in landmarks.items():
            dx, dy = lx - x[0], ly - x[1]
            r = math.hypot(dx, dy)
            if r <= max_range_m:
                b = math.remainder(math.atan2(dy, dx) - x[2], 2 * math.pi)
                r_meas = r + noise.range_m * rng.standard_normal()
                b_meas = b + noise.bearing_rad * rng.standard_normal()
                msgs.append(RangeBearing(t, lid, r_meas, b_meas))
        out.append(msgs)
        x = x + dt * np.array([v * math.cos(x[2]), v * math.sin(x[2]), omega])
        truth.append((t + dt, *x))
    return out, np.array(truth)


def batched(steps: list[list[Message]]) -> list[list[Message]]:
    """Each step's RangeBearing messages as one RangeBearings message (after the others)."""
    out = []
    for msgs in steps:
        rbs = [m for m in msgs if isinstance(m, RangeBearing)]
        rest = [m for m in msgs if not isinstance(m, RangeBearing)]
        if rbs:
            ids = [m.landmark_id for m in rbs]
            ranges, bearings = [m.range_m for m in rbs], [m.bearing_rad for m in rbs]
            rest.append(RangeBearings.of(rbs[0].t, ids, ranges, bearings))
        out.append(rest)
    return out
