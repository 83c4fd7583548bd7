"""Depth cameras as sources of `DepthFrame`s: Kinect v1 (libfreenect), fakenect, RealSense.

`open_depth(spec, calibration, clock, **options)` opens one:

=================  ==========================================================================
``kinect``         the first Kinect v1 (libfreenect device index 0)
``kinect:INDEX``   Kinect number INDEX
``fakenect:DIR``   a fakenect recording folder replayed through the real libfreenect sync
                   API with Debian's fake libfreenect (`hardware.fakenect`)
``realsense``      the first Intel RealSense (``pip install 'walker-slam[realsense]'``)
=================  ==========================================================================

Every problem opening one (an unknown spec, a missing folder or binding, no device)
raises `DeviceError` (a ValueError) with one line saying what to do. A source has the
`calibration`, `metadata` ({"depth_camera": {...}}, strict JSON), `messages()` (a
blocking iterator that yields frames as they arrive, with strictly increasing t) and
`close()` (callable from any thread: a blocked `messages()` then ends promptly and the
device, or its capture process, is released).

Kinect v1
---------
Capture runs in a process of its own (`hardware.kinect_worker`, libfreenect's sync API
through the PyPI `freenect` binding); `fakenect:DIR` is the same process started with
the fake library preloaded, so the tests replay through exactly the live code path. One
process serves a Kinect's depth and video (a USB Kinect opens in one process only): the
depth source and `kinect_rgb_frames` on the same device share it.

Depth is read as 11-bit raw disparity (``FREENECT_DEPTH_11BIT``, the only format the
fake library supports; ``DEPTH_MM`` aborts in it) and converted to millimetres by a
2048-entry table (`kinect_raw_to_mm_table`)::

    z [m] = 1 / (raw · −0.0030711016 + 3.3309495161)

Nicolas Burrus's ``raw_depth_to_meters`` (his Kinect calibration notes and RGBDemo): the
refined constants of the first-order fit 100 / (−0.00307 raw + 3.33) cm that the
OpenKinect wiki (Imaging Information) derives from the ROS ``kinect_node`` calibration
data ("less than 2 cm off within 2.5 m"). It is the form of the triangulation model z = b·f /
(d_off − d) that libfreenect's own factory-calibrated conversion (`freenect_raw_to_mm`
in src/registration.c) also has — depth inverse-linear in the raw value —, which is why
it is preferred here over the empirical 0.1236 m · tan(raw / 2842.5 + 1.1863) of
Stéphane Magnenat (the two differ by ~4 cm at 0.85 m). The formula gives 300 mm at raw
0 and diverges at raw ≈ 1084.6; raw 2047 is "no reading". The table holds 0 (invalid)
for 2047, for raw ≥ 1085 (no positive depth), for depths beyond uint16 millimetres, and
for depths outside the usable range (the calibration's `depth_range_m`, 0.8–3.5 m:
raw ≈ 678–991), as the simulated depth camera does: the mapper sees the same kind of
frame live as in simulation. Pass ``range_m=(0, 65.535)`` to keep everything the
formula gives. Raw values above 2047 (impossible in 11-bit mode) read 0.

Intrinsics: libfreenect's sync API gives none, so they are the calibration's
`depth_intrinsics` when its size is the frame's, and otherwise scaled to the frame
(`scale_intrinsics`: fx, fy by the size ratio; cx, cy keeping pixel centres at integer
coordinates, c' = (c + 0.5)·s − 0.5, the convention of `CameraIntrinsics.from_fov`).

Decimation (``decimation=k``): each k×k block of the 640×480 frame becomes one pixel
holding the nearest valid depth in the block (`decimate_nearest`; 0 when the block
has none). For an occupancy mapper that steers a walker around obstacles the nearest
reading is the safe choice: a thin obstacle (a chair leg, a table edge) that covers a
few pixels of a block survives, where a median would drop it; and at a depth edge the
block takes the foreground surface instead of a median of two surfaces (an average of
the two middle values, for an even count: a phantom point between them). The cost is
that a nearer surface widens by up to k − 1 native pixels at its edges (at k = 4 about
1 cm at 2 m: a native pixel spans z / 589 there), and that a lone valid pixel makes
its block valid. The default decimation (None) is the integer k that makes the frame
the calibration's size (4 for the default 160×120 calibration, the simulator's), else 1;
the intrinsics are scaled to the decimated size.

Time stamps (``stamp``): the capture process reads the host's monotonic clock right
after libfreenect hands over a frame (the arrival); the frame also carries the Kinect's
timestamp, a 60 MHz counter of the camera's own clock that wraps every 71.6 s (the
documented rate; OpenNI2-FreenectDriver divides it by 60 for microseconds). The
default, ``stamp="device"``, unwraps that counter (using the arrival gaps to count
wraps, and re-basing when the two clocks disagree by over a second) and maps it onto
the run's `HostClock` with `hardware.clock.ClockMap` from the (device, arrival) pairs:
t = device time + the smallest arrival − device difference seen (per window, with
drift). That removes the jitter of USB transfer, the libfreenect thread and the
scheduler, and t is never later than the frame's arrival; what remains is a constant
bias of the minimum transfer latency (the frame is complete only after its last USB
packet, so capture is earlier than t by roughly that), which cannot be measured
without a reference and is not removed. ``stamp="arrival"`` uses the arrival time as is.
A frame whose time would not be after the previous one's (a repeated device timestamp)
is dropped and counted (`frames_unstamped`).

A consumer slower than the camera does not build up a backlog: the source keeps at
most `queue_frames` frames and drops the oldest (`frames_dropped`); libfreenect's own
buffer ring also keeps only the newest frame (`frames_skipped` counts those under
fakenect, where each frame's recording line is known).

fakenect
--------
``fakenect:DIR`` replays DIR at the recorded pace (`hardware.fakenect.ReplayFolder`)
and ends cleanly after the last depth frame of INDEX.txt (the fake library does not
loop and would block past its end). Replay needs the `freenect` binding, Debian's
libfreenect-bin / libfreenect-dev and a C compiler for the `freenect_camera_to_world`
shim (built once into the user's cache folder). Its device timestamps are the recorded
ones. `hardware.fakenect.FakenectWriter` records a folder from arrays.

RealSense
---------
`RealSenseDepthSource`: depth in millimetres from the device's depth scale, intrinsics
from the depth stream's profile, decimation and range as above, time stamps from the
frame's timestamp (milliseconds in its timestamp domain) mapped like the Kinect's. It
cannot be tested here (no device): only its errors are.

RGB for the tag camera
----------------------
`kinect_rgb_frames(clock, index=0, stop=None)` iterates over (t, image) of the
Kinect's RGB camera: image 480×640×3 uint8 in **BGR** order (OpenCV's), t on `clock`
as for depth. `index` is a libfreenect device index or a spec (``kinect``,
``kinect:1``, ``fakenect:DIR``).
"""

