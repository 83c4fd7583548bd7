"""Fitting an MRCLAM robot's barcode-camera range against its ground truth.

The recorded range z is the landmark's forward distance along the camera axis, scaled
and offset per camera: z = k·r·cos(b) + c with r, b the true range and bearing
(`hardware.datasets.mrclam`). `fit_range` fits (k, c) of one robot by least squares on
a dataset opened with `calibration="none"`, the true r·cos(b) computed from the ground
truth pose interpolated at each measurement and the landmark's surveyed position. Rows
whose bearing is more than `max_bearing_error_rad` off the truth are a wrong barcode
reading and are left out; the fit is repeated once without the rows beyond
`clip_sigma` standard deviations of its residual (a barcode partly hidden).

This is how the per-robot values of `hardware.datasets.mrclam.DATASET1_RANGE` were
obtained, on Dataset 1's approximate ground truth (tests/hardware/datasets/test_mrclam.py
refits them and checks them on Dataset 7).

The odometry's distance noise (`velocity_noise`): the localizers model the commanded
speed's error as white, σ(ds) = velocity_frac·|v|·√dt, but the recorded error is
correlated in time (a speed that is off by a few per cent for a while): its rms over
disjoint windows of W s, divided by that model's σ over the same windows, grows with W
(Dataset 1, robots 1–4 pooled: velocity_frac 0.21 over 1 s, 0.31 over 5 s, 0.34 over
10 s, 0.37 over 20 s). A white model is right at one time scale only; the one that
matters is how long the odometry alone carries the pose between landmark sightings,
`time_weighted_gap`: the mean length of the gap between sighting times that an instant
falls in (Σg² / Σg; 5.8 s on Dataset 1's robots 1–4). The proposed velocity_frac is the
fit at that window."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hardware.datasets.base import Dataset, DatasetError, interpolate_poses
from hardware.datasets.model_twin import true_velocities
from hardware.geometry import between, wrap_angle
from hardware.messages import GroundTruthPose, RangeBearing, VelocityOdometry


@dataclass(frozen=True)
class RangeFit:
    """z = scale·r·cos(b) + offset_m; rows used, and the residual's rms over them [m]."""

    scale: float
    offset_m: float
    rows: int
    rms_m: float


def truth_table(ds: Dataset, what: str) -> tuple[np.ndarray, np.ndarray]:
    """ds's ground truth as (times, poses (N, 3)); a DatasetError naming `what` would be
    fitted when it has fewer than two poses."""
    gt = list(ds.messages([GroundTruthPose]))
    if len(gt) < 2:
        raise DatasetError(f"{ds.name}: no ground truth to fit {what} against")
    return np.array([m.t for m in gt]), np.array([(m.x, m.y, m.theta) for m in gt])


def sighting_geometry(ds: Dataset) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(recorded range, recorded bearing, true forward, true lateral offset [m]) of each
    landmark sighting within the ground truth's span: the landmark's surveyed position
    in the frame of the true pose, interpolated at the sighting (linear in x, y and the
    unwrapped heading)."""
    t, poses = truth_table(ds, "the range calibration")
    rb = [m for m in ds.messages([RangeBearing]) if t[0] <= m.t <= t[-1]]
    pose = interpolate_poses(t, poses, np.array([m.t for m in rb]))
    lm = np.array([ds.metadata["landmarks"][str(m.landmark_id)] for m in rb]).reshape(-1, 2)
    seen = between(pose, np.column_stack([lm, np.zeros(len(lm))]))
    forward, lateral = seen[:, 0], seen[:, 1]
    recorded = np.array([(m.range_m, m.bearing_rad) for m in rb]).reshape(-1, 2)
    return recorded[:, 0], recorded[:, 1], forward, lateral


def forward_distances(ds: Dataset, max_bearing_error_rad: float = 0.15):
    """(recorded range, true forward distance r·cos b) of the sightings within the
    ground truth's span whose bearing agrees with the truth to max_bearing_error_rad."""
    z, bearing, forward, lateral = sighting_geometry(ds)
    right = np.abs(wrap_angle(np.arctan2(lateral, forward) - bearing)) < max_bearing_error_rad
    return z[right], forward[right]


def fit_range(
    ds: Dataset, max_bearing_error_rad: float = 0.15, clip_sigma: float = 3.0
) -> RangeFit:
    """The range scale and offset of ds's robot (module docstring); ds opened with
    calibration="none"."""
    if ds.metadata.get("sensor_calibration", {}).get("name") != "none":
        raise DatasetError(f"{ds.name}: fit the range on the files' values (calibration=none)")
    z, forward = forward_distances(ds, max_bearing_error_rad)
    if len(z) < 10:
        raise DatasetError(f"{ds.name}: {len(z)} sightings within the ground truth, need 10")
    a = np.column_stack([forward, np.ones_like(forward)])
    coef = np.linalg.lstsq(a, z, rcond=None)[0]
    res = z - a @ coef
    keep = np.abs(res) < clip_sigma * res.std()
    coef = np.linalg.lstsq(a[keep], z[keep], rcond=None)[0]
    res = z[keep] - a[keep] @ coef
    return RangeFit(
        float(coef[0]), float(coef[1]), int(keep.sum()), float(np.sqrt(np.mean(res**2)))
    )


def time_weighted_gap(datasets: list[Dataset]) -> float:
    """Σg² / Σg over the gaps g between consecutive sighting times of all `datasets`
    [s]: the mean length of the gap that a random instant falls in (module docstring)."""
    gaps = [np.diff(np.unique([m.t for m in ds.messages([RangeBearing])])) for ds in datasets]
    g = np.concatenate(gaps)
    return float(np.sum(g**2) / np.sum(g))


def velocity_noise(datasets: list[Dataset], window_s: float, step_s: float = 0.05) -> float:
    """The velocity_frac [1/√s] of the white model σ(ds) = velocity_frac·|v|·√dt that
    gives the recorded distance error's mean square over disjoint windows of window_s,
    pooled over `datasets` (their odometry as opened, e.g. calibrated): on a lattice of
    step_s within the ground truth's span, the commanded speed (held from row to row)
    against the ground truth's (the arc between lattice points), summed per window."""
    n = max(round(window_s / step_s), 1)
    err2 = var = 0.0
    for ds in datasets:
        truth_t, poses = truth_table(ds, "the odometry noise")
        odo = np.array([(m.t, m.v) for m in ds.messages([VelocityOdometry])])
        lattice = np.arange(max(odo[0, 0], truth_t[0]), min(odo[-1, 0], truth_t[-1]), step_s)
        true_v, _ = true_velocities(lattice, truth_t, poses)
        v = odo[np.searchsorted(odo[:, 0], lattice, side="right") - 1, 1]
        m = (len(lattice) - 1) // n * n  # whole windows (the last lattice point has no arc)
        err2 += float(np.sum(((v - true_v)[:m] * step_s).reshape(-1, n).sum(axis=1) ** 2))
        var += float(np.sum(v[:m] ** 2) * step_s)
    return math.sqrt(err2 / var)
