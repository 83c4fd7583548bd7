"""`walkerslam`: the command-line interface. Each command calls one function of
`experiments.run` and prints a short summary; known errors become one line and exit 2."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from experiments import calibrate_commands, live_commands, study_commands
from experiments.cli_common import (
    MitigationOpt,
    console,
    err_console,
    friendly,
    parse_mitigations,
    parse_size,
    print_error,
    progress_bar,
)
from hardware.errors import ConfigError

app = typer.Typer(
    help="walker-slam: localization and mapping under brake-induced wheel slip.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode="markdown",
)


def _print_metrics(metrics: dict, files: dict[str, Path]) -> None:
    table = Table(show_header=False, box=None)
    for key in (
        "duration_s",
        "ate_rmse_m",
        "ate_rmse_unaligned_m",
        "rpe_trans_m",
        "final_position_error_m",
        "landmark_rmse_m",
        "relations_trans_mean_m",
        "gps_rmse_m",
        "gps_rmse_unaligned_m",
        "wall_spread_m",
        "reference_wall_spread_m",
        "map_precision",
        "phantom_area_m2",
        "braking_impulse_nms",
        "realtime_factor",
    ):
        if key in metrics:
            table.add_row(key, f"{metrics[key]:.3f}")
        if key == "duration_s" and "groundtruth_kind" in metrics:
            from experiments.metrics import GROUND_TRUTH, truth_names

            names = truth_names(metrics["groundtruth_kind"])
            if names != GROUND_TRUTH:
                table.add_row("errors against", names.against)
    if "gps_fixes_used" in metrics:
        table.add_row(
            "gps fixes",
            f"{metrics['gps_fixes_used']} used, {metrics['gps_jumps_left_out']} jumps left out, "
            f"{metrics['gps_dropouts']} dropouts ({metrics['gps_dropout_s']:.0f} s)",
        )
    if "collisions" in metrics:
        c = metrics["collisions"]
        table.add_row(
            "collisions",
            f"{c['total']} (front {c['front']}, side {c['side']}, rear-wheel {c['rear-wheel']})",
        )
    if "reference_map" in metrics:
        r = metrics["reference_map"]
        table.add_row(
            "map from true poses",
            f"precision {r['map_precision']:.3f}, phantom {r['phantom_area_m2']:.3f} m²",
        )
    console.print(table)
    console.print("files: " + ", ".join(str(p) for p in files.values()), highlight=False)


@app.command()
@friendly
def simulate(
    output: Annotated[Path, typer.Option("-o", "--output", help="trial log to write (.mcap)")],
    course: Annotated[
        str, typer.Option(help="built-in course name or a course JSON file")
    ] = "thesis-course",
    controller: Annotated[str, typer.Option(help="braking controller")] = "open-loop",
    localizer: Annotated[
        str, typer.Option(help="localizer the controller uses")
    ] = "dead-reckoning",
    surface: Annotated[
        str, typer.Option(help="clean, dusty or a slip coefficient in [0, 0.95]")
    ] = "dusty",
    seed: Annotated[int, typer.Option(help="random seed of the run")] = 0,
    duration: Annotated[float, typer.Option(help="longest simulated time [s]")] = 300.0,
    depth_size: Annotated[
        str, typer.Option(help="depth image size WxH, up to 640x480")
    ] = "160x120",
    gyro: Annotated[
        bool,
        typer.Option(
            "--gyro",
            help="carry a simulated MEMS yaw-rate gyro (an MPU-6050) and record its "
            "/imu/gyro stream; the other sensors are as without it",
        ),
    ] = False,
    calibration: Annotated[
        Path | None,
        typer.Option(
            help="walker calibration JSON whose wheel diameters and track the walker's "
            "software believes (the simulated walker stays the true one)"
        ),
    ] = None,
    mitigation: MitigationOpt = None,
    slip_scale: Annotated[
        str,
        typer.Option(help="L,R: each rear wheel's factor of the surface's slip coefficient"),
    ] = "1,1",
    start_still: Annotated[
        float,
        typer.Option(
            help="seconds the user stands still at the start before walking (the walker "
            "at rest while the recording starts: a gyro learns its bias then)"
        ),
    ] = 0.0,
) -> None:
    """Simulate a trial in closed loop and record it, with ground truth, to an MCAP log.

    (Long for its option list: typer reads the options from this signature.)"""
    from dataclasses import replace

    from experiments.config import checked, convert
    from experiments.run import simulate_trial
    from hardware.sim.gyro import GyroSimConfig
    from hardware.sim.simulator import SimConfig

    width, height = parse_size(depth_size)
    mitigations = parse_mitigations(mitigation, localizer, calibration)[0]
    override = _calibration_override(calibration, [SimConfig().calibration()])
    scale = convert(slip_scale, tuple[float, float], "--slip-scale")
    sim_config = checked(
        lambda: replace(
            SimConfig(),
            depth_width=width,
            depth_height=height,
            surface=surface,
            seed=seed,
            duration_s=duration,
            gyro=GyroSimConfig(enabled=gyro),
            slip_scale=scale,
            start_still_s=start_still,
        ),
        "simulate",
    )

    with progress_bar(f"simulating {course}", duration) as update:
        res = simulate_trial(
            course,
            output,
            sim_config=sim_config,
            controller=controller,
            localizer=localizer,
            surface=surface,
            seed=seed,
            duration_s=duration,
            progress=update,
            calibration=override,
            mitigations=mitigations,
        )
    c = res.collisions
    console.print(
        f"recorded {res.sim_time_s:.1f} s of {course} "
        f"({'route completed' if res.finished_route else 'time limit'}) "
        f"in {res.wall_time_s:.1f} s → {res.path}\ncollisions: {c['total']} (front {c['front']}, "
        f"side {c['side']}, rear-wheel {c['rear-wheel']})",
        highlight=False,
    )


RobotOpt = Annotated[int | None, typer.Option(help="mrclam: robot number (1-5)")]
SetOpt = Annotated[
    list[str] | None,
    typer.Option(
        "--set",
        help="LOCALIZER.FIELD=VALUE: a field of a localizer's config, nested fields by "
        "path (e.g. gtsam.scan_matching=true, ekf-slam.noise.brake_aware=true); repeatable",
    ),
]


def _localizer_overrides(sets: list[str] | None, names: list[str]) -> dict[str, dict]:
    """--set options → {localizer: {field path: typed value}}, for the localizers run."""
    from experiments.config import parse_sets
    from slam.base import LOCALIZERS

    return parse_sets(sets or [], {n: LOCALIZERS for n in names}, names)


RelationsOpt = Annotated[
    Path | None, typer.Option(help="carmen: benchmark relations file (Kümmerle et al.)")
]
TimeOffsetOpt = Annotated[
    float | None, typer.Option(help="carmen: seconds added to the relations' times")
]


DatasetOpt = Annotated[
    list[str] | None,
    typer.Option(
        "--dataset-option",
        help="NAME=VALUE: an option of the dataset importer (with --format), e.g. "
        "calibration=none for MRCLAM's uncorrected values; repeatable",
    ),
]


DATASET_OPTIONS_NEED_FORMAT = (
    "--robot, --relations, --time-offset and --dataset-option need --format"
)


def _dataset_options(robot, relations, time_offset, extra: list[str] | None = None) -> dict:
    given = {"robot": robot, "relations": relations, "time_offset": time_offset}
    out = {k: (str(v) if isinstance(v, Path) else v) for k, v in given.items() if v is not None}
    for text in extra or []:
        name, eq, value = text.partition("=")
        if not eq or not name.strip():
            raise ConfigError(f"--dataset-option takes NAME=VALUE, got '{text}'")
        out[name.strip()] = value.strip()
    return out


@app.command(name="import")
@friendly
def import_(
    format: Annotated[str, typer.Argument(help="mrclam, carmen, victoria-park or mtrx5700")],
    path: Annotated[Path, typer.Argument(help="dataset folder or log file")],
    output: Annotated[Path, typer.Option("-o", "--output", help="trial log to write (.mcap)")],
    robot: RobotOpt = None,
    relations: RelationsOpt = None,
    time_offset: TimeOffsetOpt = None,
    dataset_option: DatasetOpt = None,
) -> None:
    """Convert a public dataset into a trial log (messages, calibration, ground truth)."""
    from hardware.datasets import import_dataset

    summary = import_dataset(
        format, path, output, **_dataset_options(robot, relations, time_offset, dataset_option)
    )
    d = summary.to_dict()
    console.print(
        f"wrote {d['path']}: {d.get('messages', '?')} messages over {d['duration_s']:.1f} s",
        highlight=False,
    )


# the options of `replay` that take more than a line
_ReplayMapModelOpt = Annotated[
    str, typer.Option(help="log-odds, or view-count (the thesis's >50 % of views)")
]
_ReplayFormatOpt = Annotated[
    str | None, typer.Option(help="read LOG as a dataset: mrclam, carmen, victoria-park, mtrx5700")
]
_ReplayControllerOpt = Annotated[
    str | None,
    typer.Option(
        help="recompute the brake commands with this controller on the replay's pose "
        "and map, and compare them with the logged ones"
    ),
]
_ReplayFoxgloveOpt = Annotated[
    bool,
    typer.Option(
        "--foxglove",
        help="serve the replay to Foxglove (WebSocket), paced to real time; the final "
        "state stays up until Ctrl-C (or --linger S)",
    ),
]
_ReplayLingerOpt = Annotated[
    float | None, typer.Option(help="--foxglove: serve this long after the end [s]")
]
CalibrationOpt = Annotated[
    Path | None,
    typer.Option(
        help="walker calibration JSON (e.g. from walkerslam calibrate) whose wheel diameters "
        "and track replace the log's for the odometry"
    ),
]


@app.command()
@friendly
def replay(
    log: Annotated[Path, typer.Argument(help="trial log (.mcap), or a dataset with --format")],
    localizer: Annotated[str, typer.Option(help="localizer to run")] = "dead-reckoning",
    out: Annotated[Path, typer.Option(help="output folder")] = Path("out/replay"),
    map_model: _ReplayMapModelOpt = "log-odds",
    resolution: Annotated[float, typer.Option(help="map cell size [m]")] = 0.05,
    format: _ReplayFormatOpt = None,
    robot: RobotOpt = None,
    relations: RelationsOpt = None,
    time_offset: TimeOffsetOpt = None,
    controller: _ReplayControllerOpt = None,
    set_: SetOpt = None,
    dataset_option: DatasetOpt = None,
    foxglove: _ReplayFoxgloveOpt = False,
    foxglove_port: Annotated[int, typer.Option(help="--foxglove: port (0: any free)")] = 8765,
    speed: Annotated[float, typer.Option(help="--foxglove: replay speed, × real time")] = 1.0,
    fast: Annotated[bool, typer.Option("--fast", help="--foxglove: do not pace")] = False,
    linger: _ReplayLingerOpt = None,
    calibration: CalibrationOpt = None,
    mitigation: MitigationOpt = None,
    scan_corners: Annotated[
        bool,
        typer.Option(
            "--scan-corners",
            help="also give the localizer each laser scan's corners as landmarks without IDs",
        ),
    ] = False,
    landmark_map: Annotated[
        Path | None,
        typer.Option(
            help='a landmark map to localize in, instead of the log\'s: {"id": [x, y]} JSON, '
            "e.g. an earlier SLAM replay's landmarks.json (particle-filter)",
        ),
    ] = None,
) -> None:
    """Replay a trial log through a localizer and the mapper; write maps, trajectories,
    metrics (with the drag metrics: phantom area over time, obstacle drag, over-steer).

    (Long for its option list: typer reads the options from this signature.)"""
    from control.base import CONTROLLERS
    from experiments.config import configure
    from experiments.run import check_gyro, given_map, replay_log, source_metadata
    from mapping.grid import GridConfig, MapModel
    from mapping.mapper import MapperConfig
    from slam.base import LOCALIZERS

    LOCALIZERS.spec(localizer)  # an unknown name: one line, before any work
    overrides = _localizer_overrides(set_, [localizer]).get(localizer, {})
    names, mitigated = parse_mitigations(mitigation, localizer, calibration)
    checked = configure(LOCALIZERS, localizer, None, {**mitigated.localizer_settings, **overrides})
    given_map(landmark_map, checked.config, localizer)  # a bad map file: before any work
    _check_out_dir(out)
    if controller is not None:
        CONTROLLERS.spec(controller)  # an unknown name: one line, before any work
    if map_model not in [m.value for m in MapModel]:
        raise ConfigError(f"unknown map model '{map_model}'; valid: log-odds, view-count")
    mapper_config = MapperConfig(grid=GridConfig(resolution_m=resolution, model=map_model))
    trial, total = _open_source(
        log, format, _dataset_options(robot, relations, time_offset, dataset_option)
    )
    override = _calibration_override(calibration, [trial.calibration])
    start: list[float] = []

    def elapsed(t: float) -> float:
        if not start:
            start.append(t)
        return t - start[0]

    # the settings the source proposes (e.g. a dataset's noise levels), then --set
    built = configure(
        LOCALIZERS, localizer, source_metadata(trial), {**mitigated.localizer_settings, **overrides}
    )
    check_gyro(built.config, trial, str(log))
    if built.proposed:
        what = ", ".join(f"{k}={v}" for k, v in built.proposed.items())
        err_console.print(f"note: the source proposes {what}", highlight=False, soft_wrap=True)
    view = _replay_view(trial, foxglove_port, speed) if foxglove else None
    try:
        with progress_bar(f"replaying with {localizer}", total) as update:
            res = replay_log(
                trial,
                out,
                localizer=localizer,
                localizer_overrides=overrides,
                mapper_config=mapper_config,
                controller=controller,
                calibration=override,
                mitigations=names,
                scan_corners=scan_corners,
                landmark_map=landmark_map,
                progress=lambda t: update(elapsed(t)),
                phase=update.phase,
                observers=(
                    (lambda p: [view.observer(p, realtime=not fast, speed=speed)])
                    if view is not None
                    else None
                ),
            )
        _print_metrics(res.metrics, res.files)
        _print_drag(res.metrics)
        if view is not None:
            view.publish_state(res.pipeline)
            _linger(view, linger)
    finally:
        if view is not None:
            view.close()


def _open_source(log: Path, format: str | None, dataset_opts: dict):
    """The trial to replay and its duration (None when a dataset's is unknown until read);
    a bad file fails here, before the progress bar."""
    if format is not None:
        from hardware.datasets import open_dataset

        return open_dataset(format, log, **dataset_opts), None
    if dataset_opts:
        raise ConfigError(DATASET_OPTIONS_NEED_FORMAT)
    from hardware.log import read_log

    trial = read_log(log)
    t0, t1 = trial.time_range if trial.message_count else (0.0, 0.0)
    return trial, t1 - t0


def _calibration_override(path: Path | None, calibrations: list):
    """--calibration's file, checked against the sources' calibrations (their encoders)
    before any work; None without the option."""
    from experiments.calibration_override import CalibrationOverride

    override = CalibrationOverride.load(path)
    if override is not None:
        for cal in calibrations:
            override.apply(cal)
    return override


def _replay_view(trial, port: int, speed: float):
    """The Foxglove view of a replay (experiments.live_view), its address printed."""
    from experiments.live_view import FoxgloveView

    if not speed > 0:
        raise ConfigError(f"--speed must be > 0, got {speed}")
    view = FoxgloveView(trial.calibration, port=port)
    console.print(f"live view: {view.url} (Foxglove: open a WebSocket connection)")
    return view


def _check_out_dir(out: Path) -> None:
    """An output folder that cannot be one fails before any work."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: the output folder is a file")


