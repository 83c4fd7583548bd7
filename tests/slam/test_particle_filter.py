"""Particle filter (Monte Carlo localization): seeded, falls back to odometry, counts what
it cannot use, resamples on degeneracy, beats dead reckoning with a known tag map, and
localises by depth frames against a map (see the xfail for a map built by itself)."""

import math

import numpy as np
import pytest

from experiments.metrics import ate
from experiments.pipeline import Pipeline
from hardware.calibration import WalkerCalibration
from hardware.log import read_log
from hardware.messages import (
    DepthFrame,
    EncoderTicks,
    GroundTruthPose,
    LaserScan,
    RangeBearing,
    TagDetection,
    TagDetections,
)
from hardware.sim.landmark_drive import DriveNoise, landmark_drive
from mapping.mapper import OccupancyMapper
from slam import landmarks
from slam.base import create
from slam.dead_reckoning import DeadReckoningConfig
from slam.grid_rbpf import GridRbpfConfig
from slam.motion import MotionNoise
from slam.particle_filter import (
    ODOMETRY_ONLY_NOTE,
    ParticleFilter,
    ParticleFilterConfig,
    systematic_resample,
)
from slam.trajectory import Trajectory

CAL = WalkerCalibration()
# A range-bearing sensor whose range is as informative as its bearing (MRCLAM-like), for the
# synthetic RangeBearing tests (the defaults describe a tag camera: precise bearing only).
RB_SENSOR = {"range_sigma_m": 0.05, "range_sigma_frac": 0.02, "bearing_sigma_rad": 0.03}


def arc_ticks(n: int, left: int = 20, right: int = 24, dt: float = 0.02) -> list[EncoderTicks]:
    """Cumulative ticks of a gentle left arc, one message every dt."""
    return [EncoderTicks(dt * k, left * k, right * k) for k in range(n + 1)]


def test_registered_and_create_fills_the_landmark_map():
    lm = {3: np.array([1.0, 2.0])}
    pf = create("particle-filter", CAL, initial_pose=(1.0, 2.0, 0.5), landmark_map=lm)
    assert isinstance(pf, ParticleFilter)
    assert pf.config.landmark_map is lm
    assert pf.config.initial_pose == (1.0, 2.0, 0.5)
    assert np.allclose(pf.particles, [1.0, 2.0, 0.5])  # initial_sigma 0: the start is known
    with pytest.raises(ValueError, match="n_particles"):
        ParticleFilterConfig(n_particles=0)


def _run_synthetic(seed: int) -> ParticleFilter:
    cfg = ParticleFilterConfig(
        n_particles=200, seed=seed, initial_sigma=(0.1, 0.1, 0.05), landmark_map={1: [3.0, 1.0]}
    )
    pf = ParticleFilter(cfg, CAL)
    for k, m in enumerate(arc_ticks(60)):
        pf.process(m)
        if k % 5 == 0:  # landmark 1 seen from roughly where odometry says the walker is
            pose = pf.estimate().pose
            d = np.array([3.0, 1.0]) - pose[:2]
            pf.process(RangeBearing(m.t, 1, float(np.hypot(*d)) + 0.02, 0.0))
    return pf


def test_same_seed_same_result_different_seed_different_particles():
    a, b, c = _run_synthetic(0), _run_synthetic(0), _run_synthetic(1)
    assert np.array_equal(a.particles, b.particles)
    assert np.array_equal(a.trajectory().poses, b.trajectory().poses)
    assert a.diagnostics() == b.diagnostics()
    assert not np.allclose(a.particles, c.particles)


class _FixedOffset:
    """A generator stand-in whose random() returns a given number."""

    def __init__(self, u: float) -> None:
        self.u = u

    def random(self) -> float:
        return self.u


def test_systematic_resample_is_filterpys_algorithm(monkeypatch):
    import filterpy.monte_carlo.resampling as fp

    w = np.random.default_rng(4).dirichlet(np.full(300, 0.3))
    u = 0.637
    # filterpy draws its offset from numpy's global generator: give both the same offset
    monkeypatch.setattr(fp, "random", lambda: u)
    assert np.array_equal(systematic_resample(w, _FixedOffset(u)), fp.systematic_resample(w))
    assert np.array_equal(
        systematic_resample(w, np.random.default_rng(3)),
        systematic_resample(w, np.random.default_rng(3)),
    )


