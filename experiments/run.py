"""The jobs behind the CLI: record a simulated trial, replay a log through a localizer.

Each returns a result object; nothing here prints (the CLI does). Every run writes its
config next to its output.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, is_dataclass, replace
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from control.base import CONTROLLERS
from experiments import metrics as M
from experiments.pipeline import LoopConfig, Pipeline, run_closed_loop
from hardware.datasets import Dataset
from hardware.log import LogWriter, TrialLog, read_log
from hardware.sim.simulator import SimConfig, Simulator
from hardware.sim.world import World, load_world
from mapping.export import save_map_server, save_png
from mapping.mapper import MapperConfig
from slam import landmarks
from slam.base import create

VERSION = metadata.version("walker-slam")  # from pyproject.toml, via the install
# The mapper's obstacle band: what the map should show of the true world.
MAP_BAND_M = (0.05, 2.0)


def _jsonable(obj: Any) -> Any:
    if is_dataclass(obj) and not isinstance(obj, type):
        return asdict(obj)
    return obj


@dataclass(frozen=True)
class SimulateResult:
    path: Path
    sim_time_s: float
    wall_time_s: float
    collisions: dict[str, int]
    finished_route: bool


def simulate_trial(
    course: str,
    out_path: str | Path,
    *,
    controller: str = "open-loop",
    localizer: str = "dead-reckoning",
    surface: str | float = "dusty",
    seed: int = 0,
    duration_s: float = 300.0,
    sim_config: SimConfig | None = None,
    loop: LoopConfig | None = None,
    progress: Callable[[float], None] | None = None,
) -> SimulateResult:
    """Simulate `course` in closed loop and record everything to an MCAP trial log."""
    world = load_world(course)
    cfg = replace(sim_config or SimConfig(), surface=surface, seed=seed, duration_s=duration_s)
    loop = loop or LoopConfig()
    sim = Simulator(world, cfg)
    cal = sim.calibration
    loc = create(localizer, cal, initial_pose=world.start_pose)
    ctl_spec = CONTROLLERS.spec(controller)
    ctl = CONTROLLERS.create(controller, cal)
    config = {
        "command": "simulate",
        "walker_slam_version": VERSION,
        "course": course,
        "initial_pose": list(world.start_pose),
        "controller": controller,
        "controller_config": _jsonable(ctl_spec.config_type()),
        "localizer": localizer,
        "localizer_config": _jsonable(loc.config),
        "loop": asdict(loop),
        "sim": cfg.to_dict(),
    }
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    pipeline = Pipeline(loc, cal, reference_map=False)
    t0 = time.perf_counter()
    with LogWriter(out_path, cal, metadata={"config": config, "world": world.to_dict()}) as log:
        run_closed_loop(sim, pipeline, ctl, loop, sink=log.write, progress=progress)
    return SimulateResult(
        out_path,
        sim.t,
        time.perf_counter() - t0,
        M.collision_counts(pipeline.recorded.collisions),
        bool(sim.user.finished),
    )


@dataclass
class ReplayResult:
    out_dir: Path
    metrics: dict[str, Any]
    duration_s: float
    files: dict[str, Path] = field(default_factory=dict)
    pipeline: Pipeline | None = None
    world: World | None = None


def replay_log(
    log: str | Path | TrialLog | Dataset,
    out_dir: str | Path,
    *,
    localizer: str = "dead-reckoning",
    localizer_config: Any = None,
    mapper_config: MapperConfig | None = None,
    figures: bool = True,
    reference_map: bool = True,
    progress: Callable[[float], None] | None = None,
) -> ReplayResult:
    """Run a recorded trial (a log path, an opened log or an opened dataset) through a
    localizer and the mapper; write estimates, maps, metrics against ground truth (when
    the source has it) and the run's config.

    reference_map: also map the same frames at the true poses (when the log has ground
    truth), for the side-by-side figure and the reference map scores.
    """
    trial = log if isinstance(log, TrialLog | Dataset) else read_log(log)
    log_path = trial.path if isinstance(trial, TrialLog) else f"{trial.name}"
    cal = trial.calibration
    world = World.from_dict(trial.metadata["world"]) if "world" in trial.metadata else None
    initial_pose = trial.metadata.get("config", {}).get("initial_pose")
    true_landmarks = landmarks.from_metadata(trial.metadata)
    loc = create(
        localizer,
        cal,
        localizer_config,
        initial_pose=initial_pose,
        landmark_map=true_landmarks,
    )
    pipeline = Pipeline(loc, cal, mapper_config, reference_map=reference_map)
    t0 = time.perf_counter()
    pipeline.run(trial.messages(), progress)
    runtime = time.perf_counter() - t0

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rec = pipeline.recorded
    duration = rec.t_last - rec.t_first if rec.counts else 0.0
    files: dict[str, Path] = {}
    metrics: dict[str, Any] = {
        "log": str(log_path),
        "localizer": localizer,
        "duration_s": duration,
        "messages": rec.counts,
        "runtime_s": runtime,
        "realtime_factor": duration / runtime if runtime > 0 else math.inf,
    }
    estimated_landmarks = None
    if true_landmarks is not None and hasattr(loc, "landmarks"):
        estimated_landmarks = {i: mean for i, (mean, _) in loc.landmarks().items()}
        metrics["landmark_rmse_unaligned_m"] = M.landmark_rmse(estimated_landmarks, true_landmarks)
    diagnostics = loc.diagnostics()
    if diagnostics:
        metrics["localizer_diagnostics"] = diagnostics
    est = loc.trajectory()
    files["trajectory"] = out / "trajectory.tum"
    est.write_tum(files["trajectory"])
    gt = rec.groundtruth_trajectory()
    if gt is not None and len(est) > 1:
        files["groundtruth"] = out / "groundtruth.tum"
        gt.write_tum(files["groundtruth"])
        metrics.update(M.ate(est, gt))
        metrics.update(M.rpe(est, gt))
        if estimated_landmarks is not None:
            metrics["landmark_rmse_m"] = M.landmark_rmse(
                estimated_landmarks, true_landmarks, M.trajectory_alignment(est, gt)
            )
    if "relations" in trial.metadata and len(est) > 1:
        metrics.update(M.relation_errors(est, np.array(trial.metadata["relations"]["rows"])))
    outlines = []
    if world is not None:
        outlines = [p for _, p in world.footprint_polygons(*MAP_BAND_M)]
        area = pipeline.mapper.grid.resolution**2
        metrics.update(M.map_scores(pipeline.mapper.occupied_xy(), area, outlines))
        if pipeline.reference is not None and gt is not None:
            ref = M.map_scores(pipeline.reference.occupied_xy(), area, outlines)
            metrics["reference_map"] = {"note": "same frames mapped at the true poses", **ref}
    if rec.collisions or world is not None:
        metrics["collisions"] = M.collision_counts(rec.collisions)
    if rec.commands:
        metrics["braking_impulse_nms"] = M.braking_impulse(
            rec.commands, cal.brake.torque_off_nm, rec.t_last
        )

    files["map_png"] = save_png(
        pipeline.mapper.grid,
        out / "map.png",
        outlines=outlines,
        trajectory=est.poses[:, :2],
        scale=4,
    )
    files["map_yaml"], files["map_pgm"] = save_map_server(pipeline.mapper.grid, out / "map.yaml")
    if figures:
        from experiments.report import write_figures

        files.update(write_figures(out, pipeline, est, gt, outlines))
    files["metrics"] = out / "metrics.json"
    files["metrics"].write_text(json.dumps(metrics, indent=2) + "\n")
    files["config"] = out / "config.json"
    run_config = {
        "command": "replay",
        "walker_slam_version": VERSION,
        "log": str(log_path),
        "localizer": localizer,
        "localizer_config": _jsonable(loc.config),
        "mapper_config": _jsonable(pipeline.mapper.config),
        "recorded_config": trial.metadata.get("config"),
    }
    files["config"].write_text(json.dumps(run_config, indent=2, default=str) + "\n")
    return ReplayResult(out, metrics, duration, files, pipeline, world)
