"""Compass headings and position fixes fused in ekf-slam, particle-filter and gtsam
(slam.absolute): the updates against hand-computed Kalman results, the heading wrap, the
gate and the robust likelihood, the GPS-like factor's Jacobian, drifted odometry pulled
back, and nothing changed while fusion is off."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest
from absolute_runs import drifting_run, position_rmse
from gtsam.symbol_shorthand import X
from helpers import numerical_jacobian

from experiments.config import configure, parse_sets
from hardware.calibration import WalkerCalibration
from hardware.errors import ConfigError
from hardware.geometry import wrap_angle
from hardware.messages import CompassHeading, PositionFix, VelocityOdometry
from slam.absolute import AbsoluteConfig, absolute_observation
from slam.base import LOCALIZERS, create
from slam.ekf_slam import EkfSlam, EkfSlamConfig
from slam.gtsam_factors import position_factor
from slam.particle_filter import ParticleFilter, ParticleFilterConfig

CAL = WalkerCalibration()
BOTH = AbsoluteConfig(use_compass=True, use_position=True)


def ekf_after_odometry(initial_pose, omega=0.2, absolute=BOTH) -> EkfSlam:
    """An EKF moved 1 s by velocity odometry (so its covariance has cross terms)."""
    ekf = EkfSlam(EkfSlamConfig(initial_pose=initial_pose, absolute=absolute), CAL)
    for k in range(11):
        ekf.process(VelocityOdometry(0.1 * k, 0.5, omega))
    return ekf


# ------------------------------------------------------------------ the shared model


def test_message_sigma_wins_over_the_configured_one():
    cfg = AbsoluteConfig(use_compass=True, use_position=True, compass_sigma_rad=0.3)
    assert absolute_observation(CompassHeading(1.0, 0.2, 0.05), cfg).sigma == 0.05
    assert absolute_observation(CompassHeading(1.0, 0.2), cfg).sigma == 0.3  # NaN: unknown
    assert absolute_observation(PositionFix(1.0, 0.0, 0.0, 0.0), cfg).sigma == 1.0  # 0: unusable
    assert absolute_observation(CompassHeading(1.0, 7.0), cfg).z[0] == pytest.approx(
        7 - 2 * math.pi
    )
    assert absolute_observation(PositionFix(1.0, 0.0, 0.0), AbsoluteConfig()) is None  # off


def test_settings_by_field_path_and_bad_values():
    sets = parse_sets(
        ["ekf-slam.absolute.use_compass=true", "gtsam.absolute.robust_k=1.5"],
        {"ekf-slam": LOCALIZERS, "gtsam": LOCALIZERS},
    )
    cfg = configure(LOCALIZERS, "ekf-slam", None, sets["ekf-slam"]).config
    assert cfg.absolute.use_compass and not cfg.absolute.use_position
    assert configure(LOCALIZERS, "gtsam", None, sets["gtsam"]).config.absolute.robust_k == 1.5
    with pytest.raises(ConfigError, match="gate_prob must be in"):
        configure(LOCALIZERS, "particle-filter", None, {"absolute.gate_prob": 0.0})


def test_gate_is_the_chi_squared_quantile():
    cfg = AbsoluteConfig(gate_prob=0.999)
    assert cfg.gate(1) == pytest.approx(10.828, abs=1e-3)
    assert cfg.gate(2) == pytest.approx(-2 * math.log(0.001), rel=1e-9)
    assert AbsoluteConfig(gate_prob=1.0).gate(2) == math.inf


# ------------------------------------------------------------------ ekf-slam


def test_ekf_heading_update_is_the_hand_computed_kalman_update():
    ekf = ekf_after_odometry((1.0, 2.0, 0.3))
    x, p = ekf.state()
    assert abs(p[0, 2]) > 1e-4 and abs(p[1, 2]) > 1e-4  # heading correlated with position
    sigma, nu = 0.08, 0.05
    ekf.process(CompassHeading(1.0, x[2] + nu, sigma))
    s = p[2, 2] + sigma**2
    x_expected = x + p[:, 2] / s * nu
    p_expected = p - np.outer(p[:, 2], p[:, 2]) / s
    x1, p1 = ekf.state()
    assert np.allclose(x1, x_expected, rtol=0, atol=1e-12)
    assert np.allclose(p1, p_expected, rtol=0, atol=1e-15)
    assert np.allclose(ekf.estimate().pose, x1) and np.allclose(ekf.trajectory().poses[-1], x1)
    assert ekf.diagnostics()["compass_updates"] == 1 and "note" not in ekf.diagnostics()


def test_ekf_position_update_is_the_hand_computed_kalman_update():
    ekf = ekf_after_odometry((1.0, 2.0, 0.3))
    x, p = ekf.state()
    z, sigma = x[:2] + np.array([0.1, -0.07]), 0.2
    ekf.process(PositionFix(1.0, *z, sigma))
    s = p[:2, :2] + sigma**2 * np.eye(2)
    k = p[:, :2] @ np.linalg.inv(s)
    x1, p1 = ekf.state()
    assert np.allclose(x1, x + k @ (z - x[:2]), rtol=0, atol=1e-12)
    assert np.allclose(p1, p - k @ s @ k.T, rtol=0, atol=1e-15)
    assert ekf.diagnostics()["position_updates"] == 1


def test_ekf_heading_update_across_the_wrap():
    """Heading π − 0.02, compass −π + 0.02: the innovation is +0.04 rad (not −2π + 0.04),
    and the updated heading passes π and wraps to −π + 0.01."""
    ekf = ekf_after_odometry((0.0, 0.0, math.pi - 0.02), omega=0.0)
    x, p = ekf.state()
    assert x[2] == pytest.approx(math.pi - 0.02)
    sigma = math.sqrt(p[2, 2] / 3.0)  # gain 3/4
    ekf.process(CompassHeading(1.0, -math.pi + 0.02, sigma))
    assert ekf.diagnostics()["compass_updates"] == 1
    assert ekf.state()[0][2] == pytest.approx(-math.pi + 0.01, abs=1e-9)


def test_ekf_gates_an_outlier_fix():
    ekf = ekf_after_odometry((0.0, 0.0, 0.0))
    before = ekf.state()[0]
    ekf.process(PositionFix(1.0, 50.0, 50.0, 0.5))
    assert np.array_equal(ekf.state()[0], before)
    assert ekf.diagnostics()["absolute_gated"] == 1
    ungated = ekf_after_odometry((0.0, 0.0, 0.0), absolute=AbsoluteConfig(True, True, gate_prob=1))
    ungated.process(PositionFix(1.0, 50.0, 50.0, 0.5))
    assert ungated.state()[0][0] > before[0] + 1.0  # without the gate it is dragged away


# ------------------------------------------------------------------ particle-filter


def cloud(absolute: AbsoluteConfig, initial_pose=(0.0, 0.0, 0.0), n=2000) -> ParticleFilter:
    cfg = ParticleFilterConfig(
        initial_pose=initial_pose,
        initial_sigma=(1.0, 1.0, 0.3),
        n_particles=n,
        seed=3,
        absolute=absolute,
    )
    return ParticleFilter(cfg, CAL)


def test_particle_weights_follow_the_robust_position_likelihood():
    cfg = AbsoluteConfig(use_position=True, outlier_prob=0.01, outlier_radius_m=10.0)
    pf = cloud(cfg)
    p = pf.particles.copy()
    pf.process(PositionFix(0.0, 0.4, -0.3, 0.5))
    r2 = (p[:, 0] - 0.4) ** 2 + (p[:, 1] + 0.3) ** 2
    density = 0.99 * np.exp(-r2 / 0.5) / (2 * math.pi * 0.25) + 0.01 / (math.pi * 100.0)
    assert np.allclose(pf.weights, density / density.sum(), rtol=1e-9, atol=0)
    assert pf.diagnostics()["position_updates"] == 1


def test_particle_weights_follow_the_heading_likelihood_across_the_wrap():
    cfg = AbsoluteConfig(use_compass=True, outlier_prob=0.0)
    pf = cloud(cfg, initial_pose=(0.0, 0.0, math.pi - 0.05))
    theta = pf.particles[:, 2].copy()
    assert np.any(theta < 0) and np.any(theta > 0)  # the cloud straddles ±π
    pf.process(CompassHeading(0.0, -math.pi + 0.05, 0.2))
    r = wrap_angle(-math.pi + 0.05 - theta)
    density = np.exp(-0.5 * (r / 0.2) ** 2)
    assert np.allclose(pf.weights, density / density.sum(), rtol=1e-9, atol=0)
    assert math.cos(pf.estimate().pose[2]) < -0.99  # still facing −x, not pulled to 0


def test_particle_posterior_is_the_gaussian_product():
    """Prior N(0, 1) per axis, fix z with σ 0.5: posterior mean 0.8·z, variance 0.2."""
    pf = cloud(AbsoluteConfig(use_position=True, outlier_prob=0.0), n=20000)
    pf.process(PositionFix(0.0, 1.0, -1.0, 0.5))
    est = pf.estimate()
    assert est.pose[:2] == pytest.approx([0.8, -0.8], abs=0.03)
    assert np.diag(est.covariance)[:2] == pytest.approx([0.2, 0.2], rel=0.1)


def test_an_outlier_fix_does_not_wipe_out_the_particles():
    robust = cloud(AbsoluteConfig(use_position=True, outlier_prob=0.01))
    robust.process(PositionFix(0.0, 50.0, 50.0, 0.5))
    assert robust.n_eff > 0.99 * 2000
    plain = cloud(AbsoluteConfig(use_position=True, outlier_prob=0.0))
    plain.process(PositionFix(0.0, 50.0, 50.0, 0.5))
    assert plain.n_eff < 2.0


# ------------------------------------------------------------------ gtsam


@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.7, -0.4), (-1.5, 2.0)])
def test_position_factor_jacobian_is_the_numerical_one(offset):
    rng = np.random.default_rng(5)
    z = rng.normal(size=2)
    for _ in range(5):
        pose = gtsam.Pose2(*rng.normal(size=2), rng.uniform(-math.pi, math.pi))
        factor = position_factor(X(0), z, np.array(offset), gtsam.noiseModel.Unit.Create(2))

        def error(xi, pose=pose, factor=factor):
            values = gtsam.Values()
            values.insert(X(0), pose.retract(xi))
            return factor.unwhitenedError(values)

        values = gtsam.Values()
        values.insert(X(0), pose)
        analytic = factor.linearize(values).jacobian()[0]
        assert np.allclose(analytic, numerical_jacobian(error, np.zeros(3)), atol=1e-6)
        if offset == (0.0, 0.0):  # no offset: gtsam's own translation prior
            prior = gtsam.PoseTranslationPrior2D(X(0), z, gtsam.noiseModel.Unit.Create(2))
            assert np.allclose(factor.unwhitenedError(values), prior.unwhitenedError(values))
            assert np.allclose(analytic, prior.linearize(values).jacobian()[0])


def test_gtsam_heading_prior_across_the_wrap():
    """A compass heading just past −π pulls a keyframe at π − 0.1 the short way round."""
    cfg = LOCALIZERS.spec("gtsam").config_type(
        initial_pose=(0.0, 0.0, math.pi - 0.1),
        prior_sigma=(1e-3, 1e-3, 1.0),  # the start's heading barely known
        absolute=AbsoluteConfig(use_compass=True),
    )
    loc = create("gtsam", CAL, cfg)
    loc.process(VelocityOdometry(0.0, 0.0, 0.0))
    loc.process(CompassHeading(0.0, -math.pi + 0.1, 0.01))
    assert loc.estimate().pose[2] == pytest.approx(-math.pi + 0.1, abs=1e-3)
    assert loc.diagnostics()["compass_factors"] == 1


# ------------------------------------------------------------------ all three


@pytest.mark.parametrize(
    ("name", "bound"), [("ekf-slam", 0.15), ("particle-filter", 0.15), ("gtsam", 0.15)]
)
def test_fixes_pull_a_drifted_trajectory_back(name, bound):
    """Odometry that over-reports the turn by 40 % drifts metres off in a minute; with
    fixes (σ 0.3 m) and headings (σ 0.1 rad) every second the path stays within a
    fraction of the fixes' noise of the truth."""
    messages, truth = drifting_run(seed=1)
    cfg = LOCALIZERS.spec(name).config_type(absolute=BOTH)
    fused, odometry_only = create(name, CAL, cfg), create(name, CAL)
    for m in messages:
        fused.process(m)
        odometry_only.process(m)
    drifted = position_rmse(odometry_only.trajectory(), truth)
    assert drifted > 3.0
    assert position_rmse(fused.trajectory(), truth) < bound


@pytest.mark.parametrize("name", ["ekf-slam", "particle-filter", "gtsam"])
def test_while_off_absolute_messages_change_nothing(name):
    messages, _ = drifting_run(seed=2, steps=200)
    odometry = [m for m in messages if isinstance(m, VelocityOdometry)]
    with_fixes, without = create(name, CAL), create(name, CAL)
    for m in messages:
        with_fixes.process(m)
    for m in odometry:
        without.process(m)
    assert np.array_equal(with_fixes.trajectory().poses, without.trajectory().poses)
    assert with_fixes.diagnostics() == without.diagnostics()
