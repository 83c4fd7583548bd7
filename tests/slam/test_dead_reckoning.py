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


def test_increment_jacobians_match_finite_differences():
    from slam.motion import apply_increment, increment_jacobians

    rng = np.random.default_rng(7)
    for _ in range(30):
        pose = np.array([rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(-3, 3)])
        u = np.array([rng.uniform(-0.3, 0.3), rng.choice([0.0, 1e-6, rng.uniform(-1, 1)])])
        f, g = increment_jacobians(pose[2], *u)

        def num(fun, x, eps=1e-6):
            cols = []
            for i in range(len(x)):
                d = np.zeros_like(x)
                d[i] = eps
                diff = fun(x + d) - fun(x - d)
                diff[2] = math.remainder(diff[2], 2 * math.pi)
                cols.append(diff / (2 * eps))
            return np.column_stack(cols)

        assert np.allclose(f, num(lambda p, u=u: apply_increment(p, *u), pose), atol=1e-6)
        assert np.allclose(g, num(lambda v, pose=pose: apply_increment(pose, *v), u), atol=1e-6)


def test_covariance_propagation_equals_matrix_form():
    """P' = F P Fᵀ + G Q Gᵀ with the odometry model's Q, computed with matrices."""
    from slam.motion import OdometryModel, apply_increment, increment_jacobians

    dr = create("dead-reckoning", CAL, initial_pose=(0.0, 0.0, 0.3))
    model = OdometryModel(CAL)
    rng = np.random.default_rng(8)
    left = right = 0
    pose, cov = np.array([0.0, 0.0, 0.3]), np.zeros((3, 3))
    first = EncoderTicks(0.0, 0, 0)
    dr.process(first)
    model.increment(first)
    for k in range(1, 200):
        left, right = left + int(rng.integers(-3, 12)), right + int(rng.integers(-3, 12))
        msg = EncoderTicks(0.01 * k, left, right)
        dr.process(msg)
        inc = model.increment(msg)
        f, g = increment_jacobians(pose[2], inc.ds, inc.dtheta)
        cov = f @ cov @ f.T + g @ inc.cov @ g.T
        pose = apply_increment(pose, inc.ds, inc.dtheta)
    est = dr.estimate()
    assert np.allclose(est.covariance, cov, rtol=1e-9, atol=1e-15)
    assert np.allclose(est.pose, pose)


def test_wheel_noise_maps_to_increment_covariance():
    """Var(ds), Var(dθ) and their covariance from independent wheel noise (J Σ Jᵀ)."""
    from slam.motion import OdometryModel

    model = OdometryModel(CAL)
    model.increment(EncoderTicks(0.0, 0, 0))
    inc = model.increment(EncoderTicks(0.1, 100, 300))
    m = CAL.metres_per_count
    sigma = np.diag([0.0025 * 100 * m, 0.0025 * 300 * m])
    j = np.array([[0.5, 0.5], [-1 / CAL.track_m, 1 / CAL.track_m]])
    assert np.allclose(inc.cov, j @ sigma @ j.T)


def test_brake_aware_noise_grows_with_the_logged_torque():
    from hardware.messages import BrakeCommand
    from slam.motion import MotionNoise, OdometryModel

    noise = MotionNoise(brake_aware=True, bias_per_full_brake=0.1)
    plain, aware = OdometryModel(CAL), OdometryModel(CAL, noise)
    for model in (plain, aware):
        model.increment(BrakeCommand(0.0, CAL.brake.torque_max_nm, CAL.brake.torque_off_nm))
        model.increment(EncoderTicks(0.0, 0, 0))
    a = plain.increment(EncoderTicks(0.1, 90, 100))
    b = aware.increment(EncoderTicks(0.1, 90, 100))
    assert b.cov[1, 1] > 2 * a.cov[1, 1]
    # the left wheel's under-report (10 % at full brake) is removed: 90 counts → 100
    assert b.dtheta == pytest.approx(0.0, abs=1e-12)


def test_trajectory_recorder_keeps_the_newest_pose_per_time():
    from slam.trajectory import TrajectoryRecorder

    rec = TrajectoryRecorder()
    assert len(rec) == 0 and np.isnan(rec.last_t)
    rec.amend((9.0, 9.0, 9.0))  # nothing to amend yet
    rec.record(0.0, (0.0, 0.0, 0.0))
    rec.record(1.0, (1.0, 0.0, 0.0))
    rec.record(1.0, (1.5, 0.0, 0.0))  # same time: the newest wins
    rec.record(0.5, (7.0, 7.0, 7.0))  # earlier: ignored
    rec.amend((2.0, 0.0, 0.1))
    tr = rec.trajectory()
    assert list(tr.t) == [0.0, 1.0] and rec.last_t == 1.0
    assert np.allclose(tr.poses, [[0.0, 0.0, 0.0], [2.0, 0.0, 0.1]])


