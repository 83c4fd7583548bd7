"""Per-wheel slip estimation: the slip-corrected motion and its Jacobians, the brake
level an increment carries, the EKF's and GTSAM's slip prediction and factor checked
against numerical derivatives, and each localizer learning k from landmarks."""

import math

import gtsam
import numpy as np
import pytest
from helpers import numerical_jacobian, wandering_ticks
from slip_world import slip_run

from hardware.calibration import WalkerCalibration
from hardware.messages import BrakeCommand, EncoderTicks, RangeBearing
from slam.base import LOCALIZERS, create
from slam.brake_schedule import BrakeSchedule
from slam.ekf_slam import EkfSlamConfig
from slam.gtsam_slip import slip_odometry_error
from slam.motion import (
    Increment,
    MotionNoise,
    OdometryModel,
    apply_increment,
    propagate,
    slip_corrected,
    split_increment,
    wheel_increment,
)
from slam.slip import SlipEstimation, predict_with_slip

CAL = WalkerCalibration()
TRACK = CAL.track_m


def test_slip_corrected_distances_and_their_jacobian():
    wheels, levels = (0.02, 0.03), (0.5, 0.25)
    ds, dth, _ = slip_corrected(wheels, levels, np.array([0.1, 0.2]), TRACK)
    d = (0.02 / (1 - 0.05), 0.03 / (1 - 0.05))  # each wheel's encoder distance / (1 − k·l)
    assert (float(ds), float(dth)) == pytest.approx(wheel_increment(*d, TRACK))
    assert slip_corrected(wheels, levels, np.zeros(2), TRACK)[:2] == pytest.approx(
        wheel_increment(*wheels, TRACK)
    )

    def f(k):
        return np.array(slip_corrected(wheels, levels, k, TRACK)[:2], dtype=float)

    for k in ([0.1, 0.2], [0.0, 0.0], [-0.3, 0.6]):
        np.testing.assert_allclose(
            slip_corrected(wheels, levels, np.array(k), TRACK)[2],
            numerical_jacobian(f, np.array(k)),
            rtol=1e-6,
            atol=1e-10,
        )
    # one row per particle gives the rows one at a time
    ks = np.random.default_rng(0).uniform(-0.2, 0.3, (5, 2))
    many = slip_corrected(wheels, levels, ks, TRACK)
    for i, k in enumerate(ks):
        one = slip_corrected(wheels, levels, k, TRACK)
        for a, b in zip(many, one, strict=True):
            np.testing.assert_allclose(a[i], b, rtol=1e-12)


def test_an_increment_carries_its_wheel_distances_and_brake_levels():
    """The counted distances (before the brake-aware de-biasing), the commanded levels;
    the increment's own (ds, dθ) is what it always was."""
    brake = CAL.brake
    half = brake.torque_off_nm + 0.5 * (brake.torque_max_nm - brake.torque_off_nm)
    noise = MotionNoise(brake_aware=True, bias_per_full_brake=0.1)
    for model in (OdometryModel(CAL), OdometryModel(CAL, noise)):
        model.increment(EncoderTicks(0.0, 0, 0))
        model.increment(BrakeCommand(0.0, half, brake.torque_off_nm))
        inc = model.increment(EncoderTicks(0.1, 90, 100))
        m = CAL.metres_per_count
        assert inc.wheels == pytest.approx((90 * m, 100 * m))
        assert inc.brake_level == pytest.approx((0.5, 0.0))
    plain = OdometryModel(CAL)
    plain.increment(EncoderTicks(0.0, 0, 0))
    inc = plain.increment(EncoderTicks(0.1, 90, 100))
    assert (inc.ds, inc.dtheta) == wheel_increment(90 * m, 100 * m, TRACK)