def _linger(view, seconds: float | None) -> None:
    """Keep the live view serving after a replay: `seconds`, or until Ctrl-C."""
    import time

    console.print(
        f"serving the final state at {view.url}"
        + (f" for {seconds:.0f} s" if seconds is not None else "; Ctrl-C to stop"),
        highlight=False,
    )
    try:
        if seconds is not None:
            time.sleep(max(seconds, 0.0))
        else:
            while True:
                time.sleep(1.0)
    except KeyboardInterrupt:
        pass


def _print_drag(metrics: dict) -> None:
    """One line each for the drag metrics of a replay (experiments.drag)."""
    lines = []
    if "drag" in metrics and "local" in metrics["drag"]:
        d = metrics["drag"]["local"]
        braked = d["braked_turn"]
        during = (
            f"{braked['mean_m']:.3f} m in braked turns ({braked['frames']} frames), "
            if braked["frames"]
            else ""
        )
        lines.append(
            f"obstacle drag in 1 s: {during}{d['other']['mean_m']:.3f} m otherwise; "
            f"absolute {metrics['drag']['absolute']['all']['mean_m']:.3f} m"
        )
    if "over_steer" in metrics and metrics["over_steer"].get("episodes"):
        o = metrics["over_steer"]
        lines.append(
            f"over-steer ({o['commands']} {o['controller']} commands vs the true pose and map): "
            f"{o['over_steer_deg']:.1f}° over {o['episodes']} braking episodes "
            f"(under-steer {o['under_steer_deg']:.1f}°)"
        )
    if "controller_replay" in metrics:
        c = metrics["controller_replay"]
        if c.get("commands"):
            lines.append(
                f"controller replay ({c['controller']}): {c['commands']} commands, RMS difference "
                f"{c['rms_diff_nm']:.3f} N·m, same braked side "
                f"{100 * c['same_side_fraction']:.1f} %"
            )
        else:
            lines.append(f"controller replay ({c['controller']}): no brake commands in the log")
    for line in lines:
        console.print(line, highlight=False)


