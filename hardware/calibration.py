"""What the software believes about the walker: encoders, track, sensor mounts, brakes.

The calibration travels inside every trial log, so replay uses the numbers the trial was
recorded with. The simulator's *true* walker may differ from it (that is how wheel
diameter and track errors are simulated).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from hardware.errors import ConfigError
from hardware.frames import BODY_R_OPTICAL, make_transform, rot_rpy
from hardware.messages import CameraIntrinsics


@dataclass(frozen=True)
class Mount:
    """Pose of a sensor on the walker body (x forward, y left, z up; rear-axle origin).

    roll/pitch/yaw orient a body-style sensor frame (x along the optical axis);
    positive pitch looks down.
    """

    x: float
    y: float
    z: float
    roll: float = 0.0
    pitch: float = 0.0
    yaw: float = 0.0

    def walker_T_optical(self) -> np.ndarray:
        """Transform from the camera optical frame (x right, y down, z forward) to the walker."""
        r = rot_rpy(self.roll, self.pitch, self.yaw) @ BODY_R_OPTICAL
        return make_transform(r, np.array([self.x, self.y, self.z]))


@dataclass(frozen=True)
class BrakeCalibration:
    """Magnetic-particle brake: torque ≈ off + slope·pwm, PWM 0–255 (thesis §3)."""

    torque_off_nm: float = 0.068
    torque_max_nm: float = 3.95
    pwm_max: int = 255

    @property
    def slope_nm_per_pwm(self) -> float:
        return (self.torque_max_nm - self.torque_off_nm) / self.pwm_max

    def pwm(self, torque_nm: float) -> int:
        """PWM duty (0–255) that gives at least the residual torque and at most full torque."""
        p = (torque_nm - self.torque_off_nm) / self.slope_nm_per_pwm
        return int(min(max(round(p), 0), self.pwm_max))

    def torque(self, pwm: float) -> float:
        return self.torque_off_nm + self.slope_nm_per_pwm * float(min(max(pwm, 0), self.pwm_max))

    def level(self, torque_nm: float) -> float:
        """How far `torque_nm` is engaged above the residual torque, as a share of the
        brake's range (0 released, 1 full), clipped to [0, 1]."""
        span = self.torque_max_nm - self.torque_off_nm
        return min(max((torque_nm - self.torque_off_nm) / span, 0.0), 1.0)

    def levels(self, cmd: Any) -> tuple[float, float]:
        """(left, right) `level` of a BrakeCommand."""
        return self.level(cmd.left_nm), self.level(cmd.right_nm)

    def clamp(self, torque_nm: float) -> float:
        return float(min(max(torque_nm, self.torque_off_nm), self.torque_max_nm))


def wheel_diameters(mean_m: float, ratio: float) -> tuple[float, float]:
    """(left, right) diameters whose mean is `mean_m` and ratio right/left `ratio`
    (ratio 1: both exactly `mean_m`)."""
    return 2.0 * mean_m / (1.0 + ratio), 2.0 * mean_m * ratio / (1.0 + ratio)


def _kinect_depth() -> CameraIntrinsics:
    return CameraIntrinsics.from_fov(160, 120, math.radians(57.0), math.radians(43.0))


def _kinect_rgb() -> CameraIntrinsics:
    return CameraIntrinsics.from_fov(640, 480, math.radians(62.0), math.radians(48.6))


