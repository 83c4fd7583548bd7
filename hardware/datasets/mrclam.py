"""UTIAS MRCLAM (Multi-Robot Cooperative Localization and Mapping, Leung et al., IJRR 2011).

`open_dataset("mrclam", FOLDER, robot=N)` reads one robot of a dataset folder
(`MRCLAM_Dataset1` … `9`: five iRobot Create robots, fifteen barcoded landmarks, Vicon
ground truth). Files are whitespace/TAB separated text with `#` header lines, plain or
gzipped (`X.dat` or `X.dat.gz`):

    Barcodes.dat               subject barcode      (subjects 1–5 robots, 6–20 landmarks)
    Landmark_Groundtruth.dat   subject x y x_std y_std   [m]
    RobotN_Odometry.dat        t v ω                 [s Unix, m/s, rad/s]
    RobotN_Measurement.dat     t barcode range bearing   [s, -, m, rad CCW from heading]
    RobotN_Groundtruth.dat     t x y θ               [s, m, m, rad] (Vicon, ~100 Hz, gaps)

Conversion
----------
- Odometry rows → `VelocityOdometry(t, v, ω)`: the velocities hold from t to the next
  row (what the dead-reckoning localizer integrates). Rows with equal timestamps are kept
  (a localizer integrates nothing over a zero interval; the later row then holds).
- Measurement rows: the barcode is mapped to a subject through Barcodes.dat. Subjects
  6–20 (the landmarks) → `RangeBearing(t, landmark_id=subject, range, bearing)`;
  subjects 1–5 are the other robots, skipped and counted (metadata "skipped"
  "other_robots"); barcodes not in Barcodes.dat are spurious, skipped and counted
  ("unknown_barcodes", their values in "unknown_barcode_values").
- Ground truth rows → `GroundTruthPose` (θ wrapped to (−π, π]).
- Landmark_Groundtruth.dat → metadata "landmarks" {"6": [x, y], …} and
  "landmark_std" {"6": [x_std, y_std], …}.
- Times stay absolute Unix seconds, as in the files (float64: ~0.2 µs resolution at
  1.25e9 s, finer than the files' 1 ms); only the odometry's are shifted by the
  calibration's delay (below). All five robots and the ground truth share this clock,
  so several robots' logs line up.
- initial_pose (metadata "config") is the ground truth interpolated at the first
  odometry time (the pose a localizer starts from; "initial_pose_t" records that
  time), or (0, 0, 0) without ground truth.

Ground truth (option `groundtruth`, metadata "groundtruth" {"kind", "source", "note"}):

    "auto"         exact Vicon file if present, else the approximate one, else none
    "exact"        RobotN_Groundtruth.dat (a DatasetError if it is missing)
    "approximate"  groundtruth_approx/RobotN_Groundtruth_intsec.csv(.gz): Dataset 1's
                   Vicon rows re-saved through a spreadsheet with timestamps truncated to
                   whole seconds (`t_int,x,y,θ`, one header line). The rows of one second
                   are spread evenly over it (t = s + (k + ½)/n, k = 0…n−1), so timing
                   errors are up to ±0.5 s (~0.1 m at the robots' 0.1–0.3 m/s)
    "none"         no ground truth

Calibration: the walker defaults, with the iRobot Create's (Roomba base) wheel track
0.258 m and ~0.34 m round body (Hacking Roomba, Fig. 5-5) as track and footprint. The
dataset's odometry is velocities, so no encoder calibration applies.

Sensor calibration (option `calibration`, metadata "sensor_calibration")
-------------------------------------------------------------------------
Compared with the Vicon ground truth, the files' values have systematic errors that are
the same on every robot and in both datasets checked (1 and 7):

- The "range" column is the landmark's *forward* distance along the camera axis (what a
  barcode's apparent height gives), not its Euclidean range: against the truth the
  recorded range is k·r·cos(bearing) + c, with the b² term of r·(1 − b²/2) fitted at
  −0.454·r·b² on both datasets (−0.5 for a pure cos), so at the edge of the view
  (|b| ≈ 0.45 rad) the recorded range is ~10 % short. The conversion
  r = (z − c) / (k·cos b) removes it (dataset 7: range error rms 0.15 → 0.06 m).
- The odometry (commanded velocities) leads the motion: the heading and distance
  increments match the Vicon's best ~0.22 s later (the camera's measurements are on the
  Vicon's clock to within 0.03 s), and the robots drive 8 % less far and turn 5 % less
  than commanded.
- Each robot's camera has its own range scale k: 1.013, 1.052, 1.013, 1.020 for robots
  1–4 on Dataset 1 and within 0.004 of these on Dataset 7 (`mrclam_fit.fit_range`). With
  one k for all, robot 2's ranges are ~5 cm long and robots 1 and 3's ~4 cm short, and
  each robot's map comes out scaled by its own error (robot 2's by 2.4 %).

`calibration="dataset1"` (default) applies the values fitted on Dataset 1's (approximate)
ground truth, robots 1–4 — so on Dataset 7 they are a held-out calibration (fitted
on Dataset 7 itself they come out within 0.01 of these: k 1.024, c 0.041 m, delay
0.20–0.23 s, speed 0.906, turn 0.955): odometry times + 0.22 s, v × 0.917, ω × 0.945,
and range r = (z − c) / (k·cos b) with each robot's own k and c (`DATASET1_RANGE`;
robot 5, without ground truth in Dataset 1, the pooled k 1.0218, c 0.050 m).
`calibration="dataset1-pooled"`: the pooled k and c for every robot.
`calibration="none"`: the files' values as they are.

With the calibration the metadata "localizer_settings" also gives the noise levels
fitted on Dataset 1 ({field path: value}, applied by replay and compare to every
localizer config that has the field, before any --set): range σ 0.03 + 0.015·r m
(the calibrated range's rms error grows as ~0.015·r; the floor covers the robots'
own range biases of a few cm, which are constant in time and so not averaged away),
bearing σ 0.015 rad (rms 0.016–0.019), and velocity-odometry noise over 1 s of
σ(ds) = 0.3·|v|, σ(dθ) = 0.23·|ω| + 0.011 rad (slam.motion.MotionNoise). The speed's
error is correlated in time, so a white model fits one time scale only: 0.3 is its fit
over the time the odometry alone carries the pose between sightings (5.8 s on Dataset
1; over 1 s windows the fit is 0.21; `mrclam_fit.velocity_noise`); until 2026-12-03 it
was 0.13. Without the calibration there are none (the localizers' defaults were fitted
to the raw files).

Model twin (option `twin`, metadata "twin"): `twin=SEED` keeps the robot's schedule (the
odometry's times, each sighting's time and landmark ID), its ground truth and the
surveyed landmarks, and regenerates the odometry and the sightings from the ground truth
with white noise of exactly the proposed levels (`hardware.datasets.model_twin`), which
are then proposed with or without the calibration. A localizer's error on the twin is
what the schedule and geometry allow when its model is right; against the recorded
values it shows how much the data break the model. `twin_values=odometry` or
`sightings` regenerates only those (the others keep the recorded, calibrated values),
to tell which of the two breaks it. The name gets "_twinSEED" (and "_odometry" or
"_sightings").
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from hardware.calibration import WalkerCalibration
from hardware.choices import Choice, coerce
from hardware.datasets.base import (
    Dataset,
    DatasetError,
    as_float,
    as_int,
    coerce_option,
    config_metadata,
    interpolate_pose,
    range_bearing_stream,
    require_folder,
    sorted_by_time,
    span_and_counts,
    tie_ordered_streams,
    time_order,
    velocity_stream,
)
from hardware.datasets.model_twin import (
    TwinNoise,
    twin_generators,
    twin_odometry,
    twin_sightings,
)
from hardware.datasets.synthetic_slip import inject_slip
from hardware.datasets.textio import FolderFiles, find_optional, read_table
from hardware.messages import BrakeCommand, RangeBearing, VelocityOdometry
from hardware.registry import Spec

ROBOTS = (1, 2, 3, 4, 5)
LANDMARK_SUBJECTS = tuple(range(6, 21))


class TwinValues(Choice):
    """Which of the model twin's values are regenerated (module docstring)."""

    ALL = "all"
    ODOMETRY = "odometry"
    SIGHTINGS = "sightings"


