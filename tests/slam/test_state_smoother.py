"""Full-state RTS smoothing of EKF-SLAM (slam.state_smoother): on a linear-Gaussian SLAM
problem it equals the batch least-squares solution; the bridge between epochs keeps the
epochs' poses; on MRCLAM the poses take the final map."""

import numpy as np
import pytest

from slam.rts import arc_steps, rts_smooth
from slam.state_smoother import StateSmoother, bridge, bridge_covariances


def _linear_slam(seed: int):
    """A linear SLAM run: pose (x, y, θ) moved by x' = x + a θ + u (F = I + a e₀e₂ᵀ +
    b e₁e₂ᵀ, as the EKF's composed odometry), noise Q on the pose; landmarks observed as
    z = l − (x, y) + noise R, each joining the state at its first sighting (l = p + z).
    Filtered as EkfSlam does, recording its epochs; returns the smoother and the batch
    solution's poses, and the filter's last state."""
    rng = np.random.default_rng(seed)
    q, r, steps = np.diag([0.02, 0.01, 0.003]), 0.05 * np.eye(2), 40
    lms = rng.uniform(-3, 3, size=(4, 2))
    x, p = np.zeros(3), np.zeros((3, 3))
    index: dict[int, int] = {}
    sm = StateSmoother(3, budget_bytes=1e9)
    moments = StateSmoother(3, budget_bytes=1e9)  # the same predictions, as moments
    rows, rhs = [], []  # the batch problem: whitened rows over [poses..., landmarks...]
    n_pose = 3 * (steps + 1)
    w_q, w_r = np.linalg.inv(np.linalg.cholesky(q)), np.linalg.inv(np.linalg.cholesky(r))

    def row(entries, width):
        out = np.zeros((width, n_pose + 2 * len(lms)))
        for col, block in entries:
            out[:, col : col + block.shape[1]] += block
        return out

    rows.append(row([(0, 1e6 * np.eye(3))], 3))  # the known start
    rhs.append(np.zeros(3))
    truth = np.zeros(3)
    for k in range(1, steps + 1):
        a, b = rng.normal(0, 0.5, 2)
        f = np.eye(3)
        f[0, 2], f[1, 2] = a, b
        u = rng.normal(0, 0.3, 3)
        truth = f @ truth + u + rng.multivariate_normal(np.zeros(3), q)
        # the prediction, recorded as EkfSlam._sync does, then written into the state
        top_mean, top_cov = f @ x[:3] + u, f @ p[:3, :3] @ f.T + q
        sm.begin(k, x, p, a, b, None, top_mean, top_cov)
        big = np.eye(len(x))
        big[:3, :3] = f
        pred_rows = (big @ p @ big.T)[:3]
        pred_rows[:, :3] = top_cov
        moments.begin_sampled(k, x, p, top_mean, (p @ big.T)[:, :3], pred_rows)
        p = big @ p @ big.T
        p[:3, :3] = top_cov
        x = x.copy()
        x[:3] = top_mean
        rows.append(w_q @ row([(3 * k, np.eye(3)), (3 * (k - 1), -f)], 3))
        rhs.append(w_q @ u)
        for i in rng.choice(len(lms), size=2, replace=False):
            z = lms[i] - truth[:2] + rng.multivariate_normal(np.zeros(2), r)
            rows.append(w_r @ row([(n_pose + 2 * i, np.eye(2)), (3 * k, -np.eye(3)[:2])], 2))
            rhs.append(w_r @ z)
            if i not in index:  # l = p + z: augment
                n = len(x)
                h = np.zeros((2, n))
                h[:, :2] = np.eye(2)
                aug = np.zeros((n + 2, n + 2))
                aug[:n, :n] = p
                aug[n:, :n] = h @ p
                aug[:n, n:] = (h @ p).T
                aug[n:, n:] = h @ p @ h.T + r
                x, p, index[i] = np.r_[x, x[:2] + z], aug, n
                continue
            j = index[i]
            h = np.zeros((2, len(x)))
            h[:, j : j + 2], h[:, :2] = np.eye(2), -np.eye(2)
            s = h @ p @ h.T + r
            gain = p @ h.T @ np.linalg.inv(s)
            x = x + gain @ (z - h @ x)
            p = (np.eye(len(x)) - gain @ h) @ p
    a_mat, b_vec = np.vstack(rows), np.concatenate(rhs)
    # landmarks never seen would make it singular: every one is seen (2 of 4, 40 times)
    sol = np.linalg.lstsq(a_mat, b_vec, rcond=None)[0]
    return sm, sol[:n_pose].reshape(-1, 3), x, p, moments


@pytest.mark.parametrize("seed", [0, 1])
def test_full_state_rts_equals_the_batch_solution_of_a_linear_slam_problem(seed):
    sm, batch, x, p, moments = _linear_slam(seed)
    steps, smoothed, filtered = sm.smoothed(x, p)
    assert list(steps) == list(range(1, 41))
    np.testing.assert_allclose(smoothed, batch[1:], atol=1e-6)
    # and it is not the filter's answer
    assert np.abs(filtered[:-1] - batch[1:-1]).max() > 0.05
    # the prediction given by its moments (FastSLAM's form: Cov(x_e, top⁻) and the
    # predicted covariance's top rows) smooths the same
    np.testing.assert_allclose(moments.smoothed(x, p)[1], batch[1:], atol=1e-6)


