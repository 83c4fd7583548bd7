"""FastSLAM 1.0 / 2.0: models against numerical Jacobians and the reference formulas, a
small synthetic world with known truth, the simulated course with slip, bad inputs."""

import math

import numpy as np
import pytest
from helpers import numerical_jacobian

from experiments.metrics import ate, landmark_rmse, trajectory_alignment
from hardware.calibration import WalkerCalibration
from hardware.frames import invert_transform, make_transform
from hardware.geometry import wrap_angle
from hardware.log import read_log
from hardware.messages import (
    EncoderTicks,
    GroundTruthPose,
    RangeBearing,
    TagDetection,
    TagDetections,
)
from hardware.sim.landmark_drive import DriveNoise, landmark_drive
from slam import fastslam_kernels as kernels
from slam.base import available, create
from slam.fastslam import (
    FastSlamConfig,
    landmark_from_tag_pose,
    landmark_from_tag_pose_jacobians,
    propagate_linearised,
    systematic_resample,
    tag_pose,
    tag_pose_jacobians,
)
from slam.landmarks import from_metadata
from slam.measurement import range_bearing, range_bearing_jacobians
from slam.motion import MotionNoise, apply_increment, increment_jacobians
from slam.slip import SlipEstimation
from slam.trajectory import Trajectory


@pytest.fixture
def cases():
    rng = np.random.default_rng(11)
    poses = np.column_stack(
        [rng.uniform(-5, 5, 30), rng.uniform(-5, 5, 30), rng.uniform(-3, 3, 30)]
    )
    tags = np.column_stack([rng.uniform(-6, 6, (30, 2)), rng.uniform(-3, 3, 30)])
    return poses, tags


# -- models ------------------------------------------------------------------------------


def test_tag_pose_model_jacobians_and_inverse(cases):
    for pose, tag in zip(*cases, strict=True):
        g_s, g_l = tag_pose_jacobians(pose, tag)
        assert np.allclose(
            g_s,
            numerical_jacobian(lambda p, tag=tag: tag_pose(p, tag), pose, wrap=(1, 2)),
            atol=1e-6,
        )
        assert np.allclose(
            g_l,
            numerical_jacobian(lambda m, pose=pose: tag_pose(pose, m), tag, wrap=(1, 2)),
            atol=1e-6,
        )
        z = tag_pose(pose, tag)
        back = landmark_from_tag_pose(pose, z)
        assert np.allclose(back[:2], tag[:2]) and math.remainder(back[2] - tag[2], 2 * math.pi) == (
            pytest.approx(0.0, abs=1e-9)
        )
        j_s, j_z = landmark_from_tag_pose_jacobians(pose, z)
        assert np.allclose(
            j_s,
            numerical_jacobian(lambda p, z=z: landmark_from_tag_pose(p, z), pose, wrap=(1, 2)),
            atol=1e-6,
        )
        assert np.allclose(
            j_z,
            numerical_jacobian(
                lambda zz, pose=pose: landmark_from_tag_pose(pose, zz), z, wrap=(1, 2)
            ),
            atol=1e-6,
        )


def predict(poses, landmarks):
    """The compiled observation model, particle by particle."""
    n, d = landmarks.shape
    zhat, g_s, g_l = np.empty((n, d)), np.empty((n, d, 3)), np.empty((n, d, d))
    for i in range(n):
        kernels._predict(poses[i], landmarks[i], d, zhat[i], g_s[i], g_l[i])
    return zhat, g_s, g_l


def test_compiled_observation_model_equals_slam_measurement(cases):
    poses, tags = cases
    zhat, g_s, g_l = predict(poses, tags[:, :2].copy())
    assert np.allclose(zhat, range_bearing(poses, tags[:, :2]))
    ref_s, ref_l = range_bearing_jacobians(poses, tags[:, :2])
    assert np.allclose(g_s, ref_s) and np.allclose(g_l, ref_l)
    zhat, g_s, g_l = predict(poses, tags)
    assert np.allclose(zhat, tag_pose(poses, tags))
    ref_s, ref_l = tag_pose_jacobians(poses, tags)
    assert np.allclose(g_s, ref_s) and np.allclose(g_l, ref_l)


@pytest.mark.parametrize(("ds", "dtheta"), [(0.02, 0.01), (0.5, -0.8), (0.03, 0.0)])
def test_linearised_propagation_equals_slam_motion(ds, dtheta):
    rng = np.random.default_rng(3)
    poses = np.column_stack([rng.normal(size=(5, 2)), rng.uniform(-3, 3, 5)])
    a = rng.normal(size=(5, 3, 3))
    pending = a @ a.transpose(0, 2, 1)
    q = np.array([[2e-5, 3e-6], [3e-6, 4e-5]])
    moved, p = propagate_linearised(poses, pending, ds, dtheta, q)
    assert np.allclose(moved, apply_increment(poses, ds, dtheta))
    for i in range(5):
        f, g = increment_jacobians(poses[i, 2], ds, dtheta)
        assert np.allclose(p[i], f @ pending[i] @ f.T + g @ q @ g.T)


