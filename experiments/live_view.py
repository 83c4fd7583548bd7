"""A live view of a run in Foxglove, over the Foxglove WebSocket protocol (foxglove-sdk).

`FoxgloveView` starts a WebSocket server that the Foxglove app connects to (Open
connection → Foxglove WebSocket → ws://HOST:PORT; `view.url`, `view.app_url()`) and
publishes what a run sees and what the SLAM pipeline makes of it. `view.observer(pipeline)`
attaches it to either loop:

    # a replay: an observer of experiments.drag.Observed, like the drag metrics
    obs = view.observer(pipeline, realtime=True)    # paced to the messages' times
    pipeline.run(Observed(trial.messages(), [..., obs]))
    obs.finish()                                    # the final pose, path and map

    # the closed loop (live, simulation): its record and on_command callbacks
    obs = view.observer(pipeline)
    run_closed_loop(source, sink, pipeline, ctl, loop,
                    record=obs.record, on_command=obs.on_command)

or, in any loop of one's own, `view.observe(pipeline, msg)` after each
`pipeline.feed(msg)`. `view.close()` stops the server.

Topics. Every `hardware.messages` message goes out exactly as the trial log stores it
(`hardware.log`: same topics, schemas, payloads and frame ids, companion channels
included), so a live view and a recorded log look alike in Foxglove:

    /encoders /brakes/command /range_bearing /odometry/velocity /imu/gyro /collisions
    /events
    /tags/detections /range_bearings   json (walker.* JSON schemas)
    /depth/image                foxglove.RawImage 16UC1, frame "depth_optical"
    /depth/camera_info          foxglove.CameraCalibration
    /scan                       foxglove.LaserScan, frame "walker"
    /groundtruth/pose           foxglove.PoseInFrame, frame "world"
    (+ the log's "/exact" companions)

and, for the view only:

    /slam/pose                  foxglove.PoseInFrame     the localizer's pose, frame "world"
    /slam/estimate              json walker.PoseEstimate t, x, y, theta, covariance
                                                         (3×3 row-major, x y θ)
    /slam/pose/uncertainty      foxglove.SceneUpdate     95 % position ellipse and the
                                                         heading's ±2σ, frame "world"
    /slam/trajectory            foxglove.PosesInFrame    the localizer's trajectory
    /map                        foxglove.Grid            the occupancy map, frame "world"
    /map/reference              foxglove.Grid            the same frames mapped at the true
                                                         poses (when the pipeline has one)
    /tags/scene                 foxglove.SceneUpdate     a square and the ID of each
                                                         detected tag, frame "tag_optical"
    /tf                         foxglove.FrameTransforms world → walker (the localizer's
                                                         pose), walker → depth_optical and
                                                         walker → tag_optical (the mounts)

Grid cells (cell_stride 5): "occupancy" int8 at offset 0 (−1 unknown, else round(100·p),
p the occupancy probability; ROS's map convention) and "red", "green", "blue", "alpha"
uint8 at 1–4 (grey 255·(1 − p), transparent where unknown), so the 3D panel shows the
map in its "RGBA (separate fields)" colour mode. Row 0 is the lowest y; the grid's pose
is the world (x, y) of its lower-left corner (the mapper's `origin`). A grid larger than
`ViewConfig.grid_max_cells` is sent coarser: k×k blocks (k the least integer that fits)
pooled by the maximum occupancy, so an obstacle cell is never lost (cell size k·res).

Times: message timestamps are round(t·1e9) ns of the messages' own `t` (the run's
clock), as in the trial log; the log time (the frame header's timestamp) is the latest
`t` so far, never going back, like the log time a live recorder writes (`FeedOrder`), so
a client sees time advance even when a device delivers late.

Cost per call in the caller's thread, one Foxglove client in another process subscribed
to everything (the shared 2-core development machine, another job using one core;
back-to-back calls / calls spaced as in a run, where each also waits for the woken SDK
and client threads):

    depth frame 160×120          0.07–0.13 ms / 0.9 ms     no client: 2 µs (not encoded)
    depth frame 640×480          0.6–1.0 ms / 1.9–2.4 ms
    brake command (JSON)         11–30 µs / 0.1 ms
    pose + /slam/estimate + uncertainty + /tf       0.3–0.4 ms / 1.6–2.2 ms
    trajectory 2000 poses        2.4–2.8 ms / 4.1–4.6 ms (+ the localizer's trajectory())
    map 200×200 / 400×400 cells  1.0–1.8 ms / 1.3–5.4 ms
    map 1000×1000 / 2000×2000    6.5–23 ms / 44–59 ms (sent as 500×500 / 667×667 cells)
    background=True, a depth frame: ~1 µs to queue (the worker then pays the above)

A whole replay (40 s simulated trial, 5205 messages, dead reckoning at ~120× real
time): 0.35 s with the view and no client (0.33 s without), 0.76 s with a client
subscribed to everything.

So what costs is throttled: the map (≤ 2 Hz), the trajectory (≤ 1 Hz; at most 2000
poses, evenly thinned), the pose (≤ 20 Hz) and the depth image (≤ 15 Hz: a 640×480
stream at 30 Hz is 18 MB/s through the socket and the client); every other message is
published as it comes. Each limit holds in wall time and in run time (`ViewConfig`), so a
fast replay pays at most the limits per wall second and a real-time one shows every state
they allow; and the map and the trajectory back off further when they are expensive
(`busy_fraction`: at most ~2 % of the caller's time each). A channel nobody subscribes
to costs nothing (nothing is encoded, the localizer is not asked). Sending happens on the
SDK's threads; a client that falls behind loses its oldest messages (the SDK's
per-client backlog) instead of slowing the caller. For a live loop, `background=True`
takes the messages' encoding off the frame-to-command path (it still shares the GIL, so
the worker's ~0.2–1 ms per 640×480 frame can delay the loop's Python by as much).

What the view reads from the pipeline never changes its results: the localizer's
`estimate()` and `trajectory()` are only called right after an odometry message, depth
frame or scan, or right after the closed loop asked for the pose of a command, where the
pipeline or the localizer has already folded in the observations it held (FastSLAM
folds the observations of one time together; asking it between two of them would split
the batch and change its path); the map is only read. The localizers' `landmarks()` is
not called for the same reason (EKF-SLAM's would sync its state).
"""

