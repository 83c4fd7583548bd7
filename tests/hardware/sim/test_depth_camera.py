"""Simulated depth camera: z-depth on known geometry, range limits, occlusion, noise."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hardware.calibration import Mount, WalkerCalibration
from hardware.frames import planar_pose_to_transform
from hardware.messages import CameraIntrinsics, DepthFrame
from hardware.sim.depth_camera import DepthCameraConfig, SimDepthCamera
from hardware.sim.world import Box, Obstacle, World, load_world, table_boxes

CAL = WalkerCalibration()
NO_NOISE = DepthCameraConfig(noise_coeff=0.0, dropout=0.0)
H_CAM = 0.495  # camera height
X_CAM = 0.41  # camera ahead of the rear axle


def world_of(*obstacles: Obstacle) -> World:
    return World("test", (-10, 10, -10, 10), obstacles, (), np.array([[0, 0], [1, 0]]), (0, 0, 0))


def wall(
    name: str, x: float, y: float, yaw: float, length: float = 8.0, height: float = 2.4
) -> Obstacle:
    return Obstacle(name, "wall", (Box(x, y, yaw, 0.1, length, 0.0, height),))


def camera(w: World, config: DepthCameraConfig = NO_NOISE, seed: int = 0) -> SimDepthCamera:
    return SimDepthCamera(w, CAL, config, np.random.default_rng(seed))


def pixel_rays(k: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
    xn = (np.arange(k.width) - k.cx) / k.fx
    yn = (np.arange(k.height) - k.cy) / k.fy
    return np.meshgrid(xn, yn)


def floor_depth(k: CameraIntrinsics, h: float = H_CAM) -> np.ndarray:
    """Level camera: z-depth at which each row's rays meet the floor (inf above the horizon)."""
    yn = (np.arange(k.height) - k.cy) / k.fy
    d = np.where(yn > 0, h / np.where(yn > 0, yn, 1.0), np.inf)
    return np.broadcast_to(d[:, None], (k.height, k.width))


def expected_mm(z: np.ndarray, lo: float = 0.8, hi: float = 3.5) -> np.ndarray:
    return np.where((z >= lo) & (z <= hi), np.rint(z * 1000.0), 0)


def test_oblique_wall_matches_plane_intersection() -> None:
    # Wall face: the plane through (3, 0) with normal (-cos a, -sin a), seen from a walker
    # turned by 0.3 rad. Analytic z-depth per pixel: t = (c - n·o) / (n·d_optical_in_world).
    a = 0.25
    face = np.array([3.0, 0.0])
    n = -np.array([math.cos(a), math.sin(a)])
    centre = face - 0.05 * n
    w = world_of(wall("w", *centre, a, length=20.0))
    pose = (0.2, -0.3, 0.3)
    cam = camera(w)
    depth = cam.render(pose)
    k = cam.intrinsics
    assert depth.dtype == np.uint16 and depth.shape == (k.height, k.width)
    world_T_opt = planar_pose_to_transform(*pose) @ CAL.depth_mount.walker_T_optical()
    r, o = world_T_opt[:3, :3], world_T_opt[:3, 3]
    xs, ys = pixel_rays(k)
    d = np.stack([xs, ys, np.ones_like(xs)], axis=-1) @ r.T
    n3 = np.array([n[0], n[1], 0.0])
    t_wall = (n3 @ np.array([*face, 0.0]) - n3 @ o) / (d @ n3)
    z = np.minimum(t_wall, floor_depth(k))
    want = expected_mm(z)
    assert (want > 0).mean() > 0.5
    assert np.abs(depth.astype(int) - want).max() <= 1


def test_floor_rows_follow_camera_height() -> None:
    cam = camera(world_of())
    depth = cam.render((1.0, 2.0, 0.7))
    k = cam.intrinsics
    want = expected_mm(floor_depth(k))
    assert np.abs(depth.astype(int) - want).max() <= 1
    rows = np.flatnonzero(want[:, 0] > 0)
    assert len(rows) > 10  # the floor is visible (beyond ~1.3 m) in the lower image
    assert (depth[: int(k.cy) + 1] == 0).all()  # nothing above the horizon


def test_out_of_range_boxes_read_zero() -> None:
    near = world_of(wall("near", X_CAM + 0.6 + 0.05, 0.0, 0.0))
    assert (camera(near).render((0, 0, 0)) == 0).all()  # 0.6 m: too near (floor hidden too)
    far = world_of(wall("far", X_CAM + 4.0 + 0.05, 0.0, 0.0))
    depth = camera(far).render((0, 0, 0))
    k = CAL.depth_intrinsics
    np.testing.assert_array_equal(depth, expected_mm(floor_depth(k)))  # only floor pixels


def test_box_in_front_of_a_wall_occludes_it() -> None:
    w = world_of(
        wall("wall", X_CAM + 3.0 + 0.05, 0.0, 0.0),
        Obstacle("crate", "box", (Box(X_CAM + 1.5 + 0.2, 0.0, 0.0, 0.4, 0.4, 0.0, 1.0),)),
    )
    cam = camera(w)
    depth = cam.render((0, 0, 0))
    k = cam.intrinsics
    u0 = round(k.cx)
    v_mid = round(k.cy)
    assert depth[v_mid, u0] == 1500  # crate face at 1.5 m (its top 1.0 m is above the camera)
    assert depth[v_mid, 5] == 3000  # the wall, seen past the crate's side
    crate_cols = np.flatnonzero(depth[v_mid] == 1500)
    # The crate (0.4 m wide at 1.5 m) covers fx·0.4/1.5 columns.
    assert len(crate_cols) == pytest.approx(k.fx * 0.4 / 1.5, abs=1.5)
    assert ((depth[v_mid] == 1500) | (depth[v_mid] == 3000)).all()


