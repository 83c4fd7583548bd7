"""Online estimation of each rear wheel's slip coefficient: the settings and the prediction.

Model: a braked wheel's encoder counts (1 − s) of the distance it rolls, s = k·l, with
l the brake's commanded level ((τ − τ_off)/(τ_max − τ_off), `slam.motion.OdometryModel`)
and k unknown per wheel, (k_left, k_right): a slow random walk (the floor changes), whose
σ grows by random_walk_per_s per √s, from the prior N(k_prior, k_sigma²). The odometry
then moves by `slam.motion.slip_corrected` (true distance = encoder distance /
(1 − k·l)), and the observations (tags) correct k through its correlation with the
pose: a heading that over-rotated in a braked turn says the braked wheel slipped more
than k assumed. Odometry without wheels (velocity messages) moves as it is.

Each localizer carries k its own way: ekf-slam as two more state entries
(`predict_with_slip`: the pose and k predicted together, with the Jacobians), gtsam as
a variable per keyframe (`slam.gtsam_slip`), fastslam per particle. With the estimate on,
the fixed de-biasing of the motion noise (`noise.bias_per_full_brake`) is not applied:
the estimate replaces it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from slam.motion import MAX_SLIP, Increment, apply_increment, increment_jacobians, slip_corrected


@dataclass(frozen=True)
class SlipEstimation:
    """Per-wheel slip estimation (module docstring), off by default.

    estimate: on / off. k_prior: the prior mean of (k_left, k_right), slip ratio per unit
    brake level; k_sigma: its standard deviation (0.1 covers a clean floor's 0.02 and a
    dusty one's 0.12 from 0); random_walk_per_s: how fast k may change, σ per √s.
    """

    estimate: bool = False
    k_prior: tuple[float, float] = (0.0, 0.0)
    k_sigma: float = 0.1
    random_walk_per_s: float = 0.001

    def __post_init__(self) -> None:
        if len(self.k_prior) != 2 or not all(abs(k) < MAX_SLIP for k in self.k_prior):
            raise ValueError(f"slip.k_prior must be two values in (-0.9, 0.9), got {self.k_prior}")
        if not (math.isfinite(self.k_sigma) and self.k_sigma > 0):
            raise ValueError(f"slip.k_sigma must be > 0, got {self.k_sigma}")
        if not (math.isfinite(self.random_walk_per_s) and self.random_walk_per_s >= 0):
            raise ValueError(f"slip.random_walk_per_s must be >= 0, got {self.random_walk_per_s}")

    def prior_cov(self) -> np.ndarray:
        """The prior covariance of (k_left, k_right)."""
        return np.eye(2) * self.k_sigma**2


def increment_with_slip(
    inc: Increment, k: np.ndarray, track: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ds, dθ, J = ∂(ds, dθ)/∂k) of an increment at slip coefficients k (..., 2); an
    increment without wheel distances is its own (ds, dθ), J = 0; one whose turn is a
    gyro's keeps that turn (dθ's row of J is 0) and has its distance corrected."""
    if inc.wheels is None:
        shape = np.shape(k)[:-1]
        return np.full(shape, inc.ds), np.full(shape, inc.dtheta), np.zeros((*shape, 2, 2))
    ds, dtheta, j = slip_corrected(inc.wheels, inc.brake_level, k, track)
    if inc.gyro_turn:
        dtheta = np.full(np.shape(ds), inc.dtheta)
        j[..., 1, :] = 0.0
    return ds, dtheta, j


class SlipStep(NamedTuple):
    """One odometry step of the pose and k (`predict_with_slip`)."""

    pose: np.ndarray  # (3,) moved
    cov: np.ndarray  # (5, 5) of (x, y, θ, k_left, k_right)
    f: np.ndarray  # (3, 3) ∂pose'/∂pose
    f_k: np.ndarray  # (3, 2) ∂pose'/∂k
    ds: float  # the increment at k
    dtheta: float
    q: np.ndarray  # (2, 2) its covariance with k's share, Q + J cov_kk Jᵀ


def predict_with_slip(
    pose: np.ndarray, cov: np.ndarray, inc: Increment, k: np.ndarray, track: float, walk: float
) -> SlipStep:
    """One odometry step of the joint Gaussian of (x, y, θ, k_left, k_right).

    pose' = pose ⊕ arc(ds(k), dθ(k)), k' = k + w, w ~ N(0, walk·dt·I) (walk: variance per
    second); cov (5×5) → F₅ cov F₅ᵀ + G₅ Q G₅ᵀ + W with F₅ = [[F, F_k], [0, I]], F =
    ∂pose'/∂pose, F_k = ∂pose'/∂k = G J, G = ∂pose'/∂(ds, dθ), J = ∂(ds, dθ)/∂k and Q the
    increment's covariance. q (returned) adds k's share to Q, for a pose-only smoother."""
    ds, dth, jk = increment_with_slip(inc, k, track)
    ds, dth = float(ds), float(dth)
    f, g = increment_jacobians(float(pose[2]), ds, dth)
    fk = g @ jk
    f5 = np.eye(5)
    f5[:3, :3] = f
    f5[:3, 3:] = fk
    new = f5 @ cov @ f5.T
    new[:3, :3] += g @ inc.cov @ g.T
    new[3:, 3:] += np.eye(2) * (walk * inc.dt)
    q = inc.cov + jk @ cov[3:, 3:] @ jk.T
    moved = apply_increment(pose, ds, dth)
    return SlipStep(moved, 0.5 * (new + new.T), f, fk, ds, dth, q)


def slip_diagnostics(k: np.ndarray, cov: np.ndarray) -> dict[str, list[float]]:
    """What a localizer reports of its slip estimate: slip_k (k_left, k_right) and
    slip_k_sigma, their standard deviations."""
    sigma = np.sqrt(np.maximum(np.diag(cov), 0.0))
    return {"slip_k": [float(v) for v in k], "slip_k_sigma": [float(v) for v in sigma]}
