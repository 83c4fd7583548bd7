"""Potential-field braking: the repulsion against hand-computed cases and its brake sides."""

import math

import numpy as np
import pytest

from control.base import ControlInput, create
from control.potential_field import PotentialFieldConfig, repulsion
from hardware.calibration import WalkerCalibration

CAL = WalkerCalibration()
OFF, FULL = CAL.brake.torque_off_nm, CAL.brake.torque_max_nm
CFG = PotentialFieldConfig()


def command(points, pose=(0.0, 0.0, 0.0), v=0.8):
    ctl = create("potential-field", CAL)
    return ctl.command(ControlInput(0.0, np.asarray(points, float), np.array(pose), v, 0.0))


def test_single_cell_hand_computed():
    # a cell 0.6 m from the reference point (0.3, 0), 30° to the left
    p = [[0.3 + 0.6 * math.cos(math.radians(30)), 0.6 * math.sin(math.radians(30))]]
    # m = 0.05 · (1/0.6² − 1/1.2²) = 0.05 · (2.777… − 0.694…) = 0.05 · 2.083… = 0.1041667
    m = 0.05 * (1 / 0.36 - 1 / 1.44)
    f = repulsion(np.array(p), CFG)
    assert f.fx == pytest.approx(-m * math.cos(math.radians(30)))
    assert f.fy == pytest.approx(-m * 0.5)
    assert f.fx_band == pytest.approx(f.fx)  # y = 0.3 <= 0.345: inside the band ahead
    cmd = command(p)
    slow = 0.8 * m * math.cos(math.radians(30))
    assert cmd.left_nm == pytest.approx(OFF + slow)  # ≈ 0.140
    assert cmd.right_nm == pytest.approx(OFF + 1.5 * m * 0.5 + slow)  # ≈ 0.218


def test_nothing_to_repel_no_braking():
    assert (command(np.zeros((0, 2))).left_nm, command(np.zeros((0, 2))).right_nm) == (OFF, OFF)
    # behind the reference point, or beyond the influence radius
    cmd = command([[0.2, 0.6], [-0.5, -0.3], [0.3 + 1.25, 0.0], [0.3, 1.3]])
    assert (cmd.left_nm, cmd.right_nm) == (OFF, OFF)


def obstacle_left():
    """A post 0.7 m ahead of the walker's front and 0.35 m to its left (world frame)."""
    ang = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    return np.column_stack([1.0 + 0.1 * np.cos(ang), 0.45 + 0.1 * np.sin(ang)])


def test_brakes_the_side_away_from_an_obstacle():
    cmd = command(obstacle_left())
    assert cmd.right_nm > OFF + 0.1  # turn right, away from the obstacle on the left
    assert cmd.left_nm == pytest.approx(OFF)
    mirrored = command(obstacle_left() * np.array([1.0, -1.0]))
    assert (mirrored.left_nm, mirrored.right_nm) == pytest.approx((cmd.right_nm, cmd.left_nm))


def test_works_in_the_world_frame():
    # the same scene with the walker at (2, -1) facing +y: rotate the points by +90°
    pts = obstacle_left()
    world = np.column_stack([2.0 - pts[:, 1], -1.0 + pts[:, 0]])
    a = command(pts)
    b = command(world, pose=(2.0, -1.0, math.pi / 2))
    assert (b.left_nm, b.right_nm) == pytest.approx((a.left_nm, a.right_nm))


def test_obstacle_straight_ahead_brakes_both_equally():
    y = np.arange(-0.5, 0.5 + 1e-9, 0.05)
    wall = np.column_stack([np.full_like(y, 0.9), y])
    cmd = command(wall)
    assert cmd.left_nm == pytest.approx(cmd.right_nm)
    assert cmd.left_nm > OFF + 0.3
    nearer = command(wall - [0.2, 0.0])
    assert nearer.left_nm > cmd.left_nm
    # very close: clamped to the brake's maximum
    assert command(wall - [0.55, 0.0]).left_nm == FULL


def test_no_braking_unless_moving_forward():
    for v in (0.0, -0.3):
        cmd = command(obstacle_left(), v=v)
        assert (cmd.left_nm, cmd.right_nm) == (OFF, OFF)


def test_config_validation():
    with pytest.raises(ValueError, match="min_distance_m < radius_m"):
        PotentialFieldConfig(radius_m=0.05)
    with pytest.raises(ValueError, match="half_fov_deg"):
        PotentialFieldConfig(half_fov_deg=0.0)
