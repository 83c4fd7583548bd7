"""hardware.small_linalg against numpy's BLAS/LAPACK results, and the same bits whatever
kernels OpenBLAS picks (the reason it exists)."""

import os
import subprocess
import sys

import numpy as np
import pytest

from hardware import small_linalg as sl


def _spd(rng, n):
    a = rng.normal(size=(n, n))
    return a @ a.T + 0.1 * np.eye(n)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_inverse_and_solve_agree_with_numpy(n):
    rng = np.random.default_rng(n)
    for _ in range(20):
        a = rng.normal(size=(n, n))
        b = rng.normal(size=n)
        np.testing.assert_allclose(sl.inv(a), np.linalg.inv(a), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(sl.solve(a, b), np.linalg.solve(a, b), rtol=1e-8, atol=1e-10)
    with pytest.raises(np.linalg.LinAlgError):
        sl.inv(np.zeros((n, n)))
    with pytest.raises(ValueError, match="1×1 to 3×3"):
        sl.inv(np.eye(4))


def test_eigen_decompositions_agree_with_numpy():
    rng = np.random.default_rng(5)
    for m in [_spd(rng, 2) for _ in range(20)] + [np.diag([2.0, 1.0]), np.eye(2)]:
        lam, vec = sl.eigh2(m)
        np.testing.assert_allclose(lam, np.linalg.eigvalsh(m), rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(vec @ np.diag(lam) @ vec.T, m, atol=1e-12)
        np.testing.assert_allclose(vec.T @ vec, np.eye(2), atol=1e-12)
    for m in [_spd(rng, 3) for _ in range(20)] + [np.diag([3.0, 1.0, 2.0]), np.eye(3)]:
        np.testing.assert_allclose(sl.eigvalsh3(m), np.linalg.eigvalsh(m), rtol=1e-9, atol=1e-12)


def test_products_agree_with_numpy():
    rng = np.random.default_rng(6)
    j, w = rng.normal(size=(50, 3)), rng.random(50)
    a, m, v = rng.normal(size=(3, 3)), _spd(rng, 3), rng.normal(size=3)
    np.testing.assert_allclose(sl.gram(j, w), j.T @ (j * w[:, None]), rtol=1e-12)
    np.testing.assert_allclose(sl.gram(j), j.T @ j, rtol=1e-12)
    np.testing.assert_allclose(sl.congruence(a, m), a @ m @ a.T, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sl.matvec(a, v), a @ v, rtol=1e-12)
    assert sl.dot(v, v) == pytest.approx(float(v @ v), rel=1e-12)


_BITS = """
import hashlib, numpy as np
from hardware import small_linalg as sl
rng = np.random.default_rng(0)
j, w = rng.normal(size=(1000, 3)), rng.random(1000)
h = sl.gram(j, w)
out = [h, sl.solve(h, rng.normal(size=3)), sl.congruence(rng.normal(size=(3, 3)), h), j.T @ j]
print(" ".join(hashlib.md5(np.ascontiguousarray(x).tobytes()).hexdigest() for x in out))
"""


def test_the_same_bits_under_other_blas_kernels():
    """Under OPENBLAS_CORETYPE=Haswell (valid on any x86-64 CPU with AVX2, which this
    machine kind has) the written-out results keep their bits."""

    def run(env_extra):
        env = {**os.environ, **env_extra}
        out = subprocess.run([sys.executable, "-c", _BITS], env=env, capture_output=True,
                             text=True, check=True)  # fmt: skip
        return out.stdout.split()

    default, haswell = run({}), run({"OPENBLAS_CORETYPE": "Haswell"})
    assert default[:3] == haswell[:3]
