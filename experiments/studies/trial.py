"""One simulated closed-loop trial of a study: the unit of work the engines distribute.

`run_trial(spec)` does what `experiments.run.simulate_trial` does (simulator → localizer
→ mapper → controller, optionally recorded to an MCAP trial log that `walkerslam replay`
reads) with what a study varies on top: a controller and localizer config (field
overrides), the trial's `UserProfile`, or a constant-force pusher with a shifted start
pose and initial speed (the corner tests). It returns plain data (picklable, JSON-able
but for the path arrays): the metrics, the collisions and the true and estimated paths.
Everything is reproducible from the spec: same spec, same result, in any process.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from control.base import CONTROLLERS
from experiments import metrics as M
from experiments.pipeline import FeedOrder, LoopConfig, Pipeline, run_closed_loop
from experiments.run import MAP_BAND_M, VERSION
from experiments.studies.settings import SOURCE_SETTINGS, build_config, source_settings
from hardware.log import LogWriter
from hardware.sim.simulator import WALKER_PARTS, SimConfig, Simulator
from hardware.sim.slip import proposed_localizer_settings
from hardware.sim.user import ConstantPush, UserProfile
from hardware.sim.world import load_world
from slam.base import LOCALIZERS, create

# Paths are kept at this rate (ground truth arrives at 50 Hz).
PATH_RATE_HZ = 10.0


@dataclass(frozen=True)
class RunSpec:
    """Everything that defines one run of a study.

    controller_overrides / localizer_overrides: (field, value) pairs replacing fields of
    the registered default config. A localizer with a `seed` field gets the trial seed
    unless overridden. user_profile: the simulated user's variation (route users).
    push_n: (left, right) constant handle forces instead of a route-following user.
    start_offset: (ahead, left, turn) of the start pose in the course's start frame
    [m, m, rad]; initial_speed_mps: forward speed at t = 0. log_path: record the trial
    there (None: no log). labels: study bookkeeping (cell, trial index, sweep value...).
    """

    course: str
    controller: str
    localizer: str = "dead-reckoning"
    surface: str | float = "dusty"
    seed: int = 0
    duration_s: float = 300.0
    controller_overrides: tuple[tuple[str, Any], ...] = ()
    localizer_overrides: tuple[tuple[str, Any], ...] = ()
    user_profile: UserProfile | None = None
    push_n: tuple[float, float] | None = None
    start_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    initial_speed_mps: float = 0.0
    log_path: str | None = None
    labels: dict[str, Any] = field(default_factory=dict)


def _config_dict(cfg: Any) -> dict[str, Any]:
    d = asdict(cfg)
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}


def proposed_settings(spec: RunSpec) -> dict[str, Any]:
    """The trial-log metadata entry of the settings the simulated trial proposes."""
    return {SOURCE_SETTINGS: proposed_localizer_settings(spec.surface)}


def localizer_config(spec: RunSpec) -> Any:
    """The run's live localizer: its defaults, the trial's proposals, the overrides."""
    over = dict(spec.localizer_overrides)
    proposed = source_settings(LOCALIZERS, spec.localizer, proposed_settings(spec))
    cfg = build_config(LOCALIZERS, spec.localizer, [*proposed.items(), *over.items()])
    if "seed" not in over and any(f.name == "seed" for f in fields(cfg)):
        cfg = replace(cfg, seed=spec.seed)
    return cfg


def shifted_pose(pose: tuple[float, float, float], offset: tuple[float, float, float]):
    """`pose` moved by (ahead, left, turn) in its own frame."""
    x, y, th = pose
    a, b, dth = offset
    c, s = math.cos(th), math.sin(th)
    return (x + a * c - b * s, y + a * s + b * c, math.remainder(th + dth, 2 * math.pi))


def min_clearance(world, poses: np.ndarray) -> float:
    """Smallest distance from a corner of the walker's footprint (frame and rear wheels)
    to an obstacle outline over `poses` (N×3); 0 when a corner is inside an obstacle."""
    outlines = [p for _, p in world.footprint_polygons()]
    if not outlines or len(poses) == 0:
        return math.inf
    corners = np.concatenate([p for _, p in WALKER_PARTS])  # (K, 2) walker frame
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    wx = poses[:, 0, None] + c[:, None] * corners[:, 0] - s[:, None] * corners[:, 1]
    wy = poses[:, 1, None] + s[:, None] * corners[:, 0] + c[:, None] * corners[:, 1]
    pts = np.column_stack([wx.ravel(), wy.ravel()])
    return float(M.distance_to_outlines(pts, outlines).min())


def _decimate(t: np.ndarray, rate_hz: float) -> np.ndarray:
    """Indices of samples at most `rate_hz` apart (always the first and the last)."""
    if len(t) == 0:
        return np.zeros(0, dtype=int)
    bins = np.floor((t - t[0]) * rate_hz + 1e-9).astype(int)
    keep = np.concatenate([[True], np.diff(bins) > 0])
    keep[-1] = True
    return np.nonzero(keep)[0]


def run_trial(spec: RunSpec) -> dict[str, Any]:
    """Simulate one trial; returns {"spec", "config", "metrics", "collisions", "path",
    "estimate"} (paths: arrays of (t, x, y, θ) rows at PATH_RATE_HZ)."""
    world = load_world(spec.course)
    if any(spec.start_offset):
        world = replace(world, start_pose=shifted_pose(world.start_pose, spec.start_offset))
    ctl_cfg = build_config(CONTROLLERS, spec.controller, spec.controller_overrides)
    loc_cfg = localizer_config(spec)
    cfg = replace(
        SimConfig(),
        surface=spec.surface,
        seed=spec.seed,
        duration_s=spec.duration_s,
        user_profile=spec.user_profile,
    )
    user = ConstantPush(*spec.push_n) if spec.push_n is not None else None
    sim = Simulator(world, cfg, user=user)
    sim.state.v = float(spec.initial_speed_mps)
    cal = sim.calibration
    loc = create(spec.localizer, cal, loc_cfg, initial_pose=world.start_pose)
    ctl = CONTROLLERS.create(spec.controller, cal, config=ctl_cfg)
    loop = LoopConfig()
    config = {
        "command": "study-run",
        "walker_slam_version": VERSION,
        "course": spec.course,
        "initial_pose": list(world.start_pose),
        "controller": spec.controller,
        "controller_config": _config_dict(ctl_cfg),
        "localizer": spec.localizer,
        "localizer_config": _config_dict(loc.config),
        "loop": asdict(loop),
        "sim": cfg.to_dict(),
        "user": (
            {"kind": "constant-push", "left_n": spec.push_n[0], "right_n": spec.push_n[1]}
            if spec.push_n is not None
            else {"kind": "route-follower"}
        ),
        "initial_speed_mps": spec.initial_speed_mps,
        "labels": dict(spec.labels),
    }
    pipeline = Pipeline(loc, cal, reference_map=False)
    t0 = time.perf_counter()
    if spec.log_path:
        path = Path(spec.log_path)
        path.parent.mkdir(parents=True, exist_ok=True)
        meta = {"config": config, "world": world.to_dict(), **proposed_settings(spec)}
        with LogWriter(path, cal, metadata=meta) as log:
            run_closed_loop(sim, sim, pipeline, ctl, loop, record=FeedOrder(log))
    else:
        run_closed_loop(sim, sim, pipeline, ctl, loop)
    wall = time.perf_counter() - t0

    rec = pipeline.recorded
    gt = rec.groundtruth_trajectory()
    est = loc.trajectory()
    metrics: dict[str, Any] = {
        "sim_time_s": sim.t,
        "finished_route": bool(sim.user.finished),
        "wall_time_s": wall,
    }
    counts = M.collision_counts(rec.collisions)
    metrics.update({f"collisions_{k.replace('-', '_')}": v for k, v in counts.items()})
    if gt is not None and len(est) > 1:
        metrics.update(M.ate(est, gt))
    outlines = [p for _, p in world.footprint_polygons(*MAP_BAND_M)]
    area = pipeline.mapper.grid.resolution**2
    metrics.update(M.map_scores(pipeline.mapper.occupied_xy(), area, outlines))
    metrics["braking_impulse_nms"] = M.braking_impulse(
        rec.commands, cal.brake.torque_off_nm, rec.t_last
    )
    path = np.zeros((0, 4))
    if gt is not None:
        keep = _decimate(gt.t, PATH_RATE_HZ)
        path = np.column_stack([gt.t[keep], gt.poses[keep]])
        metrics["min_clearance_m"] = min_clearance(world, gt.poses[_decimate(gt.t, 20.0)])
        turn = math.remainder(gt.poses[-1, 2] - world.start_pose[2], 2 * math.pi)
        metrics["final_heading_deg"] = math.degrees(turn)
        metrics["distance_m"] = float(np.sum(np.hypot(*np.diff(gt.poses[:, :2], axis=0).T)))
    keep = _decimate(est.t, PATH_RATE_HZ)
    estimate = np.column_stack([est.t[keep], est.poses[keep]]) if len(est) else np.zeros((0, 4))
    metrics = {
        k: (None if isinstance(v, float) and not math.isfinite(v) else v)
        for k, v in metrics.items()
    }
    return {
        "spec": spec,
        "config": config,
        "metrics": metrics,
        "collisions": [(c.t, c.kind, c.obstacle, c.x, c.y) for c in rec.collisions],
        "path": path,
        "estimate": estimate,
    }
