"""CARMEN laser logs, in particular GMapping-corrected ones (Intel lab, Radish/Freiburg).

`open_dataset("carmen", LOG, relations=None, time_offset=None, ...)` reads one CARMEN
text log (plain or gzip), one record per line, fields separated by whitespace:

    ODOM x y θ tv rv accel ipc_timestamp ipc_hostname logger_timestamp
    FLASER n r_1 … r_n x y θ odom_x odom_y odom_θ ipc_timestamp ipc_hostname logger_timestamp
    PARAM name value …        recorded in metadata "dataset" "params" (first value)
    anything else (NEFF, SYNC, …, '#' comments)   counted and ignored

Laser scans
-----------
FLASER → `LaserScan(t = ipc_timestamp, angle_min = −π/2, angle_increment, ranges as
float32, range_max)`: 180° centred on the heading, beam i at −90° + i·step with step
180°/n for n = 180/360 and 180°/(n − 1) for n = 181/361 (CARMEN convention; Intel:
n = 180, 1° steps). Readings at the log's largest reading (81.83 m on Intel) mean "no
return": range_max defaults to that value rounded to float32, so those readings are
>= range_max (LaserScan's "no return") while every real reading is below it; the option
`range_max` overrides it.

Corrected poses and re-anchored odometry
----------------------------------------
In a GMapping-corrected log the x y θ of each FLASER is GMapping's corrected pose, and
odometry is re-anchored at each scan: right after the FLASER (a NEFF line may come
between) an ODOM line repeats the corrected pose (a *reset*, timestamp 0 or garbage), and
the following ODOM lines continue from it with the raw odometry increments. A reset is
recognised as the first ODOM line after a FLASER whose x y θ equal the FLASER's; a log
without resets is a raw log (its ODOM poses form one chain, no ground truth).

- Corrected scan poses → `GroundTruthPose(t_scan, x, y, θ)`; metadata "groundtruth"
  {"kind": "slam-corrected"}: they are GMapping's output, not independent ground truth.
- Raw odometry: between consecutive ODOM lines of one inter-scan segment (the reset
  line counts as the segment's first pose, at the scan's time; the jump from the last
  line before a scan to the reset is GMapping's correction and is skipped) the raw
  relative motion is T_prev⁻¹·T_next. It is emitted as `VelocityOdometry` that the
  dead-reckoning localizer integrates exactly (constant v, ω per piece: an exact arc),
  see `odometry` below. In the GMapping logs the last ODOM line before a FLASER has the
  scan's timestamp, so the chain passes through every scan, and dead reckoning
  reproduces the relative motion of the ODOM lines between two scans exactly.
- Where the raw motion is unknown (a segment with no ODOM line besides the reset, as in
  most of orebro; or a scan whose last ODOM line has another timestamp) a
  VelocityOdometry(t, NaN, NaN) is emitted: the motion until the next ODOM line is not
  known (dead reckoning stands still there; a localizer's motion model gives it
  MotionNoise.unknown_sigma, and gtsam's scan matching searches a full turn; counted in
  metadata "dataset" "odometry" "gaps").

Odometry pieces (option `odometry`). One constant-(v, ω) arc only reaches points whose
direction is half its heading change; the raw increments are rarely that consistent
(the printed poses have 6 significant digits, ~0.1 mm steps; some robots integrate
odometry Euler-style, moving along the old heading; seattle's per-line motion
direction is off the arc's by 0.2 rad in the median, while over a whole segment the
motion is aligned with the heading within 0.02 rad). Two emissions:

    "smooth" (default) per run of motion (scan to scan): one arc per ODOM interval,
             starting from its natural arc (its heading change, its chord projected on
             the arc's direction dθ/2, v·Δt = chord·(dθ/2)/sin(dθ/2), v < 0 backwards),
             then the smallest weighted change of the arc lengths and heading changes
             (the heading changes keep their sum; an interval's σ = 1 mm (mrad) + 10 %
             of its own length and turn, like an odometry noise model) that ends the run
             exactly at the logged pose of its last ODOM line (Gauss-Newton to ~1e-13).
             Dead reckoning is thus exact at every scan and close to the ODOM lines in
             between (Intel: arc lengths change by at most 2.7 mm and turns by 0.009
             rad; poses at the ODOM lines within 5 mm and 0.015 rad, 0.4 mm median;
             seattle, whose lines jitter by centimetres: within 4 cm). A run that the
             adjustment cannot close with changes below 5 cm / 0.1 rad (or whose one
             interval has nothing to adjust) is closed with the two exact arcs below on
             its longest interval instead, if that turns less; metadata "dataset"
             "odometry" counts both.
    "exact"  every interval (dx, dy, dθ) reproduced exactly by two arcs of equal
             duration and equal chord c = d / (2 cos(dθ/4)), heading changes
             α₁ = 2b − dθ/2 and α₂ = dθ − α₁, b the chord direction (or its reverse,
             backwards) closest to dθ/2 (one arc when the motion is arc-consistent).
             Exact at every ODOM line, but where the robot turns in place the position
             jitter makes the arcs swing the heading back and forth ("heading_swings":
             two-arc intervals turning > 0.1 rad beyond |dθ|; Intel 2068 of 13630
             intervals, seattle 15831 of 19069), which inflates a filter's motion noise.

Timestamps (option `timestamps`)
--------------------------------
"log": the ipc timestamps, repaired to be strictly increasing, which odometry needs
(v = Δs/Δt). They are not monotonic in the GMapping logs (ODOM lines step back up to
0.9 s from logger interleaving, 3070 intervals on Intel; 4 scans step back up to 0.86 s),
while the *order* of the lines is the order of motion (the poses rotate smoothly in file
order). So the file order is kept and times are re-fitted:

1. scan times: isotonic regression (pool-adjacent-violators: least-squares
   non-decreasing fit), ties spread 1 ms apart; scans in order keep their logged time;
2. the last ODOM line before a scan with the scan's timestamp takes the scan's time;
3. the other ODOM lines of the segment between two scans: isotonic regression of their
   logged times, clipped into the open interval between the two scan times, ties spread
   evenly (at most 1 ms apart, never reaching the scans).

Metadata "dataset" "time_repair" counts the lines and scans that moved and the largest
shift. "synthetic": scan k at (k + 1)·`scan_period` s, the ODOM lines between two
scans evenly spaced between them (those after the last scan within one period). "auto"
(default) uses "log" unless more than 20 % of consecutive scans share a timestamp
(orebro and freiburg-campus log all zeros; csail and belgioioso log absolute times with
6 significant digits, 10–1000 s steps).

Proposed localizer settings
---------------------------
Metadata "localizer_settings" (`carmen_localizer_settings`), which replay and compare
apply to the localizer's config before any --set: velocity-odometry noise as a random
walk in distance ("noise.velocity_model": "distance"; the velocities only transport the
integrated odometry, and the repaired times give no rate: 38 % of Intel's pieces last
<= 10 ms), and scans scored with all their beams up to 20 m. Metadata "mapper_settings"
proposes the same 20 m to the occupancy mapper (`ScanConfig.max_range_m`): farther hits
are not mapped (they still clear free space to 20 m), so the per-particle-map filter's
60 maps stay the building's size (grown to the laser's 80 m readings, they took 24 GB
on the Seattle log; now its maps hold 3.3 GB, the process 8.6 GB at its peak).

Relations (Kümmerle et al. 2009)
--------------------------------
`relations`: a `.relations` file (`t1 t2 x y z roll pitch yaw`: the pose at t2 in the
robot frame at t1, absolute ipc times of the raw log). Stored in metadata "relations"
{"columns": ["t1", "t2", "x", "y", "yaw"], "rows": [...], "time_offset_s", ...} with
t converted to this log's time base: t_log = t_abs − time_offset. `time_offset`: given,
or (None) read from the single `*timestamps.csv` beside the relations file
(`gfs_timestamp_s,clf_ipc_timestamp_s,offset_s`, one row per FLASER of this log; the
median offset is used, 976052857.337 s ± 5 ms for Intel; its gfs times must match this
log's scan times).

initial_pose: the first corrected scan pose carried back along the raw odometry to the
first odometry message (so dead reckoning from it passes exactly through the first
corrected pose); the first corrected pose when no odometry precedes the first scan;
(0, 0, 0) for a raw log.

Dataset.arrays: "corrected_poses" (scans × 3, as logged), "scan_times" (the scans' final
times), "scan_times_logged".
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hardware.calibration import WalkerCalibration
from hardware.choices import Choice, coerce
from hardware.datasets.base import (
    Dataset,
    DatasetError,
    as_float,
    coerce_option,
    config_metadata,
    span_and_counts,
    tie_ordered_streams,
    velocity_stream,
)
from hardware.datasets.textio import iter_lines, parse_floats, read_table
from hardware.geometry import arc_end1, between1, compose1, wrap1
from hardware.messages import LaserScan, VelocityOdometry
from hardware.registry import Spec
from hardware.small_linalg import solve


class OdometryMode(Choice):
    """The odometry imported (module docstring): smoothed between scans, or exact."""

    SMOOTH = "smooth"
    EXACT = "exact"


class TimestampMode(Choice):
    """Which timestamps (module docstring): auto, the logged ones, or synthetic."""

    AUTO = "auto"
    LOG = "log"
    SYNTHETIC = "synthetic"


MAX_TIE_GAP_S = 1e-3
SYNTHETIC_THRESHOLD = 0.2  # share of consecutive scans with equal timestamps
SWING_RAD = 0.1
# smooth mode: weights and limits of the per-run adjustment of arc lengths and turns
SMOOTH_SIGMA_FLOOR = 1e-3  # m, rad
SMOOTH_SIGMA_REL = 0.1  # per m or rad of the interval's own motion
SMOOTH_MAX_DS_M = 0.05
SMOOTH_MAX_DTH_RAD = 0.1


@dataclass(frozen=True)
class CarmenOptions:
    """See the module docstring. relations: path to a .relations file or None;
    time_offset: seconds from this log's time base to the relations' (None: from the
    timestamp CSV beside the relations); odometry: "smooth" | "exact"; range_max: the "no
    return" reading (None: the log's largest reading); timestamps: "auto" | "log" |
    "synthetic"; scan_period: seconds between scans for synthetic timestamps."""

    relations: str | Path | None = None
    time_offset: float | None = None
    odometry: OdometryMode = OdometryMode.SMOOTH
    range_max: float | None = None
    timestamps: TimestampMode = TimestampMode.AUTO
    scan_period: float = 1.0

    def __post_init__(self) -> None:
        coerce(self, odometry=OdometryMode, timestamps=TimestampMode)
        coerce_option(self, "time_offset", as_float, allow_none=True)
        coerce_option(self, "range_max", as_float, allow_none=True)
        period = as_float("scan_period", self.scan_period)
        if period is None or period <= 0:
            raise ValueError(f"scan_period must be > 0, got {self.scan_period!r}")
        object.__setattr__(self, "scan_period", period)
        if self.range_max is not None and self.range_max <= 0:
            raise ValueError(f"range_max must be > 0, got {self.range_max!r}")


# ---------------------------------------------------------------------------------------
# parsing


@dataclass
class _Node:
    """One ODOM line in the chain: a pose in the odometry frame `frame` at logged time."""

    pose: tuple[float, float, float]
    t_logged: float
    frame: int
    line: int
    t: float = math.nan  # repaired time


@dataclass
class _Scan:
    t_logged: float
    ranges: list[float]
    pose: tuple[float, float, float]
    line: int
    anchor: int | None = None  # index of the ODOM node at the scan's time (segment end)
    reset_frame: int | None = None  # frame started by the reset line after this scan
    reset_pose: tuple[float, float, float] | None = None
    t: float = math.nan


@dataclass
class _Log:
    nodes: list[_Node] = field(default_factory=list)
    scans: list[_Scan] = field(default_factory=list)
    scan_nodes: list[list[int]] = field(default_factory=list)  # nodes after scan k-1, before k
    params: dict[str, str] = field(default_factory=dict)
    ignored: dict[str, int] = field(default_factory=dict)
    odom_lines: int = 0
    resets: int = 0


def _odom_pose(path: Path, lineno: int, tok: list[str]) -> tuple[tuple[float, float, float], float]:
    """(x y θ, ipc timestamp) of an ODOM line's fields `tok`."""
    if len(tok) < 10:
        raise DatasetError(
            f"{path}: line {lineno}: ODOM needs 9 fields after the tag, got {len(tok) - 1}"
        )
    x, y, th, _tv, _rv, _acc, t = parse_floats(path, lineno, tok[1:8])
    return (x, y, th), t