from __future__ import annotations

import atexit
import math
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import asdict
from importlib.util import find_spec
from pathlib import Path
from typing import Any

import numpy as np

from hardware import fakenect as fk
from hardware import kinect_worker as wire
from hardware.calibration import WalkerCalibration
from hardware.clock import ClockMap, HostClock
from hardware.devices import DEPTH_CAMERAS, DeviceSpec, lookup, split_spec
from hardware.errors import DeviceError
from hardware.messages import CameraIntrinsics, DepthFrame
from hardware.source import Source

KINECT_WIDTH = fk.WIDTH
KINECT_HEIGHT = fk.HEIGHT
KINECT_RAW_NO_READING = fk.RAW_MAX
KINECT_TICKS_PER_S = fk.TICKS_PER_S
# z [m] = 1 / (raw · A + B): Burrus's fit on the OpenKinect wiki (see the module docstring).
KINECT_INVERSE_DEPTH_A = -0.0030711016  # 1/m per raw unit
KINECT_INVERSE_DEPTH_B = 3.3309495161  # 1/m
KINECT_RAW_TO_MM = "z_mm = 1000 / (-0.0030711016 raw + 3.3309495161)"

STAMP_MODES = ("device", "arrival")
_PACKAGE_ROOT = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------- conversions


def kinect_raw_to_mm_table(range_m: tuple[float, float] | None = None) -> np.ndarray:
    """The 2048-entry uint16 table raw 11-bit disparity → depth [mm] (0 = invalid).

    Invalid: raw 2047 (no reading), raw ≥ 1085 (the formula gives no positive depth),
    depths over 65535 mm, and — when `range_m` = (min, max) [m] is given — depths
    outside it (compared before rounding to millimetres, as the simulator does).
    """
    raw = np.arange(KINECT_RAW_NO_READING + 1, dtype=np.float64)
    inverse_m = KINECT_INVERSE_DEPTH_A * raw + KINECT_INVERSE_DEPTH_B
    positive = inverse_m > 0
    z_m = np.divide(1.0, inverse_m, out=np.full_like(raw, np.inf), where=positive)
    mm = np.rint(z_m * 1000.0)
    valid = positive & (mm >= 1) & (mm <= np.iinfo(np.uint16).max)
    if range_m is not None:
        lo, hi = float(range_m[0]), float(range_m[1])
        if not 0.0 <= lo < hi:
            raise ValueError(f"range_m must be (min, max) with 0 <= min < max, got {range_m}")
        valid &= (z_m >= lo) & (z_m <= hi)
    valid[KINECT_RAW_NO_READING] = False
    return np.where(valid, mm, 0.0).astype(np.uint16)


def kinect_raw_to_mm(raw: np.ndarray, table: np.ndarray | None = None) -> np.ndarray:
    """Depth [mm] (uint16, 0 = invalid) of raw 11-bit values through `table` (default:
    `kinect_raw_to_mm_table()` without a range limit); values above 2047 read 0."""
    if table is None:
        table = kinect_raw_to_mm_table()
    return np.take(table, np.asarray(raw, dtype=np.intp), mode="clip")


