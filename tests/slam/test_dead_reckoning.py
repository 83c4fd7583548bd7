"""Dead reckoning on exactly known wheel motions."""

import math

import numpy as np
import pytest

from hardware.calibration import WalkerCalibration
from hardware.messages import EncoderTicks, VelocityOdometry
from slam.base import UnknownNameError, create
from slam.dead_reckoning import DeadReckoningConfig
from slam.trajectory import Trajectory

CAL = WalkerCalibration()


def ticks_for_arc(radius, angle, steps, cal=CAL):
    """Cumulative ticks for a circular arc of the axle centre (radius > 0 turns left)."""
    b = cal.track_m
    per_count = cal.metres_per_count
    out = []
    for k in range(steps + 1):
        phi = angle * k / steps
        left = (radius - b / 2) * phi / per_count
        right = (radius + b / 2) * phi / per_count
        out.append(EncoderTicks(0.1 * k, round(left), round(right)))
    return out


@pytest.mark.parametrize("radius", [0.5, 2.0, -1.5, 10.0])
def test_arc_end_pose(radius):
    angle = 1.5 if radius > 0 else -1.5
    dr = create("dead-reckoning", CAL)
    for m in (
        ticks_for_arc(abs(radius), abs(angle), 400)
        if radius > 0
        else _mirror(ticks_for_arc(abs(radius), abs(angle), 400))
    ):
        dr.process(m)
    x, y, th = dr.estimate().pose
    ex, ey = radius * math.sin(angle), radius * (1 - math.cos(angle))
    # one count is 2.5 mm; integer rounding bounds the error to a few counts
    assert (x, y) == pytest.approx((ex, ey), abs=0.01)
    assert th == pytest.approx(angle, abs=0.01)


def _mirror(msgs):
    return [EncoderTicks(m.t, m.right, m.left) for m in msgs]


def test_exact_integration_does_not_depend_on_message_rate():
    coarse = create("dead-reckoning", CAL)
    fine = create("dead-reckoning", CAL)
    for m in ticks_for_arc(1.0, 3.0, 10):
        coarse.process(m)
    for m in ticks_for_arc(1.0, 3.0, 1000):
        fine.process(m)
    assert np.allclose(coarse.estimate().pose, fine.estimate().pose, atol=0.01)


def test_straight_line_and_covariance_grows():
    dr = create("dead-reckoning", CAL)
    for k in range(101):
        dr.process(EncoderTicks(0.01 * k, 4 * k, 4 * k))
    est = dr.estimate()
    assert est.pose == pytest.approx([400 * CAL.metres_per_count, 0.0, 0.0])
    assert np.all(np.linalg.eigvalsh(est.covariance) >= -1e-15)
    assert est.covariance[1, 1] > 0 and est.covariance[2, 2] > 0
    assert len(dr.trajectory()) == 101


def test_velocity_odometry_circle():
    dr = create("dead-reckoning", CAL, DeadReckoningConfig(initial_pose=(1.0, 0.0, math.pi / 2)))
    for k in range(1001):
        dr.process(VelocityOdometry(k * 0.01, 0.5, 0.5))  # radius 1 around the origin
    x, y, th = dr.estimate().pose
    assert math.hypot(x, y) == pytest.approx(1.0, abs=1e-9)
    assert th == pytest.approx(math.remainder(math.pi / 2 + 5.0, 2 * math.pi), abs=1e-9)


def test_unknown_localizer_lists_valid_names():
    with pytest.raises(UnknownNameError, match=r"valid: .*dead-reckoning"):
        create("kalman-magic", CAL)


def test_tum_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.01, 0.1, 50))
    poses = np.column_stack([rng.normal(size=50), rng.normal(size=50), rng.uniform(-3, 3, 50)])
    tr = Trajectory(t, poses)
    tr.write_tum(tmp_path / "a.tum")
    back = Trajectory.read_tum(tmp_path / "a.tum")
    assert np.allclose(back.t, t) and np.allclose(back.poses, poses, atol=1e-8)


def test_wheel_increment_jacobian_matches_finite_differences():
    from slam.motion import wheel_increment, wheel_increment_jacobian

    def midpoint(theta, ds_l, ds_r, track):
        ds, dth = wheel_increment(ds_l, ds_r, track)
        h = theta + 0.5 * dth
        return np.array([ds * math.cos(h), ds * math.sin(h), dth])

    rng = np.random.default_rng(7)
    for _ in range(20):
        theta, left, r = rng.uniform(-3, 3), rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2)
        ds, dth = wheel_increment(left, r, 0.64)
        j = np.array(wheel_increment_jacobian(theta, ds, dth, 0.64))
        eps = 1e-7
        num = np.column_stack(
            [
                (midpoint(theta, left + eps, r, 0.64) - midpoint(theta, left - eps, r, 0.64))
                / (2 * eps),
                (midpoint(theta, left, r + eps, 0.64) - midpoint(theta, left, r - eps, 0.64))
                / (2 * eps),
            ]
        )
        assert np.allclose(j, num, atol=1e-7)


def test_covariance_propagation_equals_matrix_form():
    """P' = F P Fᵀ + G Q Gᵀ, computed independently with matrices."""
    from slam.motion import arc_increment, wheel_increment, wheel_increment_jacobian

    cfg = DeadReckoningConfig(initial_pose=(0.0, 0.0, 0.3))
    dr = create("dead-reckoning", CAL, cfg)
    rng = np.random.default_rng(8)
    left = right = 0
    pose, cov = np.array([0.0, 0.0, 0.3]), np.zeros((3, 3))
    dr.process(EncoderTicks(0.0, 0, 0))
    for k in range(1, 200):
        dl, dr_ = rng.integers(-3, 12), rng.integers(-3, 12)
        left, right = left + dl, right + dr_
        dr.process(EncoderTicks(0.01 * k, left, right))
        ds_l, ds_r = dl * CAL.metres_per_count, dr_ * CAL.metres_per_count
        ds, dth = wheel_increment(ds_l, ds_r, CAL.track_m)
        g = np.array(wheel_increment_jacobian(pose[2], ds, dth, CAL.track_m))
        dx, dy = arc_increment(ds, dth, pose[2])
        f = np.array([[1, 0, -dy], [0, 1, dx], [0, 0, 1.0]])
        q = cfg.wheel_noise_m * np.diag([abs(ds_l), abs(ds_r)])
        cov = f @ cov @ f.T + g @ q @ g.T
        pose = pose + np.array([dx, dy, dth])
    est = dr.estimate()
    assert np.allclose(est.covariance, cov, rtol=1e-9, atol=1e-15)
    assert np.allclose(est.pose[:2], pose[:2])