@app.command()
@friendly
def demo(
    out: Annotated[Path, typer.Option(help="output folder")] = Path("out/demo"),
    seed: Annotated[int, typer.Option(help="random seed")] = 0,
    duration: Annotated[float, typer.Option(help="longest simulated time [s]")] = 300.0,
) -> None:
    """Simulate thesis-course on a dusty floor with open-loop braking, replay it with dead
    reckoning, and write maps, trajectories and error figures against ground truth."""
    from experiments.run import replay_log, simulate_trial

    out.mkdir(parents=True, exist_ok=True)
    log = out / "trial.mcap"
    with progress_bar("simulating thesis-course (dusty, open-loop)", duration) as update:
        sim = simulate_trial(
            "thesis-course",
            log,
            controller="open-loop",
            surface="dusty",
            seed=seed,
            duration_s=duration,
            progress=update,
        )
    console.print(
        f"simulated {sim.sim_time_s:.1f} s in {sim.wall_time_s:.1f} s → {log}", highlight=False
    )
    with progress_bar("replaying with dead-reckoning", sim.sim_time_s) as update:
        res = replay_log(log, out, localizer="dead-reckoning", progress=update)
    m = res.metrics
    ref_phantom = m.get("reference_map", {}).get("phantom_area_m2", float("nan"))
    console.print(
        "\n[bold]Dead reckoning under brake slip[/]: the estimate drifts "
        f"{m.get('final_position_error_m', float('nan')):.2f} m by the end; obstacles seen "
        f"during braked turns are dragged across the map ({m.get('phantom_area_m2', 0):.2f} m² of "
        f"phantom obstacles vs {ref_phantom:.2f} m² "
        "when the same frames are mapped at the true poses).",
        highlight=False,
    )
    _print_metrics(m, res.files)
    console.print(
        f"\nopen {out / 'maps_side_by_side.png'} for the map comparison.", highlight=False
    )