def fold_one(poses, p, lm, lc, z, r, seen=None, gate=1e9, proposal=True):
    """kernels.fold of one observation of landmark column 0 → (used, μ, Σ, Δ log w)."""
    n = len(lm)
    mu, sigma, logw = poses.copy(), p.copy(), np.zeros(n)
    seen = np.ones((n, 1), bool) if seen is None else seen[:, None]
    had = np.empty((1, n), bool)
    used = kernels.fold(
        mu, sigma, lm[:, None].copy(), lc[:, None].copy(), seen, np.full(n, 1.0 / n),
        np.zeros(1, np.int64), z[None], r[None], gate, 1.0, proposal, logw, had,
    )  # fmt: skip
    assert np.array_equal(had[0], seen[:, 0])
    return int(used[0]), mu, sigma, logw


@pytest.mark.parametrize("d", [2, 3])
def test_compiled_proposal_is_the_fastslam2_gaussian(cases, d):
    """The Kalman form of the kernel = the information form of EQUATIONS.md (Appendix A)
    for an invertible P, with Q = G_l Σ_l G_lᵀ + R; the weight is N(ν; 0, G_s P G_sᵀ + Q)."""
    rng = np.random.default_rng(5)
    poses, tags = cases
    n = len(poses)
    lm = tags[:, :d].copy()
    a = rng.normal(size=(n, 3, 3)) * 0.1
    p = a @ a.transpose(0, 2, 1) + 1e-3 * np.eye(3)
    b = rng.normal(size=(n, d, d)) * 0.1
    lc = b @ b.transpose(0, 2, 1) + 0.01 * np.eye(d)
    r = np.array([0.02, 0.003, 0.05][:d])
    model = tag_pose if d == 3 else range_bearing
    jac = tag_pose_jacobians if d == 3 else range_bearing_jacobians
    z = model(poses[0], lm[0]) + 0.05  # the first particle's view, off a little
    used, mu, sigma, dlogw = fold_one(poses, p, lm, lc, z, r)
    assert used == 1
    for i in range(n):
        g_s, g_l = jac(poses[i], lm[i])
        q = g_l @ lc[i] @ g_l.T + np.diag(r)
        nu = z - model(poses[i], lm[i])
        nu[1:] = (nu[1:] + np.pi) % (2 * np.pi) - np.pi
        q_inv = np.linalg.inv(q)
        sig_ref = np.linalg.inv(g_s.T @ q_inv @ g_s + np.linalg.inv(p[i]))
        mu_ref = sig_ref @ g_s.T @ q_inv @ nu + poses[i]
        mu_ref[2] = (mu_ref[2] + np.pi) % (2 * np.pi) - np.pi
        assert np.allclose(sigma[i], sig_ref, atol=1e-12)
        assert np.allclose(mu[i], mu_ref, atol=1e-12)
        s = g_s @ p[i] @ g_s.T + q
        log_n = -0.5 * (
            nu @ np.linalg.solve(s, nu) + np.log(np.linalg.det(s)) + d * np.log(2 * np.pi)
        )
        assert dlogw[i] == pytest.approx(log_n, abs=1e-9)
    # a singular P (standing still) leaves the poses where they are
    _, mu0, sigma0, _ = fold_one(poses, np.zeros((n, 3, 3)), lm, lc, z, r)
    assert np.allclose(mu0, poses) and np.allclose(sigma0, 0.0)
    # FastSLAM 1.0: only the weights; particles that had not seen it untouched
    seen = np.arange(n) % 2 == 0
    _, mu1, _, dlogw1 = fold_one(poses, p, lm, lc, z, r, seen=seen, proposal=False)
    assert np.array_equal(mu1, poses) and np.all(dlogw1[~seen] == 0) and np.all(dlogw1[seen] != 0)
    # the gate: ν̄ᵀ C⁻¹ ν̄ of the particles' mixture, C = mean S_i + spread of the ν_i
    nus, ss = [], []
    for i in range(n):
        g_s, g_l = jac(poses[i], lm[i])
        nu = z - model(poses[i], lm[i])
        nus.append(np.concatenate([nu[:1], (nu[1:] + np.pi) % (2 * np.pi) - np.pi]))
        ss.append(g_s @ p[i] @ g_s.T + g_l @ lc[i] @ g_l.T + np.diag(r))
    nus = np.array(nus)
    nu_bar = nus.mean(axis=0)
    c = np.mean(ss, axis=0) + (nus - nu_bar).T @ (nus - nu_bar) / n
    maha = nu_bar @ np.linalg.solve(c, nu_bar)
    used, mu_g, _, dlogw_g = fold_one(poses, p, lm, lc, z, r, gate=maha * (1 - 1e-9))
    assert used == 0 and np.array_equal(mu_g, poses) and np.all(dlogw_g == 0)
    assert fold_one(poses, p, lm, lc, z, r, gate=maha * (1 + 1e-9))[0] == 1


