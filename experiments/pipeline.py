"""source → localizer → mapper (→ controller): one loop for replay, simulation and live use.

`Pipeline.feed(msg)` is the whole data path: every message goes to the localizer; depth
frames and laser scans go to the mapper at the localizer's current pose (and, when
ground truth is known, to a reference mapper at the true pose, so the two maps can be
compared). `run_closed_loop` adds the controller and the brake sink around a timed
source (`hardware.source`: the simulator, or live devices).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from control.base import ControlInput, Controller
from control.safety import SafeController, SafetyConfig
from hardware.calibration import WalkerCalibration
from hardware.choices import Choice, coerce
from hardware.errors import ConfigError
from hardware.messages import (
    BrakeCommand,
    Collision,
    DepthFrame,
    EncoderTicks,
    GroundTruthPose,
    LaserScan,
    Message,
    VelocityOdometry,
)
from hardware.source import CommandSink, TimedSource
from mapping.hygiene import MapHygiene
from mapping.mapper import MapperConfig, OccupancyMapper
from mapping.scan_features import FeatureConfig, corner_sightings
from slam.base import FrameConsumer, Localizer, MapScorer
from slam.trajectory import Trajectory

# Ground truth is used for the reference map only when it is this close in time.
GROUNDTRUTH_TOLERANCE_S = 0.03


@dataclass
class Recorded:
    """What a run saw besides the localizer's own output."""

    groundtruth_t: list[float] = field(default_factory=list)
    groundtruth: list[tuple[float, float, float]] = field(default_factory=list)
    commands: list[BrakeCommand] = field(default_factory=list)
    collisions: list[Collision] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=dict)
    # messages dropped because their time is earlier than the previous one of their type
    out_of_order: dict[str, int] = field(default_factory=dict)
    t_first: float = math.nan
    t_last: float = math.nan
    # laser scans' hits (K×2, walker frame) with their times and the true pose at each
    # (NaN where none is near): the map's sharpness at any trajectory (experiments.sharpness)
    scan_t: list[float] = field(default_factory=list)
    scan_hits: list[np.ndarray] = field(default_factory=list)
    scan_truth: list[np.ndarray] = field(default_factory=list)

    def groundtruth_trajectory(self) -> Trajectory | None:
        if not self.groundtruth_t:
            return None
        t = np.array(self.groundtruth_t)
        keep = np.concatenate([[True], np.diff(t) > 0])
        return Trajectory(t[keep], np.array(self.groundtruth)[keep])