@app.command()
@friendly
def compare(
    logs: Annotated[
        list[Path], typer.Argument(help="trial logs (.mcap), or datasets with --format")
    ],
    localizers: Annotated[str, typer.Option(help="all, or names separated by commas")] = "all",
    seeds: Annotated[int, typer.Option(help="runs of each stochastic localizer")] = 3,
    out: Annotated[Path, typer.Option(help="output folder")] = Path("out/compare"),
    format: Annotated[
        str | None,
        typer.Option(help="read LOGS as datasets: mrclam, carmen, victoria-park, mtrx5700"),
    ] = None,
    robot: Annotated[
        str | None, typer.Option(help="mrclam: robot numbers separated by commas, e.g. 1,2,3,4,5")
    ] = None,
    relations: RelationsOpt = None,
    time_offset: TimeOffsetOpt = None,
    set_: SetOpt = None,
    dataset_option: DatasetOpt = None,
    calibration: CalibrationOpt = None,
    mitigation: MitigationOpt = None,
) -> None:
    """Run localizers on logs; write results.csv, results.db, report.md; print the table.

    With several logs (or robots) each localizer also gets a row with the mean over them."""
    from experiments.compare import compare as run_compare
    from experiments.compare import parse_localizers

    names = parse_localizers(localizers)
    overrides = _localizer_overrides(set_, names)
    # each must apply to every localizer compared: one line before any run otherwise
    mitigations = ()
    for n in names:
        mitigations = parse_mitigations(mitigation, n, calibration)[0]
    sources, calibrations = _compare_sources(
        logs, format, robot, relations, time_offset, dataset_option
    )
    override = _calibration_override(calibration, calibrations)
    if seeds < 1:
        raise ConfigError(f"--seeds must be >= 1, got {seeds}")
    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        TimeElapsedColumn(),
        console=err_console,
        transient=True,
    ) as bar:
        task = bar.add_task("comparing", total=None)
        res = run_compare(
            sources,
            names,
            seeds,
            out,
            progress=lambda what: bar.update(task, description=what),
            overrides=overrides,
            calibration=override,
            mitigations=mitigations,
        )
    console.print(_summary_table(res.summary))
    console.print("files: " + ", ".join(str(p) for p in res.files.values()), highlight=False)


