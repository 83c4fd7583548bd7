"""Rauch–Tung–Striebel smoothing of a filtered pose track driven by odometry.

A filter that reports, after every motion step k, a Gaussian N(x_k, P_k) of the pose
(after the observations of that time) and the odometry Δ_k, Σ_k that moved it from
step k−1 (in the frame of pose k−1: x_k⁻ = x_{k−1} ⊕ Δ_k) has everything the RTS
backward pass needs (Rauch, Tung & Striebel 1965; Särkkä, Bayesian Filtering and
Smoothing, §8.2, in the extended-Kalman form):

    x_k⁻ = x_{k−1} ⊕ Δ_k,   F = ∂(x ⊕ Δ)/∂x at x_{k−1},   J = ∂(x ⊕ Δ)/∂Δ (rotation)
    P_k⁻ = F P_{k−1} Fᵀ + J Σ_k Jᵀ
    C_{k−1} = P_{k−1} Fᵀ (P_k⁻)⁻¹
    x^s_{k−1} = x_{k−1} + C_{k−1} (x^s_k ⊖ x_k⁻),   starting from x^s_K = x_K.

The particle filter uses it on its weighted mean and covariance (a Gaussian summary of
the particles): an observation then corrects the stretch that led to it, spread over
the steps in proportion to the odometry's uncertainty, without the path degeneracy of
reading the particles' ancestry back (where the old past is a single particle's path).
EKF-SLAM uses it on its pose marginal (`arc_steps` turns its per-message odometry
increments into the deltas): a pose-only smoother, which treats the landmark updates
of different times as independent — not exact in SLAM, where they share the landmark
estimates, but it carries a loop closure's correction back along the path that led to
it, which the filtered poses (fixed when recorded) cannot.
"""

from __future__ import annotations

import numpy as np

from hardware.geometry import compose, wrap_angle
from slam.motion import apply_increment, sinc_and_derivative


def arc_steps(ds: np.ndarray, dtheta: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Odometry increments (K,) along exact arcs with 2×2 covariances q (K, 2, 2) → the
    deltas (K, 3) in the frame of the pose before each, and their covariances G q Gᵀ
    (K, 3, 3), G = ∂delta/∂(ds, dθ) (as `slam.motion.increment_jacobians` at θ = 0)."""
    ds = np.asarray(ds, dtype=float)
    half = 0.5 * np.asarray(dtheta, dtype=float)
    deltas = apply_increment(np.zeros((len(ds), 3)), ds, 2.0 * half)
    s, s_prime = sinc_and_derivative(half)
    chord, dchord = ds * s, 0.5 * ds * s_prime
    c, sn = np.cos(half), np.sin(half)
    g = np.zeros((len(ds), 3, 2))
    g[:, 0, 0], g[:, 1, 0] = s * c, s * sn
    g[:, 0, 1] = dchord * c - 0.5 * chord * sn
    g[:, 1, 1] = dchord * sn + 0.5 * chord * c
    g[:, 2, 1] = 1.0
    return deltas, g @ np.asarray(q, dtype=float) @ np.swapaxes(g, 1, 2)


def rts_smooth(
    means: np.ndarray, covs: np.ndarray, deltas: np.ndarray, delta_covs: np.ndarray
) -> np.ndarray:
    """Smoothed poses (K, 3) from filtered means (K, 3), covariances (K, 3, 3), and the
    odometry deltas (K, 3) / their covariances (K, 3, 3) from step k−1 to k in the frame
    of pose k−1 (entry 0 unused). Singular covariances are allowed (a known start, a
    walker standing still): a tiny jitter keeps the predicted covariance invertible."""
    means = np.asarray(means, dtype=float)
    k = len(means)
    if k < 2:
        return means.copy()
    prev, d = means[:-1], np.asarray(deltas, dtype=float)[1:]
    p = np.asarray(covs, dtype=float)[:-1]
    c, s = np.cos(prev[:, 2]), np.sin(prev[:, 2])
    pred = compose(prev, d)
    f = np.tile(np.eye(3), (k - 1, 1, 1))
    f[:, 0, 2] = -s * d[:, 0] - c * d[:, 1]
    f[:, 1, 2] = c * d[:, 0] - s * d[:, 1]
    j = np.zeros((k - 1, 3, 3))
    j[:, 0, 0], j[:, 0, 1], j[:, 1, 0], j[:, 1, 1], j[:, 2, 2] = c, -s, s, c, 1.0
    fp = f @ p
    p_pred = fp @ np.swapaxes(f, 1, 2) + j @ np.asarray(delta_covs, dtype=float)[1:] @ np.swapaxes(
        j, 1, 2
    )
    jitter = 1e-12 * np.trace(p_pred, axis1=1, axis2=2) + 1e-18  # (1e-9 m)²: all known
    p_pred += jitter[:, None, None] * np.eye(3)
    # C = P Fᵀ P⁻⁻¹ = (P⁻⁻¹ F P)ᵀ, P⁻ symmetric
    gain = np.swapaxes(np.linalg.solve(p_pred, fp), 1, 2).tolist()
    x_f = prev.tolist()
    x_p = pred.tolist()
    out = np.empty_like(means)
    out[-1] = means[-1]
    nx, ny, nt = (float(v) for v in means[-1])
    for i in range(k - 2, -1, -1):
        g, xf, xp = gain[i], x_f[i], x_p[i]
        e0, e1 = nx - xp[0], ny - xp[1]
        e2 = float(wrap_angle(nt - xp[2]))
        nx = xf[0] + g[0][0] * e0 + g[0][1] * e1 + g[0][2] * e2
        ny = xf[1] + g[1][0] * e0 + g[1][1] * e1 + g[1][2] * e2
        nt = float(wrap_angle(xf[2] + g[2][0] * e0 + g[2][1] * e1 + g[2][2] * e2))
        out[i] = (nx, ny, nt)
    return out
