"""Products, solves and eigenvalues of small matrices, written out so that their bits do
not depend on the CPU.

numpy's `@`, `np.dot` and `np.linalg` run OpenBLAS, which picks its kernels by CPU (on a
CPU with AVX-512 the SkylakeX ones, elsewhere Haswell's or Zen's): they sum in other
orders and round the last bits differently. On a laser log that is enough for the scan
matcher to accept or reject a match differently and end somewhere else (csail: ATE
0.126 m with one kernel choice, 0.163 m with another; BENCHMARKS.md). The closed forms
here give the same bits on any CPU. `einsum`'s sums of up to three terms (without
`optimize`, which would hand them to BLAS), the products of 3×3 and smaller matrices,
should too on x86: worked through for 2-, 4- and 8-lane vectors they add the same
rounded products in the same order (measured on this AVX2 machine only). A long
`einsum` reduction (`gram` over a scan's points) does not quite:
numpy accumulates it in SIMD vectors of the CPU's width (2, 4 or 8 doubles, with FMA
where there is one; numpy's einsum_sumprod.c.src) and adds the lanes at the end, so a
CPU with another vector width can round its last bits differently. Note the order is not
the written one either: on this AVX2 machine a 3-term sum over a transposed operand is
(p0 + p2) + p1. The scan path (slam.scan_matching, the covariances of slam.gtsam_smoother
and slam.scan_graph, the CARMEN importer's odometry fit) uses these instead of `@` and
np.linalg.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["congruence", "dot", "eigh2", "eigvalsh3", "gram", "inv", "matmul", "matvec", "solve"]


def matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a b for matrices (..., n, m) and (..., m, k)."""
    return np.einsum("...ij,...jk->...ik", a, b)


def matvec(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """a v for a matrix (..., n, m) and a vector (..., m)."""
    return np.einsum("...ij,...j->...i", a, v)


def dot(a: np.ndarray, b: np.ndarray) -> float:
    """aᵀ b of two vectors."""
    return float(np.einsum("i,i->", a, b))


def congruence(a: np.ndarray, m: np.ndarray) -> np.ndarray:
    """a m aᵀ (a covariance m carried by the Jacobian a)."""
    return matmul(matmul(a, m), np.swapaxes(a, -1, -2))


def gram(j: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Σₙ wₙ jₙᵀ jₙ over the rows jₙ of j (N, k): jᵀ W j (W = I without w)."""
    return np.einsum("ni,nj->ij", j, j if w is None else j * w[:, None])


def inv(a: np.ndarray) -> np.ndarray:
    """The inverse of a 1×1, 2×2 or 3×3 matrix (adjugate over determinant); raises
    np.linalg.LinAlgError when it is singular."""
    a = np.asarray(a, dtype=float)
    if a.shape not in ((1, 1), (2, 2), (3, 3)):
        raise ValueError(f"inv takes 1×1 to 3×3 matrices, got {a.shape}")
    m = a.tolist()  # Python floats: the same IEEE operations as on numpy's, ~10× cheaper
    n = len(m)
    if n == 1:
        adj, det = [[1.0]], m[0][0]
    elif n == 2:
        adj = [[m[1][1], -m[0][1]], [-m[1][0], m[0][0]]]
        det = m[0][0] * m[1][1] - m[0][1] * m[1][0]
    else:
        adj = [[0.0] * 3 for _ in range(3)]
        for i, c in enumerate(_OTHERS):
            for j, r in enumerate(_OTHERS):
                minor = m[r[0]][c[0]] * m[r[1]][c[1]] - m[r[0]][c[1]] * m[r[1]][c[0]]
                adj[i][j] = minor if (i + j) % 2 == 0 else -minor
        det = m[0][0] * adj[0][0] + m[0][1] * adj[1][0] + m[0][2] * adj[2][0]
    if det == 0.0 or not math.isfinite(det):
        raise np.linalg.LinAlgError("singular matrix")
    return np.array(adj) / det


_OTHERS = ((1, 2), (0, 2), (0, 1))  # the rows (columns) of a 3×3 matrix other than 0, 1, 2


def solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """x with a x = b for a 1×1 to 3×3 matrix a (`inv`; raises np.linalg.LinAlgError
    when a is singular)."""
    return matvec(inv(a), np.asarray(b, dtype=float))


def eigh2(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (ascending) and unit eigenvectors (columns) of a symmetric 2×2 matrix,
    in closed form."""
    a, b, d = float(m[0, 0]), float(m[0, 1]), float(m[1, 1])
    half = 0.5 * (a - d)
    root = math.hypot(half, b)
    mid = 0.5 * (a + d)
    phi = 0.5 * math.atan2(2.0 * b, a - d)  # the direction of the larger eigenvalue
    big = np.array([math.cos(phi), math.sin(phi)])
    small = np.array([-big[1], big[0]])
    return np.array([mid - root, mid + root]), np.column_stack([small, big])


def eigvalsh3(m: np.ndarray) -> np.ndarray:
    """Eigenvalues (ascending) of a symmetric 3×3 matrix, in closed form (the
    trigonometric solution of the characteristic cubic; Smith 1961)."""
    m = np.asarray(m, dtype=float)
    p1 = m[0, 1] ** 2 + m[0, 2] ** 2 + m[1, 2] ** 2
    q = (m[0, 0] + m[1, 1] + m[2, 2]) / 3.0
    if p1 == 0.0:
        return np.sort(np.diag(m).copy())
    p2 = (m[0, 0] - q) ** 2 + (m[1, 1] - q) ** 2 + (m[2, 2] - q) ** 2 + 2.0 * p1
    p = math.sqrt(p2 / 6.0)
    b = (m - q * np.eye(3)) / p
    det_b = (
        b[0, 0] * (b[1, 1] * b[2, 2] - b[1, 2] * b[2, 1])
        - b[0, 1] * (b[1, 0] * b[2, 2] - b[1, 2] * b[2, 0])
        + b[0, 2] * (b[1, 0] * b[2, 1] - b[1, 1] * b[2, 0])
    )
    phi = math.acos(min(max(det_b / 2.0, -1.0), 1.0)) / 3.0
    hi = q + 2.0 * p * math.cos(phi)
    lo = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)
    return np.array([lo, 3.0 * q - hi - lo, hi])
