"""Trial logs: a crash-safe MCAP writer and a replayer that gives back the message dataclasses.

A trial log is one MCAP file (https://mcap.dev) holding every sensor stream, the brake
commands, the calibration, the run's parameters and, in simulation, the ground truth. It
opens in Foxglove and in any MCAP reader; `read_log` turns it back into exactly the
`hardware.messages` dataclasses that were written (bit-exact floats, same array dtypes).

    with LogWriter("trial.mcap", calibration, metadata={"config": cfg, "world": world}) as log:
        for msg in source:
            log.write(msg)                      # topic from the type
        log.write(cmd, topic="/brakes/replayed")  # or an explicit one

    trial = read_log("trial.mcap")   # .calibration .metadata .attachments .topics
    for msg in trial.messages(["/encoders", "/depth/image"]):
        ...

Log format (version 1)
======================

Header: profile "", library "walker-slam log v1 (mcap-python ...)". Chunks are zstd
compressed (lz4 or none if unavailable); the summary and indexes are standard.

Metadata records (MCAP metadata maps str to str, so each dict is stored as one key
"json" holding `json.dumps(dict)`; strict JSON, no NaN):

    calibration   WalkerCalibration.to_dict(); required, a log without it is rejected
    <name>        every dict given as LogWriter(metadata={name: dict}), e.g. "config", "world",
                  "localizer_settings" (settings the source proposes to localizers,
                  experiments.studies.settings.source_settings)

Attachments: LogWriter(attachments={name: bytes}), media type application/octet-stream.

Channels: one per stream. `LogWriter.write(msg, topic=None)` uses the type's default
topic below; any other topic may be given (e.g. "/brakes/replayed" for a second brake
command stream). A topic holds a single message type.

    topic                    type               message encoding / schema name
    /encoders                EncoderTicks       json / walker.EncoderTicks
    /brakes/command          BrakeCommand       json / walker.BrakeCommand
    /depth/image             DepthFrame         protobuf / foxglove.RawImage
    /depth/camera_info         companion        protobuf / foxglove.CameraCalibration
    /depth/image/exact         companion        json / walker.DepthFrameExact
    /tags/detections         TagDetections      json / walker.TagDetections
    /range_bearing           RangeBearing       json / walker.RangeBearing
    /odometry/velocity       VelocityOdometry   json / walker.VelocityOdometry
    /scan                    LaserScan          protobuf / foxglove.LaserScan
    /scan/exact                companion        json / walker.LaserScanExact
    /groundtruth/pose        GroundTruthPose    protobuf / foxglove.PoseInFrame
    /groundtruth/pose/exact    companion        json / walker.GroundTruthPoseExact
    /collisions              Collision          json / walker.Collision
    /events                  DeviceEvent        json / walker.DeviceEvent

JSON channels have schema encoding "jsonschema"; protobuf channels carry the
FileDescriptorSet of the Foxglove schema (schema encoding "protobuf").

Companion channels complete a Foxglove message with what its schema cannot hold exactly.
For a stream on topic T they are T + "/exact" and, for depth, the camera info on T with a
trailing "/image" replaced by "/camera_info" (else T + "/camera_info"). Each companion
channel has channel metadata {"main_topic": T}, and its message is written just before
the main message with the same log time; the camera info goes with every frame.

Times: publish_time = round(t * 1e9) ns, so t must be finite and >= 0; log_time is the
same unless the writer was given the time the message was recorded (a live recorder
stores the time it fed each message to the pipeline, never earlier than t, so that a
replay in log-time order feeds them in the live run's order; a message's companions
share its log time). The float t itself is stored exactly in every JSON payload ("t"),
for Foxglove messages in the exact companion (their protobuf timestamp holds the same
ns as publish_time).

JSON payloads: compact UTF-8 objects; floats are written with Python's shortest
round-trip repr, so they read back bit-exactly; non-finite floats, which JSON lacks, are
the strings "NaN", "Infinity", "-Infinity" (the protobuf JSON mapping); integers are
JSON integers. Units are SI. Schemas (all fields required):

    walker.EncoderTicks       t [s], left, right [cumulative quadrature counts, int, may be < 0]
    walker.BrakeCommand       t [s], left_nm, right_nm [N·m commanded torque], source [str]
    walker.RangeBearing       t [s], landmark_id [int], range_m [m],
                              bearing_rad [rad, CCW from the robot heading]
    walker.VelocityOdometry   t [s], v [m/s forward], omega [rad/s yaw rate]
    walker.Collision          t [s], kind ["front" | "side" | "rear-wheel"], obstacle [str],
                              x, y [m, contact point in the world]
    walker.DeviceEvent        t [s], device [str], event [str: connected | disconnected |
                              reconnected | reset | stalled | resumed], detail [str]
    walker.TagDetections      t [s], detections: list of {tag_id [int],
                              camera_T_tag [16 numbers: the 4×4 transform, row-major, m],
                              corners_px [8 numbers: u0, v0, ..., u3, v3, px],
                              decision_margin [number, "NaN" when unknown]}
                              (arrays flat because Foxglove's JSON Schema support has no
                              nested arrays; read back as float64 4×4 and 4×2)
    walker.DepthFrameExact    t [s]
    walker.LaserScanExact     t [s], angle_increment [rad], range_max [m],
                              dtype [numpy dtype name of the ranges, e.g. "float32"]
    walker.GroundTruthPoseExact  t [s], theta [rad]

Foxglove messages:

    foxglove.RawImage           timestamp, frame_id "depth_optical", width, height,
                                encoding "16UC1", step 2·width, data: depth in millimetres as
                                little-endian uint16 (0 = invalid)
    foxglove.CameraCalibration  timestamp, frame_id "depth_optical", width, height,
                                distortion_model "plumb_bob", D = 5 zeros,
                                K = [fx 0 cx; 0 fy cy; 0 0 1], R = I, P = [K | 0]
    foxglove.LaserScan          timestamp, frame_id "walker", identity pose,
                                start_angle = angle_min,
                                end_angle = angle_min + (n - 1)·angle_increment,
                                ranges as float64 (float32 values convert exactly, NaN stays
                                NaN, inf stays inf, nothing is clipped at range_max)
    foxglove.PoseInFrame        timestamp, frame_id "world", position (x, y, 0),
                                orientation: yaw theta about z, (0, 0, sin θ/2, cos θ/2)

Crash safety: the writer flushes (closes the current chunk and hands it to the OS) at
least every 0.5 s of wall time (a background thread covers idle periods) and every 0.5 s
of log time, so a killed recorder loses at most the last half second; `fsync=True` also
survives power loss. `close()` (or leaving the `with` block) writes the summary; always
close the writer. `LogWriter.write` may be called from several threads.

Reading: `read_log` scans the file front to back and needs neither summary nor footer (so
it also reads a log that is still being written). It stops at the first truncated or
corrupt record (chunk CRCs are checked) and warns with `LogRecoveryWarning` how many
messages and seconds it recovered. Messages come out in log-time order, ties in file
order, whatever order they were written in. Channels whose schema it does not know are
skipped with an `UnsupportedChannelWarning`, and so are images that are not 16UC1.
Foxglove channels without companions (added by other tools) are read approximately: t
from the timestamp, theta from the quaternion, angle_increment from the end angle,
range_max = inf. `LogError` (one line, naming the file): missing, unreadable or empty
file, not MCAP, truncated in the header or before any message, no calibration record.
Decoded depth images are read-only arrays.
"""