from __future__ import annotations

import contextlib
import json
import math
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any

import foxglove
import numpy as np
from foxglove.channels import (
    FrameTransformsChannel,
    GridChannel,
    PoseInFrameChannel,
    PosesInFrameChannel,
    SceneUpdateChannel,
)
from foxglove.messages import (
    Color,
    CubePrimitive,
    FrameTransform,
    FrameTransforms,
    Grid,
    LinePrimitive,
    LinePrimitiveLineType,
    PackedElementField,
    PackedElementFieldNumericType,
    Point3,
    Pose,
    PoseInFrame,
    PosesInFrame,
    Quaternion,
    SceneEntity,
    SceneEntityDeletion,
    SceneEntityDeletionType,
    SceneUpdate,
    TextPrimitive,
    Timestamp,
    Vector2,
    Vector3,
)

from experiments.pipeline import Pipeline
from hardware.calibration import WalkerCalibration
from hardware.errors import ConfigError, DeviceError
from hardware.log import TOPICS, encode_parts
from hardware.messages import (
    BrakeCommand,
    CameraIntrinsics,
    DepthFrame,
    EncoderTicks,
    LaserScan,
    Message,
    RangeBearings,
    TagDetections,
    VelocityOdometry,
)
from mapping.grid import GridExtent
from slam.base import PoseEstimate
from slam.trajectory import Trajectory

__all__ = [
    "FRAME_DEPTH",
    "FRAME_TAGS",
    "FRAME_WALKER",
    "FRAME_WORLD",
    "FoxgloveView",
    "RealtimePacer",
    "ViewConfig",
    "ViewError",
    "ViewObserver",
    "grid_cells",
]

FRAME_WORLD = "world"
FRAME_WALKER = "walker"
FRAME_DEPTH = "depth_optical"  # hardware.log's frame of the depth image
FRAME_TAGS = "tag_optical"

# After these the localizer holds no unused observation (see the module docstring).
_STATE_POINTS = (EncoderTicks, VelocityOdometry, DepthFrame, LaserScan)

GRID_CELL_STRIDE = 5
ELLIPSE_95 = math.sqrt(5.991)  # chi-square 95 % radius for two degrees of freedom
_ELLIPSE_SEGMENTS = 48


@dataclass(frozen=True)
class ViewConfig:
    """Publication limits [Hz]; each holds in wall time and in run (message) time.

    pose_hz: the localizer's pose, its uncertainty and /tf.
    trajectory_hz: the localizer's whole trajectory (at most trajectory_max_poses,
        evenly spread, the latest always included).
    grid_hz: the occupancy map(s); grid_max_cells: above it the map is sent pooled.
    depth_hz: depth images (the other messages are all published).
    reference_map: also publish the pipeline's reference map (at the true poses).
    busy_fraction: the trajectory and the map each take at most about this share of the
        caller's wall time: after one that took c seconds the next waits c / busy_fraction
        (a 2000×2000-cell map, ~45 ms, then goes out about every 2 s instead of 2 Hz).
    """

    pose_hz: float = 20.0
    trajectory_hz: float = 1.0
    grid_hz: float = 2.0
    depth_hz: float = 15.0
    trajectory_max_poses: int = 2000
    grid_max_cells: int = 500_000
    reference_map: bool = True
    busy_fraction: float = 0.02

    def __post_init__(self) -> None:
        for name in ("pose_hz", "trajectory_hz", "grid_hz", "depth_hz"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name} must be > 0, got {getattr(self, name)!r}")
        if not 0 < self.busy_fraction <= 1:
            raise ConfigError(f"busy_fraction must be in (0, 1], got {self.busy_fraction!r}")
        if self.trajectory_max_poses < 2 or self.grid_max_cells < 1:
            raise ConfigError("trajectory_max_poses must be >= 2 and grid_max_cells >= 1")