def _flaser_scan(path: Path, lineno: int, tok: list[str], beams: int | None) -> _Scan:
    """The scan of a FLASER line's fields `tok`; `beams` is the earlier scans' beam count
    (None for the first scan), which every scan must have."""
    if len(tok) < 2:
        raise DatasetError(f"{path}: line {lineno}: FLASER without a beam count")
    try:
        n = int(tok[1])
    except ValueError:
        raise DatasetError(
            f"{path}: line {lineno}: FLASER beam count is not an integer: {tok[1]!r}"
        ) from None
    if n < 2:
        raise DatasetError(f"{path}: line {lineno}: FLASER with {n} beams")
    if len(tok) < n + 11:
        raise DatasetError(
            f"{path}: line {lineno}: FLASER with {n} beams needs {n + 10} fields "
            f"after the tag, got {len(tok) - 1}"
        )
    if beams is not None and beams != n:
        raise DatasetError(
            f"{path}: line {lineno}: FLASER with {n} beams, earlier scans have {beams}"
        )
    vals = parse_floats(path, lineno, [*tok[2 : 2 + n + 6], tok[8 + n]])
    return _Scan(vals[-1], vals[:n], (vals[n], vals[n + 1], vals[n + 2]), lineno)


def _parse(path: Path) -> _Log:
    """The log's ODOM chain, scans and their reset lines, in file order (module
    docstring); PARAM lines recorded, other records counted."""
    log = _Log()
    frame = 0
    pending_scan: _Scan | None = None  # scan whose reset line may come next
    segment: list[int] = []  # node indices since the last scan
    for lineno, line in iter_lines(path):
        tok = line.split()
        if not tok or tok[0].startswith("#"):
            continue
        kind = tok[0]
        if kind == "ODOM":
            pose, t = _odom_pose(path, lineno, tok)
            log.odom_lines += 1
            if pending_scan is not None and pose == pending_scan.pose:
                # reset: odometry re-anchored at the corrected scan pose
                frame += 1
                pending_scan.reset_frame = frame
                pending_scan.reset_pose = pose
                log.resets += 1
            else:
                log.nodes.append(_Node(pose, t, frame, lineno))
                segment.append(len(log.nodes) - 1)
            pending_scan = None
        elif kind == "FLASER":
            scan = _flaser_scan(path, lineno, tok, len(log.scans[0].ranges) if log.scans else None)
            if segment and log.nodes[segment[-1]].t_logged == scan.t_logged:
                scan.anchor = segment[-1]
            log.scans.append(scan)
            log.scan_nodes.append(segment)
            segment = []
            pending_scan = scan
        elif kind == "PARAM" and len(tok) >= 3:
            log.params.setdefault(tok[1], tok[2])
        else:
            log.ignored[kind] = log.ignored.get(kind, 0) + 1
    log.scan_nodes.append(segment)  # nodes after the last scan
    return log