def test_brake_levels_are_averaged_over_an_increment_after_the_delay():
    s = BrakeSchedule(0.03)
    s.command(0.0, (1.0, 0.0))  # in force from 0.03
    s.command(0.04, (0.0, 0.5))  # from 0.07
    assert s.mean(0.0, 0.02) == (0.0, 0.0)
    assert s.mean(0.02, 0.04) == pytest.approx((0.5, 0.0))
    assert s.mean(0.04, 0.06) == pytest.approx((1.0, 0.0))
    assert s.mean(0.06, 0.08) == pytest.approx((0.5, 0.25))
    assert s.mean(0.08, 0.08) == (0.0, 0.5)
    # through the odometry model: a command at 0 with 10 ms delay brakes half of the
    # first 20 ms; without a delay setting the last command's level counts (as before)
    brake = CAL.brake
    for delay, expect in ((0.01, 0.5), (None, 1.0)):
        model = OdometryModel(CAL, MotionNoise(brake_delay_s=delay))
        model.increment(EncoderTicks(0.0, 0, 0))
        model.increment(BrakeCommand(0.0, brake.torque_max_nm, brake.torque_off_nm))
        assert model.increment(EncoderTicks(0.02, 8, 8)).brake_level == (expect, 0.0)
    with pytest.raises(ValueError, match="brake_delay_s"):
        MotionNoise(brake_delay_s=-0.1)


@pytest.mark.parametrize(
    ("bad", "needle"),
    [
        ({"k_prior": (0.95, 0.0)}, "k_prior"),
        ({"k_prior": (0.1,)}, "k_prior"),
        ({"k_sigma": 0.0}, "k_sigma"),
        ({"random_walk_per_s": -1e-3}, "random_walk_per_s"),
    ],
)
def test_bad_slip_settings_are_refused(bad, needle):
    with pytest.raises(ValueError, match=needle):
        SlipEstimation(**bad)


def test_split_increment_composes_to_the_whole():
    inc = Increment(1.0, 0.02, 0.012, 0.03, np.diag([1e-6, 4e-6]), (0.011, 0.013), (0.4, 0.0))
    a, b = split_increment(inc, 0.985)
    assert (a.t, a.dt, b.t, b.dt) == pytest.approx((0.985, 0.005, 1.0, 0.015))
    pose = np.array([0.3, -0.2, 2.9])
    np.testing.assert_allclose(
        apply_increment(apply_increment(pose, a.ds, a.dtheta), b.ds, b.dtheta),
        apply_increment(pose, inc.ds, inc.dtheta),
        atol=1e-15,
    )
    np.testing.assert_allclose(a.cov + b.cov, inc.cov)
    assert np.add(a.wheels, b.wheels) == pytest.approx(inc.wheels)
    assert a.brake_level == b.brake_level == inc.brake_level
    before, _ = split_increment(inc, 0.5)  # clipped to the increment's span
    assert before.ds == 0.0 and before.dt == 0.0