class Pipeline:
    """Feeds messages to a localizer and the occupancy mapper(s)."""

    def __init__(
        self,
        localizer: Localizer,
        calibration: WalkerCalibration,
        mapper_config: MapperConfig | None = None,
        reference_map: bool = True,
        scan_features: FeatureConfig | None = None,
    ) -> None:
        self.localizer = localizer
        # laser corners (mapping.scan_features) as sightings without IDs, after each scan
        self.scan_features = scan_features
        self.calibration = calibration
        self.mapper = OccupancyMapper(calibration, mapper_config)
        self.reference = OccupancyMapper(calibration, mapper_config) if reference_map else None
        self.recorded = Recorded()
        self._latest_truth: GroundTruthPose | None = None
        hygiene = self.mapper.config.hygiene
        self.hygiene = MapHygiene(hygiene) if hygiene.active else None
        if isinstance(localizer, MapScorer):  # it scores frames against the shared map
            localizer.attach_map(self.mapper)
        # A smoother revises past poses: keep its frames (keyed by time) to rebuild the map.
        self._keep_frames = localizer.revises_past
        self._built_revision = localizer.revision
        self._rebuild = None  # (job, revision) of a background rebuild
        self._last_t: dict[str, float] = {}  # per message type, for the order check

    def feed(self, msg: Message) -> None:
        """One message to the localizer and the mappers. A message older than the previous
        one of its type (a time going backwards within a stream) is dropped and counted in
        `recorded.out_of_order`: motion models, trajectories and maps assume each stream's
        time only moves forward."""
        rec = self.recorded
        name = type(msg).__name__
        last = self._last_t.get(name)
        if last is not None and msg.t < last:
            rec.out_of_order[name] = rec.out_of_order.get(name, 0) + 1
            return
        self._last_t[name] = msg.t
        rec.counts[name] = rec.counts.get(name, 0) + 1
        if math.isnan(rec.t_first):
            rec.t_first = msg.t
        rec.t_last = max(msg.t, rec.t_last) if not math.isnan(rec.t_last) else msg.t
        if isinstance(msg, DepthFrame | LaserScan):
            self._frame(msg)
            return
        self.localizer.process(msg)
        if isinstance(msg, GroundTruthPose):
            self._latest_truth = msg
            rec.groundtruth_t.append(msg.t)
            rec.groundtruth.append((msg.x, msg.y, msg.theta))
        elif isinstance(msg, BrakeCommand):
            rec.commands.append(msg)
            if self.hygiene is not None:
                self.hygiene.brake_levels = self.calibration.brake.levels(msg)
        elif isinstance(msg, Collision):
            rec.collisions.append(msg)

    def _frame(self, msg: DepthFrame | LaserScan) -> None:
        """A depth frame or scan, projected once: to the localizer, then into the map at
        its (updated) pose and into the reference map at the true pose."""
        projection = self.mapper.project(msg)
        if isinstance(self.localizer, FrameConsumer):
            self.localizer.process_frame(msg, projection)
        else:
            self.localizer.process(msg)
        if self.scan_features is not None and isinstance(msg, LaserScan):
            corners = corner_sightings(msg, self.scan_features)
            self.recorded.counts["scan_corners"] = self.recorded.counts.get(
                "scan_corners", 0
            ) + len(corners)
            if len(corners):
                self.localizer.process(corners)
        estimate = self.localizer.estimate()
        if self._hygienic(msg.t, estimate):
            key = msg.t if self._keep_frames else None
            self.mapper.integrate_projection(projection, estimate.pose, key)
        truth, true_pose = self._latest_truth, None
        if truth is not None and abs(truth.t - msg.t) <= GROUNDTRUTH_TOLERANCE_S:
            true_pose = np.array([truth.x, truth.y, truth.theta])
        if isinstance(msg, LaserScan):
            rec = self.recorded
            rec.scan_t.append(msg.t)
            rec.scan_hits.append(np.array(projection.raw.obstacles))  # not a view of all points
            rec.scan_truth.append(np.full(3, math.nan) if true_pose is None else true_pose)
        if self.reference is not None and true_pose is not None:
            self.reference.integrate_projection(projection, true_pose)

    def _hygienic(self, t: float, estimate) -> bool:
        """Map hygiene before a frame is mapped (`mapping.hygiene`): reset the map when
        due, fade it, and say whether the frame may be mapped."""
        h = self.hygiene
        if h is None:
            return True
        if h.due_reset(t):
            if self._rebuild is not None:
                self.finish_rebuild(wait=True)
            self.mapper.reset()
        factor = h.decay_factor(t)
        if factor < 1.0:
            self.mapper.decay(factor)
        return h.admit(t, estimate.pose, estimate.covariance)

    def rebuild_map(self, background: bool = False) -> bool:
        """Re-map the kept frames at the localizer's current (smoothed) trajectory, when it
        has revised the past since the map was built. Returns whether it did (with
        background=True: whether it started; `finish_rebuild` switches to the new map
        when it is ready, so a control loop never waits for it)."""
        if self._rebuild is not None:
            self.finish_rebuild(wait=True)
        if not self._keep_frames or self.localizer.revision == self._built_revision:
            return False
        keys = np.array(sorted(self.mapper.keys()), dtype=float)
        poses = self.localizer.trajectory().interpolate(keys) if len(keys) else []
        revised = {float(k): p for k, p in zip(keys, poses, strict=True)}
        if background:
            self._rebuild = (self.mapper.start_rebuild(revised), self.localizer.revision)
            return True
        if revised:
            self.mapper.rebuild(revised)
        self._built_revision = self.localizer.revision
        return True

    def finish_rebuild(self, wait: bool = False) -> bool:
        """Switch to a background rebuild's map if it is ready (or, wait, once it is).
        Returns whether it switched."""
        if self._rebuild is None or not (wait or self._rebuild[0].done):
            return False
        job, revision = self._rebuild
        self._rebuild = None
        self.mapper.finish_rebuild(job)
        self._built_revision = revision
        return True

    def run(
        self, source: Iterable[Message], progress: Callable[[float], None] | None = None
    ) -> None:
        """Feed a whole source, then `finish`."""
        for msg in source:
            self.feed(msg)
            if progress is not None:
                progress(msg.t)
        self.finish()

    def finish(self) -> None:
        """The source has ended: the localizer's last pass (`Localizer.finish`), then the
        map rebuilt if that or anything before revised the past."""
        self.localizer.finish()
        self.rebuild_map()