def test_bridge_keeps_the_epochs_poses_and_moves_the_stretches_rigidly():
    """Between two epochs the odometry-only stretch is moved rigidly onto the smoothed
    pose that starts it, its covariance grown from zero there; the pose-only smoother
    then keeps every epoch's pose and ends each stretch at the next one's."""
    rng = np.random.default_rng(3)
    k = 30
    ds, dth = np.full(k, 0.1), rng.normal(0, 0.05, k)
    q = np.tile(np.diag([1e-4, 1e-4]), (k, 1, 1))
    deltas, delta_covs = arc_steps(ds, dth, q)
    filtered = np.zeros((k, 3))
    for j in range(1, k):
        c, s = np.cos(filtered[j - 1, 2]), np.sin(filtered[j - 1, 2])
        d = deltas[j]
        filtered[j] = filtered[j - 1] + (c * d[0] - s * d[1], s * d[0] + c * d[1], d[2])
    covs = np.tile(np.eye(3) * 1e-3, (k, 1, 1))
    steps = np.array([5, 5, 17])
    smoothed = filtered[steps] + np.array([[0.3, -0.2, 0.1], [0.2, 0.1, 0.05], [-0.1, 0.2, -0.1]])
    means, bcovs = bridge(filtered, covs, deltas, delta_covs, steps, smoothed, filtered[steps])
    np.testing.assert_allclose(means[:5], filtered[:5])  # before the first epoch: as filtered
    np.testing.assert_allclose(bcovs[:5], covs[:5])
    np.testing.assert_allclose(means[[5, 17]], smoothed[[1, 2]], atol=1e-12)  # the last at 5
    assert np.all(bcovs[[5, 17]] == 0)
    assert np.all(np.diff(np.trace(bcovs[6:17], axis1=1, axis2=2)) > 0)
    # rigid: distances between poses within a stretch are the filtered ones
    seg = slice(6, 17)
    np.testing.assert_allclose(
        np.linalg.norm(np.diff(means[seg, :2], axis=0), axis=1),
        np.linalg.norm(np.diff(filtered[seg, :2], axis=0), axis=1),
    )
    out = rts_smooth(means, bcovs, deltas, delta_covs)
    np.testing.assert_allclose(out[[5, 17]], smoothed[[1, 2]], atol=1e-6)


def test_bridged_covariances_are_the_odometry_propagation_written_in_matrices():
    """The compiled bridge (written out element by element) equals F P Fᵀ + R q Rᵀ
    in numpy, F the Jacobian of the composition by the pose and R the rotation by the
    previous heading; zero at the anchor, untouched before it."""
    rng = np.random.default_rng(11)
    k = 12
    means = rng.normal(0, 1, (k, 3))
    deltas = rng.normal(0, 0.2, (k, 3))
    a = rng.normal(0, 0.1, (k, 3, 3))
    delta_covs = a @ np.transpose(a, (0, 2, 1))
    covs = np.tile(np.eye(3), (k, 1, 1))
    anchor = np.zeros(k, dtype=np.bool_)
    anchor[[3, 8]] = True
    out = covs.copy()
    bridge_covariances(means, deltas, delta_covs, anchor, out)
    np.testing.assert_array_equal(out[:3], covs[:3])
    expect = np.zeros((3, 3))
    for j in range(3, k):
        if anchor[j]:
            expect = np.zeros((3, 3))
        else:
            th = means[j - 1, 2]
            c, s = np.cos(th), np.sin(th)
            dx, dy = deltas[j, :2]
            f = np.eye(3)
            f[0, 2], f[1, 2] = -s * dx - c * dy, c * dx - s * dy
            r = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            expect = f @ expect @ f.T + r @ delta_covs[j] @ r.T
        np.testing.assert_allclose(out[j], expect, rtol=1e-13, atol=1e-15)


def test_over_its_memory_budget_the_pose_alone_is_smoothed_and_it_says_so():
    """The epochs are kept within smoother_budget_mb; past it the filter falls back to the
    pose-only smoother (the same trajectory as smoother=rts) and its diagnostics say so."""
    from hardware.calibration import WalkerCalibration
    from hardware.messages import EncoderTicks, RangeBearing
    from slam.base import create
    from slam.ekf_slam import EkfSlamConfig

    def run(**cfg):
        cal = WalkerCalibration()
        ekf = create("ekf-slam", cal, EkfSlamConfig(**cfg))
        m = cal.metres_per_count
        for k in range(60):
            ekf.process(EncoderTicks(0.1 * k, round(0.02 * k / m), round(0.021 * k / m)))
            ekf.process(RangeBearing(0.1 * k, 1 + k % 3, 2.0 - 0.01 * k, 0.3 * (k % 3 - 1)))
        return ekf

    small = run(smoother_budget_mb=0.01)  # ~40 epochs of a 9-state covariance fit
    assert small._full.exceeded is not None and small._full.epochs == []
    assert "smoother_budget_mb (0.01 MB)" in small.diagnostics()["note"]
    pose_only = run(smoother="rts")
    np.testing.assert_allclose(small.trajectory().poses, pose_only.trajectory().poses)
    full = run()
    assert full._full.exceeded is None and "note" not in full.diagnostics()
    assert np.abs(full.trajectory().poses - pose_only.trajectory().poses).max() > 1e-4
    with pytest.raises(ValueError, match="smoother_budget_mb must be > 0"):
        EkfSlamConfig(smoother_budget_mb=0)
