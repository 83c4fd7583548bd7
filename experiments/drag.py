"""Drag metrics: how brake-induced wheel slip drags obstacles across the map, and what the
dragged map does to the braking controller (thesis §6.4, Fig 6.11).

All of them are measured while a trial log is replayed: `Observed` wraps the log's
message stream and calls the observers below before and after the pipeline takes each
message, so they see the localizer's pose and the map exactly as they were at that
moment (the map the controller saw, not the final one). Their figures (`drag.png`,
`controller_replay.png`) are drawn by `experiments.drag_figures`; this module holds no
plotting code.

Definitions (the README's wording):

- **Phantom area over time** (`PhantomSeries`): `phantom_area_m2` (occupied area farther
  than 10 cm from every true obstacle outline) of the map as it was built, sampled every
  `phantom_period_s` of log time, and once more at the end (after a smoother's rebuild),
  so the last sample is the final `phantom_area_m2`. The same for the reference map (the
  same frames mapped at the true poses). `growth_m2` sums the increases between samples;
  `growth_while_braking_m2` weighs each increase by the share of its interval with a
  brake engaged, to compare with `braking_time_fraction`.
- **Obstacle drag** (`FrameDrag`): for every depth frame (or laser scan) with a true pose
  within 30 ms, its obstacle points p (walker frame, at most 256 per frame, evenly spread)
  are placed at the pose the mapper used (E, the localizer's estimate) and at the true
  pose (T); the drag of a point is d = E⊕p − T⊕p [m] (world frame), i.e. how far from its
  true place the frame puts that piece of obstacle. Reported: mean and 95th percentile
  of |d|; `toward_turn_mean_m`, the mean component of d along the true walker's left
  axis signed by the true turn direction (> 0: dragged toward the inside of the turn);
  `inward_mean_m`, the mean lateral component toward the walker's centre line
  (−sign(p_y)·d_y; > 0: obstacles beside the walker are dragged in front of it).
  `absolute` uses the poses as they are; `local` replaces E by
  T(t−w) ⊕ (E(t−w)⁻¹ ⊕ E(t)), the estimated motion over the last w = 1 s applied to the
  true pose then: the drag added within the last second (the obstacle-point version of
  the relative pose error), which separates what a braked turn adds from the error
  accumulated before it. Frames are grouped into `braked_turn` (a logged brake command
  above the residual torque by more than 0.05 N·m in effect — the last command before
  the frame — and a true yaw rate above 0.15 rad/s), `other`, and `all`. E is the pose
  at the time the frame was mapped: for a smoother, its online estimate, not the
  smoothed pose the final map is rebuilt with.
- **Over-steer** (`over_steer`): at every logged brake command the same controller is also
  run at the true pose, with the true speed and yaw rate, on the reference map as built
  so far (the frames mapped at the true poses): the command the true situation required.
  The heading change a command series produces is taken from the thesis's linear yaw
  dynamics (5.2): a brake torque difference gives a steady yaw rate
  u = r_b (τ_L − τ_R) / (r_wheel Dφ) (> 0: left), and for this first-order system the
  heading change it eventually causes is ∫u dt whatever the inertia. Over braking
  episodes (runs of ticks where either series brakes), over-steer is how much farther the
  commands under test turn in their own direction than the reference:
  max(0, s (∫u_test − ∫u_ref)), s = sign ∫u_test (steering the wrong way counts in full);
  under-steer the opposite. The commands under test are the logged ones (recorded
  controller, the localizer it ran on) or, with `replay --controller`, the recomputed
  ones (that controller on the replay's localizer). A model figure: the user's handle
  forces are held the same in both series (in the linear model they cancel in the
  difference, so ∫u_test − ∫u_ref is the extra heading, while ∫u alone overstates the
  turn a user who steers against the brakes makes); the wheels' rolling direction, brake
  lag and the slip itself are ignored. The turn decision is discontinuous (left and
  right free areas near a tie), so small pose or map errors flip single ticks; over- and
  under-steer both collect those flips.
- **Braking impulse**: ∫ max(τ − τ_off, 0) dt per wheel and in total
  (`metrics.braking_impulse_per_wheel`).
- **Controller replay** (`CommandRecomputer`): at each logged brake command, before the
  pipeline takes it, the named controller gets the replay's current pose, the speed and
  yaw rate from `VelocityEstimator` on those poses, and the replay's map — what the
  simulator's closed loop does at each tick — and its command is compared with the logged
  one (`metrics.command_differences`).
"""

