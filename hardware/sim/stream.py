"""The simulated walker's sensors as a live device: a framed stream over a Unix socket.

`walkerslam live --sim` runs the simulated walker in a process of its own
(`hardware.sim.live_world`), as the real walker is a machine of its own: its board is
reached through a serial port (the board emulator's pty, or the firmware in simavr) and
its cameras through this stream, which carries the depth frames and tag detections the
simulated cameras produce, and the simulator's truth (ground-truth poses, collisions) so
that a recording can be scored like a simulated trial.

Wire format: a sequence of records, each `!II` (header length, payload length), a JSON
header (UTF-8, strict JSON) and a binary payload. Headers have a "type":

    hello      calibration (WalkerCalibration.to_dict()), metadata ({name: dict}); first
    depth      t, intrinsics {width, height, fx, fy, cx, cy}; payload uint16 LE, row-major
    tags       t, detections [{tag_id, camera_T_tag (16), corners_px (8), decision_margin}]
    truth      t, x, y, theta
    collision  t, kind, obstacle, x, y
    end        finished (the user completed the route), t

After hello the walker waits for the three bytes `go\n` from the reader: it starts
walking when the live process starts reading, not while it is still setting up.
Times are CLOCK_MONOTONIC seconds (`time.monotonic()`, shared by every process of the
machine); the receiving device maps them onto the run's host clock. Floats are JSON
numbers (exact round trip); non-finite numbers are not used by these messages except a
tag's unknown decision margin, sent as null.
"""

from __future__ import annotations

import json
import socket
import struct
import threading
from collections.abc import Iterator
from typing import Any

import numpy as np

from hardware.calibration import WalkerCalibration
from hardware.clock import HostClock
from hardware.errors import DeviceError
from hardware.messages import (
    CameraIntrinsics,
    Collision,
    DepthFrame,
    GroundTruthPose,
    Message,
    TagDetection,
    TagDetections,
)

_HEAD = struct.Struct("!II")
MAX_HEADER = 1 << 20
MAX_PAYLOAD = 64 << 20


class StreamError(DeviceError):
    """The sensor stream is broken (bad framing, unknown record); one line."""


def encode(msg: Message, t_mono: float) -> bytes:
    """One record for a message whose time on CLOCK_MONOTONIC is `t_mono`."""
    payload = b""
    if isinstance(msg, DepthFrame):
        k = msg.intrinsics
        head: dict[str, Any] = {
            "type": "depth",
            "intrinsics": {
                "width": k.width,
                "height": k.height,
                "fx": k.fx,
                "fy": k.fy,
                "cx": k.cx,
                "cy": k.cy,
            },
        }
        payload = np.ascontiguousarray(msg.depth_mm, dtype="<u2").tobytes()
    elif isinstance(msg, TagDetections):
        head = {
            "type": "tags",
            "detections": [
                {
                    "tag_id": int(d.tag_id),
                    "camera_T_tag": np.asarray(d.camera_T_tag, float).ravel().tolist(),
                    "corners_px": np.asarray(d.corners_px, float).ravel().tolist(),
                    "decision_margin": (
                        float(d.decision_margin) if np.isfinite(d.decision_margin) else None
                    ),
                }
                for d in msg.detections
            ],
        }
    elif isinstance(msg, GroundTruthPose):
        head = {"type": "truth", "x": msg.x, "y": msg.y, "theta": msg.theta}
    elif isinstance(msg, Collision):
        head = {"type": "collision", "kind": msg.kind, "obstacle": msg.obstacle}
        head.update(x=msg.x, y=msg.y)
    else:
        raise TypeError(f"the sensor stream does not carry {type(msg).__name__}")
    head["t"] = float(t_mono)
    return record(head, payload)


def record(head: dict[str, Any], payload: bytes = b"") -> bytes:
    data = json.dumps(head, separators=(",", ":"), allow_nan=False).encode()
    return _HEAD.pack(len(data), len(payload)) + data + payload