class VelocityEstimator:
    """Forward speed and yaw rate from the localizer's poses over the last few ticks
    (the thesis averaged over the last two control steps)."""

    def __init__(self, window: int = 3) -> None:
        self._poses: deque[tuple[float, np.ndarray]] = deque(maxlen=window)

    def update(self, t: float, pose: np.ndarray) -> tuple[float, float]:
        self._poses.append((t, pose.copy()))
        (t0, p0), (t1, p1) = self._poses[0], self._poses[-1]
        dt = t1 - t0
        if dt <= 0:
            return 0.0, 0.0
        heading = 0.5 * (p0[2] + p1[2]) if abs(p1[2] - p0[2]) < math.pi else p1[2]
        d = p1[:2] - p0[:2]
        v = (d[0] * math.cos(heading) + d[1] * math.sin(heading)) / dt
        omega = math.remainder(p1[2] - p0[2], 2 * math.pi) / dt
        return v, omega


class Trigger(Choice):
    """When the closed loop runs its controller (LoopConfig)."""

    TIMER = "timer"
    FRAME = "frame"


@dataclass(frozen=True)
class LoopConfig:
    """Closed-loop timing.

    trigger "timer": the controller runs at rate_hz of the source's clock. "frame": it
    runs right after each depth frame or scan reaches the map (the live walker's lowest
    frame-to-command latency), and at rate_hz only while no frame comes (so the safety
    layer's stale ramp still runs when the camera stalls).
    latency_s: the command reaches the brakes this much later (computation + serial +
    brake driver) — a simulated delay; a live run has the real one and uses 0.
    Every command passes through the safety layer configured by `safety`
    (control.safety). With a smoother (a localizer that revises the past), the map the
    controller reads is rebuilt along the smoothed trajectory every map_rebuild_s of
    trial time when the past has changed (0: only at the end), so the corrections reach
    the controller, not just the report. A rebuild re-maps every kept frame (~0.7 ms
    each): every 10 s costs about as much as the rest of the loop on a 90 s GTSAM trial;
    every 2 s, 4× more. rebuild_in_background: rebuild in a thread and switch to the new
    map when it is ready (a live loop: a rebuild of a long run's frames takes seconds,
    which would leave the brakes without commands meanwhile); the map the controller
    reads is then the same, a little later."""

    rate_hz: float = 10.0
    latency_s: float = 0.03
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    map_rebuild_s: float = 10.0
    trigger: Trigger = Trigger.TIMER
    rebuild_in_background: bool = False

    def __post_init__(self) -> None:
        coerce(self, trigger=Trigger)
        if not self.rate_hz > 0 or self.latency_s < 0:
            raise ConfigError("LoopConfig needs rate_hz > 0 and latency_s >= 0")


class FeedOrder:
    """Writes each message the loop fed to a trial log with a log time that never goes
    back (the later of its own time and the previous log time), so that a replay, which
    reads in log-time order, feeds them in the order the run did — also when a live
    device delivered a message later than one of another stream."""

    def __init__(self, writer) -> None:
        self.writer = writer
        self.last = 0.0

    def __call__(self, msg: Message) -> None:
        self.last = max(self.last, msg.t)
        self.writer.write(msg, log_time=self.last)


