"""The simulated MEMS gyro: its noise, bias and scale as specified, its samples integrate
to the true turn, and switching it on changes no other sensor of a trial."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from hardware.messages import BrakeCommand, DepthFrame, EncoderTicks, GroundTruthPose, GyroRate
from hardware.sim.gyro import DEG, GyroSimConfig, SimGyro
from hardware.sim.simulator import SimConfig, Simulator
from hardware.sim.world import load_world


def samples(gyro: SimGyro, rate_rad_s: float, n: int, dt: float) -> np.ndarray:
    out = np.empty(n)
    for i in range(n):
        gyro.turn(rate_rad_s * dt, dt)
        out[i] = gyro.sample()
    return out


def test_white_noise_bias_and_scale_as_specified():
    """At rest the samples scatter by N·√rate around the bias; turning at ω they average
    (1 + s)·ω + bias; every sample is a whole number of LSB (1/131 °/s)."""
    cfg = GyroSimConfig(enabled=True, bias_instability_rad_s=0.0)
    gyro = SimGyro(cfg, np.random.default_rng(7))
    rest = samples(gyro, 0.0, 40_000, 0.01)
    sigma = cfg.noise_density_rad_s_sqrt_hz * math.sqrt(100.0)
    assert np.std(rest) == pytest.approx(sigma, rel=0.03)  # 0.05 °/s: the datasheet's RMS
    assert np.std(rest) == pytest.approx(0.05 * DEG, rel=0.03)
    assert np.mean(rest) == pytest.approx(gyro.bias, abs=4 * sigma / math.sqrt(40_000))
    lsb = rest / cfg.lsb_rad_s
    assert np.array_equal(lsb, np.round(lsb))
    turning = samples(gyro, 0.8, 40_000, 0.01)
    expected = (1 + gyro.scale_error) * 0.8 + gyro.bias
    assert np.mean(turning) == pytest.approx(expected, abs=4 * sigma / math.sqrt(40_000))


def test_draws_follow_the_datasheet_tolerances():
    """Turn-on bias σ = 20/3 °/s, scale error σ = 1 % over many gyros (seeded)."""
    cfg = GyroSimConfig(enabled=True)
    gyros = [SimGyro(cfg, np.random.default_rng(s)) for s in range(2000)]
    bias = np.array([g.turn_on_bias for g in gyros])
    scale = np.array([g.scale_error for g in gyros])
    assert np.std(bias) == pytest.approx(20 / 3 * DEG, rel=0.06)
    assert np.std(scale) == pytest.approx(0.01, rel=0.06)
    assert abs(np.mean(bias)) < 0.3 * DEG and abs(np.mean(scale)) < 5e-4
    fixed = SimGyro(
        replace(cfg, turn_on_bias_rad_s=0.1, scale_error=-0.02), np.random.default_rng(0)
    )
    assert (fixed.turn_on_bias, fixed.scale_error) == (0.1, -0.02)


def test_bias_instability_is_a_stationary_gauss_markov_process():
    cfg = GyroSimConfig(
        enabled=True, noise_density_rad_s_sqrt_hz=0.0, turn_on_bias_rad_s=0.0, lsb_rad_s=0.0
    )
    gyro = SimGyro(cfg, np.random.default_rng(11))
    dt, n = 1.0, 200_000  # 4000 correlation times
    drift = samples(gyro, 0.0, n, dt)
    sigma, tau = cfg.bias_instability_rad_s, cfg.bias_correlation_s
    assert np.std(drift) == pytest.approx(sigma, rel=0.05)
    lag = int(tau / dt)
    corr = np.corrcoef(drift[:-lag], drift[lag:])[0, 1]
    assert corr == pytest.approx(math.exp(-1.0), abs=0.05)


def test_bad_gyro_settings_are_rejected():
    with pytest.raises(ValueError, match="must divide"):
        SimConfig(gyro=GyroSimConfig(rate_hz=30))
    with pytest.raises(ValueError, match="noise_density"):
        GyroSimConfig(noise_density_rad_s_sqrt_hz=-1.0)
    with pytest.raises(ValueError, match="bias_correlation_s"):
        GyroSimConfig(bias_correlation_s=0.0)


def braked_trial(seconds: float, gyro: bool) -> tuple[Simulator, list]:
    """A trial with braking (so the slip model draws), the gyro on or off."""
    cfg = SimConfig(seed=2, gyro=GyroSimConfig(enabled=gyro))
    sim = Simulator(load_world("thesis-course"), cfg)
    msgs = []
    for k in range(int(seconds / 0.1)):
        if k % 10 == 5:
            sim.send(BrakeCommand(sim.t, 1.5 if k % 20 == 5 else 0.0, 0.0))
        msgs += sim.poll(sim.t + 0.1)
    return sim, msgs


def test_the_gyro_changes_no_other_sensor_and_integrates_to_the_true_turn():
    sim, with_gyro = braked_trial(12.0, gyro=True)
    _, without = braked_trial(12.0, gyro=False)
    others = [m for m in with_gyro if not isinstance(m, GyroRate)]
    assert len(others) == len(without)
    for a, b in zip(others, without, strict=True):
        assert type(a) is type(b) and a.t == b.t
        if isinstance(a, DepthFrame):
            assert np.array_equal(a.depth_mm, b.depth_mm)
        elif not hasattr(a, "detections"):
            assert a == b
    rates = [m for m in with_gyro if isinstance(m, GyroRate)]
    assert len(rates) == 1201 and rates[0].t == 0.0 and rates[-1].t == pytest.approx(12.0)
    # at each instant the gyro sample comes before the encoder ticks
    order = [type(m) for m in with_gyro if isinstance(m, GyroRate | EncoderTicks)]
    assert order[:3] == [GyroRate, EncoderTicks, GyroRate]
    # the samples, corrected with the drawn bias and scale, integrate to the true turn
    t = np.array([m.t for m in rates])
    r = np.array([m.rate_rad_s for m in rates])
    g = sim.gyro
    turned = np.concatenate(
        [[0.0], np.cumsum((r[1:] - g.turn_on_bias) / (1 + g.scale_error) * np.diff(t))]
    )
    truth = np.array([(m.t, m.theta) for m in with_gyro if isinstance(m, GroundTruthPose)])
    true_turn = np.unwrap(truth[:, 1]) - truth[0, 1]
    assert np.ptp(true_turn) > 0.3  # the trial turns
    # white noise over 12 s: N·√12 ≈ 5e-4 rad; the bias instability adds less
    assert np.max(np.abs(np.interp(truth[:, 0], t, turned) - true_turn)) < 2e-3
    meta = sim.metadata["gyro"]
    assert meta["turn_on_bias_rad_s"] == g.turn_on_bias and meta["scale_error"] == g.scale_error
    assert "gyro" not in Simulator(load_world("corner"), SimConfig()).metadata
