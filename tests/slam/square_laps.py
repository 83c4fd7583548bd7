"""Synthetic UMBmark runs: laps of a square with rounded corners, driven exactly, as the
encoder counts wheels of a known geometry would give (shared by the calibration tests)."""

import math

import numpy as np

from hardware.calibration import WalkerCalibration
from hardware.log import LogWriter
from hardware.messages import EncoderTicks, GroundTruthPose
from slam.wheel_odometry import WheelGeometry

CPR = 256
# the thesis walker's software (203 mm wheels, contact track) ...
ASSUMED = WheelGeometry(0.203, 0.203, 0.64)
# ... and a true walker with the dimension table's track and a 1 % larger right wheel
TRUE = WheelGeometry(2 * 0.204 / 2.01, 2 * 0.204 * 1.01 / 2.01, 0.68)


def square_steps(
    side: float, laps: int, direction: int, radius: float = 0.5, step: float = 0.01
) -> tuple[np.ndarray, np.ndarray]:
    """(ds, dθ) steps of `laps` laps of a square, starting and ending mid-side, corners
    turned on arcs of `radius` (direction +1: counter-clockwise)."""
    straight = side - 2.0 * radius
    arc = 0.5 * math.pi * radius

    def piece(length: float, turn: float) -> tuple[np.ndarray, np.ndarray]:
        n = max(1, round(length / step))
        return np.full(n, length / n), np.full(n, turn / n)

    pieces = [piece(0.5 * straight, 0.0)]
    for k in range(4 * laps):
        pieces.append(piece(arc, direction * 0.5 * math.pi))
        pieces.append(piece(straight if k < 4 * laps - 1 else 0.5 * straight, 0.0))
    return np.concatenate([p[0] for p in pieces]), np.concatenate([p[1] for p in pieces])


def true_poses(ds: np.ndarray, dtheta: np.ndarray) -> np.ndarray:
    """(N + 1, 3) poses along the steps from the origin (exact arcs)."""
    theta = np.concatenate([[0.0], np.cumsum(dtheta)])
    half = 0.5 * dtheta
    chord = ds * np.where(np.abs(half) > 1e-12, np.sin(half) / np.where(half == 0, 1, half), 1.0)
    heading = theta[:-1] + half
    x = np.concatenate([[0.0], np.cumsum(chord * np.cos(heading))])
    y = np.concatenate([[0.0], np.cumsum(chord * np.sin(heading))])
    return np.column_stack([x, y, theta])


def counts(
    ds: np.ndarray, dtheta: np.ndarray, truth: WheelGeometry = TRUE, whole: bool = False
) -> np.ndarray:
    """(N + 1, 2) cumulative counts of the two wheels of `truth` driven by the steps
    (fractional unless `whole`: then floored as a quadrature counter reports them)."""
    rolled = np.column_stack([ds - 0.5 * truth.track_m * dtheta, ds + 0.5 * truth.track_m * dtheta])
    per_count = np.pi * np.array([truth.left_diameter_m, truth.right_diameter_m]) / CPR
    c = np.vstack([[0.0, 0.0], np.cumsum(rolled, axis=0) / per_count])
    return np.floor(c) if whole else c


def write_log(path, directions, side=4.0, laps=3, groundtruth=True, rate_m=0.01) -> None:
    """A trial log of one run per direction in `directions` (one after the other, the
    walker lifted round between them), pushed at 0.5 m/s: whole counts at every step,
    the true poses too when `groundtruth`."""
    cal = WalkerCalibration(wheel_diameter_m=ASSUMED.mean_diameter_m, track_m=ASSUMED.track_m)
    t0, base = 0.0, np.zeros(2)
    with LogWriter(path, cal) as log:
        for direction in directions:
            ds, dth = square_steps(side, laps, direction, step=rate_m)
            c = counts(ds, dth, whole=True) + base
            poses = true_poses(ds, dth)
            t = t0 + np.arange(len(c)) * rate_m / 0.5
            for k in range(len(c)):
                log.write(EncoderTicks(float(t[k]), int(c[k, 0]), int(c[k, 1])))
                if groundtruth:
                    log.write(GroundTruthPose(float(t[k]), *map(float, poses[k])))
            t0, base = t[-1] + 1.0, c[-1]