class GroundTruthChoice(Choice):
    """Which ground truth to attach (module docstring): auto, the exact or the
    approximate files, or none."""

    AUTO = "auto"
    EXACT = "exact"
    APPROXIMATE = "approximate"
    NONE = "none"


APPROX_DIR = "groundtruth_approx"

CREATE_TRACK_M = 0.258
CREATE_DIAMETER_M = 0.34


class CalibrationChoice(Choice):
    """The sensors' calibration: dataset 1's fit with each robot's own range scale and
    offset, dataset 1's fit pooled over its robots, or none (raw measurements)."""

    DATASET1 = "dataset1"
    DATASET1_POOLED = "dataset1-pooled"
    NONE = "none"


@dataclass(frozen=True)
class MrclamCalibration:
    """Corrections of the files' values (module docstring): recorded range z is the
    forward distance, z = range_scale·r·cos(b) + range_offset_m; odometry takes effect
    odometry_delay_s after its timestamp, at velocity_scale·v and omega_scale·ω."""

    range_scale: float = 1.0
    range_offset_m: float = 0.0
    forward_range: bool = False
    odometry_delay_s: float = 0.0
    velocity_scale: float = 1.0
    omega_scale: float = 1.0


# Fitted on Dataset 1's approximate ground truth, robots 1-4 (see the module docstring).
DATASET1_CALIBRATION = MrclamCalibration(
    range_scale=1.0218,
    range_offset_m=0.050,
    forward_range=True,
    odometry_delay_s=0.22,
    velocity_scale=0.917,
    omega_scale=0.945,
)
# Each robot's camera has its own range scale and offset (robot: (range_scale,
# range_offset_m)), fitted on Dataset 1's approximate ground truth by
# hardware.datasets.mrclam_fit.fit_range; on Dataset 7 the same fit gives scales within
# 0.004 of these (offsets 0.02 m larger on every robot). Robot 5 has no ground truth in
# Dataset 1 and keeps the pooled values.
DATASET1_RANGE = {
    1: (1.0133, 0.0252),
    2: (1.0517, -0.0158),
    3: (1.0129, 0.0278),
    4: (1.0202, 0.0861),
}


