"""Per-wheel slip in the simulator: each wheel's coefficient, and the true effective k of
a run (what the localizers' slip estimates are judged against)."""

import numpy as np
import pytest

from hardware.calibration import BrakeCalibration
from hardware.errors import ConfigError
from hardware.messages import BrakeCommand
from hardware.sim.simulator import SimConfig, Simulator
from hardware.sim.slip import SlipModel, SlipTruth, wheel_slip_coefficients
from hardware.sim.user import ConstantPush
from hardware.sim.world import World


def test_each_wheel_slips_by_its_own_coefficient():
    fmax = 3.95 / 0.102
    model = SlipModel(
        "dusty", fmax, np.random.default_rng(0), variability=0.0, wheel_scale=(1.5, 0.5)
    )
    assert model.k_wheel == pytest.approx((0.18, 0.06))
    assert model.step(0.005, (0.4 * fmax, 0.4 * fmax)) == pytest.approx((0.4 * 0.18, 0.4 * 0.06))
    # the default is the surface's coefficient on both wheels, exactly
    assert SlipModel("dusty", fmax, np.random.default_rng(0)).k_wheel == (0.12, 0.12)


@pytest.mark.parametrize(
    ("scale", "needle"),
    [((-1.0, 1.0), "slip_scale left -1.0"), ((1.0, 9.0), "slip_scale right 9.0"), ((1.0,), "two")],
)
def test_bad_wheel_scales_are_config_errors(scale, needle):
    with pytest.raises(ConfigError, match=needle):
        wheel_slip_coefficients("dusty", scale)
    with pytest.raises(ConfigError, match=needle):
        SimConfig(slip_scale=scale)


def test_effective_k_is_the_weighted_least_squares_slope():
    truth = SlipTruth()
    rng = np.random.default_rng(1)
    for _ in range(500):
        level = rng.uniform(0.0, 1.0, 2)
        ground = rng.uniform(0.0, 0.004, 2)
        truth.add(tuple(ground), (0.1 * level[0], 0.03 * level[1]), tuple(level))
    truth.add((0.003, 0.003), (0.05, 0.05), (0.0, 0.0))  # unbraked slip counts in neither sum
    assert truth.effective_k() == pytest.approx((0.1, 0.03))
    assert SlipTruth().effective_k() == (None, None)


def test_a_run_reports_each_wheels_true_slip():
    """Both brakes held at half level while the walker is pushed straight across an empty
    floor: the left tyre (scale 1.5) slips 1.5 times the right; per unit level, slip is
    k·(τ/τ_max)/level (the residual torque) times the log-normal factor's mean over the
    run (~1)."""
    world = World("empty", (-100.0, 100.0, -100.0, 100.0), (), (), np.zeros((2, 2)), (0, 0, 0))
    cfg = SimConfig(seed=3, duration_s=30.0, slip_scale=(1.5, 1.0))
    sim = Simulator(world, cfg, user=ConstantPush(60.0, 60.0))
    brake = BrakeCalibration()
    torque = brake.torque_off_nm + 0.5 * (brake.torque_max_nm - brake.torque_off_nm)
    sim.send(BrakeCommand(0.0, torque, torque))
    list(sim.messages())
    out = sim.slip_summary()
    assert out["k_wheel"] == pytest.approx([0.18, 0.12])
    per_level = torque / brake.torque_max_nm / 0.5
    k_left, k_right = out["k_effective"]
    assert k_left == pytest.approx(0.18 * per_level, rel=0.1)
    assert k_right == pytest.approx(0.12 * per_level, rel=0.1)
    assert k_left / k_right == pytest.approx(1.5, rel=0.1)
    assert min(out["braked_distance_m"]) > 50.0