class _Gate:
    """Lets one event through per period, in wall time and in run time alike; after an
    event that took cost_s of the caller's time, the next one waits at least
    cost_s / busy_fraction of wall time, so an expensive stream backs off by itself."""

    def __init__(self, rate_hz: float, busy_fraction: float, clock: Callable[[], float]) -> None:
        self.period = 1.0 / rate_hz
        self.busy_fraction = busy_fraction
        self.clock = clock
        self.wall = -math.inf
        self.hold = self.period
        self.t = -math.inf

    def ready(self, t: float) -> bool:
        # A run clock that went backwards (a new run, a stale message) does not block.
        run_ok = t - self.t >= self.period or t < self.t
        return run_ok and self.clock() - self.wall >= self.hold

    def take(self, t: float, cost_s: float = 0.0) -> None:
        self.wall, self.t = self.clock(), t
        self.hold = max(self.period, cost_s / self.busy_fraction)


def _prototype(cls: type) -> Message | None:
    """Some message of type cls, to learn its channels from the log's encoding (None
    when this does not know how to make one)."""
    if cls is DepthFrame:
        return DepthFrame(0.0, np.zeros((1, 1), np.uint16), CameraIntrinsics(1, 1, 1, 1, 0, 0))
    if cls is LaserScan:
        return LaserScan(0.0, 0.0, 0.0, np.zeros(1), 1.0)
    if cls is TagDetections:
        return TagDetections(0.0)
    if cls is RangeBearings:
        return RangeBearings.of(0.0, [], [], [])
    zero: dict[Any, Any] = {"float": 0.0, "int": 0, "str": "", float: 0.0, int: 0, str: ""}
    try:  # a flat message of numbers and strings
        return cls(**{f.name: zero[f.type] for f in fields(cls)})
    except (KeyError, TypeError, ValueError):
        return None


def _ns(t: float) -> int:
    return round(float(t) * 1e9)


def _stamp(t: float) -> Timestamp:
    sec, nsec = divmod(_ns(t), 1_000_000_000)
    return Timestamp(sec, nsec)


def _jf(x: float) -> float | str:
    """A float as JSON, non-finite ones as the strings the trial log uses."""
    x = float(x)
    if math.isfinite(x):
        return x
    return "NaN" if x != x else ("Infinity" if x > 0 else "-Infinity")


def _yaw_quaternion(theta: float) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(theta / 2.0), w=math.cos(theta / 2.0))


def _planar_pose(x: float, y: float, theta: float) -> Pose:
    return Pose(position=Vector3(x=float(x), y=float(y), z=0.0), orientation=_yaw_quaternion(theta))


