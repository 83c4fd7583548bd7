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
refits them and checks them on Dataset 7)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hardware.datasets.base import Dataset, DatasetError, interpolate_poses
from hardware.geometry import between, wrap_angle
from hardware.messages import GroundTruthPose, RangeBearing


@dataclass(frozen=True)
class RangeFit:
    """z = scale·r·cos(b) + offset_m; rows used, and the residual's rms over them [m]."""

    scale: float
    offset_m: float
    rows: int
    rms_m: float


def sighting_geometry(ds: Dataset) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(recorded range, recorded bearing, true forward, true lateral offset [m]) of each
    landmark sighting within the ground truth's span: the landmark's surveyed position
    in the frame of the true pose, interpolated at the sighting (linear in x, y and the
    unwrapped heading)."""
    gt = list(ds.messages([GroundTruthPose]))
    if len(gt) < 2:
        raise DatasetError(f"{ds.name}: no ground truth to fit the range calibration against")
    t = np.array([m.t for m in gt])
    rb = [m for m in ds.messages([RangeBearing]) if t[0] <= m.t <= t[-1]]
    at = np.array([m.t for m in rb])
    pose = interpolate_poses(t, np.array([(m.x, m.y, m.theta) for m in gt]), at)
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