def test_a_gyro_turn_is_kept_and_the_slipped_distance_corrected():
    """With the gyro (slam.gyro) the turn is measured, not counted: slip estimation then
    corrects the distance alone. The gyro-fused increment keeps its wheel distances and
    brake levels; its turn is the gyro's at any k, and dθ's row of J is 0."""
    from hardware.messages import GyroRate
    from slam.gyro import GyroFusion
    from slam.slip import increment_with_slip

    model = OdometryModel(CAL, MotionNoise(gyro=GyroFusion(enabled=True)))
    brake = CAL.brake
    half = brake.torque_off_nm + 0.5 * (brake.torque_max_nm - brake.torque_off_nm)
    for msg in (
        GyroRate(0.0, 0.0),
        EncoderTicks(0.0, 0, 0),
        BrakeCommand(0.0, half, brake.torque_off_nm),
        GyroRate(0.1, 0.4),
    ):
        model.increment(msg)
    inc = model.increment(EncoderTicks(0.1, 90, 100))
    m = CAL.metres_per_count
    assert inc.gyro_turn and inc.wheels == pytest.approx((90 * m, 100 * m))
    assert inc.brake_level == pytest.approx((0.5, 0.0))
    assert inc.dtheta != pytest.approx(wheel_increment(90 * m, 100 * m, TRACK)[1])
    k = np.array([[0.0, 0.0], [0.3, 0.1]])
    ds, dth, jac = increment_with_slip(inc, k, TRACK)
    ds_w, _, jac_w = slip_corrected(inc.wheels, inc.brake_level, k, TRACK)
    np.testing.assert_array_equal(ds, ds_w)
    assert ds[1] > ds[0]  # the braked wheel rolled further than it counted
    np.testing.assert_array_equal(dth, [inc.dtheta, inc.dtheta])
    np.testing.assert_array_equal(jac[:, 0], jac_w[:, 0])
    assert not jac[:, 1].any()
    assert all(part.gyro_turn for part in split_increment(inc, 0.05))
    # a gap in velocity odometry stays a measured turn with the gyro (its distance as wide)
    from hardware.messages import VelocityOdometry

    gap = OdometryModel(CAL, MotionNoise(gyro=GyroFusion(enabled=True)))
    for msg in (GyroRate(0.0, 0.0), VelocityOdometry(0.0, math.nan, math.nan), GyroRate(0.1, 0.4)):
        gap.increment(msg)
    inc = gap.increment(VelocityOdometry(0.1, 0.2, 0.0))
    assert inc.gyro_turn and not inc.unknown and inc.dtheta == pytest.approx(0.04, rel=0.1)
    assert inc.cov[0, 0] == MotionNoise().unknown_sigma[0] ** 2  # the gap's distance


def _random_increment(rng):
    cov = rng.uniform(1e-7, 1e-5, (2, 2))
    cov = cov @ cov.T
    wheels = tuple(rng.uniform(0.005, 0.02, 2))
    return Increment(0.02, 0.02, 0.0, 0.0, cov, wheels, tuple(rng.uniform(0.0, 1.0, 2)))


@pytest.mark.parametrize("seed", range(5))
def test_slip_prediction_jacobians_are_the_numerical_ones(seed):
    rng = np.random.default_rng(seed)
    inc = _random_increment(rng)
    pose = rng.uniform(-2.0, 2.0, 3)
    k = rng.uniform(0.0, 0.2, 2)

    def moved(p, kk):
        return predict_with_slip(p, np.zeros((5, 5)), inc, kk, TRACK, 0.0).pose

    step = predict_with_slip(pose, np.zeros((5, 5)), inc, k, TRACK, 0.0)
    num_f = numerical_jacobian(lambda p: moved(p, k), pose, wrap=(2,))
    num_fk = numerical_jacobian(lambda kk: moved(pose, kk), k, wrap=(2,))
    np.testing.assert_allclose(step.f, num_f, atol=1e-7)
    np.testing.assert_allclose(step.f_k, num_fk, atol=1e-7)


def test_slip_prediction_matches_the_pose_only_one_when_k_is_known():
    """With k certain and no random walk, the pose block is `propagate`'s; k's block grows
    by the walk alone, and its correlation with the pose by F_k."""
    rng = np.random.default_rng(4)
    inc = _random_increment(rng)
    pose = np.array([1.0, 2.0, 0.7])
    p3 = np.diag([1e-4, 2e-4, 1e-3])
    cov = np.zeros((5, 5))
    cov[:3, :3] = p3
    k = np.array([0.1, 0.05])
    step = predict_with_slip(pose, cov, inc, k, TRACK, 0.0)
    ds, dth, _ = slip_corrected(inc.wheels, inc.brake_level, k, TRACK)
    want_pose, want_cov, _ = propagate(tuple(pose), tuple(map(tuple, p3)), ds, dth, inc.cov)
    np.testing.assert_allclose(step.pose, want_pose, atol=1e-15)
    np.testing.assert_allclose(step.cov[:3, :3], want_cov, rtol=1e-12, atol=1e-18)
    assert not np.any(step.cov[3:, :])
    cov[3:, 3:] = np.eye(2) * 0.01
    walked = predict_with_slip(pose, cov, inc, k, TRACK, walk=0.5)
    np.testing.assert_allclose(walked.cov[3:, 3:], np.eye(2) * (0.01 + 0.5 * inc.dt))
    np.testing.assert_allclose(walked.cov[:3, 3:], step.f_k * 0.01)