def sensor_calibration(choice: str, robot: int) -> MrclamCalibration:
    """The corrections a `calibration` option gives robot `robot` (module docstring)."""
    if choice == CalibrationChoice.NONE:
        return MrclamCalibration()
    if choice == CalibrationChoice.DATASET1 and robot in DATASET1_RANGE:
        scale, offset = DATASET1_RANGE[robot]
        return replace(DATASET1_CALIBRATION, range_scale=scale, range_offset_m=offset)
    return DATASET1_CALIBRATION


# The noise of the calibrated values, fitted on Dataset 1 (module docstring); field paths
# of the localizer configs (slam.*Config), applied where a config has the field.
DATASET1_LOCALIZER_SETTINGS = {
    "range_sigma_m": 0.03,
    "range_sigma_frac": 0.015,
    "bearing_sigma_rad": 0.015,
    "noise.velocity_frac": 0.3,
    "noise.omega_frac": 0.23,
    "noise.omega_floor": 0.011,
}


@dataclass(frozen=True)
class MrclamOptions:
    """robot: 1–5. groundtruth: "auto" | "exact" | "approximate" | "none".
    calibration: "dataset1" (the corrections fitted on Dataset 1, each robot's own range
    scale and offset; module docstring) | "dataset1-pooled" (the range's pooled over
    Dataset 1's robots) | "none" (the files' values). slip: a braking walker's slip put
    into the odometry, the slip ratio at full "brake" of the inner wheel of every turn
    (`hardware.datasets.synthetic_slip`; 0: none), drawn with slip_seed. twin: None (the
    recorded values) or a seed: the model twin (`hardware.datasets.model_twin`; module
    docstring), the odometry and sightings regenerated from the ground truth with the
    proposed noise levels; slip, if any, is put into the twin's odometry. twin_values:
    "all" | "odometry" | "sightings": which of them (the others keep the recorded ones)."""

    robot: int = 1
    groundtruth: GroundTruthChoice = GroundTruthChoice.AUTO
    calibration: CalibrationChoice = CalibrationChoice.DATASET1
    slip: float = 0.0
    slip_seed: int = 0
    twin: int | None = None
    twin_values: TwinValues = TwinValues.ALL

    def __post_init__(self) -> None:
        coerce_option(self, "robot", as_int)
        coerce_option(self, "slip", as_float)
        coerce_option(self, "slip_seed", as_int)
        if self.twin is not None and str(self.twin).lower() != "none":
            coerce_option(self, "twin", as_int)
        else:
            object.__setattr__(self, "twin", None)
        if not (math.isfinite(self.slip) and 0.0 <= self.slip < 0.95):
            raise ValueError(f"slip must be in [0, 0.95), got {self.slip}")
        coerce(
            self,
            groundtruth=GroundTruthChoice,
            calibration=CalibrationChoice,
            twin_values=TwinValues,
        )
        if self.twin is None and self.twin_values != TwinValues.ALL:
            raise ValueError(f"twin_values={self.twin_values} needs twin=SEED")


