"""Line segments and corners from a 2-D laser scan (split-and-merge), as range-bearing
landmarks without IDs — the features the PICO maze robot's EKF-SLAM ran on.

A scan's returns (below `max_range_m`) become points in the sensor frame, in beam order.
They are cut into runs where two neighbouring returns lie farther apart than
`break_m + break_frac·r` or a beam has no return. Each run is split recursively at the
point farthest from the chord between its ends while that distance exceeds
`split_m + split_frac·r` (iterative end-point fit, Douglas–Peucker); neighbouring pieces
of one run whose total-least-squares lines are nearly collinear (angle below
`merge_angle_rad` and each piece's ends within the split threshold of the other's line)
are merged back. A piece is a line when it has at least `min_points` returns and is
`min_length_m` long; its line is the total-least-squares fit of its points and its ends
are the first and last points projected onto it.

A **corner** is where two lines meet: consecutive lines of one run, or the last line of a
run and the first of the next when their facing ends are within `corner_gap_m`, whose
directions differ by `corner_angle_rad` (min, max), and whose intersection lies within
`corner_gap_m` of both facing ends. Corners of the walls and the convex corners of boxes
are both found; a corner whose far side is hidden (an occlusion edge) is not one, since
no second line meets it there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hardware.geometry import transform_points
from hardware.messages import LaserScan, RangeBearings
from mapping.scan_points import scan_hits


@dataclass(frozen=True)
class FeatureConfig:
    """See the module docstring."""

    max_range_m: float = 20.0
    break_m: float = 0.2
    break_frac: float = 0.05
    split_m: float = 0.03
    split_frac: float = 0.005
    merge_angle_rad: float = math.radians(5.0)
    min_points: int = 5
    min_length_m: float = 0.3
    corner_angle_rad: tuple[float, float] = (math.radians(45.0), math.radians(135.0))
    corner_gap_m: float = 0.3

    def __post_init__(self) -> None:
        if self.min_points < 2 or self.max_range_m <= 0 or self.split_m <= 0:
            raise ValueError("min_points must be >= 2, max_range_m and split_m > 0")
        lo, hi = self.corner_angle_rad
        if not 0.0 < lo <= hi < math.pi:
            raise ValueError(f"corner_angle_rad must be 0 < min <= max < π, got {lo}, {hi}")


@dataclass(frozen=True)
class Line:
    """A fitted segment: its ends (sensor frame), unit direction and point count."""

    start: np.ndarray
    end: np.ndarray
    direction: np.ndarray
    points: int

    @property
    def length(self) -> float:
        return float(np.hypot(*(self.end - self.start)))


@dataclass(frozen=True)
class ScanFeatures:
    """The lines (in beam order) and corners (k, 2: sensor-frame points) of one scan."""

    lines: list[Line]
    corners: np.ndarray

    def corner_range_bearings(self) -> np.ndarray:
        """The corners as (range, bearing) rows in the sensor frame."""
        c = self.corners.reshape(-1, 2)
        return np.column_stack([np.hypot(c[:, 0], c[:, 1]), np.arctan2(c[:, 1], c[:, 0])])


def _fit(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Total least squares line: (centroid, unit direction)."""
    mean = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - mean, full_matrices=False)
    return mean, vt[0]


def _line(points: np.ndarray) -> Line:
    mean, d = _fit(points)
    if d @ (points[-1] - points[0]) < 0:
        d = -d
    a = mean + d * float(d @ (points[0] - mean))
    b = mean + d * float(d @ (points[-1] - mean))
    return Line(a, b, d, len(points))


def _threshold(config: FeatureConfig, p: np.ndarray) -> float:
    return config.split_m + config.split_frac * float(np.hypot(*p))


def _split(points: np.ndarray, config: FeatureConfig) -> list[np.ndarray]:
    """Iterative end-point fit: the run cut at its farthest points from the chords."""
    if len(points) < 3:
        return [points]
    a, b = points[0], points[-1]
    chord = b - a
    n = float(np.hypot(*chord))
    if n < 1e-9:
        dist = np.hypot(*(points - a).T)
    else:
        dist = np.abs(chord[0] * (points[:, 1] - a[1]) - chord[1] * (points[:, 0] - a[0])) / n
    k = int(np.argmax(dist))
    if dist[k] <= _threshold(config, points[k]) or k in (0, len(points) - 1):
        return [points]
    return _split(points[: k + 1], config) + _split(points[k:], config)