def _compare_sources(logs, format, robot, relations, time_offset, dataset_option):
    """compare's sources — trial log paths (each read once to fail fast on a bad file), or
    the datasets opened for each log and --robot — and their calibrations."""
    sources: list = []
    calibrations: list = []
    if format is not None:
        from hardware.datasets import open_dataset

        robots: list[int | None] = [None]
        if robot is not None:
            try:
                robots = [int(r) for r in robot.split(",") if r.strip()]
            except ValueError:
                raise ConfigError(
                    f"--robot must be numbers separated by commas, got {robot!r}"
                ) from None
        for log in logs:
            for r in robots:
                opts = _dataset_options(r, relations, time_offset, dataset_option)
                sources.append(open_dataset(format, log, **opts))
                calibrations.append(sources[-1].calibration)
    else:
        if robot is not None or relations is not None or time_offset is not None or dataset_option:
            raise ConfigError(DATASET_OPTIONS_NEED_FORMAT)
        from hardware.log import read_log

        for log in logs:
            calibrations.append(read_log(log).calibration)  # a bad file fails before any run
        sources = list(logs)
    return sources, calibrations


def _summary_table(summary: list[dict]) -> Table:
    """compare's table: a row per log and localizer, the metrics any row has (mean±std)."""
    short = {
        "ate_rmse_m": "ATE m",
        "ate_rmse_unaligned_m": "ATE unal. m",
        "rpe_trans_m": "RPE m",
        "relations_trans_mean_m": "rel. m",
        "relations_rot_mean_deg": "rel. deg",
        "gps_rmse_m": "GPS m",
        "gps_rmse_unaligned_m": "GPS unal. m",
        "landmark_rmse_m": "landm. m",
        "wall_spread_m": "walls m",
        "phantom_area_m2": "phantom m²",
        "realtime_factor": "× RT",
    }
    shown = [k for k in short if any(s[k] is not None for s in summary)]
    table = Table("log", "localizer", "runs", *[short[k] for k in shown])
    for s in summary:
        cells = []
        for k in shown:
            v = s[k]
            spread = "" if v is None or s["runs"] == 1 else f"±{v[1]:.3f}"
            cells.append("" if v is None else f"{v[0]:.3f}{spread}")
        table.add_row(s["log"], s["localizer"], str(s["runs"]), *cells)
    return table


