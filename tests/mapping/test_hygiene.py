"""Map hygiene: periodic reset, decay and gating of what is mapped."""

import math

import numpy as np
import pytest

from experiments.pipeline import Pipeline
from hardware.messages import BrakeCommand, DepthFrame
from hardware.sim.simulator import SimConfig, Simulator
from hardware.sim.user import ConstantPush
from hardware.sim.world import load_world
from mapping.grid import GridConfig, OccupancyGrid, ViewCountGrid
from mapping.hygiene import HygieneConfig, MapHygiene
from mapping.mapper import MapperConfig
from mapping.observation import PlanarObservation
from slam.base import create


def test_decay_fades_log_odds_and_only_log_odds() -> None:
    grid = OccupancyGrid(GridConfig())
    ends = np.array([[1.0, 0.0], [1.0, 0.5]])
    obs = PlanarObservation(np.zeros(2), 0.0, ends, ends)
    grid.integrate(obs.in_world(np.zeros(3)), centre_xy=np.zeros(2))
    before = grid.log_odds.copy()
    assert np.abs(before).max() > 0
    grid.decay(0.25)
    np.testing.assert_allclose(grid.log_odds, 0.25 * before, rtol=1e-6)
    with pytest.raises(ValueError, match="factor"):
        grid.decay(0.0)
    with pytest.raises(ValueError, match="decay"):
        ViewCountGrid(GridConfig(model="view-count")).decay(0.5)


def test_reset_decay_and_gates_follow_their_settings() -> None:
    h = MapHygiene(HygieneConfig(reset_every_s=10.0, decay_half_life_s=2.0))
    assert [h.due_reset(t) for t in (3.0, 12.9, 13.0, 22.0, 23.0)] == [
        False,
        False,
        True,
        False,
        True,
    ]
    assert h.counts["resets"] == 2
    assert h.decay_factor(0.0) == 1.0
    assert h.decay_factor(2.0) == pytest.approx(0.5)
    assert h.decay_factor(3.0) == pytest.approx(0.5**0.5)
    # Heading σ gate.
    g = MapHygiene(HygieneConfig(gate_heading_sigma_rad=0.1))
    assert g.admit(0.0, np.zeros(3), np.diag([0.0, 0.0, 0.09**2]))
    assert not g.admit(0.1, np.zeros(3), np.diag([0.0, 0.0, 0.11**2]))
    # Braked-turn gate: turning at 1 rad/s with a brake on is not mapped; without it is.
    b = MapHygiene(HygieneConfig(gate_braked_turn=True))
    cov = np.zeros((3, 3))
    assert b.admit(0.0, np.zeros(3), cov)
    assert b.admit(0.1, np.array([0.0, 0.0, 0.1]), cov)  # turning, brakes released
    b.brake_levels = (0.3, 0.0)
    assert not b.admit(0.2, np.array([0.0, 0.0, 0.2]), cov)
    assert b.admit(0.3, np.array([0.0, 0.0, 0.2]), cov)  # braked, not turning
    assert b.counts["gated_braked_turn"] == 1
    with pytest.raises(ValueError, match="reset_every_s"):
        HygieneConfig(reset_every_s=0.0)
    assert not HygieneConfig().active


def braked_turn(seconds: float = 6.0) -> list:
    """A walker pushed harder on its left handle with its right brake on: a braked
    right turn in the thesis course, with depth frames."""
    sim = Simulator(load_world("thesis-course"), SimConfig(seed=1), user=ConstantPush(14.0, 6.0))
    cmd = BrakeCommand(0.0, 0.068, 1.5)
    sim.send(cmd)
    return [cmd, *sim.poll(seconds)]


def mapped(msgs: list, hygiene: HygieneConfig) -> Pipeline:
    cal = SimConfig().calibration()
    pipe = Pipeline(
        create("dead-reckoning", cal, initial_pose=load_world("thesis-course").start_pose),
        cal,
        MapperConfig(hygiene=hygiene),
        reference_map=False,
    )
    pipe.run(msgs)
    return pipe


def test_the_pipeline_gates_braked_turns_resets_and_fades() -> None:
    msgs = braked_turn()
    frames = sum(isinstance(m, DepthFrame) for m in msgs)
    plain = mapped(msgs, HygieneConfig())
    gated = mapped(msgs, HygieneConfig(gate_braked_turn=True))
    assert plain.hygiene is None
    n = gated.hygiene.counts["gated_braked_turn"]
    assert 5 < n < frames  # the frames while it turns faster than 0.15 rad/s
    assert len(gated.mapper.occupied_xy()) < len(plain.mapper.occupied_xy())
    released = mapped(msgs[1:], HygieneConfig(gate_braked_turn=True))  # no brake command
    assert released.hygiene.counts["gated_braked_turn"] == 0
    reset = mapped(msgs, HygieneConfig(reset_every_s=2.0))
    assert reset.hygiene.counts["resets"] == math.floor(6.0 / 2.0)
    assert len(reset.mapper.occupied_xy()) < len(plain.mapper.occupied_xy())
    faded = mapped(msgs, HygieneConfig(decay_half_life_s=0.5))
    assert np.abs(faded.mapper.grid.log_odds).sum() < np.abs(plain.mapper.grid.log_odds).sum()