def test_without_observations_it_follows_odometry_and_says_so():
    # Low noise, so that the cloud stays nearly Gaussian: then its mean is the odometry's
    # pose and its spread the odometry's covariance, up to sampling error.
    noise = MotionNoise(wheel_m=1e-4)
    filtered = ParticleFilterConfig(noise=noise, smoother="none")
    pf = create("particle-filter", CAL, filtered)
    dr = create("dead-reckoning", CAL, DeadReckoningConfig(noise=noise))
    for m in arc_ticks(100, left=10, right=12):
        pf.process(m)
        dr.process(m)
    est, ref = pf.estimate(), dr.estimate()
    sigma = np.sqrt(np.diag(ref.covariance))
    assert np.all(np.abs(est.pose - ref.pose) < 0.2 * sigma)  # 0.2σ ≈ 4.5 standard errors
    ratio = np.diag(est.covariance) / np.diag(ref.covariance)
    assert np.all(np.abs(ratio - 1) < 0.25), ratio  # sampling error of a variance ~ √(2/n)
    assert len(pf.trajectory()) == len(dr.trajectory())
    d = pf.diagnostics()
    assert d["note"] == ODOMETRY_ONLY_NOTE
    assert d["resamples"] == 0 and d["landmark_observations"] == 0 and d["scan_updates"] == 0


def test_unknown_landmark_ids_are_counted_not_used():
    pf = ParticleFilter(
        ParticleFilterConfig(
            n_particles=100, initial_sigma=(0.2, 0.2, 0.1), landmark_map={7: (2, 0)},
            association_enabled=False,
        ),
        CAL,
    )  # fmt: skip
    pf.process(EncoderTicks(0.0, 0, 0))
    before = pf.particles.copy()
    pf.process(RangeBearing(0.0, 99, 2.0, 0.0))  # not in the map
    pf.process(RangeBearing(0.0, -1, 1.0, 0.3))  # no ID
    cam_T_tag = np.eye(4)
    cam_T_tag[2, 3] = 2.0  # 2 m in front of the tag camera
    pf.process(TagDetections(0.0, (TagDetection(42, cam_T_tag, np.zeros((4, 2))),)))
    assert np.array_equal(pf.particles, before)
    assert np.allclose(pf.weights, 1.0 / 100)
    d = pf.diagnostics()
    assert d["unknown_ids"] == 3 and d["landmark_observations"] == 0
    assert d["note"] == ODOMETRY_ONLY_NOTE
    pf.process(RangeBearing(0.0, 7, 2.0, 0.0))  # a known one is used
    d = pf.diagnostics()
    assert d["landmark_observations"] == 1 and "note" not in d


def test_resamples_when_the_weights_degenerate():
    cfg = ParticleFilterConfig(
        n_particles=400,
        initial_sigma=(0.5, 0.5, 0.2),
        landmark_map={1: (3.0, 0.0), 2: (0.0, 3.0)},
        **RB_SENSOR,
    )
    pf = ParticleFilter(cfg, CAL)
    pf.process(EncoderTicks(0.0, 0, 0))
    spread = pf.particles[:, :2].std(axis=0)
    assert pf.n_eff == pytest.approx(400)
    # at the true pose (0, 0, 0) both landmarks are 3 m away, ahead and to the left
    pf.process(RangeBearing(0.0, 1, 3.0, 0.0))
    pf.process(RangeBearing(0.0, 2, 3.0, math.pi / 2))
    # both observations of t = 0 are weighted in before the particles are resampled once,
    # when the next message moves them
    assert pf.diagnostics()["resamples"] == 0
    pf.process(EncoderTicks(0.02, 0, 0))
    d = pf.diagnostics()
    assert d["resamples"] == 1
    assert d["n_eff_min"] < cfg.resample_threshold * cfg.n_particles
    assert pf.n_eff == pytest.approx(400)  # resampled: equal weights again
    assert np.all(pf.particles[:, :2].std(axis=0) < 0.5 * spread)
    assert np.hypot(*pf.estimate().pose[:2]) < 0.15


