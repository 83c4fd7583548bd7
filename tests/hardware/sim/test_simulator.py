"""The simulator as a whole: sources, determinism, and its collision broad phase."""

import numpy as np
import pytest

import hardware.sim.simulator as simulator
from hardware.messages import Collision, DepthFrame, EncoderTicks, GroundTruthPose, TagDetections
from hardware.sim.simulator import SimConfig, Simulator
from hardware.sim.world import load_world


def run(seconds, seed=4, **cfg):
    sim = Simulator(load_world("thesis-course"), SimConfig(seed=seed, **cfg))
    msgs = sim.poll(seconds)
    return sim, msgs


def truth(msgs):
    return np.array([(m.t, m.x, m.y, m.theta) for m in msgs if isinstance(m, GroundTruthPose)])


def test_message_rates_and_order():
    _, msgs = run(2.0)
    times = [m.t for m in msgs]
    assert times == sorted(times)
    count = lambda typ: sum(isinstance(m, typ) for m in msgs)  # noqa: E731
    assert count(GroundTruthPose) == 101 and count(EncoderTicks) == 101
    assert count(DepthFrame) == 21 and count(TagDetections) == 21


def test_same_seed_same_trial_and_other_seed_differs():
    _, a = run(20.0)
    _, b = run(20.0)
    _, c = run(20.0, seed=5)
    assert np.array_equal(truth(a), truth(b))
    assert not np.array_equal(truth(a), truth(c))


def test_broad_phase_changes_nothing(monkeypatch):
    """Skipping contact checks while the walker's clearance lasts must give the very same
    trial as checking every step (a user who drifts a lot, so there are collisions)."""
    from dataclasses import replace

    from hardware.sim.user import UserParams

    user = replace(UserParams(), heading_drift_rad_per_sqrt_m=0.25)
    _, fast = run(40.0, seed=1, user=user)
    monkeypatch.setattr(simulator, "CLEARANCE_HORIZON_M", 0.0)
    _, every_step = run(40.0, seed=1, user=user)
    assert np.array_equal(truth(fast), truth(every_step))
    hits = [m for m in fast if isinstance(m, Collision)]
    assert hits == [m for m in every_step if isinstance(m, Collision)]
    assert len(hits) >= 1


def test_bad_rates_are_rejected():
    with pytest.raises(ValueError, match="must divide"):
        SimConfig(depth_rate_hz=7)


def test_unequal_true_wheels_count_apart_and_the_default_is_equal():
    """wheel_diameter_ratio_error makes the true right wheel larger by that ratio (the
    mean kept): pushed straight, it turns fewer times; 0 gives both exactly the mean."""
    from hardware.sim.user import ConstantPush

    d = SimConfig().walker.wheel_diameter_m
    assert SimConfig().true_wheel_diameters_m() == (d, d)
    cfg = SimConfig(seed=2, wheel_diameter_ratio_error=0.01, surface=0.0)
    left, right = cfg.true_wheel_diameters_m()
    assert right / left == pytest.approx(1.01, rel=1e-12)
    assert (left + right) / 2 == pytest.approx(d, rel=1e-15)
    assert cfg.calibration().wheel_diameter_ratio == 1.0  # the software does not know
    sim = Simulator(load_world("corner"), cfg, user=ConstantPush(20.0, 20.0))
    msgs = sim.poll(4.0)
    ticks, gt = [m for m in msgs if isinstance(m, EncoderTicks)], truth(msgs)
    assert abs(gt[-1, 3]) < 1e-9  # the walker itself went straight
    assert ticks[-1].left / ticks[-1].right == pytest.approx(1.01, abs=2 / ticks[-1].right)
    with pytest.raises(ValueError, match="wheel_diameter_ratio_error"):
        SimConfig(wheel_diameter_ratio_error=-1.0)


def test_a_sighted_user_knows_where_the_walker_is():
    """The `umbmark` course is walked by a sighted helper following tape: their sense of
    position is the truth, however far they walk."""
    sim = Simulator(load_world("umbmark"), SimConfig(seed=3, surface="clean"))
    assert sim.user.p.sighted and sim.user.p.lookahead_m == 0.6
    sim.poll(30.0)
    assert sim.user.progress_m > 10.0  # round corners
    sim.user.forces(sim.state, sim.dt)  # what the user does at each step: feel, push
    assert np.array_equal(sim.user.belief, sim.pose())
