"""Analytic depth images of simple scenes (planes, axis-aligned boxes) for mapping tests.

Scenes are in the world frame (z up, floor at z = 0); the camera sits on its mount on a
walker at planar pose (x, y, θ) (default: the origin, so scene = walker frame). Each pixel's
ray is intersected exactly with every primitive; the nearest hit gives the z-depth (along
the optical axis, as the Kinect reports it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hardware.calibration import Mount
from hardware.frames import planar_pose_to_transform
from hardware.messages import CameraIntrinsics, DepthFrame


@dataclass(frozen=True)
class Plane:
    """Points p with normal · p = offset."""

    normal: tuple[float, float, float]
    offset: float


@dataclass(frozen=True)
class Box:
    """Axis-aligned box [lo, hi] (walker frame, metres)."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]


FLOOR = Plane((0.0, 0.0, 1.0), 0.0)


def wall_at_x(x: float) -> Plane:
    return Plane((1.0, 0.0, 0.0), x)


def _rays(
    intrinsics: CameraIntrinsics, mount: Mount, pose: tuple[float, float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """Camera centre (3,) and world-frame ray per unit z-depth (H, W, 3)."""
    u, v = np.meshgrid(np.arange(intrinsics.width), np.arange(intrinsics.height))
    opt = np.stack(
        [
            (u - intrinsics.cx) / intrinsics.fx,
            (v - intrinsics.cy) / intrinsics.fy,
            np.ones(u.shape),
        ],
        axis=-1,
    )
    t = planar_pose_to_transform(*pose) @ mount.walker_T_optical()
    return t[:3, 3], opt @ t[:3, :3].T


def _hit_plane(c: np.ndarray, d: np.ndarray, p: Plane) -> np.ndarray:
    n = np.asarray(p.normal, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (p.offset - n @ c) / (d @ n)
    return np.where(t > 0, t, np.inf)


def _hit_box(c: np.ndarray, d: np.ndarray, b: Box) -> np.ndarray:
    lo, hi = np.asarray(b.lo, dtype=float), np.asarray(b.hi, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - c) / d, (hi - c) / d
    t_near = np.nanmax(np.minimum(t1, t2), axis=-1)
    t_far = np.nanmin(np.maximum(t1, t2), axis=-1)
    return np.where((t_near <= t_far) & (t_near > 0), t_near, np.inf)


def render_depth_m(
    intrinsics: CameraIntrinsics,
    mount: Mount,
    scene: list[Plane | Box],
    pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> np.ndarray:
    """(H, W) float64 z-depth [m] of the nearest surface; inf where nothing is hit."""
    c, d = _rays(intrinsics, mount, pose)
    depth = np.full(d.shape[:2], np.inf)
    for prim in scene:
        hit = _hit_plane(c, d, prim) if isinstance(prim, Plane) else _hit_box(c, d, prim)
        depth = np.minimum(depth, hit)
    return depth


def depth_frame(
    intrinsics: CameraIntrinsics,
    mount: Mount,
    scene: list[Plane | Box],
    pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
    t: float = 0.0,
    max_m: float = 8.0,
) -> DepthFrame:
    """A DepthFrame (uint16 mm, 0 = no return beyond max_m) of the scene from `pose`."""
    z = render_depth_m(intrinsics, mount, scene, pose)
    mm = np.where(np.isfinite(z) & (z <= max_m), np.round(z * 1000.0), 0.0)
    return DepthFrame(t, mm.astype(np.uint16), intrinsics)