def test_compiled_sample_handles_singular_covariances():
    """μ + L e with L L^T = Σ for PSD Σ, a zero pivot and a zero matrix included."""
    rng = np.random.default_rng(4)
    a = rng.normal(size=(4, 3, 2))  # rank 2
    mats = np.concatenate([a @ a.transpose(0, 2, 1), np.zeros((1, 3, 3)), np.eye(3)[None]])
    mats[1, 0, :] = mats[1, :, 0] = 0.0  # a zero first pivot
    n = len(mats)
    low = np.empty((n, 3, 3))
    for k in range(3):  # column k of L: the sample at e = unit vector k, from μ = 0
        out = np.empty((n, 3))
        e = np.zeros((n, 3))
        e[:, k] = 1.0
        kernels.sample(np.zeros((n, 3)), mats, e, out)
        low[:, :, k] = out
    assert np.all(np.isfinite(low)) and np.allclose(np.triu(low, 1), 0.0)
    assert np.allclose(low @ low.transpose(0, 2, 1), mats, atol=1e-9)


@pytest.mark.parametrize("d", [2, 3])
def test_compiled_moments_are_the_particles_weighted_moments(d):
    """kernels.state_moments and prediction_moments against numpy on stacked vectors:
    headings and tag yaws straddling ±π (circular means, wrapped deviations), landmark
    columns taken out of order, with slip coefficients in the top."""
    rng = np.random.default_rng(7)
    n, cap = 9, 4
    w = rng.random(n)
    w /= w.sum()
    heading = np.pi + rng.normal(0, 0.2, n)
    top = np.c_[rng.normal(2, 0.3, (n, 2)), heading, rng.normal(1, 0.01, (n, 2))]
    top[:, 2] = wrap_angle(top[:, 2])
    means = rng.normal(0, 3, (n, cap, d))
    if d == 3:
        means[..., 2] = wrap_angle(np.pi + rng.normal(0, 0.2, (n, cap)))
    a = rng.normal(size=(n, cap, d, d))
    covs = a @ np.swapaxes(a, -1, -2)
    b = rng.normal(size=(n, 3, 3))
    pending = b @ np.swapaxes(b, -1, -2)
    cols = np.array([2, 0, 3])

    def circular(v):
        return math.atan2(w @ np.sin(v), w @ np.cos(v))

    stacked = np.concatenate([top, means[:, cols].reshape(n, -1)], axis=1)
    angles = [2] + ([5 + d * m + 2 for m in range(len(cols))] if d == 3 else [])
    mean = w @ stacked
    for j in angles:
        mean[j] = circular(stacked[:, j])
    dev = stacked - mean
    dev[:, angles] = wrap_angle(dev[:, angles])
    cov = (dev * w[:, None]).T @ dev
    cov[:3, :3] += np.einsum("n,nij->ij", w, pending)
    for m, col in enumerate(cols):
        o = 5 + d * m
        cov[o : o + d, o : o + d] += np.einsum("n,nij->ij", w, covs[:, col])
    size = 5 + d * len(cols)
    x, p, got = np.empty(size), np.empty((size, size)), np.empty((n, size))
    kernels.state_moments(top, pending, means, covs, cols, w, x, p, got)
    np.testing.assert_allclose(x, mean, atol=1e-12)
    np.testing.assert_allclose(got, dev, atol=1e-12)
    np.testing.assert_allclose(p, cov, atol=1e-12)
    # the same particles moved on: the prediction's moments against the state before
    moved = top + rng.normal(0, 0.1, top.shape)
    moved[:, 2] = wrap_angle(moved[:, 2])
    m_top = w @ moved
    m_top[2] = circular(moved[:, 2])
    dt = moved - m_top
    dt[:, 2] = wrap_angle(dt[:, 2])
    mean_p, cross, rows = np.empty(5), np.empty((size, 5)), np.empty((5, size))
    kernels.prediction_moments(moved, pending, w, dev, mean_p, cross, rows)
    np.testing.assert_allclose(mean_p, m_top, atol=1e-12)
    np.testing.assert_allclose(cross, (dev * w[:, None]).T @ dt, atol=1e-12)
    want = np.concatenate([dt, dev[:, 5:]], axis=1)
    want = (dt * w[:, None]).T @ want
    want[:3, :3] += np.einsum("n,nij->ij", w, pending)
    np.testing.assert_allclose(rows, want, atol=1e-12)


