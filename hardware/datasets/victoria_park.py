"""ACFR Victoria Park (Guivant & Nebot 2001): a utility car among trees, with GPS.

`open_dataset("victoria-park", FOLDER)` reads the text copies of the dataset (plain or
gzipped CSV, one `#` header line, comma separated):

    aa3_dr.csv          time_ms, speed_mps, steering_rad     (~40 Hz, 61945 rows)
    tree_detections.csv scan_index, time_s, range_m, bearing_rad, diameter_m
                        (trees extracted from the laser scans by the dataset's
                        detectTreesI16.m; bearing is the laser angle in [0, π], 0 = right)
    aa3_gpsx.csv        timeGps_ms, Lo_m, La_m                (GPS in metres: x, y)

Vehicle model (info_original.txt, car.bmp; Guivant & Nebot, IEEE T-RA 17(3), 2001):
wheelbase L = 2.83 m; the speed encoder is on the rear-left wheel, H = 0.76 m left of the
centreline; the laser is a = 0.95 m ahead of the front axle (L + a = 3.78 m ahead of the
rear axle) and b = 0.5 m to the left. The reference point is the rear-axle centre (which
has no lateral velocity, like the walker's):

    v = v_enc / (1 − tan(α)·H/L)      (the encoder wheel is the inner one in a left turn)
    ω = v·tan(α)/L                    (bicycle model, α the steering angle, CCW positive)

- Odometry rows → `VelocityOdometry(t = time_ms/1000, v, ω)`, held until the next row.
- Tree detections → `RangeBearing(t, landmark_id=-1, range, bearing)`: −1 means the
  association is unknown (this is the unknown-association benchmark). With
  measurements_from="rear-axle" (default) each detection is re-expressed from the
  rear-axle centre, the pose the localizers estimate: point p = (L + a, b) +
  r·(cos β, sin β) with β = bearing − π/2 (the laser's x axis is the vehicle's heading),
  range = |p|, bearing = atan2(p_y, p_x). measurements_from="laser" keeps the laser's
  own range and β (then a localizer must model the 3.78 m / 0.5 m offset). The data
  confirm the offset: with dead reckoning over the first 120 s, detections of the same
  tree in scans < 3 s apart lie 2.9 cm apart (median) with (3.78, +0.5) m, against
  3.6 cm with (3.78, −0.5), 4.7 cm with (0.95, 0.5) and 5.4 cm with no offset. The tree
  diameters have no message field: they are in `Dataset.arrays["tree_diameter_m"]`,
  aligned with the RangeBearing messages in time order (ties in file order).
- GPS has no heading, so it is not a GroundTruthPose: metadata "gps" {"columns":
  ["t", "x", "y"], "rows": [[t, x, y], ...]} (t in s). It is partial ground truth: the
  unit had dropouts and jumps, and its antenna position on the car is not documented.
- Times are the dataset's seconds (21.8–1570.5 s), not offset.
- initial_pose: the first GPS fix with the commonly used heading 35.5° (the start pose
  of the usual Victoria Park EKF demonstrations; option initial_heading_deg). It is not
  ground truth, and the antenna need not be at the rear axle (its position is unknown).

Calibration: the walker defaults with track_m = 2H = 1.52 m (the rear track).

Proposed localizer settings (metadata "localizer_settings", applied by replay and compare
before any --set, with measurements_from="rear-axle"): a tree detection's noise, range σ
0.3 m and bearing σ 0.03 rad (TREE_NOISE, below), and gtsam's keyframes and updates
for a car (GTSAM_SETTINGS).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hardware.calibration import WalkerCalibration
from hardware.choices import Choice, coerce
from hardware.datasets.base import (
    Dataset,
    DatasetError,
    as_float,
    coerce_option,
    config_metadata,
    range_bearing_stream,
    require_folder,
    sorted_by_time,
    span_and_counts,
    tie_ordered_streams,
    velocity_stream,
)
from hardware.datasets.textio import FolderFiles, read_table
from hardware.geometry import wrap1
from hardware.messages import RangeBearing, VelocityOdometry
from hardware.registry import Spec

WHEELBASE_M = 2.83  # L
ENCODER_OFFSET_M = 0.76  # H: rear-left encoder wheel, left of the centreline
LASER_AHEAD_OF_FRONT_AXLE_M = 0.95  # a
LASER_LEFT_M = 0.5  # b
LASER_X_M = WHEELBASE_M + LASER_AHEAD_OF_FRONT_AXLE_M  # 3.78 m ahead of the rear axle
INITIAL_HEADING_DEG = 35.5


class MeasurementOrigin(Choice):
    """Where detections are measured from (module docstring): the rear axle or the laser."""

    REAR_AXLE = "rear-axle"
    LASER = "laser"


@dataclass(frozen=True)
class VictoriaParkOptions:
    """measurements_from: "rear-axle" (default) or "laser"; initial_heading_deg: the
    heading of initial_pose (the first GPS fix)."""

    measurements_from: MeasurementOrigin = MeasurementOrigin.REAR_AXLE
    initial_heading_deg: float = INITIAL_HEADING_DEG

    def __post_init__(self) -> None:
        coerce(self, measurements_from=MeasurementOrigin)
        coerce_option(self, "initial_heading_deg", as_float)


def rear_axle_velocity(speed: np.ndarray, steering: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(v, ω) of the rear-axle centre from the rear-left wheel speed and the steering."""
    tan = np.tan(steering)
    v = speed / (1.0 - tan * ENCODER_OFFSET_M / WHEELBASE_M)
    return v, v * tan / WHEELBASE_M


