"""Live devices as one timed source on the run's host clock.

`LiveSources(devices, clock)` runs each device's `messages()` in a thread of its own and
hands what arrived to the closed loop (`experiments.pipeline.run_closed_loop`) through
`poll(until, stop_at_frame)`, merged in time order — the same interface the simulator
offers, so the loop is the one that runs in simulation and in replay.

Queues are bounded where it is safe to drop: when the loop falls behind, the oldest
depth frames, laser scans and tag images of a device are dropped (and counted per
device); encoder ticks, events and everything else are never dropped. A device that has
delivered nothing for `stale_s` gets a DeviceEvent "stalled" in the stream (and
"resumed" when it delivers again), so a recording shows the stall; the brakes react to
it through the safety layer's data ages, not through this.

A device that ends its stream ends the run (a recording played to its end, a port that
was lost with reconnection off); a device that raises is a fault: `poll` re-raises it
in the loop's thread (a `DeviceFault` with the original exception as its cause, or a
bug's own exception), so whatever runs the loop releases the brakes on the way out.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

from hardware.clock import HostClock
from hardware.errors import DeviceError
from hardware.messages import DepthFrame, DeviceEvent, LaserScan, Message, TagDetections

DROPPABLE = (DepthFrame, LaserScan, TagDetections)
# Streams that deliver continuously: each is watched for a stall on its own (events,
# collisions and commands come when they come).
CONTINUOUS = (
    "EncoderTicks",
    "GyroRate",
    "VelocityOdometry",
    "DepthFrame",
    "LaserScan",
    "TagDetections",
    "GroundTruthPose",
)


class DeviceFault(DeviceError):
    """A device failed the way devices fail (an OSError, or a driver's one-line error
    such as `hardware.arduino.BoardError`); the cause is the device's exception. Any
    other exception in a device's thread is a bug and is re-raised as it is."""

    def __init__(self, device: str, exc: BaseException) -> None:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        super().__init__(f"{device}: {first}")
        self.device = device


@dataclass
class DeviceStats:
    """Per device: messages received and dropped, arrival times of the last second."""

    received: int = 0
    dropped: int = 0
    by_type: dict[str, int] = field(default_factory=dict)  # received, per message type
    dropped_by_type: dict[str, int] = field(default_factory=dict)
    last_arrival: float = float("-inf")
    last_by_type: dict[str, float] = field(default_factory=dict)
    stalled: set[str] = field(default_factory=set)  # streams ("*": the whole device)
    ended: bool = False
    max_queued: int = 0  # most messages waiting in its queue at once
    max_frames_queued: dict[str, int] = field(default_factory=dict)  # per droppable kind
    recent: deque[float] = field(default_factory=lambda: deque(maxlen=2000))

    def rate_hz(self, now: float, window_s: float = 1.0) -> float:
        n = sum(1 for a in self.recent if now - a <= window_s)
        return n / window_s

    def snapshot(self) -> DeviceStats:
        """A copy that its device's thread does not change."""
        return replace(
            self,
            by_type=dict(self.by_type),
            dropped_by_type=dict(self.dropped_by_type),
            max_frames_queued=dict(self.max_frames_queued),
            last_by_type=dict(self.last_by_type),
            stalled=set(self.stalled),
            recent=deque(self.recent, maxlen=self.recent.maxlen),
        )


@dataclass
class _Device:
    name: str
    source: Any
    queue: deque[Message] = field(default_factory=deque)
    stats: DeviceStats = field(default_factory=DeviceStats)
    thread: threading.Thread | None = None


