"""Synthetic slip in velocity odometry (MRCLAM `slip=K`)."""

import numpy as np
import pytest

from hardware.calibration import BrakeCalibration
from hardware.datasets.synthetic_slip import inject_slip

TRACK = 0.258


def odometry() -> np.ndarray:
    """10 s at 50 Hz: straight, a left turn at 0.25 rad/s, a right turn at 0.5 rad/s."""
    t = np.arange(0.0, 10.0, 0.02)
    w = np.where(t < 3, 0.0, np.where(t < 6, 0.25, -0.5))
    return np.column_stack([t, np.full(len(t), 0.2), w])


def test_no_slip_changes_nothing_and_bad_values_are_refused() -> None:
    odo = odometry()
    out = inject_slip(odo, 0.0, TRACK, seed=0)
    np.testing.assert_allclose(out.odometry, odo, atol=1e-15)
    with pytest.raises(ValueError, match="slip"):
        inject_slip(odo, 0.97, TRACK, seed=0)


def test_the_inner_wheel_of_each_turn_under_reports_by_k_times_its_level() -> None:
    odo = odometry()
    k = 0.3
    out = inject_slip(odo, k, TRACK, seed=3)
    t, v, w = odo.T
    vl, vr = v - w * TRACK / 2, v + w * TRACK / 2
    sl = out.odometry[:, 1] - out.odometry[:, 2] * TRACK / 2
    sr = out.odometry[:, 1] + out.odometry[:, 2] * TRACK / 2
    straight, left, right = t < 3, (t >= 3) & (t < 6), t >= 6
    np.testing.assert_allclose(out.odometry[straight], odo[straight])
    # left turn (ω > 0): the left wheel is braked at level 0.5, the right one rolls free
    np.testing.assert_allclose(out.levels[left], [[0.5, 0.0]] * left.sum())
    np.testing.assert_allclose(sr[left], vr[left])
    ratio = 1.0 - sl[left] / vl[left]
    np.testing.assert_allclose(ratio, out.ratio[left, 0])
    assert 0.5 * k * 0.5 < ratio.mean() < 1.5 * k * 0.5  # s = k · level · m(t), E[m] = 1
    # the right turn at full level: the right wheel slips
    np.testing.assert_allclose(out.levels[right], [[0.0, 1.0]] * right.sum())
    assert np.all(sr[right] <= vr[right] + 1e-12) and np.allclose(sl[right], vl[right])
    # the odometry over-turns toward the braked side, as on the walker
    assert np.sum(out.odometry[left, 2]) > np.sum(w[left])
    # brake commands where the level changes, the brake's own torques
    cmds = out.brake_commands(BrakeCalibration())
    assert [round(c.t, 2) for c in cmds] == [0.0, 3.0, 6.0]
    assert cmds[1].left_nm == pytest.approx(0.068 + 0.5 * (3.95 - 0.068))
    assert cmds[2].right_nm == pytest.approx(3.95) and cmds[2].left_nm == pytest.approx(0.068)
    summary = out.summary(k)
    assert summary["k_wheel"] == [k, k]
    assert all(0.5 * k < e < 1.5 * k for e in summary["k_effective"])