@dataclass
class _Robot:
    """What one robot's files hold, checked and in time order (odometry and ranges as in
    the files, before the calibration)."""

    odometry: np.ndarray  # t v ω
    sightings: np.ndarray  # the measurement rows of landmarks: t barcode range bearing
    sighting_ids: np.ndarray  # the landmark (subject) of each sighting
    measurement_rows: int
    skipped: dict[str, Any]
    landmarks: np.ndarray  # subject x y x_std y_std
    landmark_ids: np.ndarray  # the landmarks' subjects as int64
    gt_kind: str
    truth: tuple[np.ndarray, np.ndarray] | None  # ground truth times, poses (x y θ)
    files: dict[str, str]  # the files read {name: path}
    notes: list[str]  # what the reading changed (metadata "dataset" "notes")


def _read_sorted(path: Path, columns: int, notes: list[str]) -> np.ndarray:
    """The rows of a table with its time first, stably sorted by time."""
    return sorted_by_time(read_table(path, columns).data, path.name, notes)


def _barcodes(path: Path) -> dict[int, int]:
    """{barcode: subject} of Barcodes.dat; a DatasetError for a barcode listed twice."""
    table = read_table(path, 2)
    subjects = table.integer_column(0, "subject")
    codes = table.integer_column(1, "barcode")
    out: dict[int, int] = {}
    for line, s, c in zip(table.lines.tolist(), subjects.tolist(), codes.tolist(), strict=True):
        if c in out:
            raise DatasetError(f"{path}: line {line}: barcode {c} listed twice")
        out[c] = s
    return out


