"""The live jobs behind `walkerslam live` and `walkerslam board`.

`run_live(options)` puts a localizer and a braking controller on the walker: the serial
board (`hardware.arduino`), the depth camera (`hardware.depth`) and the tag camera
(`hardware.tags`) are live sources on one host clock, merged by `hardware.live`, fed
through the same pipeline and closed loop as a simulation (`experiments.pipeline`:
frame-triggered, the safety layer around the controller), the board is the command
sink, and every stream and command is recorded crash-safely to a trial log in the order
it was fed, so `walkerslam replay` of the recording reproduces the live poses. With
`sim=True` the walker is the simulator, run in real time in a process of its own
(`hardware.sim.live_world`) behind the board emulator on a pty (or the firmware in
simavr) and the simulated cameras; nothing else changes.

Whatever ends the run — the duration, Ctrl-C / SIGTERM (`LiveRun.stop`), the end of the
simulated route or of a replayed recording, a device fault or a bug — the board is sent
zero brake torque first, then the devices are closed and the log is closed. Nothing here
prints: `on_status` receives a `LiveStatus` a few times a second for the CLI to show.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import queue
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from control.base import CONTROLLERS
from control.safety import SafeController
from experiments.calibration_override import CalibrationOverride, applied
from experiments.config import configure
from experiments.mitigations import Mitigated, check_calibration, resolve
from experiments.pipeline import LoopConfig, Pipeline, run_closed_loop
from experiments.warm_up import warm_up
from hardware.arduino import ArduinoBoard, BoardConfig, BoardStats
from hardware.calibration import WalkerCalibration
from hardware.clock import HostClock
from hardware.errors import ConfigError
from hardware.live import LiveSources
from hardware.log import LogWriter
from hardware.messages import BrakeCommand, DepthFrame, EncoderTicks, LaserScan, Message
from mapping.mapper import MapperConfig
from slam.base import LOCALIZERS, create
from slam.motion import uses_gyro

# What a live run's loop does unless told otherwise: a command right after every depth
# frame (the lowest frame-to-command latency), at 10 Hz while frames stall, no simulated
# latency (the real one is there), a smoother's map rebuilt in a thread.
LIVE_LOOP = LoopConfig(trigger="frame", latency_s=0.0, rebuild_in_background=True)


class LiveError(ConfigError):
    """A live run that cannot start (a device missing, a bad option); one line."""


@dataclass(frozen=True)
class SimWalker:
    """The simulated walker of `live --sim`: its course and trial, its board."""

    course: str = "thesis-course"
    seed: int = 0
    surface: str = "dusty"
    duration_s: float = 300.0
    depth_size: tuple[int, int] = (160, 120)
    depth_rate_hz: int = 10
    firmware: bool = False  # the compiled firmware in simavr instead of the emulator
    gyro: bool = False  # the walker's gyro, an IMU on the board
    cpus: tuple[int, ...] | None = None  # CPUs for the simulated walker (another machine)


@dataclass(frozen=True)
class LiveOptions:
    """Everything a live run is made of (the CLI's options)."""

    localizer: str = "dead-reckoning"
    controller: str = "open-loop"
    serial: str | None = None
    depth: str = "none"  # kinect, realsense, fakenect:DIR, sim:SOCKET (a simulated walker)
    camera: str = "none"  # a device index, a video file or folder, kinect; "sim" with sim:
    camera_yaml: str | None = None
    camera_fps: float | None = None  # pace a tag-camera video file or image folder
    calibration: str | None = None  # a JSON file of WalkerCalibration fields
    record: str | None = None
    duration_s: float | None = None
    localizer_overrides: dict[str, Any] = field(default_factory=dict)
    controller_overrides: dict[str, Any] = field(default_factory=dict)
    mitigations: tuple[str, ...] = ()  # experiments.mitigations, before the overrides
    sim: SimWalker | None = None
    loop: LoopConfig = LIVE_LOOP
    board: BoardConfig = field(default_factory=BoardConfig)
    max_frames: int = 2
    foxglove_port: int | None = None  # serve the live view (experiments.live_view) here
    foxglove_host: str = "127.0.0.1"


@dataclass
class LiveStatus:
    """A snapshot of a live run, for the status line."""

    t: float
    rates_hz: dict[str, float]
    dropped: dict[str, int]
    stalled: list[str]
    latency_ms: tuple[float, float]  # p50, p99 of the last commands triggered by frames
    commanded_nm: tuple[float, float]
    board_pwm: tuple[int, int] | None  # what the board reports it applies
    board_timed_out: bool
    board_errors: int  # bad lines both ways, sequence gaps
    sigma_xy_m: float
    sigma_theta_deg: float
    stale: tuple[str, ...]
    events: list[str]
    view_url: str | None = None


@dataclass
class LiveResult:
    duration_s: float
    ended_by: str  # "duration", "stopped", "route finished", "<device> ended"
    counts: dict[str, int]
    dropped: dict[str, int]
    latency_ms: dict[str, float]
    # (frame time, frame-to-command latency, arrival-to-command latency) [s]
    latency_samples: list[tuple[float, float, float]]
    board: dict[str, Any]
    commands: int
    files: dict[str, Path]
    pipeline: Pipeline
    sources: dict[str, Any]  # per device: hardware.live.DeviceStats
    warm_up_s: float  # compiling the kernels before the devices opened (wall time)


class ThreadedRecorder:
    """Writes what the loop fed to a trial log from a thread of its own (a 640×480 depth
    frame takes ~8 ms to encode and compress: not on the frame-to-command path), with
    `FeedOrder`'s log times (the later of the message's time and the previous one), so a
    replay feeds the messages in the live order. The writer flushes every 0.5 s: a
    killed process loses at most that and the few messages still queued."""

    def __init__(self, writer: LogWriter) -> None:
        self.writer = writer
        self.last = 0.0
        self._q: queue.SimpleQueue[tuple[Message, float] | None] = queue.SimpleQueue()
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()

    @classmethod
    def open(
        cls, path: Path, calibration: WalkerCalibration, metadata: dict[str, Any]
    ) -> ThreadedRecorder:
        """A recorder of a new trial log at `path` (its folder made if need be)."""
        path.parent.mkdir(parents=True, exist_ok=True)
        return cls(LogWriter(path, calibration, metadata=metadata))

    def __call__(self, msg: Message) -> None:
        self.last = max(self.last, msg.t)
        self._q.put((msg, self.last))

    def _run(self) -> None:
        while (item := self._q.get()) is not None:
            try:
                self.writer.write(item[0], log_time=item[1])
            except Exception as e:  # reported by close()
                self.error = e

    def close(self) -> None:
        self._q.put(None)
        self._thread.join()
        self.writer.close()
        if self.error is not None:
            raise self.error


class _Latency:
    """Frame-to-command latency: from a depth frame's time (its capture on the host
    clock) to the moment the command it triggered was written to the board; and the
    part of it after the frame arrived from its device (what this process adds)."""

    def __init__(self, clock: HostClock, arrival: Callable[[Message], float]) -> None:
        self.clock = clock
        self.arrival = arrival
        self.samples: list[float] = []  # [s]
        self.after_arrival: list[float] = []  # [s]
        self.frame_t: list[float] = []  # the frames' times
        self.commands = 0

    def __call__(self, cmd: BrakeCommand, frame: DepthFrame | LaserScan | None) -> None:
        self.commands += 1
        if frame is not None:
            now = self.clock.now()
            self.samples.append(now - frame.t)
            self.after_arrival.append(now - self.arrival(frame))
            self.frame_t.append(frame.t)

    def percentiles(self, last: int | None = None) -> tuple[float, float]:
        s = self.samples[-last:] if last else self.samples
        if not s:
            return (math.nan, math.nan)
        p50, p99 = np.percentile(np.asarray(s) * 1e3, [50, 99])
        return float(p50), float(p99)


class LiveRun:
    """One live run; `run()` blocks until it ends. `stop()` may be called from a signal
    handler or another thread."""

    def __init__(
        self,
        options: LiveOptions,
        on_status: Callable[[LiveStatus], None] | None = None,
        status_hz: float = 4.0,
        on_phase: Callable[[str], None] | None = None,
    ) -> None:
        self.options = options
        self.on_status = on_status
        self.on_phase = on_phase  # what the run does before its loop, for the user
        self.status_period = 1.0 / status_hz
        self.clock = HostClock()
        self._world: subprocess.Popen | None = None
        self._world_dir: tempfile.TemporaryDirectory | None = None
        self._sources: LiveSources | None = None
        self._stop_requested = False
        self._events: deque[str] = deque(maxlen=4)
        self._safe: SafeController | None = None
        #: what the simulated walker reported (--sim): brake outputs, injected faults
        self.world_log: list[dict[str, Any]] = []
        self.view_url: str | None = None  # the live view's address (foxglove_port)
        # what a run is made of (built by run())
        self.cal = WalkerCalibration()
        self.calibration_file: CalibrationOverride | None = None  # --calibration
        self.mitigated = Mitigated()  # --mitigation's effect (resolved in _check_options)
        self.calibration_override: dict[str, Any] | None = None  # its record, with --sim
        self.devices: list[tuple[str, Any]] = []
        self.metadata: dict[str, Any] = {}
        self.board: ArduinoBoard | None = None
        self.pipeline: Pipeline | None = None
        self.recorder: ThreadedRecorder | None = None
        self.view = self.watcher = None
        self.files: dict[str, Path] = {}
        self._gyro = False  # the localizer reads the gyro (checked against the board)
        self.warm_up_s = 0.0  # how long compiling the kernels took before the devices

    def stop(self) -> None:
        self._stop_requested = True
        if self._sources is not None:
            self._sources.stop()

    def world_command(self, line: str) -> None:
        """A line to the simulated walker's standard input (fault injection with --sim:
        unplug, replug, reset, stall S; see hardware.sim.live_world)."""
        if self._world is None or self._world.stdin is None:
            raise LiveError("no simulated walker to command (live without --sim)")
        self._world.stdin.write(line.strip() + "\n")
        self._world.stdin.flush()

    # -- setting up --------------------------------------------------------------------
    def _start_world(self, sim: SimWalker) -> tuple[str, str]:
        self._world_dir = tempfile.TemporaryDirectory(prefix="walkerslam-sim-")
        cmd = [
            sys.executable,
            "-m",
            "hardware.sim.live_world",
            "--dir",
            self._world_dir.name,
            "--course",
            sim.course,
            "--seed",
            str(sim.seed),
            "--surface",
            str(sim.surface),
            "--duration",
            str(sim.duration_s),
            "--depth-size",
            f"{sim.depth_size[0]}x{sim.depth_size[1]}",
            "--depth-rate",
            str(sim.depth_rate_hz),
            "--board",
            "firmware" if sim.firmware else "emulator",
            *(["--gyro"] if sim.gyro else []),
        ]
        self._world = subprocess.Popen(
            cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1
        )
        if sim.cpus:
            os.sched_setaffinity(self._world.pid, set(sim.cpus))
        self._world_events: queue.SimpleQueue[dict[str, Any] | None] = queue.SimpleQueue()
        threading.Thread(target=self._watch_world, name="world-events", daemon=True).start()
        ready = self._world_event("ready", timeout_s=120.0)
        return ready["port"], ready["socket"]

    def _watch_world(self) -> None:
        world = self._world
        assert world is not None and world.stdout is not None
        for line in world.stdout:
            with contextlib.suppress(ValueError):
                ev = json.loads(line)
                if ev.get("event") == "done":
                    self._events.append(
                        "sim: route finished" if ev.get("finished") else "sim: time limit"
                    )
                self.world_log.append(ev)
                self._world_events.put(ev)
        self._world_events.put(None)

    def _world_event(self, name: str, timeout_s: float) -> dict[str, Any]:
        """The simulated walker's next event called `name` (others are skipped)."""
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            try:
                ev = self._world_events.get(timeout=left)
            except queue.Empty:
                break
            if ev is None:
                code = self._world.wait() if self._world is not None else "?"
                raise LiveError(f"the simulated walker exited (code {code}) before '{name}'")
            if ev.get("event") == name:
                return ev
            if ev.get("event") == "error":
                raise LiveError(f"the simulated walker failed: {ev.get('error')}")
        raise LiveError(f"the simulated walker did not report '{name}' within {timeout_s:.0f} s")

    def _stop_world(self) -> None:
        world, self._world = self._world, None
        if world is not None:
            with contextlib.suppress(OSError, ValueError):
                world.stdin.write("quit\n")
                world.stdin.close()
            try:
                world.wait(timeout=10.0)
            except subprocess.TimeoutExpired:
                world.kill()
                world.wait()
        if self._world_dir is not None:
            self._world_dir.cleanup()
            self._world_dir = None

    def _calibration(self) -> WalkerCalibration:
        """The walker's calibration: --calibration's file (or the thesis walker's), with
        the tag camera's calibration."""
        opts, file = self.options, self.calibration_file
        cal = file.calibration if file is not None else WalkerCalibration()
        if opts.camera_yaml:
            from hardware.camera_calibration import load_camera_yaml, with_tag_camera

            cal = with_tag_camera(cal, load_camera_yaml(opts.camera_yaml))
        return cal

    def _devices(self, cal: WalkerCalibration) -> list[tuple[str, Any]]:
        opts = self.options
        devices: list[tuple[str, Any]] = []
        if opts.depth != "none" and not opts.depth.startswith("sim:"):
            from hardware.depth import open_depth

            devices.append(("depth", open_depth(opts.depth, cal, self.clock)))
        if opts.camera not in ("none", "sim"):
            from hardware.tags import open_tag_camera

            devices.append(
                (
                    "tags",
                    open_tag_camera(
                        opts.camera,
                        cal,
                        self.clock,
                        camera_yaml=opts.camera_yaml,
                        fps=opts.camera_fps,
                    ),
                )
            )
        return devices

    # -- running -----------------------------------------------------------------------
    def run(self) -> LiveResult:
        ctl_cfg = self._check_options()
        self._warm_up()
        finished = False
        try:
            if self.on_phase is not None:
                self.on_phase("opening the devices")
            self._open_devices()
            self._build(ctl_cfg)
            record, on_command = self._outputs()
            t_start = self.clock.now()
            self._loop(record, on_command)
            duration, ended = self.clock.now() - t_start, self._ended_by()
            finished = True
        finally:
            self._shut_down(finished)
        return self._result(duration, ended)

    # the steps of a run ----------------------------------------------------------------
    def _check_options(self) -> Any:
        """Unknown names and bad --set values fail before any device opens."""
        opts = self.options
        LOCALIZERS.spec(opts.localizer)
        CONTROLLERS.spec(opts.controller)
        self.mitigated = resolve(opts.mitigations, opts.localizer)
        check_calibration(self.mitigated, opts.calibration)
        self._gyro = uses_gyro(
            configure(LOCALIZERS, opts.localizer, None, self._localizer_settings()).config
        )
        if opts.sim is None and not opts.serial:
            raise LiveError("live needs --serial PORT (or --sim)")
        self.calibration_file = CalibrationOverride.load(opts.calibration)
        return configure(CONTROLLERS, opts.controller, None, opts.controller_overrides).config

    def _warm_up(self) -> None:
        """The numba kernels compiled before any device opens (experiments.warm_up)."""
        opts = self.options
        if self.on_phase is not None:
            self.on_phase(f"warming up: {opts.localizer} and the map on the simulated course")
        self.warm_up_s = warm_up(
            opts.localizer,
            opts.controller,
            opts.localizer_overrides,
            opts.controller_overrides,
            opts.mitigations,
            opts.loop,
            self._gyro,
        )

    def _localizer_settings(self) -> dict[str, Any]:
        """The mitigations' localizer fields, then --set."""
        return {**self.mitigated.localizer_settings, **self.options.localizer_overrides}

    def _open_devices(self) -> None:
        """The simulated walker (--sim), the board (handshake), the cameras."""
        opts = self.options
        serial, sock = opts.serial, None
        if opts.sim is not None:
            serial, sock = self._start_world(opts.sim)
        elif opts.depth.startswith("sim:"):
            sock = opts.depth.removeprefix("sim:")
        if sock is not None:
            from hardware.sim.stream import SimSensors

            sensors = SimSensors(sock, self.clock)
            # the simulated walker's software calibration, with --calibration's odometry
            self.cal, self.calibration_override = applied(
                self.calibration_file, sensors.calibration
            )
            self.devices.append(("sim", sensors))
        else:
            self.cal = self._calibration()
        self.board = ArduinoBoard(serial, self.cal, self.clock, opts.board)
        self.board.open()
        self.devices.insert(0, ("board", self.board))
        self.devices.extend(self._devices(self.cal))
        for _, dev in self.devices:
            self.metadata.update(getattr(dev, "metadata", {}) or {})

    def _build(self, ctl_cfg: Any) -> None:
        """Localizer (with what the devices propose, then --set), controller behind the
        safety layer, pipeline."""
        opts, cal = self.options, self.cal
        self.initial = (self.metadata.get("world") or {}).get("start_pose") or (0.0, 0.0, 0.0)
        built = configure(LOCALIZERS, opts.localizer, self.metadata, self._localizer_settings())
        hs = self.board.handshake if self.board is not None else None
        if uses_gyro(built.config) and (hs is None or hs.gyro_lsb_per_10dps is None):
            raise LiveError(
                f"{self.board.port if self.board else 'the board'}: the board reports no "
                f"gyro (no IMU answered it) but {opts.localizer}.noise.gyro.enabled is set"
            )
        self.proposed = built.proposed
        loc = create(opts.localizer, cal, built.config, initial_pose=tuple(self.initial))
        ctl = CONTROLLERS.create(opts.controller, cal, config=ctl_cfg)
        self._safe = SafeController(ctl, cal, opts.loop.safety)
        hygiene = self.mitigated.hygiene
        mapper = MapperConfig(hygiene=hygiene) if hygiene is not None else None
        self.pipeline = Pipeline(loc, cal, mapper, reference_map=False)
        self.config = self._config(loc, ctl_cfg, self.initial, self.proposed)
        self.latency = _Latency(self.clock, lambda frame: self._sources.arrival(frame))

    def _outputs(self):
        """The recorder and the live view: the loop's `record` and `on_command`."""
        opts = self.options
        if opts.record:
            self.files["log"] = Path(opts.record)
            meta = {"config": self.config, **self.metadata}
            self.recorder = ThreadedRecorder.open(self.files["log"], self.cal, meta)
        record = self.recorder
        on_command: Callable[[BrakeCommand, DepthFrame | LaserScan | None], None] = self.latency
        if opts.foxglove_port is not None:
            from experiments.live_view import FoxgloveView

            self.view = FoxgloveView(
                self.cal, host=opts.foxglove_host, port=opts.foxglove_port, background=True
            )
            self.view_url = self.view.url
            self.watcher = self.view.observer(self.pipeline)
            record = _both(self.recorder, self.watcher.record)
            on_command = _both(self.latency, self.watcher.on_command)
        return record, on_command

    def _loop(self, record, on_command) -> None:
        """The closed loop over the live sources until they are done."""
        opts = self.options
        self._sources = LiveSources(self.devices, self.clock, max_frames=opts.max_frames)
        if self._stop_requested:
            self._sources.stop()
        timer = None
        if opts.duration_s is not None:
            timer = threading.Timer(opts.duration_s, self._sources.stop)
            timer.daemon = True
            timer.start()
        last_status = [-math.inf]

        def progress(t: float) -> None:
            now = self.clock.now()
            if self.on_status is not None and now - last_status[0] >= self.status_period:
                last_status[0] = now
                self.on_status(self._status(self.pipeline, self.board, self.latency))

        try:
            run_closed_loop(
                self._sources,
                self.board,
                self.pipeline,
                self._safe,
                opts.loop,
                record=record,
                progress=progress,
                on_command=on_command,
            )
        finally:
            if timer is not None:
                timer.cancel()

    def _shut_down(self, finished: bool) -> None:
        """The brakes first (zero, recorded), then the devices (what they still had is
        fed and recorded: nothing is lost at the end), then the log."""
        board, pipeline, recorder = self.board, self.pipeline, self.recorder
        if board is not None:
            if pipeline is not None and board.commanded_pwm != (0, 0):
                off = self.cal.brake.torque_off_nm
                release = BrakeCommand(self.clock.now(), off, off, "release")
                pipeline.feed(release)
                if recorder is not None:
                    recorder(release)
            board.close()
        if self._sources is not None:
            self._sources.close()
            if pipeline is not None:
                for msg in self._sources.remaining():
                    pipeline.feed(msg)
                    if recorder is not None:
                        recorder(msg)
        else:
            for _, dev in self.devices:
                dev.close()
        self._stop_world()
        if recorder is not None:
            recorder.close()
        if self.view is not None and not finished:
            self.view.close()

    def _result(self, duration: float, ended: str) -> LiveResult:
        """The smoother's final map, the live view's last state, the numbers."""
        self.pipeline.finish()
        if self.watcher is not None:
            self.watcher.finish()
            self.view.close()
        stats = self._sources.stats
        lat = self.latency
        p50, p99 = lat.percentiles()
        return LiveResult(
            duration_s=duration,
            ended_by=ended,
            counts={k: v for s in stats.values() for k, v in s.by_type.items()},
            dropped={name: s.dropped for name, s in stats.items()},
            latency_ms={"p50": p50, "p99": p99, "frames": len(lat.samples)},
            latency_samples=list(zip(lat.frame_t, lat.samples, lat.after_arrival, strict=True)),
            board=self.board.stats.to_dict() | {"metadata": self.board.metadata["board"]},
            commands=lat.commands,
            files=self.files,
            pipeline=self.pipeline,
            sources=stats,
            warm_up_s=self.warm_up_s,
        )

    def _ended_by(self) -> str:
        src = self._sources
        if src is not None and src.ended_by is not None:
            if src.ended_by == "sim":
                return "the simulated trial ended (route finished or its duration)"
            return f"{src.ended_by} stream ended"
        if self._stop_requested:
            return "stopped"
        return "duration"

    def _config(self, loc, ctl_cfg, initial, proposed) -> dict[str, Any]:
        from experiments.run import VERSION, _jsonable

        opts = self.options
        return {
            "command": "live",
            "walker_slam_version": VERSION,
            # the run's clock: t = time.monotonic() - host_clock_start (to line a recording
            # up with other processes of the machine)
            "host_clock_start": self.clock.start,
            "initial_pose": list(initial),
            "localizer": opts.localizer,
            "localizer_config": _jsonable(loc.config),
            "source_localizer_settings": proposed,
            "controller": opts.controller,
            "controller_config": _jsonable(ctl_cfg),
            "loop": asdict(opts.loop),
            "devices": {
                "serial": opts.serial if opts.sim is None else "sim",
                "depth": opts.depth,
                "camera": opts.camera,
                "camera_yaml": opts.camera_yaml,
            },
            "calibration_file": opts.calibration,
            "mitigations": self.mitigated.record(),
            "calibration_override": self.calibration_override,
            "sim": asdict(opts.sim) if opts.sim is not None else None,
        }

    def _status(self, pipeline: Pipeline, board: ArduinoBoard, latency: _Latency) -> LiveStatus:
        src = self._sources
        assert src is not None
        now = self.clock.now()
        rates, dropped, stalled = {}, {}, []
        for name, s in src.stats.items():
            rates[name] = s.rate_hz(now)
            dropped[name] = s.dropped
            stalled.extend(name if k == "*" else f"{name}/{k}" for k in sorted(s.stalled))
        st: BoardStats = board.stats
        tick = st.last_tick
        board_errors = st.bad_lines + st.seq_gaps
        if st.status is not None:
            b = st.status
            board_errors += b.rx_bad_crc + b.rx_malformed + b.rx_overflow
        est = pipeline.localizer.estimate()
        cov = np.asarray(est.covariance)
        cmds = pipeline.recorded.commands
        last = cmds[-1] if cmds else None
        safe = self._safe
        return LiveStatus(
            t=now,
            rates_hz=rates,
            dropped=dropped,
            stalled=stalled,
            latency_ms=latency.percentiles(last=300),
            commanded_nm=(last.left_nm, last.right_nm) if last else (math.nan, math.nan),
            board_pwm=(tick.pwm_left, tick.pwm_right) if tick else None,
            board_timed_out=bool(tick and tick.timed_out),
            board_errors=board_errors,
            sigma_xy_m=float(math.sqrt(max(cov[0, 0] + cov[1, 1], 0.0))),
            sigma_theta_deg=float(math.degrees(math.sqrt(max(cov[2, 2], 0.0)))),
            stale=safe.last_stale if safe is not None else (),
            events=list(self._events),
            view_url=self.view_url,
        )


def _both(first, second):
    """Call `first` (if any), then `second`, with the same arguments."""
    if first is None:
        return second

    def both(*args):
        first(*args)
        second(*args)

    return both


def run_live(
    options: LiveOptions, on_status: Callable[[LiveStatus], None] | None = None
) -> LiveResult:
    """One live run with `options`; see LiveRun."""
    return LiveRun(options, on_status).run()


@dataclass
class BoardBenchResult:
    """What `walkerslam board` saw."""

    handshake: Any
    duration_s: float
    ticks: int
    counts: tuple[int, int]
    stats: dict[str, Any]
    files: dict[str, Path]


@dataclass
class BoardReading:
    """One update of the bench tool's live display."""

    t: float
    counts: tuple[int, int]
    rate_hz: float
    pwm: tuple[int, int] | None
    timed_out: bool
    stats: BoardStats


def bench_board(
    port: str,
    *,
    calibration: WalkerCalibration | None = None,
    duration_s: float | None = None,
    record: str | None = None,
    brake_nm: tuple[float, float] | None = None,
    on_update: Callable[[BoardReading], None] | None = None,
    stop: threading.Event | None = None,
    config: BoardConfig | None = None,
) -> BoardBenchResult:
    """The bench tool for wiring the walker: handshake, the counts live, a brake command
    held for the duration (torques in N·m), ticks and commands recorded to a trial log.
    Ends at the duration or when `stop` is set; always releases the brakes."""
    cal = calibration or WalkerCalibration()
    clock = HostClock()
    board = ArduinoBoard(port, cal, clock, config)
    hs = board.open()
    stop = stop or threading.Event()
    files: dict[str, Path] = {}
    writer = None
    if record:
        files["log"] = Path(record)
        writer = _bench_recorder(files["log"], cal, board, port, brake_nm, duration_s)
    watcher = _close_when(stop, duration_s, board)
    t0 = clock.now()
    counts = _BenchCounts()
    try:
        if brake_nm is not None:
            cmd = BrakeCommand(clock.now(), brake_nm[0], brake_nm[1], "board-bench")
            board.send(cmd)
            if writer is not None:
                writer(cmd)
        for msg in board.messages():
            if writer is not None:
                writer(msg)
            counts.add(msg)
            now = clock.now()
            if on_update is not None and now - counts.last_update >= 0.1:
                on_update(counts.reading(now, now - t0, board))
    finally:
        stop.set()
        board.close()
        watcher.join(timeout=2.0)
        if writer is not None:
            if brake_nm is not None:
                off = cal.brake.torque_off_nm
                writer(BrakeCommand(clock.now(), off, off, "board-bench"))
            writer.close()
    return BoardBenchResult(
        hs, clock.now() - t0, counts.ticks, counts.counts, board.stats.to_dict(), files
    )


def _bench_recorder(
    path: Path,
    cal: WalkerCalibration,
    board: ArduinoBoard,
    port: str,
    brake_nm: tuple[float, float] | None,
    duration_s: float | None,
) -> ThreadedRecorder:
    """The bench tool's trial log, with its settings and the board's metadata."""
    settings = {
        "command": "board",
        "port": str(port),
        "brake_nm": list(brake_nm) if brake_nm else None,
        "duration_s": duration_s,
    }
    return ThreadedRecorder.open(path, cal, {"config": settings, **board.metadata})


def _close_when(stop: threading.Event, duration_s: float | None, board) -> threading.Thread:
    """A started thread that closes the board (zero brake; its messages() ends) when
    `stop` is set or after duration_s (None: only on stop)."""

    def closer() -> None:
        stop.wait(duration_s)
        board.close()

    watcher = threading.Thread(target=closer, name="board-bench-stop", daemon=True)
    watcher.start()
    return watcher


class _BenchCounts:
    """What the bench tool counts: encoder messages, the latest counts, and the times of
    the recent ones (for the rate over the last second)."""

    def __init__(self) -> None:
        self.ticks = 0
        self.counts = (0, 0)
        self.recent: deque[float] = deque(maxlen=500)
        self.last_update = -math.inf

    def add(self, msg: Message) -> None:
        """Count one message from the board (only encoder messages count)."""
        if isinstance(msg, EncoderTicks):
            self.ticks += 1
            self.counts = (msg.left, msg.right)
            self.recent.append(msg.t)

    def reading(self, now: float, elapsed: float, board: ArduinoBoard) -> BoardReading:
        """The display's update at host time `now` (`elapsed` since the start)."""
        self.last_update = now
        tick = board.stats.last_tick
        rate = sum(1 for t in self.recent if now - t <= 1.0)
        return BoardReading(
            elapsed,
            self.counts,
            float(rate),
            (tick.pwm_left, tick.pwm_right) if tick else None,
            bool(tick and tick.timed_out),
            board.stats,
        )
