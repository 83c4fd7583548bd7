"""Compiled (numba) FastSLAM observation step: the proposal, gate and weights, the pose
sample and the landmark EKFs, for every particle in one loop each.

The arithmetic of slam.fastslam (its docstring has the equations), written per particle
on the small matrices (D = 2: range, bearing; D = 3: with the tag's yaw) instead of as
~25 numpy calls on stacked arrays per observation: at 100 particles a numpy call costs
more than its arithmetic. The random draws stay with the caller (numpy's Generator, so a
run is reproducible from its seed and draws what it drew before).

Conventions: poses (N, 3); motion covariances `sigma` (N, 3, 3); landmark means (N, C, D)
and covariances (N, C, D, D); seen (N, C); an observation m is (cols[m], z[m] (D,), its
noise variances r[m] (D,): R is diagonal).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from slam.kernel_math import inverse, wrap

LOG_TWO_PI = math.log(2.0 * math.pi)


@njit(cache=True, nogil=True, inline="always")
def _predict(pose, lm, d, zhat, g_s, g_l) -> None:
    """ẑ (d,), ∂h/∂s (d, 3) and ∂h/∂l (d, d) of the range-bearing(-yaw) model."""
    dx = lm[0] - pose[0]
    dy = lm[1] - pose[1]
    q = max(dx * dx + dy * dy, 1e-12)
    r = math.sqrt(q)
    zhat[0] = math.hypot(dx, dy)
    zhat[1] = wrap(math.atan2(dy, dx) - pose[2])
    g_s[:, :] = 0.0
    g_l[:, :] = 0.0
    g_l[0, 0], g_l[0, 1] = dx / r, dy / r
    g_l[1, 0], g_l[1, 1] = -dy / q, dx / q
    g_s[0, 0], g_s[0, 1] = -dx / r, -dy / r
    g_s[1, 0], g_s[1, 1] = dy / q, -dx / q
    g_s[1, 2] = -1.0
    if d == 3:
        zhat[2] = wrap(lm[2] - pose[2])
        g_s[2, 2] = -1.0
        g_l[2, 2] = 1.0


@njit(cache=True, nogil=True, inline="always")
def _mul(a, b, out, b_transposed) -> None:
    """out = A B (or A Bᵀ) of small matrices."""
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            acc = 0.0
            for e in range(a.shape[1]):
                acc += a[i, e] * (b[j, e] if b_transposed else b[e, j])
            out[i, j] = acc


@njit(cache=True, nogil=True, inline="always")
def _gcg(g, c, cg, out) -> None:
    """cg = C Gᵀ and out = G C Gᵀ for a symmetric C (n×n) and G (m×n)."""
    _mul(c, g, cg, True)
    _mul(g, cg, out, False)


@njit(cache=True, nogil=True, inline="always")
def _kalman(c, cg, s_inv, nu, k, mean, cov) -> None:
    """The Kalman step of a Gaussian (mean, C) given cg = C Gᵀ, S⁻¹ and ν: K = cg S⁻¹,
    mean += K ν, cov = C − K cgᵀ (= C − K S Kᵀ), symmetrised (cov may be c itself)."""
    n, d = cg.shape
    _mul(cg, s_inv, k, False)
    for a in range(n):
        acc = 0.0
        for e in range(d):
            acc += k[a, e] * nu[e]
        mean[a] += acc
    for a in range(n):
        for b in range(a, n):
            acc = 0.0
            for e in range(d):
                acc += k[a, e] * cg[b, e] + k[b, e] * cg[a, e]
            v = c[a, b] - 0.5 * acc
            cov[a, b] = v
            cov[b, a] = v


@njit(cache=True, nogil=True, inline="always")
def _innovation(z, zhat, d, nu) -> None:
    nu[0] = z[0] - zhat[0]
    for i in range(1, d):
        nu[i] = wrap(z[i] - zhat[i])


@njit(cache=True, nogil=True, inline="always")
def _log_normal(nu, s_inv, det, d) -> float:
    maha = 0.0
    for i in range(d):
        for j in range(d):
            maha += nu[i] * s_inv[i, j] * nu[j]
    return -0.5 * (maha + math.log(det) + d * LOG_TWO_PI)


@njit(cache=True, nogil=True)
def fold(mu, sigma, means, covs, seen, w, cols, z, r, gate, gain, proposal, logw, had_seen):
    """Fold each observation of known landmarks into the proposal (`proposal`: 2.0; mu,
    sigma updated in place) and the weights (logw += log N(ν; 0, S) / gain, in place).

    Returns `used` (M,) int8: 0 gated (the weighted mixture of N(ν_i, S_i) puts ν̄ beyond
    `gate`), 1 used, 2 new to every particle (nothing to fold). had_seen (M, N) is
    filled with the particles that had seen the landmark."""
    n = mu.shape[0]
    m_obs, d = z.shape
    used = np.zeros(m_obs, np.int8)
    zhat = np.empty(d)
    g_s = np.empty((d, 3))
    g_l = np.empty((d, d))
    lg = np.empty((d, d))
    q = np.empty((d, d))
    pg = np.empty((3, d))
    k = np.empty((3, d))
    nus = np.empty((n, d))
    ss = np.empty((n, d, d))
    dets = np.empty(n)
    s_invs = np.empty((n, d, d))
    mu_new = np.empty((n, 3))
    sig_new = np.empty((n, 3, 3))
    c_mix = np.empty((d, d))
    c_inv = np.empty((d, d))
    mean_nu = np.empty(d)
    for o in range(m_obs):
        col = cols[o]
        any_seen = False
        for i in range(n):
            had_seen[o, i] = seen[i, col]
            any_seen = any_seen or seen[i, col]
        if not any_seen:
            used[o] = 2
            continue
        w_sum = 0.0
        for i in range(n):
            if not seen[i, col]:
                continue
            w_sum += w[i]
            _predict(mu[i], means[i, col], d, zhat, g_s, g_l)
            _innovation(z[o], zhat, d, nus[i])
            _gcg(g_l, covs[i, col], lg, q)  # Q = G_l Σ_l G_lᵀ + R
            for a in range(d):
                q[a, a] += r[o, a]
            s = ss[i]
            if proposal:  # S = G_s P G_sᵀ + Q, μ = s + K ν, Σ = P − K S Kᵀ
                _gcg(g_s, sigma[i], pg, s)
                for a in range(d):
                    for b in range(d):
                        s[a, b] += q[a, b]
                dets[i] = inverse(s, d, s_invs[i])
                for a in range(3):
                    mu_new[i, a] = mu[i, a]
                _kalman(sigma[i], pg, s_invs[i], nus[i], k, mu_new[i], sig_new[i])
            else:
                s[:, :] = q
                dets[i] = inverse(s, d, s_invs[i])
        # the gate: ν̄ᵀ C⁻¹ ν̄ of the weighted mixture matched to one Gaussian
        mean_nu[:] = 0.0
        for i in range(n):
            if seen[i, col]:
                for a in range(d):
                    mean_nu[a] += w[i] / w_sum * nus[i, a]
        c_mix[:, :] = 0.0
        for i in range(n):
            if seen[i, col]:
                wi = w[i] / w_sum
                for a in range(d):
                    for b in range(d):
                        dn = (nus[i, a] - mean_nu[a]) * (nus[i, b] - mean_nu[b])
                        c_mix[a, b] += wi * (ss[i, a, b] + dn)
        inverse(c_mix, d, c_inv)
        maha = 0.0
        for a in range(d):
            for b in range(d):
                maha += mean_nu[a] * c_inv[a, b] * mean_nu[b]
        if maha > gate:
            continue
        used[o] = 1
        for i in range(n):
            if not seen[i, col]:
                continue
            if proposal:
                mu[i, 0] = mu_new[i, 0]
                mu[i, 1] = mu_new[i, 1]
                mu[i, 2] = wrap(mu_new[i, 2])
                sigma[i] = sig_new[i]
            logw[i] += _log_normal(nus[i], s_invs[i], dets[i], d) / gain
    return used


@njit(cache=True, nogil=True)
def sample(mu, sigma, e, out) -> None:
    """out = μ + L e, L the lower Cholesky factor of each PSD Σ (a squared pivot below
    1e-12 of the trace counts as zero and its column is dropped: a singular Σ, e.g. a
    walker standing still, needs no jitter); θ wrapped."""
    for i in range(mu.shape[0]):
        a = sigma[i]
        tiny = math.sqrt(1e-12 * max(a[0, 0] + a[1, 1] + a[2, 2], 1e-300))
        l00 = math.sqrt(max(a[0, 0], 0.0))
        l10 = a[1, 0] / l00 if l00 > tiny else 0.0
        l20 = a[2, 0] / l00 if l00 > tiny else 0.0
        l11 = math.sqrt(max(a[1, 1] - l10 * l10, 0.0))
        l21 = (a[2, 1] - l20 * l10) / l11 if l11 > tiny else 0.0
        l22 = math.sqrt(max(a[2, 2] - l20 * l20 - l21 * l21, 0.0))
        out[i, 0] = mu[i, 0] + l00 * e[i, 0]
        out[i, 1] = mu[i, 1] + l10 * e[i, 0] + l11 * e[i, 1]
        out[i, 2] = wrap(mu[i, 2] + l20 * e[i, 0] + l21 * e[i, 1] + l22 * e[i, 2])


@njit(cache=True, nogil=True)
def update_landmarks(poses, means, covs, seen, cols, z, r, used, had_seen, gain, logw) -> None:
    """The landmark EKF step at the sampled poses for each used observation in turn;
    landmarks new to a particle initialised from the inverse model (covariance
    J_z R J_zᵀ); a particle that met the landmark earlier in this step (not in
    had_seen) is weighted now."""
    n = poses.shape[0]
    d = z.shape[1]
    zhat = np.empty(d)
    g_s = np.empty((d, 3))
    g_l = np.empty((d, d))
    nu = np.empty(d)
    s = np.empty((d, d))
    s_inv = np.empty((d, d))
    pg = np.empty((d, d))
    k = np.empty((d, d))
    for o in range(len(cols)):
        if used[o] == 0:
            continue
        col = cols[o]
        for i in range(n):
            lm = means[i, col]
            lc = covs[i, col]
            if seen[i, col]:
                _predict(poses[i], lm, d, zhat, g_s, g_l)
                _innovation(z[o], zhat, d, nu)
                _gcg(g_l, lc, pg, s)  # S = G_l Σ G_lᵀ + R
                for a in range(d):
                    s[a, a] += r[o, a]
                det = inverse(s, d, s_inv)
                _kalman(lc, pg, s_inv, nu, k, lm, lc)
                if d == 3:
                    lm[2] = wrap(lm[2])
                if not had_seen[o, i]:  # met earlier in this step: weighted now
                    logw[i] += _log_normal(nu, s_inv, det, d) / gain
            else:
                rr, b_ = z[o, 0], z[o, 1]
                ang = poses[i, 2] + b_
                c, sn = math.cos(ang), math.sin(ang)
                lm[0] = poses[i, 0] + rr * c
                lm[1] = poses[i, 1] + rr * sn
                # J_z = [[c, −r s], [s, r c]] (and 1 for the yaw): J_z R J_zᵀ
                v0, v1 = r[o, 0], r[o, 1]
                lc[:, :] = 0.0
                lc[0, 0] = c * c * v0 + rr * rr * sn * sn * v1
                lc[1, 1] = sn * sn * v0 + rr * rr * c * c * v1
                lc[0, 1] = lc[1, 0] = c * sn * v0 - rr * rr * sn * c * v1
                if d == 3:
                    lm[2] = wrap(poses[i, 2] + z[o, 2])
                    lc[2, 2] = r[o, 2]
                seen[i, col] = True
