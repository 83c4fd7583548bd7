"""MTRX5700 (University of Sydney) "Robot Navigation and Mapping" assignment data —
SIMULATED in Player/Stage, with Gaussian noise added; not evidence of real-world
performance (../shared/data/mtrx5700_stage_sim/SOURCE.md).

`open_dataset("mtrx5700", FOLDER)` reads four whitespace-separated text files (CRLF, `%`
comment lines; plain or gzipped):

    velocityObs.txt    time_s time_us v [m/s] turn_rate [rad/s]   decimated, noise-free
    positionObs.txt    time_s time_us x [m] y [m]                 "GPS": true + N(0, 0.5 m)
    compassObs.txt     time_s time_us heading [rad]               true + N(0, 0.25 rad)
    laserFeatures.txt  x [m] y [m]                                the laser beacons (map)

(laserObs.txt, the raw laser scans, is not read: the public copy lacks it.)

- t = time_s + 1e-6·time_us, the files' Unix seconds, not offset; time_us must be an
  integer in [0, 1e6). Rows out of time order are stably sorted (noted in metadata).
- Velocity rows → `VelocityOdometry(t, v, ω)`, held until the next row.
- Position rows → `PositionFix(t, x, y, sigma_m=0.5)`; compass rows →
  `CompassHeading(t, heading, sigma_rad=0.25)`, the heading wrapped to (−π, π] (the
  file's run from −0.21 to 6.55 rad: noise added to a heading in [0, 2π)). Every fix and
  heading has the time of a velocity row; at equal times the velocity comes first.
- Beacons → metadata "landmarks" {"0": [x, y], ...} (file order): a known map, for
  figures and future beacon observations (there are none without the scans).

Reference trajectory (option reference="dead-reckoning", the default). There is no ground
truth. The velocities are the simulator's noise-free values, so dead reckoning on them
should follow the true path — but integrated as they are from (0, 0, 0), it does not:
the fixes scatter 1.46 m RMS around it (0.89 m after the best rigid fit of its start;
0.71 m is what σ 0.5 m per axis gives), and the compass's mean residual grows from 0.15
rad in the first half of the run to 0.28 rad in the second. One scale factor on both v and ω
(a time scale — what a simulator clock running slower than the timestamps would give;
the cause is not documented) and the start pose, fitted by least squares to the fixes
(σ 0.5 m) and the compass (σ 0.25 rad), explain the data as the files describe it:
scale 0.9766 ± 0.0012, start (−0.056, 0.049, 0.026 rad); residuals 0.53 / 0.52 m per
axis around the fixes (0.5 expected) and 0.27 rad around the compass (0.25), no trend
left (eighths of the run agree within 2–3 standard errors). So the importer emits
`GroundTruthPose` messages of dead reckoning on the scaled velocities from the fitted
start, at every velocity time, as the reference the metrics score against, and labels
it in metadata "groundtruth": "dead reckoning on the noise-free velocities, time-scaled
and started as fitted to the fixes and compass: a near-truth reference, NOT ground
truth", with the fit (`ReferenceFit`: the scale, the start, their σ, the residuals and
`reference_sigma_rms_m`, the reference's own position uncertainty from the fit's
covariance). The fit uses the same fixes the localizers fuse (4 parameters against 976
residuals). reference="none": no GroundTruthPose. The messages keep the files' unscaled
velocities: the localizers see the odometry as recorded, scale error included.

initial_pose: the reference's start (fitted); (0, 0, 0), the report's, with
reference="none". Calibration: the walker's defaults (velocity odometry needs no wheel
geometry). Metadata "localizer_settings" switches on compass and fix fusion
(`absolute.use_compass`, `absolute.use_position`, with the files' σ as the fallback
noise) in every localizer that has them (slam.absolute).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import least_squares

from hardware.calibration import WalkerCalibration
from hardware.choices import Choice, coerce
from hardware.datasets.base import (
    Dataset,
    DatasetError,
    StreamFactory,
    config_metadata,
    require_folder,
    sorted_by_time,
    span_and_counts,
    tie_ordered_streams,
    velocity_stream,
)
from hardware.datasets.textio import FolderFiles, Table, read_table
from hardware.geometry import wrap_angle
from hardware.messages import CompassHeading, PositionFix, VelocityOdometry
from hardware.registry import Spec

POSITION_SIGMA_M = 0.5  # the files' headers: "standard deviation of 0.5m"
COMPASS_SIGMA_RAD = 0.25  # "standard deviation of 0.25rad"
FILES = ("velocityObs.txt", "positionObs.txt", "compassObs.txt", "laserFeatures.txt")
REFERENCE_NOTE = (
    "dead reckoning on the noise-free simulator velocities, time-scaled and started as "
    "fitted to the GPS fixes and the compass: a near-truth reference, NOT ground truth"
)


class ReferenceKind(Choice):
    """The reference trajectory the importer offers (module docstring), or none."""

    DEAD_RECKONING = "dead-reckoning"
    NONE = "none"


@dataclass(frozen=True)
class Mtrx5700Options:
    """reference: "dead-reckoning" (GroundTruthPose messages of the fitted dead-reckoning
    reference, module docstring) or "none"."""

    reference: ReferenceKind = ReferenceKind.DEAD_RECKONING

    def __post_init__(self) -> None:
        coerce(self, reference=ReferenceKind)


def dead_reckon(
    t: np.ndarray, v: np.ndarray, w: np.ndarray, start: np.ndarray, scale: float = 1.0
) -> np.ndarray:
    """Poses (N, 3) at the times t of exact-arc dead reckoning on (scale·v, scale·ω), each
    held from its time to the next, from `start`; θ unwrapped (continuous)."""
    dt = np.diff(t)
    ds, dth = scale * v[:-1] * dt, scale * w[:-1] * dt
    theta = start[2] + np.concatenate([[0.0], np.cumsum(dth)])
    half = 0.5 * dth
    chord = ds * np.sinc(half / math.pi)  # the arc's chord: ds·sin(h)/h
    heading = theta[:-1] + half
    x = start[0] + np.concatenate([[0.0], np.cumsum(chord * np.cos(heading))])
    y = start[1] + np.concatenate([[0.0], np.cumsum(chord * np.sin(heading))])
    return np.column_stack([x, y, theta])


@dataclass(frozen=True)
class ReferenceFit:
    """The fitted reference (module docstring): scale and start pose (x, y, θ) with their
    standard deviations, the fixes' and compass's residuals around it, and the RMS over
    the run of the reference's own position σ (from the fit's covariance)."""

    scale: float
    start: tuple[float, float, float]
    scale_sigma: float
    start_sigma: tuple[float, float, float]
    fix_residual_mean_m: tuple[float, float]
    fix_residual_std_m: tuple[float, float]
    compass_residual_mean_rad: float
    compass_residual_std_rad: float
    reference_sigma_rms_m: float


def _residuals(q: np.ndarray, vel: np.ndarray, fix: np.ndarray, compass: np.ndarray):
    """Normalised residuals of the fixes (x then y) and the compass for parameters q =
    (x0, y0, θ0, scale)."""
    poses = dead_reckon(vel[:, 0], vel[:, 1], vel[:, 2], q[:3], q[3])
    t = vel[:, 0]
    rx = (fix[:, 1] - np.interp(fix[:, 0], t, poses[:, 0])) / POSITION_SIGMA_M
    ry = (fix[:, 2] - np.interp(fix[:, 0], t, poses[:, 1])) / POSITION_SIGMA_M
    rc = wrap_angle(compass[:, 1] - np.interp(compass[:, 0], t, poses[:, 2]))
    return np.concatenate([rx, ry, rc / COMPASS_SIGMA_RAD])


def fit_reference(vel: np.ndarray, fix: np.ndarray, compass: np.ndarray) -> ReferenceFit:
    """Least-squares scale and start of dead reckoning on `vel` (t, v, ω rows) against
    the fixes (t, x, y) and the compass (t, heading) at their documented σ."""
    sol = least_squares(_residuals, np.array([0.0, 0.0, 0.0, 1.0]), args=(vel, fix, compass))
    cov = np.linalg.inv(sol.jac.T @ sol.jac)
    n = len(fix)
    rx = sol.fun[:n] * POSITION_SIGMA_M
    ry = sol.fun[n : 2 * n] * POSITION_SIGMA_M
    rc = sol.fun[2 * n :] * COMPASS_SIGMA_RAD
    return ReferenceFit(
        scale=float(sol.x[3]),
        start=(float(sol.x[0]), float(sol.x[1]), float(wrap_angle(sol.x[2]))),
        scale_sigma=float(math.sqrt(cov[3, 3])),
        start_sigma=tuple(float(math.sqrt(cov[i, i])) for i in range(3)),
        fix_residual_mean_m=(float(rx.mean()), float(ry.mean())),
        fix_residual_std_m=(float(rx.std()), float(ry.std())),
        compass_residual_mean_rad=float(rc.mean()),
        compass_residual_std_rad=float(rc.std()),
        reference_sigma_rms_m=_reference_sigma(vel, sol.x, cov),
    )


def _reference_sigma(vel: np.ndarray, q: np.ndarray, cov: np.ndarray) -> float:
    """RMS over the run of the reference's position σ, √trace(J Σ Jᵀ) per pose, J the
    positions' derivatives by the parameters (central differences)."""
    t, v, w = vel[:, 0], vel[:, 1], vel[:, 2]
    cols = []
    for i, step in enumerate((1e-4, 1e-4, 1e-6, 1e-7)):
        d = np.zeros(4)
        d[i] = step
        hi = dead_reckon(t, v, w, (q + d)[:3], (q + d)[3])[:, :2]
        lo = dead_reckon(t, v, w, (q - d)[:3], (q - d)[3])[:, :2]
        cols.append((hi - lo) / (2.0 * step))
    jac = np.stack(cols, axis=-1)  # (N, 2, 4)
    var = np.einsum("nij,jk,nik->n", jac, cov, jac)
    return float(math.sqrt(np.mean(var)))