def _collinear(p: np.ndarray, q: np.ndarray, config: FeatureConfig) -> bool:
    if len(p) < 2 or len(q) < 2:
        return False
    dp = _fit(p)[1]
    dq = _fit(q)[1]
    if math.acos(min(1.0, abs(float(dp @ dq)))) > config.merge_angle_rad:
        return False
    both = np.concatenate([p, q])
    m, d = _fit(both)
    normal = np.array([-d[1], d[0]])
    off = np.abs((both - m) @ normal)
    return bool(np.all(off <= [_threshold(config, x) for x in both]))


def _runs(scan: LaserScan, config: FeatureConfig) -> list[np.ndarray]:
    """The returns in beam order, cut where neighbours are far apart or a beam is empty."""
    ok = scan_hits(scan, config.max_range_m)
    r = np.where(ok, np.asarray(scan.ranges, dtype=float), 0.0)  # (no inf · 0 below)
    a = scan.angles
    pts = np.column_stack([r * np.cos(a), r * np.sin(a)])
    gap = np.hypot(*np.diff(pts, axis=0).T) > config.break_m + config.break_frac * r[1:]
    # a run starts at a return whose previous beam is empty or too far from it
    start = ok & np.concatenate([[True], ~ok[:-1] | gap])
    ids = np.cumsum(start)
    return [pts[ok & (ids == k)] for k in range(1, int(ids[-1]) + 1)] if len(r) else []


def _corner(u: Line, v: Line, config: FeatureConfig) -> np.ndarray | None:
    """Where line u's end meets line v's start, if they form a corner."""
    lo, hi = config.corner_angle_rad
    angle = math.acos(max(-1.0, min(1.0, float(u.direction @ v.direction))))
    if not lo <= angle <= hi:
        return None
    m = np.column_stack([u.direction, -v.direction])
    if abs(np.linalg.det(m)) < 1e-9:
        return None
    s, _ = np.linalg.solve(m, v.start - u.start)
    x = u.start + s * u.direction
    if (
        np.hypot(*(x - u.end)) > config.corner_gap_m
        or np.hypot(*(x - v.start)) > config.corner_gap_m
    ):
        return None
    return x


def extract(scan: LaserScan, config: FeatureConfig | None = None) -> ScanFeatures:
    """The scan's lines and corners (module docstring), in the sensor frame."""
    config = config or FeatureConfig()
    lines: list[Line] = []
    run_of: list[int] = []
    for k, run in enumerate(_runs(scan, config)):
        pieces = _split(run, config)
        merged: list[np.ndarray] = []
        for piece in pieces:
            if merged and _collinear(merged[-1], piece, config):
                merged[-1] = np.concatenate([merged[-1], piece[1:]])
            else:
                merged.append(piece)
        for piece in merged:
            if len(piece) >= config.min_points:
                line = _line(piece)
                if line.length >= config.min_length_m:
                    lines.append(line)
                    run_of.append(k)
    corners = []
    for i in range(len(lines) - 1):
        u, v = lines[i], lines[i + 1]
        if run_of[i] != run_of[i + 1] and np.hypot(*(u.end - v.start)) > config.corner_gap_m:
            continue
        if (x := _corner(u, v, config)) is not None:
            corners.append(x)
    return ScanFeatures(lines, np.array(corners, dtype=float).reshape(-1, 2))


def corner_sightings(
    scan: LaserScan,
    config: FeatureConfig | None = None,
    sensor_offset: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> RangeBearings:
    """The scan's corners as range-bearing sightings without IDs (−1) from the walker's
    reference point, the laser mounted at sensor_offset (x, y, yaw) on it."""
    c = transform_points(np.asarray(sensor_offset, dtype=float), extract(scan, config).corners)
    ids = np.full(len(c), -1, dtype=np.int64)
    return RangeBearings.of(scan.t, ids, np.hypot(c[:, 0], c[:, 1]), np.arctan2(c[:, 1], c[:, 0]))
