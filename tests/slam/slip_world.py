"""A synthetic run whose wheels slip exactly as the localizers' slip model says: braked
turns (left brake in left turns, right in right ones) past point landmarks, encoder ticks
that lose k·level of each wheel's distance, range-bearing sightings between the ticks."""

from __future__ import annotations

import math

import numpy as np

from hardware.calibration import WalkerCalibration
from hardware.messages import BrakeCommand, EncoderTicks, Message, RangeBearing
from slam.motion import apply_increment

TICK_S = 0.02
# (seconds, speed m/s, turn rate rad/s, left level, right level)
SEGMENTS = [
    (2.0, 0.5, 0.0, 0.0, 0.0),
    (3.0, 0.5, 0.6, 0.8, 0.0),
    (2.0, 0.5, 0.0, 0.0, 0.0),
    (3.0, 0.5, -0.6, 0.0, 0.8),
]


def slip_run(
    k: tuple[float, float],
    rng: np.random.Generator,
    laps: int = 4,
    obs_offset_s: float = 0.01,
    bearing_sigma: float = 0.005,
    range_sigma: float = 0.02,
) -> tuple[list[Message], np.ndarray, np.ndarray]:
    """(messages in time order, true poses at the ticks (K, 4: t, x, y, θ), landmarks
    (L, 2)). Sightings at obs_offset_s after a tick, every 0.1 s, of the landmarks within
    3.5 m and ±0.5 rad, with Gaussian noise."""
    cal = WalkerCalibration()
    half, m = 0.5 * cal.track_m, cal.metres_per_count
    brake = cal.brake
    span = brake.torque_max_nm - brake.torque_off_nm
    pose, t = np.zeros(3), 0.0
    rolled = np.zeros(2)
    msgs: list[Message] = [EncoderTicks(0.0, 0, 0)]
    truth = [(0.0, *pose)]
    sightings = []  # (t, pose) of each sighting, landmarks added below
    for seconds, v, w, level_l, level_r in SEGMENTS * laps:
        msgs.append(
            BrakeCommand(
                t, brake.torque_off_nm + level_l * span, brake.torque_off_nm + level_r * span
            )
        )
        for _ in range(round(seconds / TICK_S)):
            if round(t / TICK_S) % 5 == 0:
                sightings.append(
                    (t + obs_offset_s, apply_increment(pose, v * obs_offset_s, w * obs_offset_s))
                )
            pose = apply_increment(pose, v * TICK_S, w * TICK_S)
            t += TICK_S
            ground = np.array([v - w * half, v + w * half]) * TICK_S
            rolled += ground * (1.0 - np.array(k) * (level_l, level_r))
            msgs.append(EncoderTicks(t, math.floor(rolled[0] / m), math.floor(rolled[1] / m)))
            truth.append((t, *pose))
    truth_arr = np.array(truth)
    lo, hi = truth_arr[:, 1:3].min(0) - 2.0, truth_arr[:, 1:3].max(0) + 2.0
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0], 1.5), np.arange(lo[1], hi[1], 1.5))
    landmarks = np.stack([gx.ravel(), gy.ravel()], axis=1)
    for ts, p in sightings:
        d = landmarks - p[:2]
        r = np.hypot(d[:, 0], d[:, 1])
        b = np.arctan2(d[:, 1], d[:, 0]) - p[2]
        b = (b + np.pi) % (2 * np.pi) - np.pi
        for i in np.flatnonzero((r < 3.5) & (np.abs(b) < 0.5)):
            z_r = r[i] + range_sigma * rng.standard_normal()
            z_b = b[i] + bearing_sigma * rng.standard_normal()
            msgs.append(RangeBearing(ts, int(i), float(z_r), float(z_b)))
    msgs.sort(key=lambda msg: msg.t)  # stable: a tick before a command of its time
    return msgs, truth_arr, landmarks
