"""The GTSAM smoother's slip factors (slam.slip): keyframe odometry that depends on the
wheels' slip coefficients k = (k_left, k_right), a Point2 variable per keyframe.

Between keyframes a and b the odometry is integrated with the estimate k₀ of k at the
time, giving the relative pose δ₀ (x, y, θ in a's frame) and J = ∂δ/∂k (3×2,
accumulated through the exact arcs). For another k the relative pose is, to first
order, δ(k) = δ₀ + J (k − k₀) — linear in k, exact in the poses: the factor's error is
Logmap(Z⁻¹ · X_a⁻¹ X_b) with Z = Pose2(δ(k)), as a BetweenFactorPose2 whose
measurement moves with k. Its Jacobians are analytic: with E = Z⁻¹ X_a⁻¹ X_b and L =
∂Logmap/∂E, ∂e/∂X_a = L ∂(X_a⁻¹X_b)/∂X_a, ∂e/∂X_b = L ∂(X_a⁻¹X_b)/∂X_b and ∂e/∂k =
−L Ad(E⁻¹) T J, where T = blockdiag(R(θ_Z)ᵀ, 1) takes a change of δ's coordinates into
Z's tangent space. k's random walk is a BetweenFactorPoint2 between successive
keyframes' variables, σ = random_walk_per_s·√Δt.
"""

from __future__ import annotations

import math
from functools import partial

import gtsam
import numpy as np


def slip_odometry_error(
    xa: gtsam.Pose2,
    xb: gtsam.Pose2,
    k: np.ndarray,
    delta0: np.ndarray,
    jk: np.ndarray,
    k0: np.ndarray,
    jacobians: bool = False,
) -> tuple[np.ndarray, list[np.ndarray] | None]:
    """The factor's error (3,) at poses xa, xb and slip k; with jacobians, also
    [∂e/∂xa, ∂e/∂xb (3×3, in the poses' tangent spaces), ∂e/∂k (3×2)]."""
    z = np.asarray(delta0, dtype=float) + jk @ (np.asarray(k, dtype=float) - k0)
    zp = gtsam.Pose2(float(z[0]), float(z[1]), float(z[2]))
    if not jacobians:
        return gtsam.Pose2.Logmap(zp.between(xa.between(xb))), None
    ha = np.zeros((3, 3), order="F")
    hb = np.zeros((3, 3), order="F")
    rel = xa.between(xb, ha, hb)
    err = zp.between(rel)
    hlog = np.zeros((3, 3), order="F")
    e = gtsam.Pose2.Logmap(err, hlog)
    c, s = math.cos(zp.theta()), math.sin(zp.theta())
    t = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    hk = -hlog @ err.inverse().AdjointMap() @ t @ jk
    return e, [hlog @ ha, hlog @ hb, hk]


def _error(delta0, jk, k0, factor: gtsam.CustomFactor, values: gtsam.Values, h):
    keys = factor.keys()
    e, jac = slip_odometry_error(
        values.atPose2(keys[0]),
        values.atPose2(keys[1]),
        values.atPoint2(keys[2]),
        delta0,
        jk,
        k0,
        jacobians=h is not None,
    )
    if h is not None:
        h[0], h[1], h[2] = jac
    return e


def slip_odometry_factor(
    key_a: int,
    key_b: int,
    key_k: int,
    delta0: np.ndarray,
    jk: np.ndarray,
    k0: np.ndarray,
    noise: gtsam.noiseModel.Base,
) -> gtsam.CustomFactor:
    """The odometry factor X_a → X_b measured as δ₀ at k₀, moving by J (k − k₀) with the
    slip variable key_k (module docstring)."""
    args = (np.array(delta0, dtype=float), np.array(jk, dtype=float), np.array(k0, dtype=float))
    return gtsam.CustomFactor(noise, [key_a, key_b, key_k], partial(_error, *args))


def slip_walk_factor(key_a: int, key_b: int, sigma: float) -> gtsam.BetweenFactorPoint2:
    """k's random walk from one keyframe's variable to the next, σ per component."""
    return gtsam.BetweenFactorPoint2(
        key_a, key_b, np.zeros(2), gtsam.noiseModel.Isotropic.Sigma(2, sigma)
    )