@app.command(name="slip-push")
@friendly
def slip_push(
    out: Annotated[Path, typer.Option(help="output folder")] = Path("out/slip-push"),
    surface: Annotated[
        list[str] | None, typer.Option(help="surfaces to compare [default: clean, dusty]")
    ] = None,
    level: Annotated[float, typer.Option(help="brake level, fraction of full PWM")] = 0.6,
    length: Annotated[float, typer.Option(help="length of the push [m]")] = 6.0,
    seed: Annotated[int, typer.Option(help="random seed")] = 0,
) -> None:
    """Thesis Fig 6.1: push the walker straight with neither, left, right or both brakes
    engaged; plot the true and the dead-reckoned paths."""
    from experiments.report import plot_slip_push
    from experiments.slip import BRAKE_SETTINGS, straight_push

    out.mkdir(parents=True, exist_ok=True)
    surfaces = surface or ["clean", "dusty"]
    results = [straight_push(s, b, level, length, seed) for s in surfaces for b in BRAKE_SETTINGS]
    table = Table("surface", "brakes", "lateral drift [m]", "heading error [deg]")
    summary = []
    for r in results:
        heading = float(
            r.end_in_start_frame(r.dead_reckoning)[2] - r.end_in_start_frame(r.truth)[2]
        )
        table.add_row(
            str(r.surface), r.brakes, f"{r.lateral_drift_m:+.3f}", f"{heading * 57.2958:+.1f}"
        )
        summary.append(
            {
                "surface": r.surface,
                "brakes": r.brakes,
                "lateral_drift_m": r.lateral_drift_m,
                "heading_error_rad": heading,
            }
        )
    console.print(table)
    fig = plot_slip_push(results, out / "slip_push.png")
    (out / "slip_push.json").write_text(
        json.dumps({"level": level, "length_m": length, "seed": seed, "results": summary}, indent=2)
        + "\n"
    )
    console.print(f"files: {fig}, {out / 'slip_push.json'}", highlight=False)


