"""The message types a log holds, in one table (`CODECS`): for each `hardware.messages` type
its default topic, its schema and companion channels, how it is encoded into channel
messages and decoded back. Adding a message type is one `Codec` entry here (and, for a
structured one, its schemas in `schemas.py`); the writer, the reader, `TOPICS` and
`encode_parts` all follow the table."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import msgspec
import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.LaserScan_pb2 import LaserScan as PbLaserScan
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

from hardware.log.schemas import (
    CAMERA_CALIBRATION,
    DEPTH_EXACT,
    LASER_SCAN,
    POSE_EXACT,
    POSE_IN_FRAME,
    RANGE_BEARINGS,
    RAW_IMAGE,
    SCAN_EXACT,
    TAG_DETECTIONS,
    ChannelSchema,
    flat_fields,
    flat_schema,
)
from hardware.messages import (
    BrakeCommand,
    CameraIntrinsics,
    Collision,
    CompassHeading,
    DepthFrame,
    DeviceEvent,
    EncoderTicks,
    GroundTruthPose,
    GyroRate,
    LaserScan,
    Message,
    PositionFix,
    RangeBearing,
    RangeBearings,
    TagDetection,
    TagDetections,
    VelocityOdometry,
)

Part = tuple[str, ChannelSchema, bytes]  # (topic, schema, payload) of one MCAP message
Companions = dict[str, tuple[int, Any]]  # schema name -> (log time ns, decoded payload)


class Skip(Exception):
    """A message the replayer cannot represent; its topic is skipped with a warning."""


@dataclass(frozen=True)
class Companion:
    """A channel written with every message of a type, just before it: what the main
    message's (Foxglove) schema cannot hold."""

    schema: ChannelSchema
    topic: Callable[[str], str]  # its topic, from the main topic
    parse: Callable[[bytes], Any]


@dataclass(frozen=True)
class Codec:
    """How one message type is logged and read back.

    encode(msg, ns) gives the payloads, one per companion (in order) and the main
    message's last, Foxglove timestamps at `ns`; parse turns the main payload into an
    intermediate that build(parsed, log time ns, companions) makes the message from, with
    the companions' parsed payloads at hand (see `exact`)."""

    cls: type
    topic: str  # default topic
    schema: ChannelSchema
    encode: Callable[[Any, int], list[bytes]]
    parse: Callable[[bytes], Any]
    build: Callable[[Any, int, Companions], Message]
    companions: tuple[Companion, ...] = ()


# --------------------------------------------------------------------------- helpers


def message_ns(t: float) -> int:
    """A message time [s] as MCAP nanoseconds."""
    t = float(t)
    if not (math.isfinite(t) and t >= 0.0):
        raise ValueError(f"message time must be finite and >= 0 (MCAP log time), got {t!r}")
    return round(t * 1e9)


def _jf(x: float) -> float | str:
    """A float as JSON: itself if finite, else "NaN" / "Infinity" / "-Infinity"."""
    x = float(x)
    if math.isfinite(x):
        return x
    return "NaN" if x != x else ("Infinity" if x > 0 else "-Infinity")


def _jarr(a: np.ndarray) -> list[float | str]:
    """An array as a flat (row-major) JSON list of float64 values."""
    flat = np.asarray(a, dtype=np.float64).ravel()
    return flat.tolist() if np.isfinite(flat).all() else [_jf(x) for x in flat.tolist()]


def dumps(obj: dict[str, Any]) -> bytes:
    """Compact strict JSON (no NaN)."""
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


def _stamp(ns: int, msg: Any) -> None:
    msg.timestamp.seconds, msg.timestamp.nanos = divmod(ns, 1_000_000_000)


def exact(comp: Companions, schema: ChannelSchema, ns: int) -> dict[str, Any] | None:
    """The exact companion written with the main message at `ns`, consumed."""
    entry = comp.pop(schema.name, None)
    return entry[1] if entry is not None and entry[0] == ns else None


def _exact_topic(topic: str) -> str:
    return topic + "/exact"


def _camera_info_topic(topic: str) -> str:
    return topic.removesuffix("/image") + "/camera_info"