def _approx_groundtruth(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Times spread within their whole second and poses of an `_intsec` CSV."""
    table = read_table(path, 4, delimiter=",", skip_header=1)
    sec = table.data[:, 0]
    if np.any(np.diff(sec) < 0):
        i = int(np.nonzero(np.diff(sec) < 0)[0][0]) + 1
        raise DatasetError(f"{path}: line {table.lines[i]}: time steps back")
    # rows of one second: k = 0..n-1 -> s + (k + 0.5)/n
    starts = np.r_[0, np.nonzero(np.diff(sec))[0] + 1]
    counts = np.diff(np.r_[starts, len(sec)])
    k = np.arange(len(sec)) - np.repeat(starts, counts)
    t = sec + (k + 0.5) / np.repeat(counts, counts)
    return t, table.data[:, 1:4]


def _check_robot(folder: Path, robot: int) -> None:
    """A DatasetError unless `robot` is one of the robots with an odometry file."""
    present = [r for r in ROBOTS if find_optional(folder, f"Robot{r}_Odometry.dat")]
    if robot not in ROBOTS or robot not in present:
        valid = ", ".join(str(r) for r in present) or "none found"
        raise DatasetError(f"{folder}: unknown robot number {robot}; valid: {valid}")


def _measurements(
    path: Path, barcodes: dict[int, int], notes: list[str]
) -> tuple[np.ndarray, np.ndarray, int, dict[str, Any]]:
    """The landmark sightings of a measurement file in time order, their subjects, the
    number of rows, and what was skipped (metadata "skipped"): barcodes of other robots
    and barcodes not in Barcodes.dat."""
    table = read_table(path, 4)
    codes = table.integer_column(1, "barcode")
    meas = table.data
    order = time_order(meas[:, 0], "measurements", notes)
    if order is not None:
        meas, codes = meas[order], codes[order]
    subject = np.array([barcodes.get(c, -1) for c in codes.tolist()], dtype=np.int64)
    is_landmark = np.isin(subject, LANDMARK_SUBJECTS)
    is_robot = np.isin(subject, ROBOTS)
    unknown = ~(is_landmark | is_robot)
    skipped = {
        "other_robots": int(np.count_nonzero(is_robot)),
        "unknown_barcodes": int(np.count_nonzero(unknown)),
        "unknown_barcode_values": sorted({int(c) for c in codes[unknown].tolist()}),
    }
    return meas[is_landmark], subject[is_landmark], len(meas), skipped


def _groundtruth_names(robot: int) -> tuple[str, str]:
    """The exact and the approximate ground-truth file of `robot`."""
    return f"Robot{robot}_Groundtruth.dat", f"{APPROX_DIR}/Robot{robot}_Groundtruth_intsec.csv"


def _groundtruth(
    files: FolderFiles, robot: int, choice: str, notes: list[str]
) -> tuple[str, tuple[np.ndarray, np.ndarray] | None]:
    """(kind, (times, poses)) of the ground truth option `groundtruth` picks (module
    docstring); ("none", None) without."""
    exact_name, approx_name = _groundtruth_names(robot)
    if choice in ("auto", "exact") and (choice == "exact" or files.has(exact_name)):
        g = _read_sorted(files.find(exact_name), 4, notes)
        return "exact", (g[:, 0], g[:, 1:4])
    if choice in ("auto", "approximate") and (choice == "approximate" or files.has(approx_name)):
        return "approximate", _approx_groundtruth(files.find(approx_name))
    return "none", None


def _read_robot(folder: Path, options: MrclamOptions) -> _Robot:
    """Read and check the folder's files for robot `options.robot`, in a fixed order (so
    the first bad file is the one reported)."""
    robot = options.robot
    files = FolderFiles(folder)
    notes: list[str] = []
    barcodes = _barcodes(files.find("Barcodes.dat"))
    landmarks = read_table(files.find("Landmark_Groundtruth.dat"), 5)
    subjects = landmarks.integer_column(0, "subject")
    odometry = _read_sorted(files.find(f"Robot{robot}_Odometry.dat"), 3, notes)
    meas, ids, rows, skipped = _measurements(
        files.find(f"Robot{robot}_Measurement.dat"), barcodes, notes
    )
    gt_kind, truth = _groundtruth(files, robot, options.groundtruth, notes)
    return _Robot(
        odometry=odometry,
        sightings=meas,
        sighting_ids=ids,
        measurement_rows=rows,
        skipped=skipped,
        landmarks=landmarks.data,
        landmark_ids=subjects,
        gt_kind=gt_kind,
        truth=truth,
        files=files.found,
        notes=notes,
    )


def _calibrate(robot: _Robot, cal: MrclamCalibration) -> tuple[np.ndarray, np.ndarray]:
    """The odometry (t v ω) and the landmark ranges with `cal`'s corrections applied."""
    odo = robot.odometry.copy()
    odo[:, 0] += cal.odometry_delay_s
    odo[:, 1] *= cal.velocity_scale
    odo[:, 2] *= cal.omega_scale
    rb = robot.sightings
    ranges = rb[:, 2]
    if cal.forward_range:
        ranges = (ranges - cal.range_offset_m) / (cal.range_scale * np.cos(rb[:, 3]))
    return odo, ranges


