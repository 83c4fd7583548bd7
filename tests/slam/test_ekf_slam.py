"""EKF-SLAM: beats dead reckoning under slip, maps the tags, handles bad observations."""

import numpy as np
import pytest
from helpers import replay, wandering_ticks

from experiments.metrics import ate
from hardware.calibration import WalkerCalibration
from hardware.messages import EncoderTicks, RangeBearing
from hardware.sim.world import World
from slam.base import create
from slam.ekf_slam import EkfSlamConfig


@pytest.mark.slow
def test_beats_dead_reckoning_and_maps_tags(course_trial):
    """Over the whole route, which comes back past tags seen before (no loop closure
    happens on the way out: every tag is new there)."""
    dr, pipe, trial = replay(course_trial, "dead-reckoning")
    ekf, _, _ = replay(course_trial, "ekf-slam")
    gt = pipe.recorded.groundtruth_trajectory()
    e_dr, e_ekf = ate(dr.trajectory(), gt), ate(ekf.trajectory(), gt)
    assert e_ekf["ate_rmse_unaligned_m"] < 0.6 * e_dr["ate_rmse_unaligned_m"]
    assert e_ekf["ate_rmse_m"] < e_dr["ate_rmse_m"]
    world = World.from_dict(trial.metadata["world"])
    lms = ekf.landmarks()
    assert len(lms) >= 5
    err = [np.hypot(*(mean - [world.tag(i).x, world.tag(i).y])) for i, (mean, _) in lms.items()]
    assert np.median(err) < 0.25
    # the filter's covariance stays a covariance
    assert np.all(np.linalg.eigvalsh(ekf.state()[1]) > -1e-9)


@pytest.mark.slow
def test_same_input_same_output(course_trial):
    a, _, _ = replay(course_trial, "ekf-slam")
    b, _, _ = replay(course_trial, "ekf-slam")
    assert np.array_equal(a.trajectory().poses, b.trajectory().poses)


def test_without_observations_it_is_dead_reckoning_and_says_so():
    cal = WalkerCalibration()
    ekf, dr = create("ekf-slam", cal), create("dead-reckoning", cal)
    for k in range(100):
        m = EncoderTicks(0.02 * k, 5 * k, 6 * k)
        ekf.process(m)
        dr.process(m)
    assert np.allclose(ekf.trajectory().poses, dr.trajectory().poses)
    assert np.allclose(ekf.estimate().covariance, dr.estimate().covariance)
    assert "odometry only" in ekf.diagnostics()["note"]


def _loop_with_biased_odometry(smoother: str):
    """Two landmarks seen from the known start, a 4 m straight drive (true y = 0) whose
    ticks say it curves left (right wheel 3 % long), unseen, then the same landmarks
    seen again from the end (a loop closure). A range-bearing sensor whose range is as
    informative as its bearing (the defaults' tag camera gives little range)."""
    cal = WalkerCalibration()
    sensor = {"range_sigma_m": 0.05, "range_sigma_frac": 0.02, "bearing_sigma_rad": 0.03}
    ekf = create("ekf-slam", cal, EkfSlamConfig(smoother=smoother, **sensor))
    lms = {1: (-1.0, 1.0), 2: (-1.0, -1.0)}

    def see(t: float, x: float) -> None:
        for lid, (u, v) in lms.items():
            ekf.process(
                RangeBearing(t, lid, float(np.hypot(u - x, v)), float(np.arctan2(v, u - x)))
            )

    m = cal.metres_per_count
    ekf.process(EncoderTicks(0.0, 0, 0))
    see(0.0, 0.0)
    for k in range(1, 201):
        ekf.process(EncoderTicks(0.02 * k, round(0.02 * k / m), round(0.0206 * k / m)))
    see(4.0, 4.0)
    return ekf


@pytest.mark.parametrize("smoother", ["rts-full", "rts"])
def test_smoother_carries_a_loop_closure_back_along_the_path(smoother):
    """The filtered poses of the drive keep their drift; the RTS-smoothed ones (of the
    whole state, the default, or of the pose alone) are pulled back toward the truth
    (y = 0), and the past counts as revised."""
    smooth, filtered = _loop_with_biased_odometry(smoother), _loop_with_biased_odometry("none")
    assert smooth.revises_past and not filtered.revises_past and smooth.revision > 0
    t_mid = np.array([2.0, 2.5, 3.0, 3.5])
    lat_s = np.abs(smooth.trajectory().interpolate(t_mid)[:, 1])
    lat_f = np.abs(filtered.trajectory().interpolate(t_mid)[:, 1])
    assert np.all(lat_f > 0.05)  # the drift is there to correct
    assert np.all(lat_s < 0.5 * lat_f), (lat_s, lat_f)
    # the last pose is the filter's in both (the smoother starts from it)
    np.testing.assert_allclose(smooth.trajectory().poses[-1], filtered.trajectory().poses[-1])
    with pytest.raises(ValueError, match="smoother"):
        EkfSlamConfig(smoother="ancestry")