# --------------------------------------------------------------------------- flat JSON messages

_TO_JSON: dict[str, Callable[[Any], Any]] = {"float": _jf, "int": int, "str": str}


def _built(msg: Message, ns: int, comp: Companions) -> Message:
    return msg


def flat(cls: type, topic: str, docs: dict[str, str]) -> Codec:
    """A message of float, int and str fields stored as one JSON object of its fields;
    docs: {field: description} for its JSON Schema."""
    convert = [(name, _TO_JSON[type_name]) for name, type_name in flat_fields(cls)]

    def encode(msg: Any, ns: int) -> list[bytes]:
        return [dumps({name: conv(getattr(msg, name)) for name, conv in convert})]

    # msgspec types the fields (all required; a float field also takes "NaN",
    # "Infinity", "-Infinity" and integers; extra fields ignored)
    parse = msgspec.json.Decoder(cls, strict=False).decode
    return Codec(cls, topic, flat_schema(cls, docs), encode, parse, _built)


# --------------------------------------------------------------------------- tag detections


def _enc_tags(msg: TagDetections, ns: int) -> list[bytes]:
    dets = [
        {
            "tag_id": int(d.tag_id),
            "camera_T_tag": _jarr(d.camera_T_tag),
            "corners_px": _jarr(d.corners_px),
            "decision_margin": _jf(d.decision_margin),
        }
        for d in msg.detections
    ]
    return [dumps({"t": float(msg.t), "detections": dets})]


def _dec_tags(obj: Any, ns: int, comp: Companions) -> TagDetections:
    dets = tuple(
        TagDetection(
            tag_id=int(d["tag_id"]),
            camera_T_tag=np.array(d["camera_T_tag"], dtype=np.float64).reshape(4, 4),
            corners_px=np.array(d["corners_px"], dtype=np.float64).reshape(-1, 2),
            decision_margin=float(d["decision_margin"]),
        )
        for d in obj["detections"]
    )
    return TagDetections(float(obj["t"]), dets)


# --------------------------------------------------------------------------- range-bearing frames


def _enc_range_bearings(msg: RangeBearings, ns: int) -> list[bytes]:
    obj = {
        "t": float(msg.t),
        "landmark_ids": [int(i) for i in msg.landmark_ids],
        "ranges_m": _jarr(msg.ranges_m),
        "bearings_rad": _jarr(msg.bearings_rad),
    }
    return [dumps(obj)]


def _dec_range_bearings(obj: Any, ns: int, comp: Companions) -> RangeBearings:
    def floats(key: str) -> list[float]:
        return [float(x) for x in obj[key]]  # float("NaN") reads the non-finite strings

    return RangeBearings.of(
        obj["t"], [int(i) for i in obj["landmark_ids"]], floats("ranges_m"), floats("bearings_rad")
    )


# --------------------------------------------------------------------------- depth frames


def _enc_depth(msg: DepthFrame, ns: int) -> list[bytes]:
    k = msg.intrinsics
    cal = CameraCalibration(
        frame_id="depth_optical",
        width=k.width,
        height=k.height,
        distortion_model="plumb_bob",
        D=[0.0] * 5,
        K=[k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0],
        R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        P=[k.fx, 0.0, k.cx, 0.0, 0.0, k.fy, k.cy, 0.0, 0.0, 0.0, 1.0, 0.0],
    )
    img = RawImage(
        frame_id="depth_optical",
        width=k.width,
        height=k.height,
        encoding="16UC1",
        step=2 * k.width,
        data=np.ascontiguousarray(msg.depth_mm, dtype="<u2").tobytes(),
    )
    _stamp(ns, cal)
    _stamp(ns, img)
    return [dumps({"t": float(msg.t)}), cal.SerializeToString(), img.SerializeToString()]