def test_systematic_resample_is_filterpys_with_our_generator(monkeypatch):
    import filterpy.monte_carlo.resampling as fr

    rng = np.random.default_rng(2)
    w = rng.random(50) ** 4
    w /= w.sum()
    u = np.random.default_rng(9).random()
    monkeypatch.setattr(fr, "random", lambda: u)
    ours = systematic_resample(w, np.random.default_rng(9))
    assert np.array_equal(ours, fr.systematic_resample(w))


def test_config_is_checked_and_registered():
    assert "fastslam" in available()
    loc = create("fastslam", WalkerCalibration())
    assert loc.config == FastSlamConfig() and loc.config.version == 2
    for bad in (
        {"version": 3},
        {"n_particles": 0},
        {"observation": "bearing-only"},
        {"weight_gain": 0.5},
        {"smoother": "rts"},
        {"smoother_budget_mb": 0},
    ):
        with pytest.raises(ValueError):
            FastSlamConfig(**bad)


# -- a synthetic world: 8 tags on a circle, the walker loops inside it -----------------------

TAG_HEIGHT_M = 0.35


def detection(cal, tag_id, r, b, yaw):
    """A TagDetection at range r, bearing b, with its outward normal at heading `yaw`,
    all in the walker frame (so tag_observations returns exactly these)."""
    p = np.array([r * math.cos(b), r * math.sin(b), TAG_HEIGHT_M])
    z_axis = -np.array([math.cos(yaw), math.sin(yaw), 0.0])  # into the tag
    y_axis = np.array([0.0, 0.0, -1.0])  # down
    walker_T_tag = make_transform(np.column_stack([np.cross(y_axis, z_axis), y_axis, z_axis]), p)
    camera_T_tag = invert_transform(cal.tag_mount.walker_T_optical()) @ walker_T_tag
    return TagDetection(int(tag_id), camera_T_tag, np.zeros((4, 2)))


def synthetic_run(seed=0, duration_s=40.0, sigma=(0.02, 0.01, 0.02), wheel_m=0.0025):
    """Encoder ticks (50 Hz) from an exact wobbly loop of radius ~1.5 m, each wheel's
    distance with added noise of variance wheel_m·|d| (the filter's own model), and tag
    detections (10 Hz, within 4 m and ±60°) with Gaussian range/bearing/yaw noise."""
    rng = np.random.default_rng(seed)
    cal = WalkerCalibration()
    a = 2 * np.pi * np.arange(8) / 8
    tags = 3.0 * np.column_stack([np.cos(a), np.sin(a)])
    tag_yaw = a + np.pi  # facing the centre
    dt, v = 0.02, 0.5
    pose = np.array([1.5, 0.0, math.pi / 2])
    counts = np.zeros(2)
    msgs, times, truth = [], [], []
    for k in range(int(duration_s / dt) + 1):
        t = k * dt
        if k > 0:
            omega = v / 1.5 + 0.15 * math.cos(t)
            d = np.array([v - 0.5 * omega * cal.track_m, v + 0.5 * omega * cal.track_m]) * dt
            pose = apply_increment(pose, d.mean(), (d[1] - d[0]) / cal.track_m)
            d += rng.standard_normal(2) * np.sqrt(wheel_m * np.abs(d))
            counts += d / cal.metres_per_count
        msgs.append(EncoderTicks(t, *(int(c) for c in np.floor(counts))))
        times.append(t)
        truth.append(pose)
        if k % 5 == 0:
            dets = []
            for i in range(8):
                r, b = range_bearing(pose, tags[i])
                if r < 4.0 and abs(b) < math.radians(60):
                    n = sigma * rng.standard_normal(3)
                    yaw = math.remainder(tag_yaw[i] - pose[2], 2 * math.pi)
                    dets.append(detection(cal, i, r + n[0], b + n[1], yaw + n[2]))
            msgs.append(TagDetections(t, tuple(dets)))
    return msgs, Trajectory(np.array(times), np.array(truth)), tags, cal


@pytest.fixture(scope="module")
def synthetic():
    return synthetic_run()