class LiveSources:
    """See the module docstring. `devices` are (name, source) pairs; each source's
    messages must be stamped on `clock`."""

    def __init__(
        self,
        devices: Sequence[tuple[str, Any]],
        clock: HostClock,
        *,
        max_frames: int = 2,
        stale_s: float = 0.3,
    ) -> None:
        if max_frames < 1:
            raise ValueError(f"max_frames must be >= 1, got {max_frames}")
        self.clock = clock
        self.max_frames = max_frames
        self.stale_s = stale_s
        self._devices = [_Device(name, src) for name, src in devices]
        self._cond = threading.Condition()
        self._held: list[tuple[float, int, int, Message]] = []  # (t, device rank, n, msg)
        self._arrivals: dict[int, float] = {}  # id(frame) -> arrival, for latency
        self._n = 0
        self._stopped = False
        self._ended_by: str | None = None
        self._fault: BaseException | None = None
        self._started = False
        self._t_start = 0.0

    # -- TimedSource -----------------------------------------------------------------
    @property
    def t(self) -> float:
        return self.clock.now()

    @property
    def done(self) -> bool:
        return self._stopped or self._ended_by is not None or self._fault is not None

    @property
    def ended_by(self) -> str | None:
        """The device whose stream ended the run, if one did."""
        return self._ended_by

    @property
    def stats(self) -> dict[str, DeviceStats]:
        """Each device's statistics as they are now: copies, taken under the lock that
        the devices' threads update them under."""
        with self._cond:
            return {d.name: d.stats.snapshot() for d in self._devices}

    def start(self) -> None:
        if self._started:
            return
        self._started = True
        self._t_start = self.clock.now()
        for d in self._devices:
            d.thread = threading.Thread(target=self._pump, args=(d,), name=f"live-{d.name}")
            d.thread.daemon = True
            d.thread.start()

    def poll(self, until: float, stop_at_frame: bool = False) -> list[Message]:
        """Wait until the clock reaches `until` (or, stop_at_frame, a frame arrived) and
        return what arrived up to then in time order; DeviceFault if a device failed."""
        self.start()
        with self._cond:
            while True:
                if self._fault is not None:
                    raise self._fault
                self._drain()
                now = self.clock.now()
                self._check_stalls(now)
                if stop_at_frame and any(isinstance(h[3], DROPPABLE[:2]) for h in self._held):
                    return self._take(now)
                if now >= until or self.done:
                    return self._take(until)
                self._cond.wait(timeout=until - now)

    def arrival(self, frame: Message) -> float:
        """When a depth frame or scan arrived from its device (host clock; NaN if it is
        not known), once: for the latency from arrival to the command it triggered."""
        with self._cond:
            return self._arrivals.pop(id(frame), float("nan"))

    def remaining(self) -> list[Message]:
        """What arrived but was not polled (after close(): the devices' last messages,
        which a recording must not lose), in time order."""
        with self._cond:
            self._drain()
            return self._take(float("inf"))

    def stop(self) -> None:
        """End the run (Ctrl-C, SIGTERM, the duration): `done` becomes true."""
        with self._cond:
            self._stopped = True
            self._cond.notify_all()

    def close(self) -> None:
        """Stop, close every device (their threads end) and wait for the threads."""
        self.stop()
        for d in self._devices:
            try:
                d.source.close()
            finally:
                if d.thread is not None and d.thread is not threading.current_thread():
                    d.thread.join(timeout=3.0)

    # -- internals --------------------------------------------------------------------
    def _pump(self, d: _Device) -> None:
        # Everything a device yields is queued, after stop() as well: a driver may yield
        # what it decoded before it was closed (a serial read can hold many reports when
        # the host fell behind), and remaining() hands that to the recording. The
        # stream ends when close() closes the device.
        try:
            for msg in d.source.messages():
                with self._cond:
                    self._arrive(d, msg)
                    self._cond.notify_all()
        except Exception as e:
            with self._cond:
                if not self._stopped:
                    if isinstance(e, OSError | ValueError):
                        fault: BaseException = DeviceFault(d.name, e)
                        fault.__cause__ = e
                    else:
                        fault = e  # a bug: re-raised with its own traceback
                    self._fault = fault
                self._cond.notify_all()
            return
        with self._cond:
            d.stats.ended = True
            if not self._stopped and self._ended_by is None:
                self._ended_by = d.name
            self._cond.notify_all()

    def _arrive(self, d: _Device, msg: Message) -> None:
        s = d.stats
        now = self.clock.now()
        if isinstance(msg, DROPPABLE):
            kind = type(msg).__name__
            same = [m for m in d.queue if type(m) is type(msg)]
            if len(same) >= self.max_frames:
                oldest = same.pop(0)
                d.queue.remove(oldest)
                self._arrivals.pop(id(oldest), None)
                s.dropped += 1
                s.dropped_by_type[kind] = s.dropped_by_type.get(kind, 0) + 1
            s.max_frames_queued[kind] = max(s.max_frames_queued.get(kind, 0), len(same) + 1)
        d.queue.append(msg)
        s.max_queued = max(s.max_queued, len(d.queue))
        if isinstance(msg, DROPPABLE[:2]):
            self._arrivals[id(msg)] = now
            while len(self._arrivals) > 64:  # frames nobody asked about
                self._arrivals.pop(next(iter(self._arrivals)))
        s.received += 1
        name = type(msg).__name__
        s.by_type[name] = s.by_type.get(name, 0) + 1
        s.last_arrival = now
        if name in CONTINUOUS:
            s.last_by_type[name] = now
        s.recent.append(now)
        for stream in ("*", name):
            if stream in s.stalled:
                s.stalled.discard(stream)
                what = "delivering again" if stream == "*" else f"{name} again"
                d.queue.append(DeviceEvent(now, d.name, "resumed", what))

    def _check_stalls(self, now: float) -> None:
        """A device that delivered nothing, or a stream of it (a camera of a device that
        also sends other things) that stopped, for longer than stale_s."""
        for d in self._devices:
            s = d.stats
            if s.ended:
                continue
            since = s.last_arrival if s.received else self._t_start
            if "*" not in s.stalled and now - since > self.stale_s:
                s.stalled.add("*")
                why = f"nothing for {now - since:.2f} s" if s.received else "nothing yet"
                d.queue.append(DeviceEvent(now, d.name, "stalled", why))
            for name, last in s.last_by_type.items():
                if name not in s.stalled and now - last > self.stale_s:
                    s.stalled.add(name)
                    why = f"no {name} for {now - last:.2f} s"
                    d.queue.append(DeviceEvent(now, d.name, "stalled", why))

    def _drain(self) -> None:
        for rank, d in enumerate(self._devices):
            while d.queue:
                msg = d.queue.popleft()
                self._n += 1
                self._held.append((msg.t, rank, self._n, msg))

    def _take(self, until: float) -> list[Message]:
        self._held.sort(key=lambda h: (h[0], h[1], h[2]))
        keep = [h for h in self._held if h[0] > until]
        out = [h[3] for h in self._held if h[0] <= until]
        self._held = keep
        return out