from __future__ import annotations

import heapq
import io
import itertools
import json
import math
import os
import struct
import threading
import time
import warnings
import zlib
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, NoReturn

import lz4.frame
import msgspec
import numpy as np
import zstandard
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.LaserScan_pb2 import LaserScan as PbLaserScan
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Header, Metadata, Schema
from mcap.records import Message as McapMessage
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer
from mcap_protobuf.schema import build_file_descriptor_set

from hardware.calibration import WalkerCalibration
from hardware.errors import LogError
from hardware.messages import (
    BrakeCommand,
    CameraIntrinsics,
    Collision,
    DepthFrame,
    DeviceEvent,
    EncoderTicks,
    GroundTruthPose,
    LaserScan,
    Message,
    RangeBearing,
    TagDetection,
    TagDetections,
    VelocityOdometry,
)

__all__ = [
    "FLUSH_INTERVAL_S",
    "TOPICS",
    "LogError",
    "LogReader",
    "LogRecoveryWarning",
    "LogWriter",
    "TrialLog",
    "UnsupportedChannelWarning",
    "encode_parts",
    "read_log",
    "replay",
]

FLUSH_INTERVAL_S = 0.5
FORMAT = "walker-slam log v1"
MAGIC = b"\x89MCAP0\r\n"


# LogError: hardware.errors.LogError (a WalkerSlamError), raised with one line naming the
# file and the problem.


class LogRecoveryWarning(UserWarning):
    """A truncated or corrupt log was read up to its last intact record."""


class UnsupportedChannelWarning(UserWarning):
    """A channel (or its messages) that the replayer cannot turn into messages is skipped."""


# --------------------------------------------------------------------------- encoding


def _ns(t: float) -> int:
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


def _dumps(obj: dict[str, Any]) -> bytes:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


def _stamp(ns: int, msg: Any) -> None:
    msg.timestamp.seconds, msg.timestamp.nanos = divmod(ns, 1_000_000_000)


@dataclass(frozen=True)
class _Schema:
    name: str
    encoding: str  # MCAP schema encoding
    message_encoding: str  # MCAP channel message encoding
    data: bytes = field(repr=False)


def _json_schema(name: str, doc: str, props: dict[str, dict[str, Any]]) -> _Schema:
    schema = {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": name,
        "description": doc + ' Non-finite numbers are the strings "NaN", "Infinity", "-Infinity".',
        "type": "object",
        "properties": props,
        "required": list(props),
    }
    return _Schema(name, "jsonschema", "json", json.dumps(schema, indent=1).encode())


