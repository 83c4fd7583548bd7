"""slam.motion's exact-arc odometry: one pose on floats equals the array path to the bit."""

from __future__ import annotations

import numpy as np

from slam.motion import apply_increment, increment_jacobians, sinc_and_derivative


def _cases(n: int = 20000):
    rng = np.random.default_rng(7)
    poses = np.column_stack(
        [rng.uniform(-50, 50, n), rng.uniform(-50, 50, n), rng.uniform(-np.pi, np.pi, n)]
    )
    ds = rng.normal(0.0, 0.05, n)
    # turns of every size: straight (below the series' 1e-4), small, in-place, wrapping
    dtheta = np.concatenate(
        [
            rng.normal(0.0, 1e-5, n // 4),
            rng.normal(0.0, 0.01, n // 4),
            rng.normal(0.0, 0.5, n // 4),
            rng.uniform(-4.0, 4.0, n - 3 * (n // 4)),
        ]
    )
    return poses, ds, dtheta


def test_one_pose_moves_exactly_as_the_array_of_poses():
    poses, ds, dtheta = _cases()
    many = apply_increment(poses, ds, dtheta)  # the broadcast path, per row
    rows = zip(poses, ds.tolist(), dtheta.tolist(), strict=True)
    one = np.array([apply_increment(p, a, b) for p, a, b in rows])
    assert np.array_equal(one, many)
    assert np.all(np.abs(one[:, 2]) <= np.pi)


def test_one_sinc_equals_the_array_sinc():
    _, _, dtheta = _cases()
    s, d = sinc_and_derivative(dtheta)
    pairs = np.array([sinc_and_derivative(float(u)) for u in dtheta])
    assert np.array_equal(pairs[:, 0], s) and np.array_equal(pairs[:, 1], d)


def test_jacobians_match_finite_differences():
    rng = np.random.default_rng(3)
    for _ in range(50):
        pose = np.array([rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-3, 3)])
        ds, dth = float(rng.normal(0, 0.3)), float(rng.normal(0, 0.6))
        f, g = increment_jacobians(float(pose[2]), ds, dth)
        h = 1e-6
        num_f = np.column_stack(
            [
                (apply_increment(pose + h * e, ds, dth) - apply_increment(pose - h * e, ds, dth))
                / (2 * h)
                for e in np.eye(3)
            ]
        )
        num_g = np.column_stack(
            [
                (apply_increment(pose, ds + h, dth) - apply_increment(pose, ds - h, dth)) / (2 * h),
                (apply_increment(pose, ds, dth + h) - apply_increment(pose, ds, dth - h)) / (2 * h),
            ]
        )
        assert np.allclose(f, num_f, atol=1e-6) and np.allclose(g, num_g, atol=1e-6)
