"""Wheel geometry of a differential drive and what it does to dead reckoning.

`WheelGeometry` is what odometry from wheel encoders needs: the two wheel diameters and
the track. `dead_reckon` integrates cumulative encoder counts with a geometry, exactly
as the `dead-reckoning` localizer does (the exact arc of `slam.motion`), vectorised, so
that a calibration can re-run a whole log's odometry for every candidate geometry.
`fit_to_groundtruth` finds the geometry that explains a path whose true poses are known
(a simulated run, a motion-capture run) by linear least squares:

  heading:  θ(t) − θ(0) = (c_R·R(t) − c_L·L(t)) / b      (exact without slip)
  distance: s(t) = (c_L·L(t) + c_R·R(t)) / 2

where L(t), R(t) are the distances the wheels rolled by the counts and the geometry
the counts were converted with, c = (true diameter) / (that diameter), b the true track
and s the true path length (each step of the true poses taken as an arc, as odometry
does). The first is linear in (c_R/b, c_L/b); given those, the
second is linear in b.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from hardware.calibration import WalkerCalibration
from slam.motion import sinc_and_derivative


@dataclass(frozen=True)
class WheelGeometry:
    """Left and right wheel diameters and the track (rear-wheel contact distance) [m]."""

    left_diameter_m: float
    right_diameter_m: float
    track_m: float

    def __post_init__(self) -> None:
        for name in ("left_diameter_m", "right_diameter_m", "track_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be > 0, got {v}")

    @classmethod
    def of(cls, calibration: WalkerCalibration) -> WheelGeometry:
        """The geometry a walker calibration's odometry uses."""
        left, right = calibration.wheel_diameters_m
        return cls(left, right, calibration.track_m)

    @property
    def mean_diameter_m(self) -> float:
        return 0.5 * (self.left_diameter_m + self.right_diameter_m)

    @property
    def diameter_ratio(self) -> float:
        """Right wheel diameter / left (UMBmark's E_d)."""
        return self.right_diameter_m / self.left_diameter_m

    def applied_to(self, calibration: WalkerCalibration) -> WalkerCalibration:
        """`calibration` with this geometry (its mean diameter, ratio and track)."""
        return replace(
            calibration,
            wheel_diameter_m=self.mean_diameter_m,
            wheel_diameter_ratio=self.diameter_ratio,
            track_m=self.track_m,
        )

    def scaled(self, left: float, right: float, track: float) -> WheelGeometry:
        """Each diameter and the track multiplied by a factor."""
        return WheelGeometry(
            float(self.left_diameter_m * left),
            float(self.right_diameter_m * right),
            float(self.track_m * track),
        )


def wheel_distances(counts: np.ndarray, geometry: WheelGeometry, counts_per_rev: int) -> np.ndarray:
    """(N, 2) distances rolled by the left and right wheels since the first sample, from
    (N, 2) cumulative encoder counts."""
    counts = np.asarray(counts, dtype=float)
    per_count = np.pi * np.array([geometry.left_diameter_m, geometry.right_diameter_m])
    return (counts - counts[0]) * (per_count / counts_per_rev)


def dead_reckon(
    counts: np.ndarray,
    geometry: WheelGeometry,
    counts_per_rev: int,
    start: Sequence[float] = (0.0, 0.0, 0.0),
) -> np.ndarray:
    """(N, 3) poses (x, y, θ; θ unwrapped) integrated from (N, 2) cumulative counts along
    exact arcs between samples, from `start` at the first sample."""
    wheels = np.diff(wheel_distances(counts, geometry, counts_per_rev), axis=0)
    ds = 0.5 * (wheels[:, 0] + wheels[:, 1])
    dtheta = (wheels[:, 1] - wheels[:, 0]) / geometry.track_m
    theta = start[2] + np.concatenate([[0.0], np.cumsum(dtheta)])
    sinc, _ = sinc_and_derivative(0.5 * dtheta)
    heading = theta[:-1] + 0.5 * dtheta
    chord = ds * sinc
    x = start[0] + np.concatenate([[0.0], np.cumsum(chord * np.cos(heading))])
    y = start[1] + np.concatenate([[0.0], np.cumsum(chord * np.sin(heading))])
    return np.column_stack([x, y, theta])


@dataclass(frozen=True)
class GroundTruthRun:
    """One run for `fit_to_groundtruth`: cumulative counts and the true poses at the same
    times (N, 3; θ unwrapped or not)."""

    counts: np.ndarray
    truth: np.ndarray


def fit_to_groundtruth(
    runs: Sequence[GroundTruthRun], assumed: WheelGeometry, counts_per_rev: int
) -> WheelGeometry:
    """The wheel geometry that best explains the true motion of `runs` (module docstring),
    relative to the `assumed` geometry the counts are converted with."""
    rolled, turned, walked = [], [], []
    for run in runs:
        wheels = wheel_distances(run.counts, assumed, counts_per_rev)
        truth = np.asarray(run.truth, dtype=float)
        theta = np.unwrap(truth[:, 2])
        # each step's arc from its chord and turn (as odometry integrates them)
        chords = np.hypot(np.diff(truth[:, 0]), np.diff(truth[:, 1]))
        steps = chords / sinc_and_derivative(0.5 * np.diff(theta))[0]
        rolled.append(wheels)
        turned.append(theta - theta[0])
        walked.append(np.concatenate([[0.0], np.cumsum(steps)]))
    wheels, dtheta, s = (np.concatenate(v) for v in (rolled, turned, walked))
    # θ = p·R − q·L with p = c_R / b, q = c_L / b
    a = np.column_stack([wheels[:, 1], -wheels[:, 0]])
    (p, q), *_ = np.linalg.lstsq(a, dtheta, rcond=None)
    # s = b·(q·L + p·R) / 2
    g = 0.5 * (q * wheels[:, 0] + p * wheels[:, 1])
    b = float(g @ s / (g @ g))
    return assumed.scaled(q * b, p * b, b / assumed.track_m)
