"""Closed-loop braking: eqs 5.11, 5.14–5.16 against hand-computed cases, and the controller."""

import math
from dataclasses import replace

import numpy as np
import pytest

from control.base import CONTROLLERS, ControlInput, create
from control.closed_loop import (
    ClosedLoop,
    ClosedLoopConfig,
    brake_forces,
    handle_forces,
    handle_forces_dynamic,
    least_braking_forces,
    least_braking_yaw_rate,
)
from hardware.calibration import WalkerCalibration
from hardware.sim.dynamics import WalkerParams, steady_state_radius

CAL = WalkerCalibration()  # wheel 0.203 m: r_wheel = 0.1015 m
OFF, FULL = CAL.brake.torque_off_nm, CAL.brake.torque_max_nm
ALPHA = 46 / 64  # α r_b = 46/64 · 0.32 = 0.23 exactly


def wall_ahead(distance_from_camera, y_from=-1.0, y_to=1.0):
    y = np.arange(y_from, y_to + 1e-9, 0.05)
    return np.column_stack([np.full_like(y, CAL.depth_mount.x + distance_from_camera), y])


def blocked_left(distance):
    """A wall across the path plus clutter on the left: the free side is the right."""
    return np.vstack([wall_ahead(distance), [[0.41 + 0.6, 0.5], [0.41 + 0.5, 0.4]]])


# -- the equations ------------------------------------------------------------------------


def test_eq_5_11_handle_forces_hand_computed():
    # v = 1, φ̇ = 0.46, F_bL = 2, F_bR = 4.3, D = 16, Dφ = 7, α = 46/64, r_b = 0.32
    # F_hL + F_hR = 1·16 + 6.3 = 22.3
    # F_hR − F_hL = 0.46·7 / 0.23 + 2.3 / (46/64) = 14 + 3.2 = 17.2
    left, right = handle_forces(1.0, 0.46, 2.0, 4.3, 16.0, 7.0, ALPHA, 0.32)
    assert left == pytest.approx(2.55)
    assert right == pytest.approx(19.75)


def test_eq_5_11_with_inertial_terms():
    # m v̇ = 31.5·0.32 = 10.08 N more push; I φ̈ = 8.69·0.5 = 4.345 N·m more yaw torque,
    # i.e. 4.345 / (r_b α) = 4.345 / 0.23 = 18.891304 N more difference
    left, right = handle_forces_dynamic(
        1.0, 0.46, 0.32, 0.5, 2.0, 4.3, 16, 7, ALPHA, 0.32, 31.5, 8.69
    )
    s, d = 22.3 + 10.08, 17.2 + 4.345 / 0.23
    assert left == pytest.approx(0.5 * (s - d))
    assert right == pytest.approx(0.5 * (s + d))


def test_eq_5_14_brake_forces_hand_computed():
    # F_hL = 10, F_hR = 20, v_d = 0.5, φ̇_d = 0.23, D = 16, Dφ = 6.4, r_b = 0.32
    # −v_d D = −8; F_hL + F_hR = 30; φ̇_d Dφ / r_b = 4.6; α (F_hR − F_hL) = 7.1875
    left, right = brake_forces(0.5, 0.23, 10.0, 20.0, 16.0, 6.4, ALPHA, 0.32)
    assert left == pytest.approx(0.5 * (-8 + 30 + 4.6 - 7.1875))  # 9.70625
    assert right == pytest.approx(0.5 * (-8 + 30 - 4.6 + 7.1875))  # 12.29375


def test_eq_5_11_and_5_14_are_inverses():
    f_hl, f_hr = handle_forces(0.7, -0.3, 3.0, 1.0, 16.0, 7.0, ALPHA, 0.32)
    assert brake_forces(0.7, -0.3, f_hl, f_hr, 16.0, 7.0, ALPHA, 0.32) == pytest.approx((3.0, 1.0))


def test_eq_5_16_turn_left_symmetric_push():
    # R = 2, F_h = 15 each, F_min = 0.5, D = 16, Dφ/r_b = 6.4/0.32 = 20, R D = 32
    # φ̇_d = −(2·0.5 − 30 − 0) / (20 + 32) = 29/52
    w = least_braking_yaw_rate(2.0, 15.0, 15.0, 0.5, 16.0, 6.4, ALPHA, 0.32)
    assert w == pytest.approx(29 / 52)
    left, right = least_braking_forces(2.0, 15.0, 15.0, 0.5, 40.0, 16.0, 6.4, ALPHA, 0.32)
    # inner (left) from 5.14 with v_d = 2·29/52: ½[−(58/52)·16 + 30 + (29/52)·20 − 0]
    assert left == pytest.approx(0.5 * (-(58 / 52) * 16 + 30 + (29 / 52) * 20))  # 11.653846
    assert right == pytest.approx(0.5)