def _prop(json_type: str, description: str, **extra: Any) -> dict[str, Any]:
    """One field; Foxglove's JSON Schema support needs a single type and no nested arrays."""
    return {"type": json_type, "description": description, **extra}


def _proto_schema(cls: Any) -> _Schema:
    data = build_file_descriptor_set(cls).SerializeToString()
    return _Schema(cls.DESCRIPTOR.full_name, "protobuf", "protobuf", data)


T_PROP = _prop("number", "time [s], exact; the publish time is round(t*1e9) ns")
_NUMBERS = {"type": "number"}

# Flat JSON messages: type -> (default topic, {field: description}); fields follow the dataclass.
_FLAT: dict[type, tuple[str, dict[str, str]]] = {
    EncoderTicks: (
        "/encoders",
        {"left": "left rear wheel, cumulative quadrature counts", "right": "right rear wheel"},
    ),
    BrakeCommand: (
        "/brakes/command",
        {
            "left_nm": "commanded left brake torque [N·m]",
            "right_nm": "commanded right brake torque [N·m]",
            "source": "who commanded it",
        },
    ),
    RangeBearing: (
        "/range_bearing",
        {
            "landmark_id": "landmark ID",
            "range_m": "range [m]",
            "bearing_rad": "bearing [rad], CCW from the robot heading",
        },
    ),
    VelocityOdometry: (
        "/odometry/velocity",
        {"v": "forward speed [m/s]", "omega": "yaw rate [rad/s]"},
    ),
    Collision: (
        "/collisions",
        {
            "kind": "'front', 'side' or 'rear-wheel'",
            "obstacle": "obstacle name",
            "x": "contact point x [m, world]",
            "y": "contact point y [m, world]",
        },
    ),
    DeviceEvent: (
        "/events",
        {
            "device": "the device: 'board', 'depth', 'tags'",
            "event": "connected, disconnected, reconnected, reset, stalled, resumed",
            "detail": "what happened, in words",
        },
    ),
}
_FIELDS: dict[type, list[tuple[str, str]]] = {  # (field, type name) in dataclass order
    cls: [(f.name, f.type if isinstance(f.type, str) else f.type.__name__) for f in fields(cls)]
    for cls in _FLAT
}
_JSON_TYPE = {"float": "number", "int": "integer", "str": "string"}
_TO_JSON: dict[str, Callable[[Any], Any]] = {"float": _jf, "int": int, "str": str}
_FLAT_SCHEMAS: dict[type, _Schema] = {
    cls: _json_schema(
        f"walker.{cls.__name__}",
        (cls.__doc__ or "").strip().split("\n")[0],
        {
            name: T_PROP if name == "t" else _prop(_JSON_TYPE[type_name], docs[name])
            for name, type_name in _FIELDS[cls]
        },
    )
    for cls, (_, docs) in _FLAT.items()
}
TAG_DETECTIONS = _json_schema(
    "walker.TagDetections",
    "AprilTags detected in one tag-camera image (possibly none).",
    {
        "t": T_PROP,
        "detections": _prop(
            "array",
            "one entry per tag",
            items={
                "type": "object",
                "properties": {
                    "tag_id": _prop("integer", "tag ID"),
                    "camera_T_tag": _prop(
                        "array",
                        "4×4 tag pose in the camera optical frame, row-major [m]",
                        items=_NUMBERS,
                    ),
                    "corners_px": _prop(
                        "array", "corners u0, v0, u1, v1, u2, v2, u3, v3 [px]", items=_NUMBERS
                    ),
                    "decision_margin": _prop("number", "detector margin, NaN if unknown"),
                },
                "required": ["tag_id", "camera_T_tag", "corners_px", "decision_margin"],
            },
        ),
    },
)
DEPTH_EXACT = _json_schema(
    "walker.DepthFrameExact", "Exact time of the depth frame on the main topic.", {"t": T_PROP}
)
SCAN_EXACT = _json_schema(
    "walker.LaserScanExact",
    "LaserScan fields that foxglove.LaserScan cannot hold exactly.",
    {
        "t": T_PROP,
        "angle_increment": _prop("number", "angle between beams [rad]"),
        "range_max": _prop("number", "ranges >= range_max are no return [m]"),
        "dtype": _prop("string", "numpy dtype of the ranges, e.g. float32"),
    },
)
POSE_EXACT = _json_schema(
    "walker.GroundTruthPoseExact",
    "Exact time and heading of the ground-truth pose on the main topic.",
    {"t": T_PROP, "theta": _prop("number", "heading [rad], CCW from world +x")},
)
RAW_IMAGE = _proto_schema(RawImage)
CAMERA_CALIBRATION = _proto_schema(CameraCalibration)
LASER_SCAN = _proto_schema(PbLaserScan)
POSE_IN_FRAME = _proto_schema(PoseInFrame)

#: Default topic of every message type.
TOPICS: dict[type, str] = {
    **{cls: topic for cls, (topic, _) in _FLAT.items()},
    DepthFrame: "/depth/image",
    TagDetections: "/tags/detections",
    LaserScan: "/scan",
    GroundTruthPose: "/groundtruth/pose",
}

