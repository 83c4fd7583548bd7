"""Small compiled (numba) helpers the filters' kernels share: an angle wrapped to (−π, π],
the inverse of a 2×2 or 3×3 matrix, filling and copying small matrices, and greedy
nearest-neighbour pairing.

The kernels fill and copy their small arrays with loops (`fill`, `copy_vector`,
`copy_into`), not slice assignment (`a[:, :] = 0.0`, `a[i] = b[i]`), and multiply small
matrices written out, not with `@`: numba compiles a slice assignment through its general
indexing code, once per array type and function, and `@` through BLAS. Compile times on
the first run after an install, which each test worker pays: FastSLAM's `fold` 19–23 →
14–16 s; on 2026-12-05 the grid filter's `propose` 12 → 5 s, the smoother's
`bridge_covariances` 10.5 → 1.0 s, `mapping.distance.capped_squared_distances` 5.6 →
1.6 s. The same values to the bit, but for the bridge's sums of products (now written in
one order instead of BLAS's)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

TWO_PI = 2.0 * math.pi


@njit(cache=True, nogil=True, inline="always")
def wrap(a: float) -> float:
    """(−π, π], as hardware.geometry.wrap_angle."""
    return math.pi - ((math.pi - a) % TWO_PI)


@njit(cache=True, nogil=True, inline="always")
def inverse(a, d, out) -> float:
    """out = a⁻¹ of a symmetric d×d (d = 2 or 3) matrix by its adjugate; returns det a."""
    if d == 2:
        det = a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]
        out[0, 0] = a[1, 1] / det
        out[1, 1] = a[0, 0] / det
        out[0, 1] = -a[0, 1] / det
        out[1, 0] = -a[1, 0] / det
        return det
    c00 = a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]
    c01 = a[1, 2] * a[2, 0] - a[1, 0] * a[2, 2]
    c02 = a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]
    det = a[0, 0] * c00 + a[0, 1] * c01 + a[0, 2] * c02
    out[0, 0] = c00 / det
    out[1, 0] = c01 / det
    out[2, 0] = c02 / det
    out[0, 1] = (a[0, 2] * a[2, 1] - a[0, 1] * a[2, 2]) / det
    out[1, 1] = (a[0, 0] * a[2, 2] - a[0, 2] * a[2, 0]) / det
    out[2, 1] = (a[0, 1] * a[2, 0] - a[0, 0] * a[2, 1]) / det
    out[0, 2] = (a[0, 1] * a[1, 2] - a[0, 2] * a[1, 1]) / det
    out[1, 2] = (a[0, 2] * a[1, 0] - a[0, 0] * a[1, 2]) / det
    out[2, 2] = (a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]) / det
    return det


@njit(cache=True, nogil=True, inline="always")
def fill(a, value) -> None:
    """a[:, :] = value for a 2-D array."""
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            a[i, j] = value


@njit(cache=True, nogil=True, inline="always")
def copy_vector(dst, src) -> None:
    """dst[:] = src for 1-D arrays of one length."""
    for i in range(src.shape[0]):
        dst[i] = src[i]


@njit(cache=True, nogil=True, inline="always")
def copy_into(dst, src) -> None:
    """dst[:, :] = src for 2-D arrays of one shape."""
    for i in range(src.shape[0]):
        for j in range(src.shape[1]):
            dst[i, j] = src[i, j]


@njit(cache=True, nogil=True)
def greedy_pairs(d2, gate, out, taken) -> None:
    """Greedy nearest neighbour on squared distances d2 (n, m): repeatedly the smallest
    entry within `gate` whose row and column are both still free (the first in row-major
    order among equal ones), so each row and column is paired at most once. Writes each
    row's column to out (n,) (−1: none); taken (m,) is scratch. The same pairs as taking
    the entries within the gate in a stable sort of their distances (slam.association.
    nearest_neighbour)."""
    n, m = d2.shape
    out[:] = -1
    taken[:] = False
    for _ in range(min(n, m)):
        best, bi, bj = np.inf, -1, -1
        for i in range(n):
            if out[i] >= 0:
                continue
            for j in range(m):
                if not taken[j] and d2[i, j] < best:
                    best, bi, bj = d2[i, j], i, j
        if bi < 0 or not best <= gate:
            return
        out[bi] = bj
        taken[bj] = True