def laser_to_rear_axle(rng: np.ndarray, bearing_laser: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Range and bearing from the rear-axle centre of a detection at the laser's range
    and laser angle (0 = right, π/2 = ahead)."""
    beta = bearing_laser - 0.5 * math.pi
    px = LASER_X_M + rng * np.cos(beta)
    py = LASER_LEFT_M + rng * np.sin(beta)
    return np.hypot(px, py), np.arctan2(py, px)


FILES = ("aa3_dr.csv", "tree_detections.csv", "aa3_gpsx.csv")


def _read(files: FolderFiles, notes: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The odometry, tree and GPS tables, each stably sorted by time (all three files are
    found before any is read)."""
    dr, trees, gps = [files.find(name) for name in FILES]
    return (
        sorted_by_time(read_table(dr, 3, delimiter=",").data, "aa3_dr", notes),
        sorted_by_time(read_table(trees, 5, delimiter=",").data, "trees", notes, col=1),
        sorted_by_time(read_table(gps, 3, delimiter=",").data, "gps", notes),
    )


def _odometry(dr: np.ndarray, path: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, v, ω) of the rear-axle centre from the odometry rows; a DatasetError at a
    steering angle of ±90°, where the model has no speed."""
    steer = dr[:, 2]
    bad = np.nonzero(np.abs(steer) >= 0.5 * math.pi - 1e-6)[0]
    if len(bad):
        raise DatasetError(f"{path}: data row {bad[0] + 1}: steering angle {steer[bad[0]]} rad")
    v, w = rear_axle_velocity(dr[:, 1], steer)
    return dr[:, 0] / 1000.0, v, w


def _detections(trees: np.ndarray, origin: str) -> tuple[np.ndarray, np.ndarray]:
    """Range and bearing (CCW from the heading) of each tree from `origin` (module
    docstring: "rear-axle" or "laser")."""
    if origin == "rear-axle":
        return laser_to_rear_axle(trees[:, 2], trees[:, 3])
    return trees[:, 2].copy(), trees[:, 3] - 0.5 * math.pi


def _vehicle_metadata() -> dict[str, Any]:
    """Metadata "dataset" "vehicle": the car's geometry and odometry model."""
    return {
        "wheelbase_L_m": WHEELBASE_M,
        "encoder_offset_H_m": ENCODER_OFFSET_M,
        "laser_a_m": LASER_AHEAD_OF_FRONT_AXLE_M,
        "laser_b_m": LASER_LEFT_M,
        "laser_on_vehicle_xy_m": [LASER_X_M, LASER_LEFT_M],
        "reference_point": "rear-axle centre",
        "odometry_model": "v = v_enc / (1 - tan(steer) H / L); omega = v tan(steer) / L",
    }


# Proposed to the localizers (metadata "localizer_settings"): the noise of a tree
# detection. The same tree in consecutive scans (0.2 s apart, dead reckoning between
# them) is consistent to σ 0.02-0.05 m in range (growing with range) and 0.0025 rad in
# bearing; used as independent noise that makes EKF-SLAM overconfident (1202 landmarks
# for a few hundred trees, 18 m RMSE against the GPS), because a trunk's detected centre
# moves with the viewing angle, an error shared by the scans of a pass. 0.3 m and
# 0.03 rad: FastSLAM, whose per-particle maps carry no pose correlation, needs it to
# recognise a trunk again (with 0.1 m, 0.01 rad: 15-30 m RMSE and twice the trees);
# EKF-SLAM (4.29 m) and gtsam (4.16 m) are as good as or better than with 0.1 m, 0.01 rad
# (BENCHMARKS.md, issue 14).
TREE_NOISE = {"range_sigma_m": 0.3, "range_sigma_frac": 0.0, "bearing_sigma_rad": 0.03}
# And for gtsam: a keyframe per 2 m or 1 s of sightings (the car drives 3 m/s and sees
# trees in every 0.2 s scan; the walker's 0.25 m made 9 keyframes a second), one iSAM2
# update per keyframe rather than per scan, and Cholesky (QR is there for long
# odometry-only chains; a graph tied by landmarks factors well): the same RMSE over the
# first 600 s (4.23 m) at 79× real time instead of 13× (BENCHMARKS.md, issue 14).
GTSAM_SETTINGS = {
    "keyframe_distance_m": 2.0,
    "obs_keyframe_dt_s": 1.0,
    "update_per_sighting": False,
    "factorization": "CHOLESKY",
}


def _metadata(
    options: VictoriaParkOptions,
    folder: Path,
    t_dr: np.ndarray,
    trees: np.ndarray,
    gps_rows: np.ndarray,
    files: FolderFiles,
    notes: list[str],
) -> dict[str, dict[str, Any]]:
    """All the metadata (module docstring); initial_pose is the first GPS fix."""
    initial = (
        float(gps_rows[0, 1]),
        float(gps_rows[0, 2]),
        wrap1(math.radians(options.initial_heading_deg)),
    )
    counts = {"VelocityOdometry": len(t_dr), "RangeBearing": len(trees)}
    return {
        "config": config_metadata(
            "victoria-park",
            folder,
            options,
            initial,
            initial_pose_source=(
                "first GPS fix and the commonly used initial heading; not ground truth"
            ),
        ),
        "dataset": {
            "name": "victoria_park",
            "description": (
                "ACFR Victoria Park (Guivant & Nebot, IEEE T-RA 17(3), 2001): utility car, "
                "wheel speed + steering, laser tree detections, GPS"
            ),
            "time_base": "seconds of the dataset's clock (aa3_dr time / 1000), not offset",
            **span_and_counts(counts, t_dr, trees[:, 1]),
            "laser_scans_with_trees": len(np.unique(trees[:, 0])),
            "vehicle": _vehicle_metadata(),
            "measurements_from": options.measurements_from,
            "landmark_id": "-1 on every RangeBearing: association unknown",
            "tree_diameters": "in Dataset.arrays['tree_diameter_m'] only (not in the log)",
            "files": files.found,
            "notes": notes,
        },
        "gps": {
            "columns": ["t", "x", "y"],
            "rows": gps_rows.tolist(),
            "note": (
                "partial ground truth: no heading (so no GroundTruthPose), dropouts and "
                "jumps; antenna position on the car not documented; x = Lo_m, y = La_m"
            ),
        },
        "groundtruth": {"kind": "none", "note": "only GPS positions, see metadata 'gps'"},
        "localizer_settings": (
            {**TREE_NOISE, **GTSAM_SETTINGS} if options.measurements_from == "rear-axle" else {}
        ),
    }


def open_victoria_park(options: VictoriaParkOptions, path: Path) -> Dataset:
    """The Victoria Park folder (module docstring): read the three tables, convert the
    odometry and the detections to the rear-axle centre, build the streams and metadata."""
    folder = require_folder(path, "victoria-park")
    notes: list[str] = []
    files = FolderFiles(folder)
    dr, trees, gps = _read(files, notes)
    t_dr, v, w = _odometry(dr, files.found["aa3_dr.csv"])
    rng, brg = _detections(trees, options.measurements_from)
    gps_rows = np.column_stack([gps[:, 0] / 1000.0, gps[:, 1], gps[:, 2]])
    unknown = np.full(len(trees), -1, dtype=np.int64)
    streams = tie_ordered_streams(
        (VelocityOdometry, velocity_stream(t_dr, v, w)),
        (RangeBearing, range_bearing_stream(trees[:, 1], unknown, rng, brg)),
    )
    metadata = _metadata(options, folder, t_dr, trees, gps_rows, files, notes)
    arrays = {
        "tree_diameter_m": trees[:, 4].copy(),
        "tree_scan_index": trees[:, 0].astype(np.int64),
        "gps": gps_rows,
    }
    calibration = WalkerCalibration(track_m=2.0 * ENCODER_OFFSET_M)
    return Dataset("victoria_park", calibration, metadata, streams, arrays)


SPEC = Spec(
    "victoria-park",
    VictoriaParkOptions,
    open_victoria_park,
    "ACFR Victoria Park folder: car odometry (speed + steering), tree detections, GPS",
)
