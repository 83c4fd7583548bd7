"""`walkerslam calibrate`: the walker's wheel diameters and track from UMBmark logs.

Reads the encoder counts (and the ground truth, when a log has it) of one or more logs
of laps of a taped square pushed both ways, estimates the wheel geometry — by the UMBmark
closed form (`slam.umbmark`, needs no ground truth) or by least squares against the
ground truth (`slam.wheel_odometry.fit_to_groundtruth`) — and writes a calibration file
(`hardware.calibration`'s JSON) that `--calibration FILE` of the other commands reads.
Nothing here prints (the CLI does).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hardware.calibration import WalkerCalibration, load_calibration, save_calibration
from hardware.choices import Choice
from hardware.errors import CalibrationError, ConfigError
from hardware.log import read_log
from slam.square_run import SquareRun
from slam.umbmark import (
    CountsRun,
    UmbmarkFit,
    analyse_runs,
    fit_umbmark,
    require_both_directions,
)
from slam.wheel_odometry import GroundTruthRun, WheelGeometry, fit_to_groundtruth


class Method(Choice):
    """How the geometry is estimated: ground truth when every log has it, else UMBmark."""

    AUTO = "auto"
    UMBMARK = "umbmark"
    GROUND_TRUTH = "ground-truth"


@dataclass(frozen=True)
class CalibrationLog:
    """One log's encoder counts at times t ((N, 2)), its true poses at those times (None
    without ground truth) and the calibration it was recorded with."""

    name: str
    t: np.ndarray
    counts: np.ndarray
    truth: np.ndarray | None
    calibration: WalkerCalibration


def read_calibration_log(path: str | Path) -> CalibrationLog:
    """The counts and ground truth of a trial log; CalibrationError without ticks."""
    trial = read_log(path)
    enc = np.array([(m.t, m.left, m.right) for m in trial.messages(["/encoders"])], float)
    if len(enc) < 2:
        raise CalibrationError(f"{path}: no encoder ticks to calibrate from")
    truth = None
    if "/groundtruth/pose" in trial.topics:
        gt = np.array(
            [(m.t, m.x, m.y, m.theta) for m in trial.messages(["/groundtruth/pose"])], float
        )
        inside = (enc[:, 0] >= gt[0, 0]) & (enc[:, 0] <= gt[-1, 0])
        if len(gt) > 1 and inside.all():
            theta = np.unwrap(gt[:, 3])
            truth = np.column_stack(
                [np.interp(enc[:, 0], gt[:, 0], v) for v in (gt[:, 1], gt[:, 2], theta)]
            )
    return CalibrationLog(str(path), enc[:, 0], enc[:, 1:], truth, trial.calibration)


@dataclass(frozen=True)
class ReturnErrors:
    """The laps of one direction: how many, and the mean and spread of their closures
    (x along the side, y to the left [m], heading [rad]; `slam.umbmark`)."""

    laps: int
    mean: np.ndarray
    std: np.ndarray


def return_errors(runs: Sequence[SquareRun], direction: int) -> ReturnErrors:
    errors = np.array([c.error for r in runs for c in r.closures_of(direction)]).reshape(-1, 3)
    if not len(errors):
        return ReturnErrors(0, np.full(3, np.nan), np.full(3, np.nan))
    return ReturnErrors(len(errors), errors.mean(axis=0), errors.std(axis=0))


@dataclass
class CalibrateResult:
    """What `calibrate` found: the method, the geometry assumed and estimated, the laps'
    return errors per direction (+1 counter-clockwise, -1 clockwise) before and after,
    UMBmark's iteration (with that method), the calibration written and its file."""

    method: Method
    assumed: WheelGeometry
    estimate: WheelGeometry
    before: dict[int, ReturnErrors]
    after: dict[int, ReturnErrors]
    umbmark: UmbmarkFit | None
    side_m: float | None
    calibration: WalkerCalibration
    path: Path


def calibrate(
    logs: Sequence[str | Path],
    out: str | Path,
    *,
    side_m: float | None = None,
    base: str | Path | None = None,
    method: Method | str = Method.AUTO,
) -> CalibrateResult:
    """Estimate the wheel geometry from UMBmark logs and write the calibration `out`:
    `base` (a calibration file; default the first log's) with the estimated wheel
    diameters and track. side_m: the square's side (the scale; without it the mean
    diameter is kept by UMBmark). CalibrationError when the logs show no laps of a
    square in both directions."""
    method = Method.parse(method, "--method")
    if side_m is not None and not (math.isfinite(side_m) and side_m > 0):
        raise ConfigError(f"--side must be > 0 m, got {side_m}")
    runs = [read_calibration_log(p) for p in logs]
    base_cal = load_calibration(base) if base is not None else runs[0].calibration
    cpr = _counts_per_rev(runs, base_cal, base)
    method = _method(method, runs)
    assumed = WheelGeometry.of(runs[0].calibration)
    counts = [CountsRun(r.t, r.counts) for r in runs]
    before = analyse_runs(counts, assumed, cpr, side_m)
    _check_laps(runs, before)
    fit = None
    if method == Method.UMBMARK:
        fit = fit_umbmark(counts, assumed, cpr, side_m)
        estimate = fit.geometry
    else:
        truth = [GroundTruthRun(r.counts, r.truth) for r in runs if r.truth is not None]
        estimate = fit_to_groundtruth(truth, assumed, cpr)
    after = analyse_runs(counts, estimate, cpr, side_m)
    calibration = estimate.applied_to(base_cal)
    path = save_calibration(calibration, out)
    return CalibrateResult(
        method, assumed, estimate,
        {d: return_errors(before, d) for d in (1, -1)},
        {d: return_errors(after, d) for d in (1, -1)},
        fit, side_m, calibration, path,
    )  # fmt: skip


def _counts_per_rev(runs: Sequence[CalibrationLog], base: WalkerCalibration, base_path) -> int:
    """The encoders' counts per revolution, the same in every log and in the base."""
    cpr = runs[0].calibration.counts_per_rev
    for r in runs[1:]:
        if r.calibration.counts_per_rev != cpr:
            raise CalibrationError(
                f"{r.name}: {r.calibration.counts_per_rev} counts per revolution, "
                f"{runs[0].name}: {cpr} (logs of one walker, please)"
            )
    if base.counts_per_rev != cpr:
        raise ConfigError(
            f"{base_path}: calibrated for {base.counts_per_rev} counts per revolution, "
            f"the logs' encoders count {cpr}"
        )
    return cpr


def _method(method: Method, runs: Sequence[CalibrationLog]) -> Method:
    """The method to use: auto is ground truth when every log has it."""
    without = [r.name for r in runs if r.truth is None]
    if method == Method.AUTO:
        return Method.UMBMARK if without else Method.GROUND_TRUTH
    if method == Method.GROUND_TRUTH and without:
        raise CalibrationError(
            f"{without[0]}: no ground truth to fit to (use --method umbmark or auto)"
        )
    return method


def _check_laps(runs: Sequence[CalibrationLog], analysed: Sequence[SquareRun]) -> None:
    """Every log has laps of a square, and all of them together laps both ways."""
    for run, a in zip(runs, analysed, strict=True):
        if not a.closures:
            square = sum(c.square for c in a.corners)
            raise CalibrationError(
                f"{run.name}: no laps of a square found ({len(a.corners)} turns, {square} of "
                "them corners of 60-120°): not a UMBmark run, or a different --side"
            )
    require_both_directions(analysed, ", ".join(r.name for r in runs))