def test_no_resampling_while_the_weights_stay_even():
    pf = ParticleFilter(ParticleFilterConfig(n_particles=100, landmark_map={1: (3.0, 0.0)}), CAL)
    pf.process(EncoderTicks(0.0, 0, 0))
    pf.process(RangeBearing(0.0, 1, 3.1, 0.0))  # all particles alike: every weight the same
    assert pf.diagnostics()["resamples"] == 0
    assert pf.n_eff == pytest.approx(100)


def _straight_drive_with_biased_odometry(cfg: ParticleFilterConfig) -> ParticleFilter:
    """The walker drives 4 m straight along +x in 4 s while its ticks say it curves left
    (right wheel 10 % long); a landmark map of two tags is seen only in the last second,
    from the true poses."""
    pf = ParticleFilter(cfg, CAL)
    m = CAL.metres_per_count
    for k in range(201):
        t = 0.02 * k
        x = 1.0 * t  # true pose (x, 0, 0)
        pf.process(EncoderTicks(t, round(0.02 * k / m), round(0.022 * k / m)))
        if t >= 3.0 and k % 5 == 0:
            for lid, (u, v) in {1: (6.0, 1.0), 2: (6.0, -1.0)}.items():
                pf.process(RangeBearing(t, lid, math.hypot(u - x, v), math.atan2(v, u - x)))
    return pf


@pytest.mark.parametrize("smoother", ["rts", "ancestry"])
def test_smoothed_trajectory_corrects_the_stretch_before_the_observations(smoother):
    """Smoothing (RTS over the filtered moments, or the particles' ancestry) lets the
    observations of the last second also pull the path that led there back to the truth
    (y = 0), which the filtered means, fixed when they were recorded, cannot; the
    smoother revises the past."""
    lm = {1: (6.0, 1.0), 2: (6.0, -1.0)}
    noise = MotionNoise(wheel_m=0.01)
    common = {"n_particles": 500, "landmark_map": lm, "noise": noise, "seed": 3, **RB_SENSOR}
    smooth = _straight_drive_with_biased_odometry(ParticleFilterConfig(**common, smoother=smoother))
    filtered = _straight_drive_with_biased_odometry(ParticleFilterConfig(**common, smoother="none"))
    assert smooth.revises_past and not filtered.revises_past
    assert smooth.revision > 0
    t_mid = np.array([1.5, 2.0, 2.5])
    lateral_smooth = np.abs(smooth.trajectory().interpolate(t_mid)[:, 1])
    lateral_filtered = np.abs(filtered.trajectory().interpolate(t_mid)[:, 1])
    # measured (seeds 0-3): rts 0.03-0.08 m, ancestry 0.01-0.09 m, filtered 0.17-0.50 m
    assert np.all(lateral_smooth < 0.6 * lateral_filtered), (lateral_smooth, lateral_filtered)
    assert np.hypot(*smooth.trajectory().poses[-1, :2] - (4.0, 0.0)) < 0.1
    with pytest.raises(ValueError, match="smoother"):
        ParticleFilterConfig(smoother="fixed-lag")


def test_scan_proposal_draws_the_odometry_noise_of_one_step_at_a_sighting():
    # sightings at every odometry step; the odometry's turn noise a floor with no share of
    # the speed, so one step's covariance (ds, dθ) maps to a rank-2 pose covariance: its
    # draw at the next sighting must still be a draw (it was a Cholesky error)
    lm = {0: (10.0, -2.0), 1: (15.0, 10.0), 2: (3.0, 15.0), 3: (-5.0, 5.0)}
    drive = DriveNoise(v=0.5, omega=math.radians(10.0), range_m=0.3, bearing_rad=0.035)
    steps, truth = landmark_drive(lm, 100, 0.1, 1.0, 0.1, drive, seed=0)
    noise = MotionNoise(velocity_frac=0.16, omega_frac=0.0, omega_floor=0.055)
    sensor = {"range_sigma_m": 0.3, "range_sigma_frac": 0.0, "bearing_sigma_rad": 0.035}
    cfg = ParticleFilterConfig(n_particles=100, proposal="scan", noise=noise, **sensor)
    pf = create("particle-filter", CAL, cfg, landmark_map=lm)
    for msgs in steps:
        for m in msgs:
            pf.process(m)
    assert pf.diagnostics()["landmark_updates"] == 100
    assert ate(pf.trajectory(), Trajectory(truth[:, 0], truth[:, 1:]))["ate_rmse_m"] < 0.2


