"""`walkerslam live` and `walkerslam board`: the walker live, and the bench tool for
wiring it (`experiments.live`). `register(app)` adds them to the CLI; errors follow the
CLI's rule (one line `error: …`, exit 2; a bug keeps its traceback)."""

from __future__ import annotations

import math
import signal
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated

import typer
from rich.live import Live
from rich.text import Text

from experiments.cli_common import (
    MitigationOpt,
    console,
    err_console,
    friendly,
    parse_mitigations,
    parse_size,
)
from hardware.errors import ConfigError


@contextmanager
def _stop_on_signals(stop):
    """SIGINT (Ctrl-C) and SIGTERM call `stop()` once; a second Ctrl-C interrupts."""
    seen = {"n": 0}
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}

    def handler(signum, frame):
        seen["n"] += 1
        if seen["n"] > 1 and signum == signal.SIGINT:
            raise KeyboardInterrupt
        stop()

    for s in previous:
        signal.signal(s, handler)
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


@contextmanager
def _status_display(console, live_type, text_type):
    """A status line that updates in place; it appears with the first update (so that an
    error before it is one line of its own) and is cleared at the end."""
    view = None

    def show(line: str) -> None:
        nonlocal view
        if view is None:
            view = live_type(console=console, auto_refresh=False, transient=True)
            view.start()
        view.update(text_type(line), refresh=True)

    try:
        yield show
    finally:
        if view is not None:
            view.stop()


def _fmt_nm(v: float) -> str:
    return "—" if not math.isfinite(v) else f"{v:.2f}"


def status_line(s) -> str:
    """One line of a LiveStatus (experiments.live)."""
    rates = " ".join(f"{k} {v:.0f}Hz" for k, v in s.rates_hz.items())
    dropped = sum(s.dropped.values())
    p50, p99 = s.latency_ms
    lat = "—" if not math.isfinite(p50) else f"{p50:.1f}/{p99:.1f} ms"
    pwm = "—" if s.board_pwm is None else f"{s.board_pwm[0]}/{s.board_pwm[1]}"
    if s.board_timed_out:
        pwm += " (timed out)"
    stale = ",".join(s.stale) if s.stale else "-"
    stalled = f" stalled {','.join(s.stalled)}" if s.stalled else ""
    events = f" | {s.events[-1]}" if s.events else ""
    if s.view_url:
        events += f" | view {s.view_url}"
    return (
        f"{s.t:7.1f}s | {rates} | frame→cmd p50/p99 {lat} | brakes "
        f"{_fmt_nm(s.commanded_nm[0])}/{_fmt_nm(s.commanded_nm[1])} N·m PWM {pwm} | "
        f"σ {s.sigma_xy_m:.2f} m {s.sigma_theta_deg:.1f}° | dropped {dropped} | board errors "
        f"{s.board_errors} | stale {stale}{stalled}{events}"
    )


def _parse_pair(text: str, what: str) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in text.split(","))
    except ValueError:
        raise ConfigError(f"{what} takes two numbers L,R, got '{text}'") from None
    return a, b


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")


def image_files(paths: list[Path]) -> list[Path]:
    """The image files named, a folder standing for the images in it (sorted)."""
    out: list[Path] = []
    for p in paths:
        if p.is_dir():
            found = sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
            if not found:
                raise ConfigError(f"{p}: no images in the folder ({', '.join(IMAGE_SUFFIXES)})")
            out.extend(found)
        elif not p.exists():
            raise ConfigError(f"{p}: no such image")
        else:
            out.append(p)
    return out


