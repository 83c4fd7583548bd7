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
from pathlib import Path
from typing import Any

import numpy as np

from control.base import CONTROLLERS
from experiments import drag
from experiments import metrics as M
from experiments.calibration_override import CalibrationOverride, applied
from experiments.config import Configured, configure, propose
from experiments.drag import DragConfig
from experiments.mitigations import Mitigated, check_calibration, check_source, resolve
from experiments.pipeline import LoopConfig, Pipeline
from experiments.sharpness import ScanSharpness, scan_clouds, scan_sharpness
from experiments.simulation import VERSION, RunSpec, simulate
from hardware.calibration import WalkerCalibration
from hardware.datasets import Dataset
from hardware.errors import ConfigError, UnknownNameError
from hardware.log import TrialLog, read_log
from hardware.messages import LANDMARK_MESSAGES, MESSAGE_TYPES, GyroRate, LaserScan
from hardware.sim.simulator import SimConfig
from hardware.sim.world import World
from hardware.source import PROPOSED_MAPPER_SETTINGS, PROPOSED_SETTINGS
from mapping.export import save_map_server
from mapping.mapper import MapperConfig
from mapping.scan_features import FeatureConfig
from slam import landmarks
from slam.base import LOCALIZERS, KnownMapConfig, LandmarkMapper, SlipEstimator, create
from slam.motion import uses_gyro

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
    calibration: CalibrationOverride | None = None,
    mitigations: Sequence[str] = (),
) -> SimulateResult:
    """Simulate `course` in closed loop and record everything to an MCAP trial log
    (`experiments.simulation.simulate`, the studies' trials' implementation too);
    calibration: a file whose wheel diameters and track the software believes;
    mitigations: of the live localizer and map (the walker carries what they need)."""
    spec = RunSpec(
        course,
        controller,
        localizer,
        surface=surface,
        seed=seed,
        duration_s=duration_s,
        seed_localizer=False,
        log_path=str(out_path),
        mitigations=tuple(mitigations),
    )
    run = simulate(
        spec, sim_config=sim_config, loop=loop, progress=progress, calibration=calibration
    )
    return SimulateResult(
        Path(out_path),
        run.sim.t,
        run.wall_s,
        M.collision_counts(run.pipeline.recorded.collisions),
        bool(run.sim.user.finished),
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


@dataclass
class _Replay:
    """A replay being built, run and evaluated (the steps of `replay_log`)."""

    trial: TrialLog | Dataset
    log_path: str
    out: Path
    localizer: str
    built: Configured
    calibration: WalkerCalibration  # the log's, or with --calibration's odometry
    calibration_override: dict[str, Any] | None
    pipeline: Pipeline
    world: World | None
    true_landmarks: dict | None
    outlines: list
    drag_cfg: DragConfig
    controller: str | None
    mitigated: Mitigated
    landmark_map: str | None = None  # --landmark-map's file (given to the localizer)
    phantom: drag.PhantomSeries | None = None
    frame_drag: drag.FrameDrag | None = None
    recomputer: drag.CommandRecomputer | None = None
    reference_commands: drag.CommandRecomputer | None = None
    observed: drag.Observed | None = None
    runtime_s: float = 0.0
    sharpness: ScanSharpness | None = None  # a laser replay's map sharpness


def replay_log(
    log: str | Path | TrialLog | Dataset,
    out_dir: str | Path,
    *,
    localizer: str = "dead-reckoning",
    localizer_config: Any = None,
    localizer_overrides: dict[str, Any] | None = None,
    mapper_config: MapperConfig | None = None,
    figures: bool = True,
    map_figure: bool = True,
    reference_map: bool = True,
    controller: str | None = None,
    drag_config: DragConfig | None = None,
    drag_metrics: bool = True,
    progress: Callable[[float], None] | None = None,
    phase: Callable[[str], None] | None = None,
    observers: Callable[[Pipeline], Sequence[Any]] | None = None,
    calibration: CalibrationOverride | None = None,
    mitigations: Sequence[str] = (),
    scan_corners: bool = False,
    landmark_map: str | Path | None = None,
) -> ReplayResult:
    """Run a recorded trial (a log path, an opened log or an opened dataset) through a
    localizer and the mapper; write estimates, maps, metrics against ground truth (when
    the source has it) and the run's config — in four steps: build, run, evaluate, write.

    The localizer's config: `localizer_config` as it is, or else its defaults, then the
    settings the source proposes (metadata "localizer_settings", e.g. a dataset's fitted
    noise levels), then `localizer_overrides` ({field path: value}, the user's --set)
    (`experiments.config.configure`; config.json records which proposals applied and
    which the config had no field for).
    figures: the figures besides map.png; map_figure: map.png (a study whose replays'
    folders are removed skips it).
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
    progress(t): each message's time; phase(text): what happens after the messages
    (metrics, figures), for a progress display.
    calibration: a calibration file whose wheel diameters and track replace the log's
    (`experiments.calibration_override`; recorded in config.json).
    mitigations: names of encoder-slip mitigations (`experiments.mitigations`): their
    localizer fields come before `localizer_overrides`, their map hygiene replaces the
    mapper config's; the source must hold what they need (recorded in config.json).
    scan_corners: each laser scan's corners (mapping.scan_features) also go to the
    localizer, as range-bearing sightings without IDs (counted: `scan_corners`).
    landmark_map: a landmark map file (slam.landmarks: {"id": [x, y]}, e.g. the
    landmarks.json of an earlier SLAM replay) for a localizer that localizes in a known
    map (the particle filter), instead of the log's; the metrics against the log's true
    landmarks are unchanged.


    (Its length is this docstring; the body is the four named steps.)"""
    mitigated = resolve(mitigations, localizer)
    check_calibration(mitigated, calibration)
    localizer_overrides = {**mitigated.localizer_settings, **(localizer_overrides or {})}
    if mitigated.hygiene is not None:
        mapper_config = replace(mapper_config or MapperConfig(), hygiene=mitigated.hygiene)
    r = _build(
        log, out_dir, localizer, localizer_config, localizer_overrides, mapper_config,
        reference_map, controller, drag_config, calibration, mitigated, landmark_map,
    )  # fmt: skip
    if scan_corners:
        r.pipeline.scan_features = FeatureConfig()
    _attach_evaluation(r, drag_metrics, observers)
    _run(r, progress)
    if phase is not None:
        phase("metrics")
    metrics, gt = _evaluate(r)
    if phase is not None:
        phase("figures and files" if figures else "files")
    files = _write(r, metrics, gt, figures, map_figure)
    duration = metrics["duration_s"]
    return ReplayResult(r.out, metrics, duration, files, r.pipeline, r.world)


def message_types(trial: TrialLog | Dataset) -> set[type]:
    """The message types a log or dataset holds."""
    if isinstance(trial, TrialLog):
        return set(trial.topics.values())
    counts = trial.counts()
    return {t for t in MESSAGE_TYPES if counts.get(t.__name__, 0) > 0}


# what a source with laser scans and no landmark messages proposes (source_metadata)
SCAN_MODES = {"scan_matching": True, "use_scans": True}


def source_metadata(trial: TrialLog | Dataset) -> dict[str, Any]:
    """A source's metadata, its proposed localizer settings completed by one rule: a
    source with laser scans and no landmark messages (tags, range-bearing) proposes the
    localizers' scan-based modes (gtsam's scan matching, the particle filter's scan
    likelihood), without which a landmark localizer runs as dead reckoning (Intel: 7.4 m
    relations error). The source's own proposals come after, and the user's --set after
    them."""
    types = message_types(trial)
    if LaserScan not in types or types & set(LANDMARK_MESSAGES):
        return trial.metadata
    proposed = {**SCAN_MODES, **(trial.metadata.get(PROPOSED_SETTINGS) or {})}
    return {**trial.metadata, PROPOSED_SETTINGS: proposed}


def check_gyro(config: Any, trial: TrialLog | Dataset, name: str) -> None:
    """ConfigError naming the source when a localizer's config asks for the gyro
    (noise.gyro.enabled) and the source has no gyro messages: the user asked for the
    gyro explicitly, so running without it would misreport what was measured."""
    if not uses_gyro(config):
        return
    if GyroRate not in message_types(trial):
        raise ConfigError(
            f"{name}: no gyro messages (GyroRate, topic /imu/gyro) but noise.gyro.enabled "
            "is set; record the trial with a gyro (simulate --gyro) or leave it off"
        )


def _out_dir(out_dir: str | Path) -> Path:
    """The output folder, made now (a user's mistake fails before the replay)."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: the output folder is a file")
    out.mkdir(parents=True, exist_ok=True)
    return out


def _build(
    log, out_dir, localizer, localizer_config, overrides, mapper_config, reference_map,
    controller, drag_config, calibration_file, mitigated, landmark_map=None,
) -> _Replay:  # fmt: skip
    """The source, the calibration, the localizer's config, the localizer, the pipeline."""
    trial = log if isinstance(log, TrialLog | Dataset) else read_log(log)
    cal, override = applied(calibration_file, trial.calibration)
    log_path = str(trial.path) if isinstance(trial, TrialLog) else f"{trial.name}"
    check_source(mitigated, message_types(trial), log_path)
    if localizer_config is None:
        built = configure(LOCALIZERS, localizer, source_metadata(trial), overrides or {})
    else:
        built = Configured(localizer_config)
    check_gyro(built.config, trial, log_path)
    out = _out_dir(out_dir)
    if controller is not None:
        CONTROLLERS.spec(controller)  # an unknown name fails before the replay
    world = World.from_dict(trial.metadata["world"]) if "world" in trial.metadata else None
    true_landmarks = landmarks.from_metadata(trial.metadata)
    given = given_map(landmark_map, built.config, localizer)
    loc = create(
        localizer,
        cal,
        built.config,
        initial_pose=trial.metadata.get("config", {}).get("initial_pose"),
        landmark_map=given if given is not None else true_landmarks,
    )
    proposed = trial.metadata.get(PROPOSED_MAPPER_SETTINGS) or {}
    mapper_config = propose(mapper_config or MapperConfig(), proposed, "mapper")
    pipeline = Pipeline(loc, cal, mapper_config, reference_map=reference_map)
    outlines = [p for _, p in world.footprint_polygons(*MAP_BAND_M)] if world is not None else []
    return _Replay(
        trial, log_path, out, localizer, built, cal, override, pipeline, world, true_landmarks,
        outlines, drag_config or DragConfig(), controller, mitigated,
        None if landmark_map is None else str(landmark_map),
    )  # fmt: skip


def given_map(path: str | Path | None, config: Any, localizer: str) -> dict | None:
    """The landmark map file's map (slam.landmarks.load), checked to be of use: only a
    localizer that localizes in a known map takes one, and a config that names its own
    map keeps it."""
    if path is None:
        return None
    if not isinstance(config, KnownMapConfig):
        raise ConfigError(
            f"{path}: {localizer} builds its own map; a landmark map is for a localizer "
            "that localizes in one (particle-filter)"
        )
    if config.landmark_map is not None:
        raise ConfigError(f"{path}: {localizer}'s config already names a landmark map")
    return landmarks.load(path)


def _attach_evaluation(r: _Replay, drag_metrics: bool, observers) -> None:
    """What watches the replay's messages: the drag metrics, a recomputing controller,
    the same controller at the true pose (over-steer), the caller's observers."""
    pipeline, cal = r.pipeline, r.calibration
    truth = drag.TruthTracker()
    if r.world is not None and drag_metrics:
        r.phantom = drag.PhantomSeries(pipeline, r.outlines, r.drag_cfg)
    if drag_metrics:
        r.frame_drag = drag.FrameDrag(pipeline, truth, r.drag_cfg)
    if r.controller is not None:
        r.recomputer = drag.CommandRecomputer(r.controller, cal, drag.estimated_input(pipeline))
    recorded = (r.trial.metadata.get("config") or {}).get("controller")
    steer = r.controller or _registered_controller(recorded)
    if steer is not None and pipeline.reference is not None and drag_metrics:
        r.reference_commands = drag.CommandRecomputer(steer, cal, drag.true_input(pipeline, truth))
    watching = [
        o
        for o in (truth, r.phantom, r.frame_drag, r.recomputer, r.reference_commands)
        if o is not None
    ]
    if observers is not None:
        watching += list(observers(pipeline))
    r.observed = drag.Observed(r.trial.messages(), watching)


def _run(r: _Replay, progress) -> None:
    """Every message through the pipeline; the evaluation's time left out."""
    t0 = time.perf_counter()
    r.pipeline.run(r.observed, progress)
    r.runtime_s = time.perf_counter() - t0 - r.observed.seconds


def _evaluate(r: _Replay):
    """The metrics (metrics.json) and the ground-truth trajectory (when known); warns
    about dropped messages and a localizer's fallback."""
    pipeline, cal = r.pipeline, r.calibration
    loc, rec = pipeline.localizer, pipeline.recorded
    duration = rec.t_last - rec.t_first if rec.counts else 0.0
    runtime = r.runtime_s
    metrics: dict[str, Any] = {
        "log": r.log_path,
        "localizer": r.localizer,
        "duration_s": duration,
        "messages": rec.counts,
        "runtime_s": runtime,
        "realtime_factor": duration / runtime if runtime > 0 else math.inf,
        "evaluation_runtime_s": r.observed.seconds,  # drag metrics during the replay
    }
    estimated = None
    if r.true_landmarks is not None and isinstance(loc, LandmarkMapper):
        # none estimated (a map nothing observed, e.g. MTRX5700's beacons): no landmark metric
        estimated = {i: mean for i, (mean, _) in loc.landmarks().items()} or None
    if estimated is not None:
        metrics["landmark_rmse_unaligned_m"] = M.landmark_rmse(estimated, r.true_landmarks)
    _diagnostics(r, metrics)
    if isinstance(loc, SlipEstimator) and (slip := loc.slip_estimate()) is not None:
        metrics["slip"] = M.slip_errors(*slip, r.trial.metadata.get("slip"))
    est = loc.trajectory()
    gt = rec.groundtruth_trajectory()
    if gt is not None and len(est) > 1:
        metrics["groundtruth_kind"] = M.groundtruth_kind(r.trial.metadata)
        metrics.update(M.ate(est, gt))
        metrics.update(M.heading_errors(est, gt))
        metrics.update(M.rpe(est, gt))
        if estimated is not None:
            metrics["landmark_rmse_m"] = M.landmark_rmse(
                estimated, r.true_landmarks, M.trajectory_alignment(est, gt)
            )
    if "relations" in r.trial.metadata and len(est) > 1:
        metrics.update(M.relation_errors(est, np.array(r.trial.metadata["relations"]["rows"])))
    if "gps" in r.trial.metadata and len(est) > 1:
        metrics.update(M.gps_errors(est, np.array(r.trial.metadata["gps"]["rows"])))
    if rec.scan_t and len(est) > 1:
        clouds = scan_clouds(rec.scan_t, rec.scan_hits, est, np.array(rec.scan_truth))
        r.sharpness = scan_sharpness(clouds)  # sharpness.png shows the same spreads
        metrics["map_sharpness"] = sharp = r.sharpness.metrics()
        for who, prefix in (("estimated", ""), ("reference", "reference_")):
            if who in sharp:
                fine, coarse = (s["wall_spread_median_m"] for s in sharp[who])
                metrics[f"{prefix}wall_spread_m"] = fine
                metrics[f"{prefix}wall_spread_coarse_m"] = coarse
    if r.world is not None:
        area = pipeline.mapper.grid.resolution**2
        metrics.update(M.map_scores(pipeline.mapper.occupied_xy(), area, r.outlines))
        if pipeline.reference is not None and gt is not None:
            ref = M.map_scores(pipeline.reference.occupied_xy(), area, r.outlines)
            metrics["reference_map"] = {"note": "same frames mapped at the true poses", **ref}
    if rec.collisions or r.world is not None:
        metrics["collisions"] = M.collision_counts(rec.collisions)
    if rec.commands:
        off = cal.brake.torque_off_nm
        metrics["braking_impulse_nms"] = M.braking_impulse(rec.commands, off, rec.t_last)
        metrics["braking_impulse"] = M.braking_impulse_per_wheel(rec.commands, off, rec.t_last)
        if gt is not None and len(est) > 1:
            metrics.update(
                drag.heading_error_while_braking(
                    est, gt, rec.commands, off, r.drag_cfg.brake_threshold_nm
                )
            )
    return metrics, gt


def _diagnostics(r: _Replay, metrics: dict[str, Any]) -> None:
    """The localizer's diagnostics and the messages dropped, in the metrics and warned."""
    rec, diagnostics = r.pipeline.recorded, r.pipeline.localizer.diagnostics()
    if diagnostics:
        metrics["localizer_diagnostics"] = diagnostics
    if rec.out_of_order:
        metrics["out_of_order_dropped"] = dict(rec.out_of_order)
        what = ", ".join(f"{n} {name}" for name, n in sorted(rec.out_of_order.items()))
        warnings.warn(
            f"{r.log_path}: dropped messages whose time went backwards in their stream: {what}",
            ReplayWarning,
            stacklevel=4,
        )
    if diagnostics.get("note"):
        warnings.warn(
            f"{r.log_path}: {r.localizer}: {diagnostics['note']}", ReplayWarning, stacklevel=4
        )


def _write(
    r: _Replay, metrics: dict[str, Any], gt, figures: bool, map_figure: bool
) -> dict[str, Path]:
    """trajectory.tum, groundtruth.tum, the drag series, maps, figures, metrics.json,
    config.json."""
    out, pipeline = r.out, r.pipeline
    est = pipeline.localizer.trajectory()
    files: dict[str, Path] = {"trajectory": out / "trajectory.tum"}
    est.write_tum(files["trajectory"])
    if gt is not None and len(est) > 1:
        files["groundtruth"] = out / "groundtruth.tum"
        gt.write_tum(files["groundtruth"])
    files.update(
        _drag_metrics(
            metrics, out, pipeline, gt, r.phantom, r.frame_drag, r.recomputer,
            r.reference_commands, r.drag_cfg, figures, r.trial.metadata.get("config") or {},
        )
    )  # fmt: skip
    names = M.truth_names(metrics.get("groundtruth_kind"))  # what the figures call gt
    if map_figure:
        from experiments.report import write_map_png

        files["map_png"] = write_map_png(
            out / "map.png", pipeline.mapper.grid, r.outlines, est, gt, localizer=r.localizer,
            log=r.log_path, names=names,
        )  # fmt: skip
    files["map_yaml"], files["map_pgm"] = save_map_server(pipeline.mapper.grid, out / "map.yaml")
    if figures:
        from experiments.report import write_figures

        figs = write_figures(
            out, pipeline, est, gt, r.outlines, localizer=r.localizer, log=r.log_path,
            sharpness=r.sharpness, names=names,
        )  # fmt: skip
        files.update(figs)
    loc = pipeline.localizer
    marks: dict[int, np.ndarray] = {}  # the landmarks it made: for gps.png, landmarks.json
    if isinstance(loc, LandmarkMapper):
        marks = {i: mean for i, (mean, _) in loc.landmarks().items()}
    if figures and "gps" in r.trial.metadata and len(est) > 1:
        from experiments.report import gps_figure, save

        xy = np.array(list(marks.values())).reshape(-1, 2)
        fit = M.fit_gps(est, np.array(r.trial.metadata["gps"]["rows"]))
        fig = gps_figure(est, fit, metrics, xy, localizer=r.localizer, log=r.log_path)
        files["gps_png"] = save(fig, out / "gps.png")
    if marks:
        files["landmarks"] = landmarks.save(out / "landmarks.json", marks)
    if pipeline.hygiene is not None:
        metrics["map_hygiene"] = dict(pipeline.hygiene.counts)
    files["metrics"] = out / "metrics.json"
    files["metrics"].write_text(json.dumps(metrics, indent=2) + "\n")
    files["config"] = out / "config.json"
    run_config = {
        "command": "replay",
        "walker_slam_version": VERSION,
        "log": r.log_path,
        "localizer": r.localizer,
        "localizer_config": _jsonable(pipeline.localizer.config),
        "source_localizer_settings": r.built.proposed,
        "source_localizer_settings_skipped": r.built.skipped,
        "localizer_overrides": r.built.overrides,
        "mitigations": r.mitigated.record(),
        "scan_corners": pipeline.scan_features is not None,
        "landmark_map": r.landmark_map,
        "calibration_override": r.calibration_override,
        "mapper_config": _jsonable(pipeline.mapper.config),
        "controller": r.controller,
        "drag_config": asdict(r.drag_cfg),
        "recorded_config": r.trial.metadata.get("config"),
    }
    files["config"].write_text(json.dumps(run_config, indent=2, default=str) + "\n")
    return files


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
    """Add the drag metrics (experiments.drag) to `metrics`; write their CSVs and figures.

    (Long for the three evaluations it gathers, each a few lines.)"""
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
