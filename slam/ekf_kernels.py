"""Compiled (numba) EKF-SLAM corrections, in place on the state (x, P).

`range_bearing_update` is the closed-form update by one range-bearing observation (H has
a pose block G_s and the landmark's block G_l, both from (dx, dy), so P Hᵀ is two
combinations of five columns of P and S a 2×2); `apply` is the correction every update
ends with, x += K ν and P −= K (P Hᵀ)ᵀ symmetrised, for any H (the absolute
observations use it with their own P Hᵀ). In numpy the closed form took ~15 calls on
vectors of the state's length per observation: their per-call cost, not the arithmetic,
was most of an EKF-SLAM step (issue 13).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from slam.kernel_math import wrap

TWO_PI = 2.0 * math.pi


@njit(cache=True, nogil=True)
def apply(x, p, k, pht, nu) -> None:
    """x += K ν (θ = x[2] wrapped to (−π, π]); P ← P − ½ (K (P Hᵀ)ᵀ + (P Hᵀ) Kᵀ), which is
    P − K S Kᵀ symmetrised."""
    n, m = k.shape
    for a in range(n):
        acc = 0.0
        for e in range(m):
            acc += k[a, e] * nu[e]
        x[a] += acc
    x[2] = wrap(x[2])
    for a in range(n):
        for b in range(a, n):
            acc = 0.0
            for e in range(m):
                acc += k[a, e] * pht[b, e] + k[b, e] * pht[a, e]
            v = 0.5 * (p[a, b] + p[b, a]) - 0.5 * acc
            p[a, b] = v
            p[b, a] = v


@njit(cache=True, nogil=True)
def range_bearing_update(x, p, j, z_range, z_bearing, var_r, var_b, gate) -> bool:
    """The Kalman update of (x, P) by range z_range and bearing z_bearing of the landmark
    at state index j (noise variances var_r, var_b); False (and no change) when the
    innovation's squared Mahalanobis distance exceeds `gate`."""
    n = x.shape[0]
    dx, dy = x[j] - x[0], x[j + 1] - x[1]
    q = max(dx * dx + dy * dy, 1e-12)
    r = math.sqrt(q)
    # G_l = [[a, b], [c, d]]; G_s = [−G_l | (0, −1)ᵀ]
    a, b, c, d = dx / r, dy / r, -dy / q, dx / q
    pht = np.empty((n, 2))
    for i in range(n):
        pj = p[i, j] - p[i, 0]
        pj1 = p[i, j + 1] - p[i, 1]
        pht[i, 0] = a * pj + b * pj1
        pht[i, 1] = c * pj + d * pj1 - p[i, 2]
    h0 = pht[j, 0] - pht[0, 0]
    h1 = pht[j, 1] - pht[0, 1]
    g0 = pht[j + 1, 0] - pht[1, 0]
    g1 = pht[j + 1, 1] - pht[1, 1]
    s00 = a * h0 + b * g0 + var_r
    s01 = a * h1 + b * g1
    s10 = c * h0 + d * g0 - pht[2, 0]
    s11 = c * h1 + d * g1 - pht[2, 1] + var_b
    nu = np.empty(2)
    nu[0] = z_range - r
    e = z_bearing - math.atan2(dy, dx) + x[2]
    nu[1] = e - TWO_PI * round(e / TWO_PI)  # math.remainder
    det = s00 * s11 - s01 * s10
    i00, i01, i10, i11 = s11 / det, -s01 / det, -s10 / det, s00 / det
    m0 = i00 * nu[0] + i01 * nu[1]
    m1 = i10 * nu[0] + i11 * nu[1]
    if nu[0] * m0 + nu[1] * m1 > gate:
        return False
    k = np.empty((n, 2))  # K = P Hᵀ S⁻¹
    for i in range(n):
        k[i, 0] = pht[i, 0] * i00 + pht[i, 1] * i10
        k[i, 1] = pht[i, 0] * i01 + pht[i, 1] * i11
    apply(x, p, k, pht, nu)
    return True