# ---------------------------------------------------------------------------------------
# time repair


def isotonic(y: np.ndarray) -> np.ndarray:
    """Least-squares non-decreasing fit of y (pool adjacent violators)."""
    vals: list[float] = []
    wts: list[int] = []
    for v in y.tolist():
        vals.append(v)
        wts.append(1)
        while len(vals) > 1 and vals[-2] > vals[-1]:
            w = wts[-2] + wts[-1]
            vals[-2] = (vals[-2] * wts[-2] + vals[-1] * wts[-1]) / w
            wts[-2] = w
            vals.pop()
            wts.pop()
    return np.repeat(np.array(vals), wts)


def spread_ties(f: np.ndarray, lo: float, hi: float, gap: float) -> np.ndarray:
    """Strictly increasing times close to non-decreasing f, inside the open (lo, hi).

    Consecutive times are at least `g` = min(gap, (hi − lo)/(n + 1)) apart (gap when a
    bound is infinite); f must lie in [lo, hi].
    """
    n = len(f)
    if n == 0:
        return f.copy()
    g = gap
    if math.isfinite(lo) and math.isfinite(hi):
        g = min(gap, (hi - lo) / (n + 1))
    out = f.astype(np.float64).copy()
    prev = lo
    for i in range(n):
        if math.isfinite(prev):
            out[i] = max(out[i], prev + g)
        prev = out[i]
    nxt = hi
    for i in range(n - 1, -1, -1):
        if math.isfinite(nxt):
            out[i] = min(out[i], nxt - g)
        nxt = out[i]
    return out