def test_outlier_is_gated_and_unknown_ids_are_counted():
    cal = WalkerCalibration()
    ekf = create("ekf-slam", cal, EkfSlamConfig())
    ekf.process(EncoderTicks(0.0, 0, 0))
    ekf.process(RangeBearing(0.0, 7, 2.0, 0.0))  # landmark 7 at (2, 0)
    for k in range(1, 20):
        ekf.process(EncoderTicks(0.05 * k, 0, 0))
        ekf.process(RangeBearing(0.05 * k, 7, 2.0, 0.0))
    before = ekf.estimate().pose.copy()
    ekf.process(RangeBearing(1.0, 7, 5.0, 1.0))  # 3 m off: an outlier
    ekf.process(RangeBearing(1.0, -1, 1.0, 0.0))  # no ID
    assert np.allclose(ekf.estimate().pose, before)
    d = ekf.diagnostics()
    assert d["gated"] == 1 and d["without_id"] == 1 and d["new_landmarks"] == 1
    mean, cov = ekf.landmarks()[7]
    assert mean == pytest.approx([2.0, 0.0], abs=1e-6)
    assert cov[0, 0] < 0.05**2  # many consistent sightings shrink it


def test_deferred_cross_covariance_equals_the_full_prediction():
    """Predictions move only the pose block; the pose–landmark rows catch up at the next
    update. The result must equal predicting the full state at every step:
    P ← F P Fᵀ + G Q Gᵀ with F, G the exact-arc Jacobians padded with the identity."""
    from slam.motion import OdometryModel, apply_increment, increment_jacobians

    cal = WalkerCalibration()
    ekf = create("ekf-slam", cal, EkfSlamConfig())
    for k in range(10):  # some pose uncertainty first, so the landmarks correlate with it
        ekf.process(EncoderTicks(0.05 * k, 20 * k, 25 * k))
    ekf.process(RangeBearing(0.45, 3, 2.0, 0.3))
    ekf.process(RangeBearing(0.45, 4, 3.0, -0.5))
    x, p = ekf.state()
    odo = OdometryModel(cal, ekf.config.noise)
    odo.increment(EncoderTicks(0.45, 180, 225))
    for msg in wandering_ticks(np.random.default_rng(5), range(10, 50), 180, 225):
        ekf.process(msg)
        inc = odo.increment(msg)
        f, g = increment_jacobians(x[2], inc.ds, inc.dtheta)
        big_f = np.eye(len(x))
        big_f[:3, :3] = f
        x[:3] = apply_increment(x[:3], inc.ds, inc.dtheta)
        p = big_f @ p @ big_f.T
        p[:3, :3] += g @ inc.cov @ g.T
    got_x, got_p = ekf.state()
    np.testing.assert_allclose(got_x, x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got_p, p, rtol=1e-9, atol=1e-12)
    assert np.abs(p[:3, 3:]).max() > 1e-3  # the cross-covariance did move


def test_the_closed_form_update_is_the_kalman_update():
    """`_update` (closed form, issue 13) gives what the textbook update with the full H
    gives: x + K ν and P − K S Kᵀ, K = P Hᵀ S⁻¹, to rounding."""
    from hardware.calibration import WalkerCalibration
    from hardware.geometry import wrap_angle
    from slam.base import create
    from slam.measurement import range_bearing, range_bearing_jacobians

    rng = np.random.default_rng(3)
    ekf = create("ekf-slam", WalkerCalibration())
    n = 3 + 2 * 4
    a = rng.standard_normal((n, n))
    ekf._x = np.concatenate([[0.3, -0.2, 0.4], rng.uniform(-5, 5, n - 3)])
    ekf._P = a @ a.T * 0.01 + np.eye(n) * 1e-3
    x0, p0 = ekf._x.copy(), ekf._P.copy()
    j = 7
    h = np.zeros((2, n))
    h[:, :3], h[:, j : j + 2] = range_bearing_jacobians(x0[:3], x0[j : j + 2])
    z = range_bearing(x0[:3], x0[j : j + 2]) + np.array([0.05, 0.02])
    s = h @ p0 @ h.T + ekf._noise(z)
    k = p0 @ h.T @ np.linalg.inv(s)
    nu = z - range_bearing(x0[:3], x0[j : j + 2])
    nu[1] = wrap_angle(nu[1])
    ekf._update(j, z)
    expected = x0 + k @ nu
    expected[2] = wrap_angle(expected[2])
    assert np.allclose(ekf._x, expected, rtol=0, atol=1e-12)
    assert np.allclose(ekf._P, p0 - k @ s @ k.T, rtol=0, atol=1e-12)
    assert ekf.counts["updates"] == 1
    # and a residual beyond the gate changes nothing
    ekf._update(j, z + np.array([5.0, 0.0]))
    assert ekf.counts["gated"] == 1 and ekf.counts["updates"] == 1