@pytest.mark.parametrize("seed", range(5))
def test_gtsam_slip_factor_jacobians_are_the_numerical_ones(seed):
    """In the tangent spaces of the poses (x ⊕ Exp(δ), as GTSAM retracts) and of k."""
    rng = np.random.default_rng(seed)
    xa = gtsam.Pose2(*rng.uniform(-2, 2, 3))
    xb = xa.compose(gtsam.Pose2(*rng.uniform(-0.3, 0.3, 3)))
    delta0 = np.array([0.25, 0.02, 0.1]) + rng.uniform(-0.05, 0.05, 3)
    jk, k0, k = rng.normal(size=(3, 2)), np.array([0.05, 0.1]), rng.uniform(0, 0.2, 2)
    _, (ha, hb, hk) = slip_odometry_error(xa, xb, k, delta0, jk, k0, jacobians=True)

    def at(a=xa, b=xb, kk=k):
        return slip_odometry_error(a, b, kk, delta0, jk, k0)[0]

    num_a = numerical_jacobian(lambda d: at(a=xa.retract(d)), np.zeros(3))
    num_b = numerical_jacobian(lambda d: at(b=xb.retract(d)), np.zeros(3))
    np.testing.assert_allclose(ha, num_a, atol=1e-6)
    np.testing.assert_allclose(hb, num_b, atol=1e-6)
    np.testing.assert_allclose(hk, numerical_jacobian(lambda kk: at(kk=kk), k), atol=1e-6)
    # at the measured motion (k = k₀, xb = xa ⊕ δ₀) the error vanishes
    xb0 = xa.compose(gtsam.Pose2(*delta0))
    assert np.allclose(slip_odometry_error(xa, xb0, k0, delta0, jk, k0)[0], 0.0, atol=1e-12)


def test_ekf_deferred_cross_covariance_with_slip_equals_the_full_prediction():
    """As without slip (test_ekf_slam): the pose–landmark rows catch up at the next update,
    now through ∂pose/∂k as well; the result equals predicting the whole state
    [x, y, θ, k_L, k_R, landmarks] at every step."""
    slip = SlipEstimation(estimate=True, k_prior=(0.05, 0.02), random_walk_per_s=0.01)
    ekf = create("ekf-slam", CAL, EkfSlamConfig(slip=slip))
    brake = CAL.brake
    ekf.process(BrakeCommand(0.0, brake.torque_max_nm, 1.0))
    for k in range(10):
        ekf.process(EncoderTicks(0.05 * k, 20 * k, 25 * k))
    ekf.process(RangeBearing(0.45, 3, 2.0, 0.3))
    ekf.process(RangeBearing(0.45, 4, 3.0, -0.5))
    x, p = ekf.state()
    assert len(x) == 9 and ekf.index == {3: 5, 4: 7}
    odo = OdometryModel(CAL, ekf.config.noise)
    odo.increment(BrakeCommand(0.0, brake.torque_max_nm, 1.0))
    odo.increment(EncoderTicks(0.45, 180, 225))
    walk = ekf.config.slip.random_walk_per_s**2
    for msg in wandering_ticks(np.random.default_rng(5), range(10, 50), 180, 225):
        ekf.process(msg)
        inc = odo.increment(msg)
        step = predict_with_slip(x[:3], p[:5, :5], inc, x[3:5], TRACK, walk)
        big_f = np.eye(len(x))
        big_f[:3, :3] = step.f
        big_f[:3, 3:5] = step.f_k
        x[:3] = step.pose
        p = big_f @ p @ big_f.T
        p[:5, :5] = step.cov
    got_x, got_p = ekf.state()
    np.testing.assert_allclose(got_x, x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got_p, p, rtol=1e-9, atol=1e-12)
    assert np.abs(p[:3, 5:]).max() > 1e-3 and np.abs(p[:3, 3:5]).max() > 1e-4