def _repair_times(log: _Log, mode: str, period: float) -> dict[str, Any]:
    scans, nodes = log.scans, log.nodes
    logged_scan = np.array([s.t_logged for s in scans], dtype=np.float64)
    if mode == "synthetic":
        scan_t = (np.arange(len(scans)) + 1.0) * period
    else:
        scan_t = spread_ties(isotonic(logged_scan), -math.inf, math.inf, MAX_TIE_GAP_S)
    for s, t in zip(scans, scan_t.tolist(), strict=True):
        s.t = t
    bounds = [-math.inf, *scan_t.tolist(), math.inf]
    for k, segment in enumerate(log.scan_nodes):
        lo, hi = bounds[k], bounds[k + 1]
        anchor = scans[k].anchor if k < len(scans) else None
        free = [i for i in segment if i != anchor]
        if anchor is not None:
            nodes[anchor].t = hi
        if not free:
            continue
        if mode == "synthetic":
            a = lo if math.isfinite(lo) else 0.0
            b = hi if math.isfinite(hi) else a + period
            n = len(free)
            fitted = a + (b - a) * (np.arange(1, n + 1) / (n + 1))
        else:
            logged = np.array([nodes[i].t_logged for i in free], dtype=np.float64)
            fitted = np.clip(isotonic(logged), lo, hi)
            lo_eff = lo if math.isfinite(lo) else float(fitted[0]) - MAX_TIE_GAP_S
            fitted = spread_ties(fitted, lo_eff, hi, MAX_TIE_GAP_S)
        for i, t in zip(free, fitted.tolist(), strict=True):
            nodes[i].t = t
    node_t = np.array([n.t for n in nodes], dtype=np.float64)
    if mode == "synthetic":
        return {"mode": "synthetic", "scan_period_s": period}
    node_shift = np.abs(node_t - np.array([n.t_logged for n in nodes], dtype=np.float64))
    scan_shift = np.abs(scan_t - logged_scan)
    return {
        "mode": "log",
        "odom_lines_retimed": int(np.count_nonzero(node_shift > 0)),
        "odom_lines_retimed_over_1ms": int(np.count_nonzero(node_shift > 1e-3)),
        "max_odom_shift_s": float(node_shift.max()) if len(nodes) else 0.0,
        "scans_retimed": int(np.count_nonzero(scan_shift > 0)),
        "max_scan_shift_s": float(scan_shift.max()) if len(scans) else 0.0,
        "logged_backsteps": int(
            np.count_nonzero(np.diff([n.t_logged for n in nodes]) < 0)
            + np.count_nonzero(np.diff(logged_scan) < 0)
        ),
    }


# ---------------------------------------------------------------------------------------
# odometry


def _arc_length(chord: float, dtheta: float) -> float:
    """Length of the arc with signed chord `chord` turning by dtheta."""
    half = 0.5 * dtheta
    if abs(half) < 1e-9:
        return chord * (1.0 + half * half / 6.0)
    return chord * half / math.sin(half)


def exact_pieces(dx: float, dy: float, dth: float) -> list[tuple[float, float]]:
    """(arc length, heading change) of one or two equal-duration arcs reaching exactly
    (dx, dy, dth) from the origin (see the module docstring)."""
    d = math.hypot(dx, dy)
    if d == 0.0:
        return [(0.0, dth)]
    phi = math.atan2(dy, dx)
    half = 0.5 * dth
    # chord direction b: phi or its reverse, whichever is closer to dth/2
    b, sign = phi, 1.0
    if abs(wrap1(phi - half)) > 0.5 * math.pi:
        b, sign = wrap1(phi - math.pi), -1.0
    b = half + wrap1(b - half)  # b - dth/2 in (-pi/2, pi/2]
    a1 = 2.0 * b - 0.5 * dth
    a2 = dth - a1
    chord = sign * d / (2.0 * math.cos(0.25 * dth))
    if abs(a1 - a2) <= 1e-12 * max(1.0, abs(dth)):
        return [(2.0 * _arc_length(chord, 0.5 * dth), dth)]
    return [(_arc_length(chord, a1), a1), (_arc_length(chord, a2), a2)]


def arc_piece(dx: float, dy: float, dth: float) -> tuple[float, float]:
    """(arc length, dth) of the arc with heading change dth whose chord is the projection
    of (dx, dy) on the arc's chord direction dth/2."""
    chord = dx * math.cos(0.5 * dth) + dy * math.sin(0.5 * dth)
    return (_arc_length(chord, dth), dth)


@dataclass
class _TimePoint:
    t: float
    pose_in: tuple[float, float, float] | None  # pose reached here (frame frame_in)
    frame_in: int | None
    pose_out: tuple[float, float, float] | None  # pose motion continues from (frame_out)
    frame_out: int | None