def decimate_nearest(depth_mm: np.ndarray, factor: int) -> np.ndarray:
    """Each factor×factor block → its nearest valid depth (smallest non-zero), 0 if none.

    The image size must be a multiple of `factor` in both directions.
    """
    factor = int(factor)
    if factor < 1:
        raise ValueError(f"decimation must be a positive integer, got {factor}")
    d = np.asarray(depth_mm)
    if d.dtype != np.uint16 or d.ndim != 2:
        raise ValueError(f"depth must be a 2-D uint16 array, got {d.dtype} {d.shape}")
    if factor == 1:
        return d
    h, w = d.shape
    if h % factor or w % factor:
        raise ValueError(f"decimation {factor} does not divide the image size {w}x{h}")
    # 0 - 1 wraps to 65535, so the block minimum skips invalid pixels; + 1 wraps back.
    shifted = (d - np.uint16(1)).reshape(h // factor, factor, w // factor, factor)
    return shifted.min(axis=(1, 3)) + np.uint16(1)


def scale_intrinsics(k: CameraIntrinsics, width: int, height: int) -> CameraIntrinsics:
    """`k` for the same camera sampled at width×height (each axis by its own ratio).

    Pixel centres are at integer coordinates, so c' = (c + 0.5)·s − 0.5.
    """
    if (k.width, k.height) == (width, height):
        return k
    sx, sy = width / k.width, height / k.height
    return CameraIntrinsics(
        int(width),
        int(height),
        k.fx * sx,
        k.fy * sy,
        (k.cx + 0.5) * sx - 0.5,
        (k.cy + 0.5) * sy - 0.5,
    )


def default_decimation(width: int, height: int, calibrated: CameraIntrinsics) -> int:
    """The integer k with (width, height) = k · the calibration's size, else 1."""
    cw, ch = calibrated.width, calibrated.height
    if cw > 0 and ch > 0 and width % cw == 0 and height % ch == 0 and width // cw == height // ch:
        return max(1, width // cw)
    return 1


def _frame_intrinsics(
    calibration: WalkerCalibration, width: int, height: int, decimation: int | None
) -> tuple[CameraIntrinsics, int, str]:
    calibrated = calibration.depth_intrinsics
    k = default_decimation(width, height, calibrated) if decimation is None else int(decimation)
    if k < 1 or width % k or height % k:
        raise DeviceError(
            f"decimation {decimation} does not divide the depth frame {width}x{height}"
        )
    native = scale_intrinsics(calibrated, width, height)
    out = scale_intrinsics(native, width // k, height // k)
    if (calibrated.width, calibrated.height) == (out.width, out.height):
        out, origin = calibrated, "calibration"
    else:
        origin = f"calibration ({calibrated.width}x{calibrated.height}) scaled"
    return out, k, origin


def _range(
    calibration: WalkerCalibration, range_m: tuple[float, float] | None
) -> tuple[float, float]:
    lo, hi = calibration.depth_range_m if range_m is None else range_m
    return float(lo), float(hi)


def _frame_info(
    decimation: int,
    range_m: tuple[float, float],
    stamp: str,
    intrinsics: CameraIntrinsics,
    intrinsics_from: str,
) -> dict[str, Any]:
    """The part of a depth camera's metadata that says how its frames are made."""
    return {
        "decimation": decimation,
        "decimation_rule": "nearest valid depth per block",
        "range_m": list(range_m),
        "stamp": stamp,
        "intrinsics": asdict(intrinsics),
        "intrinsics_from": intrinsics_from,
    }


# --------------------------------------------------------------------------- time stamps


class _Stamper:
    """Host-clock times of one stream's frames from (device time, arrival) pairs.

    ticks_per_s / wrap describe the device counter (the Kinect: 60 MHz, 2^32; a
    RealSense: milliseconds, no wrap). See the module docstring.
    """

    RESYNC_S = 1.0

    def __init__(self, clock: HostClock, mode: str, ticks_per_s: float, wrap: int | None) -> None:
        if mode not in STAMP_MODES:
            raise DeviceError(f"unknown stamp mode {mode!r}; valid: {', '.join(STAMP_MODES)}")
        self.clock, self.mode = clock, mode
        self.ticks_per_s, self.wrap = float(ticks_per_s), wrap
        self.map = ClockMap()
        self._prev: tuple[float, float] | None = None  # (ticks, arrival)
        self._device_s = 0.0
        self.last_t = -math.inf
        self.resyncs = 0

    def _device_time(self, ticks: float, arrival: float) -> float | None:
        if self._prev is None:
            self._device_s = ticks / self.ticks_per_s
        else:
            prev_ticks, prev_arrival = self._prev
            gap = arrival - prev_arrival
            if self.wrap:
                d = (ticks - prev_ticks) % self.wrap
                period = self.wrap / self.ticks_per_s
                wraps = round((gap - d / self.ticks_per_s) / period)
                step = (d + wraps * self.wrap) / self.ticks_per_s
            else:
                step = (ticks - prev_ticks) / self.ticks_per_s
            if step == 0:
                return None  # the same device time twice
            if step < 0 or abs(step - gap) > max(self.RESYNC_S, 0.5 * gap):
                # The device clock jumped (restart, garbage): continue by the host's gap.
                self.map.reset()
                self.resyncs += 1
                step = max(gap, 1e-6)
            self._device_s += step
        self._prev = (ticks, arrival)
        return self._device_s

    def stamp(self, ticks: float, arrival_monotonic: float) -> float | None:
        """t on the host clock, or None when it would not follow the previous frame's."""
        arrival = self.clock.to_host(arrival_monotonic)
        if self.mode == "arrival":
            t = arrival
        else:
            device_s = self._device_time(ticks, arrival_monotonic)
            if device_s is None:
                return None
            self.map.observe(device_s, arrival)
            t = self.map.to_host(device_s)
        if not t > self.last_t:
            return None
        self.last_t = t
        return t


# --------------------------------------------------------------------------- Kinect process

_TIMEOUT = object()


class _RawFrame:
    __slots__ = ("arrival", "image", "timestamp")

    def __init__(self, timestamp: int, arrival: float, image: np.ndarray) -> None:
        self.timestamp, self.arrival, self.image = timestamp, arrival, image


class _Subscription:
    """One consumer's queue of a Kinect stream (bounded: drops the oldest)."""

    def __init__(self, feed: _Feed, maxlen: int) -> None:
        self.feed = feed
        self.cond = threading.Condition()
        self.frames: deque[_RawFrame] = deque()
        self.maxlen = max(1, int(maxlen))
        self.ended = False
        self.closed = False
        self.error: str | None = None
        self.dropped = 0

    def put(self, frame: _RawFrame) -> None:
        with self.cond:
            if self.closed:
                return
            self.frames.append(frame)
            if len(self.frames) > self.maxlen:
                self.frames.popleft()
                self.dropped += 1
            self.cond.notify_all()

    def finish(self, error: str | None = None) -> None:
        with self.cond:
            self.ended = True
            if error and self.error is None:
                self.error = error
            self.cond.notify_all()

    def close(self) -> None:
        with self.cond:
            self.closed = True
            self.frames.clear()
            self.cond.notify_all()

    def get(self, timeout: float | None = None) -> Any:
        """The next frame; None when the stream is over (ended or closed); `_TIMEOUT`
        after `timeout` seconds without one. Raises DeviceError when the device failed."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self.cond:
            while True:
                if self.closed:
                    return None
                if self.frames:
                    return self.frames.popleft()
                if self.error is not None:
                    raise DeviceError(self.error)
                if self.ended:
                    return None
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return _TIMEOUT
                self.cond.wait(remaining)

    def wait_ready(self, timeout: float, what: str) -> None:
        """Block until a frame, the end or an error is there (the frame stays queued)."""
        deadline = time.monotonic() + timeout
        with self.cond:
            while not (self.frames or self.ended or self.error or self.closed):
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise DeviceError(f"no {what} frame within {timeout:g} s")
                self.cond.wait(remaining)
            if self.error is not None and not self.frames:
                raise DeviceError(self.error)


class _Feed:
    """What the hub knows of one stream of the device, subscribed to or not."""

    def __init__(self, kind: str, lines: list[int] | None) -> None:
        self.kind = kind
        self.sub: _Subscription | None = None
        self.ended = False
        self.error: str | None = None
        self.received = 0
        self.skipped = 0
        # fakenect: the recording's line numbers of this stream, and each one's ordinal
        self.lines = lines
        self.ordinal = {line: i for i, line in enumerate(lines)} if lines is not None else {}
        self.last_ordinal = -1


_HUBS: dict[tuple[str, str], _KinectHub] = {}
_HUBS_LOCK = threading.Lock()


def _stderr_tail(f: Any, lines: int = 3) -> str:
    try:
        f.seek(0)
        text = f.read().decode(errors="replace")
    except (OSError, ValueError):
        return ""
    tail = [ln.strip() for ln in text.splitlines() if ln.strip()][-lines:]
    return " | ".join(tail)


class _KinectHub:
    """The capture process of one Kinect (or fakenect folder) and its streams' consumers."""

    def __init__(self, key: tuple[str, str], index: int, replay: fk.ReplayFolder | None) -> None:
        self.key, self.index, self.replay = key, index, replay
        self.lock = threading.Lock()
        self.feeds: dict[str, _Feed] = {}
        if replay is not None:
            for kind in ("depth", "video"):
                self.feeds[kind] = _Feed(kind, replay.lines[kind])
        self.proc: subprocess.Popen | None = None
        self._stderr: Any = None
        self._reader: threading.Thread | None = None
        self._closing = False

    # -- process

    def _start(self, kinds: list[str]) -> None:
        env = dict(os.environ)
        if self.replay is not None:
            try:
                env = fk.replay_environment(self.replay.path, env)
            except fk.FakenectError as exc:
                raise DeviceError(str(exc)) from None
        env["PYTHONPATH"] = os.pathsep.join(
            p for p in (str(_PACKAGE_ROOT), env.get("PYTHONPATH", "")) if p
        )
        read_fd, write_fd = os.pipe()
        self._stderr = tempfile.TemporaryFile()
        cmd = [sys.executable, "-m", "hardware.kinect_worker", "--fd", str(write_fd)]
        cmd += ["--index", str(self.index)]
        for kind in kinds:
            cmd += ["--stream", kind]
        try:
            self.proc = subprocess.Popen(
                cmd,
                stdin=subprocess.PIPE,
                stdout=subprocess.DEVNULL,
                stderr=self._stderr,
                pass_fds=(write_fd,),
                env=env,
                start_new_session=True,
            )
        except OSError as exc:
            os.close(read_fd)
            raise DeviceError(f"cannot start the Kinect capture process: {exc}") from None
        finally:
            os.close(write_fd)
        self._reader = threading.Thread(
            target=self._read_loop,
            args=(read_fd,),
            name=f"kinect-reader-{self.key[1]}",
            daemon=True,
        )
        self._reader.start()

    def _command(self, kind: str) -> None:
        assert self.proc is not None and self.proc.stdin is not None
        try:
            self.proc.stdin.write(f"{kind}\n".encode())
            self.proc.stdin.flush()
        except OSError:
            pass  # the process is gone; the reader reports it

    def _read_loop(self, fd: int) -> None:
        with os.fdopen(fd, "rb", buffering=1 << 20) as f:
            while True:
                head = f.read(wire.HEADER.size)
                if len(head) < wire.HEADER.size:
                    break
                magic, stream, status, w, h, ch, ts, arrival, n = wire.HEADER.unpack(head)
                payload = f.read(n)
                if magic != wire.MAGIC or len(payload) < n:
                    self._fail_all("the Kinect capture process sent a malformed record")
                    break
                kind = "depth" if stream == wire.STREAM_DEPTH else "video"
                if status == wire.STATUS_ERROR:
                    self._fail(kind, payload.decode(errors="replace"))
                    continue
                dtype = np.uint16 if kind == "depth" else np.uint8
                shape = (h, w) if ch == 1 else (h, w, ch)
                self._deliver(kind, ts, arrival, np.frombuffer(payload, dtype=dtype).reshape(shape))
        if not self._closing:
            try:
                code = self.proc.wait(timeout=5) if self.proc is not None else None
            except subprocess.TimeoutExpired:
                code = "still running"
            tail = _stderr_tail(self._stderr)
            self._fail_all(
                f"the Kinect capture process exited (code {code})" + (f": {tail}" if tail else "")
            )

    # -- streams

    def _feed(self, kind: str) -> _Feed:
        if kind not in self.feeds:
            self.feeds[kind] = _Feed(kind, None)
        return self.feeds[kind]

    def _deliver(self, kind: str, ts: int, arrival: float, image: np.ndarray) -> None:
        with self.lock:
            feed = self._feed(kind)
            if feed.ended:
                return
            last = False
            if self.replay is not None:
                line = ts
                if line not in feed.ordinal:
                    self._fail_locked(kind, f"fakenect replayed an unexpected frame (line {line})")
                    return
                ts = self.replay.entries[line].timestamp
                ordinal = feed.ordinal[line]
                feed.skipped += max(0, ordinal - feed.last_ordinal - 1)
                feed.last_ordinal = ordinal
                last = line == feed.lines[-1]
            feed.received += 1
            sub = feed.sub
            if last:
                feed.ended = True
        if sub is not None:
            sub.put(_RawFrame(ts, arrival, image))
            if last:
                sub.finish()

    def _fail_locked(self, kind: str, message: str) -> None:
        feed = self._feed(kind)
        if feed.ended:
            return
        feed.ended, feed.error = True, message
        if feed.sub is not None:
            feed.sub.finish(message)

    def _fail(self, kind: str, message: str) -> None:
        with self.lock:
            self._fail_locked(kind, message)

    def _fail_all(self, message: str) -> None:
        with self.lock:
            kinds = set(self.feeds) | ({"depth", "video"} if self.replay is None else set())
            for kind in kinds:
                self._fail_locked(kind, message)

    def attach(self, kind: str, maxlen: int) -> _Subscription:
        with self.lock:
            if self._closing:
                raise DeviceError("the Kinect is being closed")
            feed = self._feed(kind)
            if feed.sub is not None:
                raise DeviceError(f"the {kind} stream of {self.describe()} is already open")
            if feed.error is not None:
                raise DeviceError(feed.error)
            if feed.lines is not None and not feed.lines:
                raise DeviceError(f"{self.describe()} has no {kind} frames")
            sub = _Subscription(feed, maxlen)
            feed.sub = sub
            if feed.ended:
                sub.finish()
            start = self.proc is None
            if start:
                if self.replay is not None:
                    kinds = [k for k in ("depth", "video") if self.replay.lines[k]]
                else:
                    kinds = [kind]
            elif self.replay is None:
                self._command(kind)
        if start:
            try:
                self._start(kinds)
            except BaseException:
                self.detach(sub)
                raise
        return sub

    def detach(self, sub: _Subscription) -> None:
        sub.close()
        with self.lock:
            if sub.feed.sub is sub:
                sub.feed.sub = None
            if any(f.sub is not None for f in self.feeds.values()):
                return
            self._closing = True
        with _HUBS_LOCK:
            if _HUBS.get(self.key) is self:
                del _HUBS[self.key]
        self._shutdown()

    def _shutdown(self) -> None:
        proc = self.proc
        if proc is not None:
            try:
                if proc.stdin is not None:
                    proc.stdin.close()  # the worker exits at the end of its stdin
            except OSError:
                pass
            try:
                proc.wait(timeout=2.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=5.0)
        if self._reader is not None and self._reader is not threading.current_thread():
            self._reader.join(timeout=5.0)
        if self._stderr is not None:
            self._stderr.close()
        if self.replay is not None:
            self.replay.close()

    def describe(self) -> str:
        if self.replay is not None:
            return f"fakenect recording {self.replay.source}"
        return f"Kinect {self.index}"

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None else None


@atexit.register
def _close_all_hubs() -> None:
    """At exit, end capture processes and remove staged recordings nobody closed."""
    with _HUBS_LOCK:
        hubs = list(_HUBS.values())
    for hub in hubs:
        with hub.lock:
            subs = [f.sub for f in hub.feeds.values() if f.sub is not None]
        for sub in subs:
            hub.detach(sub)


def _check_binding() -> None:
    if find_spec("freenect") is None:
        raise DeviceError(
            "the Kinect needs the freenect Python binding: apt-get install libfreenect-dev, "
            "then pip install 'walker-slam[kinect]' (make install-live)"
        )


def _kinect_index(arg: str | None) -> int:
    if arg is None:
        return 0
    if not arg.isdigit():
        raise DeviceError(f"kinect:INDEX needs a device index >= 0, got 'kinect:{arg}'")
    return int(arg)


def _parse_kinect_device(device: int | str) -> tuple[int, Path | None]:
    """(index, fakenect folder or None) of an index or a spec kinect[:INDEX] / fakenect:DIR."""
    name, arg = split_spec(f"kinect:{device}" if isinstance(device, int) else device)
    if name == "kinect":
        return _kinect_index(arg), None
    if name == "fakenect":
        if not arg:
            raise DeviceError("fakenect:DIR needs a recording folder")
        return 0, Path(arg)
    raise DeviceError(f"unknown Kinect {device!r}; valid: kinect, kinect:INDEX, fakenect:DIR")


def _subscribe(
    index: int, folder: Path | None, kind: str, maxlen: int
) -> tuple[_KinectHub, _Subscription]:
    _check_binding()
    if folder is not None:
        if not folder.is_dir():
            raise DeviceError(f"fakenect folder not found: {folder}")
        key = ("fakenect", str(folder.resolve()))
    else:
        key = ("kinect", str(index))
    with _HUBS_LOCK:
        hub = _HUBS.get(key)
        if hub is None:
            replay = None
            if folder is not None:
                try:
                    replay = fk.ReplayFolder(folder)
                except fk.FakenectError as exc:
                    raise DeviceError(str(exc)) from None
            hub = _KinectHub(key, index, replay)
            _HUBS[key] = hub
    try:
        return hub, hub.attach(kind, maxlen)
    except BaseException:
        with _HUBS_LOCK:
            if _HUBS.get(key) is hub and hub.proc is None:
                del _HUBS[key]
                if hub.replay is not None:
                    hub.replay.close()
        raise


class _KinectStream:
    """One stream (depth or video) of a Kinect's capture process: its subscription, the
    counts of frames lost on the way, and closing."""

    _hub: Any
    _sub: Any
    _closed: bool

    @property
    def frames_dropped(self) -> int:
        """Frames dropped because the consumer fell more than `queue_frames` behind."""
        return self._sub.dropped

    @property
    def frames_skipped(self) -> int:
        """fakenect: recorded frames that libfreenect's buffer ring replaced unread."""
        return self._sub.feed.skipped

    @property
    def worker_pid(self) -> int | None:
        """The capture process (shared by the depth and video streams of a device)."""
        return self._hub.pid

    def _attach(
        self,
        clock: HostClock,
        stamp: str,
        index: int,
        folder: Path | None,
        kind: str,
        queue_frames: int,
    ) -> None:
        """Subscribe to the device's `kind` frames (its capture process started if need
        be), with a stamper for the Kinect's clock."""
        self._stamper = _Stamper(clock, stamp, KINECT_TICKS_PER_S, fk.TICK_WRAP)
        self._hub, self._sub = _subscribe(index, folder, kind, queue_frames)
        self._closed = False
        self.frames_unstamped = 0

    def _wait_first(self, timeout_s: float, kind: str) -> None:
        """Wait for the stream's first frame; closes the stream if it does not come
        (`DeviceError`) or the wait is interrupted."""
        try:
            self._sub.wait_ready(timeout_s, f"{kind} ({self._hub.describe()})")
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._hub.detach(self._sub)

    def __enter__(self):
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class KinectDepthSource(_KinectStream):
    """Depth frames of a Kinect v1 (or a fakenect recording) — see the module docstring.

    index: libfreenect device index; fakenect: a recording folder to replay instead of
    a device. decimation: None (match the calibration's size), or an integer k.
    range_m: usable depth range [m] (None: the calibration's). stamp: "device" or
    "arrival". open_timeout_s: how long to wait for the first frame when opening.
    queue_frames: frames kept for a consumer that falls behind.
    """

    def __init__(
        self,
        calibration: WalkerCalibration,
        clock: HostClock,
        *,
        index: int = 0,
        fakenect: str | os.PathLike | None = None,
        decimation: int | None = None,
        range_m: tuple[float, float] | None = None,
        stamp: str = "device",
        open_timeout_s: float = 10.0,
        queue_frames: int = 8,
    ) -> None:
        self._calibration = calibration
        self.clock = clock
        self.range_m = _range(calibration, range_m)
        try:
            self.table = kinect_raw_to_mm_table(self.range_m)
        except ValueError as exc:
            raise DeviceError(str(exc)) from None
        self.intrinsics, self.decimation, origin = _frame_intrinsics(
            calibration, KINECT_WIDTH, KINECT_HEIGHT, decimation
        )
        folder = None if fakenect is None else Path(fakenect)
        self._attach(clock, stamp, int(index), folder, "depth", queue_frames)
        info: dict[str, Any] = {
            "device": "fakenect" if folder is not None else "kinect",
            "driver": "libfreenect sync API, 11-bit raw depth",
            "raw_to_mm": KINECT_RAW_TO_MM,
            "native_size": [KINECT_WIDTH, KINECT_HEIGHT],
            **_frame_info(self.decimation, self.range_m, stamp, self.intrinsics, origin),
        }
        if folder is not None:
            info["path"] = str(folder.resolve())
            info["recorded_frames"] = len(self._hub.replay.lines["depth"])
        else:
            info["index"] = int(index)
        self._metadata = {"depth_camera": info}
        self._wait_first(open_timeout_s, "depth")

    @property
    def calibration(self) -> WalkerCalibration:
        return self._calibration

    @property
    def metadata(self) -> dict[str, Any]:
        return self._metadata

    def to_frame(self, raw: np.ndarray, t: float) -> DepthFrame:
        """The DepthFrame of one raw 11-bit 480×640 image taken at t."""
        mm = np.take(self.table, raw, mode="clip")
        return DepthFrame(t, decimate_nearest(mm, self.decimation), self.intrinsics)

    def messages(self) -> Iterator[DepthFrame]:
        while True:
            raw = self._sub.get()
            if raw is None:
                return
            if raw.image.shape != (KINECT_HEIGHT, KINECT_WIDTH):
                raise DeviceError(f"Kinect depth frame of unexpected shape {raw.image.shape}")
            t = self._stamper.stamp(raw.timestamp, raw.arrival)
            if t is None:
                self.frames_unstamped += 1
                continue
            yield self.to_frame(raw.image, t)


class KinectVideoStream(_KinectStream):
    """Iterator of (t, BGR image) from a Kinect's RGB camera (see `kinect_rgb_frames`)."""

    def __init__(
        self,
        clock: HostClock,
        index: int | str = 0,
        stop: Any = None,
        *,
        stamp: str = "device",
        open_timeout_s: float = 10.0,
        queue_frames: int = 4,
    ) -> None:
        device, folder = _parse_kinect_device(index)
        self.stop = stop
        self._attach(clock, stamp, device, folder, "video", queue_frames)
        self._wait_first(open_timeout_s, "video")

    def __iter__(self) -> KinectVideoStream:
        return self

    def __next__(self) -> tuple[float, np.ndarray]:
        while True:
            if self.stop is not None and self.stop.is_set():
                self.close()
            raw = self._sub.get(timeout=None if self.stop is None else 0.1)
            if raw is _TIMEOUT:
                continue
            if raw is None:
                self.close()
                raise StopIteration
            t = self._stamper.stamp(raw.timestamp, raw.arrival)
            if t is None:
                self.frames_unstamped += 1
                continue
            return t, np.ascontiguousarray(raw.image[:, :, ::-1])


def kinect_rgb_frames(
    clock: HostClock, index: int | str = 0, stop: Any = None, **options: Any
) -> KinectVideoStream:
    """The Kinect's RGB camera as an iterator of (t, image) for the tag camera.

    image: 480×640×3 uint8, **BGR** (OpenCV's order; libfreenect delivers RGB).
    t: capture time on `clock` [s], strictly increasing (the 60 MHz device timestamp
    mapped onto the host clock, as for depth; ``stamp="arrival"`` for the arrival).
    index: a libfreenect device index, or a spec "kinect", "kinect:INDEX",
    "fakenect:DIR" (a recording: its video frames at the recorded pace, ending after
    the last one).
    stop: anything with ``is_set()`` (a `threading.Event`): the iterator ends soon
    (≤ 0.1 s) after it is set. `close()` (from any thread) also ends it and releases the
    device. Opening waits for the first frame (``open_timeout_s``, default 10 s) and
    raises `DeviceError` on one line if there is none. With a depth source open on
    the same device both share one capture process; a stream started after the other
    begins at the frame then current, so a recording's first few video frames can be
    missed when video is opened after depth. Other options: ``queue_frames``.
    """
    return KinectVideoStream(clock, index, stop, **options)


# --------------------------------------------------------------------------- RealSense


def _import_pyrealsense2() -> Any:
    try:
        import pyrealsense2 as rs
    except ImportError:
        raise DeviceError(
            "the RealSense needs pyrealsense2: pip install 'walker-slam[realsense]'"
        ) from None
    return rs


def _start_realsense(rs: Any, width: int, height: int, fps: int) -> tuple[Any, Any]:
    """(pipeline, profile) of the first RealSense's z16 depth stream width×height at fps,
    started; `DeviceError` when there is none or the stream cannot start."""
    context = rs.context()
    devices = context.query_devices()
    if len(devices) == 0:
        raise DeviceError("no RealSense device found (pyrealsense2 sees none connected)")
    pipeline = rs.pipeline(context)
    config = rs.config()
    config.enable_stream(rs.stream.depth, int(width), int(height), rs.format.z16, int(fps))
    try:
        return pipeline, pipeline.start(config)
    except RuntimeError as exc:
        raise DeviceError(
            f"cannot start the RealSense depth stream {width}x{height}@{fps}: {exc}"
        ) from None


def _stream_intrinsics(rs: Any, profile: Any) -> CameraIntrinsics:
    """The pinhole intrinsics of a started pipeline's depth stream."""
    intr = profile.get_stream(rs.stream.depth).as_video_stream_profile().get_intrinsics()
    return CameraIntrinsics(int(intr.width), int(intr.height), intr.fx, intr.fy, intr.ppx, intr.ppy)


def _device_info(rs: Any, device: Any) -> dict[str, str]:
    """A RealSense's name, serial number and firmware version ("" for what it cannot tell)."""

    def info(key: Any) -> str:
        try:
            return str(device.get_info(key))
        except RuntimeError:
            return ""

    return {
        "name": info(rs.camera_info.name),
        "serial": info(rs.camera_info.serial_number),
        "firmware": info(rs.camera_info.firmware_version),
    }


class RealSenseDepthSource:
    """Depth frames of an Intel RealSense through pyrealsense2 (untested here: no device).

    The depth stream (z16, width×height at fps) is converted to millimetres with the
    device's depth scale (z_m = value · scale; exact when the scale is 1 mm, the D400
    default), restricted to range_m (None: the calibration's), decimated like the
    Kinect's (None: to the calibration's size when that is an integer divisor). The
    intrinsics are the depth stream profile's (scaled by the decimation), not the
    calibration's. Time stamps: the frame's timestamp (ms, in the device's timestamp
    domain) mapped onto `clock` like the Kinect's, or the arrival (stamp="arrival").
    """

    def __init__(
        self,
        calibration: WalkerCalibration,
        clock: HostClock,
        *,
        width: int = 640,
        height: int = 480,
        fps: int = 30,
        decimation: int | None = None,
        range_m: tuple[float, float] | None = None,
        stamp: str = "device",
        frame_timeout_s: float = 5.0,
    ) -> None:
        rs = _import_pyrealsense2()
        self._rs = rs
        self._calibration = calibration
        self.clock = clock
        self.range_m = _range(calibration, range_m)
        self._stamper = _Stamper(clock, stamp, 1000.0, None)
        self.frame_timeout_s = float(frame_timeout_s)
        self._pipeline, profile = _start_realsense(rs, width, height, fps)
        device = profile.get_device()
        self.depth_scale_m = float(device.first_depth_sensor().get_depth_scale())
        native = _stream_intrinsics(rs, profile)
        k = default_decimation(native.width, native.height, calibration.depth_intrinsics)
        k = k if decimation is None else int(decimation)
        if k < 1 or native.width % k or native.height % k:
            self._pipeline.stop()
            raise DeviceError(
                f"decimation {k} does not divide the depth frame {native.width}x{native.height}"
            )
        self.decimation = k
        self.intrinsics = scale_intrinsics(native, native.width // k, native.height // k)
        self._lo_mm = self.range_m[0] * 1000.0
        self._hi_mm = self.range_m[1] * 1000.0
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self._running = True
        self._iterating = False
        self.frames_unstamped = 0
        self._metadata = {
            "depth_camera": {
                "device": "realsense",
                **_device_info(rs, device),
                "depth_scale_m": self.depth_scale_m,
                "native_size": [native.width, native.height],
                "fps": int(fps),
                **_frame_info(k, self.range_m, stamp, self.intrinsics, "device stream profile"),
            }
        }

    @property
    def calibration(self) -> WalkerCalibration:
        return self._calibration

    @property
    def metadata(self) -> dict[str, Any]:
        return self._metadata

    def _stop_pipeline(self) -> None:
        with self._lock:
            if self._running:
                self._running = False
                self._pipeline.stop()

    def _to_mm(self, values: np.ndarray) -> np.ndarray:
        if abs(self.depth_scale_m - 0.001) < 1e-12:
            z_mm = values.astype(np.float64)
        else:
            z_mm = values.astype(np.float64) * (self.depth_scale_m * 1000.0)
        valid = (values > 0) & (z_mm >= self._lo_mm) & (z_mm <= self._hi_mm) & (z_mm < 65535.5)
        return np.where(valid, np.rint(z_mm), 0.0).astype(np.uint16)

    def messages(self) -> Iterator[DepthFrame]:
        with self._lock:
            if not self._running:
                return
            self._iterating = True
        try:
            waited = 0.0
            while not self._closed.is_set():
                ok, frames = self._pipeline.try_wait_for_frames(100)
                if not ok:
                    waited += 0.1
                    if waited >= self.frame_timeout_s:
                        raise DeviceError(
                            f"no RealSense depth frame for {self.frame_timeout_s:g} s"
                        )
                    continue
                waited = 0.0
                arrival = time.monotonic()
                depth = frames.get_depth_frame()
                if not depth:
                    continue
                t = self._stamper.stamp(float(depth.get_timestamp()), arrival)
                if t is None:
                    self.frames_unstamped += 1
                    continue
                values = np.asanyarray(depth.get_data())
                mm = decimate_nearest(self._to_mm(values), self.decimation)
                yield DepthFrame(t, mm, self.intrinsics)
        finally:
            self._iterating = False
            self._stop_pipeline()

    def close(self) -> None:
        self._closed.set()
        with self._lock:
            iterating = self._iterating
        if not iterating:
            self._stop_pipeline()  # else messages() stops it within 0.1 s

    def __enter__(self) -> RealSenseDepthSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ------------------------------------------------------------- the registry's members


def _open_kinect(
    arg: str | None, calibration: WalkerCalibration, clock: HostClock, **options: Any
) -> KinectDepthSource:
    return KinectDepthSource(calibration, clock, index=_kinect_index(arg), **options)


def _open_fakenect(
    arg: str | None, calibration: WalkerCalibration, clock: HostClock, **options: Any
) -> KinectDepthSource:
    _, folder = _parse_kinect_device(f"fakenect:{arg or ''}")
    return KinectDepthSource(calibration, clock, fakenect=folder, **options)


def _open_realsense(
    arg: str | None, calibration: WalkerCalibration, clock: HostClock, **options: Any
) -> RealSenseDepthSource:
    if arg is not None:
        raise DeviceError(f"realsense takes no argument, got 'realsense:{arg}'")
    return RealSenseDepthSource(calibration, clock, **options)


KINECT = DeviceSpec(
    "kinect", None, _open_kinect, "Kinect v1 through libfreenect", forms=("kinect", "kinect:INDEX")
)
FAKENECT = DeviceSpec(
    "fakenect",
    None,
    _open_fakenect,
    "a fakenect recording replayed through the real libfreenect sync API",
    forms=("fakenect:DIR",),
)
REALSENSE = DeviceSpec(
    "realsense",
    None,
    _open_realsense,
    "the first Intel RealSense (pip install 'walker-slam[realsense]')",
    forms=("realsense",),
)


def open_depth(
    spec: str, calibration: WalkerCalibration, clock: HostClock, **options: Any
) -> Source:
    """Open the depth camera `spec` (NAME[:ARG] of hardware.devices.DEPTH_CAMERAS: kinect,
    kinect:INDEX, fakenect:DIR, realsense, and any an installed package adds).

    options go to the source (`KinectDepthSource`, `RealSenseDepthSource`): e.g.
    decimation, range_m, stamp. Raises DeviceError (one line) when it cannot open.
    """
    member, arg = lookup(DEPTH_CAMERAS, spec)
    return member.factory(arg, calibration, clock, **options)
