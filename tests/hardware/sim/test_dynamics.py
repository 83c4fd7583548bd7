"""Walker dynamics against the thesis's steady-state equations and basic physics."""

import math

import numpy as np
import pytest

from hardware.sim.dynamics import Brakes, WalkerParams, WalkerState, steady_state_radius, step
from hardware.sim.slip import Encoders, SlipModel, surface_coefficient


def run(params, handle_l, handle_r, torque_l, torque_r, seconds=40.0, dt=0.005):
    s = WalkerState()
    brakes = Brakes(params)
    brakes.set_command(torque_l, torque_r)
    for _ in range(int(seconds / dt)):
        brakes.step(dt)
        wl, wr = s.wheel_speeds(params.half_track_m)
        fl, fr = brakes.ground_forces(wl, wr)
        step(s, params, handle_l, handle_r, fl, fr, dt)
    return s, brakes


@pytest.mark.parametrize(
    ("handle", "torques"),
    [((20.0, 20.0), (0.068, 1.0)), ((15.0, 25.0), (2.0, 0.068)), ((30.0, 25.0), (0.5, 1.5))],
)
def test_steady_state_turn_radius_matches_eq_5_9(handle, torques):
    p = WalkerParams()
    s, _ = run(p, *handle, *torques)
    wl, wr = s.wheel_speeds(p.half_track_m)
    assert wl > 0.1 and wr > 0.1  # both wheels rolling forward: full Coulomb brake force
    fl, fr = (t / p.wheel_radius_m for t in torques)
    expected = steady_state_radius(p, *handle, fl, fr)
    assert s.v / s.omega == pytest.approx(expected, rel=0.05)
    # and the steady speed of eq 5.7
    assert s.v == pytest.approx((sum(handle) - fl - fr) / p.damping, rel=1e-3)


def test_straight_push_without_brakes_stays_straight():
    p = WalkerParams()
    s, _ = run(p, 12.0, 12.0, 0.068, 0.068, seconds=10.0)
    assert abs(s.phi) < 1e-9 and abs(s.y) < 1e-9
    assert s.x > 5.0


def test_braking_one_wheel_turns_toward_it():
    p = WalkerParams()
    s, _ = run(p, 20.0, 20.0, 2.0, 0.068, seconds=3.0)
    assert s.omega > 0.1  # left brake → counter-clockwise (left) turn


def test_brake_lag_reaches_63_percent_after_one_time_constant():
    p = WalkerParams()
    b = Brakes(p)
    b.set_command(3.0, 0.068)
    dt = 0.001
    for _ in range(round(p.brake_time_constant_s / dt)):
        b.step(dt)
    frac = (b.torque[0] - 0.068) / (3.0 - 0.068)
    assert frac == pytest.approx(1 - math.exp(-1), abs=0.01)


def test_brake_command_is_clamped_to_torque_range():
    b = Brakes(WalkerParams())
    b.set_command(10.0, -1.0)
    assert b.command == [3.95, 0.068]


def test_coast_down_follows_exponential_decay():
    """Eq 6.2 with both brakes off: v(t) = −F_off/D (1 − e^{−Dt/m}) + v0 e^{−Dt/m}."""
    p = WalkerParams()
    s = WalkerState(v=1.0)
    b = Brakes(p)
    dt = 0.0005
    for _ in range(int(1.0 / dt)):
        wl, wr = s.wheel_speeds(p.half_track_m)
        fl, fr = b.ground_forces(wl, wr)
        step(s, p, 0.0, 0.0, fl, fr, dt)
    f_off = 2 * p.brake_torque_off_nm / p.wheel_radius_m
    decay = math.exp(-p.damping * 1.0 / p.mass_kg)
    assert s.v == pytest.approx(-f_off / p.damping * (1 - decay) + decay, rel=0.01)


def test_slip_grows_with_brake_force_and_surface():
    rng = np.random.default_rng(0)
    fmax = 3.95 / 0.102
    clean = SlipModel("clean", fmax, rng, variability=0.0)
    dusty = SlipModel("dusty", fmax, np.random.default_rng(0), variability=0.0)
    assert clean.step(0.005, (0.6 * fmax, 0.0)) == pytest.approx((0.6 * 0.02, 0.0))
    assert dusty.step(0.005, (0.6 * fmax, 0.0)) == pytest.approx((0.6 * 0.12, 0.0))
    assert surface_coefficient("0.3") == 0.3
    with pytest.raises(ValueError, match="valid: clean, dusty"):
        surface_coefficient("ice")


def test_encoders_count_whole_revolutions():
    enc = Encoders(0.204, 256)
    enc.roll(math.pi * 0.204, -math.pi * 0.204 / 2, (0.0, 0.0))
    assert enc.counts() == (256, -128)
    enc.roll(math.pi * 0.204, 0.0, (0.5, 0.0))  # half of it skidded: half a revolution
    assert enc.counts() == (384, -128)