def _time_points(log: _Log) -> list[_TimePoint]:
    pts: list[_TimePoint] = []
    nodes = log.nodes
    for k, segment in enumerate(log.scan_nodes):
        for i in segment:
            n = nodes[i]
            pts.append(_TimePoint(n.t, n.pose, n.frame, n.pose, n.frame))
        if k < len(log.scans):
            s = log.scans[k]
            if s.reset_frame is None:
                continue  # raw log: the chain continues through the scan
            if s.anchor is not None and pts and pts[-1].t == s.t:
                pts[-1].pose_out, pts[-1].frame_out = s.reset_pose, s.reset_frame
            else:
                pts.append(_TimePoint(s.t, None, None, s.reset_pose, s.reset_frame))
    return pts


def _runs(pts: list[_TimePoint]) -> list[list[int]]:
    """Maximal chains of time points joined by known raw motion (a scan junction ends one
    run and starts the next)."""
    runs: list[list[int]] = []
    cur = [0] if pts else []
    for i in range(len(pts) - 1):
        a, b = pts[i], pts[i + 1]
        if a.pose_out is None or a.frame_out != b.frame_in or b.pose_in is None:
            runs.append(cur)
            cur = [i + 1]
            continue
        cur.append(i + 1)
        if b.frame_out != b.frame_in:
            runs.append(cur)
            cur = [i + 1]
    if cur:
        runs.append(cur)
    return runs


def _dsinc_half(dtheta: np.ndarray) -> np.ndarray:
    """d/dθ of sin(θ/2)/(θ/2), elementwise."""
    x = 0.5 * np.asarray(dtheta, dtype=np.float64)
    small = np.abs(x) < 1e-4
    xs = np.where(small, 1.0, x)
    return np.where(small, -x / 6.0, 0.5 * (xs * np.cos(xs) - np.sin(xs)) / (xs * xs))


