"""Timestamped message types shared by every source (live drivers, logs, datasets, simulator).

All times are seconds (float) on one clock per trial; all quantities are SI.
Messages are immutable; array fields are numpy arrays that must not be mutated.
"""

from __future__ import annotations

import heapq
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True, slots=True)
class EncoderTicks:
    """Cumulative quadrature counts of the left and right rear wheels (as the board reports)."""

    t: float
    left: int
    right: int


@dataclass(frozen=True, slots=True)
class BrakeCommand:
    """Commanded brake torque per rear wheel [N·m]; `source` names who commanded it."""

    t: float
    left_nm: float
    right_nm: float
    source: str = "controller"


@dataclass(frozen=True, slots=True)
class CameraIntrinsics:
    """Pinhole intrinsics of an image stream (optical frame: x right, y down, z forward)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def from_fov(
        cls, width: int, height: int, hfov_rad: float, vfov_rad: float
    ) -> CameraIntrinsics:
        fx = (width / 2.0) / np.tan(hfov_rad / 2.0)
        fy = (height / 2.0) / np.tan(vfov_rad / 2.0)
        return cls(width, height, float(fx), float(fy), (width - 1) / 2.0, (height - 1) / 2.0)

    @property
    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True, slots=True, eq=False)
class DepthFrame:
    """Depth image in millimetres (uint16, 0 = invalid) with the intrinsics it was taken with."""

    t: float
    depth_mm: np.ndarray
    intrinsics: CameraIntrinsics

    def __post_init__(self) -> None:
        d = self.depth_mm
        if d.dtype != np.uint16 or d.ndim != 2:
            raise ValueError(f"depth_mm must be a 2-D uint16 array, got {d.dtype} {d.shape}")
        if d.shape != (self.intrinsics.height, self.intrinsics.width):
            raise ValueError(
                f"depth_mm shape {d.shape} does not match intrinsics "
                f"{self.intrinsics.height}x{self.intrinsics.width}"
            )


@dataclass(frozen=True, slots=True, eq=False)
class TagDetection:
    """One AprilTag seen in an image: its pose in the camera optical frame and its corners.

    Tag frame as pupil-apriltags reports it: origin at the tag centre, x right, y down,
    z into the tag (away from a camera that faces it). `corners_px` (4×2) wrap
    counter-clockwise in the image starting at the tag's (-s/2, +s/2) corner.
    """

    tag_id: int
    camera_T_tag: np.ndarray
    corners_px: np.ndarray
    decision_margin: float = float("nan")


@dataclass(frozen=True, slots=True, eq=False)
class TagDetections:
    """All tags detected in one tag-camera image (possibly none: that is information too)."""

    t: float
    detections: tuple[TagDetection, ...] = ()


@dataclass(frozen=True, slots=True)
class RangeBearing:
    """Range [m] and bearing [rad, CCW from the robot's heading] to a landmark with known ID."""

    t: float
    landmark_id: int
    range_m: float
    bearing_rad: float


@dataclass(frozen=True, slots=True, eq=False)
class RangeBearings:
    """Range [m] and bearing [rad, CCW from the robot's heading] to several landmarks seen
    at one time (a sensor's whole frame): entry i is landmark_ids[i] at ranges_m[i],
    bearings_rad[i]. An ID of −1 means the landmark's identity is unknown. The batched form
    of `RangeBearing`: a localizer treats it exactly as the same observations arriving as
    one RangeBearing message each with this time."""

    t: float
    landmark_ids: np.ndarray  # (n,) int64
    ranges_m: np.ndarray  # (n,) float64
    bearings_rad: np.ndarray  # (n,) float64

    def __post_init__(self) -> None:
        n = len(self.landmark_ids)
        if len(self.ranges_m) != n or len(self.bearings_rad) != n:
            raise ValueError(
                f"RangeBearings at t={self.t}: {n} ids, {len(self.ranges_m)} ranges and "
                f"{len(self.bearings_rad)} bearings (one each per landmark)"
            )

    def __len__(self) -> int:
        return len(self.landmark_ids)

    @classmethod
    def of(cls, t: float, ids, ranges, bearings) -> RangeBearings:
        """From any sequences, copied into read-only arrays."""

        def frozen(a, dtype) -> np.ndarray:
            out = np.array(a, dtype=dtype).reshape(-1)
            out.flags.writeable = False
            return out

        return cls(
            float(t),
            frozen(ids, np.int64),
            frozen(ranges, np.float64),
            frozen(bearings, np.float64),
        )


@dataclass(frozen=True, slots=True)
class VelocityOdometry:
    """Forward speed [m/s] and yaw rate [rad/s] commanded or measured from t onwards; both
    NaN: the motion from t until the next message is not known (a gap in the odometry)."""

    t: float
    v: float
    omega: float


@dataclass(frozen=True, slots=True)
class GyroRate:
    """Yaw rate [rad/s] of the walker body from its gyro: the z-axis angular rate, CCW
    positive, as the sensor reports it (its bias and scale error included).

    A MEMS gyro's output is low-pass filtered and sampled; the rate is taken as the mean
    over the interval since the gyro's previous sample, so that the samples, each held
    over the interval it ends, integrate to the angle turned.
    """

    t: float
    rate_rad_s: float


@dataclass(frozen=True, slots=True, eq=False)
class LaserScan:
    """Planar range scan in the robot frame; beam i is at angle_min + i·angle_increment.

    Ranges that are not finite, <= 0 or >= range_max are "no return".
    """

    t: float
    angle_min: float
    angle_increment: float
    ranges: np.ndarray
    range_max: float

    @property
    def angles(self) -> np.ndarray:
        return self.angle_min + self.angle_increment * np.arange(len(self.ranges))


@dataclass(frozen=True, slots=True)
class GroundTruthPose:
    """True planar pose of the robot reference point (rear-axle centre on the walker)."""

    t: float
    x: float
    y: float
    theta: float


@dataclass(frozen=True, slots=True)
class Collision:
    """Start of a contact between the walker footprint and an obstacle (simulator truth).

    kind is 'front', 'side' or 'rear-wheel' (thesis Table 6.3); x, y is the contact point.
    """

    t: float
    kind: str
    obstacle: str
    x: float
    y: float


@dataclass(frozen=True, slots=True)
class DeviceEvent:
    """Something a live device did that a reader of the log must know about.

    device names it ("board", "depth", "tags"); event is one of
    "connected", "disconnected" (the port went away: a gap in its streams starts),
    "reconnected" (the gap ends), "reset" (the board restarted: its counters restarted,
    the driver re-based them so odometry continues without a jump), "stalled" /
    "resumed" (a stream stopped delivering for longer than its stale limit and came
    back); detail says more in words (counts, reasons).
    """

    t: float
    device: str
    event: str
    detail: str = ""


@dataclass(frozen=True, slots=True)
class CompassHeading:
    """The walker's heading [rad] in the map frame (CCW from +x, wrapped to (−π, π]) from
    an absolute sensor (a compass, a simulator's noisy true heading), with its standard
    deviation [rad] when the source knows it, NaN otherwise (a localizer then uses its
    configured noise, slam.absolute.AbsoluteConfig)."""

    t: float
    heading_rad: float
    sigma_rad: float = float("nan")


@dataclass(frozen=True, slots=True)
class PositionFix:
    """An absolute position [m] of the walker's reference point (the rear-axle centre) in
    the map frame, e.g. a GPS fix projected to local metres, with its standard deviation
    per axis [m] when the source knows it, NaN otherwise."""

    t: float
    x: float
    y: float
    sigma_m: float = float("nan")


Message = (
    EncoderTicks
    | BrakeCommand
    | DepthFrame
    | TagDetections
    | RangeBearing
    | RangeBearings
    | VelocityOdometry
    | GyroRate
    | LaserScan
    | GroundTruthPose
    | Collision
    | DeviceEvent
    | CompassHeading
    | PositionFix
)

MESSAGE_TYPES: tuple[type, ...] = (
    EncoderTicks,
    BrakeCommand,
    DepthFrame,
    TagDetections,
    RangeBearing,
    RangeBearings,
    VelocityOdometry,
    GyroRate,
    LaserScan,
    GroundTruthPose,
    Collision,
    DeviceEvent,
    CompassHeading,
    PositionFix,
)

# the messages that carry landmark sightings (localizers read them through
# slam.measurement.landmark_observation)
LANDMARK_MESSAGES: tuple[type, ...] = (TagDetections, RangeBearing, RangeBearings)


@dataclass(order=True, slots=True)
class _Head:
    t: float
    rank: int
    msg: Message = field(compare=False)


def merge(*sources: Iterable[Message]) -> Iterator[Message]:
    """Merge several time-ordered sources into one time-ordered stream.

    Ties keep the order of the sources as given (stable), so messages from the first
    source come first at equal timestamps.
    """

    def tagged(rank: int, src: Iterable[Message]) -> Iterator[_Head]:
        for m in src:
            yield _Head(m.t, rank, m)

    for head in heapq.merge(*(tagged(i, s) for i, s in enumerate(sources))):
        yield head.msg