def _model_twin(
    robot: _Robot, odo: np.ndarray, ranges: np.ndarray, options: MrclamOptions, path: Path
) -> tuple[_Robot, np.ndarray, np.ndarray, dict[str, Any]]:
    """The robot's model twin (hardware.datasets.model_twin) from its calibrated odometry
    and ranges: with twin_values "all" or "sightings" the sightings within the ground
    truth's span with regenerated values (the robot's `sightings` with them; the ranges
    as the calibration gives them), with "all" or "odometry" the odometry rows within
    the span with regenerated velocities; and the metadata "twin"."""
    if robot.truth is None:
        raise DatasetError(f"{path}: twin needs ground truth for robot (groundtruth is none)")
    noise = TwinNoise.from_settings(DATASET1_LOCALIZER_SETTINGS)
    odo_rng, sight_rng = twin_generators(options.twin)
    rows = len(odo)
    if options.twin_values != TwinValues.SIGHTINGS:
        odo = twin_odometry(odo[:, 0], robot.truth, noise, odo_rng)
    kept = np.ones(len(ranges), bool)
    if options.twin_values != TwinValues.ODOMETRY:
        landmarks = dict(zip(robot.landmark_ids.tolist(), robot.landmarks[:, 1:3], strict=True))
        xy = np.array([landmarks[i] for i in robot.sighting_ids.tolist()]).reshape(-1, 2)
        kept, ranges, bearings = twin_sightings(
            robot.sightings[:, 0], xy, robot.truth, noise, sight_rng
        )
        sightings = robot.sightings[kept].copy()
        sightings[:, 2], sightings[:, 3] = ranges, bearings
        robot = replace(robot, sightings=sightings, sighting_ids=robot.sighting_ids[kept])
    what = {TwinValues.ALL: "odometry and sightings"}.get(
        options.twin_values, f"the {options.twin_values} only"
    )
    metadata = {
        "seed": options.twin,
        "values": str(options.twin_values),
        "noise": asdict(noise),
        "odometry_rows_left_out": rows - len(odo),
        "sightings_left_out": int(np.sum(~kept)),
        "note": (
            f"{what} regenerated from the ground truth with white noise "
            "of the proposed levels, at the recorded times and IDs "
            "(hardware/datasets/model_twin.py); rows outside the ground truth's span "
            "left out"
        ),
    }
    return robot, odo, ranges, metadata


def _groundtruth_metadata(kind: str, files: dict[str, str], robot: int) -> dict[str, Any]:
    """Metadata "groundtruth": its kind, source, file and how far to trust it."""
    exact_name, approx_name = _groundtruth_names(robot)
    if kind == "exact":
        return {"kind": kind, "source": "Vicon motion capture", "file": files[exact_name]}
    if kind == "approximate":
        return {
            "kind": kind,
            "source": "Vicon rows re-saved with timestamps truncated to whole seconds",
            "file": files[approx_name],
            "note": (
                "rows of one second spread evenly over it (t = s + (k + 0.5)/n); timing "
                "error up to +-0.5 s, about 0.1 m at the robots' speeds: coarse scoring only"
            ),
        }
    return {"kind": "none", "note": "no ground truth for this robot in this folder"}


def _sensor_calibration_metadata(name: str, cal: MrclamCalibration) -> dict[str, Any]:
    """Metadata "sensor_calibration": the option's name, the corrections and what they mean."""
    return {
        "name": name,
        **asdict(cal),
        "note": (
            "recorded range z = range_scale*r*cos(bearing) + range_offset_m, converted "
            "to r; odometry times + odometry_delay_s, v * velocity_scale, "
            "omega * omega_scale (hardware/datasets/mrclam.py)"
            if name != "none"
            else "the files' values, uncorrected"
        ),
    }


def _dataset_metadata(
    name: str, number: int, robot: _Robot, odo: np.ndarray, cal: MrclamCalibration
) -> dict[str, Any]:
    """Metadata "dataset": description, time base and span, counts, files and notes."""
    rb = robot.sightings
    gt_t = robot.truth[0] if robot.truth is not None else np.empty(0)
    counts = {
        "VelocityOdometry": len(odo),
        "GroundTruthPose": len(gt_t),
        "RangeBearing": len(rb),
    }
    return {
        "name": name,
        "description": (
            "UTIAS MRCLAM (Leung et al., IJRR 30(8), 2011): iRobot Create with a "
            "monocular camera, 15 barcoded landmarks, Vicon ground truth"
        ),
        "robot": number,
        "time_base": (
            "Unix epoch seconds, as in the files; odometry + "
            f"{cal.odometry_delay_s} s (sensor_calibration)"
        ),
        **span_and_counts(counts, odo[:, 0], gt_t, rb[:, 0]),
        "measurement_rows": robot.measurement_rows,
        "files": robot.files,
        "notes": robot.notes,
    }


