"""The jobs behind the CLI: record a simulated trial, replay a log through a localizer.

Each returns a result object; nothing here prints (the CLI does). Every run writes its
config next to its output.
"""

from __future__ import annotations

import json
import math
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, is_dataclass, replace
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from control.base import CONTROLLERS
from experiments import drag
from experiments import metrics as M
from experiments.drag import DragConfig
from experiments.pipeline import FeedOrder, LoopConfig, Pipeline, run_closed_loop
from experiments.studies.settings import build_config, source_settings
from hardware.datasets import Dataset
from hardware.log import LogWriter, TrialLog, read_log
from hardware.registry import UnknownNameError
from hardware.sim.simulator import SimConfig, Simulator
from hardware.sim.world import World, load_world
from mapping.export import save_map_server
from mapping.mapper import MapperConfig
from slam import landmarks
from slam.base import LOCALIZERS, create

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
    # The trial proposes its simulated encoders' noise to every later replay; the live
    # localizer takes it too, so a live run and its replay are the same run.
    loc_cfg = build_config(
        LOCALIZERS, localizer, source_settings(LOCALIZERS, localizer, sim.metadata).items()
    )
    loc = create(localizer, cal, loc_cfg, initial_pose=world.start_pose)
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
    metadata = {"config": config, **sim.metadata}
    with LogWriter(out_path, cal, metadata=metadata) as log:
        run_closed_loop(sim, sim, pipeline, ctl, loop, record=FeedOrder(log), progress=progress)
    return SimulateResult(
        out_path,
        sim.t,
        time.perf_counter() - t0,
        M.collision_counts(pipeline.recorded.collisions),
        bool(sim.user.finished),
    )


class ReplayWarning(UserWarning):
    """What a replay's user should know about it: messages dropped (a stream's time going
    backwards), a localizer's fallback (e.g. no observations: odometry only)."""


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
    controller: str | None = None,
    drag_config: DragConfig | None = None,
    drag_metrics: bool = True,
    progress: Callable[[float], None] | None = None,
    observers: Callable[[Pipeline], Sequence[Any]] | None = None,
) -> ReplayResult:
    """Run a recorded trial (a log path, an opened log or an opened dataset) through a
    localizer and the mapper; write estimates, maps, metrics against ground truth (when
    the source has it) and the run's config.

    reference_map: also map the same frames at the true poses (when the log has ground
    truth), for the side-by-side figure, the reference map scores and the over-steer
    metric (experiments.drag).
    controller: recompute the brake commands with this controller (registry name) at each
    logged command, on the replay's pose and map, and compare them with the logged ones
    (`controller_replay` in the metrics); over-steer is then measured on them.
    drag_metrics: measure the drag metrics (phantom area over time, obstacle drag,
    over-steer) during the replay. Their time is left out of the real-time factor, but
    they also slow the loop itself (allocations, caches): compare and the benchmarks
    switch them off.
    observers: given the pipeline, more observers of the message stream
    (`experiments.drag.Observed`: before(msg), after(msg)), e.g. the live view's
    (`FoxgloveView.observer`); their time is left out of the real-time factor too.
    localizer_config None: the localizer's defaults with the settings the source proposes
    (metadata "localizer_settings", e.g. a dataset's fitted noise levels; see
    `experiments.studies.settings.source_settings`); a config given is used as it is.
    """
    trial = log if isinstance(log, TrialLog | Dataset) else read_log(log)
    log_path = trial.path if isinstance(trial, TrialLog) else f"{trial.name}"
    cal = trial.calibration
    world = World.from_dict(trial.metadata["world"]) if "world" in trial.metadata else None
    initial_pose = trial.metadata.get("config", {}).get("initial_pose")
    true_landmarks = landmarks.from_metadata(trial.metadata)
    proposed = source_settings(LOCALIZERS, localizer, trial.metadata)
    if localizer_config is None:
        localizer_config = build_config(LOCALIZERS, localizer, proposed.items())
    loc = create(
        localizer,
        cal,
        localizer_config,
        initial_pose=initial_pose,
        landmark_map=true_landmarks,
    )
    if controller is not None:
        CONTROLLERS.spec(controller)  # an unknown name fails before the replay
    pipeline = Pipeline(loc, cal, mapper_config, reference_map=reference_map)
    drag_cfg = drag_config or DragConfig()
    outlines = [p for _, p in world.footprint_polygons(*MAP_BAND_M)] if world is not None else []
    truth = drag.TruthTracker()
    phantom = (
        drag.PhantomSeries(pipeline, outlines, drag_cfg)
        if world is not None and drag_metrics
        else None
    )
    frame_drag = drag.FrameDrag(pipeline, truth, drag_cfg) if drag_metrics else None
    recomputer = (
        drag.CommandRecomputer(controller, cal, drag.estimated_input(pipeline))
        if controller is not None
        else None
    )
    recorded_controller = (trial.metadata.get("config") or {}).get("controller")
    steer_name = controller or _registered_controller(recorded_controller)
    reference_commands = (
        drag.CommandRecomputer(steer_name, cal, drag.true_input(pipeline, truth))
        if steer_name is not None and pipeline.reference is not None and drag_metrics
        else None
    )
    watching = [
        o for o in (truth, phantom, frame_drag, recomputer, reference_commands) if o is not None
    ]
    if observers is not None:
        watching += list(observers(pipeline))
    source = drag.Observed(trial.messages(), watching)
    t0 = time.perf_counter()
    pipeline.run(source, progress)
    runtime = time.perf_counter() - t0 - source.seconds  # the evaluation left out

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
        "evaluation_runtime_s": source.seconds,  # drag metrics during the replay
    }
    estimated_landmarks = None
    if true_landmarks is not None and hasattr(loc, "landmarks"):
        estimated_landmarks = {i: mean for i, (mean, _) in loc.landmarks().items()}
        metrics["landmark_rmse_unaligned_m"] = M.landmark_rmse(estimated_landmarks, true_landmarks)
    diagnostics = loc.diagnostics()
    if diagnostics:
        metrics["localizer_diagnostics"] = diagnostics
    if rec.out_of_order:
        metrics["out_of_order_dropped"] = dict(rec.out_of_order)
        what = ", ".join(f"{n} {name}" for name, n in sorted(rec.out_of_order.items()))
        warnings.warn(
            f"{log_path}: dropped messages whose time went backwards in their stream: {what}",
            ReplayWarning,
            stacklevel=2,
        )
    if diagnostics.get("note"):
        warnings.warn(
            f"{log_path}: {localizer}: {diagnostics['note']}", ReplayWarning, stacklevel=2
        )
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
    if world is not None:
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
        metrics["braking_impulse"] = M.braking_impulse_per_wheel(
            rec.commands, cal.brake.torque_off_nm, rec.t_last
        )
    files.update(
        _drag_metrics(
            metrics,
            out,
            pipeline,
            gt,
            phantom,
            frame_drag,
            recomputer,
            reference_commands,
            drag_cfg,
            figures,
            trial.metadata.get("config") or {},
        )
    )

    from experiments.report import write_map_png

    files["map_png"] = write_map_png(
        out / "map.png", pipeline.mapper.grid, outlines, est, gt, localizer=localizer, log=log_path
    )
    files["map_yaml"], files["map_pgm"] = save_map_server(pipeline.mapper.grid, out / "map.yaml")
    if figures:
        from experiments.report import write_figures

        files.update(
            write_figures(out, pipeline, est, gt, outlines, localizer=localizer, log=log_path)
        )
    files["metrics"] = out / "metrics.json"
    files["metrics"].write_text(json.dumps(metrics, indent=2) + "\n")
    files["config"] = out / "config.json"
    run_config = {
        "command": "replay",
        "walker_slam_version": VERSION,
        "log": str(log_path),
        "localizer": localizer,
        "localizer_config": _jsonable(loc.config),
        "source_localizer_settings": proposed,
        "mapper_config": _jsonable(pipeline.mapper.config),
        "controller": controller,
        "drag_config": asdict(drag_cfg),
        "recorded_config": trial.metadata.get("config"),
    }
    files["config"].write_text(json.dumps(run_config, indent=2, default=str) + "\n")
    return ReplayResult(out, metrics, duration, files, pipeline, world)