def test_scan_proposal_draws_a_long_stretch_as_the_motion_model_does():
    # 40 s of odometry without a sighting, then one: the scan proposal draws each step's
    # noise along its arc from the last drawn pose, so with the same seed its particles are
    # the motion proposal's; one Gaussian of the accumulated covariance could not bend
    # with the heading's uncertainty (MRCLAM robot 3's 40 s without a landmark)
    lm = {0: (10.0, -2.0), 1: (3.0, 15.0)}
    drive = DriveNoise(v=0.2, omega=0.1, range_m=0.1, bearing_rad=0.02)
    steps, _ = landmark_drive(lm, 400, 0.1, 1.0, 0.1, drive, seed=0)
    msgs = [
        m for k, s in enumerate(steps) for m in s if k == 399 or not isinstance(m, RangeBearing)
    ]
    clouds = []
    for proposal in ("motion", "scan"):
        pf = create(
            "particle-filter",
            CAL,
            ParticleFilterConfig(n_particles=300, proposal=proposal),
            landmark_map=lm,
        )
        for m in msgs:
            pf.process(m)
        pf.estimate()  # the sighting held is used
        assert pf.diagnostics()["landmark_updates"] == 1
        clouds.append(pf.particles)
    np.testing.assert_allclose(clouds[1], clouds[0], rtol=0, atol=1e-9)
    assert np.std(clouds[0][:, 2]) > 0.2  # a wide, bent cloud: σθ over 40 s


def test_an_outlier_does_not_wipe_out_the_right_particles():
    """Robust landmark likelihood: among correct observations of two tags, one with a
    wrong ID (π off in bearing, as MRCLAM's misread barcodes) leaves the estimate at the
    truth; with the plain Gaussian (outlier_prob 0) it drags the cloud away."""
    lm = {1: (3.0, 0.0), 2: (0.0, 3.0), 3: (-3.0, 0.0)}

    def run(eps: float) -> np.ndarray:
        cfg = ParticleFilterConfig(
            n_particles=1000, initial_sigma=(0.3, 0.3, 0.1), landmark_map=lm, seed=2,
            outlier_prob=eps, **RB_SENSOR,
        )  # fmt: skip
        pf = ParticleFilter(cfg, CAL)
        pf.process(EncoderTicks(0.0, 0, 0))
        for k in range(3):  # the truth is (0, 0, 0)
            pf.process(RangeBearing(0.1 * k, 1, 3.0, 0.0))
            pf.process(RangeBearing(0.1 * k, 2, 3.0, math.pi / 2))
        pf.process(RangeBearing(0.3, 3, 1.5, 0.0))  # tag 3 is 3 m behind, not 1.5 m ahead
        pf.process(EncoderTicks(0.4, 0, 0))
        return pf.estimate().pose

    robust, plain = run(0.01), run(0.0)
    assert np.hypot(*robust[:2]) < 0.05 and abs(robust[2]) < 0.02
    assert np.hypot(*plain[:2]) > 3 * np.hypot(*robust[:2])
    with pytest.raises(ValueError, match="outlier_prob"):
        ParticleFilterConfig(outlier_prob=1.0)


def _box_room_scan(pose, t, room=(-2.0, 4.0, -2.5, 3.0), n=180, range_max=8.0) -> LaserScan:
    """A 360° laser scan from `pose` inside a rectangular room (ray to the nearest wall)."""
    x, y, th = pose
    angles = -math.pi + 2 * math.pi * np.arange(n) / n
    c, s = np.cos(th + angles), np.sin(th + angles)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (room[1] - x) / c, (room[0] - x) / c)
        ty = np.where(s > 0, (room[3] - y) / s, (room[2] - y) / s)
    return LaserScan(t, -math.pi, 2 * math.pi / n, np.minimum(tx, ty), range_max)


