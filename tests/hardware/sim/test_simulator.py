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