@app.command(name="list")
@friendly
def list_names(
    name: Annotated[
        str | None,
        typer.Argument(
            help="a localizer, controller or dataset format: its settings; a mitigation, "
            "or 'mitigations': what they set"
        ),
    ] = None,
) -> None:
    """List built-in courses, localizers, controllers, dataset formats, mitigations and
    live devices; with a NAME, its settings (what `--set NAME.FIELD=VALUE` takes) with
    their defaults, or what a mitigation sets ('mitigations': all of them)."""
    from rich.text import Text

    from control.base import CONTROLLERS
    from experiments.config import describe, explained_in
    from experiments.mitigations import MITIGATIONS
    from hardware.datasets import FORMATS
    from hardware.devices import DEPTH_CAMERAS, TAG_CAMERAS, forms
    from hardware.errors import UnknownNameError
    from hardware.sim.world import available_courses
    from slam.base import LOCALIZERS

    registries = (LOCALIZERS, CONTROLLERS, FORMATS)
    if name == "mitigations" or name in MITIGATIONS.names():
        _list_mitigations(None if name == "mitigations" else name)
        return
    if name is None:
        console.print("courses:         " + ", ".join(available_courses()), highlight=False)
        for reg in registries:
            console.print(f"{reg.kind + 's:':16s} " + ", ".join(reg.names()), highlight=False)
        console.print("mitigations:     " + ", ".join(MITIGATIONS.names()), highlight=False)
        for reg in (DEPTH_CAMERAS, TAG_CAMERAS):  # devices: --depth / --camera of live
            console.print(f"{reg.kind + 's:':16s} " + ", ".join(forms(reg)), highlight=False)
        console.print("settings of one: walkerslam list NAME", highlight=False)
        return
    for reg in registries:
        if name in reg.names():
            spec = reg.spec(name)
            console.print(f"{reg.kind} {name}: {spec.summary}", highlight=False, soft_wrap=True)
            table = Table("setting", "default", "type", box=None)
            for path, default, typ in describe(spec.config_type):
                table.add_row(*(Text(v) for v in (f"{name}.{path}", default, typ)))
            console.print(table)
            groups = explained_in(spec.config_type)
            if groups:
                console.print("explained in (python -m pydoc CLASS):", highlight=False)
                width = max(len(name) + 2 + len(g) for g, _ in groups)
                for group, where in groups:
                    console.print(f"  {name + '.' + group + '*':{width}s} {where}", highlight=False)
            return
    valid = sorted(n for reg in (*registries, MITIGATIONS) for n in reg.names())
    raise UnknownNameError("localizer, controller, dataset format or mitigation", name, valid)


