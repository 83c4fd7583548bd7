"""Planar laser scan → obstacle points and free-space rays in the walker frame.

Beam i points at angle_min + i·angle_increment in the sensor frame, which sits at
`sensor_offset` = (x, y, yaw) on the walker. A reading that is finite, > 0 and
< range_max is a hit. With `max_range_m` set, hits farther than it are not obstacles
(too unreliable) but still clear free space up to max_range_m. Other readings are
"no return": they clear free space up to min(range_max, max_range_m) only with
`no_return_as_free`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hardware.geometry import transform_points
from hardware.messages import LaserScan
from mapping.observation import PlanarObservation, as_pose


@dataclass(frozen=True)
class ScanConfig:
    """max_range_m: farthest reading used as an obstacle (None: up to range_max).
    no_return_as_free: beams with no return clear free space up to the usable range.
    """

    max_range_m: float | None = None
    no_return_as_free: bool = False


def scan_hits(scan: LaserScan, max_range_m: float | None = None) -> np.ndarray:
    """Which beams hit something (module docstring): a reading that is finite, > 0 and
    < range_max, and with max_range_m not beyond it."""
    r = np.asarray(scan.ranges, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        hit = np.isfinite(r) & (r > 0) & (r < scan.range_max)
        if max_range_m is not None:
            hit &= r <= max_range_m
    return hit


def scan_to_observation(
    scan: LaserScan,
    sensor_offset: tuple[float, float, float] | np.ndarray = (0.0, 0.0, 0.0),
    config: ScanConfig | None = None,
) -> PlanarObservation:
    """Hits and free-space ray ends of `scan` in the walker frame (no view wedge)."""
    cfg = config or ScanConfig()
    offset = as_pose(sensor_offset, "sensor_offset")
    r = np.asarray(scan.ranges, dtype=np.float64)
    if r.ndim != 1:
        raise ValueError(f"scan.ranges must have shape (N,), got {r.shape}")
    usable = scan.range_max if cfg.max_range_m is None else min(cfg.max_range_m, scan.range_max)
    returned = scan_hits(scan)
    hit = returned & (r <= usable)
    cut = ~hit if cfg.no_return_as_free else returned & ~hit
    end_r = np.where(hit, r, usable)
    keep = hit | cut
    a = scan.angles[keep]
    ends_sensor = np.column_stack([end_r[keep] * np.cos(a), end_r[keep] * np.sin(a)])
    ends = transform_points(offset, ends_sensor)
    return PlanarObservation(
        sensor_xy=offset[:2],
        sensor_yaw=offset[2],
        obstacles=ends[hit[keep]],
        ray_ends=ends,
        view=None,
    )
