"""The particle filter's scan-informed proposal: odometry prior × scan likelihood, per particle.

With the odometry alone as the proposal, particles spread with the motion noise and a
sharp scan likelihood then keeps only the few that landed near its peak (N_eff → 1 at
every scan, on a laser log). The improved proposal of Grisetti, Stachniss and Burgard
(IEEE T-RO 2007, GMapping) draws each particle from p(x | x_prev, u, z, map) ∝
p(z | x, map) · p(x | x_prev, u) instead, approximated by a Gaussian fitted around the
likelihood's peak, and weights it by the normaliser η = ∫ p(z | x, map) p(x | x_prev, u) dx.
Here all particles share one map, so the likelihood is evaluated once per frame on a pose
lattice and every particle reuses it:

1. coarse search: the frame's log-likelihood S(x) (`score`) on a lattice around the
   particles' mean covering their prior (3σ, clipped to a window); its best pose x*;
2. a fine lattice around x*, one coarse step either side;
3. per particle i with prior N(x̄ᵢ, Σᵢ): τᵢ(g) = exp(S(g)) · N(g; x̄ᵢ, Σᵢ) on the fine
   lattice → the mean μᵢ and covariance Cᵢ of τᵢ (plus the lattice's own quantisation,
   step²/12 per axis), log ηᵢ = log Σ_g τᵢ(g) (+ a constant).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from hardware.geometry import wrap_angle
from slam.kernel_math import inverse, wrap


@dataclass(frozen=True)
class ProposalLattice:
    """The lattices of the scan proposal (module docstring): the coarse search covers the
    particles' prior (3σ of the accumulated odometry covariance, plus their spread)
    clipped to window_m (min, max half-width in x and y) and window_rad, in steps of
    step_m and step_rad; the fine lattice around its best pose has fine_steps steps per
    coarse step either side; sigma_floor (x, y, θ) is added to every prior's σ (in
    quadrature)."""

    window_m: tuple[float, float] = (0.15, 0.5)
    window_rad: tuple[float, float] = (0.05, 0.3)
    step_m: float = 0.05
    step_rad: float = 0.02
    fine_steps: int = 3
    sigma_floor: tuple[float, float, float] = (0.01, 0.01, 0.005)

    def __post_init__(self) -> None:
        if min(self.step_m, self.step_rad) <= 0 or self.fine_steps < 1:
            raise ValueError("lattice steps must be > 0 and fine_steps >= 1")
        if len(self.sigma_floor) != 3 or min(self.sigma_floor) < 0:
            raise ValueError(f"sigma_floor must be three values >= 0, got {self.sigma_floor}")


def lattice(centre: np.ndarray, half_steps: tuple[int, int, int], steps: np.ndarray) -> np.ndarray:
    """(M, 3) poses centre + (i·step_x, j·step_y, k·step_θ) for |i|, |j|, |k| ≤ half_steps
    (θ not wrapped, so that offsets from the centre stay small numbers)."""
    axes = [np.arange(-h, h + 1) * s for h, s in zip(half_steps, steps, strict=True)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return grid + np.asarray(centre, dtype=float)


@njit(cache=True, nogil=True)
def fit_one(poses, log_likelihood, prior_mean, prior_cov, steps, mu, cov) -> float:
    """One particle's Gaussian fit of likelihood × prior on a lattice (module doc, 3):
    mu (3,) and cov (3, 3) filled, log η returned (see `gaussian_fit`)."""
    inv = np.empty((3, 3))
    det = inverse(prior_cov, 3, inv)
    m = poses.shape[0]
    log_tau = np.empty(m)
    d = np.empty(3)
    top = -math.inf
    for g in range(m):
        d[0] = poses[g, 0] - prior_mean[0]
        d[1] = poses[g, 1] - prior_mean[1]
        d[2] = wrap(poses[g, 2] - prior_mean[2])
        maha = 0.0
        for i in range(3):
            for j in range(3):
                maha += d[i] * inv[i, j] * d[j]
        log_tau[g] = log_likelihood[g] - 0.5 * maha - 0.5 * math.log(det)
        top = max(top, log_tau[g])
    total = 0.0
    for g in range(m):
        log_tau[g] = math.exp(log_tau[g] - top)  # now the unnormalised weights
        total += log_tau[g]
    centre = m // 2  # offsets from the lattice centre: no wrap
    mean_off = np.zeros(3)
    for g in range(m):
        for i in range(3):
            mean_off[i] += log_tau[g] / total * (poses[g, i] - poses[centre, i])
    for i in range(3):
        for j in range(3):
            acc = 0.0
            for g in range(m):
                di = poses[g, i] - poses[centre, i] - mean_off[i]
                dj = poses[g, j] - poses[centre, j] - mean_off[j]
                acc += log_tau[g] / total * di * dj
            cov[i, j] = acc + (steps[i] * steps[i] / 12.0 if i == j else 0.0)
    for i in range(3):
        mu[i] = poses[centre, i] + mean_off[i]
    mu[2] = wrap(mu[2])
    return top + math.log(total)


@njit(cache=True, nogil=True)
def gaussian_fit(
    poses: np.ndarray,
    log_likelihood: np.ndarray,
    prior_mean: np.ndarray,
    prior_cov: np.ndarray,
    steps: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per particle, the Gaussian fit of likelihood × prior on a lattice (module doc, 3).

    poses (M, 3) the lattice (centred on poses[M // 2]), log_likelihood (M,) at each,
    prior_mean (N, 3), prior_cov (N, 3, 3) (positive definite), steps (3,) the lattice
    steps. Returns (μ (N, 3), C (N, 3, 3), log η (N,)); μ's heading is wrapped.
    """
    n = prior_mean.shape[0]
    mu = np.empty((n, 3))
    cov = np.empty((n, 3, 3))
    log_eta = np.empty(n)
    for k in range(n):
        log_eta[k] = fit_one(
            poses, log_likelihood, prior_mean[k], prior_cov[k], steps, mu[k], cov[k]
        )
    return mu, cov, log_eta


def sample_gaussians(mean: np.ndarray, cov: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One draw from each N(mean_i, cov_i): (N, 3); headings wrapped."""
    chol = np.linalg.cholesky(cov)
    out = mean + np.einsum("nij,nj->ni", chol, rng.standard_normal(mean.shape))
    out[:, 2] = wrap_angle(out[:, 2])
    return out


def rotate_covariance(cov: np.ndarray, headings: np.ndarray) -> np.ndarray:
    """(N, 3, 3): the body-frame covariance `cov` (3×3: x, y in the frame of a pose with
    heading h, θ) in the world frame for each heading h."""
    c, s = np.cos(headings), np.sin(headings)
    r = np.zeros((len(headings), 3, 3))
    r[:, 0, 0], r[:, 0, 1], r[:, 1, 0], r[:, 1, 1] = c, -s, s, c
    r[:, 2, 2] = 1.0
    return r @ cov @ np.transpose(r, (0, 2, 1))
