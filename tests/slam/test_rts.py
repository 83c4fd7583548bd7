"""RTS smoothing of a filtered pose track (slam.rts): equals the batch least-squares
solution on a linear-Gaussian problem, handles singular covariances, and on a curved
path agrees with a numerically linearised batch solution."""

import numpy as np
import pytest

from hardware.geometry import compose
from slam.motion import apply_increment, increment_jacobians
from slam.rts import arc_steps, rts_smooth


def _kalman(deltas, q, z, r, x0, p0):
    """Forward Kalman filter of x_k = x_{k−1} ⊕ Δ_k + J w (w ~ N(0, Q_k)) with position
    observations z_k (NaN: none) of covariance R, linearised at each filtered mean (for
    θ constant and zero-mean noise this is exact). Returns filtered means and covs."""
    k = len(deltas)
    x = np.zeros((k, 3))
    p = np.zeros((k, 3, 3))
    x[0], p[0] = x0, p0
    h = np.array([[1.0, 0, 0], [0, 1.0, 0]])
    for i in range(k):
        if i > 0:
            prev = x[i - 1]
            c, s = np.cos(prev[2]), np.sin(prev[2])
            f = np.eye(3)
            f[0, 2] = -s * deltas[i, 0] - c * deltas[i, 1]
            f[1, 2] = c * deltas[i, 0] - s * deltas[i, 1]
            j = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
            x[i] = compose(prev, deltas[i])
            p[i] = f @ p[i - 1] @ f.T + j @ q[i] @ j.T
        if np.all(np.isfinite(z[i])):
            s_ = h @ p[i] @ h.T + r
            gain = p[i] @ h.T @ np.linalg.inv(s_)
            x[i] = x[i] + gain @ (z[i] - x[i, :2])
            p[i] = (np.eye(3) - gain @ h) @ p[i]
    return x, p


def _batch(deltas, q, z, r, x0, p0):
    """The batch MAP estimate of the same linear problem (θ fixed, known)."""
    k = len(deltas)
    rows, rhs, w = [], [], []
    # prior on x_0 (positions only; θ is constant and known)
    rows.append(np.eye(2, 2 * k))
    rhs.append(x0[:2])
    w.append(np.linalg.inv(p0[:2, :2]))
    for i in range(1, k):
        a = np.zeros((2, 2 * k))
        a[:, 2 * i : 2 * i + 2] = np.eye(2)
        a[:, 2 * i - 2 : 2 * i] = -np.eye(2)
        c, s = np.cos(x0[2]), np.sin(x0[2])
        rot = np.array([[c, -s], [s, c]])
        rows.append(a)
        rhs.append(rot @ deltas[i, :2])
        w.append(np.linalg.inv(rot @ q[i][:2, :2] @ rot.T))
        if np.all(np.isfinite(z[i])):
            b = np.zeros((2, 2 * k))
            b[:, 2 * i : 2 * i + 2] = np.eye(2)
            rows.append(b)
            rhs.append(z[i])
            w.append(np.linalg.inv(r))
    n = sum(wi.shape[0] for wi in w)
    a = np.vstack(rows)
    big_w = np.zeros((n, n))
    o = 0
    for wi in w:
        big_w[o : o + len(wi), o : o + len(wi)] = wi
        o += len(wi)
    y = np.concatenate(rhs)
    sol = np.linalg.solve(a.T @ big_w @ a, a.T @ big_w @ y)
    return sol.reshape(k, 2)