_Part = tuple[str, _Schema, bytes]  # (topic, schema, payload) of one MCAP message


def _camera_info_topic(topic: str) -> str:
    return topic.removesuffix("/image") + "/camera_info"


def encode_parts(msg: Message, topic: str, ns: int) -> list[_Part]:
    """The channel messages of one message on `topic`, (topic, schema, payload) with its
    companions first and the main message last, timestamps at `ns` — what the log writes
    and the live view (experiments.live_view) serves."""
    if type(msg) in _FLAT:
        obj = {
            name: _TO_JSON[type_name](getattr(msg, name)) for name, type_name in _FIELDS[type(msg)]
        }
        return [(topic, _FLAT_SCHEMAS[type(msg)], _dumps(obj))]
    if isinstance(msg, TagDetections):
        dets = [
            {
                "tag_id": int(d.tag_id),
                "camera_T_tag": _jarr(d.camera_T_tag),
                "corners_px": _jarr(d.corners_px),
                "decision_margin": _jf(d.decision_margin),
            }
            for d in msg.detections
        ]
        return [(topic, TAG_DETECTIONS, _dumps({"t": float(msg.t), "detections": dets}))]
    if isinstance(msg, DepthFrame):
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
        return [
            (topic + "/exact", DEPTH_EXACT, _dumps({"t": float(msg.t)})),
            (_camera_info_topic(topic), CAMERA_CALIBRATION, cal.SerializeToString()),
            (topic, RAW_IMAGE, img.SerializeToString()),
        ]
    if isinstance(msg, LaserScan):
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
        exact = {
            "t": float(msg.t),
            "angle_increment": _jf(msg.angle_increment),
            "range_max": _jf(msg.range_max),
            "dtype": ranges.dtype.name,
        }
        return [
            (topic + "/exact", SCAN_EXACT, _dumps(exact)),
            (topic, LASER_SCAN, scan.SerializeToString()),
        ]
    if isinstance(msg, GroundTruthPose):
        pose = PoseInFrame(frame_id="world")
        pose.pose.position.x, pose.pose.position.y = float(msg.x), float(msg.y)
        pose.pose.orientation.z = math.sin(msg.theta / 2.0)
        pose.pose.orientation.w = math.cos(msg.theta / 2.0)
        _stamp(ns, pose)
        exact = {"t": float(msg.t), "theta": _jf(msg.theta)}
        return [
            (topic + "/exact", POSE_EXACT, _dumps(exact)),
            (topic, POSE_IN_FRAME, pose.SerializeToString()),
        ]
    raise TypeError(f"cannot log a {type(msg).__name__}")


# --------------------------------------------------------------------------- writer


def _best_compression() -> CompressionType:
    for kind, module in ((CompressionType.ZSTD, "zstandard"), (CompressionType.LZ4, "lz4")):
        try:
            __import__(module)
            return kind
        except ImportError:
            pass
    return CompressionType.NONE