def test_scan_likelihood_finds_the_pose_in_a_mapped_room():
    truth = np.array([0.3, -0.2, 0.4])
    mapper = OccupancyMapper(CAL)
    for _ in range(3):
        mapper.integrate_scan(_box_room_scan(truth, 0.0), truth)
    cfg = ParticleFilterConfig(
        initial_pose=tuple(truth), initial_sigma=(0.3, 0.3, 0.15), n_particles=300,
        use_scans=True, scan_every_m=0.0, scan_every_rad=0.0, max_beams=60,
    )  # fmt: skip
    pf = ParticleFilter(cfg, CAL)
    pf.attach_map(mapper)
    pf.process(EncoderTicks(0.0, 0, 0))
    prior_error = np.hypot(*(pf.particles[:, :2] - truth[:2]).T).mean()
    for k in range(3):
        pf.process(_box_room_scan(truth, 0.1 * k))
    est = pf.estimate()
    assert pf.diagnostics()["scan_updates"] == 3
    assert np.hypot(*(est.pose[:2] - truth[:2])) < 0.1 < prior_error
    assert abs(est.pose[2] - truth[2]) < 0.05


def test_scans_without_a_map_are_ignored():
    pf = ParticleFilter(ParticleFilterConfig(use_scans=True), CAL)
    pf.process(EncoderTicks(0.0, 0, 0))
    pf.process(_box_room_scan((0.0, 0.0, 0.0), 0.0))
    assert pf.diagnostics()["scan_updates"] == 0
    assert pf.diagnostics()["note"] == ODOMETRY_ONLY_NOTE


# -- the simulated course (tests/conftest.py: ~160 s on a dusty floor, with slip) ----------


def _groundtruth(times: list[float], poses: list[tuple]) -> Trajectory:
    t = np.array(times)
    keep = np.concatenate([[True], np.diff(t) > 0])
    return Trajectory(t[keep], np.array(poses)[keep])


def _replay(log, config=None, landmark_map=None):
    """Feed a trial to the particle filter and to dead reckoning (no mapper)."""
    trial = read_log(log)
    start = trial.metadata["config"]["initial_pose"]
    pf = create("particle-filter", trial.calibration, config, start, landmark_map=landmark_map)
    dr = create("dead-reckoning", trial.calibration, initial_pose=start)
    gt_t, gt = [], []
    for m in trial.messages():
        pf.process(m)
        dr.process(m)
        if isinstance(m, GroundTruthPose):
            gt_t.append(m.t)
            gt.append((m.x, m.y, m.theta))
    return pf, dr, _groundtruth(gt_t, gt), trial


@pytest.mark.slow
def test_known_tag_map_beats_dead_reckoning(course_trial):
    """At the defaults (500 particles, RTS-smoothed path). Measured: aligned ATE 0.018 m
    (unaligned 0.019 m; the filtered means: 0.014 m) against dead reckoning's 0.558 m."""
    lm = landmarks.from_metadata(read_log(course_trial).metadata)
    pf, dr, gt, _ = _replay(course_trial, landmark_map=lm)
    e_pf, e_dr = ate(pf.trajectory(), gt), ate(dr.trajectory(), gt)
    assert e_pf["ate_rmse_m"] < e_dr["ate_rmse_m"]
    assert e_pf["ate_rmse_unaligned_m"] < e_dr["ate_rmse_unaligned_m"]
    assert e_pf["ate_rmse_m"] < 0.05
    d = pf.diagnostics()
    assert d["landmark_observations"] > 500 and d["unknown_ids"] == 0
    assert "note" not in d