def _dec_depth(img: Any, ns: int, comp: Companions) -> DepthFrame:
    if img.encoding != "16UC1":
        raise Skip(f"image encoding {img.encoding!r} is not 16UC1 depth")
    if CAMERA_CALIBRATION.name not in comp:
        raise Skip("no camera_info before the image")
    cal = comp[CAMERA_CALIBRATION.name][1]
    k = CameraIntrinsics(cal.width, cal.height, cal.K[0], cal.K[4], cal.K[2], cal.K[5])
    rows = np.frombuffer(img.data, dtype="<u2").reshape(img.height, img.step // 2)
    ex = exact(comp, DEPTH_EXACT, ns)
    t = ex["t"] if ex else img.timestamp.ToNanoseconds() / 1e9
    return DepthFrame(float(t), rows[:, : img.width].astype(np.uint16, copy=False), k)


# --------------------------------------------------------------------------- laser scans


def _enc_scan(msg: LaserScan, ns: int) -> list[bytes]:
    ranges = np.asarray(msg.ranges)
    n = len(ranges)
    scan = PbLaserScan(
        frame_id="walker",
        start_angle=float(msg.angle_min),
        end_angle=float(msg.angle_min + max(n - 1, 0) * msg.angle_increment),
        ranges=ranges.astype(np.float64).tolist(),
    )
    scan.pose.orientation.w = 1.0
    _stamp(ns, scan)
    ex = {
        "t": float(msg.t),
        "angle_increment": _jf(msg.angle_increment),
        "range_max": _jf(msg.range_max),
        "dtype": ranges.dtype.name,
    }
    return [dumps(ex), scan.SerializeToString()]


def _dec_scan(scan: Any, ns: int, comp: Companions) -> LaserScan:
    n = len(scan.ranges)
    ex = exact(comp, SCAN_EXACT, ns) or {
        "t": scan.timestamp.ToNanoseconds() / 1e9,
        "angle_increment": (scan.end_angle - scan.start_angle) / (n - 1) if n > 1 else 0.0,
        "range_max": math.inf,
        "dtype": "float64",
    }
    ranges = np.array(scan.ranges, dtype=np.float64).astype(ex["dtype"])
    return LaserScan(
        float(ex["t"]),
        scan.start_angle,
        float(ex["angle_increment"]),
        ranges,
        float(ex["range_max"]),
    )


# --------------------------------------------------------------------------- ground truth


def _enc_pose(msg: GroundTruthPose, ns: int) -> list[bytes]:
    pose = PoseInFrame(frame_id="world")
    pose.pose.position.x, pose.pose.position.y = float(msg.x), float(msg.y)
    pose.pose.orientation.z = math.sin(msg.theta / 2.0)
    pose.pose.orientation.w = math.cos(msg.theta / 2.0)
    _stamp(ns, pose)
    return [dumps({"t": float(msg.t), "theta": _jf(msg.theta)}), pose.SerializeToString()]


def _dec_pose(pose: Any, ns: int, comp: Companions) -> GroundTruthPose:
    q = pose.pose.orientation
    ex = exact(comp, POSE_EXACT, ns) or {
        "t": pose.timestamp.ToNanoseconds() / 1e9,
        "theta": 2.0 * math.atan2(q.z, q.w),
    }
    p = pose.pose.position
    return GroundTruthPose(float(ex["t"]), p.x, p.y, float(ex["theta"]))


# --------------------------------------------------------------------------- the table

_json = msgspec.json.decode

CODECS: dict[type, Codec] = {
    c.cls: c
    for c in (
        flat(
            EncoderTicks,
            "/encoders",
            {"left": "left rear wheel, cumulative quadrature counts", "right": "right rear wheel"},
        ),
        flat(
            BrakeCommand,
            "/brakes/command",
            {
                "left_nm": "commanded left brake torque [N·m]",
                "right_nm": "commanded right brake torque [N·m]",
                "source": "who commanded it",
            },
        ),
        flat(
            RangeBearing,
            "/range_bearing",
            {
                "landmark_id": "landmark ID",
                "range_m": "range [m]",
                "bearing_rad": "bearing [rad], CCW from the robot heading",
            },
        ),
        flat(
            VelocityOdometry,
            "/odometry/velocity",
            {"v": "forward speed [m/s]", "omega": "yaw rate [rad/s]"},
        ),
        flat(
            GyroRate,
            "/imu/gyro",
            {
                "rate_rad_s": "yaw rate of the walker body [rad/s], z axis, CCW positive, "
                "as the gyro reports it (mean over the interval since its previous sample)"
            },
        ),
        flat(
            Collision,
            "/collisions",
            {
                "kind": "'front', 'side' or 'rear-wheel'",
                "obstacle": "obstacle name",
                "x": "contact point x [m, world]",
                "y": "contact point y [m, world]",
            },
        ),
        flat(
            DeviceEvent,
            "/events",
            {
                "device": "the device: 'board', 'depth', 'tags'",
                "event": "connected, disconnected, reconnected, reset, stalled, resumed",
                "detail": "what happened, in words",
            },
        ),
        Codec(
            DepthFrame,
            "/depth/image",
            RAW_IMAGE,
            _enc_depth,
            RawImage.FromString,
            _dec_depth,
            (
                Companion(DEPTH_EXACT, _exact_topic, _json),
                Companion(CAMERA_CALIBRATION, _camera_info_topic, CameraCalibration.FromString),
            ),
        ),
        Codec(TagDetections, "/tags/detections", TAG_DETECTIONS, _enc_tags, _json, _dec_tags),
        Codec(
            RangeBearings,
            "/range_bearings",
            RANGE_BEARINGS,
            _enc_range_bearings,
            _json,
            _dec_range_bearings,
        ),
        Codec(
            LaserScan,
            "/scan",
            LASER_SCAN,
            _enc_scan,
            PbLaserScan.FromString,
            _dec_scan,
            (Companion(SCAN_EXACT, _exact_topic, _json),),
        ),
        Codec(
            GroundTruthPose,
            "/groundtruth/pose",
            POSE_IN_FRAME,
            _enc_pose,
            PoseInFrame.FromString,
            _dec_pose,
            (Companion(POSE_EXACT, _exact_topic, _json),),
        ),
        flat(
            CompassHeading,
            "/compass",
            {
                "heading_rad": "heading [rad], CCW from the map's +x, in (-pi, pi]",
                "sigma_rad": "standard deviation [rad], NaN when unknown",
            },
        ),
        flat(
            PositionFix,
            "/fix",
            {
                "x": "position x [m, map frame]",
                "y": "position y [m, map frame]",
                "sigma_m": "standard deviation per axis [m], NaN when unknown",
            },
        ),
    )
}

#: Default topic of every message type.
TOPICS: dict[type, str] = {cls: codec.topic for cls, codec in CODECS.items()}


def encode_parts(msg: Message, topic: str, ns: int) -> list[Part]:
    """The channel messages of one message on `topic`, (topic, schema, payload) with its
    companions first and the main message last, timestamps at `ns` — what the log writes
    and the live view (experiments.live_view) serves."""
    codec = CODECS.get(type(msg))
    if codec is None:
        raise TypeError(f"cannot log a {type(msg).__name__}")
    payloads = codec.encode(msg, ns)
    if not codec.companions:
        return [(topic, codec.schema, payloads[0])]
    # zip ends with the companions; the last payload is the main message's
    parts = [
        (c.topic(topic), c.schema, p) for c, p in zip(codec.companions, payloads, strict=False)
    ]
    parts.append((topic, codec.schema, payloads[-1]))
    return parts


@dataclass(frozen=True)
class SchemaReader:
    """How the replayer reads a channel of one schema: parse the payload, then (for a main
    channel) build the message; companions are only parsed."""

    schema: ChannelSchema
    parse: Callable[[bytes], Any]
    build: Callable[[Any, int, Companions], Message] | None = None  # None: a companion
    cls: type | None = None


#: Schema name -> its reader, for every schema of the table.
READERS: dict[str, SchemaReader] = {
    **{
        comp.schema.name: SchemaReader(comp.schema, comp.parse)
        for codec in CODECS.values()
        for comp in codec.companions
    },
    **{
        codec.schema.name: SchemaReader(codec.schema, codec.parse, codec.build, codec.cls)
        for codec in CODECS.values()
    },
}