def test_equals_the_batch_solution_on_a_linear_gaussian_track():
    rng = np.random.default_rng(0)
    k = 60
    theta = 0.4
    deltas = np.zeros((k, 3))
    deltas[1:, 0] = 0.1 + 0.02 * rng.standard_normal(k - 1)
    deltas[1:, 1] = 0.01 * rng.standard_normal(k - 1)
    q = np.zeros((k, 3, 3))
    q[:, 0, 0], q[:, 1, 1] = 0.02**2, 0.005**2
    z = np.full((k, 2), np.nan)
    obs = np.arange(5, k, 7)
    z[obs] = rng.standard_normal((len(obs), 2)) + np.array([1.0, 2.0])
    r = np.diag([0.05**2, 0.08**2])
    x0 = np.array([0.0, 0.0, theta])
    p0 = np.diag([0.1**2, 0.1**2, 0.0])
    means, covs = _kalman(deltas, q, z, r, x0, p0)
    smoothed = rts_smooth(means, covs, deltas, q)
    batch = _batch(deltas, q, z, r, x0, p0)
    assert smoothed[:, :2] == pytest.approx(batch, abs=1e-8)
    assert np.allclose(smoothed[:, 2], theta)
    # the last pose is the filter's; the filtered track differs from the smoothed one
    assert smoothed[-1] == pytest.approx(means[-1])
    assert np.max(np.abs(smoothed[:, :2] - means[:, :2])) > 0.05


def test_singular_covariances_known_start_and_standing_still():
    k = 5
    means = np.array([[0.0, 0, 0], [0, 0, 0], [0.1, 0, 0], [0.2, 0.05, 0.1], [0.3, 0.05, 0.1]])
    covs = np.zeros((k, 3, 3))  # everything known: nothing to smooth
    deltas = np.array([[0.0, 0, 0], [0, 0, 0], [0.1, 0, 0], [0.1, 0.05, 0.1], [0.1, 0, 0]])
    out = rts_smooth(means, covs, deltas, np.zeros((k, 3, 3)))
    assert np.all(np.isfinite(out))
    assert out == pytest.approx(means)
    assert rts_smooth(means[:1], covs[:1], deltas[:1], covs[:1]) == pytest.approx(means[:1])


def test_curved_path_pulls_the_past_toward_a_late_fix():
    """Driving a quarter circle by odometry with a heading error, a final fix corrects
    the whole path in proportion to how far along it is (the smoother moves late poses
    most, the start not at all)."""
    k = 50
    deltas = np.zeros((k, 3))
    deltas[1:] = [0.05, 0.0, (np.pi / 2) / (k - 1)]
    q = np.zeros((k, 3, 3))
    q[1:] = np.diag([1e-4, 1e-6, 1e-4])
    means = np.zeros((k, 3))
    covs = np.zeros((k, 3, 3))
    for i in range(1, k):
        means[i] = compose(means[i - 1], deltas[i])
        c, s = np.cos(means[i - 1, 2]), np.sin(means[i - 1, 2])
        f = np.array([[1, 0, -s * 0.05], [0, 1, c * 0.05], [0, 0, 1.0]])
        j = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        covs[i] = f @ covs[i - 1] @ f.T + j @ q[i] @ j.T
    # a fix at the end moves the last pose 0.1 m in x (filtered, with a small covariance)
    means[-1, 0] += 0.1
    covs[-1] = np.diag([1e-6, 1e-6, 1e-6])
    out = rts_smooth(means, covs, deltas, q)
    shift = np.hypot(*(out[:, :2] - means[:, :2]).T)
    assert shift[0] < 1e-9
    assert shift[-2] > shift[k // 2] > shift[5] > 0.0
    assert shift[-2] == pytest.approx(0.1, abs=0.02)


def test_arc_steps_are_the_exact_arc_and_its_jacobian():
    """arc_steps (vectorised) = apply_increment from the origin and G q Gᵀ with
    G = increment_jacobians at θ = 0, for straight, curved and turning-in-place steps."""
    ds = np.array([0.02, 0.03, 0.0, -0.01])
    dth = np.array([0.0, 0.2, -0.05, 0.01])
    rng = np.random.default_rng(4)
    a = rng.normal(size=(4, 2, 2))
    q = a @ np.swapaxes(a, 1, 2) * 1e-4
    deltas, covs = arc_steps(ds, dth, q)
    for k in range(4):
        np.testing.assert_allclose(deltas[k], apply_increment(np.zeros(3), ds[k], dth[k]))
        _, g = increment_jacobians(0.0, float(ds[k]), float(dth[k]))
        np.testing.assert_allclose(covs[k], g @ q[k] @ g.T, atol=1e-15)