@pytest.mark.slow
def test_depth_frames_against_a_map_at_the_true_poses_localise(course_trial):
    """The scan likelihood alone, against a map it did not build itself (the frames mapped
    at the true poses, each frame scored before it is added). 500 particles (the default).
    Measured on the trial of the goggle-wearing users (2026-12-02): aligned ATE 0.031 m
    (1000: 0.029 m); dead reckoning 0.305 m. With 200 particles seed 1 gives 0.029 m but
    seed 0 loses its heading (36°) in a 5 s pivot about the fully braked right wheel at
    the south-west table corner, where the depth frames see little, and ends 2.5 m off
    (ATE 0.99 m): too few particles for that pivot."""
    trial = read_log(course_trial)
    cfg = ParticleFilterConfig(n_particles=500, use_scans=True)
    pf = create("particle-filter", trial.calibration, cfg, trial.metadata["config"]["initial_pose"])
    mapper = OccupancyMapper(trial.calibration)
    pf.attach_map(mapper)
    truth, gt_t, gt = None, [], []
    for m in trial.messages():
        pf.process(m)
        if isinstance(m, GroundTruthPose):
            truth = (m.x, m.y, m.theta)
            gt_t.append(m.t)
            gt.append(truth)
        elif isinstance(m, DepthFrame):
            mapper.integrate_depth(m, np.array(truth))
    e = ate(pf.trajectory(), _groundtruth(gt_t, gt))
    assert e["ate_rmse_m"] < 0.08
    assert pf.diagnostics()["scan_updates"] > 200


@pytest.mark.slow
def test_depth_frames_against_a_map_per_particle_beat_dead_reckoning_without_tags(course_trial):
    """The Rao-Blackwellized filter (grid-rbpf, 60 particles, each with its own
    grid) on the walker's 160×120 depth frames, the tag map ignored: it removes much of
    the slip's drift. Measured on course_trial (defaults, seed 0): aligned ATE 0.054 m vs
    dead reckoning 0.558 m, unaligned 0.306 vs 0.969 m; with the goggle-wearing users of
    2026-12-02 (trials with less drift) 0.095–0.131 m vs 0.26–0.39 m aligned; on this
    trial unaligned 0.391 vs 0.626 m."""
    trial = read_log(course_trial)
    start = trial.metadata["config"]["initial_pose"]
    cfg = GridRbpfConfig(use_landmarks=False)
    pf = create("grid-rbpf", trial.calibration, cfg, start, landmark_map={1: (0.0, 0.0)})
    pipe = Pipeline(pf, trial.calibration, reference_map=False)
    dr = create("dead-reckoning", trial.calibration, initial_pose=start)
    for m in trial.messages():
        pipe.feed(m)
        dr.process(m)
    gt = pipe.recorded.groundtruth_trajectory()
    d = pf.diagnostics()
    assert d["scan_updates"] > 200 and d["landmark_observations"] == 0  # scans only
    e_pf, e_dr = ate(pf.trajectory(), gt), ate(dr.trajectory(), gt)
    assert e_pf["ate_rmse_m"] < 0.5 * e_dr["ate_rmse_m"]
    assert e_pf["ate_rmse_unaligned_m"] < 0.8 * e_dr["ate_rmse_unaligned_m"]


@pytest.mark.slow
@pytest.mark.xfail(
    reason="depth frames against the shared map that the filter's own estimates build: "
    "measured on course_trial (500 particles, defaults + use_scans, 2026-12-02, the "
    "pipeline's one projection per frame, the mapper's point lattice): unaligned ATE 0.952 m "
    "vs dead reckoning 0.969 m (aligned 0.706 vs 0.558 m); with seed 3: 0.752 m (aligned "
    "0.580). Before the shared projection (the filter's own, off the lattice): 1.076 and "
    "0.870 m. Measured again 2026-12-06 (today's simulator; the field refreshed where no "
    "frame is scored): unaligned 0.595 m vs dead reckoning 0.626 m (aligned 0.503 vs "
    "0.403 m), seed 3 0.655 m; the commit before that change 0.814 and 0.488 m. It lands "
    "either side of this test's unaligned bound by the seed and stays worse than dead "
    "reckoning aligned, so it stays an xfail: a frame matches the map of the frames just "
    "before it to about 1° (rms at the true poses), and that error is built into the map "
    "the next frame is matched to, so the heading drifts about as fast as the odometry's.",
    strict=False,
)
def test_depth_frames_against_its_own_map_beat_dead_reckoning(course_trial):
    trial = read_log(course_trial)
    start = trial.metadata["config"]["initial_pose"]
    pf = create("particle-filter", trial.calibration, ParticleFilterConfig(use_scans=True), start)
    pipe = Pipeline(pf, trial.calibration, reference_map=False)
    pf.attach_map(pipe.mapper)  # what the pipeline is to do for every localizer with attach_map
    dr = create("dead-reckoning", trial.calibration, initial_pose=start)
    for m in trial.messages():
        pipe.feed(m)
        dr.process(m)
    gt = pipe.recorded.groundtruth_trajectory()
    assert pf.diagnostics()["scan_updates"] > 200
    e_pf, e_dr = ate(pf.trajectory(), gt), ate(dr.trajectory(), gt)
    assert e_pf["ate_rmse_unaligned_m"] < e_dr["ate_rmse_unaligned_m"]