def matched(version, observation="range-bearing", **kw):
    """The filter told the synthetic world's true noise, which is independent from frame
    to frame: the textbook weights (weight_gain 1), and the 100 particles it was measured
    with (the default is 300)."""
    return FastSlamConfig(
        **{
            "n_particles": 100,
            "initial_pose": (1.5, 0.0, math.pi / 2),
            "version": version,
            "observation": observation,
            "range_sigma_m": 0.02,
            "range_sigma_frac": 0.0,
            "bearing_sigma_rad": 0.01,
            "yaw_sigma_rad": 0.02,
            "yaw_sigma_per_m2": 0.0,
            "weight_gain": 1.0,
            **kw,
        }
    )


def replay(loc, msgs):
    for m in msgs:
        loc.process(m)
    return loc


@pytest.mark.parametrize(
    ("version", "observation"), [(1, "range-bearing"), (2, "range-bearing"), (2, "tag-pose")]
)
def test_synthetic_world_tracks_pose_and_maps_tags(synthetic, version, observation):
    msgs, gt, tags, cal = synthetic
    dr = replay(create("dead-reckoning", cal, initial_pose=gt.poses[0]), msgs)
    fs = replay(create("fastslam", cal, matched(version, observation)), msgs)
    e, e_dr = ate(fs.trajectory(), gt), ate(dr.trajectory(), gt)
    err = np.hypot(*(fs.trajectory().interpolate(gt.t)[:, :2] - gt.poses[:, :2]).T)
    # measured (seed 0): ATE 2–3.5 cm, worst 6–8 cm, against 80 cm for dead reckoning
    assert e["ate_rmse_unaligned_m"] < 0.06
    assert err.max() < 0.15
    assert e_dr["ate_rmse_unaligned_m"] > 5 * e["ate_rmse_unaligned_m"]
    lms = fs.landmarks()
    assert sorted(lms) == list(range(8))
    lm_err = np.array([np.hypot(*(mean - tags[i])) for i, (mean, _) in lms.items()])
    # measured: mean 1–3 cm, worst 3–4.5 cm; a first sighting is 2–5 cm uncertain
    assert lm_err.mean() < 0.06 and lm_err.max() < 0.12
    # converged: hundreds of sightings shrank every landmark's σ to ~3 mm in each particle
    # (from 2–3 cm at first sight; conditioned on its path); the map's covariance adds the
    # particles' spread (measured: largest σ 2.5–11 mm, nearer the real error)
    sigma = [np.sqrt(np.linalg.eigvalsh(cov).max()) for _, cov in lms.values()]
    assert max(sigma) < 0.02
    d = fs.diagnostics()
    assert d["new_landmarks"] == 8 and d["updates"] > 900 and d["without_id"] == 0
    if observation == "tag-pose":
        yaws = {i: mean[2] for i, (mean, _) in fs.landmarks(full=True).items()}
        true_yaw = 2 * np.pi * np.arange(8) / 8 + np.pi
        assert max(abs(math.remainder(yaws[i] - true_yaw[i], 2 * math.pi)) for i in yaws) < 0.05


def test_the_map_is_the_particles_weighted_mean():
    # issue 13's kind of drive among five landmarks, at the default weight gain (weights
    # that select slowly): each particle's map carries its own path noise, their weighted
    # mean (the estimate that goes with the weighted-mean path) does not; measured (seed
    # 0): 0.046 m against the highest-weight particle's 0.152 m (seeds 1, 2: 0.042 / 0.346,
    # 0.046 / 0.087)
    lm = {0: (10.0, -2.0), 1: (15.0, 10.0), 2: (3.0, 15.0), 3: (-5.0, 5.0), 4: (-5.0, 20.0)}
    drive = DriveNoise(v=0.5, omega=math.radians(10.0), range_m=0.3, bearing_rad=0.035)
    steps, truth = landmark_drive(lm, 300, 0.1, 1.0, 0.1, drive, seed=0)
    noise = MotionNoise(velocity_frac=0.16, omega_frac=0.0, omega_floor=0.055)
    sensor = {"range_sigma_m": 0.3, "range_sigma_frac": 0.0, "bearing_sigma_rad": 0.035}
    cfg = FastSlamConfig(noise=noise, **sensor)
    fs = replay(create("fastslam", WalkerCalibration(), cfg), [m for s in steps for m in s])
    gt = Trajectory(truth[:, 0], truth[:, 1:])
    align = trajectory_alignment(fs.trajectory(), gt)
    got = fs.landmarks()
    assert sorted(got) == sorted(lm)
    seen = fs.seen[:, fs.index[3]]
    w = np.exp(fs.log_weights[seen]) / np.exp(fs.log_weights[seen]).sum()
    np.testing.assert_allclose(got[3][0], w @ fs.means[seen, fs.index[3], :2], atol=1e-12)
    best = int(np.argmax(fs.log_weights))
    best_map = {i: fs.means[best, col, :2] for i, col in fs.index.items()}
    error = landmark_rmse({i: mean for i, (mean, _) in got.items()}, lm, align)
    assert error < 0.08 and error < 0.6 * landmark_rmse(best_map, lm, align)


