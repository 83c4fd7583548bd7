"""One simulated closed-loop trial of a study: the unit of work the engines distribute.

`run_trial(spec)` runs the trial with `experiments.simulation.simulate` — the one
implementation `walkerslam simulate` uses too (simulator → localizer → mapper →
controller, optionally recorded to an MCAP trial log that `walkerslam replay` reads),
with what a study varies on top in its `RunSpec`: controller and localizer overrides,
the trial's `UserProfile`, or a constant-force pusher with a shifted start pose and
initial speed (the corner tests) — and reduces it to plain data (picklable, JSON-able
but for the path arrays): the metrics, the collisions and the true and estimated paths.
Everything is reproducible from the spec: same spec, same result, in any process.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from experiments import metrics as M
from experiments.calibration_override import CalibrationOverride
from experiments.run import MAP_BAND_M
from experiments.simulation import RunSpec, simulate
from hardware.sim.simulator import WALKER_PARTS

# Paths are kept at this rate (ground truth arrives at 50 Hz).
PATH_RATE_HZ = 10.0


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


def run_trial(spec: RunSpec, calibration: CalibrationOverride | None = None) -> dict[str, Any]:
    """Simulate one trial (`experiments.simulation.simulate`; calibration: the software's,
    from a file); returns {"spec", "config", "metrics", "collisions", "path", "estimate"}
    (paths: arrays of (t, x, y, θ) rows at PATH_RATE_HZ)."""
    run = simulate(spec, command="study-run", calibration=calibration)
    sim, world, pipeline, config, wall = run.sim, run.world, run.pipeline, run.config, run.wall_s
    loc, cal = pipeline.localizer, pipeline.calibration
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