def _timed(table: Table, name: str, notes: list[str]) -> np.ndarray:
    """A table whose first two columns are time_s, time_us: rows (t, rest...) sorted by
    t; a DatasetError naming the line when time_us is not an integer in [0, 1e6)."""
    us = table.integer_column(1, "time_us")
    bad = np.nonzero((us < 0) | (us >= 1_000_000))[0]
    if len(bad):
        i = bad[0]
        raise DatasetError(
            f"{table.path}: line {table.lines[i]}: time_us must be in [0, 1000000), got {us[i]}"
        )
    t = table.data[:, 0] + 1e-6 * us
    return sorted_by_time(np.column_stack([t, table.data[:, 2:]]), name, notes)


def _read(files: FolderFiles, notes: list[str]):
    """(velocities (t, v, ω), fixes (t, x, y), compass (t, heading), beacons (x, y)); all
    four files are found before any is read."""
    paths = [files.find(name) for name in FILES]
    tables = [read_table(p, n, comments=("%",)) for p, n in zip(paths, (4, 4, 3, 2), strict=True)]
    vel = _timed(tables[0], "velocityObs", notes)
    if len(vel) < 2:
        raise DatasetError(f"{paths[0]}: needs at least two velocity rows, has {len(vel)}")
    fix = _timed(tables[1], "positionObs", notes)
    compass = _timed(tables[2], "compassObs", notes)
    return vel, fix, compass, tables[3].data