def _run_end(s: np.ndarray, th: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """End position of arcs (s_i, θ_i) from the origin and the Jacobian blocks
    ∂end/∂s (2×m), ∂end/∂θ (2×m)."""
    phi = np.concatenate([[0.0], np.cumsum(th)[:-1]])
    k = np.sinc(th / (2.0 * np.pi))  # sin(θ/2)/(θ/2)
    dk = _dsinc_half(th)
    mid = phi + 0.5 * th
    u = np.vstack([np.cos(mid), np.sin(mid)])  # 2×m
    perp = np.vstack([-u[1], u[0]])
    chords = s * k * u  # 2×m
    end = chords.sum(axis=1)
    d_s = k * u
    # own chord: d/dθ_j [s_j k(θ_j) u(φ_j + θ_j/2)]; later chords rotate with φ
    own = s * (dk * u + 0.5 * k * perp)
    later = np.cumsum(chords[:, ::-1], axis=1)[:, ::-1]  # Σ_{i>=j}
    later = np.hstack([later[:, 1:], np.zeros((2, 1))])  # Σ_{i>j}
    return end, d_s, own + np.vstack([-later[1], later[0]])


def _smooth_run(rel: list[tuple[float, float, float]]) -> tuple[list, float, float] | None:
    """Arcs (length, heading change) for a run of relative motions `rel`: each interval's
    natural arc (its heading change, its chord projected on the arc's direction), then
    the smallest weighted change of lengths and heading changes (summing to the run's
    total) that ends the run exactly at its logged end pose (Gauss-Newton); an
    interval's weight σ = 1 mm (mrad) + 10 % of its own length and turn. Returns (arcs,
    largest length change, largest heading change), or None if it does not converge."""
    m = len(rel)
    if m < 2:
        return None
    th0 = np.array([r[2] for r in rel])
    s0 = np.array([arc_piece(*r)[0] for r in rel])
    target = (0.0, 0.0, 0.0)
    for r in rel:
        target = compose1(target, r)
    goal = np.array([target[0], target[1], float(th0.sum())])
    # like an odometry noise model: intervals that moved more may change more
    sig_s = SMOOTH_SIGMA_FLOOR + SMOOTH_SIGMA_REL * np.abs(s0)
    sig_th = SMOOTH_SIGMA_FLOOR + SMOOTH_SIGMA_REL * (np.abs(th0) + np.abs(s0))
    w = np.concatenate([sig_s**2, sig_th**2])
    s, th = s0.copy(), th0.copy()
    for _ in range(8):
        end, d_s, d_th = _run_end(s, th)
        r = goal - np.array([end[0], end[1], th.sum()])
        if np.max(np.abs(r)) < 1e-13:
            break
        jac = np.vstack([np.hstack([d_s, d_th]), np.r_[np.zeros(m), np.ones(m)]])  # 3×2m
        jw = jac * w
        try:
            step = np.einsum("ij,i->j", jw, solve(np.einsum("ik,jk->ij", jw, jac), r))
        except np.linalg.LinAlgError:
            return None
        s, th = s + step[:m], th + step[m:]
    else:
        return None
    ds_max = float(np.max(np.abs(s - s0)))
    dth_max = float(np.max(np.abs(th - th0)))
    return list(zip(s.tolist(), th.tolist(), strict=True)), ds_max, dth_max


def _swing(pieces: list[list[tuple[float, float]]], rel: list[tuple[float, float, float]]) -> float:
    """How far the two-arc intervals turn beyond their net heading change."""
    out = 0.0
    for p, r in zip(pieces, rel, strict=True):
        if len(p) == 2:
            out = max(out, max(abs(p[0][1]), abs(p[1][1])) - abs(r[2]))
    return out


def _close_on_longest(rel: list[tuple[float, float, float]]) -> list[list[tuple[float, float]]]:
    """Pieces per interval: one natural arc each, except the longest interval, whose
    motion is solved so that the run ends exactly (two arcs)."""
    natural = [arc_piece(*m) for m in rel]
    k = max(range(len(rel)), key=lambda i: math.hypot(rel[i][0], rel[i][1]))
    before = after = (0.0, 0.0, 0.0)
    target = (0.0, 0.0, 0.0)
    for i, m in enumerate(rel):
        target = compose1(target, m)
        if i < k:
            before = compose1(before, arc_end1(*natural[i]))
        elif i > k:
            after = compose1(after, arc_end1(*natural[i]))
    # before * M * after = target  ->  M = before^-1 * target * after^-1
    inv_after = between1(after, (0.0, 0.0, 0.0))
    mx, my, mth = compose1(between1(before, target), inv_after)
    pieces: list[list[tuple[float, float]]] = [[p] for p in natural]
    pieces[k] = exact_pieces(mx, my, wrap1(mth))
    return pieces


@dataclass
class _OdometryStats:
    """What `_odometry` did (metadata "dataset" "odometry")."""

    mode: str
    time_points: int = 0
    intervals: int = 0
    messages: int = 0
    gaps: int = 0
    heading_swings: int = 0
    runs: int = 0
    runs_adjusted: int = 0
    runs_closed_by_two_arcs: int = 0
    max_length_change_m: float = 0.0
    max_heading_change_rad: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        """The statistics; those of the runs only in smooth mode."""
        smooth_only = (
            "runs",
            "runs_adjusted",
            "runs_closed_by_two_arcs",
            "max_length_change_m",
            "max_heading_change_rad",
        )
        return {
            k: v for k, v in asdict(self).items() if self.mode == "smooth" or k not in smooth_only
        }


def _smooth_pieces(
    rel: list[tuple[float, float, float]], stats: _OdometryStats
) -> list[list[tuple[float, float]]]:
    """Pieces per interval of one run in smooth mode (module docstring): the adjusted
    arcs, or two arcs on the longest interval where the adjustment fails, or is large
    and swings the heading more than the two arcs would."""
    if not rel:
        return []
    solved = _smooth_run(rel)
    closing = None
    if solved is not None and (solved[1] > SMOOTH_MAX_DS_M or solved[2] > SMOOTH_MAX_DTH_RAD):
        closing = _close_on_longest(rel)
        if solved[2] > _swing(closing, rel):
            solved = None
    if solved is None:
        stats.runs_closed_by_two_arcs += 1
        return closing if closing is not None else _close_on_longest(rel)
    stats.runs_adjusted += 1
    stats.max_length_change_m = max(stats.max_length_change_m, solved[1])
    stats.max_heading_change_rad = max(stats.max_heading_change_rad, solved[2])
    return [[arc] for arc in solved[0]]


def _emit(
    rows: list[tuple[float, float, float]],
    t0: float,
    t1: float,
    pieces: list[tuple[float, float]],
    dth: float,
    stats: _OdometryStats,
) -> None:
    """Rows (t, v, ω) of an interval from t0 to t1 moved as `pieces` (arc length, heading
    change) of equal duration; two pieces turning beyond the net `dth` count as a swing."""
    if len(pieces) == 2 and max(abs(p[1]) for p in pieces) > abs(dth) + SWING_RAD:
        stats.heading_swings += 1
    times = [t0 + j * (t1 - t0) / len(pieces) for j in range(len(pieces))] + [t1]
    for j, (ds, da) in enumerate(pieces):
        # the interval exactly as a localizer computes it (next.t - this.t)
        dt = times[j + 1] - times[j]
        rows.append((times[j], ds / dt, da / dt))


def _odometry(log: _Log, mode: str) -> tuple[np.ndarray, dict[str, Any]]:
    """VelocityOdometry rows (t, v, ω) and statistics (see the module docstring): each
    run's intervals as pieces, then a standstill where the run ends (a gap or the end)."""
    pts = _time_points(log)
    runs = _runs(pts)
    rows: list[tuple[float, float, float]] = []
    stats = _OdometryStats(mode, time_points=len(pts), runs=len(runs))
    for r, run in enumerate(runs):
        pairs = list(itertools.pairwise(run))
        rel = [between1(pts[i].pose_out, pts[j].pose_in) for i, j in pairs]
        stats.intervals += len(rel)
        if mode == "exact":
            pieces = [exact_pieces(*m) for m in rel]
        else:
            pieces = _smooth_pieces(rel, stats)
        for (i, j), p, m in zip(pairs, pieces, rel, strict=True):
            _emit(rows, pts[i].t, pts[j].t, p, m[2], stats)
        joined = r + 1 < len(runs) and runs[r + 1][0] == run[-1]
        if r + 1 < len(runs) and not joined:  # a gap: the raw motion is not known
            rows.append((pts[run[-1]].t, math.nan, math.nan))
            stats.gaps += 1
        elif not joined:  # the end of the log
            rows.append((pts[run[-1]].t, 0.0, 0.0))
    stats.messages = len(rows)
    return np.array(rows, dtype=np.float64).reshape(-1, 3), stats.to_dict()


# ---------------------------------------------------------------------------------------
# relations


def _time_offset(relations: Path, scan_logged: np.ndarray) -> tuple[float, str]:
    csvs = sorted(relations.parent.glob("*timestamps.csv"))
    if len(csvs) != 1:
        found = "none" if not csvs else ", ".join(p.name for p in csvs)
        raise DatasetError(
            f"{relations}: give time_offset, or put one *timestamps.csv beside the "
            f"relations file (found {found})"
        )
    table = read_table(csvs[0], 3, delimiter=",")
    gfs = table.data[:, 0]
    if len(gfs) != len(scan_logged) or not np.allclose(gfs, scan_logged, atol=1e-6, rtol=0):
        raise DatasetError(
            f"{csvs[0]}: its {len(gfs)} gfs timestamps do not match this log's "
            f"{len(scan_logged)} scans"
        )
    return float(np.median(table.data[:, 2])), str(csvs[0])


def _relations(path: Path, offset: float) -> list[list[float]]:
    table = read_table(path, 8)
    d = table.data
    rows = np.column_stack([d[:, 0] - offset, d[:, 1] - offset, d[:, 2], d[:, 3], d[:, 7]])
    return [[round(r[0], 6), round(r[1], 6), r[2], r[3], r[4]] for r in rows.tolist()]


# ---------------------------------------------------------------------------------------


def beam_step(n: int) -> float:
    """CARMEN's angular step for n beams over 180°."""
    return math.pi / (n - 1 if n % 2 else n)


def _scan_stream(times: np.ndarray, ranges: np.ndarray, step: float, range_max: float):
    def gen() -> Iterator[LaserScan]:
        for t, r in zip(times.tolist(), ranges, strict=True):
            yield LaserScan(t, -0.5 * math.pi, step, r, range_max)

    return gen


def _initial_pose(log: _Log, odo: np.ndarray) -> tuple[float, float, float]:
    """First corrected pose carried back along the emitted odometry to its first message."""
    if not log.scans:
        return (0.0, 0.0, 0.0)
    first = log.scans[0]
    gt0 = (first.pose[0], first.pose[1], first.pose[2])
    if first.reset_frame is None:
        return (0.0, 0.0, 0.0)
    if len(odo) == 0 or odo[0, 0] >= first.t:
        return (gt0[0], gt0[1], wrap1(gt0[2]))
    # integrate the emitted messages up to the first scan, from the origin
    p = (0.0, 0.0, 0.0)
    for (t0, v, w), t1 in zip(odo.tolist(), odo[1:, 0].tolist(), strict=False):
        if t0 >= first.t:
            break
        dt = min(t1, first.t) - t0
        if dt > 0:
            p = compose1(p, arc_end1(v * dt, w * dt))
    inv = between1(p, (0.0, 0.0, 0.0))  # p⁻¹
    x, y, th = compose1(gt0, inv)
    return (x, y, wrap1(th))


# A SICK LMS reads reliably to about 20 m (Intel's readings reach 25 m, sparse and noisy
# beyond 20); beyond that a point says little about the pose.
USABLE_RANGE_M = 20.0


def carmen_localizer_settings(n_beams: int) -> dict[str, Any]:
    """The settings a CARMEN log proposes to localizers (metadata "localizer_settings",
    applied by replay and compare before --set): its odometry is the robot's integrated
    wheel odometry, carried as velocities over repaired timestamps that cannot give a
    rate, so its errors grow with distance and turn, not time
    (slam.motion.MotionNoise.velocity_model "distance"); scans are scored with all their
    beams up to the laser's usable range. (A laser log has scans and no landmark IDs:
    replay and compare propose the localizers' scan-based modes for any such source,
    experiments.run.source_metadata.)"""
    return {
        "noise.velocity_model": "distance",
        "max_range_m": USABLE_RANGE_M,
        "max_beams": int(n_beams),
        "scan.max_range_m": USABLE_RANGE_M,
    }


def _read_log(path: Path) -> _Log:
    """The parsed log; a DatasetError for a folder or a log without laser scans."""
    if path.is_dir():
        raise DatasetError(f"{path}: is a folder; carmen takes one log file")
    log = _parse(path)
    if not log.scans:
        raise DatasetError(f"{path}: no FLASER lines (not a CARMEN laser log?)")
    return log


def _retime(
    log: _Log, options: CarmenOptions, logged_scan: np.ndarray, path: Path
) -> tuple[str, dict[str, Any]]:
    """Give every scan and ODOM line its final time (option `timestamps`, module
    docstring): the mode used and metadata "time_repair"; a DatasetError for negative
    times."""
    mode = options.timestamps
    equal_share = float(np.mean(np.diff(logged_scan) == 0)) if len(logged_scan) > 1 else 0.0
    if mode == "auto":
        mode = "synthetic" if equal_share > SYNTHETIC_THRESHOLD else "log"
    time_repair = _repair_times(log, mode, options.scan_period)
    if mode == "synthetic":
        time_repair["reason"] = (
            f"{equal_share:.0%} of consecutive scans share a logged timestamp"
            if options.timestamps == "auto"
            else "requested"
        )
    scan_t = np.array([s.t for s in log.scans], dtype=np.float64)
    node_t = np.array([n.t for n in log.nodes], dtype=np.float64)
    t_min = min(scan_t.min(), node_t.min() if len(node_t) else math.inf)
    if t_min < 0:
        raise DatasetError(f"{path}: negative timestamps ({t_min:g} s); use timestamps='synthetic'")
    return mode, time_repair


def _scan_ranges(log: _Log, range_max: float | None) -> tuple[np.ndarray, float, float]:
    """The scans' ranges (scans × beams, float32, read-only), the largest reading, and
    range_max: the option, else the largest reading, as float32 (module docstring)."""
    ranges = np.array([s.ranges for s in log.scans], dtype=np.float32)
    ranges.setflags(write=False)
    largest = float(np.max(ranges))
    limit = range_max if range_max is not None else largest
    return ranges, largest, float(np.float32(limit))


def _relations_metadata(
    rel_path: Path, time_offset: float | None, logged_scan: np.ndarray
) -> dict[str, Any]:
    """Metadata "relations": a relations file in this log's time base (time_offset given,
    or from the timestamp CSV beside it)."""
    if time_offset is not None:
        offset, source = time_offset, "option time_offset"
    else:
        offset, source = _time_offset(rel_path, logged_scan)
    return {
        "columns": ["t1", "t2", "x", "y", "yaw"],
        "rows": _relations(rel_path, offset),
        "file": str(rel_path.resolve()),
        "time_offset_s": offset,
        "time_offset_source": source,
        "note": (
            "pose of the robot at t2 in its frame at t1 (Kuemmerle et al. 2009); "
            "t = t_abs - time_offset_s, in this log's time base"
        ),
    }


def _groundtruth_metadata(corrected: bool) -> dict[str, Any]:
    """Metadata "groundtruth": the corrected scan poses, or none in a raw log."""
    if not corrected:
        return {"kind": "none", "note": "raw log: no reset lines"}
    return {
        "kind": "slam-corrected",
        "source": "the x y theta of each FLASER line",
        "note": (
            "GMapping's corrected scan poses: the output of a SLAM system, a good "
            "reference for mapping but not independent ground truth"
        ),
    }


def _dataset_metadata(
    name: str,
    log: _Log,
    mode: str,
    time_repair: dict[str, Any],
    odo: np.ndarray,
    odo_stats: dict[str, Any],
    scan_t: np.ndarray,
    largest: float,
    range_max: float,
) -> dict[str, Any]:
    """Metadata "dataset": time base and span, counts, the laser, the log's records, the
    time repair and the odometry's statistics."""
    corrected = log.resets > 0
    n_beams = len(log.scans[0].ranges)
    counts = {
        "VelocityOdometry": len(odo),
        "GroundTruthPose": len(scan_t) if corrected else 0,
        "LaserScan": len(scan_t),
    }
    return {
        "name": name,
        "description": "CARMEN laser log" + (" (GMapping-corrected)" if corrected else ""),
        "time_base": (
            "seconds as logged (ipc timestamps), repaired to be strictly increasing"
            if mode == "log"
            else "synthetic: scan k at (k + 1) * scan_period"
        ),
        **span_and_counts(counts, scan_t, odo[:, 0]),
        "scans": len(scan_t),
        "beams": n_beams,
        "angle_increment_rad": beam_step(n_beams),
        "range_max": range_max,
        "largest_reading": largest,
        "odom_lines": log.odom_lines,
        "reset_lines": log.resets,
        "corrected": corrected,
        "time_repair": time_repair,
        "odometry": odo_stats,
        "params": dict(log.params),
        "ignored_records": dict(log.ignored),
    }


def open_carmen(options: CarmenOptions, path: Path) -> Dataset:
    """A CARMEN log (module docstring): parse and check it, repair its times, emit its
    odometry, build the streams and the metadata."""
    path = Path(path)
    log = _read_log(path)
    logged_scan = np.array([s.t_logged for s in log.scans], dtype=np.float64)
    mode, time_repair = _retime(log, options, logged_scan, path)
    scan_t = np.array([s.t for s in log.scans], dtype=np.float64)
    corrected = log.resets > 0
    odo, odo_stats = _odometry(log, options.odometry)
    odo_stats["scans_without_odometry"] = sum(1 for s in log.scans if s.anchor is None)
    ranges, largest, range_max = _scan_ranges(log, options.range_max)
    poses = np.array([s.pose for s in log.scans], dtype=np.float64)
    n_beams = ranges.shape[1]
    streams = tie_ordered_streams(
        (VelocityOdometry, velocity_stream(odo[:, 0], odo[:, 1], odo[:, 2])),
        (LaserScan, _scan_stream(scan_t, ranges, beam_step(n_beams), range_max)),
        (scan_t, poses) if corrected else None,
    )
    initial = _initial_pose(log, odo) if corrected else (0.0, 0.0, 0.0)
    name = path.name.removesuffix(".gz").removesuffix(".log")
    metadata: dict[str, dict[str, Any]] = {
        "config": config_metadata("carmen", path, options, initial),
        "dataset": _dataset_metadata(
            name, log, mode, time_repair, odo, odo_stats, scan_t, largest, range_max
        ),
        "groundtruth": _groundtruth_metadata(corrected),
        "localizer_settings": carmen_localizer_settings(n_beams),
        # hits beyond the usable range are not mapped either (they still clear free
        # space up to it): the maps stay the building's size, not the laser's 80 m
        "mapper_settings": {"scan.max_range_m": USABLE_RANGE_M},
    }
    if options.relations is not None:
        metadata["relations"] = _relations_metadata(
            Path(options.relations), options.time_offset, logged_scan
        )
    arrays = {
        "corrected_poses": poses,
        "scan_times": scan_t,
        "scan_times_logged": logged_scan,
    }
    return Dataset(name, WalkerCalibration(), metadata, streams, arrays)


SPEC = Spec(
    "carmen",
    CarmenOptions,
    open_carmen,
    "CARMEN laser log (GMapping-corrected): laser scans, raw odometry, corrected poses",
)
