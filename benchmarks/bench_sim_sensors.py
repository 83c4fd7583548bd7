"""Speed of the simulated sensors, collision check and physics step on the built-in
thesis-course.

Renders depth frames at poses along the route (level Kinect mount at 160×120 and
640×480, and a tilted mount that takes the general path), runs tag detection and the
walker contact check, and prints the time per call; then runs a simulated user (seed 0,
no braking) along the route with the cameras at 1 Hz and prints the time per 200 Hz
physics step (the user's step, the dynamics, the slip, the broad phase and contacts).
Targets: depth 160×120 <= 2.5 ms/frame (the simulator must run >= 20× real time with depth
at 10 Hz, tags at 10 Hz and contacts at 200 Hz).

Usage: .venv/bin/python benchmarks/bench_sim_sensors.py [--frames N]
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable, Sequence

import numpy as np

from hardware.calibration import Mount, WalkerCalibration
from hardware.messages import CameraIntrinsics
from hardware.sim.collision import body_rectangle
from hardware.sim.depth_camera import DepthCameraConfig, SimDepthCamera
from hardware.sim.tag_camera import SimTagCamera, TagCameraConfig
from hardware.sim.world import load_world


def per_call_ms(
    fn: Callable[[Sequence[float]], object], poses: list[tuple[float, float, float]]
) -> float:
    fn(poses[0])  # warm-up
    best = math.inf
    for _ in range(3):
        t0 = time.perf_counter()
        for p in poses:
            fn(p)
        best = min(best, (time.perf_counter() - t0) / len(poses))
    return best * 1e3


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=60, help="poses along the route")
    args = ap.parse_args()
    world = load_world("thesis-course")
    cal = WalkerCalibration()
    route = world.route
    heading = np.arctan2(np.diff(route[:, 1]), np.diff(route[:, 0]))
    idx = np.linspace(0, len(heading) - 1, args.frames).astype(int)
    poses = [(float(route[i, 0]), float(route[i, 1]), float(heading[i])) for i in idx]
    rng = np.random.default_rng(0)
    print(
        f"thesis-course: {len(world.box_array)} boxes, {len(world.tags)} tags, {len(poses)} poses"
    )

    vga = CameraIntrinsics.from_fov(640, 480, math.radians(57.0), math.radians(43.0))
    tilted = Mount(0.41, 0.0, 0.495, pitch=math.radians(10.0))
    cases = [
        ("depth 160x120 level", DepthCameraConfig()),
        ("depth 640x480 level", DepthCameraConfig(intrinsics=vga)),
        ("depth 160x120 tilted 10° (general path)", DepthCameraConfig(mount=tilted)),
    ]
    for name, cfg in cases:
        cam = SimDepthCamera(world, cal, cfg, rng)
        print(f"{name:42s} {per_call_ms(cam.render, poses):7.2f} ms/frame")

    tags = SimTagCamera(world, cal, TagCameraConfig(), rng)
    n_det = sum(len(tags.detect(p)) for p in poses) / len(poses)
    print(
        f"{'tag detection (640x480)':42s} {per_call_ms(tags.detect, poses):7.2f} ms/call "
        f"({n_det:.2f} tags/call)"
    )

    # Contacts at the physics rate: consecutive poses 3.75 mm apart (0.75 m/s at 200 Hz).
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(route, axis=0).T))])
    along = np.arange(0.0, s[-1], 0.75 / 200)
    xs, ys = np.interp(along, s, route[:, 0]), np.interp(along, s, route[:, 1])
    hs = heading[np.minimum(np.searchsorted(s, along, side="right") - 1, len(heading) - 1)]

    def walker_parts(pose: Sequence[float]) -> list[tuple[str, np.ndarray]]:
        return [
            ("frame", body_rectangle(pose, -0.10, 0.64, -0.28, 0.28)),
            ("left-wheel", body_rectangle(pose, -0.102, 0.102, 0.28, 0.345)),
            ("right-wheel", body_rectangle(pose, -0.102, 0.102, -0.345, -0.28)),
        ]

    for label, dy in (("on the route", 0.0), ("0.4 m left of the route", 0.4)):
        parts = [walker_parts((x, y + dy, h)) for x, y, h in zip(xs, ys, hs, strict=True)]
        t0 = time.perf_counter()
        n_con = sum(len(world.contacts(p)) for p in parts)
        us = (time.perf_counter() - t0) / len(parts) * 1e6
        print(
            f"{'contacts, ' + label:42s} {us:7.1f} µs/call ({n_con / len(parts):.2f} contacts/call)"
        )

    from hardware.sim.simulator import SimConfig, Simulator
    from hardware.sim.user import UserProfile

    cfg = SimConfig(
        depth_rate_hz=1, tag_rate_hz=1, seed=0, duration_s=400.0, user_profile=UserProfile.sample(0)
    )
    sim = Simulator(world, cfg)
    sim.poll(1.0)  # (the compiled kernels loaded)
    steps, t0 = sim.steps, time.perf_counter()
    sim.poll(cfg.duration_s)
    steps = sim.steps - steps
    us = (time.perf_counter() - t0) / steps * 1e6
    print(f"{'physics step, a user on the route':42s} {us:7.1f} µs/step ({steps} steps)")


if __name__ == "__main__":
    main()