def _fix_stream(fix: np.ndarray) -> StreamFactory:
    def gen() -> Iterator[PositionFix]:
        for t, x, y in fix.tolist():
            yield PositionFix(t, x, y, POSITION_SIGMA_M)

    return gen


def _compass_stream(compass: np.ndarray) -> StreamFactory:
    def gen() -> Iterator[CompassHeading]:
        for t, heading in compass.tolist():
            yield CompassHeading(t, float(wrap_angle(heading)), COMPASS_SIGMA_RAD)

    return gen


def _metadata(
    options: Mtrx5700Options,
    folder: Path,
    data: tuple[np.ndarray, ...],
    fit: ReferenceFit | None,
    files: FolderFiles,
    notes: list[str],
) -> dict[str, dict[str, Any]]:
    """All the metadata (module docstring)."""
    vel, fix, compass, beacons = data
    initial = fit.start if fit is not None else (0.0, 0.0, 0.0)
    counts = {"VelocityOdometry": len(vel), "PositionFix": len(fix), "CompassHeading": len(compass)}
    if fit is not None:
        counts["GroundTruthPose"] = len(vel)
        truth = {"kind": "reference", "note": REFERENCE_NOTE, "fit": asdict(fit)}
    else:
        truth = {"kind": "none", "note": "no ground truth (option reference=none)"}
    return {
        "config": config_metadata("mtrx5700", folder, options, initial),
        "dataset": {
            "name": "mtrx5700_stage_sim",
            "description": (
                "MTRX5700 (University of Sydney) assignment data, SIMULATED in Player/Stage: "
                "noise-free velocities, GPS-like fixes (sigma 0.5 m), compass (sigma "
                "0.25 rad), laser beacon map; the raw laser scans are not available"
            ),
            "time_base": "Unix seconds as in the files (time_s + 1e-6 time_us), not offset",
            **span_and_counts(counts, vel[:, 0], fix[:, 0], compass[:, 0]),
            "files": files.found,
            "notes": notes,
        },
        "landmarks": {str(i): [float(x), float(y)] for i, (x, y) in enumerate(beacons.tolist())},
        "groundtruth": truth,
        "localizer_settings": {
            "absolute.use_compass": True,
            "absolute.use_position": True,
            "absolute.compass_sigma_rad": COMPASS_SIGMA_RAD,
            "absolute.position_sigma_m": POSITION_SIGMA_M,
        },
    }


def open_mtrx5700(options: Mtrx5700Options, path: Path) -> Dataset:
    """The MTRX5700 folder (module docstring): read the four files, fit the reference,
    build the streams and metadata."""
    folder = require_folder(path, "mtrx5700")
    notes: list[str] = []
    files = FolderFiles(folder)
    vel, fix, compass, beacons = _read(files, notes)
    truth = None
    fit = None
    if options.reference == "dead-reckoning":
        fit = fit_reference(vel, fix, compass)
        poses = dead_reckon(vel[:, 0], vel[:, 1], vel[:, 2], np.array(fit.start), fit.scale)
        truth = (vel[:, 0], poses)
    streams = tie_ordered_streams(
        (VelocityOdometry, velocity_stream(vel[:, 0], vel[:, 1], vel[:, 2])),
        (PositionFix, _fix_stream(fix)),
        truth,
    )
    streams[CompassHeading] = _compass_stream(compass)  # an observation too: after the fixes
    metadata = _metadata(options, folder, (vel, fix, compass, beacons), fit, files, notes)
    arrays = {"beacons_xy": beacons.copy()}
    return Dataset("mtrx5700_stage_sim", WalkerCalibration(), metadata, streams, arrays)


SPEC = Spec(
    "mtrx5700",
    Mtrx5700Options,
    open_mtrx5700,
    "MTRX5700 Player/Stage data (SIMULATED): velocities, GPS-like fixes, compass, beacon map",
)