class LogWriter:
    """Writes a trial log; crash-safe (see the module docstring) and thread-safe.

    `message_count` counts messages written, `flushed_count` those handed to the OS by the
    last flush (what survives if the process is killed now).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        calibration: WalkerCalibration,
        metadata: dict[str, dict[str, Any]] | None = None,
        attachments: dict[str, bytes] | None = None,
        *,
        flush_interval_s: float = FLUSH_INTERVAL_S,
        fsync: bool = False,
        background_flush: bool = True,
    ) -> None:
        self.path = Path(path)
        self.message_count = 0
        self.flushed_count = 0
        self._interval = flush_interval_s
        self._fsync = fsync
        records = [("calibration", _dumps(calibration.to_dict()))]
        for name, d in (metadata or {}).items():
            if name == "calibration":
                raise ValueError("metadata name 'calibration' is reserved")
            try:
                records.append((name, _dumps(d)))
            except (TypeError, ValueError) as e:
                raise ValueError(f"metadata {name!r} is not strict JSON: {e}") from None
        self._file = open(self.path, "wb")
        self._mcap = Writer(self._file, compression=_best_compression())
        self._mcap.start(profile="", library=f"{FORMAT} ({LIBRARY_IDENTIFIER})")
        for name, data in records:
            self._mcap.add_metadata(name, {"json": data.decode()})
        for name, blob in (attachments or {}).items():
            self._mcap.add_attachment(0, 0, name, "application/octet-stream", bytes(blob))
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}  # topic -> (channel id, schema name)
        self._sequence: dict[int, int] = {}
        self._lock = threading.Lock()
        self._closed = False
        self._last_flush = time.monotonic()
        self._unflushed_t0: float | None = None  # log time of the first unflushed message
        self._flush_locked()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if background_flush:
            self._thread = threading.Thread(target=self._flush_loop, name="LogWriter", daemon=True)
            self._thread.start()

    def write(self, msg: Message, topic: str | None = None, log_time: float | None = None) -> None:
        """Log one message on `topic` (default: the type's topic, see TOPICS).

        log_time [s]: when the message was recorded, default its own time `t`. A live
        recorder gives the time it handed the message to the pipeline (never earlier
        than t), so a replay, which reads in log-time order, feeds the messages in the
        order the live run did."""
        if type(msg) not in TOPICS:
            raise TypeError(f"cannot log a {type(msg).__name__}")
        topic = topic or TOPICS[type(msg)]
        ns = _ns(msg.t)
        log_ns = ns if log_time is None else _ns(log_time)
        parts = encode_parts(msg, topic, ns)  # encode outside the lock
        with self._lock:
            if self._closed:
                raise ValueError(f"{self.path}: log writer is closed")
            channels = [self._channel(part_topic, schema, topic) for part_topic, schema, _ in parts]
            for channel, (_, _, data) in zip(channels, parts, strict=True):
                seq = self._sequence[channel] = (self._sequence[channel] + 1) & 0xFFFFFFFF
                self._mcap.add_message(channel, log_ns, data, ns, seq)
            self.message_count += 1
            t = float(msg.t)
            if self._unflushed_t0 is None:
                self._unflushed_t0 = t
            if (
                abs(t - self._unflushed_t0) >= self._interval
                or time.monotonic() - self._last_flush >= self._interval
            ):
                self._flush_locked()

    def flush(self) -> None:
        """Close the current chunk and hand everything written so far to the OS."""
        with self._lock:
            if not self._closed:
                self._flush_locked()

    def close(self) -> None:
        """Flush, write the summary and footer, and close the file. Idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        with self._lock:
            if self._closed:
                return
            self._closed = True
            try:
                self._mcap.finish()
                self._file.flush()
                if self._fsync:
                    os.fsync(self._file.fileno())
                self.flushed_count = self.message_count
            finally:
                self._file.close()

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _channel(self, topic: str, schema: _Schema, main_topic: str) -> int:
        known = self._channels.get(topic)
        if known is not None:
            if known[1] != schema.name:
                raise ValueError(f"topic {topic!r} holds {known[1]}, cannot write {schema.name}")
            return known[0]
        if schema.name not in self._schemas:
            self._schemas[schema.name] = self._mcap.register_schema(
                schema.name, schema.encoding, schema.data
            )
        meta = {} if topic == main_topic else {"main_topic": main_topic}
        channel = self._mcap.register_channel(
            topic, schema.message_encoding, self._schemas[schema.name], meta
        )
        self._channels[topic] = (channel, schema.name)
        self._sequence[channel] = 0
        return channel

    def _flush_locked(self) -> None:
        self._mcap.flush()  # finishes the chunk and flushes the Python file object
        if self._fsync:
            os.fsync(self._file.fileno())
        self.flushed_count = self.message_count
        self._last_flush = time.monotonic()
        self._unflushed_t0 = None

    def _flush_loop(self) -> None:
        while not self._stop.wait(self._interval / 5):
            with self._lock:
                if (
                    not self._closed
                    and self.flushed_count < self.message_count
                    and time.monotonic() - self._last_flush >= self._interval
                ):
                    self._flush_locked()


# --------------------------------------------------------------------------- decoding


class _Skip(Exception):
    """A message the replayer cannot represent; its topic is skipped with a warning."""


Companions = dict[str, tuple[int, Any]]  # schema name -> (log time ns, decoded payload)


def _exact(comp: Companions, schema: _Schema, ns: int) -> dict[str, Any] | None:
    """The exact companion written with the main message at `ns`, consumed."""
    entry = comp.pop(schema.name, None)
    return entry[1] if entry is not None and entry[0] == ns else None


def _flat_parser(cls: type) -> Callable[[bytes], Message]:
    """JSON bytes → the flat message itself, typed by msgspec (fields required; a float
    field also takes "NaN", "Infinity", "-Infinity" and integers; extra fields ignored)."""
    return msgspec.json.Decoder(cls, strict=False).decode


def _built(msg: Message, ns: int, comp: Companions) -> Message:
    return msg


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


def _dec_depth(img: Any, ns: int, comp: Companions) -> DepthFrame:
    if img.encoding != "16UC1":
        raise _Skip(f"image encoding {img.encoding!r} is not 16UC1 depth")
    if CAMERA_CALIBRATION.name not in comp:
        raise _Skip("no camera_info before the image")
    cal = comp[CAMERA_CALIBRATION.name][1]
    k = CameraIntrinsics(cal.width, cal.height, cal.K[0], cal.K[4], cal.K[2], cal.K[5])
    rows = np.frombuffer(img.data, dtype="<u2").reshape(img.height, img.step // 2)
    exact = _exact(comp, DEPTH_EXACT, ns)
    t = exact["t"] if exact else img.timestamp.ToNanoseconds() / 1e9
    return DepthFrame(float(t), rows[:, : img.width].astype(np.uint16, copy=False), k)


def _dec_scan(scan: Any, ns: int, comp: Companions) -> LaserScan:
    n = len(scan.ranges)
    ex = _exact(comp, SCAN_EXACT, ns) or {
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


def _dec_pose(pose: Any, ns: int, comp: Companions) -> GroundTruthPose:
    q = pose.pose.orientation
    ex = _exact(comp, POSE_EXACT, ns) or {
        "t": pose.timestamp.ToNanoseconds() / 1e9,
        "theta": 2.0 * math.atan2(q.z, q.w),
    }
    p = pose.pose.position
    return GroundTruthPose(float(ex["t"]), p.x, p.y, float(ex["theta"]))


@dataclass(frozen=True)
class _Reader:
    """How to read one schema: parse bytes, then (main only) build the message."""

    schema: _Schema
    parse: Callable[[bytes], Any]
    build: Callable[[Any, int, Companions], Message] | None = None  # None: a companion
    cls: type | None = None


_READERS: dict[str, _Reader] = {
    r.schema.name: r
    for r in (
        *(_Reader(_FLAT_SCHEMAS[c], _flat_parser(c), _built, c) for c in _FLAT),
        _Reader(TAG_DETECTIONS, msgspec.json.decode, _dec_tags, TagDetections),
        _Reader(RAW_IMAGE, RawImage.FromString, _dec_depth, DepthFrame),
        _Reader(LASER_SCAN, PbLaserScan.FromString, _dec_scan, LaserScan),
        _Reader(POSE_IN_FRAME, PoseInFrame.FromString, _dec_pose, GroundTruthPose),
        _Reader(CAMERA_CALIBRATION, CameraCalibration.FromString),
        _Reader(DEPTH_EXACT, msgspec.json.decode),
        _Reader(SCAN_EXACT, msgspec.json.decode),
        _Reader(POSE_EXACT, msgspec.json.decode),
    )
}


# --------------------------------------------------------------------------- reader


@dataclass
class _Block:
    """A chunk (or an unchunked message record) in the data section, in file order."""

    offset: int
    start_ns: int
    end_ns: int
    channels: frozenset[int]


@dataclass
class _Role:
    main_topic: str
    reader: _Reader


def _record_stream(body: bytes) -> ReadDataStream:
    return ReadDataStream(io.BytesIO(body))


_CHUNK_HEAD = struct.Struct("<QQQII")  # start, end, uncompressed size, CRC, len(compression)
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, length
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time


_Record = tuple[int, int, bytes]  # a message record: (log time ns, channel id, data)


def _chunk_records(body: bytes, validate: bool) -> tuple[list[_Record], list[Any]]:
    """(messages, schema and channel records) of a chunk (MCAP spec layout), parsed with
    struct: message records are fixed-layout and by far the most numerous, so this is much
    faster than the generic record reader, which is kept for the rare schema and channel
    records. Messages come as plain tuples, in file order."""
    _, _, usize, crc, clen = _CHUNK_HEAD.unpack_from(body, 0)
    pos = _CHUNK_HEAD.size
    compression = body[pos : pos + clen].decode()
    (dlen,) = struct.unpack_from("<Q", body, pos + clen)
    pos += clen + 8
    data = body[pos : pos + dlen]
    if len(data) != dlen:
        raise ValueError("truncated chunk")
    if compression == "zstd":
        data = zstandard.decompress(data, usize)
    elif compression == "lz4":
        data = lz4.frame.decompress(data)
    elif compression:
        raise ValueError(f"unsupported chunk compression {compression!r}")
    if validate and crc and zlib.crc32(data) != crc:
        raise ValueError("chunk CRC mismatch")
    messages: list[_Record] = []
    others: list[Any] = []
    record_head, message_head = _RECORD_HEAD.unpack_from, _MESSAGE_HEAD.unpack_from
    head, mhead = _RECORD_HEAD.size, _MESSAGE_HEAD.size
    pos, n = 0, len(data)
    while pos < n:
        opcode, length = record_head(data, pos)
        pos += head
        end = pos + length
        if end > n:
            raise ValueError("truncated record in chunk")
        if opcode == Opcode.MESSAGE:
            channel, _, log_ns, _ = message_head(data, pos)
            messages.append((log_ns, channel, data[pos + mhead : end]))
        elif opcode == Opcode.SCHEMA:
            others.append(Schema.read(_record_stream(data[pos:end])))
        elif opcode == Opcode.CHANNEL:
            others.append(Channel.read(_record_stream(data[pos:end])))
        pos = end
    return messages, others


def _messages_in(opcode: int, body: bytes, validate: bool = False) -> tuple[list[_Record], list]:
    """(messages, schema and channel records) of a chunk or an unchunked message record."""
    if opcode == Opcode.CHUNK:
        return _chunk_records(body, validate)
    rec = McapMessage.read(_record_stream(body), len(body))
    return [(rec.log_time, rec.channel_id, rec.data)], []


class TrialLog:
    """A trial log opened for replay: calibration, metadata, attachments and messages; a
    message source (`hardware.source.Source`).

    Opening scans the whole file once (without needing its summary), so problems are
    reported here: `LogError` for files that cannot be used, `LogRecoveryWarning` for a
    truncated or corrupt file, `UnsupportedChannelWarning` for channels it skips.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.metadata: dict[str, dict[str, Any]] = {}
        self.attachments: dict[str, bytes] = {}
        self.complete = False  # False: truncated or corrupt, read up to the damage
        self._blocks: list[_Block] = []
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        self._counts: dict[int, list[int]] = {}  # channel -> [count, first ns, last ns]
        problem = self._scan()
        raw_cal = self.metadata.pop("calibration", None)
        if raw_cal is None:
            self._fail(
                f"truncated at byte {problem[0]} before the calibration record"
                if problem
                else "no calibration record"
            )
        try:
            self.calibration = WalkerCalibration.from_dict(raw_cal)
        except (TypeError, ValueError) as e:
            self._fail(f"invalid calibration record: {e}")
        self._roles: dict[int, _Role] = {}
        #: readable topics -> message type
        self.topics: dict[str, type] = {}
        self._classify()
        counts = [
            self._counts[c] for c, r in self._roles.items() if r.reader.build and c in self._counts
        ]
        #: number of messages (companions not counted)
        self.message_count = sum(c[0] for c in counts)
        #: (first, last) log time [s], None if there are no messages
        self.time_range = (
            (min(c[1] for c in counts) / 1e9, max(c[2] for c in counts) / 1e9) if counts else None
        )
        if problem:
            offset, what = problem
            if self.message_count == 0:
                self._fail(f"{what} at byte {offset} before any message")
            first, last = self.time_range or (0.0, 0.0)
            hint = " (writer killed or still writing?)" if what == "truncated" else ""
            warnings.warn(
                LogRecoveryWarning(
                    f"{self.path.name}: {what} at byte {offset}{hint}; recovered "
                    f"{self.message_count} messages spanning {last - first:.3f} s "
                    f"(log time {first:.3f} to {last:.3f} s)"
                ),
                stacklevel=3,
            )

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[Message]:
        """Messages on `topics` (default all readable ones) in log-time order."""
        wanted = None if topics is None else set(topics)
        channels = {c for c, r in self._roles.items() if wanted is None or r.main_topic in wanted}
        state: dict[str, Companions] = {}
        skipped: set[str] = set()
        for ns, channel, data in self._records(channels):
            role = self._roles[channel]
            if role.main_topic in skipped:
                continue
            comp = state.setdefault(role.main_topic, {})
            try:
                payload = role.reader.parse(data)
                if role.reader.build is None:
                    comp[role.reader.schema.name] = (ns, payload)
                    continue
                msg = role.reader.build(payload, ns, comp)
            except _Skip as e:
                skipped.add(role.main_topic)
                warnings.warn(
                    UnsupportedChannelWarning(
                        f"{self.path.name}: skipping {role.main_topic!r}: {e}"
                    ),
                    stacklevel=2,
                )
                continue
            except Exception as e:
                topic = self._channels[channel].topic
                self._fail(f"cannot decode the message on {topic!r} at {ns} ns: {e!r}")
            yield msg

    def __iter__(self) -> Iterator[Message]:
        return self.messages()

    def close(self) -> None:
        """Nothing to release: every `messages()` iteration opens the file itself."""

    # -- scanning

    def _fail(self, what: str) -> NoReturn:
        raise LogError(f"{self.path}: {what}")

    def _open(self) -> io.BufferedReader:
        try:
            return open(self.path, "rb")
        except FileNotFoundError:
            self._fail("no such file")
        except IsADirectoryError:
            self._fail("is a directory, not a log file")
        except PermissionError:
            self._fail("permission denied")
        except OSError as e:
            self._fail(f"cannot open: {e.strerror}")

    def _scan(self) -> tuple[int, str] | None:
        """Read the data section; (byte offset, what) of the first damage, None if intact."""
        with self._open() as f:
            try:
                size = os.fstat(f.fileno()).st_size
                magic = f.read(len(MAGIC))
            except OSError as e:
                self._fail(f"cannot read: {e.strerror}")
            if not magic:
                self._fail("empty file (0 bytes)")
            if magic != MAGIC:
                if MAGIC.startswith(magic):
                    self._fail(f"truncated in the header ({size} bytes)")
                self._fail(f"not an MCAP file (starts with {magic!r})")
            offset = len(MAGIC)
            seen_header = False
            while True:
                head = f.read(9)
                if len(head) < 9:
                    what = "truncated"
                    break
                opcode, length = struct.unpack("<BQ", head)
                if length > size - offset - 9:
                    what = "truncated"
                    break
                body = f.read(length)
                try:
                    if not seen_header:
                        if opcode != Opcode.HEADER:
                            self._fail("not an MCAP file (no header record)")
                        Header.read(_record_stream(body))
                        seen_header = True
                    elif opcode in (Opcode.CHUNK, Opcode.MESSAGE):
                        self._scan_block(offset, opcode, body)
                    elif opcode == Opcode.SCHEMA:
                        schema = Schema.read(_record_stream(body))
                        self._schemas[schema.id] = schema
                    elif opcode == Opcode.CHANNEL:
                        channel = Channel.read(_record_stream(body))
                        self._channels[channel.id] = channel
                    elif opcode == Opcode.METADATA:
                        self._add_metadata(Metadata.read(_record_stream(body)))
                    elif opcode == Opcode.ATTACHMENT:
                        att = Attachment.read(_record_stream(body))
                        self.attachments[att.name] = att.data
                    elif opcode in (Opcode.DATA_END, Opcode.FOOTER):
                        self.complete = True
                        return None
                except LogError:
                    raise
                except Exception:
                    what = f"corrupt {_opcode_name(opcode)} record"
                    break
                offset += 9 + length
            if not seen_header:
                self._fail(f"truncated in the header ({size} bytes)")
            return offset, what

    def _scan_block(self, offset: int, opcode: int, body: bytes) -> None:
        messages, others = _messages_in(opcode, body, validate=True)
        for rec in others:
            if isinstance(rec, Schema):
                self._schemas[rec.id] = rec
            else:
                self._channels[rec.id] = rec
        if not messages:
            return
        per_channel: dict[int, list[int]] = {}
        for ns, c, _ in messages:
            per_channel.setdefault(c, []).append(ns)
        for c, times in per_channel.items():
            stats = self._counts.setdefault(c, [0, times[0], times[0]])
            stats[0] += len(times)
            stats[1], stats[2] = min(stats[1], *times), max(stats[2], *times)
        start = min(ns for ns, _, _ in messages)
        end = max(ns for ns, _, _ in messages)
        self._blocks.append(_Block(offset, start, end, frozenset(per_channel)))

    def _add_metadata(self, record: Metadata) -> None:
        if set(record.metadata) == {"json"}:
            try:
                self.metadata[record.name] = json.loads(record.metadata["json"])
            except ValueError as e:
                self._fail(f"metadata record {record.name!r} is not JSON: {e}")
        else:
            self.metadata[record.name] = dict(record.metadata)

    def _classify(self) -> None:
        for cid, channel in sorted(self._channels.items()):
            schema = self._schemas.get(channel.schema_id)
            reader = _READERS.get(schema.name) if schema else None
            main = channel.topic if reader and reader.build else channel.metadata.get("main_topic")
            if (
                reader is None
                or schema is None
                or (schema.encoding, channel.message_encoding)
                != (reader.schema.encoding, reader.schema.message_encoding)
                or not main
            ):
                name = schema.name if schema else "(none)"
                warnings.warn(
                    UnsupportedChannelWarning(
                        f"{self.path.name}: skipping channel {channel.topic!r} with unsupported "
                        f"schema {name!r} ({channel.message_encoding})"
                    ),
                    stacklevel=4,
                )
                continue
            self._roles[cid] = _Role(main, reader)
            if reader.cls is not None:
                self.topics[main] = reader.cls

    def _records(self, channels: set[int]) -> Iterator[tuple[int, int, bytes]]:
        """(log time, channel, data) of the messages on `channels`, in log-time order
        (ties in file order)."""
        blocks = [b for b in self._blocks if b.channels & channels]
        disjoint = all(a.end_ns <= b.start_ns for a, b in itertools.pairwise(blocks))
        with self._open() as f:
            if disjoint:
                # Blocks follow each other in time (a recorder writes them so): a stable
                # sort within each block is the global order.
                for block in blocks:
                    recs = [r for r in self._read_block(f, block) if r[1] in channels]
                    recs.sort(key=_log_time)
                    yield from recs
                return
            heap: list[tuple[int, int, int, Any]] = [(b.start_ns, b.offset, -1, b) for b in blocks]
            heapq.heapify(heap)
            while heap:
                _, offset, index, item = heapq.heappop(heap)
                if index >= 0:
                    yield item
                    continue
                for i, rec in enumerate(self._read_block(f, item)):
                    if rec[1] in channels:
                        heapq.heappush(heap, (rec[0], offset, i, rec))

    def _read_block(self, f: io.BufferedReader, block: _Block) -> list[_Record]:
        try:
            f.seek(block.offset)
            opcode, length = struct.unpack("<BQ", f.read(9))
            return _messages_in(opcode, f.read(length))[0]
        except Exception as e:
            self._fail(f"changed or unreadable while replaying (byte {block.offset}): {e!r}")


def _log_time(record: _Record) -> int:
    return record[0]


def _opcode_name(opcode: int) -> str:
    try:
        return Opcode(opcode).name.lower()
    except ValueError:
        return f"opcode-{opcode:#x}"


def read_log(path: str | os.PathLike[str]) -> TrialLog:
    """Open a trial log for replay (see TrialLog)."""
    return TrialLog(path)


LogReader = TrialLog  # alias


def replay(path: str | os.PathLike[str], topics: Iterable[str] | None = None) -> Iterator[Message]:
    """All messages of a trial log (or those on `topics`) in log-time order."""
    yield from read_log(path).messages(topics)