def test_table_from_the_side_shows_legs_and_top_but_free_space_under_it() -> None:
    table = Obstacle(
        "table", "table", table_boxes(X_CAM + 2.0 + 0.4, 0.0, 0.0, width=1.6, depth=0.8)
    )
    w = world_of(wall("wall", X_CAM + 3.3 + 0.05, 0.0, 0.0), table)
    cam = camera(w)
    depth = cam.render((0, 0, 0))
    k = cam.intrinsics
    xs, ys = pixel_rays(k)
    # Height of each pixel's ray at the table's near face (z = 2.0 m).
    h_at_table = H_CAM - ys * 2.0
    y_at_table = -xs * 2.0  # optical x is to the right, world y to the left
    leg_y = 0.8 - 0.03 - 0.025  # near legs at y = ±0.745 (5 cm legs, 3 cm inset)
    top = (h_at_table > 0.725) & (h_at_table < 0.745) & (np.abs(y_at_table) < 0.78)
    assert top.sum() > 0 and (depth[top] == 2000).all()  # top edge at 2.0 m
    leg = (np.abs(np.abs(y_at_table) - leg_y) < 0.01) & (h_at_table > 0.1) & (h_at_table < 0.7)
    assert leg.sum() > 0
    assert (depth[leg] == 2000 + 30).all()  # leg front face, 3 cm behind the top edge
    # Rays that stay below the top (0.72 m) all the way to its far edge (2.8 m) pass under
    # the table and see the wall; rays rising more steeply meet the top's underside.
    under = (np.abs(y_at_table) < 0.5) & (h_at_table > 0.2) & (h_at_table < 0.55)
    assert under.sum() > 100 and (depth[under] == 3300).all()
    underside = (np.abs(y_at_table) < 0.5) & (h_at_table > 0.65) & (h_at_table < 0.7)
    assert (depth[underside] > 2000).all() and (depth[underside] < 2800).all()


def test_noise_grows_with_square_of_depth() -> None:
    w = world_of(wall("wall", X_CAM + 3.0 + 0.05, 0.0, 0.0, length=20.0))
    cam = camera(w, DepthCameraConfig(dropout=0.0), seed=3)
    k = cam.intrinsics
    rows = slice(0, int(k.cy))  # above the horizon: the wall only, z = 3.0 m exactly
    z = np.concatenate([cam.render((0, 0, 0))[rows].ravel() for _ in range(3)]) / 1000.0
    assert np.std(z) == pytest.approx(1.425e-3 * 3.0**2, rel=0.10)
    assert np.mean(z) == pytest.approx(3.0, abs=1e-3)


def test_dropout_and_reproducibility() -> None:
    w = world_of(wall("wall", X_CAM + 2.0 + 0.05, 0.0, 0.0, length=20.0))
    a = camera(w, DepthCameraConfig(), seed=11).render((0, 0, 0))
    b = camera(w, DepthCameraConfig(), seed=11).render((0, 0, 0))
    np.testing.assert_array_equal(a, b)
    assert (a == 0).mean() == pytest.approx(0.005, abs=0.002)
    DepthFrame(0.0, a, CAL.depth_intrinsics)  # a valid message


def test_vga_intrinsics_and_tilted_mount_match_brute_force() -> None:
    # The level fast path, and the general path for a tilted and rolled camera, against
    # casting every pixel's ray at every box.
    w = load_world("thesis-course")
    vga = CameraIntrinsics.from_fov(320, 240, math.radians(57), math.radians(43))
    level = camera(w, DepthCameraConfig(noise_coeff=0, dropout=0, intrinsics=vga))
    tilted = camera(
        w,
        DepthCameraConfig(
            noise_coeff=0, dropout=0, mount=Mount(0.41, 0.05, 0.8, roll=0.05, pitch=0.35, yaw=-0.1)
        ),
    )
    assert level.level and not tilted.level
    for cam in (level, tilted):
        k = cam.intrinsics
        xs, ys = pixel_rays(k)
        for pose in [(0.95, 0.5, math.pi / 2), (5.2, 3.5, -math.pi / 2), (9.0, 6.2, 0.3)]:
            m = planar_pose_to_transform(*pose) @ cam.walker_T_optical
            d = (np.stack([xs, ys, np.ones_like(xs)], axis=-1) @ m[:3, :3].T).reshape(-1, 3)
            t_max = 3.5 * 1.05 + 0.05
            t, _ = cam.caster.cast(m[:3, 3], d, t_max)
            with np.errstate(divide="ignore"):
                t_floor = np.where(d[:, 2] < 0, -m[2, 3] / d[:, 2], np.inf)
            t = np.minimum(t, np.where(t_floor <= t_max, t_floor, np.inf)).reshape(xs.shape)
            got = cam.true_depth(pose)
            np.testing.assert_array_equal(np.isfinite(got), np.isfinite(t))
            fin = np.isfinite(t)
            assert np.abs(got[fin] - t[fin]).max() < 1e-5