def test_eq_5_16_turn_right_asymmetric_push_and_clamp():
    # R = −1, F_hL = 10, F_hR = 20, F_min = 0.5; α (F_hR − F_hL) = 7.1875
    # φ̇_d = (1 − 30 + 7.1875) / (20 + 16) = −21.8125/36; v_d = R φ̇_d = 21.8125/36
    w = least_braking_yaw_rate(-1.0, 10.0, 20.0, 0.5, 16.0, 6.4, ALPHA, 0.32)
    assert w == pytest.approx(-21.8125 / 36)
    v_d = 21.8125 / 36
    inner = 0.5 * (-v_d * 16 + 30 - w * 20 + 7.1875)  # 19.805556
    left, right = least_braking_forces(-1.0, 10.0, 20.0, 0.5, 40.0, 16.0, 6.4, ALPHA, 0.32)
    assert (left, right) == pytest.approx((0.5, inner))
    # the inner brake cannot exceed its maximum
    assert least_braking_forces(-1.0, 10.0, 20.0, 0.5, 15.0, 16.0, 6.4, ALPHA, 0.32) == (0.5, 15.0)
    # nor go below its minimum (the user already turns tighter than asked)
    assert least_braking_forces(-5.0, 20.0, 5.0, 0.5, 40.0, 16.0, 6.4, ALPHA, 0.32) == (0.5, 0.5)


@pytest.mark.parametrize("radius", [1.0, 2.5, -1.3, -4.0])
def test_least_braking_solution_gives_the_radius_at_steady_state(radius):
    """Independent check through eq 5.9 of the simulator's dynamics module."""
    p = WalkerParams(damping=16.0, yaw_damping=7.0)
    f = least_braking_forces(radius, 14.0, 17.0, 0.67, 200.0, 16.0, 7.0, p.alpha, p.half_track_m)
    assert steady_state_radius(p, 14.0, 17.0, *f) == pytest.approx(radius)
    # one-sided: the outer brake stays at its minimum
    assert min(f) == pytest.approx(0.67)


def test_straight_on_releases_both():
    assert least_braking_forces(math.inf, 10, 20, 0.5, 40, 16, 7, ALPHA, 0.32) == (0.5, 0.5)
    with pytest.raises(ValueError):
        least_braking_yaw_rate(0.0, 10, 20, 0.5, 16, 7, ALPHA, 0.32)


# -- the controller -----------------------------------------------------------------------


def test_controller_hand_computed_turn_right():
    """Wall 0.8 m ahead of the camera, left blocked: R_d = −(0.8 + 0.5) = −1.3 m.

    v = 0.9, φ̇ = 0, both brakes at the residual 0.068 N·m: F_b = 0.068 / 0.1015 N each.
    5.11 (first tick: no v̇, φ̈): F_hL = F_hR = ½ (0.9·16 + 2 F_b).
    5.16, R < 0: φ̇_d = (2 F_b − (F_hL + F_hR) + 0) / (7/0.32 + 1.3·16) = −14.4 / 42.675.
    5.14: F_bR = ½ [−R φ̇_d·16 + (F_hL + F_hR) − φ̇_d·7/0.32 + 0]; τ = F_bR · 0.1015.
    """
    ctl = create("closed-loop", CAL)
    fb = 0.068 / 0.1015
    s = 0.9 * 16 + 2 * fb
    w = (2 * fb - s) / (7 / 0.32 + 1.3 * 16)
    assert w == pytest.approx(-14.4 / 42.675)
    f_br = 0.5 * (-(-1.3 * w) * 16 + s - w * 7 / 0.32)
    inp = ControlInput(1.0, blocked_left(0.8), np.zeros(3), 0.9, 0.0, brake_nm=(OFF, OFF))
    cmd = ctl.command(inp)
    assert ctl.last_radius == pytest.approx(-1.3)
    assert ctl.last_handle == pytest.approx((s / 2, s / 2))
    assert cmd.left_nm == pytest.approx(OFF)
    assert cmd.right_nm == pytest.approx(f_br * 0.1015)  # ≈ 0.817 N·m
    assert cmd.source == "closed-loop"


def test_mirrored_scene_mirrors_the_command():
    a = create("closed-loop", CAL).command(
        ControlInput(0.0, blocked_left(0.8), np.zeros(3), 0.9, 0.1, brake_nm=(0.5, 0.2))
    )
    mirrored = blocked_left(0.8) * np.array([1.0, -1.0])
    b = create("closed-loop", CAL).command(
        ControlInput(0.0, mirrored, np.zeros(3), 0.9, -0.1, brake_nm=(0.2, 0.5))
    )
    assert (a.left_nm, a.right_nm) == pytest.approx((b.right_nm, b.left_nm))
    assert a.right_nm > OFF  # turning right


