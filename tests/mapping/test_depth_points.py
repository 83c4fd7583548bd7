"""Depth image → walker-frame obstacle points and free-space rays, on analytic scenes."""

from __future__ import annotations

import math
import warnings
from dataclasses import replace

import numpy as np
import pytest
from synthetic_depth import FLOOR, Box, depth_frame, render_depth_m, wall_at_x

from hardware.calibration import Mount, WalkerCalibration
from mapping.depth_points import (
    DepthConfig,
    depth_to_observation,
    depth_to_walker_points,
    project_depth_frame,
)

CAL = WalkerCalibration()  # Kinect 160×120, mounted 0.41 m ahead, 0.495 m high, level
FAR_X = 0.41 + 3.5  # a level camera's far range, as walker x


def _frame(scene, mount: Mount = CAL.depth_mount):
    return depth_frame(CAL.depth_intrinsics, mount, scene)


def test_level_wall_two_metres_ahead_is_at_x_2_41():
    obs = project_depth_frame(_frame([FLOOR, wall_at_x(2.41)]), CAL)
    assert len(obs.obstacles) > 5000
    np.testing.assert_allclose(obs.obstacles[:, 0], 2.41, atol=1e-3)
    # The wall spans the horizontal field of view: |y| up to 2 m · tan(28.5°).
    half_width = 2.0 * math.tan(math.radians(28.5))
    assert obs.obstacles[:, 1].max() == pytest.approx(half_width, abs=0.02)
    assert obs.obstacles[:, 1].min() == pytest.approx(-half_width, abs=0.02)
    np.testing.assert_allclose(obs.sensor_xy, [0.41, 0.0])
    assert obs.sensor_yaw == pytest.approx(0.0)


@pytest.mark.parametrize("pitch", [-0.1, 0.2, 0.35])
def test_pitched_camera_sees_the_same_wall_x(pitch):
    mount = Mount(0.41, 0.0, 0.495, pitch=pitch)
    obs = project_depth_frame(
        _frame([FLOOR, wall_at_x(2.41)], mount), replace(CAL, depth_mount=mount)
    )
    assert len(obs.obstacles) > 2000
    np.testing.assert_allclose(obs.obstacles[:, 0], 2.41, atol=1e-3)
    # The 3-D points of the wall have the heights the pitch implies: the image centre
    # row looks down (pitch > 0) or up (pitch < 0) at the wall.
    pts = depth_to_walker_points(
        _frame([wall_at_x(2.41)], mount).depth_mm, CAL.depth_intrinsics, mount, (0.8, 3.5)
    )
    centre_height = 0.495 - 2.0 * math.tan(pitch)
    assert np.median(pts[:, 2]) == pytest.approx(centre_height, abs=0.02)


def test_yawed_camera_reports_its_heading():
    mount = Mount(0.41, 0.0, 0.495, yaw=0.3)
    obs = project_depth_frame(_frame([FLOOR], mount), replace(CAL, depth_mount=mount))
    assert obs.sensor_yaw == pytest.approx(0.3)


def test_floor_only_gives_no_obstacles_but_free_space_on_the_floor():
    frame = _frame([FLOOR])
    obs = project_depth_frame(frame, CAL)
    assert len(obs.obstacles) == 0
    # The lowest pixel row looks down at (119 − cy) / fy (about 21.3°), so the floor is
    # seen from 0.495 m · fy / (119 − cy) ahead of the camera.
    intr = CAL.depth_intrinsics
    nearest = 0.41 + 0.495 * intr.fy / (intr.height - 1 - intr.cy)
    assert len(obs.ray_ends) > 3000
    assert obs.ray_ends[:, 0].min() == pytest.approx(nearest, abs=1e-3)
    assert obs.ray_ends[:, 0].max() == pytest.approx(FAR_X, abs=1e-3)  # cut at the far range
    # The upper half (no return) clears nothing unless asked to.
    no_return = int(np.count_nonzero(frame.depth_mm == 0))
    assert no_return > 0
    obs_free = project_depth_frame(frame, CAL, DepthConfig(no_return_as_free=True))
    assert len(obs_free.ray_ends) == len(obs.ray_ends) + no_return
    extra = obs_free.ray_ends[len(obs.ray_ends) :]
    np.testing.assert_allclose(extra[:, 0], FAR_X, atol=1e-3)