# the options of `live` that take more than a line
_SerialOpt = Annotated[str | None, typer.Option(help="the board's serial port, e.g. /dev/ttyACM0")]
_DepthOpt = Annotated[
    str,
    typer.Option(
        help="kinect, kinect:INDEX, realsense, fakenect:DIR or none; all: walkerslam list"
    ),
]
_CameraOpt = Annotated[
    str,
    typer.Option(
        help="tag camera: a device INDEX, a video file or image folder, kinect, or none; "
        "all: walkerslam list"
    ),
]
_CameraCalibrationOpt = Annotated[
    Path | None,
    typer.Option(help="the tag camera's calibration YAML (walkerslam calibrate-camera)"),
]
_CameraFpsOpt = Annotated[
    float | None,
    typer.Option(help="pace a tag-camera video file or image folder to this rate"),
]
_CalibrationOpt = Annotated[
    Path | None,
    typer.Option(
        help="walker calibration JSON (default: the thesis walker; e.g. from walkerslam "
        "calibrate); with --sim its wheel diameters and track replace the simulated "
        "walker's software calibration"
    ),
]
_RecordOpt = Annotated[
    Path | None, typer.Option(help="record every stream and command to this .mcap")
]
_SetOpt = Annotated[
    list[str] | None,
    typer.Option(
        "--set",
        help="NAME.FIELD=VALUE: a field of the localizer's or controller's config (repeatable)",
    ),
]
_SimOpt = Annotated[
    bool,
    typer.Option(
        "--sim",
        help="the simulated walker in real time: board emulator on a pty, simulated cameras",
    ),
]
_FirmwareOpt = Annotated[
    bool, typer.Option("--firmware", help="--sim: the compiled firmware in simavr")
]
_GyroOpt = Annotated[
    bool,
    typer.Option("--gyro", help="--sim: the walker carries a yaw-rate gyro (an IMU on the board)"),
]
_FoxgloveOpt = Annotated[
    bool, typer.Option("--foxglove", help="serve the streams to Foxglove (WebSocket)")
]
_TriggerOpt = Annotated[
    str,
    typer.Option(
        help="frame: a command right after each depth frame (at --rate while "
        "frames stall); timer: commands at --rate only"
    ),
]


def live(
    localizer: Annotated[str, typer.Option(help="localizer to run")] = "dead-reckoning",
    controller: Annotated[str, typer.Option(help="braking controller")] = "open-loop",
    serial: _SerialOpt = None,
    depth: _DepthOpt = "none",
    camera: _CameraOpt = "none",
    camera_calibration: _CameraCalibrationOpt = None,
    camera_fps: _CameraFpsOpt = None,
    calibration: _CalibrationOpt = None,
    mitigation: MitigationOpt = None,
    record: _RecordOpt = None,
    duration: Annotated[float | None, typer.Option(help="stop after this many s")] = None,
    set_: _SetOpt = None,
    sim: _SimOpt = False,
    firmware: _FirmwareOpt = False,
    gyro: _GyroOpt = False,
    course: Annotated[str, typer.Option(help="--sim: course name or JSON")] = "thesis-course",
    seed: Annotated[int, typer.Option(help="--sim: random seed")] = 0,
    surface: Annotated[str, typer.Option(help="--sim: clean, dusty or S")] = "dusty",
    depth_size: Annotated[str, typer.Option(help="--sim: depth image WxH")] = "160x120",
    depth_rate: Annotated[int, typer.Option(help="--sim: depth frames per second")] = 10,
    sim_duration: Annotated[float, typer.Option(help="--sim: longest simulated trial [s]")] = 300.0,
    foxglove: _FoxgloveOpt = False,
    foxglove_port: Annotated[int, typer.Option(help="--foxglove: port (0: any)")] = 8765,
    trigger: _TriggerOpt = "frame",
    rate: Annotated[float, typer.Option(help="the controller's loop rate [Hz]")] = 10.0,
) -> None:
    """Run a localizer and a braking controller live on the walker (or, with --sim, on
    the simulated walker in real time), recording everything; Ctrl-C stops and
    releases the brakes.

    (Long for its option list: typer reads the options from this signature.)"""
    from dataclasses import replace

    from experiments.live import LIVE_LOOP, LiveError, LiveOptions, LiveRun, SimWalker

    sets = _live_sets(localizer, controller, set_ or [])
    names, mitigated = parse_mitigations(mitigation, localizer, calibration)
    if sim and (serial is not None or depth != "none" or camera != "none"):
        raise LiveError("--sim brings its own board and cameras: drop --serial/--depth/--camera")
    if (firmware or gyro) and not sim:
        raise LiveError("--firmware and --gyro go with --sim")
    sim_walker = None
    if sim:
        sim_walker = SimWalker(
            course=course,
            seed=seed,
            surface=surface,
            duration_s=sim_duration,
            depth_size=parse_size(depth_size),
            depth_rate_hz=depth_rate,
            firmware=firmware,
            gyro=gyro or "gyro" in mitigated.simulated,
        )
    opts = LiveOptions(
        localizer=localizer,
        controller=controller,
        serial=serial,
        depth=depth,
        camera=camera,
        camera_yaml=str(camera_calibration) if camera_calibration else None,
        camera_fps=camera_fps,
        calibration=str(calibration) if calibration else None,
        record=str(record) if record else None,
        duration_s=duration,
        localizer_overrides=sets.get(localizer, {}),
        controller_overrides=sets.get(controller, {}),
        mitigations=names,
        sim=sim_walker,
        foxglove_port=foxglove_port if foxglove else None,
        loop=replace(LIVE_LOOP, trigger=trigger, rate_hz=rate),
    )
    with _status_display(err_console, Live, Text) as show:
        run = LiveRun(opts, on_status=lambda s: show(status_line(s)), on_phase=show)
        with _stop_on_signals(run.stop):
            res = run.run()
    _print_live_result(res)