def test_applied_brake_torques_enter_the_estimate_through_the_wheel_radius():
    ctl = create("closed-loop", CAL)
    ctl.command(ControlInput(0.0, np.zeros((0, 2)), np.zeros(3), 0.9, 0.0, brake_nm=(2.03, OFF)))
    # 5.11: F_bL = 2.03 / 0.1015 = 20 N (not 2.03 / 0.32), F_bR = 0.068 / 0.1015
    fbl, fbr = 20.0, 0.068 / 0.1015
    s = 0.9 * 16 + fbl + fbr
    d = (fbr - fbl) / ALPHA
    assert ctl.last_handle == pytest.approx((0.5 * (s - d), 0.5 * (s + d)))


def test_unknown_applied_torques_fall_back_to_the_last_command():
    pts = blocked_left(0.8)
    a = create("closed-loop", CAL)
    first = a.command(ControlInput(0.0, pts, np.zeros(3), 0.9, 0.0, brake_nm=(OFF, OFF)))
    second = a.command(ControlInput(0.1, pts, np.zeros(3), 0.9, -0.1))
    b = create("closed-loop", CAL)
    b.command(ControlInput(0.0, pts, np.zeros(3), 0.9, 0.0, brake_nm=(OFF, OFF)))
    explicit = b.command(
        ControlInput(0.1, pts, np.zeros(3), 0.9, -0.1, brake_nm=(first.left_nm, first.right_nm))
    )
    assert (second.left_nm, second.right_nm) == (explicit.left_nm, explicit.right_nm)


def test_regimes_beyond_d_max_below_d_min_and_not_moving():
    ctl = create("closed-loop", CAL)
    cmd = ctl.command(ControlInput(0.0, blocked_left(1.4), np.zeros(3), 0.9, 0.0))
    assert (cmd.left_nm, cmd.right_nm) == (OFF, OFF)
    assert math.isinf(ctl.last_radius)
    # below d_min: pivot about the inner (right) wheel, inner brake full
    cmd = ctl.command(ControlInput(0.1, blocked_left(0.4), np.zeros(3), 0.9, 0.0))
    assert (cmd.left_nm, cmd.right_nm) == (OFF, FULL)
    for v in (0.0, -0.4):
        cmd = ctl.command(ControlInput(0.2, blocked_left(0.7), np.zeros(3), v, 0.0))
        assert (cmd.left_nm, cmd.right_nm) == (OFF, OFF)


def test_thesis_form_needs_no_inertia_or_filter():
    """The default (mass = inertia = 0, no filter): the estimate is 5.11 on every tick,
    whatever the previous ones were."""
    cfg = ClosedLoopConfig()
    assert (cfg.mass_kg, cfg.yaw_inertia, cfg.handle_filter_s) == (0.0, 0.0, 0.0)
    ctl = ClosedLoop(cfg, CAL)
    ctl.command(ControlInput(0.0, np.zeros((0, 2)), np.zeros(3), 0.3, 0.5, brake_nm=(OFF, OFF)))
    ctl.command(ControlInput(0.1, np.zeros((0, 2)), np.zeros(3), 1.0, 0.46, brake_nm=(1.0, 2.0)))
    fb = (1.0 / 0.1015, 2.0 / 0.1015)
    assert ctl.last_handle == pytest.approx(handle_forces(1.0, 0.46, *fb, 16.0, 7.0, ALPHA, 0.32))
    # the settling form filters: the same second tick gives a different (smoothed) estimate
    settling = ClosedLoopConfig(mass_kg=31.5, yaw_inertia=8.69, handle_filter_s=0.3)
    d = create("closed-loop", CAL, settling)
    d.command(ControlInput(0.0, np.zeros((0, 2)), np.zeros(3), 0.3, 0.5, brake_nm=(OFF, OFF)))
    d.command(ControlInput(0.1, np.zeros((0, 2)), np.zeros(3), 1.0, 0.46, brake_nm=(1.0, 2.0)))
    assert d.last_handle != pytest.approx(ctl.last_handle)


def test_config_validation_and_registry():
    assert {"closed-loop", "potential-field", "open-loop", "none"} <= set(CONTROLLERS.names())
    assert ClosedLoopConfig().D == 16.0 and ClosedLoopConfig().D_phi == 7.0
    assert ClosedLoopConfig().alpha == ALPHA and ClosedLoopConfig().r_b == 0.32
    with pytest.raises(ValueError, match="d_min < d_max"):
        ClosedLoopConfig(d_min_m=1.3)
    with pytest.raises(ValueError, match="D_phi"):
        replace(ClosedLoopConfig(), D_phi=0.0)