from __future__ import annotations

import csv
import math
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from control.base import CONTROLLERS, ControlInput
from experiments.metrics import command_differences, distance_to_outlines
from experiments.pipeline import GROUNDTRUTH_TOLERANCE_S, Pipeline, VelocityEstimator
from hardware.calibration import WalkerCalibration
from hardware.geometry import between, compose
from hardware.messages import (
    BrakeCommand,
    DepthFrame,
    EncoderTicks,
    GroundTruthPose,
    LaserScan,
    Message,
    VelocityOdometry,
)
from mapping.depth_points import project_depth_frame
from mapping.scan_points import scan_to_observation
from slam.trajectory import Trajectory

MAX_POINTS_PER_FRAME = 256


@dataclass(frozen=True)
class DragConfig:
    """phantom_period_s: sampling period of the phantom-area series [s of log time];
    phantom_tolerance_m: distance from a true outline beyond which a cell is a phantom;
    brake_threshold_nm: a brake is engaged when its torque exceeds the residual by this;
    turn_rate_threshold_rad_s: the walker is turning when its true |yaw rate| exceeds this;
    local_window_s: w of the local drag; yaw_damping_nms: Dφ of the over-steer model
    (the simulator's default, mid of the thesis's 7–11 N·m·s/rad)."""

    phantom_period_s: float = 1.0
    phantom_tolerance_m: float = 0.1
    brake_threshold_nm: float = 0.05
    turn_rate_threshold_rad_s: float = 0.15
    local_window_s: float = 1.0
    yaw_damping_nms: float = 9.0

    def __post_init__(self) -> None:
        if self.phantom_period_s <= 0 or self.local_window_s <= 0 or self.yaw_damping_nms <= 0:
            raise ValueError("phantom_period_s, local_window_s and yaw_damping_nms must be > 0")


class Observer(Protocol):
    def before(self, msg: Message) -> None: ...

    def after(self, msg: Message) -> None: ...


class Observed:
    """The messages of `source`, with each observer's `before(msg)` called before the
    consumer (a Pipeline) takes msg and `after(msg)` once it has (when it asks for the
    next one, or the stream ends). `seconds` is the time spent in the observers, so that
    a replay's real-time factor can leave the evaluation out."""

    def __init__(self, source: Iterable[Message], observers: Sequence[Observer]) -> None:
        self.source, self.observers = source, list(observers)
        self.seconds = 0.0

    def __iter__(self) -> Iterator[Message]:
        if not self.observers:
            yield from self.source
            return
        clock, observers = time.perf_counter, self.observers
        for msg in self.source:
            t0 = clock()
            for o in observers:
                o.before(msg)
            self.seconds += clock() - t0
            yield msg
            t0 = clock()
            for o in observers:
                o.after(msg)
            self.seconds += clock() - t0


class TruthTracker:
    """The latest ground-truth pose of the stream."""

    def __init__(self) -> None:
        self.latest: GroundTruthPose | None = None

    def before(self, msg: Message) -> None:
        pass

    def after(self, msg: Message) -> None:
        if isinstance(msg, GroundTruthPose):
            self.latest = msg

    def pose_at(self, t: float) -> np.ndarray | None:
        """The latest true pose if it is within GROUNDTRUTH_TOLERANCE_S of t, else None."""
        g = self.latest
        if g is None or abs(g.t - t) > GROUNDTRUTH_TOLERANCE_S:
            return None
        return np.array([g.x, g.y, g.theta])


# -- brake state and true motion ------------------------------------------------------


def brake_engaged_at(
    commands: Sequence[BrakeCommand], times: np.ndarray, torque_off_nm: float, threshold_nm: float
) -> np.ndarray:
    """Whether the last command strictly before each time has a brake above the residual
    torque by more than threshold (the command of the same tick is not applied yet)."""
    times = np.asarray(times, float)
    if not commands:
        return np.zeros(len(times), bool)
    ct = np.array([c.t for c in commands])
    level = np.array([max(c.left_nm, c.right_nm) for c in commands]) - torque_off_nm
    i = np.searchsorted(ct, times, side="left") - 1
    return (i >= 0) & (level[np.maximum(i, 0)] > threshold_nm)


