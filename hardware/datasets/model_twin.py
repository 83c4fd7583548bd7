"""A dataset's model twin: its schedule, with data that follow the localizers' models.

A localizer's error on a real dataset mixes two things: what its method loses, and what
the data break of the model it assumes (biased ranges, odometry whose error is a scale
or a lag rather than white noise, time-correlated measurement errors). The twin keeps
everything of a dataset except its sensor values — the odometry's times, every
sighting's time and landmark ID, the ground-truth trajectory and the surveyed landmarks —
and regenerates the values from the ground truth with the noise the localizers are told
(`TwinNoise`, the dataset's proposed localizer settings):

- odometry row i holds from t_i to t_{i+1} (as a `VelocityOdometry` does): the true arc
  between the ground truth at those times (distance ds along an arc turning by dθ,
  from the relative pose: ds = ±|Δp| / sinc(dθ/2)), as velocities ds/dt, dθ/dt, plus
  white noise of the model's size: σ(ds) = velocity_frac·|v|·√dt,
  σ(dθ) = (omega_frac·|ω| + omega_floor)·√dt (slam.motion.MotionNoise, "time" model);
- a sighting: the true range and bearing from the ground-truth pose at its time to its
  landmark's surveyed position, plus N(0, range_sigma_m + range_sigma_frac·r) and
  N(0, bearing_sigma_rad) (bearing wrapped). A sighting recorded with a wrong ID is
  regenerated as a right one of that ID.

Only what lies within the ground truth's time span can be regenerated; odometry rows and
sightings outside it are left out and counted. The two noise streams are drawn from one
seed's independent children, so the sightings' noise does not depend on the number of
odometry rows. What a localizer reaches on the twin is what the dataset's schedule and
geometry allow when the model is right (MRCLAM: `--dataset-option twin=SEED`;
BENCHMARKS.md compares the two).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from hardware.datasets.base import interpolate_poses
from hardware.geometry import between, wrap_angle


@dataclass(frozen=True)
class TwinNoise:
    """The twin's noise, in the localizers' terms (module docstring)."""

    velocity_frac: float  # [1/√s]
    omega_frac: float  # [1/√s]
    omega_floor: float  # [rad/√s]
    range_sigma_m: float
    range_sigma_frac: float
    bearing_sigma_rad: float

    @classmethod
    def from_settings(cls, settings: Mapping[str, float]) -> TwinNoise:
        """From a dataset's proposed localizer settings ({field path: value})."""
        return cls(
            velocity_frac=settings["noise.velocity_frac"],
            omega_frac=settings["noise.omega_frac"],
            omega_floor=settings["noise.omega_floor"],
            range_sigma_m=settings["range_sigma_m"],
            range_sigma_frac=settings["range_sigma_frac"],
            bearing_sigma_rad=settings["bearing_sigma_rad"],
        )


def true_velocities(
    t: np.ndarray, truth_t: np.ndarray, truth_poses: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(v, ω) of each row of times `t` (sorted, within the truth's span): the arc from
    the truth at t_i to the truth at t_{i+1} over t_{i+1} − t_i; 0 for the last row and
    for rows of zero duration (which move nothing)."""
    poses = interpolate_poses(truth_t, truth_poses, t)
    rel = between(poses[:-1], poses[1:])
    dth = poses[1:, 2] - poses[:-1, 2]  # unwrapped: a turn of any size
    sign = np.where(rel[:, 0] < 0, -1.0, 1.0)
    ds = sign * np.hypot(rel[:, 0], rel[:, 1]) / np.sinc(0.5 * dth / np.pi)  # sin(u)/u
    dt = np.diff(t)
    moving = dt > 0
    v, w = np.zeros(len(t)), np.zeros(len(t))
    v[:-1][moving] = ds[moving] / dt[moving]
    w[:-1][moving] = dth[moving] / dt[moving]
    return v, w


def twin_odometry(
    t: np.ndarray,
    truth: tuple[np.ndarray, np.ndarray],
    noise: TwinNoise,
    rng: np.random.Generator,
) -> np.ndarray:
    """(t, v, ω) rows at the times `t` within the truth's span (module docstring)."""
    truth_t, truth_poses = truth
    t = t[(t >= truth_t[0]) & (t <= truth_t[-1])]
    v, w = true_velocities(t, truth_t, truth_poses)
    dt = np.append(np.diff(t), 0.0)
    moving = dt > 0
    root = np.sqrt(np.where(moving, dt, 1.0))
    sv = noise.velocity_frac * np.abs(v) / root
    sw = (noise.omega_frac * np.abs(w) + noise.omega_floor) / root
    e = rng.standard_normal((len(t), 2))
    v = v + np.where(moving, e[:, 0] * sv, 0.0)
    w = w + np.where(moving, e[:, 1] * sw, 0.0)
    return np.column_stack([t, v, w])


def twin_sightings(
    t: np.ndarray,
    landmarks_xy: np.ndarray,
    truth: tuple[np.ndarray, np.ndarray],
    noise: TwinNoise,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(kept, ranges, bearings): which sightings at times `t` of the landmarks at
    `landmarks_xy` (one row per sighting) lie within the truth's span, and the kept
    ones' noisy range and bearing (module docstring)."""
    truth_t, truth_poses = truth
    kept = (t >= truth_t[0]) & (t <= truth_t[-1])
    pose = interpolate_poses(truth_t, truth_poses, t[kept])
    d = landmarks_xy[kept] - pose[:, :2]
    r = np.hypot(d[:, 0], d[:, 1])
    b = np.arctan2(d[:, 1], d[:, 0]) - pose[:, 2]
    e = rng.standard_normal((len(r), 2))
    ranges = r + e[:, 0] * (noise.range_sigma_m + noise.range_sigma_frac * r)
    bearings = wrap_angle(b + e[:, 1] * noise.bearing_sigma_rad)
    return kept, ranges, bearings


def twin_generators(seed: int) -> tuple[np.random.Generator, np.random.Generator]:
    """The odometry's and the sightings' noise streams of one seed (independent)."""
    odometry, sightings = np.random.SeedSequence(seed).spawn(2)
    return np.random.default_rng(odometry), np.random.default_rng(sightings)