SENSOR = {"range_sigma_m": "0.02", "range_sigma_frac": "0", "noise.wheel_m": "1e-4"}


def _learn(name: str, **extra):
    from experiments.config import configure

    msgs, truth, _ = slip_run((0.1, 0.06), np.random.default_rng(0))
    over = {"slip.estimate": "true", "align_observations": "true", **SENSOR, **extra}
    loc = create(name, CAL, configure(LOCALIZERS, name, None, over).config)
    for m in msgs:
        loc.process(m)
    return loc, truth


@pytest.mark.parametrize(("name", "rel"), [("ekf-slam", 0.1), ("gtsam", 0.1), ("fastslam", 0.2)])
def test_the_localizers_learn_each_wheels_slip_from_landmarks(name, rel):
    """Braked turns (left brake in the left turns, k 0.1; right in the right, k 0.06)
    past landmarks: each localizer's k converges to the truth from a prior of 0, and the
    slip-corrected path stays on the true one (dead reckoning: tens of cm off)."""
    loc, truth = _learn(name)
    k, cov = loc.slip_estimate()
    assert k == pytest.approx([0.1, 0.06], rel=rel)
    assert np.all(np.sqrt(np.diag(cov)) < 0.04)
    d = loc.diagnostics()
    assert d["slip_k"] == pytest.approx(list(k)) and len(d["slip_k_sigma"]) == 2
    err = loc.trajectory().interpolate(truth[:, 0])[:, :2] - truth[:, 1:3]
    assert math.sqrt(np.mean(np.sum(err**2, axis=1))) < 0.06


_LANDMARKS = {1: (3.0, 1.0), 2: (3.5, -1.2), 3: (4.0, 0.4)}


def _straight_drive(steps: int, sighted, scale: float = 1.0, landmarks=_LANDMARKS) -> list:
    """A drive along x at 1 m/s: encoder messages every 20 ms counting `scale` of the
    distance, and exact range-bearing sightings of `landmarks` 10 ms before each encoder
    message k (1…steps) for which sighted(k)."""
    m = CAL.metres_per_count
    msgs = [EncoderTicks(0.0, 0, 0)]
    for k in range(1, steps + 1):
        t = 0.02 * k
        if sighted(k):
            x = t - 0.01
            msgs += [
                RangeBearing(x, i, math.hypot(u - x, v), math.atan2(v, u - x))
                for i, (u, v) in landmarks.items()
            ]
        ticks = math.floor(scale * t / m)
        msgs.append(EncoderTicks(t, ticks, ticks))
    return msgs


@pytest.mark.parametrize("name", ["ekf-slam", "gtsam", "fastslam"])
def test_aligned_observations_are_used_at_their_own_time(name):
    """A straight drive at 1 m/s with exact sightings 10 ms after each encoder message:
    used at the last message's pose, each landmark lands 1 cm behind where it is; held
    and used part way through the next increment, where it is (to the encoders'
    2.5 mm counts)."""
    msgs = _straight_drive(100, lambda k: True)
    errors = {}
    for align in (False, True):
        config = LOCALIZERS.spec(name).config_type(align_observations=align, **_EXACT_SENSOR)
        loc = create(name, CAL, config)
        for msg in msgs:
            loc.process(msg)
        got = loc.landmarks()
        errors[align] = [float(got[i][0][0] - u) for i, (u, _) in _LANDMARKS.items()]
    assert np.allclose(errors[False], -0.01, atol=0.004), errors
    assert np.allclose(errors[True], 0.0, atol=0.004), errors