def _live_sets(localizer: str, controller: str, sets: list[str]) -> dict[str, dict]:
    """The --set overrides of the localizer and the controller, checked before any device
    opens (unknown names, a shared name, a field either config lacks)."""
    from control.base import CONTROLLERS
    from experiments.config import parse_sets
    from slam.base import LOCALIZERS

    LOCALIZERS.spec(localizer)
    CONTROLLERS.spec(controller)
    if localizer == controller:
        raise ConfigError("the localizer and the controller need different names")
    return parse_sets(
        sets, {localizer: LOCALIZERS, controller: CONTROLLERS}, [localizer, controller]
    )


def _print_live_result(res) -> None:
    """The summary line of a finished live run (experiments.live.LiveResult)."""
    lat = res.latency_ms
    console.print(
        f"live run ended ({res.ended_by}) after {res.duration_s:.1f} s: "
        f"{res.commands} brake commands, frame→command latency p50 {lat['p50']:.1f} ms, "
        f"p99 {lat['p99']:.1f} ms over {lat['frames']} frames; dropped "
        f"{sum(res.dropped.values())} frames; board: {res.board['ticks']} ticks, "
        f"{res.board['bad_lines']} bad lines, {res.board['seq_gaps']} sequence gaps, "
        f"{res.board['resets']} resets, {res.board['reconnects']} reconnects "
        f"(warm-up before the devices opened: {res.warm_up_s:.1f} s)",
        highlight=False,
        soft_wrap=True,
    )
    if "log" in res.files:
        console.print(f"recorded → {res.files['log']}", highlight=False, soft_wrap=True)


