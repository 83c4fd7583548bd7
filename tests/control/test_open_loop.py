"""Open-loop braking and the turn decision against hand-computed cases."""

import math

import numpy as np
import pytest

from control.base import CONTROLLERS, ControlInput, create
from control.open_loop import OpenLoopConfig, open_loop_level
from control.perception import choose_turn, front_distance
from hardware.calibration import WalkerCalibration
from hardware.geometry import to_walker_frame

CAL = WalkerCalibration()
OFF, FULL = CAL.brake.torque_off_nm, CAL.brake.torque_max_nm


def wall_ahead(distance_from_camera, y_from=-1.0, y_to=1.0):
    """Occupied points of a wall across the walker's path, in the world (walker at origin)."""
    y = np.arange(y_from, y_to + 1e-9, 0.05)
    return np.column_stack([np.full_like(y, CAL.depth_mount.x + distance_from_camera), y])


@pytest.mark.parametrize(
    ("d", "level"), [(2.0, 0.0), (1.25, 0.0), (1.0, 1 / 3), (0.875, 0.5), (0.5, 1.0), (0.2, 1.0)]
)
def test_eq_5_13_levels(d, level):
    assert open_loop_level(d, 0.5, 1.25) == pytest.approx(level)


def test_front_distance_only_counts_the_walker_width_band():
    pts = np.array([[2.0, 0.5], [3.0, 0.1], [1.0, -0.36], [-1.0, 0.0]])
    assert front_distance(pts, 0.41, 0.345, 3.5) == pytest.approx(2.59)
    assert math.isinf(front_distance(pts[[0, 2, 3]], 0.41, 0.345, 3.5))


def test_to_walker_frame():
    pose = np.array([1.0, 1.0, math.pi / 2])
    assert np.allclose(to_walker_frame(np.array([[1.0, 3.0]]), pose), [[2.0, 0.0]])


def test_turn_toward_larger_free_area():
    # obstacle on the right half at 1 m, left half open and in view
    pts = np.array(
        [[0.41 + 1.0 * math.cos(a), 1.0 * math.sin(a)] for a in np.radians(np.arange(-44, 0, 1.0))]
    )
    d = choose_turn(pts, 0.41, math.radians(45), 32, math.radians(28.5), 3.5, 0.0)
    assert d.direction == 1
    # hand-computed: in-view left arcs have r = 3.5, unseen left arcs 0
    edges = np.linspace(-math.radians(45), math.radians(45), 33)
    centres = 0.5 * (edges[:-1] + edges[1:])
    dth = edges[1] - edges[0]
    n_left_in_view = np.count_nonzero((centres > 0) & (centres <= math.radians(28.5)))
    assert d.area_left == pytest.approx(n_left_in_view * 0.5 * 3.5**2 * dth)
    assert d.area_right == pytest.approx(16 * 0.5 * 1.0**2 * dth, rel=1e-6)


def test_open_loop_brakes_the_turn_side_with_eq_5_13_torque():
    ctl = create("open-loop", CAL)
    # wall ahead at 0.875 m, blocked more on the left → turn right, brake right at half level
    pts = np.vstack([wall_ahead(0.875), [[0.41 + 0.6, 0.5], [0.41 + 0.5, 0.4]]])
    cmd = ctl.command(ControlInput(1.0, pts, np.zeros(3), v=0.8, omega=0.0))
    assert cmd.left_nm == pytest.approx(OFF)
    assert cmd.right_nm == pytest.approx(OFF + 0.5 * (FULL - OFF))


def test_no_braking_when_not_moving_forward_or_path_clear():
    ctl = create("open-loop", CAL)
    pts = wall_ahead(0.7)
    for v in (0.0, -0.3):
        cmd = ctl.command(ControlInput(0.0, pts, np.zeros(3), v=v, omega=0.0))
        assert (cmd.left_nm, cmd.right_nm) == (OFF, OFF)
    cmd = ctl.command(ControlInput(0.0, wall_ahead(2.0), np.zeros(3), v=1.0, omega=0.0))
    assert (cmd.left_nm, cmd.right_nm) == (OFF, OFF)


def test_manual_never_brakes_and_registry_lists_names():
    assert {"none", "open-loop"} <= set(CONTROLLERS.names())
    cmd = create("none", CAL).command(ControlInput(0.0, wall_ahead(0.3), np.zeros(3), 1.0, 0.0))
    assert (cmd.left_nm, cmd.right_nm) == (OFF, OFF)
    with pytest.raises(ValueError, match="d_min < d_max"):
        OpenLoopConfig(d_min_m=1.0, d_max_m=0.5)


@pytest.mark.parametrize("name", ["open-loop", "closed-loop"])
def test_turn_side_is_latched_for_a_braking_episode(name):
    """The side chosen when braking starts is kept while the obstacle stays within d_max
    (even when the free areas swap), and chosen afresh after the episode ends; with
    latch_turn=False the side follows the free areas every tick (the thesis)."""
    from dataclasses import replace

    from control.base import CONTROLLERS

    blocked_left = np.vstack([wall_ahead(0.875), [[0.41 + 0.6, 0.5], [0.41 + 0.5, 0.4]]])
    blocked_right = blocked_left * np.array([1.0, -1.0])
    clear = np.empty((0, 2))

    def braked_sides(latch):
        cfg = replace(CONTROLLERS.spec(name).config_type(), latch_turn=latch)
        ctl = create(name, CAL, cfg)
        sides = []
        for k, pts in enumerate([blocked_left, blocked_right, blocked_right, clear, blocked_right]):
            cmd = ctl.command(ControlInput(0.1 * k, pts, np.zeros(3), v=0.8, omega=0.0))
            sides.append(
                0
                if max(cmd.left_nm, cmd.right_nm) <= OFF + 1e-9
                else (1 if cmd.left_nm > cmd.right_nm else -1)
            )
        return sides

    assert braked_sides(True) == [-1, -1, -1, 0, 1]
    assert braked_sides(False) == [-1, 1, 1, 0, 1]