@pytest.mark.parametrize("name", ["ekf-slam", "fastslam"])
def test_whole_state_smoothing_keeps_the_step_before_an_aligned_observation(name):
    """A straight drive at 1 m/s whose encoders report 10 % short, with exact sightings
    every 0.5 s, 10 ms after an encoder message, held for the next one
    (align_observations): each sighting's epoch leads to the step after it, so the
    whole-state smoothed pose of the step before it is carried there by the odometry,
    not displaced by the sighting's correction (the smoothed path jumped there)."""
    msgs = _straight_drive(150, lambda k: k % 25 == 0, scale=0.9)
    config = LOCALIZERS.spec(name).config_type(
        align_observations=True, **{**_EXACT_SENSOR, "noise": MotionNoise(wheel_m=1e-3)}
    )
    loc = create(name, CAL, config)
    for msg in msgs:
        loc.process(msg)
    traj = loc.trajectory()
    step = np.diff(traj.poses[:, 0])  # 0.0174 or 0.0199 m (one count more) by the odometry
    odd = (step < 0.015) | (step > 0.025)  # were 0.009 (fastslam) and 0.07 (ekf-slam)
    assert not odd.any(), np.round(step[odd], 4)


@pytest.mark.parametrize("name", ["ekf-slam", "fastslam"])
def test_an_aligned_observation_leaves_the_step_before_it_as_recorded(name):
    """An observation held for the next odometry message corrects the pose of its own
    time, not the recorded step before it: that step's filtered pose stays the one it
    was recorded with (fastslam replaced it by the corrected pose of 10 ms later, which
    the whole-state smoother then bridged from as if it were the step's)."""
    two = {i: _LANDMARKS[i] for i in (1, 2)}  # the encoders report 10 % short
    msgs = _straight_drive(25, lambda k: k in (1, 25), scale=0.9, landmarks=two)
    sensor = {**_EXACT_SENSOR, "noise": MotionNoise(wheel_m=1e-3)}
    config = LOCALIZERS.spec(name).config_type(align_observations=True, smoother="none", **sensor)
    loc, unseen = create(name, CAL, config), create(name, CAL, config)
    for msg in msgs[:-3]:  # up to the encoder message at 0.48 s
        loc.process(msg)
        unseen.process(msg)
    before = loc.trajectory()
    assert before.t[-1] == pytest.approx(0.48)
    for msg in msgs[-3:]:  # the sightings of 0.49 s, then the encoders at 0.50 s
        loc.process(msg)
    unseen.process(msgs[-1])
    after = loc.trajectory()
    np.testing.assert_array_equal(after.poses[: len(before.t)], before.poses)
    assert after.poses[-1, 0] - unseen.trajectory().poses[-1, 0] > 0.02  # it corrected


_EXACT_SENSOR = {
    "range_sigma_m": 0.01,
    "range_sigma_frac": 0.0,
    "bearing_sigma_rad": 0.002,
    "noise": MotionNoise(wheel_m=1e-5),
}


# -- simulated trials -------------------------------------------------------------------
# The mitigation as measured (README "Wheel-slip estimation"): the slip estimate, the
# observations at their own time, the commands' 30 ms loop latency, and the encoder noise
# of a clean floor (the slip no longer needs the dusty floor's proposed 5.4e-4).
MITIGATION = {
    "slip.estimate": "true",
    "align_observations": "true",
    "noise.brake_delay_s": "0.03",
    "noise.wheel_m": "1e-4",
}


def _run_trial(path, name: str, over: dict):
    """The localizer over a trial log (no mapper); with the log's ground truth and
    metadata."""
    from experiments.config import configure
    from hardware.log import read_log
    from hardware.messages import GroundTruthPose
    from slam.trajectory import Trajectory

    trial = read_log(path)
    cfg = configure(LOCALIZERS, name, trial.metadata, over).config
    loc = create(name, trial.calibration, cfg, trial.metadata["config"]["initial_pose"])
    gt = []
    for msg in trial.messages():
        loc.process(msg)
        if isinstance(msg, GroundTruthPose) and (not gt or msg.t > gt[-1][0]):
            gt.append((msg.t, msg.x, msg.y, msg.theta))
    gt = np.array(gt)
    return loc, Trajectory(gt[:, 0], gt[:, 1:]), trial.metadata