@dataclass(frozen=True)
class WalkerCalibration:
    """Encoder, geometry and sensor calibration of the walker (defaults: the thesis walker).

    The two rear wheels may differ: wheel_diameter_m is their mean diameter and
    wheel_diameter_ratio the right wheel's diameter over the left's (UMBmark's E_d; 1.0:
    equal wheels, what a calibration without the key means). `walkerslam calibrate`
    estimates both and the track from a UMBmark run (`experiments.umbmark`).
    """

    wheel_diameter_m: float = 0.203  # the thesis code's value; measured 0.204 ± 0.002
    track_m: float = 0.64  # rear-wheel contact track (0.68 in the dimensions table)
    counts_per_rev: int = 256
    depth_mount: Mount = field(default_factory=lambda: Mount(0.41, 0.0, 0.495))
    depth_intrinsics: CameraIntrinsics = field(default_factory=_kinect_depth)
    depth_range_m: tuple[float, float] = (0.8, 3.5)
    tag_mount: Mount = field(default_factory=lambda: Mount(0.41, 0.025, 0.495))
    tag_intrinsics: CameraIntrinsics = field(default_factory=_kinect_rgb)
    tag_family: str = "tag36h11"
    tag_size_m: float = 0.165
    brake: BrakeCalibration = field(default_factory=BrakeCalibration)
    frame_width_m: float = 0.69  # overall width at the rear wheels
    frame_length_m: float = 0.74
    wheel_diameter_ratio: float = 1.0  # right / left wheel diameter

    def __post_init__(self) -> None:
        r = self.wheel_diameter_ratio
        if (
            isinstance(r, bool)
            or not isinstance(r, int | float)
            or not (math.isfinite(r) and r > 0)
        ):
            raise ValueError(f"wheel_diameter_ratio must be a number > 0, got {r!r}")

    @property
    def metres_per_count(self) -> float:
        """Ground distance per encoder count of the mean wheel."""
        return math.pi * self.wheel_diameter_m / self.counts_per_rev

    @property
    def wheel_diameters_m(self) -> tuple[float, float]:
        """(left, right) wheel diameters: mean wheel_diameter_m, ratio wheel_diameter_ratio
        (with equal wheels both are exactly wheel_diameter_m)."""
        return wheel_diameters(self.wheel_diameter_m, self.wheel_diameter_ratio)

    @property
    def metres_per_count_per_wheel(self) -> tuple[float, float]:
        """(left, right) ground distance per encoder count: what odometry multiplies the
        counts of each wheel by."""
        left, right = self.wheel_diameters_m
        return math.pi * left / self.counts_per_rev, math.pi * right / self.counts_per_rev

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> WalkerCalibration:
        """Inverse of to_dict; unknown keys are an error (they would be silently lost)."""
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown calibration keys: {sorted(unknown)}")
        kw: dict[str, Any] = dict(d)
        for key in ("depth_mount", "tag_mount"):
            if key in kw:
                kw[key] = Mount(**kw[key])
        for key in ("depth_intrinsics", "tag_intrinsics"):
            if key in kw:
                kw[key] = CameraIntrinsics(**kw[key])
        if "brake" in kw:
            kw["brake"] = BrakeCalibration(**kw["brake"])
        if "depth_range_m" in kw:
            kw["depth_range_m"] = tuple(kw["depth_range_m"])
        return cls(**kw)


def load_calibration(path: str | os.PathLike[str]) -> WalkerCalibration:
    """A walker calibration from a JSON file of WalkerCalibration fields (those not given
    keep the thesis walker's defaults); ValueError on one line naming the file."""
    p = Path(path)
    try:
        d = json.loads(p.read_text())
        if not isinstance(d, dict):
            raise ValueError(f"expected an object of calibration fields, got {type(d).__name__}")
        return WalkerCalibration.from_dict(d)
    except FileNotFoundError:
        raise ConfigError(f"{p}: no such calibration file") from None
    except (OSError, TypeError, ValueError) as e:
        raise ConfigError(f"{p}: not a walker calibration: {e}") from None


def save_calibration(calibration: WalkerCalibration, path: str | os.PathLike[str]) -> Path:
    """Write `calibration` as the JSON file `load_calibration` reads back exactly."""
    p = Path(path)
    p.write_text(json.dumps(calibration.to_dict(), indent=2) + "\n")
    return p


# What odometry from wheel encoders needs of a calibration (besides counts_per_rev).
ODOMETRY_FIELDS = ("wheel_diameter_m", "wheel_diameter_ratio", "track_m")


def odometry_fields(calibration: WalkerCalibration) -> dict[str, float]:
    """The wheel diameters and the track of `calibration`, by field name."""
    return {k: getattr(calibration, k) for k in ODOMETRY_FIELDS}


def with_odometry(
    calibration: WalkerCalibration, source: WalkerCalibration, source_name: str
) -> WalkerCalibration:
    """`calibration` (e.g. a log's: its cameras, brakes, encoders) with the wheel
    diameters and track of `source` (e.g. a `walkerslam calibrate` file named
    `source_name`); ConfigError when the two count encoder revolutions differently."""
    if source.counts_per_rev != calibration.counts_per_rev:
        raise ConfigError(
            f"{source_name}: calibrated for {source.counts_per_rev} counts per revolution, "
            f"the encoders count {calibration.counts_per_rev}"
        )
    return replace(calibration, **odometry_fields(source))
