"""alpha-blend: α = 0 is dead reckoning, α = 1 snaps to the observation, the blend in
between is the MTRX5700 report's (its compass wrap-around included), the covariance is
the fixed-gain update's, and it beats dead reckoning on drifting odometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
from absolute_runs import drifting_run, position_rmse

from hardware.calibration import WalkerCalibration
from hardware.messages import CompassHeading, PositionFix, VelocityOdometry
from slam.alpha_blend import AlphaBlend, AlphaBlendConfig
from slam.base import LOCALIZERS, create

CAL = WalkerCalibration()


def blender(alpha_position: float, alpha_heading: float, initial_pose=(1.0, 2.0, 0.3)):
    """An alpha-blend moved 1 s by velocity odometry (its covariance has cross terms)."""
    cfg = AlphaBlendConfig(
        initial_pose=initial_pose, alpha_position=alpha_position, alpha_heading=alpha_heading
    )
    loc = AlphaBlend(cfg, CAL)
    for k in range(11):
        loc.process(VelocityOdometry(0.1 * k, 0.5, 0.2))
    return loc


def report_compass_update(th_pred: float, th_obs: float, alpha: float) -> float:
    """The report's updateStageCompass (MATLAB, seeds/003 §1.c.ii), line for line."""
    a = abs(th_obs - th_pred)
    while a > math.pi:
        th_obs += -2 * math.pi if th_obs > th_pred else 2 * math.pi
        a = abs(th_obs - th_pred)
    return (1 - alpha) * th_pred + alpha * th_obs


def test_registered_with_the_reports_alphas():
    assert "alpha-blend" in LOCALIZERS.names()
    cfg = LOCALIZERS.spec("alpha-blend").config_type()
    assert (cfg.alpha_position, cfg.alpha_heading) == (0.1, 0.1)
    assert cfg.absolute.use_compass and cfg.absolute.use_position
    with pytest.raises(ValueError, match="alpha_heading must be in"):
        AlphaBlendConfig(alpha_heading=1.5)


def test_alpha_zero_is_dead_reckoning():
    messages, _ = drifting_run(seed=0, steps=300)
    blend = create("alpha-blend", CAL, AlphaBlendConfig(alpha_position=0.0, alpha_heading=0.0))
    dr = create("dead-reckoning", CAL)
    for m in messages:
        blend.process(m)
        dr.process(m)
    assert np.array_equal(blend.trajectory().poses, dr.trajectory().poses)
    assert np.array_equal(blend.estimate().covariance, dr.estimate().covariance)
    assert blend.diagnostics() == {"compass_blends": 30, "position_blends": 30}


def test_alpha_one_snaps_to_the_observation():
    loc = blender(1.0, 1.0)
    loc.process(PositionFix(1.0, 4.0, -3.0, 0.2))
    est = loc.estimate()
    assert est.pose[:2] == pytest.approx([4.0, -3.0], abs=1e-12)
    assert np.allclose(est.covariance[:2, :2], 0.04 * np.eye(2), atol=1e-15)
    assert np.allclose(est.covariance[:2, 2], 0.0, atol=1e-15)  # the fix knows nothing of θ
    loc.process(CompassHeading(1.0, -2.5, 0.1))
    assert loc.estimate().pose[2] == pytest.approx(-2.5, abs=1e-12)
    assert loc.estimate().covariance[2, 2] == pytest.approx(0.01, abs=1e-15)
    assert np.allclose(loc.trajectory().poses[-1], [4.0, -3.0, -2.5], atol=1e-12)


def test_blend_and_its_covariance():
    """x⁺ = (1 − α)·x + α·z for the position; P⁺ = (1 − α)²·P + α²·R on the observed
    block, (1 − α)·P across it, P unchanged elsewhere."""
    loc = blender(0.1, 0.1)
    before = loc.estimate()
    p = before.covariance
    loc.process(PositionFix(1.0, 0.0, 0.0, 0.5))
    after = loc.estimate()
    assert after.pose[:2] == pytest.approx(0.9 * before.pose[:2], abs=1e-12)
    assert after.pose[2] == before.pose[2]
    q = after.covariance
    assert np.allclose(q[:2, :2], 0.81 * p[:2, :2] + 0.01 * 0.25 * np.eye(2), atol=1e-15)
    assert np.allclose(q[:2, 2], 0.9 * p[:2, 2], atol=1e-15)
    assert q[2, 2] == p[2, 2]


def test_compass_blend_is_the_reports_including_the_wrap():
    rng = np.random.default_rng(4)
    for alpha in (0.1, 0.5, 0.9):
        for _ in range(50):
            heading, observed = rng.uniform(-math.pi, math.pi, 2)
            loc = AlphaBlend(
                AlphaBlendConfig(initial_pose=(0, 0, heading), alpha_heading=alpha), CAL
            )
            loc.process(CompassHeading(0.0, observed, 0.25))
            expected = report_compass_update(heading, observed, alpha)
            got = loc.estimate().pose[2]
            assert math.remainder(got - expected, 2 * math.pi) == pytest.approx(0.0, abs=1e-12)
    # across ±π it moves the short way: half way from π − 0.05 to −π + 0.05 is ±π
    loc = AlphaBlend(AlphaBlendConfig(initial_pose=(0, 0, math.pi - 0.05), alpha_heading=0.5), CAL)
    loc.process(CompassHeading(0.0, -math.pi + 0.05, 0.25))
    assert abs(loc.estimate().pose[2]) == pytest.approx(math.pi, abs=1e-12)


def test_it_corrects_drifting_odometry_and_says_when_it_cannot():
    messages, truth = drifting_run(seed=1)
    blend, dr = create("alpha-blend", CAL), create("dead-reckoning", CAL)
    for m in messages:
        blend.process(m)
        dr.process(m)
    assert position_rmse(dr.trajectory(), truth) > 5.0
    assert position_rmse(blend.trajectory(), truth) < 1.2  # measured 1.01
    quiet = create("alpha-blend", CAL)
    quiet.process(VelocityOdometry(0.0, 0.1, 0.0))
    assert "dead reckoning" in quiet.diagnostics()["note"]