def decode(head: dict[str, Any], payload: bytes, t: float) -> Message:
    """A record (other than hello/end) as a message at time `t` (the host clock's)."""
    kind = head.get("type")
    if kind == "depth":
        k = CameraIntrinsics(**head["intrinsics"])
        expected = 2 * k.width * k.height
        if len(payload) != expected:
            raise StreamError(f"depth payload of {len(payload)} bytes, expected {expected}")
        depth = np.frombuffer(payload, dtype="<u2").reshape(k.height, k.width)
        return DepthFrame(t, depth.astype(np.uint16, copy=False), k)
    if kind == "tags":
        dets = tuple(
            TagDetection(
                int(d["tag_id"]),
                np.array(d["camera_T_tag"], float).reshape(4, 4),
                np.array(d["corners_px"], float).reshape(4, 2),
                float("nan") if d["decision_margin"] is None else float(d["decision_margin"]),
            )
            for d in head["detections"]
        )
        return TagDetections(t, dets)
    if kind == "truth":
        return GroundTruthPose(t, float(head["x"]), float(head["y"]), float(head["theta"]))
    if kind == "collision":
        return Collision(t, head["kind"], head["obstacle"], float(head["x"]), float(head["y"]))
    raise StreamError(f"unknown sensor stream record {kind!r}")


class RecordReader:
    """Reads records from a connected socket; `read()` → (header, payload) or None at EOF."""

    def __init__(self, sock: socket.socket) -> None:
        self._file = sock.makefile("rb")

    def _exact(self, n: int) -> bytes | None:
        data = self._file.read(n)
        if not data:
            return None
        if len(data) != n:
            raise StreamError(f"sensor stream cut inside a record ({len(data)} of {n} bytes)")
        return data

    def read(self) -> tuple[dict[str, Any], bytes] | None:
        raw = self._exact(_HEAD.size)
        if raw is None:
            return None
        hlen, plen = _HEAD.unpack(raw)
        if hlen > MAX_HEADER or plen > MAX_PAYLOAD:
            raise StreamError(f"sensor stream record too large ({hlen} + {plen} bytes)")
        head_bytes = self._exact(hlen) or b""
        payload = self._exact(plen) if plen else b""
        try:
            head = json.loads(head_bytes)
        except ValueError as e:
            raise StreamError(f"sensor stream header is not JSON: {e}") from None
        return head, payload or b""


class SimSensors:
    """The simulated walker's cameras and truth, read from its stream socket: a live
    device (hardware.source.Source) whose messages are stamped on the run's clock."""

    device = "sim"

    def __init__(self, socket_path: str, clock: HostClock, timeout_s: float = 10.0) -> None:
        self.socket_path = socket_path
        self.clock = clock
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._sock.settimeout(timeout_s)
        try:
            self._sock.connect(socket_path)
        except OSError as e:
            self._sock.close()
            raise StreamError(
                f"{socket_path}: cannot connect to the simulated walker: {e}"
            ) from None
        self._reader = RecordReader(self._sock)
        hello = self._reader.read()
        if hello is None or hello[0].get("type") != "hello":
            raise StreamError(f"{socket_path}: the simulated walker did not say hello")
        self._sock.settimeout(None)
        self.calibration = WalkerCalibration.from_dict(hello[0]["calibration"])
        self.metadata: dict[str, Any] = hello[0]["metadata"]
        self.finished: bool | None = None  # set by the end record
        self._closed = threading.Event()

    def messages(self) -> Iterator[Message]:
        """The stream; the simulated walker starts walking when this starts reading."""
        try:
            self._sock.sendall(b"go\n")
        except OSError as e:
            raise StreamError(f"{self.socket_path}: the simulated walker went away: {e}") from None
        while not self._closed.is_set():
            try:
                rec = self._reader.read()
            except (OSError, ValueError):
                if self._closed.is_set():
                    return
                raise
            if rec is None:
                return
            head, payload = rec
            if head.get("type") == "end":
                self.finished = bool(head.get("finished"))
                return
            yield decode(head, payload, self.clock.to_host(float(head["t"])))

    def close(self) -> None:
        self._closed.set()
        try:
            self._sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._sock.close()