def test_a_correction_is_spread_by_the_variance_accumulated():
    from slam.trajectory import spread_corrections

    path = np.array([[0.0, 0.0, 3.1], [1.0, 0.0, 3.1], [2.0, 0.0, 3.1], [2.0, 0.0, 3.1]])
    delta = np.tile([0.4, -0.2, 0.1], (4, 1))
    accumulated = np.array([[0.0, 0.0], [1.0, 0.5], [2.0, 2.0], [0.0, 0.0]])
    totals = np.array([[2.0, 2.0], [2.0, 2.0], [2.0, 2.0], [0.0, 0.0]])
    out = spread_corrections(path, delta, accumulated, totals)
    assert np.allclose(out[0], path[0])  # nothing accumulated yet
    assert np.allclose(out[1], [1.2, -0.1, 3.125])  # half of x, y; a quarter of θ
    assert np.allclose(out[2], [2.4, -0.2, 3.2 - 2 * math.pi])  # all of it, θ wrapped
    assert np.allclose(out[3], path[3])  # a stretch without odometry variance: unmoved
    assert np.allclose(path[1], [1.0, 0.0, 3.1])  # the input is left as it was


def test_velocity_noise_does_not_depend_on_message_rate():
    """Velocity-odometry errors are a random walk in time: the same 2 s of motion logged at
    10 Hz or at 100 Hz ends with the same covariance (per-step σ ∝ dt would shrink it 10×
    at the higher rate, making every filter overconfident on fast logs)."""
    cal = WalkerCalibration()
    covs = []
    for rate in (10, 100):
        dr = create("dead-reckoning", cal)
        for k in range(2 * rate + 1):
            dr.process(VelocityOdometry(k / rate, 0.3, 0.0))
        covs.append(dr.estimate().covariance)
    assert np.allclose(covs[0], covs[1], rtol=0.05, atol=1e-12)
    noise = DeadReckoningConfig().noise
    # straight at 0.3 m/s for 2 s: var(x) = (k_v·v)²·2 s
    assert covs[1][0, 0] == pytest.approx((noise.velocity_frac * 0.3) ** 2 * 2.0, rel=1e-6)


def test_localizer_contracts():
    """Every registered localizer's config has the common fields; the capabilities are
    typed protocols: what estimates landmarks, what scores against the shared map."""
    from slam.base import LOCALIZERS, KnownMapConfig, LandmarkMapper, LocalizerConfig, MapScorer

    cal = WalkerCalibration()
    for name in LOCALIZERS.names():
        cfg_type = LOCALIZERS.spec(name).config_type
        assert issubclass(cfg_type, LocalizerConfig), name
        loc = create(name, cal, initial_pose=(1.0, 2.0, 0.5), landmark_map={3: (1.0, 1.0)})
        assert tuple(loc.config.initial_pose) == (1.0, 2.0, 0.5)
        if issubclass(cfg_type, KnownMapConfig):
            assert set(loc.config.landmark_map) == {3}
        mapper = name in ("ekf-slam", "fastslam", "gtsam")
        assert isinstance(loc, LandmarkMapper) == mapper, name
        assert isinstance(loc, MapScorer) == (name in ("particle-filter", "grid-rbpf")), name


def test_brake_aware_noise_corrects_velocity_odometry_as_it_does_ticks():
    """A velocity odometry's (v, ω) stands for two wheel distances; brake-aware noise
    grows the braked one by the same factor as a braked encoder's (a log with brakes but
    velocity odometry, e.g. MRCLAM with synthetic slip, is corrected, not left alone)."""
    from hardware.messages import BrakeCommand, VelocityOdometry
    from slam.motion import MotionNoise, OdometryModel

    noise = MotionNoise(brake_aware=True, bias_per_full_brake=0.1)
    plain, aware = OdometryModel(CAL), OdometryModel(CAL, noise)
    half = 0.5 * CAL.track_m
    v, omega = 0.475, 0.05 / CAL.track_m  # left wheel 0.45 m/s, right 0.5 m/s
    for model in (plain, aware):
        model.increment(BrakeCommand(0.0, CAL.brake.torque_max_nm, CAL.brake.torque_off_nm))
        model.increment(VelocityOdometry(0.0, v, omega))
    a = plain.increment(VelocityOdometry(1.0, v, omega))
    b = aware.increment(VelocityOdometry(1.0, v, omega))
    assert a.wheels == pytest.approx(b.wheels)  # what was measured stays in the increment
    left, right = b.ds - half * b.dtheta, b.ds + half * b.dtheta
    assert left == pytest.approx(a.wheels[0] / (1 - 0.1 * b.brake_level[0]))
    assert right == pytest.approx(a.wheels[1] / (1 - 0.1 * b.brake_level[1]))
    assert b.brake_level == pytest.approx((1.0, 0.0), abs=1e-9)
    assert b.dtheta == pytest.approx(0.0, abs=1e-12)  # 0.45 m → 0.5 m: straight after all
    assert b.cov[1, 1] > a.cov[1, 1] and b.cov[0, 0] > a.cov[0, 0]