def _registered_controller(name: Any) -> str | None:
    """`name` if it is a registered controller (a recorded trial's), else None."""
    if not isinstance(name, str):
        return None
    try:
        CONTROLLERS.spec(name)
    except UnknownNameError:
        return None
    return name


def _drag_metrics(
    metrics: dict[str, Any],
    out: Path,
    pipeline: Pipeline,
    gt,
    phantom: drag.PhantomSeries | None,
    frame_drag: drag.FrameDrag | None,
    recomputer: drag.CommandRecomputer | None,
    reference_commands: drag.CommandRecomputer | None,
    cfg: DragConfig,
    figures: bool,
    recorded: dict[str, Any],
) -> dict[str, Path]:
    """Add the drag metrics (experiments.drag) to `metrics`; write their CSVs and figures."""
    rec, cal = pipeline.recorded, pipeline.calibration
    off = cal.brake.torque_off_nm
    files: dict[str, Path] = {}
    if phantom is not None:
        phantom.finish(rec.t_last)
        metrics["phantom_area_over_time"] = phantom.summary(rec.commands, off)
        files["phantom_csv"] = phantom.write_csv(out / "phantom_area.csv")
    frame_series: dict[str, np.ndarray] = {}
    if gt is not None and frame_drag is not None and frame_drag.frames.t:
        metrics["drag"], frame_series = frame_drag.summary(rec.commands, off, gt)
        if frame_series:
            files["drag_csv"] = drag.write_frames_csv(frame_series, out / "drag_frames.csv")
    if recomputer is not None:
        summary = drag.controller_replay_summary(
            recomputer, cal, rec.t_last, cfg.brake_threshold_nm
        )
        metrics["controller_replay"] = {
            **summary,
            "localizer": metrics.get("localizer"),
            "recorded_controller": recorded.get("controller"),
            "recorded_localizer": recorded.get("localizer"),
            "safety_layer": recomputer.safety_layer,
        }
        files["controller_replay_csv"] = recomputer.write_csv(out / "controller_replay.csv")
        if figures:
            from experiments.drag_figures import plot_controller_replay

            files["controller_replay_png"] = plot_controller_replay(
                out / "controller_replay.png", recomputer
            )
    steer = None
    if reference_commands is not None and gt is not None and rec.commands:
        t, logged, required = reference_commands.arrays()
        tested = recomputer.arrays()[2] if recomputer is not None else logged
        summary, episodes = drag.over_steer(t, tested, required, rec.t_last, cal, cfg, gt)
        metrics["over_steer"] = {
            "controller": reference_commands.name,
            "commands": "recomputed" if recomputer is not None else "logged",
            **summary,
        }
        files["over_steer_csv"] = drag.write_episodes_csv(episodes, out / "over_steer.csv")
        if summary["ticks"]:
            steer = (t, tested, required)
    if figures and (phantom is not None or frame_series or steer is not None):
        from experiments.drag_figures import plot_drag

        files["drag_png"] = plot_drag(
            out / "drag.png", phantom, frame_series, steer, rec.commands, cal, cfg
        )
    return files
