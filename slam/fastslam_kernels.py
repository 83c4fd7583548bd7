"""Compiled (numba) FastSLAM observation step: the proposal, gate and weights, the pose
sample and the landmark EKFs, for every particle in one loop each.

The arithmetic of slam.fastslam (its docstring has the equations), written per particle
on the small matrices (D = 2: range, bearing; D = 3: with the tag's yaw) instead of as
~25 numpy calls on stacked arrays per observation: at 100 particles a numpy call costs
more than its arithmetic. The random draws stay with the caller (numpy's Generator, so a
run is reproducible from its seed and draws what it drew before).

Conventions: poses (N, 3); motion covariances `sigma` (N, 3, 3); landmark means (N, C, D)
and covariances (N, C, D, D); seen (N, C); an observation m is (cols[m], z[m] (D,), its
noise variances r[m] (D,): R is diagonal). With known IDs every particle keeps landmark
l in the same column; a sighting without an ID (`associate`) goes to a column each
particle chooses for itself, so the landmark step takes a column per observation and
particle, cols (M, N), and its status used (M, N).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from slam.kernel_math import copy_into, fill, greedy_pairs, inverse, wrap

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
    fill(g_s, 0.0)
    fill(g_l, 0.0)
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


@njit(cache=True, nogil=True, inline="always")
def _work(d):
    """Scratch for one observation step: ẑ, G_s, G_l, G_l Σ_l, Q, P G_sᵀ, K."""
    return (
        np.empty(d), np.empty((d, 3)), np.empty((d, d)), np.empty((d, d)), np.empty((d, d)),
        np.empty((3, d)), np.empty((3, d)),
    )  # fmt: skip


@njit(cache=True, nogil=True, inline="always")
def _observe(pose, sigma_i, lm, lc, z_o, r_o, d, proposal, work, nu, s, s_inv, mu_out, sig_out):
    """One observation z_o of the landmark (lm, lc) from a particle's proposal (pose,
    sigma_i): ν, S = [G_s P G_sᵀ +] G_l Σ_l G_lᵀ + R and S⁻¹ (returns det S); with
    `proposal` also its Kalman step, μ = s + K ν, Σ = P − K S Kᵀ, into mu_out (holding
    the pose) and sig_out (may be sigma_i)."""
    zhat, g_s, g_l, lg, q, pg, k = work
    _predict(pose, lm, d, zhat, g_s, g_l)
    _innovation(z_o, zhat, d, nu)
    _gcg(g_l, lc, lg, q)
    for a in range(d):
        q[a, a] += r_o[a]
    if not proposal:
        copy_into(s, q)
        return inverse(s, d, s_inv)
    _gcg(g_s, sigma_i, pg, s)
    for a in range(d):
        for b in range(d):
            s[a, b] += q[a, b]
    det = inverse(s, d, s_inv)
    _kalman(sigma_i, pg, s_inv, nu, k, mu_out, sig_out)
    return det


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
    work = _work(d)
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
            for a in range(3):
                mu_new[i, a] = mu[i, a]
            dets[i] = _observe(
                mu[i], sigma[i], means[i, col], covs[i, col], z[o], r[o], d, proposal, work,
                nus[i], ss[i], s_invs[i], mu_new[i], sig_new[i],
            )  # fmt: skip
        # the gate: ν̄ᵀ C⁻¹ ν̄ of the weighted mixture matched to one Gaussian
        for a in range(d):
            mean_nu[a] = 0.0
        for i in range(n):
            if seen[i, col]:
                for a in range(d):
                    mean_nu[a] += w[i] / w_sum * nus[i, a]
        fill(c_mix, 0.0)
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
                copy_into(sigma[i], sig_new[i])
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
def update_landmarks(
    poses, means, covs, seen, reserved, cols, z, r, used, had_seen, gain, logw
) -> None:
    """The landmark EKF step at the sampled poses for each observation o and particle i
    with used[o, i] ≠ 0, in turn; landmarks new to a particle initialised from the
    inverse model (covariance J_z R J_zᵀ); a particle that met the landmark earlier in
    this step (not in had_seen) is weighted now. cols[o, i] < 0: a landmark new to
    particle i in the first column it has free and no known ID holds (`reserved`),
    written back to cols (the caller makes sure there is one)."""
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
    for o in range(cols.shape[0]):
        for i in range(n):
            if used[o, i] == 0:
                continue
            col = cols[o, i]
            if col < 0:
                col = 0
                while seen[i, col] or reserved[col]:
                    col += 1
                cols[o, i] = col
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
                fill(lc, 0.0)
                lc[0, 0] = c * c * v0 + rr * rr * sn * sn * v1
                lc[1, 1] = sn * sn * v0 + rr * rr * c * c * v1
                lc[0, 1] = lc[1, 0] = c * sn * v0 - rr * rr * sn * c * v1
                if d == 3:
                    lm[2] = wrap(poses[i, 2] + z[o, 2])
                    lc[2, 2] = r[o, 2]
                seen[i, col] = True


@njit(cache=True, nogil=True)
def associate(
    mu, sigma, means, covs, seen, settled, z, r, inflation, gate, new_gate, gain, proposal,
    logw, cols, status,
) -> None:  # fmt: skip
    """Range-bearing sightings z (M, 2) without IDs, each particle its own data
    association (FastSLAM 2.0's per-particle maximum likelihood, with mutual exclusion):

    1. the squared Mahalanobis distance of every sighting to every landmark of the
       particle, S = G_s Σ G_sᵀ + G_l Σ_l G_lᵀ + R, Σ its proposal covariance, divided
       by `inflation` for the landmarks `settled` (N, C) (slam.association's
       AssociationConfig.inflation) — but for the landmarks whose distance D from the
       proposal mean lies so far outside the sightings' ranges that the range alone puts
       every sighting beyond the gate: d² ≥ ν_r² / S_rr and S_rr ≤ tr Σ_xy + tr Σ_l +
       max σ_r² (exact: most of a large map skipped at the price of a distance);
    2. the pairs within `gate` taken greedily, nearest first, each sighting and
       landmark at most once;
    3. each sighting in turn: a paired one folded into the proposal and the weight as a
       known landmark is (`fold`); an unpaired one weighs the particle by p₀, the
       density of a new landmark's sighting at the gate, N at squared distance `gate`
       with S = G_s Σ G_sᵀ + 2R (the inverse model's landmark covariance seen through
       the model again is R), so that pairing and not pairing are compared on one scale.

    Writes cols[o, i] (the landmark's column, −1: none) and status[o, i]: 1 paired, 2 a
    new landmark (beyond `new_gate` from every landmark of the particle), 0 ambiguous
    (within `new_gate` of one but paired with none: not used)."""
    n = mu.shape[0]
    m_obs = z.shape[0]
    cap = means.shape[1]
    d = 2
    work = _work(d)
    zhat, g_s, g_l, lg, q, pg, _ = work
    s = np.empty((d, d))
    s_inv = np.empty((d, d))
    nu = np.empty(d)
    point = np.empty(d)
    cand = np.empty(cap, np.int64)
    taken = np.empty(cap, np.bool_)
    pick = np.empty(m_obs, np.int64)
    d2 = np.empty((m_obs, cap))
    d2_min = np.empty(m_obs)
    r_min, r_max, var_r = np.inf, 0.0, 0.0
    for o in range(m_obs):
        r_min = min(r_min, z[o, 0])
        r_max = max(r_max, z[o, 0])
        var_r = max(var_r, r[o, 0])
    for i in range(n):
        nc = 0
        spread = var_r + (sigma[i, 0, 0] + sigma[i, 1, 1] if proposal else 0.0)
        for c in range(cap):
            if not seen[i, c]:
                continue
            dx = means[i, c, 0] - mu[i, 0]
            dy = means[i, c, 1] - mu[i, 1]
            dist = math.sqrt(dx * dx + dy * dy)
            gap = max(dist - r_max, r_min - dist, 0.0)
            k = inflation if settled[i, c] else 1.0
            if gap * gap > gate * k * (spread + covs[i, c, 0, 0] + covs[i, c, 1, 1]):
                continue
            _predict(mu[i], means[i, c], d, zhat, g_s, g_l)
            _gcg(g_l, covs[i, c], lg, q)
            if proposal:
                _gcg(g_s, sigma[i], pg, s)
                for a in range(d):
                    for b in range(d):
                        q[a, b] += s[a, b]
            for o in range(m_obs):
                for a in range(d):
                    for b in range(d):
                        s[a, b] = q[a, b]
                    s[a, a] += r[o, a]
                inverse(s, d, s_inv)
                _innovation(z[o], zhat, d, nu)
                maha = 0.0
                for a in range(d):
                    for b in range(d):
                        maha += nu[a] * s_inv[a, b] * nu[b]
                d2[o, nc] = maha / k
            cand[nc] = c
            nc += 1
        greedy_pairs(d2[:, :nc], gate, pick, taken[:nc])
        for o in range(m_obs):
            cols[o, i] = cand[pick[o]] if pick[o] >= 0 else -1
            d2_min[o] = np.inf
            for kk in range(nc):
                d2_min[o] = min(d2_min[o], d2[o, kk])
        for o in range(m_obs):
            c = cols[o, i]
            if c >= 0:
                det = _observe(
                    mu[i], sigma[i], means[i, c], covs[i, c], z[o], r[o], d, proposal, work,
                    nu, s, s_inv, mu[i], sigma[i],
                )  # fmt: skip
                mu[i, 2] = wrap(mu[i, 2])
                logw[i] += _log_normal(nu, s_inv, det, d) / gain
                status[o, i] = 1
                continue
            ang = mu[i, 2] + z[o, 1]
            point[0] = mu[i, 0] + z[o, 0] * math.cos(ang)
            point[1] = mu[i, 1] + z[o, 0] * math.sin(ang)
            _predict(mu[i], point, d, zhat, g_s, g_l)
            if proposal:
                _gcg(g_s, sigma[i], pg, s)
            else:
                fill(s, 0.0)
            for a in range(d):
                s[a, a] += 2.0 * r[o, a]
            det = inverse(s, d, s_inv)
            logw[i] += -0.5 * (gate + math.log(det) + d * LOG_TWO_PI) / gain
            status[o, i] = 2 if d2_min[o] > new_gate else 0


# -- the particles' moments for the whole-state smoother (slam.state_smoother) ---------------


@njit(cache=True, nogil=True)
def _top_mean(top, w, mean) -> None:
    """The weighted mean of the particles' top rows (N, t) into mean (t,), circular in θ."""
    s = c = 0.0
    for j in range(top.shape[1]):
        mean[j] = 0.0
    for i in range(top.shape[0]):
        for j in range(top.shape[1]):
            mean[j] += w[i] * top[i, j]
        s += w[i] * math.sin(top[i, 2])
        c += w[i] * math.cos(top[i, 2])
    mean[2] = math.atan2(s, c)


@njit(cache=True, nogil=True)
def state_moments(top, pending, means, covs, cols, w, x, p, dev) -> None:
    """The filtered state [top (t), landmarks cols (D each)] of the particles: its weighted
    mean x (n,) (circular in θ and, D = 3, in the tags' yaw), the particles' deviations
    from it dev (N, n) (angles wrapped), and p (n, n) = their weighted covariance plus the
    weighted mean of the motion covariances `pending` (on the pose) and of the landmarks'
    covariances (on their blocks)."""
    n_p, t = top.shape
    d = means.shape[2]
    n = t + d * len(cols)
    _top_mean(top, w, x)
    for m in range(len(cols)):
        col = cols[m]
        for k in range(d):
            acc = s = c = 0.0
            if k == 2:  # a tag's yaw
                for i in range(n_p):
                    s += w[i] * math.sin(means[i, col, k])
                    c += w[i] * math.cos(means[i, col, k])
                acc = math.atan2(s, c)
            else:
                for i in range(n_p):
                    acc += w[i] * means[i, col, k]
            x[t + d * m + k] = acc
    for i in range(n_p):
        for j in range(t):
            dev[i, j] = top[i, j] - x[j]
        dev[i, 2] = wrap(dev[i, 2])
        for m in range(len(cols)):
            for k in range(d):
                v = means[i, cols[m], k] - x[t + d * m + k]
                dev[i, t + d * m + k] = wrap(v) if k == 2 else v
    for a in range(n):
        for b in range(n):
            p[a, b] = 0.0
    for i in range(n_p):
        for a in range(n):
            va = w[i] * dev[i, a]
            for b in range(a, n):
                p[a, b] += va * dev[i, b]
        for a in range(3):
            for b in range(a, 3):
                p[a, b] += w[i] * pending[i, a, b]
        for m in range(len(cols)):
            o = t + d * m
            for a in range(d):
                for b in range(a, d):
                    p[o + a, o + b] += w[i] * covs[i, cols[m], a, b]
    for a in range(n):
        for b in range(a):
            p[a, b] = p[b, a]


@njit(cache=True, nogil=True)
def prediction_moments(top, pending, w, before, mean, cross, rows) -> None:
    """The prediction since the last update, of the same particles moved on: the
    predicted top's weighted mean (t,), cross (n, t) = Cov(state then, top now) from the
    deviations `before` (N, n) of the state then, and rows (t, n) = Cov(top now, state
    now) (the top block with the motion covariances `pending`, the landmarks' part the
    cross-covariance's: they do not move)."""
    n_p, t = top.shape
    n = before.shape[1]
    _top_mean(top, w, mean)
    for a in range(n):
        for j in range(t):
            cross[a, j] = 0.0
    for a in range(t):
        for b in range(t):
            rows[a, b] = 0.0
    dt = np.empty(t)
    for i in range(n_p):
        for j in range(t):
            dt[j] = top[i, j] - mean[j]
        dt[2] = wrap(dt[2])
        for a in range(n):
            va = w[i] * before[i, a]
            for j in range(t):
                cross[a, j] += va * dt[j]
        for a in range(t):
            for b in range(t):
                rows[a, b] += w[i] * dt[a] * dt[b]
        for a in range(3):
            for b in range(3):
                rows[a, b] += w[i] * pending[i, a, b]
    for a in range(t, n):
        for j in range(t):
            rows[j, a] = cross[a, j]