def test_nan_inf_zero_and_negative_pixels_are_ignored():
    rng = np.random.default_rng(3)
    frame = _frame([FLOOR, wall_at_x(2.41), Box((1.5, -0.2, 0.0), (1.9, 0.3, 0.6))])
    bad = rng.random(frame.depth_mm.shape) < 0.2
    clean = frame.depth_mm.copy()
    clean[bad] = 0
    noisy = frame.depth_mm.astype(np.float64)
    noisy[bad] = rng.choice([np.nan, np.inf, -np.inf, 0.0, -5.0], size=int(bad.sum()))
    intr, mount, rng_m = CAL.depth_intrinsics, CAL.depth_mount, CAL.depth_range_m
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = depth_to_observation(noisy, intr, mount, rng_m)
    want = depth_to_observation(clean, intr, mount, rng_m)
    np.testing.assert_array_equal(got.obstacles, want.obstacles)
    np.testing.assert_array_equal(got.ray_ends, want.ray_ends)
    assert len(want.obstacles) > 1000
    # Float metres with depth_scale_m = 1 give the same points as millimetres.
    metres = depth_to_observation(
        noisy / 1000.0, intr, mount, rng_m, DepthConfig(depth_scale_m=1.0)
    )
    np.testing.assert_allclose(metres.obstacles, want.obstacles, atol=1e-5)


def test_obstacle_band_and_range_limits():
    def obstacles(scene):
        return project_depth_frame(_frame([FLOOR, *scene]), CAL).obstacles

    assert len(obstacles([Box((1.8, -0.5, 0.0), (2.2, 0.5, 0.03))])) == 0  # a 3 cm sill
    low = obstacles([Box((1.8, -0.5, 0.0), (2.2, 0.5, 0.5))])  # a 0.5 m box
    np.testing.assert_allclose(low[:, 0], 1.8, atol=2e-3)
    table = obstacles([Box((1.8, -0.5, 0.7), (2.4, 0.5, 0.75))])  # an overhang, no legs
    assert len(table) > 0 and np.all(np.abs(table[:, 0] - 2.1) <= 0.31)
    assert len(obstacles([Box((1.8, -0.5, 2.1), (2.4, 0.5, 2.5))])) == 0  # above 2 m
    # A wall nearer than the 0.8 m minimum is invisible; one beyond 3.5 m is free space
    # up to the far range but no obstacle.
    near = project_depth_frame(_frame([FLOOR, wall_at_x(0.41 + 0.6)]), CAL)
    assert len(near.obstacles) == 0 and len(near.ray_ends) == 0
    for edge in (0.8, 3.5):  # the range ends themselves are in range
        at_edge = project_depth_frame(_frame([FLOOR, wall_at_x(0.41 + edge)]), CAL).obstacles
        assert len(at_edge) > 1000
        np.testing.assert_allclose(at_edge[:, 0], 0.41 + edge, atol=1e-3)
    far = project_depth_frame(_frame([FLOOR, wall_at_x(0.41 + 5.0)]), CAL)
    assert len(far.obstacles) == 0
    assert np.count_nonzero(np.isclose(far.ray_ends[:, 0], FAR_X, atol=1e-3)) > 5000


def test_rays_that_hit_above_the_band_clear_nothing():
    # A camera pitched up 23° sees only a 2.3 m high ceiling (within range): those rays
    # passed over unseen ground, so they give neither obstacles nor free space.
    mount = Mount(0.41, 0.0, 0.495, pitch=-0.4)
    frame = _frame([FLOOR, Box((0.0, -5.0, 2.3), (3.0, 5.0, 2.4))], mount)
    assert np.count_nonzero((frame.depth_mm >= 800) & (frame.depth_mm <= 3500)) > 4000
    obs = project_depth_frame(frame, replace(CAL, depth_mount=mount))
    assert len(obs.obstacles) == 0 and len(obs.ray_ends) == 0


def test_stride_keeps_every_nth_pixel():
    frame = _frame([FLOOR, wall_at_x(2.41)])
    full = project_depth_frame(frame, CAL)
    sparse = project_depth_frame(frame, CAL, DepthConfig(stride=4))
    assert len(sparse.obstacles) == pytest.approx(len(full.obstacles) / 16, rel=0.05)
    np.testing.assert_allclose(sparse.obstacles[:, 0], 2.41, atol=1e-3)


def test_bad_shapes_raise():
    depth = render_depth_m(CAL.depth_intrinsics, CAL.depth_mount, [FLOOR])
    with pytest.raises(ValueError, match=r"\(120, 160\)"):
        depth_to_observation(depth[:-1], CAL.depth_intrinsics, CAL.depth_mount, (0.8, 3.5))
    with pytest.raises(ValueError, match="stride"):
        DepthConfig(stride=0)
