"""The safety layer: forward-only, stale-data ramp, clamping and rate limiting."""

import math

import numpy as np
import pytest

from control.base import ControlInput, Controller
from control.safety import SafeController, SafetyConfig, data_ages
from hardware.calibration import WalkerCalibration
from hardware.messages import BrakeCommand

CAL = WalkerCalibration()
OFF, FULL = CAL.brake.torque_off_nm, CAL.brake.torque_max_nm
NO_MAP = np.zeros((0, 2))


class Fixed(Controller):
    """Commands whatever it is told to (set .left/.right between ticks)."""

    def __init__(self, left, right):
        self.left, self.right = left, right
        self.calls = 0

    def command(self, inp):
        self.calls += 1
        return BrakeCommand(inp.t, self.left, self.right, "fixed")


def tick(safe, t, v=0.8, **ages):
    return safe.command(ControlInput(t, NO_MAP, np.zeros(3), v, 0.0, **ages))


def fresh(t):
    return {"pose_t": t, "map_t": t, "sensor_t": t}


def test_passes_commands_through_when_fresh_and_moving():
    safe = SafeController(Fixed(1.2, 2.5), CAL)
    cmd = tick(safe, 0.1, **fresh(0.1))
    assert (cmd.left_nm, cmd.right_nm, cmd.source, cmd.t) == (1.2, 2.5, "fixed", 0.1)


@pytest.mark.parametrize("v", [0.05, 0.0, -0.4, math.nan])
def test_brakes_only_while_moving_forward(v):
    safe = SafeController(Fixed(FULL, FULL), CAL)
    cmd = tick(safe, 0.1, v=v, **fresh(0.1))
    assert (cmd.left_nm, cmd.right_nm) == (OFF, OFF)
    assert safe.controller.calls == 1  # the controller still runs


def test_clamps_to_the_brake_limits_and_replaces_non_finite():
    for raw, expected in [((10.0, -1.0), (FULL, OFF)), ((math.nan, math.inf), (OFF, OFF))]:
        safe = SafeController(Fixed(*raw), CAL)
        cmd = tick(safe, 0.1, **fresh(0.1))
        assert (cmd.left_nm, cmd.right_nm) == expected


def test_rate_limit_in_both_directions():
    cfg = SafetyConfig(rate_limit_nm_per_s=5.0)
    inner = Fixed(OFF, OFF)
    safe = SafeController(inner, CAL, cfg)
    tick(safe, 0.0, **fresh(0.0))
    inner.left = FULL
    out = [tick(safe, 0.1 * k, **fresh(0.1 * k)).left_nm for k in range(1, 11)]
    # 5 N·m/s × 0.1 s = 0.5 N·m per tick: 0.568, 1.068, ... until full torque
    expected = [min(OFF + 0.5 * k, FULL) for k in range(1, 11)]
    assert out == pytest.approx(expected)
    inner.left = OFF
    down = tick(safe, 1.1, **fresh(1.1)).left_nm
    assert down == pytest.approx(FULL - 0.5)


def test_default_rate_limit_allows_a_full_swing_per_10hz_tick():
    inner = Fixed(OFF, FULL)
    safe = SafeController(inner, CAL)
    tick(safe, 0.0, v=0.0, **fresh(0.0))  # standing: both off
    cmd = tick(safe, 0.1, **fresh(0.1))
    assert (cmd.left_nm, cmd.right_nm) == (OFF, FULL)
    inner.left, inner.right = FULL, OFF
    cmd = tick(safe, 0.2, **fresh(0.2))
    assert (cmd.left_nm, cmd.right_nm) == (FULL, OFF)


@pytest.mark.parametrize("stream", ["pose_t", "map_t", "sensor_t"])
def test_stale_data_ramps_to_the_residual_torque(stream):
    cfg = SafetyConfig(max_data_age_s=0.3, ramp_time_s=0.5)
    safe = SafeController(Fixed(3.0, OFF), CAL, cfg)
    for k in range(1, 11):  # fresh up to t = 1.0
        assert tick(safe, 0.1 * k, **fresh(0.1 * k)).left_nm == 3.0
    # from now on `stream` stops at t = 1.0; the others stay fresh
    times = [1.15, 1.25, 1.35, 1.45, 1.55, 1.65, 1.75, 1.85, 1.95]
    out = []
    for t in times:
        ages = fresh(t)
        ages[stream] = 1.0
        out.append(tick(safe, t, **ages).left_nm)
    # ages 0.15, 0.25 are fresh; 0.35 (t = 1.35) starts the ramp from 3.0 over 0.5 s
    keep = [1.0, 1.0, 1.0, 0.8, 0.6, 0.4, 0.2, 0.0, 0.0]
    assert out == pytest.approx([OFF + (3.0 - OFF) * k for k in keep])
    assert safe.last_stale == (stream.removesuffix("_t"),)
    # fresh data again: control returns (at the default rate limit, at once)
    assert tick(safe, 2.05, **fresh(2.05)).left_nm == 3.0
    assert safe.last_stale == ()


def test_never_received_is_stale_and_unreported_is_not_checked():
    safe = SafeController(Fixed(2.0, 2.0), CAL)
    cmd = tick(safe, 0.1, pose_t=0.1, map_t=-math.inf, sensor_t=0.1)
    assert (cmd.left_nm, cmd.right_nm) == (OFF, OFF)
    assert math.isinf(
        data_ages(ControlInput(0.1, NO_MAP, np.zeros(3), 0, 0, map_t=-math.inf))["map"]
    )
    # an input that reports no times at all (NaN defaults) is not held back
    safe = SafeController(Fixed(2.0, 2.0), CAL)
    cmd = tick(safe, 0.1)
    assert (cmd.left_nm, cmd.right_nm) == (2.0, 2.0)


def test_config_validation():
    with pytest.raises(ValueError, match="rate_limit"):
        SafetyConfig(rate_limit_nm_per_s=0.0)
    with pytest.raises(ValueError, match="max_data_age"):
        SafetyConfig(max_data_age_s=-1.0)