def board(
    port: Annotated[str, typer.Argument(help="serial port, e.g. /dev/ttyACM0")],
    duration: Annotated[float | None, typer.Option(help="stop after this many s")] = None,
    record: Annotated[
        Path | None, typer.Option(help="record ticks and commands to this .mcap")
    ] = None,
    brake: Annotated[
        str | None, typer.Option(help="hold this brake command, L,R torques in N·m")
    ] = None,
    calibration: Annotated[
        Path | None, typer.Option(help="walker calibration JSON (default: the thesis walker)")
    ] = None,
) -> None:
    """The bench tool for wiring the walker: handshake, print the firmware, the tick
    rate and both encoder counts live, hold a brake command; exit releases the brakes."""

    from experiments.live import bench_board
    from hardware.calibration import WalkerCalibration, load_calibration

    brake_nm = _parse_pair(brake, "--brake") if brake else None
    cal = load_calibration(calibration) if calibration is not None else WalkerCalibration()
    stop = threading.Event()

    def reading(r) -> str:
        pwm = "—" if r.pwm is None else f"{r.pwm[0]}/{r.pwm[1]}"
        s = r.stats
        return (
            f"{r.t:7.1f}s  left {r.counts[0]:>9d}  right {r.counts[1]:>9d}  "
            f"{r.rate_hz:5.0f} Hz  PWM {pwm}{' (timed out)' if r.timed_out else ''}  "
            f"bad lines {s.bad_lines}  gaps {s.seq_gaps}  resets {s.resets}"
        )

    with _status_display(err_console, Live, Text) as show:
        with _stop_on_signals(stop.set):
            res = bench_board(
                port,
                calibration=cal,
                duration_s=duration,
                record=str(record) if record else None,
                brake_nm=brake_nm,
                on_update=lambda r: show(reading(r)),
                stop=stop,
            )
    hs = res.handshake
    console.print(
        f"{port}: firmware {hs.firmware} (protocol {hs.proto}), {hs.rate_hz} Hz, "
        f"{hs.cpr} counts/rev, reset cause {hs.reset_cause}; {res.ticks} ticks in "
        f"{res.duration_s:.1f} s, counts left {res.counts[0]} right {res.counts[1]}; "
        f"brakes released",
        highlight=False,
        soft_wrap=True,
    )
    if "log" in res.files:
        console.print(f"recorded → {res.files['log']}", highlight=False, soft_wrap=True)


def calibrate_camera_cmd(
    images: Annotated[
        list[Path], typer.Argument(help="photos of a checkerboard (files or folders)")
    ],
    board: Annotated[
        str, typer.Option(help="inner corners COLSxROWS, e.g. 9x6 for 10x7 squares")
    ] = "9x6",
    square: Annotated[float, typer.Option(help="side of a square [m]")] = 0.025,
    output: Annotated[
        Path, typer.Option("-o", "--output", help="camera calibration YAML to write")
    ] = Path("camera.yaml"),
    tag_size: Annotated[
        float | None, typer.Option(help="side of the AprilTags it will see [m]")
    ] = None,
    tag_family: Annotated[str | None, typer.Option(help="their family")] = None,
    camera_name: Annotated[str, typer.Option(help="name written in the YAML")] = "camera",
    min_images: Annotated[int, typer.Option(help="fewest usable images")] = 5,
) -> None:
    """Calibrate a camera from checkerboard photos (OpenCV); print the RMS
    reprojection error and write the YAML that `walkerslam live
    --camera-calibration` reads."""
    from hardware.camera_calibration import calibrate_camera

    try:
        cols, rows = (int(v) for v in board.lower().split("x"))
    except ValueError:
        raise ConfigError(f"--board takes COLSxROWS inner corners, got '{board}'") from None
    files = image_files(images)
    res = calibrate_camera(
        [str(f) for f in files],
        (cols, rows),
        square,
        min_images=min_images,
        camera_name=camera_name,
    )
    for line in res.summary_lines():
        console.print(line, highlight=False, soft_wrap=True)
    path = res.save(output, camera_name=camera_name, tag_family=tag_family, tag_size_m=tag_size)
    console.print(f"wrote {path}", highlight=False, soft_wrap=True)


def register(app: typer.Typer) -> None:
    """Add `live`, `board` and `calibrate-camera` to `app` (the `walkerslam` CLI)."""
    app.command()(friendly(live))
    app.command()(friendly(board))
    app.command(name="calibrate-camera")(friendly(calibrate_camera_cmd))