@pytest.mark.parametrize("version", [1, 2])
def test_same_seed_same_result(synthetic, version):
    msgs = synthetic[0][:600]  # ten seconds
    cal = synthetic[3]
    a = replay(create("fastslam", cal, matched(version)), msgs)
    b = replay(create("fastslam", cal, matched(version)), msgs)
    c = replay(create("fastslam", cal, matched(version, seed=1)), msgs)
    assert np.array_equal(a.trajectory().poses, b.trajectory().poses)
    assert np.array_equal(a.means, b.means)
    assert not np.array_equal(a.trajectory().poses, c.trajectory().poses)


# -- the whole state smoothed ---------------------------------------------------------------

ISSUE13_LANDMARKS = dict(
    enumerate([(10, -2), (15, 10), (15, 15), (10, 20), (3, 15), (-5, 20), (-5, 5), (-10, 15)])
)


def issue13_drive(seed: int, **fields):
    """Issue 13's landmark drive (50 s, range σ 0.3 m, bearing σ 2°) and FastSLAM told its
    noise, with `fields` of its config; returns (the filter after the drive, the truth)."""
    drive = DriveNoise()
    steps, truth = landmark_drive(ISSUE13_LANDMARKS, 500, 0.1, 1.0, 0.1, drive, seed=seed)
    noise = MotionNoise(
        velocity_frac=drive.v * math.sqrt(0.1), omega_frac=0.0,
        omega_floor=drive.omega * math.sqrt(0.1),
    )  # fmt: skip
    sensor = {"range_sigma_m": drive.range_m, "range_sigma_frac": 0.0}
    cfg = FastSlamConfig(noise=noise, bearing_sigma_rad=drive.bearing_rad, **sensor, **fields)
    fs = replay(create("fastslam", WalkerCalibration(), cfg), [m for s in steps for m in s])
    return fs, Trajectory(truth[:, 0], truth[:, 1:])


@pytest.mark.parametrize("slip", [False, True])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_whole_state_smoother_carries_the_final_map_back(seed, slip):
    """smoother="rts-full" against the ancestry paths and the filtered means of the same
    particles (the smoothing draws nothing: the filter, its map and its filtered track
    are the same). Measured, seeds 0–3: 0.084 / 0.106 / 0.079 / 0.084 m against ancestry
    0.111 / 0.130 / 0.100 / 0.103 and filtered 0.122 / 0.149 / 0.106 / 0.133 (EKF-SLAM
    smoothed 0.063 / 0.066 / 0.061 / 0.060). With slip estimation the state's top is the
    pose and k (here without wheel encoders k moves nothing but itself): seeds 0–2 0.086
    / 0.105 / 0.077 m against 0.112 / 0.130 / 0.102 and 0.115 / 0.149 / 0.104."""
    more = {"slip": SlipEstimation(estimate=True)} if slip else {}
    full, gt = issue13_drive(seed, **more)
    paths, _ = issue13_drive(seed, smoother="ancestry", **more)
    filtered, _ = issue13_drive(seed, smoother="none", **more)
    assert full._full.top == (5 if slip else 3)
    assert full.revises_past and not filtered.revises_past
    smoothed = full.trajectory()  # (the last sightings used first)
    np.testing.assert_array_equal(full.track.trajectory().poses, filtered.trajectory().poses)
    assert full.landmarks().keys() == paths.landmarks().keys()
    for i, (mean, _) in full.landmarks().items():
        np.testing.assert_array_equal(mean, paths.landmarks()[i][0])
    error = ate(smoothed, gt)["ate_rmse_m"]
    assert error < 0.85 * ate(paths.trajectory(), gt)["ate_rmse_m"]
    assert error < 0.8 * ate(filtered.trajectory(), gt)["ate_rmse_m"]
    assert len(smoothed) == len(filtered.trajectory())  # a pose per odometry step
    assert "note" not in full.diagnostics()


def test_over_its_memory_budget_the_ancestry_paths_are_the_trajectory_and_it_says_so():
    small, _ = issue13_drive(0, smoother_budget_mb=0.05)  # the first ~60 updates' moments
    paths, _ = issue13_drive(0, smoother="ancestry")
    assert "smoother_budget_mb (0.05 MB)" in small.diagnostics()["note"]
    np.testing.assert_array_equal(small.trajectory().poses, paths.trajectory().poses)


# -- the simulated course: slip on a dusty floor -------------------------------------------


