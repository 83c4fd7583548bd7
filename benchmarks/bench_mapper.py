"""Depth-frame integration speed of the occupancy mapper, in ms per frame.

Run from the repository root: `.venv/bin/python benchmarks/bench_mapper.py` (pin it to
one core for stable numbers: `OMP_NUM_THREADS=1 taskset -c 0 ...`).

Deterministic inputs:
- "sim route": 160×120 frames of the simulator's thesis course (noise and dropout as
  simulated) from poses evenly spaced along its route, heading along the route — the
  frames a replayed trial feeds the mapper. Target on one core: <= 0.7 ms per frame, so
  that a replay (dead reckoning + mapper) runs >= 100× real time at 10 Hz.
- synthetic depth frames of a room (a plane wall, two side walls and a box, rendered
  analytically) seen from seeded walker poses along a short path, at 160×120 and 640×480.

Each number is the mean time per frame of one pass over the frames, median (and best)
over repeated passes, for the full pipeline (depth → points → free-space rays → grid
update) and for the projection alone (depth → compacted walker-frame points and ray
ends, as the mapper keeps them).
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
from hardware.messages import CameraIntrinsics, DepthFrame  # noqa: E402
from hardware.sim.depth_camera import DepthCameraConfig, SimDepthCamera  # noqa: E402
from hardware.sim.simulator import SimConfig  # noqa: E402
from hardware.sim.world import load_world  # noqa: E402
from mapping.depth_points import project_depth_frame  # noqa: E402
from mapping.grid import GridConfig  # noqa: E402
from mapping.mapper import MapperConfig, OccupancyMapper  # noqa: E402

N_FRAMES = 20
SIM_FRAMES = 300
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
        quantum = config.grid.resolution_m / 4.0  # the mapper's default compaction
        for f in frames:
            project_depth_frame(f, cal, config.depth, quantum=quantum)

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


def sim_route_frames(n: int, seed: int = 0) -> tuple[WalkerCalibration, list, np.ndarray]:
    """n simulated depth frames from poses evenly spaced along the thesis course's route."""
    world = load_world("thesis-course")
    cal = SimConfig().calibration()
    camera = SimDepthCamera(world, cal, DepthCameraConfig(), np.random.default_rng(seed))
    route = np.asarray(world.route)
    seg = np.diff(route, axis=0)
    length = np.hypot(seg[:, 0], seg[:, 1])
    start = np.concatenate([[0.0], np.cumsum(length)])
    s = np.linspace(0.0, start[-1], n, endpoint=False)
    k = np.clip(np.searchsorted(start, s, side="right") - 1, 0, len(seg) - 1)
    xy = route[k] + ((s - start[k]) / length[k])[:, None] * seg[k]
    poses = np.column_stack([xy, np.arctan2(seg[k, 1], seg[k, 0])])
    frames = [
        DepthFrame(0.1 * i, camera.render(p), cal.depth_intrinsics) for i, p in enumerate(poses)
    ]
    return cal, frames, poses


def bench_sim_route(
    route: tuple[WalkerCalibration, list, np.ndarray], config: MapperConfig, label: str
) -> None:
    cal, frames, poses = route

    def full() -> None:
        mapper = OccupancyMapper(cal, config)
        for f, p in zip(frames, poses, strict=True):
            mapper.integrate_depth(f, p)

    full()  # warm caches
    med, best = per_frame_ms(full, len(frames))
    print(
        f"{label:<20} full {med:6.2f} ms/frame (best {best:5.2f})   "
        f"replay at 10 Hz: {100.0 / med:5.0f}× real time (mapper alone)"
    )


def main() -> None:
    print(f"numpy {np.__version__}; median of {REPEATS} passes")
    log_odds = MapperConfig()
    view_count = MapperConfig(grid=GridConfig(model="view-count"))
    route = sim_route_frames(SIM_FRAMES)
    print(f"sim route: {SIM_FRAMES} frames along the thesis course")
    bench_sim_route(route, log_odds, "160x120 log-odds")
    bench_sim_route(route, view_count, "160x120 view-count")
    print(f"synthetic room: {N_FRAMES} frames")
    bench(160, 120, log_odds, "160x120 log-odds")
    bench(160, 120, view_count, "160x120 view-count")
    bench(640, 480, log_odds, "640x480 log-odds")
    bench(640, 480, view_count, "640x480 view-count")


if __name__ == "__main__":
    main()
