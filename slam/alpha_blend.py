"""`alpha-blend`: dead reckoning pulled toward each absolute observation by a fixed blend
factor — the method of the MTRX5700 data-fusion report (../shared/seeds/003: velocity
odometry corrected by GPS and compass), kept as the baseline the Kalman-weighted fusions
(ekf-slam, particle-filter, gtsam with `absolute`) are compared against.

Prediction: the odometry (encoder ticks or velocity odometry) exactly as dead reckoning
integrates it (slam.dead_reckoning). Update, on a position fix z_p (PositionFix):
(x, y) ← (1 − α_p)·(x, y) + α_p·z_p; on a compass heading z_θ (CompassHeading):
θ ← θ + α_θ·wrap(z_θ − θ), the blend taken on the circle. α_p = alpha_position and
α_θ = alpha_heading are fixed, whatever the uncertainty of either side (the report's
demonstration code used 0.1 for both; its figures also show 0.5, 0.9 and 1). Which
observations are blended: absolute.use_compass / absolute.use_position (both on here).

The report's code, and where this differs:
- Compass wrap-around: it shifts the observed heading by ±2π until it is within π of
  the predicted one, then blends linearly — that is θ + α·wrap(z − θ), as here. It lets
  the heading grow without bound; here it is wrapped to (−π, π] (same direction).
- Prediction: it takes an Euler step with the newest velocity over the time since the
  previous event, x += v_k·Δt·cos θ; here the exact arc with the velocity held from the
  previous message on (VelocityOdometry holds "from t onwards"), as every localizer
  here integrates it. On the MTRX5700 data (velocities every ~0.1 s) the two paths
  differ by centimetres, against the fixes' 0.5 m.
- It predicts up to an observation's time before blending; here the blend acts on the
  pose of the latest odometry message, as in the other localizers. Every observation
  of the MTRX5700 data has the time of a velocity message, so there it is the same.
- It starts at (0, 0, 0); here at the config's initial_pose.
- No gate and no outlier test, as in the report (absolute.gate_prob, outlier_* and
  robust_k are not read).

Covariance (the report has none): the blend is a fixed-gain linear update x⁺ = x + K·(z
− Hx) with K = α·Hᵀ, so with the prediction's error independent of the observation's
its covariance is exactly P⁺ = (I − KH)·P·(I − KH)ᵀ + K·R·Kᵀ (the Joseph form, valid
for any gain), R = σ²·I from the message's σ, else absolute.compass_sigma_rad /
position_sigma_m. Between observations P grows with the odometry noise as dead
reckoning's does. It is as right as `noise` describes the odometry.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from hardware.calibration import WalkerCalibration
from hardware.messages import Message
from hardware.registry import Spec
from slam.absolute import AbsoluteConfig, AbsoluteObservation, absolute_observation
from slam.dead_reckoning import DeadReckoning, DeadReckoningConfig


def _both_on() -> AbsoluteConfig:
    return AbsoluteConfig(use_compass=True, use_position=True)


@dataclass(frozen=True)
class AlphaBlendConfig(DeadReckoningConfig):
    """alpha-blend settings (module docstring).

    initial_pose: (x, y, θ) at the first message (defines the map frame).
    noise: odometry noise, for the covariance (slam.motion.MotionNoise).
    alpha_position, alpha_heading: the fixed blend factors in [0, 1] (0: the observation
        is ignored, 1: the state jumps to it); the report's 0.1 by default.
    absolute: which observations are blended (use_compass, use_position: both on) and
        the σ of those that carry none (for the covariance only).
    """

    alpha_position: float = 0.1
    alpha_heading: float = 0.1
    absolute: AbsoluteConfig = field(default_factory=_both_on)

    def __post_init__(self) -> None:
        for name in ("alpha_position", "alpha_heading"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {value}")


class AlphaBlend(DeadReckoning):
    """Dead reckoning with fixed-factor blends toward absolute observations."""

    config: AlphaBlendConfig

    def __init__(self, config: AlphaBlendConfig, calibration: WalkerCalibration) -> None:
        super().__init__(config, calibration)
        self.counts = {"compass_blends": 0, "position_blends": 0}

    def process(self, msg: Message) -> None:
        obs = absolute_observation(msg, self.config.absolute)
        if obs is None:
            super().process(msg)
        else:
            self._blend(obs)

    def _blend(self, obs: AbsoluteObservation) -> None:
        """x⁺ = x + K·(z ⊖ Hx), K = α·Hᵀ; P⁺ in the Joseph form (module docstring)."""
        c = self.config
        alpha = c.alpha_heading if obs.is_heading else c.alpha_position
        h = obs.jacobian
        k = alpha * h.T
        x, y, th = self._pose
        r = obs.residual(np.array(self._pose)) * alpha
        if obs.is_heading:  # remainder: exact for a heading already in [−π, π]
            th = math.remainder(th + float(r[0]), 2.0 * math.pi)
        else:
            x, y = x + float(r[0]), y + float(r[1])
        a = np.eye(3) - k @ h
        cov = a @ np.array(self._cov) @ a.T + k @ obs.covariance @ k.T
        self._pose = (x, y, th)
        self._cov = tuple(tuple(row) for row in (0.5 * (cov + cov.T)).tolist())
        self.track.amend(self._pose)
        self.counts[f"{obs.kind}_blends"] += 1

    def diagnostics(self) -> dict:
        notes = dict(self.counts)
        if not any(self.counts.values()):
            notes["note"] = "no compass heading or position fix blended: dead reckoning"
        return notes


SPEC = Spec(
    "alpha-blend",
    AlphaBlendConfig,
    AlphaBlend,
    "dead reckoning blended toward compass headings and position fixes by fixed factors "
    "(the MTRX5700 report's method)",
)