@pytest.fixture(scope="module")
def calibration_trial(tmp_path_factory):
    """The thesis course on a dusty floor with open-loop braking (seed 3), the left tyre
    slipping 1.3 times the surface's k and the right 0.8 times."""
    from experiments.run import simulate_trial
    from hardware.sim.simulator import SimConfig

    path = tmp_path_factory.mktemp("calibration") / "dusty.mcap"
    cfg = SimConfig(slip_scale=(1.3, 0.8))
    simulate_trial("thesis-course", path, surface="dusty", seed=3, sim_config=cfg)
    return path


@pytest.mark.slow
@pytest.mark.parametrize("name", ["ekf-slam", "gtsam", "fastslam"])
def test_slip_estimates_converge_to_the_true_k_on_a_calibration_run(calibration_trial, name):
    """Measured within 1 % (ekf-slam), 5 % (gtsam), 11 % (fastslam) of the effective k
    (0.162, 0.086); the issue's target is 20 %."""
    loc, _, meta = _run_trial(calibration_trial, name, MITIGATION)
    k, _ = loc.slip_estimate()
    truth = meta["slip"]["k_effective"]
    assert truth[0] == pytest.approx(1.3 / 0.8 * truth[1], rel=0.3)  # the tyres differ
    assert k == pytest.approx(truth, rel=0.2)


@pytest.mark.slow
@pytest.mark.parametrize(("name", "bound"), [("ekf-slam", 0.04), ("fastslam", 0.06)])
def test_the_mitigated_whole_state_smoothers_stay_on_the_course(course_trial, name, bound):
    """The slip-estimation mitigation (its observations held for the odometry after
    them) with each whole-state smoother on the dusty course: measured 0.026 m
    (ekf-slam) and 0.045 m (fastslam). Before each held sighting's epoch led to the
    step after it, ekf-slam's smoothed path left the room (12 m on this trial; the
    gains of a bridge that had to absorb the sighting's correction)."""
    from experiments.metrics import ate

    loc, gt, _ = _run_trial(course_trial, name, MITIGATION)
    assert ate(loc.trajectory(), gt)["ate_rmse_m"] < bound


@pytest.fixture(scope="module")
def clean_trial(tmp_path_factory):
    """course_trial's user (seed 2) on a clean floor."""
    from experiments.run import simulate_trial

    path = tmp_path_factory.mktemp("clean") / "clean.mcap"
    simulate_trial("thesis-course", path, surface="clean", seed=2)
    return path


@pytest.mark.slow
def test_slip_aware_gtsam_on_dusty_is_near_its_clean_floor_ate(course_trial, clean_trial):
    """Seed 2 (README "Wheel-slip estimation", seeds 0-2): dusty 0.066 m at defaults,
    0.026 m with the mitigation; clean 0.027 m at defaults, 0.021 m with it (the blind
    users). With the goggle-wearing users of 2026-12-02: dusty 0.045 m at defaults, 0.026 m
    with the mitigation, clean 0.021 m at defaults: 1.24 times, where the issue's target
    asks 1.2 on average; that average is measured over ten users by the slip study
    (BENCHMARKS.md, "Issue 12 targets": 1.18, single users 0.86-1.6), so this one user
    is held to 1.3."""
    from experiments.metrics import ate

    def error(path, over):
        loc, gt, _ = _run_trial(path, "gtsam", over)
        return ate(loc.trajectory(), gt)["ate_rmse_m"]

    dusty, dusty_default = error(course_trial, MITIGATION), error(course_trial, {})
    clean, clean_default = error(clean_trial, MITIGATION), error(clean_trial, {})
    assert dusty < 0.7 * dusty_default
    assert dusty < 1.3 * clean_default
    assert dusty < 1.5 * clean