def _matrix_quaternion(r: np.ndarray) -> Quaternion:
    """The quaternion (w >= 0) of a 3×3 rotation matrix, from its largest diagonal term."""
    m = np.asarray(r, dtype=float)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0.0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4)
    elif m[0, 0] >= m[1, 1] and m[0, 0] >= m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = (s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s)
    elif m[1, 1] >= m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = ((m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = ((m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s)
    x, y, z, w = (float(v) for v in q)
    if w < 0:
        x, y, z, w = -x, -y, -z, -w
    return Quaternion(x=x, y=y, z=z, w=w)


def _translation(a_T_b: np.ndarray) -> Vector3:
    x, y, z = (float(v) for v in a_T_b[:3, 3])
    return Vector3(x=x, y=y, z=z)


def _transform_pose(a_T_b: np.ndarray) -> Pose:
    return Pose(position=_translation(a_T_b), orientation=_matrix_quaternion(a_T_b[:3, :3]))


def _cell_table() -> np.ndarray:
    """(256, 5) uint8: the /map cell of each occupancy value (as uint8: 255 is −1)."""
    occ = np.arange(256, dtype=np.uint8).view(np.int8).astype(np.int16)
    known = (occ >= 0) & (occ <= 100)
    grey = np.where(known, 255 - (np.clip(occ, 0, 100) * 255 + 50) // 100, 0).astype(np.uint8)
    table = np.empty((256, GRID_CELL_STRIDE), dtype=np.uint8)
    table[:, 0] = np.arange(256)
    table[:, 1] = table[:, 2] = table[:, 3] = grey
    table[:, 4] = np.where(known, 255, 0)
    return table


_CELL_TABLE = _cell_table()


def grid_cells(grid: GridExtent, max_cells: int) -> tuple[np.ndarray, int]:
    """(cells, k): the grid as (rows, cols, 5) uint8 cells of the /map encoding (see the
    module docstring), pooled over k×k blocks when it has more than max_cells cells."""
    ny, nx = grid.shape
    occ = (grid.probability() * 100.0 + 0.5).astype(np.int8)
    occ[~grid.known()] = -1
    k = 1
    if ny * nx > max_cells:
        k = math.ceil(math.sqrt(ny * nx / max_cells))
        while math.ceil(ny / k) * math.ceil(nx / k) > max_cells:
            k += 1
        padded = np.pad(occ, ((0, -ny % k), (0, -nx % k)), constant_values=-1)
        rows = padded[0::k].copy()
        for i in range(1, k):
            np.maximum(rows, padded[i::k], out=rows)
        occ = rows[:, 0::k].copy()
        for i in range(1, k):
            np.maximum(occ, rows[:, i::k], out=occ)
    return np.take(_CELL_TABLE, occ.view(np.uint8), axis=0), k


_GRID_FIELDS = [
    PackedElementField(name="occupancy", offset=0, type=PackedElementFieldNumericType.Int8),
    *(
        PackedElementField(name=name, offset=i + 1, type=PackedElementFieldNumericType.Uint8)
        for i, name in enumerate(("red", "green", "blue", "alpha"))
    ),
]

_ESTIMATE_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "walker.PoseEstimate",
    "description": "The localizer's pose and its covariance. Non-finite numbers are the "
    'strings "NaN", "Infinity", "-Infinity".',
    "type": "object",
    "properties": {
        "t": {"type": "number", "description": "time of the estimate [s]"},
        "x": {"type": "number", "description": "x [m, world]"},
        "y": {"type": "number", "description": "y [m, world]"},
        "theta": {"type": "number", "description": "heading [rad], CCW from world +x"},
        "covariance": {
            "type": "array",
            "description": "3×3 covariance of (x, y, theta), row-major [m², m·rad, rad²]",
            "items": {"type": "number"},
        },
    },
    "required": ["t", "x", "y", "theta", "covariance"],
}


class ViewError(DeviceError):
    """The view's server cannot start (e.g. the port is taken); str() is one line."""


def _start_server(
    context: foxglove.Context, name: str, host: str, port: int, message_backlog: int | None
) -> Any:
    """The Foxglove WebSocket server of `context`, listening; `ViewError` if it cannot."""
    try:
        return foxglove.start_server(
            name=name,
            host=host,
            port=port,
            context=context,
            message_backlog_size=message_backlog,
        )
    except RuntimeError as e:  # the SDK's FoxgloveError, e.g. the port is taken
        raise ViewError(f"cannot serve the Foxglove view on {host}:{port}: {e}") from None


def _gates(config: ViewConfig, clock: Callable[[], float]) -> dict[str, _Gate]:
    """The rate gates of the pose, the trajectory, the map(s) and depth images."""
    rates = (
        ("pose", config.pose_hz),
        ("trajectory", config.trajectory_hz),
        ("grid", config.grid_hz),
        ("depth", config.depth_hz),
    )
    return {name: _Gate(rate, config.busy_fraction, clock) for name, rate in rates}


class FoxgloveView:
    """A Foxglove WebSocket server publishing a run (see the module docstring).

    host/port: where to listen (port 0 picks a free port; `port` is the one it got).
    calibration: the walker's, for the sensor mounts on /tf and the tag size; without it
    the first `observe` takes the pipeline's.
    background: `publish` only queues the message (at most queue_size; when the queue is
    full the message is dropped and counted) and a thread of the view's own encodes and
    sends it, so a live loop's frame-to-command path pays ~1 µs per message instead of
    up to ~1 ms for a 640×480 depth frame (the worker's Python still shares the GIL with
    the loop). The SLAM state is always read and sent in
    the caller's thread (reading it from another thread would race the pipeline).
    The other methods are meant to be called from the thread that runs the pipeline.
    message_backlog: messages the SDK buffers per client (its default 1024); a client
    that falls further behind loses the oldest.
    """

    def __init__(
        self,
        calibration: WalkerCalibration | None = None,
        *,
        host: str = "127.0.0.1",
        port: int = 8765,
        name: str = "walker-slam",
        config: ViewConfig | None = None,
        background: bool = False,
        queue_size: int = 64,
        message_backlog: int | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.calibration = calibration
        self.config = config or ViewConfig()
        #: what was published, and what was not and why ("unsubscribed",
        #: "depth_rate_limited", "queue_full", "not_encodable:<type>", "error:<type>")
        self.counts: dict[str, int] = {}
        #: the last exception a background publish raised (it is counted, not raised)
        self.last_error: BaseException | None = None
        self._lock = threading.Lock()  # counts and the log time, shared with the worker
        self._log_t = 0.0
        self._context = foxglove.Context()
        self._server = _start_server(self._context, name, host, port, message_backlog)
        self._host = host
        self._closed = False
        self._static: dict[str, Any] = self._slam_channels()
        # hardware messages: (type, topic) -> the channels of their parts
        self._parts: dict[tuple[type, str | None], list[foxglove.Channel]] = {}
        self._channels: dict[str, foxglove.Channel] = {}
        self._log_channels()
        self._gates = _gates(self.config, clock)
        self._queue: queue.Queue | None = None
        self._worker: threading.Thread | None = None
        if background:
            self._queue = queue.Queue(maxsize=queue_size)
            self._worker = threading.Thread(target=self._work, name="FoxgloveView", daemon=True)
            self._worker.start()

    def _slam_channels(self) -> dict[str, Any]:
        """Make the channels of the SLAM state (pose, estimate, uncertainty, trajectory,
        maps, tags, /tf); returns them by topic."""
        ctx = self._context
        self._pose = PoseInFrameChannel("/slam/pose", context=ctx)
        self._estimate = foxglove.Channel("/slam/estimate", schema=_ESTIMATE_SCHEMA, context=ctx)
        self._uncertainty = SceneUpdateChannel("/slam/pose/uncertainty", context=ctx)
        self._trajectory = PosesInFrameChannel("/slam/trajectory", context=ctx)
        self._map = GridChannel("/map", context=ctx)
        self._reference = GridChannel("/map/reference", context=ctx)
        self._tags = SceneUpdateChannel("/tags/scene", context=ctx)
        self._tf = FrameTransformsChannel("/tf", context=ctx)
        return {
            ch.topic(): ch
            for ch in (
                self._pose,
                self._estimate,
                self._uncertainty,
                self._trajectory,
                self._map,
                self._reference,
                self._tags,
                self._tf,
            )
        }

    def _log_channels(self) -> None:
        """Make the channels of every message type the log knows, on its own topic.

        They are made now: a channel made while a client is connected is advertised to
        it a moment before the SDK accepts subscriptions to it, and a client that answers
        at once is refused ("Unknown channel ID") and never asks again. Messages on other
        topics get theirs on first use."""
        for cls, main in TOPICS.items():
            proto = _prototype(cls)
            if proto is not None:
                self._parts[(cls, None)] = self._part_channels(encode_parts(proto, main, 0), main)

    # -- server

    @property
    def port(self) -> int:
        """The port the server listens on."""
        return self._server.port

    @property
    def url(self) -> str:
        """ws://host:port, for Foxglove's "Open connection"."""
        return f"ws://{self._host}:{self.port}"

    def app_url(self) -> str | None:
        """A Foxglove web-app link that opens this server (None once closed)."""
        return None if self._closed else self._server.app_url()

    def topics(self) -> list[str]:
        """The topics advertised so far (those of a topic given to `publish` appear with
        its first message)."""
        return sorted({*self._static, *self._channels})

    def is_subscribed(self, topic: str) -> bool:
        """Whether some client subscribes to `topic` now."""
        ch = self._static.get(topic) or self._channels.get(topic)
        return ch is not None and ch.has_sinks()

    def flush(self, timeout_s: float = 10.0) -> bool:
        """Wait until the background queue is empty and its last message sent (at most
        timeout_s); True when it is. Without a background thread there is nothing to wait
        for."""
        if self._queue is None:
            return True
        deadline = time.monotonic() + timeout_s
        while self._queue.unfinished_tasks:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.002)
        return True

    def close(self) -> None:
        """Send what is queued (a few seconds at most), stop the background thread and the
        server (clients are disconnected). Idempotent."""
        if self._closed:
            return
        self._closed = True
        if self._queue is not None and self._worker is not None:
            self.flush(5.0)
            with contextlib.suppress(queue.Full):
                self._queue.put(None, timeout=1.0)
            self._worker.join(5.0)
        self._server.stop()

    def __enter__(self) -> FoxgloveView:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _count(self, what: str) -> None:
        with self._lock:
            self.counts[what] = self.counts.get(what, 0) + 1

    def _log_ns(self, t: float) -> int:
        """The log time of something of time t: the latest time so far, never going back
        (as a live recorder's `FeedOrder` logs), so that a client sees log time advance."""
        with self._lock:
            self._log_t = max(self._log_t, float(t))
            return _ns(self._log_t)

    def _work(self) -> None:
        q = self._queue
        assert q is not None
        while True:
            item = q.get()
            try:
                if item is None:
                    return
                self._publish_now(*item)
            except Exception as e:  # the run goes on; the count and last_error tell
                self.last_error = e
                self._count(f"error:{type(item[0]).__name__}")
            finally:
                q.task_done()

    # -- messages

    def publish(self, msg: Message, topic: str | None = None) -> bool:
        """Publish one `hardware.messages` message as the trial log stores it (on `topic`,
        default the type's). Depth images are rate-limited (`ViewConfig.depth_hz`); a
        message nobody subscribes to is not encoded; one the log cannot encode (an
        unknown type, a negative or non-finite time) is counted in `counts` and skipped.
        Returns whether it was sent (in the background: queued)."""
        if self._queue is not None:
            try:
                self._queue.put_nowait((msg, topic))
            except queue.Full:
                self._count("queue_full")
                return False
            return True
        return self._publish_now(msg, topic)

    def _publish_now(self, msg: Message, topic: str | None) -> bool:
        if isinstance(msg, TagDetections):
            self._publish_tags(msg)
        key = (type(msg), topic)
        channels = self._parts.get(key)
        if channels is not None and not any(ch.has_sinks() for ch in channels):
            self._count("unsubscribed")
            return False
        is_depth = isinstance(msg, DepthFrame)
        if is_depth and not self._gates["depth"].ready(msg.t):
            self._count("depth_rate_limited")
            return False
        try:
            if not (math.isfinite(msg.t) and msg.t >= 0):
                raise ConfigError("message time must be finite and >= 0")
            main = topic or TOPICS[type(msg)]
            parts = encode_parts(msg, main, _ns(msg.t))
        except (AttributeError, TypeError, ValueError, KeyError):
            self._count(f"not_encodable:{type(msg).__name__}")
            return False
        if channels is None:
            channels = self._part_channels(parts, main)
            self._parts[key] = channels
        log_ns = self._log_ns(msg.t)
        for ch, (_, _, data) in zip(channels, parts, strict=True):
            ch.log(data, log_time=log_ns)
        if is_depth:
            self._gates["depth"].take(msg.t)
        self._count(type(msg).__name__)
        return True

    def _part_channels(self, parts: list, main_topic: str) -> list[foxglove.Channel]:
        """The channels of a message's encoded parts (topic, schema, data), made on first use."""
        return [self._channel(t, schema, main_topic) for t, schema, _ in parts]

    def _channel(self, topic: str, schema: Any, main_topic: str) -> foxglove.Channel:
        ch = self._channels.get(topic)
        if ch is None:
            fox_schema = foxglove.Schema(
                name=schema.name, encoding=schema.encoding, data=schema.data
            )
            ch = foxglove.Channel(
                topic,
                schema=fox_schema,
                message_encoding=schema.message_encoding,
                context=self._context,
                metadata={} if topic == main_topic else {"main_topic": main_topic},
            )
            self._channels[topic] = ch
        return ch

    def _publish_tags(self, msg: TagDetections) -> None:
        if not self._tags.has_sinks() or not (math.isfinite(msg.t) and msg.t >= 0):
            return
        size = self.calibration.tag_size_m if self.calibration else 0.165
        stamp = _stamp(msg.t)
        entities = []
        for det in msg.detections:
            pose = _transform_pose(det.camera_T_tag)
            entities.append(
                SceneEntity(
                    timestamp=stamp,
                    frame_id=FRAME_TAGS,
                    id=f"tag{det.tag_id}",
                    cubes=[
                        CubePrimitive(
                            pose=pose,
                            size=Vector3(x=size, y=size, z=0.005),
                            color=Color(r=0.1, g=0.6, b=1.0, a=0.7),
                        )
                    ],
                    texts=[
                        TextPrimitive(
                            pose=pose,
                            billboard=True,
                            font_size=14.0,
                            scale_invariant=True,
                            color=Color(r=1.0, g=1.0, b=1.0, a=1.0),
                            text=str(det.tag_id),
                        )
                    ],
                )
            )
        update = SceneUpdate(
            deletions=[SceneEntityDeletion(timestamp=stamp, type=SceneEntityDeletionType.All)],
            entities=entities,
        )
        self._tags.log(update, log_time=self._log_ns(msg.t))

    # -- SLAM state

    def publish_pose(self, estimate: PoseEstimate) -> bool:
        """The localizer's pose on /slam/pose and /slam/estimate, its uncertainty, and /tf
        (world → walker at the pose; walker → the camera frames when the calibration is
        known). Skipped (False) while the estimate has no finite time."""
        t = float(estimate.t)
        if not (math.isfinite(t) and t >= 0):
            return False
        x, y, theta = (float(v) for v in estimate.pose)
        cov = np.asarray(estimate.covariance, dtype=float).reshape(3, 3)
        ns, stamp = self._log_ns(t), _stamp(t)
        pose = _planar_pose(x, y, theta)
        if self._pose.has_sinks():
            msg = PoseInFrame(timestamp=stamp, frame_id=FRAME_WORLD, pose=pose)
            self._pose.log(msg, log_time=ns)
        if self._estimate.has_sinks():
            body = {
                "t": t,
                "x": x,
                "y": y,
                "theta": theta,
                "covariance": [_jf(v) for v in cov.ravel()],
            }
            self._estimate.log(json.dumps(body, separators=(",", ":")).encode(), log_time=ns)
        if self._uncertainty.has_sinks() and np.all(np.isfinite(cov)):
            self._uncertainty.log(_uncertainty_update(t, x, y, theta, cov), log_time=ns)
        if self._tf.has_sinks():
            tfs = [
                FrameTransform(
                    timestamp=stamp,
                    parent_frame_id=FRAME_WORLD,
                    child_frame_id=FRAME_WALKER,
                    translation=Vector3(x=x, y=y, z=0.0),
                    rotation=_yaw_quaternion(theta),
                )
            ]
            if self.calibration is not None:
                for child, mount in (
                    (FRAME_DEPTH, self.calibration.depth_mount),
                    (FRAME_TAGS, self.calibration.tag_mount),
                ):
                    walker_T_optical = mount.walker_T_optical()
                    tfs.append(
                        FrameTransform(
                            timestamp=stamp,
                            parent_frame_id=FRAME_WALKER,
                            child_frame_id=child,
                            translation=_translation(walker_T_optical),
                            rotation=_matrix_quaternion(walker_T_optical[:3, :3]),
                        )
                    )
            self._tf.log(FrameTransforms(transforms=tfs), log_time=ns)
        self._count("pose")
        return True

    def publish_trajectory(self, trajectory: Trajectory, t: float) -> bool:
        """A trajectory on /slam/trajectory (at most trajectory_max_poses, evenly spread,
        the latest included), stamped t."""
        n = len(trajectory)
        if n == 0 or not self._trajectory.has_sinks():
            return False
        m = self.config.trajectory_max_poses
        idx = np.unique(np.linspace(0, n - 1, m).round().astype(int)) if n > m else np.arange(n)
        poses = trajectory.poses[idx].tolist()
        msg = PosesInFrame(
            timestamp=_stamp(t),
            frame_id=FRAME_WORLD,
            poses=[_planar_pose(x, y, th) for x, y, th in poses],
        )
        self._trajectory.log(msg, log_time=self._log_ns(t))
        self._count("trajectory")
        return True

    def publish_grid(self, grid: GridExtent, t: float, reference: bool = False) -> bool:
        """An occupancy grid on /map (reference=True: /map/reference) as a foxglove.Grid
        in the world frame, stamped t."""
        channel = self._reference if reference else self._map
        ny, nx = grid.shape
        if ny == 0 or nx == 0 or not channel.has_sinks():
            return False
        cells, k = grid_cells(grid, self.config.grid_max_cells)
        cols = cells.shape[1]
        ox, oy = grid.origin
        size = grid.resolution * k
        msg = Grid(
            timestamp=_stamp(t),
            frame_id=FRAME_WORLD,
            pose=Pose(
                position=Vector3(x=ox, y=oy, z=0.0),
                orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
            ),
            column_count=cols,
            cell_size=Vector2(x=size, y=size),
            row_stride=cols * GRID_CELL_STRIDE,
            cell_stride=GRID_CELL_STRIDE,
            fields=_GRID_FIELDS,
            data=cells.tobytes(),
        )
        channel.log(msg, log_time=self._log_ns(t))
        self._count("reference_grid" if reference else "grid")
        return True

    # -- the pipeline

    def observe(self, pipeline: Pipeline, msg: Message) -> None:
        """Call after `pipeline.feed(msg)`: publishes msg and, within the rate limits, the
        localizer's pose, its trajectory and the map(s)."""
        if self.calibration is None:
            self.calibration = pipeline.calibration
        self.publish(msg)
        if isinstance(msg, _STATE_POINTS):
            self._publish_state(pipeline, float(msg.t), force=False)

    def publish_state(
        self, pipeline: Pipeline, t: float | None = None, *, force: bool = True
    ) -> None:
        """Publish the pose, trajectory and map(s): now (force, e.g. after a replay's final
        map rebuild) or within the rate limits. t defaults to the pipeline's last message
        time. Call it only where the localizer holds no unused observation: after the
        run, right after an odometry message, depth frame or scan, or right after the
        closed loop asked it for the pose of a command."""
        if self.calibration is None:
            self.calibration = pipeline.calibration
        if t is None:
            t = pipeline.recorded.t_last
        if t is None or not math.isfinite(t):
            return
        self._publish_state(pipeline, float(t), force=force)

    def _publish_state(self, pipeline: Pipeline, t: float, force: bool) -> None:
        g, clock = self._gates, time.perf_counter
        if force or g["pose"].ready(t):
            g["pose"].take(t)
            if self._wants(self._pose, self._estimate, self._uncertainty, self._tf):
                self.publish_pose(pipeline.localizer.estimate())
        if force or g["trajectory"].ready(t):
            t0 = clock()
            if self._trajectory.has_sinks():
                self.publish_trajectory(pipeline.localizer.trajectory(), t)
            g["trajectory"].take(t, clock() - t0)
        if force or g["grid"].ready(t):
            t0 = clock()
            self.publish_grid(pipeline.mapper.grid, t)
            if self.config.reference_map and pipeline.reference is not None:
                self.publish_grid(pipeline.reference.grid, t, reference=True)
            g["grid"].take(t, clock() - t0)

    @staticmethod
    def _wants(*channels: Any) -> bool:
        return any(ch.has_sinks() for ch in channels)

    def observer(
        self, pipeline: Pipeline, *, realtime: bool = False, speed: float = 1.0
    ) -> ViewObserver:
        """An observer for `experiments.drag.Observed` that publishes after the pipeline
        has taken each message; realtime=True also paces the stream to the messages'
        times (speed× real time)."""
        pacer = RealtimePacer(speed) if realtime else None
        return ViewObserver(self, pipeline, pacer)


def _uncertainty_update(t: float, x: float, y: float, theta: float, cov: np.ndarray) -> SceneUpdate:
    """The 95 % ellipse of the position and two rays at the heading ±2σ (0.5 m long)."""
    vals, vecs = np.linalg.eigh(0.5 * (cov[:2, :2] + cov[:2, :2].T))
    axes = ELLIPSE_95 * np.sqrt(np.maximum(vals, 0.0))
    a = np.linspace(0.0, 2.0 * math.pi, _ELLIPSE_SEGMENTS, endpoint=False)
    unit = np.vstack([np.cos(a), np.sin(a)])
    pts = (vecs @ (axes[:, None] * unit)).T + np.array([x, y])
    ring = [Point3(x=float(px), y=float(py), z=0.01) for px, py in pts.tolist()]
    s = 2.0 * math.sqrt(max(float(cov[2, 2]), 0.0))
    rays = []
    for h in (theta - s, theta + s):
        rays += [
            Point3(x=x, y=y, z=0.01),
            Point3(x=x + 0.5 * math.cos(h), y=y + 0.5 * math.sin(h), z=0.01),
        ]
    colour = Color(r=1.0, g=0.5, b=0.0, a=0.9)
    entity = SceneEntity(
        timestamp=_stamp(t),
        frame_id=FRAME_WORLD,
        id="pose_uncertainty",
        lines=[
            LinePrimitive(
                type=LinePrimitiveLineType.LineLoop,
                thickness=2.0,
                scale_invariant=True,
                points=ring,
                color=colour,
            ),
            LinePrimitive(
                type=LinePrimitiveLineType.LineList,
                thickness=2.0,
                scale_invariant=True,
                points=rays,
                color=colour,
            ),
        ],
    )
    return SceneUpdate(entities=[entity])


class RealtimePacer:
    """An observer whose `before(msg)` sleeps until msg's time has come on the wall clock
    (speed× real time, from the first message). When the consumer falls behind by more
    than max_lag_s (a slow localizer) it does not rush to catch up: the pace restarts
    from the message at hand. A message older than the latest one does not wait."""

    def __init__(
        self,
        speed: float = 1.0,
        max_lag_s: float = 1.0,
        *,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if not speed > 0:
            raise ConfigError(f"speed must be > 0, got {speed!r}")
        self.speed, self.max_lag_s = float(speed), float(max_lag_s)
        self.clock, self.sleep = clock, sleep
        self._anchor: tuple[float, float] | None = None  # (wall, run time)
        self._latest = -math.inf
        #: seconds slept so far
        self.slept_s = 0.0

    def before(self, msg: Message) -> None:
        t = float(msg.t)
        if not math.isfinite(t) or t <= self._latest:
            return
        self._latest = t
        now = self.clock()
        if self._anchor is None:
            self._anchor = (now, t)
            return
        wall0, t0 = self._anchor
        delay = wall0 + (t - t0) / self.speed - now
        if delay > 0:
            self.sleep(delay)
            self.slept_s += delay
        elif -delay > self.max_lag_s:
            self._anchor = (now, t)

    def after(self, msg: Message) -> None:
        pass


class ViewObserver:
    """A `FoxgloveView` attached to a pipeline, in either of the two loops:

    - a replay: an `experiments.drag.Observed` observer. `before(msg)` paces the stream
      (with a `RealtimePacer`), `after(msg)` is `FoxgloveView.observe` (the message, and
      within the rate limits the SLAM state after odometry, depth frames and scans).
    - the closed loop (`run_closed_loop`): `record(msg)` for every message fed and every
      command (its `record` callback; the message only), `on_command(cmd, frame)` after
      each command is sent (its `on_command` callback): the SLAM state within the rate
      limits, off the frame-to-command path, where the loop has just asked the localizer
      for its pose.

    `finish()` publishes the final state (after `Pipeline.run`, which rebuilds a
    smoother's map at the end, or after a live run's `rebuild_map`)."""

    def __init__(
        self, view: FoxgloveView, pipeline: Pipeline, pacer: RealtimePacer | None = None
    ) -> None:
        self.view, self.pipeline, self.pacer = view, pipeline, pacer

    def before(self, msg: Message) -> None:
        if self.pacer is not None:
            self.pacer.before(msg)

    def after(self, msg: Message) -> None:
        self.view.observe(self.pipeline, msg)

    def record(self, msg: Message) -> None:
        self.view.publish(msg)

    def on_command(self, cmd: BrakeCommand, frame: DepthFrame | LaserScan | None = None) -> None:
        self.view.publish_state(self.pipeline, cmd.t, force=False)

    def finish(self) -> None:
        self.view.publish_state(self.pipeline)