@pytest.mark.slow
def test_course_with_slip(course_trial):
    """Defaults (100 particles, MotionNoise(), range-bearing), seeds 0, 1, 2, measured:
    unaligned ATE: dead reckoning 0.38 m; FastSLAM 2.0 0.33 / 0.19 / 0.45 m; FastSLAM 1.0
    0.77 / 0.53 / 0.81 m. Aligned: DR 0.37; 2.0 0.23 / 0.16 / 0.28; 1.0 0.51 / 0.40 / 0.52.
    Landmark RMSE: 2.0 0.33 / 0.17 / 0.63; 1.0 0.96 / 0.49 / 0.81 (EKF-SLAM: 0.19 m
    unaligned, 0.17 m landmarks). Over seeds 0–7, 2.0 spans 0.19–0.63 m and beats DR in
    six of eight; 1.0 spans 0.33–0.81 m and beats it in one: 1.0 does NOT beat dead
    reckoning here. The default odometry noise is about five times the simulator's real
    error (DR claims σθ ≈ 0.9 rad at the end, its actual error is 0.17 rad), so the
    particles spread wide while exploring and the surviving lineage wanders; 2.0's
    proposal keeps them on the observations. So this compares medians over three seeds.
    Re-measured on the trial of the goggle-wearing users (2026-12-02), medians: unaligned
    DR 0.41 m, 2.0 0.374 m, 1.0 0.368 m — 2.0 and 1.0 tie here (within 2 %), both beat
    dead reckoning."""
    trial = read_log(course_trial)
    msgs = list(trial.messages())
    init = trial.metadata["config"]["initial_pose"]
    gt_msgs = [m for m in msgs if isinstance(m, GroundTruthPose)]
    t = np.array([m.t for m in gt_msgs])
    keep = np.concatenate([[True], np.diff(t) > 0])
    gt = Trajectory(t[keep], np.array([(m.x, m.y, m.theta) for m in gt_msgs])[keep])
    truth = from_metadata(trial.metadata)

    dr = replay(create("dead-reckoning", trial.calibration, initial_pose=init), msgs)
    e_dr = ate(dr.trajectory(), gt)
    median = {}
    for version in (1, 2):
        rows = []
        for seed in range(3):
            cfg = FastSlamConfig(version=version, seed=seed)
            fs = replay(create("fastslam", trial.calibration, cfg, initial_pose=init), msgs)
            assert len(fs.landmarks()) == len(truth) and fs.diagnostics()["resamples"] > 0
            e = ate(fs.trajectory(), gt)
            lm = landmark_rmse({i: mean for i, (mean, _) in fs.landmarks().items()}, truth)
            rows.append((e["ate_rmse_unaligned_m"], e["ate_rmse_m"], lm))
        median[version] = np.median(rows, axis=0)
    unaligned2, aligned2, lm2 = median[2]
    assert unaligned2 < e_dr["ate_rmse_unaligned_m"]
    assert aligned2 < 0.8 * e_dr["ate_rmse_m"]
    assert unaligned2 <= 1.05 * median[1][0]  # no worse than 1.0 (a tie on this trial)
    assert lm2 < 0.5


# -- no observations, outliers, unknown ids ----------------------------------------------


@pytest.mark.parametrize("version", [1, 2])
def test_without_observations_it_is_dead_reckoning_and_says_so(version):
    cal = WalkerCalibration()
    fs = create("fastslam", cal, FastSlamConfig(version=version))
    dr = create("dead-reckoning", cal)
    for k in range(100):
        m = EncoderTicks(0.02 * k, 5 * k, 6 * k)
        fs.process(m)
        dr.process(m)
    assert "odometry only" in fs.diagnostics()["note"]
    traj = fs.trajectory()  # the smoothed path, sampled every path_snapshot_s
    a, b = traj.poses, dr.trajectory().interpolate(traj.t)
    cov, cov_dr = fs.estimate().covariance, dr.estimate().covariance
    if version == 2:  # sampled only at an observation: the particles stay on the DR path
        assert np.allclose(a, b) and np.allclose(cov, cov_dr)
    else:  # sampled every step: the mean of 100 particles, within a few σ/√N
        assert np.abs(a[:, :2] - b[:, :2]).max() < 0.03
        assert np.allclose(np.diag(cov), np.diag(cov_dr), rtol=0.5)