def _list_mitigations(name: str | None) -> None:
    """What each mitigation (or the one named) sets, where it applies and what it needs."""
    from experiments.mitigations import MITIGATIONS

    table = Table("mitigation", "applies to", "sets", "needs", box=None)
    for n in [name] if name else MITIGATIONS.names():
        m = MITIGATIONS.create(n)
        sets = [
            f"{loc}.{path}={value}"
            for loc, fields in m.localizers.items()
            for path, value in fields.items()
        ]
        if m.hygiene is not None:
            sets += [
                f"map.hygiene.{k}={v}" for k, v in vars(m.hygiene).items() if v not in (None, False)
            ]
        needs = [" or ".join(t.__name__ for t in group) for group in m.needs]
        needs += ["--calibration FILE"] if m.needs_calibration else []
        needs += [f"a simulated {s}" for s in m.simulated]
        applies = "every localizer" if "*" in m.localizers else ", ".join(m.localizers)
        table.add_row(n, applies, "\n".join(sets) or "-", "\n".join(needs) or "-")
        if name:
            console.print(f"mitigation {n}: {m.summary}", highlight=False, soft_wrap=True)
    console.print(table)


@app.command()
@friendly
def info(log: Annotated[Path, typer.Argument(help="trial log (.mcap)")]) -> None:
    """Summarise a trial log: topics, message counts, time span, metadata."""
    from hardware.log import read_log

    trial = read_log(log)
    t0, t1 = trial.time_range if trial.message_count else (0.0, 0.0)
    console.print(
        f"{log}: {trial.message_count} messages over {t1 - t0:.1f} s"
        f"{'' if trial.complete else ' (incomplete: recovered)'}",
        highlight=False,
    )
    from rich.markup import escape

    heads = ("topic", "type", "messages", "rate [Hz]", "from [s]", "to [s]")
    table = Table(*map(escape, heads), box=None)
    for topic, typ in sorted(trial.topics.items()):
        n, first, last = trial.topic_counts.get(topic, (0, 0.0, 0.0))
        rate = f"{(n - 1) / (last - first):.1f}" if n > 1 and last > first else "—"
        table.add_row(topic, typ.__name__, str(n), rate, f"{first:.2f}", f"{last:.2f}")
    console.print(table)
    cal = trial.calibration
    console.print(
        f"calibration: wheel {cal.wheel_diameter_m * 1e3:.1f} mm, track {cal.track_m:.3f} m, "
        f"{cal.counts_per_rev} counts/rev, depth {cal.depth_intrinsics.width}x"
        f"{cal.depth_intrinsics.height}, tags {cal.tag_family} {cal.tag_size_m} m",
        highlight=False,
        soft_wrap=True,
    )
    console.print("metadata: " + ", ".join(["calibration", *sorted(trial.metadata)]))
    cfg = trial.metadata.get("config")
    if cfg:
        console.print(json.dumps({k: v for k, v in cfg.items() if not isinstance(v, dict)}))


study_commands.register(app)  # course-study, corner-study
live_commands.register(app)  # live, board, calibrate-camera
calibrate_commands.register(app)  # calibrate


def main(argv: list[str] | None = None) -> int:
    """The `walkerslam` console script: the commands under the CLI's error rule, and
    typer's own usage errors (a bad option value, a missing argument) on one line too."""
    try:
        code = app(args=argv, prog_name="walkerslam", standalone_mode=False)
    except typer.Abort:
        print_error("aborted")
        return 130
    except typer.TyperException as e:  # typer's usage errors (click's, vendored)
        ctx = getattr(e, "ctx", None)
        where = ctx.command_path if ctx is not None else "walkerslam"
        text = e.format_message() if hasattr(e, "format_message") else str(e)
        print_error(f"{where}: {text} (see {where} --help)")
        return 2
    return code if isinstance(code, int) else 0