def test_compiled_field_score_equals_the_cell_lookup():
    """The compiled scan likelihood (slam.grid_kernels.field_log_likelihood) sums the
    same cells as placing the points at each pose and indexing the field (`_cells`),
    points beyond the field's edge scored by its last entry."""
    from slam.particle_filter import _Field

    rng = np.random.default_rng(8)
    ny, nx = 40, 60
    log_p = np.append(rng.normal(size=ny * nx), -7.0)
    field = _Field(log_p, np.ones(ny * nx + 1, bool), (-1.0, 0.5), 0.05, (ny, nx))
    pf = create("particle-filter", WalkerCalibration())
    poses = np.column_stack(
        [rng.uniform(-0.5, 2.5, 50), rng.uniform(0.5, 2.5, 50), rng.uniform(-3, 3, 50)]
    )
    points = rng.uniform(-1.5, 1.5, (80, 2))
    expected = pf.pf.beam_weight * log_p[pf._cells(poses, points, field)].sum(axis=1)
    assert (pf._cells(poses, points, field) == ny * nx).any()  # some fall outside
    np.testing.assert_allclose(pf._score(poses, points, field), expected, rtol=1e-12)


@pytest.mark.parametrize(("sigma", "res"), [(0.1, 0.05), (0.3, 0.1), (0.05, 0.05)])
def test_likelihood_field_equals_the_formula_at_exact_distances(sigma, res):
    """The compiled field (slam.grid_kernels.log_likelihood_field) measures distances only
    up to the filter's cap; every cell, near a surface or far beyond the cap, equals
    log(p_hit·N(d; 0, σ) + p_rand) at the exact Euclidean distance (scipy's transform),
    to the last bit, and the last entry (outside the window) is log(p_rand)."""
    from scipy import ndimage

    from slam.grid_kernels import log_likelihood_field

    cfg = ParticleFilterConfig(sigma_hit_m=sigma)
    pf = ParticleFilter(cfg, WalkerCalibration())
    cap, table = pf._log_p_table(res)
    p_hit = cfg.z_hit / (math.sqrt(2.0 * math.pi) * sigma)
    p_rand = cfg.z_rand / cfg.max_range_m
    assert 1 < cap < 200 and table[-1] == math.log(p_rand)
    rng = np.random.default_rng(3)
    beyond = 0
    for density in (0.0005, 0.005, 0.05, 0.4):
        targets = rng.random((rng.integers(60, 140), rng.integers(60, 140))) < density
        targets[rng.integers(targets.shape[0]), :] |= density < 0.001  # a wall, at least
        dist = ndimage.distance_transform_edt(~targets).astype(np.float32).astype(float) * res
        expected = np.log(p_hit * np.exp(-0.5 * (dist / sigma) ** 2) + p_rand).ravel()
        got = log_likelihood_field(targets, table, cap)
        assert got.shape == (targets.size + 1,) and got[-1] == math.log(p_rand)
        np.testing.assert_array_equal(got[:-1], expected)
        beyond += np.count_nonzero(dist > cap * res)
    assert beyond > 500  # the sparse grids' cells beyond the cap are in the check