@pytest.mark.parametrize("version", [1, 2])
@pytest.mark.parametrize("associate", [False, True])
def test_outlier_is_gated_and_unknown_ids_are_counted(version, associate):
    cal = WalkerCalibration()
    fs = create("fastslam", cal, FastSlamConfig(version=version, association_enabled=associate))
    fs.process(EncoderTicks(0.0, 0, 0))
    fs.process(RangeBearing(0.0, 7, 2.0, 0.0))  # landmark 7 at (2, 0)
    for k in range(1, 20):
        fs.process(EncoderTicks(0.05 * k, 0, 0))
        fs.process(RangeBearing(0.05 * k, 7, 2.0, 0.0))
    before = fs.estimate().pose.copy()
    fs.process(RangeBearing(1.0, 7, 5.0, 1.0))  # 3 m off: an outlier
    fs.process(RangeBearing(1.0, -1, 1.0, math.pi))  # no ID, behind: 3 m from landmark 7
    if not associate:  # counted, not used
        assert np.allclose(fs.estimate().pose, before)
    d = fs.diagnostics()
    assert d["gated"] == 1 and d["without_id"] == 1 and d["new_landmarks"] == 1
    assert d["updates"] == 19
    mean, cov = fs.landmarks()[7]
    assert mean == pytest.approx([2.0, 0.0], abs=1e-6)
    assert cov[0, 0] < 0.05**2
    assert list(fs.landmarks()) == [7]  # the sighting without an ID: at most provisional
    if associate:  # a new, provisional landmark in every particle
        assert d["new"] == 1 and d["provisional_pending"] == 1 and d["map_landmarks"] == 1


def test_landmark_arrays_grow_and_range_bearing_needs_no_yaw_only_in_range_bearing_mode():
    cal = WalkerCalibration()
    fs = create("fastslam", cal, FastSlamConfig(n_particles=20))
    fs.process(EncoderTicks(0.0, 0, 0))
    for i in range(30):  # beyond the initial capacity of 8 columns
        fs.process(RangeBearing(0.1, 100 + i, 1.0 + 0.1 * i, 0.1 * i - 1.5))
    lms = fs.landmarks()
    assert len(lms) == 30 and fs.means.shape[1] >= 30
    for i in range(30):
        a = 0.1 * i - 1.5
        assert lms[100 + i][0] == pytest.approx((1.0 + 0.1 * i) * np.array([np.cos(a), np.sin(a)]))
    tp = create("fastslam", cal, FastSlamConfig(observation="tag-pose"))
    tp.process(RangeBearing(0.1, 3, 1.0, 0.0))
    assert tp.diagnostics()["without_yaw"] == 1 and not tp.landmarks()


def test_same_time_observations_in_separate_messages_share_one_proposal():
    """MRCLAM gives every landmark of an image its own RangeBearing message, all with the
    image's timestamp: they are held and folded into one FastSLAM 2.0 proposal and one
    pose sample, exactly as the same landmarks in one TagDetections frame."""
    cal = WalkerCalibration()
    optical_T_walker = invert_transform(cal.tag_mount.walker_T_optical())
    tags = {4: np.array([3.0, 1.0]), 9: np.array([2.5, -1.5])}  # world positions
    ticks = [EncoderTicks(0.02 * k, 8 * k, 9 * k) for k in range(60)]
    dr = create("dead-reckoning", cal)
    poses = {}
    for k, m in enumerate(ticks):
        dr.process(m)
        poses[k] = dr.estimate().pose

    def seen_from(k: int) -> dict[int, tuple[float, float]]:
        x, y, th = poses[k]
        c, s_ = math.cos(th), math.sin(th)
        return {
            i: (c * (u - x) + s_ * (v - y) + 0.01, -s_ * (u - x) + c * (v - y))
            for i, (u, v) in tags.items()
        }

    def frame(k: int) -> list:
        dets = tuple(
            TagDetection(
                i, optical_T_walker @ make_transform(np.eye(3), (x, y, 0.3)), np.zeros((4, 2))
            )
            for i, (x, y) in seen_from(k).items()
        )
        return [TagDetections(ticks[k].t, dets)]

    def single(k: int) -> list:
        return [
            RangeBearing(ticks[k].t, i, math.hypot(x, y), math.atan2(y, x))
            for i, (x, y) in seen_from(k).items()
        ]

    def run(observations) -> object:
        fs = create("fastslam", cal, FastSlamConfig(n_particles=50, seed=4))
        for k, m in enumerate(ticks):
            fs.process(m)
            if k in (25, 50):  # the same two tags, twice
                for o in observations(k):
                    fs.process(o)
        return fs

    a, b = run(frame), run(single)
    assert np.allclose(a.poses, b.poses, atol=1e-9)
    assert np.allclose(a.log_weights, b.log_weights, atol=1e-9)
    assert a.diagnostics()["updates"] == b.diagnostics()["updates"] == 2
    assert b.diagnostics()["new_landmarks"] == 2