def _metadata(
    name: str,
    options: MrclamOptions,
    folder: Path,
    robot: _Robot,
    odo: np.ndarray,
    cal: MrclamCalibration,
) -> dict[str, dict[str, Any]]:
    """All the metadata (module docstring); "localizer_settings" with the calibration
    or a twin (drawn with those noise levels)."""
    if robot.truth is not None:
        initial = interpolate_pose(*robot.truth, float(odo[0, 0]))
    else:
        initial = (0.0, 0.0, 0.0)
    ids = robot.landmark_ids.tolist()
    metadata: dict[str, dict[str, Any]] = {
        "config": config_metadata(
            "mrclam", folder, options, initial, initial_pose_t=float(odo[0, 0])
        ),
        "dataset": _dataset_metadata(name, options.robot, robot, odo, cal),
        "landmarks": {
            str(i): [float(x), float(y)]
            for i, (x, y) in zip(ids, robot.landmarks[:, 1:3].tolist(), strict=True)
        },
        "landmark_std": {
            str(i): [float(sx), float(sy)]
            for i, (sx, sy) in zip(ids, robot.landmarks[:, 3:5].tolist(), strict=True)
        },
        "skipped": robot.skipped,
        "groundtruth": _groundtruth_metadata(robot.gt_kind, robot.files, options.robot),
        "sensor_calibration": _sensor_calibration_metadata(options.calibration, cal),
    }
    if options.calibration != CalibrationChoice.NONE or options.twin is not None:
        metadata["localizer_settings"] = dict(DATASET1_LOCALIZER_SETTINGS)
    return metadata


def open_mrclam(options: MrclamOptions, path: Path) -> Dataset:
    """One robot of an MRCLAM folder (module docstring): read and check its files, apply
    the calibration, build the streams and the metadata."""
    folder = require_folder(path, "mrclam")
    _check_robot(folder, options.robot)
    robot = _read_robot(folder, options)
    cal = sensor_calibration(options.calibration, options.robot)
    odo, ranges = _calibrate(robot, cal)
    twin = None
    if options.twin is not None:
        robot, odo, ranges, twin = _model_twin(robot, odo, ranges, options, path)
    rb = robot.sightings
    calibration = WalkerCalibration(
        track_m=CREATE_TRACK_M,
        frame_width_m=CREATE_DIAMETER_M,
        frame_length_m=CREATE_DIAMETER_M,
    )
    slipped = (
        inject_slip(odo, options.slip, CREATE_TRACK_M, options.slip_seed) if options.slip else None
    )
    if slipped is not None:
        odo = slipped.odometry
    streams = tie_ordered_streams(
        (VelocityOdometry, velocity_stream(odo[:, 0], odo[:, 1], odo[:, 2])),
        (RangeBearing, range_bearing_stream(rb[:, 0], robot.sighting_ids, ranges, rb[:, 3])),
        robot.truth,
    )
    name = f"{folder.name}/robot{options.robot}"
    if options.twin is not None:
        # not the recorded values: never mixed up with them
        parts = "" if options.twin_values == TwinValues.ALL else f"_{options.twin_values}"
        name += f"_twin{options.twin}{parts}"
    metadata = _metadata(name, options, folder, robot, odo, cal)
    if twin is not None:
        metadata["twin"] = twin
    if slipped is not None:
        # after the odometry at equal times: a row's brake holds from it on, as its velocity
        commands = slipped.brake_commands(calibration.brake)
        motion = next(iter(streams.items()))
        streams = {motion[0]: motion[1], BrakeCommand: lambda: iter(commands), **streams}
        metadata["slip"] = slipped.summary(options.slip)
        metadata["dataset"]["counts"][BrakeCommand.__name__] = len(commands)
        metadata["dataset"]["notes"] = [
            *metadata["dataset"].get("notes", []),
            f"synthetic slip {options.slip} (seed {options.slip_seed}) on the inner wheel of "
            "every turn, with a BrakeCommand of the level that caused it "
            "(hardware.datasets.synthetic_slip)",
        ]
    arrays = {
        "landmark_ids": robot.landmark_ids,
        "landmark_xy": robot.landmarks[:, 1:3].copy(),
    }
    return Dataset(name, calibration, metadata, streams, arrays)


SPEC = Spec(
    "mrclam",
    MrclamOptions,
    open_mrclam,
    "UTIAS MRCLAM dataset folder, one robot: velocity odometry, known-ID range-bearing, Vicon",
)