def run_closed_loop(
    source: TimedSource,
    sink: CommandSink,
    pipeline: Pipeline,
    controller: Controller,
    loop: LoopConfig = LoopConfig(),
    record: Callable[[Message], None] | None = None,
    progress: Callable[[float], None] | None = None,
    on_command: Callable[[BrakeCommand, DepthFrame | LaserScan | None], None] | None = None,
) -> None:
    """Run a timed source (the simulator, live devices) in closed loop until it is done.

    Each control step: feed the source's messages up to the step through the pipeline,
    compute a brake command from the localizer's pose and the shared map, pass it
    through the safety layer (unless `controller` already is a SafeController) and send
    it to `sink` after the latency. The controller sees the torques of the last applied
    command and the times of the latest localizer update, depth frame / scan and
    odometry message the pipeline has received. Every message and command also goes to
    `record` (e.g. a `FeedOrder` around a log writer); `on_command(cmd, frame)` is
    called after each command is sent, with the frame that triggered it (None for a
    timer step).
    """
    period = 1.0 / loop.rate_hz
    on_frame = loop.trigger == "frame"
    if not isinstance(controller, SafeController):
        controller = SafeController(controller, pipeline.calibration, loop.safety)
    steps = _ControlSteps(source, pipeline, controller, loop, record)
    k = 1  # timer trigger: step k is at k·period
    next_step = period  # frame trigger: the timer step if no frame comes first
    while not source.done:
        until = next_step if on_frame else k * period
        frame = steps.advance(until, on_frame)
        if source.done:
            break
        # the step's time: the timer's, or (frame trigger) the source's clock now — the
        # frame's time in simulation, a little after it live
        t = source.t if on_frame else until
        # a live loop that fell behind its clock skips the steps it missed
        k = max(k + 1, math.floor(source.t / period) + 1)
        next_step = t + period
        steps.refresh_map(t)
        cmd = steps.command(t)
        if loop.latency_s > 0:
            steps.advance(t + loop.latency_s)
        sink.send(cmd)
        steps.applied = (cmd.left_nm, cmd.right_nm)
        if on_command is not None:
            on_command(cmd, frame)
        if progress is not None:
            progress(source.t)


class _ControlSteps:
    """What run_closed_loop keeps between its steps: feeding the source's messages, the
    map rebuilds, the controller's input and its command."""

    def __init__(
        self,
        source: TimedSource,
        pipeline: Pipeline,
        controller: Controller,
        loop: LoopConfig,
        record: Callable[[Message], None] | None,
    ) -> None:
        self.source, self.pipeline, self.controller = source, pipeline, controller
        self.loop, self.record = loop, record
        self.velocity = VelocityEstimator()
        off = pipeline.calibration.brake.torque_off_nm
        self.applied = (off, off)  # the torques of the last command sent
        self.latest = {"map": -math.inf, "sensor": -math.inf}
        self.rebuilt_at = 0.0

    def advance(self, until: float, stop_at_frame: bool = False) -> DepthFrame | LaserScan | None:
        """Feed the source's messages up to `until` (or its next frame); the last frame."""
        frame = None
        for msg in self.source.poll(until, stop_at_frame):
            self.pipeline.feed(msg)
            if isinstance(msg, DepthFrame | LaserScan):
                self.latest["map"] = msg.t
                frame = msg
            elif isinstance(msg, EncoderTicks | VelocityOdometry):
                self.latest["sensor"] = msg.t
            if self.record is not None:
                self.record(msg)
        return frame

    def refresh_map(self, t: float) -> None:
        """Switch to a background rebuild that is ready; rebuild every map_rebuild_s."""
        loop = self.loop
        if loop.rebuild_in_background:
            self.pipeline.finish_rebuild()
        if loop.map_rebuild_s > 0 and t - self.rebuilt_at >= loop.map_rebuild_s:
            self.pipeline.rebuild_map(background=loop.rebuild_in_background)
            self.rebuilt_at = t

    def command(self, t: float) -> BrakeCommand:
        """The controller's command at t from the localizer's pose and the shared map
        (fed to the pipeline and recorded)."""
        est = self.pipeline.localizer.estimate()
        v, omega = self.velocity.update(t, est.pose)
        inp = ControlInput(
            t,
            self.pipeline.mapper.occupied_xy(),
            est.pose,
            v,
            omega,
            brake_nm=self.applied,
            pose_t=est.t if math.isfinite(est.t) else -math.inf,
            map_t=self.latest["map"],
            sensor_t=self.latest["sensor"],
        )
        cmd = self.controller.command(inp)
        self.pipeline.feed(cmd)
        if self.record is not None:
            self.record(cmd)
        return cmd
