"""Depth-frame integration speed of the occupancy mapper, in ms per frame.

Run from the repository root: `.venv/bin/python benchmarks/bench_mapper.py`.
Deterministic: synthetic depth frames of a room (a plane wall, two side walls and a box,
rendered analytically) seen from seeded walker poses along a short path. Each number is
the mean time per frame of one pass over the frames, median (and best) over repeated
passes, for the full pipeline (depth → points → free-space rays → grid update) and for
the projection alone (depth → walker-frame points and ray ends). Targets on one core:
<= 5 ms per 160×120 frame, <= 30 ms per 640×480 frame.
"""

from __future__ import annotations

import math
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests" / "mapping")]  # repo + the test scene renderer

from synthetic_depth import FLOOR, Box, Plane, depth_frame  # noqa: E402

from hardware.calibration import WalkerCalibration  # noqa: E402
from hardware.messages import CameraIntrinsics  # noqa: E402
from mapping.depth_points import project_depth_frame  # noqa: E402
from mapping.grid import GridConfig  # noqa: E402
from mapping.mapper import MapperConfig, OccupancyMapper  # noqa: E402

N_FRAMES = 20
REPEATS = 5


def room_frames(intrinsics: CameraIntrinsics, seed: int = 0) -> tuple[list, np.ndarray]:
    """Frames of a 6 m × 4 m room with a box, from poses along a noisy path."""
    rng = np.random.default_rng(seed)
    cal = WalkerCalibration()
    scene = [
        FLOOR,
        Plane((1.0, 0.0, 0.0), 4.0),  # far wall
        Plane((0.0, 1.0, 0.0), 2.0),  # left wall
        Plane((0.0, 1.0, 0.0), -2.0),  # right wall
        Box((2.2, -0.4, 0.0), (2.8, 0.3, 0.9)),
    ]
    poses = np.column_stack(
        [
            np.linspace(-1.0, 0.5, N_FRAMES) + rng.normal(0, 0.02, N_FRAMES),
            rng.normal(0, 0.1, N_FRAMES),
            rng.normal(0, 0.2, N_FRAMES),
        ]
    )
    frames = [
        depth_frame(intrinsics, cal.depth_mount, scene, tuple(pose), t=0.1 * k)
        for k, pose in enumerate(poses)
    ]
    return frames, poses


def per_frame_ms(fn: Callable[[], None], n: int) -> tuple[float, float]:
    """(median, best) over REPEATS passes of the mean ms per frame of fn() over n frames."""
    times = []
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) / n * 1e3)
    return statistics.median(times), min(times)


def bench(width: int, height: int, config: MapperConfig, label: str) -> None:
    intr = CameraIntrinsics.from_fov(width, height, math.radians(57.0), math.radians(43.0))
    frames, poses = room_frames(intr)
    cal = WalkerCalibration(depth_intrinsics=intr)

    def full() -> None:
        mapper = OccupancyMapper(cal, config)
        for f, p in zip(frames, poses, strict=True):
            mapper.integrate_depth(f, p)

    def project() -> None:
        for f in frames:
            project_depth_frame(f, cal, config.depth)

    full()  # warm caches (pixel rays) before timing
    mapper = OccupancyMapper(cal, config)
    for f, p in zip(frames, poses, strict=True):
        mapper.integrate_depth(f, p)
    occ = int(mapper.grid.occupied().sum())
    full_med, full_best = per_frame_ms(full, len(frames))
    proj_med, proj_best = per_frame_ms(project, len(frames))
    print(
        f"{label:<20} full {full_med:6.2f} ms/frame (best {full_best:5.2f})   "
        f"projection alone {proj_med:5.2f} (best {proj_best:5.2f})   occupied cells {occ}"
    )


def main() -> None:
    print(f"numpy {np.__version__}; {N_FRAMES} frames, median of {REPEATS} passes")
    log_odds = MapperConfig()
    view_count = MapperConfig(grid=GridConfig(model="view-count"))
    bench(160, 120, log_odds, "160x120 log-odds")
    bench(160, 120, view_count, "160x120 view-count")
    bench(640, 480, log_odds, "640x480 log-odds")
    bench(640, 480, view_count, "640x480 view-count")


if __name__ == "__main__":
    main()