def heading_error_while_braking(
    est: Trajectory,
    truth: Trajectory,
    commands: Sequence[BrakeCommand],
    torque_off_nm: float,
    threshold_nm: float,
) -> dict[str, float]:
    """How much the estimated heading's error grows while a brake is engaged — the
    over-rotation slip causes. Per braking episode (a run of ground-truth times with a
    brake engaged, `brake_engaged_at`), the change of the signed heading error from its
    start to its end; `heading_error_braking_deg` sums their magnitudes over the trial,
    `heading_error_per_episode_deg` is their mean, `braking_episodes` their number."""
    t = truth.t
    e = est.interpolate(t)
    err = np.unwrap(np.remainder(e[:, 2] - truth.poses[:, 2] + np.pi, 2 * np.pi) - np.pi)
    on = brake_engaged_at(commands, t, torque_off_nm, threshold_nm)
    edges = np.diff(np.concatenate([[0], on.astype(int), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    added = np.degrees(np.abs(err[ends] - err[starts])) if len(starts) else np.zeros(0)
    return {
        "heading_error_braking_deg": float(added.sum()),
        "heading_error_per_episode_deg": float(added.mean()) if len(added) else 0.0,
        "braking_episodes": len(added),
    }


def yaw_rate(truth: Trajectory, times: np.ndarray, half_window_s: float = 0.1) -> np.ndarray:
    """Central-difference yaw rate [rad/s] of a trajectory at `times`."""
    th = np.unwrap(truth.poses[:, 2])
    lo = np.interp(np.asarray(times) - half_window_s, truth.t, th)
    hi = np.interp(np.asarray(times) + half_window_s, truth.t, th)
    return (hi - lo) / (2.0 * half_window_s)


def unwrapped_heading(truth: Trajectory, times: np.ndarray) -> np.ndarray:
    return np.interp(np.asarray(times, float), truth.t, np.unwrap(truth.poses[:, 2]))


# -- phantom area over time -----------------------------------------------------------


class _CellDistances:
    """Distance of map cells to the true outlines, cached by cell (a cell never moves).

    Exact up to `cap` [m]; a cell farther than cap from every outline may get any value
    above cap (inf when it is outside every outline's bounding box grown by cap), which
    keeps the cost to the outlines near each new cell.
    """

    def __init__(self, polygons: Sequence[np.ndarray], resolution: float, cap: float) -> None:
        self.polygons = [np.asarray(p, float) for p in polygons]
        self.resolution = resolution
        self.cap = cap
        if self.polygons:
            lo = np.array([p.min(axis=0) for p in self.polygons]) - cap
            hi = np.array([p.max(axis=0) for p in self.polygons]) + cap
            self._boxes = np.hstack([lo, hi])
        else:
            self._boxes = np.empty((0, 4))
        self._keys = np.empty(0, np.int64)
        self._dist = np.empty(0)

    def _distances(self, xy: np.ndarray) -> np.ndarray:
        out = np.full(len(xy), np.inf)
        b = self._boxes
        near = (
            (xy[:, None, 0] >= b[None, :, 0])
            & (xy[:, None, 1] >= b[None, :, 1])
            & (xy[:, None, 0] <= b[None, :, 2])
            & (xy[:, None, 1] <= b[None, :, 3])
        )
        for k in np.flatnonzero(near.any(axis=0)):
            idx = np.flatnonzero(near[:, k])
            d = distance_to_outlines(xy[idx], [self.polygons[k]])
            out[idx] = np.minimum(out[idx], d)
        return out

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, float).reshape(-1, 2)
        ij = np.floor(xy / self.resolution).astype(np.int64)
        keys = ij[:, 0] * (1 << 32) + (ij[:, 1] & 0xFFFFFFFF)
        pos = np.searchsorted(self._keys, keys)
        found = pos < len(self._keys)
        found[found] = self._keys[pos[found]] == keys[found]
        out = np.empty(len(xy))
        out[found] = self._dist[pos[found]]
        if not found.all():
            new_keys, first = np.unique(keys[~found], return_index=True)
            new_dist = self._distances(xy[~found][first])
            keys_all = np.concatenate([self._keys, new_keys])
            order = np.argsort(keys_all, kind="stable")
            self._keys = keys_all[order]
            self._dist = np.concatenate([self._dist, new_dist])[order]
            out[~found] = self._dist[np.searchsorted(self._keys, keys[~found])]
        return out


class PhantomSeries:
    """Samples the phantom area of the estimated and the reference map over log time."""

    def __init__(
        self, pipeline: Pipeline, polygons: Sequence[np.ndarray], config: DragConfig
    ) -> None:
        self.pipeline = pipeline
        self.config = config
        res = pipeline.mapper.grid.resolution
        self.cell_area = res * res
        self._dist = _CellDistances(polygons, res, max(0.5, 2 * config.phantom_tolerance_m))
        self.t: list[float] = []
        self.phantom: list[float] = []
        self.occupied: list[float] = []
        self.reference: list[float] = []
        self._t0: float | None = None
        self._next = -math.inf

    def _area(self, xy: np.ndarray) -> float:
        if len(xy) == 0:
            return 0.0
        n = np.count_nonzero(self._dist(xy) > self.config.phantom_tolerance_m)
        return float(n * self.cell_area)

    def sample(self, t: float) -> None:
        p = self.pipeline
        occ = p.mapper.occupied_xy()
        ref = p.reference.occupied_xy() if p.reference is not None else None
        row = (
            self._area(occ),
            len(occ) * self.cell_area,
            math.nan if ref is None else self._area(ref),
        )
        if self.t and self.t[-1] == t:  # the final sample replaces one at the same time
            self.phantom[-1], self.occupied[-1], self.reference[-1] = row
            return
        self.t.append(t)
        self.phantom.append(row[0])
        self.occupied.append(row[1])
        self.reference.append(row[2])

    def before(self, msg: Message) -> None:
        pass

    def after(self, msg: Message) -> None:
        if self._t0 is None:
            self._t0 = msg.t
            self._next = msg.t
        if msg.t >= self._next:
            self.sample(msg.t)
            period = self.config.phantom_period_s
            self._next = self._t0 + (math.floor((msg.t - self._t0) / period) + 1) * period

    def finish(self, t_end: float) -> None:
        """The last sample, of the final map (after a smoother's rebuild)."""
        if self._t0 is not None:
            self.sample(max(t_end, self.t[-1] if self.t else t_end))

    def summary(self, commands: Sequence[BrakeCommand], torque_off_nm: float) -> dict[str, Any]:
        t = np.array(self.t)
        ph = np.array(self.phantom)
        out: dict[str, Any] = {"period_s": self.config.phantom_period_s, "samples": len(t)}
        if len(t) == 0:
            return out
        growth = np.maximum(np.diff(ph), 0.0)
        # share of each interval with a brake engaged (on a 20 ms grid)
        grid = np.arange(t[0], t[-1], 0.02)
        engaged = brake_engaged_at(commands, grid, torque_off_nm, self.config.brake_threshold_nm)
        interval = np.clip(np.searchsorted(t, grid, side="right") - 1, 0, max(len(t) - 2, 0))
        hits = np.bincount(interval, weights=engaged, minlength=len(growth))[: len(growth)]
        counts = np.bincount(interval, minlength=len(growth))[: len(growth)]
        braked_share = hits / np.maximum(counts, 1)
        span = np.diff(t)
        out.update(
            {
                "final_m2": float(ph[-1]),
                "max_m2": float(ph.max()),
                "t_max_s": float(t[int(np.argmax(ph))] - t[0]),
                "mean_m2": float(ph.mean()),
                "growth_m2": float(growth.sum()),
                "growth_while_braking_m2": float(growth @ braked_share),
                "braking_time_fraction": float(braked_share @ span / span.sum())
                if span.sum() > 0
                else math.nan,
            }
        )
        ref = np.array(self.reference)
        if np.isfinite(ref).any():
            out["reference_final_m2"] = float(ref[-1])
            out["reference_max_m2"] = float(np.nanmax(ref))
        return out

    def write_csv(self, path: Path) -> Path:
        t0 = self.t[0] if self.t else 0.0
        with open(path, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(
                ["t", "t_rel_s", "phantom_area_m2", "occupied_area_m2", "reference_phantom_m2"]
            )
            for row in zip(self.t, self.phantom, self.occupied, self.reference, strict=True):
                w.writerow([f"{row[0]:.3f}", f"{row[0] - t0:.3f}", *(f"{v:.4f}" for v in row[1:])])
        return path


# -- obstacle drag ----------------------------------------------------------------------


def point_drag(
    points_walker: np.ndarray, estimated_pose: np.ndarray, true_pose: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Drag of walker-frame points placed at the estimated instead of the true pose.

    Returns (|d| [m], d_y, inward): d = E⊕p − T⊕p in the world; d_y its component along
    the true walker's left axis; inward = −sign(p_y)·d_y (> 0: toward the centre line,
    i.e. in front of the walker).
    """
    p = np.asarray(points_walker, float).reshape(-1, 2)
    d = _place(p, estimated_pose) - _place(p, true_pose)
    c, s = math.cos(true_pose[2]), math.sin(true_pose[2])
    lateral = -s * d[:, 0] + c * d[:, 1]
    return np.hypot(d[:, 0], d[:, 1]), lateral, -np.sign(p[:, 1]) * lateral


def _place(p: np.ndarray, pose: np.ndarray) -> np.ndarray:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.column_stack(
        [pose[0] + c * p[:, 0] - s * p[:, 1], pose[1] + s * p[:, 0] + c * p[:, 1]]
    )


@dataclass
class _Frames:
    t: list[float] = field(default_factory=list)
    # per frame, per point: (|d|, d_y, inward) absolute and local (local may be empty)
    absolute: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=list)
    local: list[tuple[np.ndarray, np.ndarray, np.ndarray] | None] = field(default_factory=list)


class FrameDrag:
    """Per depth frame / laser scan: the drag of its obstacle points (module doc)."""

    def __init__(self, pipeline: Pipeline, truth: TruthTracker, config: DragConfig) -> None:
        self.pipeline = pipeline
        self.truth = truth
        self.config = config
        mc = pipeline.mapper.config
        q = mc.point_quantum_m
        self._quantum = mc.grid.resolution_m / 4.0 if q is None else q
        self.frames = _Frames()
        self.skipped = 0  # frames without a true pose close enough
        self._history: deque[tuple[float, np.ndarray, np.ndarray]] = deque()

    def _points(self, msg: DepthFrame | LaserScan) -> np.ndarray:
        mc = self.pipeline.mapper.config
        if isinstance(msg, DepthFrame):
            obs = project_depth_frame(
                msg, self.pipeline.calibration, mc.depth, None, quantum=self._quantum
            )
        else:
            obs = scan_to_observation(msg, (0.0, 0.0, 0.0), mc.scan)
        pts = np.asarray(obs.obstacles, float)
        if len(pts) > MAX_POINTS_PER_FRAME:
            pts = pts[np.linspace(0, len(pts) - 1, MAX_POINTS_PER_FRAME).round().astype(int)]
        return pts

    def before(self, msg: Message) -> None:
        pass

    def after(self, msg: Message) -> None:
        if not isinstance(msg, DepthFrame | LaserScan):
            return
        true = self.truth.pose_at(msg.t)
        if true is None:
            self.skipped += 1
            return
        est = np.array(self.pipeline.localizer.estimate().pose, float)  # the mapper's pose
        pts = self._points(msg)
        f = self.frames
        f.t.append(msg.t)
        f.absolute.append(_compact(point_drag(pts, est, true)))
        w = self.config.local_window_s
        h = self._history
        h.append((msg.t, est, true))
        while len(h) >= 2 and h[1][0] <= msg.t - w + 1e-6:
            h.popleft()
        t0, e0, g0 = h[0]
        if t0 <= msg.t - w + 1e-6 and msg.t - t0 < 2.0 * w:
            moved = compose(g0, between(e0, est))
            f.local.append(_compact(point_drag(pts, moved, true)))
        else:
            f.local.append(None)

    def summary(
        self, commands: Sequence[BrakeCommand], torque_off_nm: float, truth: Trajectory | None
    ) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """metrics.json's `drag` and the per-frame series (for the CSV and the figure)."""
        f, cfg = self.frames, self.config
        t = np.array(f.t)
        out: dict[str, Any] = {
            "frames": len(t),
            "frames_without_truth": self.skipped,
            "brake_threshold_nm": cfg.brake_threshold_nm,
            "turn_rate_threshold_rad_s": cfg.turn_rate_threshold_rad_s,
            "local_window_s": cfg.local_window_s,
        }
        if len(t) == 0 or truth is None or len(truth) < 2:
            return out, {}
        omega = yaw_rate(truth, t)
        braked = brake_engaged_at(commands, t, torque_off_nm, cfg.brake_threshold_nm)
        turning = np.abs(omega) > cfg.turn_rate_threshold_rad_s
        groups = {"all": np.ones(len(t), bool), "braked_turn": braked & turning}
        groups["other"] = ~groups["braked_turn"]
        turn_sign = np.sign(omega)
        out["braked_turn_frames"] = int(groups["braked_turn"].sum())
        for kind, per_frame in (("absolute", f.absolute), ("local", f.local)):
            out[kind] = {
                g: _drag_stats([per_frame[i] for i in np.flatnonzero(m)], turn_sign[m])
                for g, m in groups.items()
            }
        series = {
            "t": t,
            "true_yaw_rate": omega,
            "braked": braked,
            "braked_turn": groups["braked_turn"],
            "mean_m": np.array([_mean(a[0]) for a in f.absolute]),
            "local_mean_m": np.array([math.nan if a is None else _mean(a[0]) for a in f.local]),
            "toward_turn_mean_m": np.array(
                [_mean(a[1]) * s for a, s in zip(f.absolute, turn_sign, strict=True)]
            ),
            "local_toward_turn_mean_m": np.array(
                [
                    math.nan if a is None else _mean(a[1]) * s
                    for a, s in zip(f.local, turn_sign, strict=True)
                ]
            ),
        }
        return out, series


def _compact(arrays: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
    return tuple(a.astype(np.float32) for a in arrays)


def _mean(a: np.ndarray) -> float:
    return float(a.mean()) if len(a) else math.nan


def _drag_stats(
    frames: list[tuple[np.ndarray, np.ndarray, np.ndarray] | None], turn_sign: np.ndarray
) -> dict[str, Any]:
    keep = [(fr, s) for fr, s in zip(frames, turn_sign, strict=True) if fr is not None]
    mags = [fr[0] for fr, _ in keep]
    n = sum(len(m) for m in mags)
    out: dict[str, Any] = {"frames": len(keep), "points": n}
    if n == 0:
        return {
            **out,
            "mean_m": math.nan,
            "p95_m": math.nan,
            "toward_turn_mean_m": math.nan,
            "inward_mean_m": math.nan,
        }
    mag = np.concatenate(mags)
    toward = np.concatenate([fr[1] * s for fr, s in keep])
    inward = np.concatenate([fr[2] for fr, _ in keep])
    return {
        **out,
        "mean_m": float(mag.mean(dtype=np.float64)),
        "p95_m": float(np.percentile(mag, 95)),
        "toward_turn_mean_m": float(toward.mean(dtype=np.float64)),
        "inward_mean_m": float(inward.mean(dtype=np.float64)),
    }


def write_frames_csv(series: dict[str, np.ndarray], path: Path) -> Path:
    keys = list(series)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(keys)
        for i in range(len(series["t"])):
            row = []
            for k in keys:
                v = series[k][i]
                row.append(int(v) if isinstance(v, np.bool_ | bool) else f"{float(v):.4f}")
            w.writerow(row)
    return path


# -- controller replay and over-steer -------------------------------------------------


class CommandRecomputer:
    """At each logged BrakeCommand, before the pipeline takes it: the command a controller
    (registry name) gives at the pose and map `where(t)` returns — (occupied_xy, pose,
    pose_t) or None when unavailable — with speed and yaw rate from a VelocityEstimator on
    those poses, as `pipeline.run_closed_loop` builds its input each tick: the optional
    ControlInput fields it fills (the torques applied — the previous logged command —, the
    times of the latest pose, depth frame / scan and odometry) are filled the same way,
    and the controller is wrapped in the safety layer as the closed loop wraps it.
    """

    def __init__(
        self,
        name: str,
        calibration: WalkerCalibration,
        where: Callable[[float], tuple[np.ndarray, np.ndarray, float] | None],
    ) -> None:
        self.name = name
        controller = CONTROLLERS.create(name, calibration)
        safe = _safety_layer()
        self.safety_layer = safe is not None
        self.controller = safe(controller, calibration) if safe is not None else controller
        self.where = where
        self.velocity = VelocityEstimator()
        off = calibration.brake.torque_off_nm
        self._applied = (off, off)
        self._latest = {"map": -math.inf, "sensor": -math.inf}
        self.t: list[float] = []
        self.logged: list[tuple[float, float]] = []
        self.recomputed: list[tuple[float, float]] = []

    def before(self, msg: Message) -> None:
        if not isinstance(msg, BrakeCommand):
            return
        got = self.where(msg.t)
        self.t.append(msg.t)
        self.logged.append((msg.left_nm, msg.right_nm))
        if got is None:
            self.recomputed.append((math.nan, math.nan))
            return
        occupied, pose, pose_t = got
        v, omega = self.velocity.update(msg.t, pose)
        optional = {
            "brake_nm": self._applied,
            "pose_t": pose_t if math.isfinite(pose_t) else -math.inf,
            "map_t": self._latest["map"],
            "sensor_t": self._latest["sensor"],
        }
        inp = ControlInput(
            t=msg.t,
            occupied_xy=occupied,
            pose=pose,
            v=v,
            omega=omega,
            **{k: v for k, v in optional.items() if k in _INPUT_FIELDS},
        )
        cmd = self.controller.command(inp)
        self.recomputed.append((cmd.left_nm, cmd.right_nm))

    def after(self, msg: Message) -> None:
        if isinstance(msg, BrakeCommand):
            self._applied = (msg.left_nm, msg.right_nm)
        elif isinstance(msg, DepthFrame | LaserScan):
            self._latest["map"] = msg.t
        elif isinstance(msg, EncoderTicks | VelocityOdometry):
            self._latest["sensor"] = msg.t

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return (
            np.array(self.t),
            np.array(self.logged, float).reshape(-1, 2),
            np.array(self.recomputed, float).reshape(-1, 2),
        )

    def write_csv(self, path: Path, labels: tuple[str, str] = ("logged", "recomputed")) -> Path:
        t, a, b = self.arrays()
        names = [f"{label}_{wheel}_nm" for label in labels for wheel in ("left", "right")]
        with open(path, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["t", *names])
            for k in range(len(t)):
                w.writerow([f"{t[k]:.3f}", *(f"{v:.4f}" for v in (*a[k], *b[k]))])
        return path


_INPUT_FIELDS = {f.name for f in fields(ControlInput)}


def _safety_layer():
    """The closed loop's safety wrapper (control.safety.SafeController), if there is one."""
    try:
        from control.safety import SafeController
    except ImportError:
        return None
    return SafeController


def estimated_input(
    pipeline: Pipeline,
) -> Callable[[float], tuple[np.ndarray, np.ndarray, float]]:
    """The replay's own view: the localizer's pose and the mapper's map."""

    def where(t: float):
        est = pipeline.localizer.estimate()
        return pipeline.mapper.occupied_xy(), est.pose, est.t

    return where


def true_input(
    pipeline: Pipeline, truth: TruthTracker
) -> Callable[[float], tuple[np.ndarray, np.ndarray, float] | None]:
    """The true situation: the true pose and the reference map (frames at true poses)."""

    def where(t: float):
        pose = truth.pose_at(t)
        if pose is None or pipeline.reference is None:
            return None
        return pipeline.reference.occupied_xy(), pose, truth.latest.t

    return where


def brake_yaw_rate(
    left_nm: np.ndarray, right_nm: np.ndarray, calibration: WalkerCalibration, config: DragConfig
) -> np.ndarray:
    """Steady yaw rate [rad/s] a brake-torque difference gives in the linear model (5.2):
    u = r_b (τ_L − τ_R) / (r_wheel Dφ), > 0 turning left."""
    r_b = calibration.track_m / 2.0
    r_w = calibration.wheel_diameter_m / 2.0
    diff = np.asarray(left_nm, float) - np.asarray(right_nm, float)
    return r_b * diff / (r_w * config.yaw_damping_nms)


def over_steer(
    t: np.ndarray,
    tested: np.ndarray,
    reference: np.ndarray,
    t_end: float,
    calibration: WalkerCalibration,
    config: DragConfig,
    truth: Trajectory | None = None,
) -> tuple[dict[str, Any], list[dict[str, float]]]:
    """Over- and under-steer of a brake-command series against the reference commands at
    the same ticks (N×2 torques each; module doc). Ticks where either is NaN are left
    out. Returns the summary and one row per braking episode."""
    t = np.asarray(t, float)
    tested = np.asarray(tested, float).reshape(-1, 2)
    reference = np.asarray(reference, float).reshape(-1, 2)
    ok = np.isfinite(tested).all(axis=1) & np.isfinite(reference).all(axis=1)
    out: dict[str, Any] = {
        "ticks": int(ok.sum()),
        "ticks_without_reference": int((~ok).sum()),
        "yaw_damping_nms": config.yaw_damping_nms,
    }
    t, tested, reference = t[ok], tested[ok], reference[ok]
    if len(t) < 2:
        return out, []
    period = float(np.median(np.diff(t)))
    dt = np.minimum(np.diff(np.append(t, max(t_end, t[-1]))), 2.0 * period)
    u_test = brake_yaw_rate(tested[:, 0], tested[:, 1], calibration, config)
    u_ref = brake_yaw_rate(reference[:, 0], reference[:, 1], calibration, config)
    off = calibration.brake.torque_off_nm
    thr = config.brake_threshold_nm
    braking = (tested.max(axis=1) - off > thr) | (reference.max(axis=1) - off > thr)
    edges = np.diff(np.concatenate([[0], braking.astype(int), [0]]))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    episodes = [
        _episode(t, dt, u_test, u_ref, a, b, truth) for a, b in zip(starts, stops, strict=True)
    ]
    out.update(_steer_totals(episodes, tested, reference, thr))
    return out, episodes


def _episode(
    t: np.ndarray,
    dt: np.ndarray,
    u_test: np.ndarray,
    u_ref: np.ndarray,
    a: int,
    b: int,
    truth: Trajectory | None,
) -> dict[str, float]:
    """over_steer.csv's row of the braking episode of ticks [a, b)."""
    psi_test = float(u_test[a:b] @ dt[a:b])
    psi_ref = float(u_ref[a:b] @ dt[a:b])
    s = math.copysign(1.0, psi_test) if psi_test != 0.0 else 0.0
    if s == 0.0:
        over, under = 0.0, abs(psi_ref)
    else:
        over = max(0.0, s * (psi_test - psi_ref))
        under = max(0.0, -s * (psi_test - psi_ref))
    row = {
        "t_start": float(t[a]),
        "duration_s": float(dt[a:b].sum()),
        "commanded_deg": math.degrees(psi_test),
        "required_deg": math.degrees(psi_ref),
        "over_steer_deg": math.degrees(over),
        "under_steer_deg": math.degrees(under),
        "wrong_way": bool(psi_test * psi_ref < 0),
    }
    if truth is not None and len(truth) > 1:
        h = unwrapped_heading(truth, [t[a], t[a] + row["duration_s"]])
        row["true_heading_change_deg"] = math.degrees(h[1] - h[0])
    return row


def _steer_totals(
    episodes: list[dict[str, float]],
    tested: np.ndarray,
    reference: np.ndarray,
    threshold_nm: float,
) -> dict[str, Any]:
    """metrics.json's `over_steer` totals over the episodes."""
    over_deg = np.array([e["over_steer_deg"] for e in episodes])
    out = {
        "episodes": len(episodes),
        "commanded_deg": float(sum(abs(e["commanded_deg"]) for e in episodes)),
        "required_deg": float(sum(abs(e["required_deg"]) for e in episodes)),
        "over_steer_deg": float(over_deg.sum()),
        "over_steer_mean_deg": float(over_deg.mean()) if len(over_deg) else 0.0,
        "over_steer_max_deg": float(over_deg.max()) if len(over_deg) else 0.0,
        "under_steer_deg": float(sum(e["under_steer_deg"] for e in episodes)),
        "wrong_way_episodes": int(sum(e["wrong_way"] for e in episodes)),
        **{
            f"vs_reference_{k}": v
            for k, v in command_differences(reference, tested, threshold_nm).items()
            if k in ("rms_diff_nm", "same_side_fraction_braking")
        },
    }
    if episodes and "true_heading_change_deg" in episodes[0]:
        out["true_heading_change_deg"] = float(
            sum(abs(e["true_heading_change_deg"]) for e in episodes)
        )
    return out


def write_episodes_csv(episodes: list[dict[str, float]], path: Path) -> Path:
    with open(path, "w", newline="") as f:
        if episodes:
            w = csv.DictWriter(f, fieldnames=list(episodes[0]))
            w.writeheader()
            for e in episodes:
                w.writerow({k: (f"{v:.4f}" if isinstance(v, float) else v) for k, v in e.items()})
    return path


def controller_replay_summary(
    recomputer: CommandRecomputer, calibration: WalkerCalibration, t_end: float, threshold_nm: float
) -> dict[str, Any]:
    """metrics.json's `controller_replay`: the recomputed commands against the logged."""
    from experiments.metrics import braking_impulse_per_wheel

    t, logged, recomputed = recomputer.arrays()
    out: dict[str, Any] = {"controller": recomputer.name}
    out.update(command_differences(logged, recomputed, threshold_nm))
    off = calibration.brake.torque_off_nm
    for label, series in (("logged", logged), ("recomputed", recomputed)):
        cmds = [
            BrakeCommand(float(a), float(b[0]), float(b[1])) for a, b in zip(t, series, strict=True)
        ]
        out[f"{label}_braking_impulse_nms"] = braking_impulse_per_wheel(cmds, off, t_end)[
            "total_nms"
        ]
    return out
