"""The iSAM2 smoother: beats the filters, revises the past, rebuilds the map, is robust."""

import math
from pathlib import Path

import numpy as np
import pytest
from helpers import replay

from experiments.metrics import ate, landmark_rmse, map_scores, trajectory_alignment
from experiments.pipeline import Pipeline
from hardware.calibration import WalkerCalibration
from hardware.geometry import wrap_angle
from hardware.log import read_log
from hardware.messages import EncoderTicks, RangeBearing, VelocityOdometry
from hardware.sim.world import World
from slam.base import create
from slam.gtsam_smoother import GtsamConfig
from slam.landmarks import from_metadata


@pytest.mark.slow
def test_smoother_beats_dead_reckoning_and_its_rebuilt_map_is_cleaner(course_trial):
    dr, dr_pipe, trial = replay(course_trial, "dead-reckoning")
    sm, sm_pipe, _ = replay(course_trial, "gtsam")
    gt = dr_pipe.recorded.groundtruth_trajectory()
    e_dr, e_sm = ate(dr.trajectory(), gt), ate(sm.trajectory(), gt)
    assert e_sm["ate_rmse_m"] < 0.5 * e_dr["ate_rmse_m"]
    assert e_sm["ate_rmse_unaligned_m"] < 0.5 * e_dr["ate_rmse_unaligned_m"]
    world = World.from_dict(trial.metadata["world"])
    outlines = [p for _, p in world.footprint_polygons(0.05, 2.0)]
    area = dr_pipe.mapper.grid.resolution**2
    phantom_dr = map_scores(dr_pipe.mapper.occupied_xy(), area, outlines)["phantom_area_m2"]
    phantom_sm = map_scores(sm_pipe.mapper.occupied_xy(), area, outlines)["phantom_area_m2"]
    assert phantom_sm < 0.5 * phantom_dr
    assert sm.revision > 100 and sm.diagnostics()["landmark_factors"] > 100


def test_odometry_only_is_the_odometry_chain_and_says_so():
    cal = WalkerCalibration()
    sm, dr = create("gtsam", cal), create("dead-reckoning", cal)
    for k in range(300):
        m = EncoderTicks(0.02 * k, 5 * k, 6 * k + (k // 50))
        sm.process(m)
        dr.process(m)
    assert np.allclose(sm.trajectory().poses, dr.trajectory().poses, atol=1e-6)
    assert "odometry only" in sm.diagnostics()["note"]


def _square_messages(outlier=False, wrong_id=False):
    """A 4 m square (exact ticks) seeing landmark 3 at (2, 2) from every keyframe;
    outlier: the third side's ranges 3 m long; wrong_id: halfway along the second
    side, three more sightings of landmark 3 at once with their bearings π off (another
    landmark's, read with the wrong ID, as MRCLAM's robot 3 has them)."""
    cal = WalkerCalibration()
    m = cal.metres_per_count
    left = right = 0
    t = 0.0
    yield EncoderTicks(t, 0, 0)
    pose = np.zeros(3)
    for side in range(4):
        for step in range(40):  # 1 m in 2.5 cm steps along x of the walker
            n = round(0.025 / m)
            left, right = left + n, right + n
            t += 0.05
            yield EncoderTicks(t, left, right)
            pose[:2] += n * m * np.array([np.cos(pose[2]), np.sin(pose[2])])
            d = np.array([2.0, 2.0]) - pose[:2]
            rng, bearing = np.hypot(*d), np.arctan2(d[1], d[0]) - pose[2]
            if outlier and side == 2:
                rng += 3.0
            yield RangeBearing(t, 3, rng, bearing)
            if wrong_id and side == 1 and step == 20:
                for k in range(3):
                    yield RangeBearing(t, 3, rng + 0.1 * k, bearing + np.pi)
        # turn 90° left on the spot
        n = round(np.pi / 2 * cal.track_m / 2 / m)
        left, right = left - n, right + n
        t += 0.5
        yield EncoderTicks(t, left, right)
        pose[2] += n * m * 2 / cal.track_m


def _square_with_landmarks(outlier=False, config=None, wrong_id=False):
    """The smoother after driving the square of `_square_messages`."""
    sm = create("gtsam", WalkerCalibration(), config)
    for msg in _square_messages(outlier, wrong_id):
        sm.process(msg)
    return sm


def test_landmark_position_and_robust_outliers():
    clean = _square_with_landmarks()
    mean, cov = clean.landmarks()[3]
    assert mean == pytest.approx([2.0, 2.0], abs=0.02)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    assert clean.diagnostics()["gated"] == 0
    # a whole side of 3 m-off ranges: the gate leaves every one out ...
    noisy = _square_with_landmarks(outlier=True)
    assert noisy.diagnostics()["gated"] == 40
    assert noisy.landmarks()[3][0] == pytest.approx(mean, abs=1e-6)
    # ... and without it they drag the landmark (by 3 cm), much less than 3 m (Huber)
    huber = _square_with_landmarks(outlier=True, config=GtsamConfig(gate_chi2=0.0))
    assert huber.diagnostics()["gated"] == 0
    assert 0.01 < np.hypot(*(huber.landmarks()[3][0] - mean)) < 0.5


def test_a_sighting_and_the_keyframe_it_starts_share_one_update():
    """One iSAM2 update per sighting time, whether or not it starts a keyframe (the
    square: 160 sightings, 34 of them starting a keyframe), plus the start's and the
    four turns' (keyframes of the odometry alone): 165, where the keyframe had an update
    of its own before 2026-12-05 (199)."""
    d = _square_with_landmarks().diagnostics()
    assert d["keyframes"] == 38 and d["landmark_factors"] == 160
    assert d["updates"] == 1 + 160 + 4


def test_sightings_with_a_wrong_id_are_gated():
    """Three sightings at once with their bearings π off (a wrong ID): gated, the
    trajectory is the clean run's; without the gate they turn the walker (here by 0.2°:
    the exact odometry holds the heading; MRCLAM robot 3's turned by 150°)."""
    clean = _square_with_landmarks()
    wrong = _square_with_landmarks(wrong_id=True)
    assert wrong.diagnostics()["gated"] == 3
    assert np.allclose(wrong.trajectory().poses, clean.trajectory().poses, atol=1e-9)
    ungated = _square_with_landmarks(wrong_id=True, config=GtsamConfig(gate_chi2=0.0))
    turned = np.abs(wrap_angle(ungated.trajectory().poses[:, 2] - clean.trajectory().poses[:, 2]))
    assert turned.max() > 1e-3
    with pytest.raises(ValueError, match="gate_chi2"):
        GtsamConfig(gate_chi2=-1.0)


def test_without_landmarks_the_observations_are_ignored():
    """use_landmarks=False (scan correction without tags on a log that has them): the
    range-bearing observations of the square add no factor and no landmark; an outlier
    side that drags the landmark-using smoother leaves this one untouched."""
    ignoring = _square_with_landmarks(outlier=True, config=GtsamConfig(use_landmarks=False))
    assert ignoring.landmarks() == {} and ignoring.diagnostics()["landmark_factors"] == 0
    odometry = create("gtsam", WalkerCalibration())
    for msg in _square_messages(outlier=True):
        if isinstance(msg, EncoderTicks):
            odometry.process(msg)
    assert np.allclose(ignoring.trajectory().poses, odometry.trajectory().poses, atol=1e-9)


def test_same_input_same_output():
    a, b = _square_with_landmarks(), _square_with_landmarks()
    assert np.array_equal(a.trajectory().poses, b.trajectory().poses)


INTEL = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "intel_lab"


@pytest.mark.data
@pytest.mark.skipif(not INTEL.exists(), reason=f"Intel lab data not found at {INTEL}")
def test_long_odometry_only_chain_does_not_break_the_solver():
    """The whole Intel log without landmarks or scans: 3000 keyframes drifting tens of
    metres. iSAM2's Cholesky factorization gave up on it as indeterminate; QR does not,
    and the smoother follows dead reckoning."""
    from hardware.datasets import open_dataset

    ds = open_dataset("carmen", INTEL / "intel.gfs.log.gz")
    start = ds.metadata["config"]["initial_pose"]
    sm, dr = (
        create("gtsam", ds.calibration, initial_pose=start),
        create("dead-reckoning", ds.calibration, initial_pose=start),
    )
    for m in ds.messages():
        sm.process(m)
        dr.process(m)
    assert sm.diagnostics()["keyframes"] > 3000
    end_sm, end_dr = sm.trajectory().poses[-1], dr.trajectory().poses[-1]
    assert np.hypot(*(end_sm[:2] - end_dr[:2])) < 0.05


@pytest.mark.slow
def test_tag_pose_factors_localize_and_map_the_tags(course_trial):
    """observation="tag-pose": each tag a Pose2, each detection a BetweenFactorPose2 with
    its yaw. On the course trial (defaults otherwise) it beats dead reckoning as the
    range-bearing factors do, and the tags' positions come out near the truth once the
    map frame is aligned (the frame itself takes the heading error of the first seconds,
    before any tag is seen). Measured (the walker-wide odometry noise default, the
    goggle-wearing users of 2026-12-02): tag RMSE 0.107 m aligned (other trials of these
    users: 0.060–0.070 m aligned, 0.17–0.43 m unaligned)."""
    trial = read_log(course_trial)
    start = trial.metadata["config"]["initial_pose"]
    sm = create("gtsam", trial.calibration, GtsamConfig(observation="tag-pose"), initial_pose=start)
    pipe = Pipeline(sm, trial.calibration, reference_map=False)
    pipe.run(trial.messages())
    dr, _, _ = replay(course_trial, "dead-reckoning")
    gt = pipe.recorded.groundtruth_trajectory()
    assert ate(sm.trajectory(), gt)["ate_rmse_m"] < 0.3 * ate(dr.trajectory(), gt)["ate_rmse_m"]
    lms = sm.landmarks()
    assert len(lms) >= 20 and sm.diagnostics()["without_yaw"] == 0
    est = {i: m for i, (m, _) in lms.items()}
    aligned = landmark_rmse(
        est, from_metadata(trial.metadata), trajectory_alignment(sm.trajectory(), gt)
    )
    assert aligned < 0.15
    assert all(np.all(np.linalg.eigvalsh(c) > 0) for _, c in lms.values())


def test_tag_pose_skips_observations_without_a_yaw():
    cal = WalkerCalibration()
    sm = create("gtsam", cal, GtsamConfig(observation="tag-pose"))
    for k in range(20):
        sm.process(EncoderTicks(0.05 * k, 10 * k, 10 * k))
        sm.process(RangeBearing(0.05 * k, 3, 2.0, 0.1))  # a range-bearing sensor: no yaw
    d = sm.diagnostics()
    assert d["without_yaw"] == 20 and d["landmark_factors"] == 0 and sm.landmarks() == {}
    with pytest.raises(ValueError, match="observation"):
        GtsamConfig(observation="tag-corners")


def test_sightings_during_an_odometry_gap_place_the_walker_across_it():
    """Driving straight at 0.5 m/s past five landmarks, seen every 0.5 s, with the
    odometry unknown for 2 s (velocity of NaN, as the CARMEN importer emits a gap): a
    sighting in the gap starts a keyframe of its own, though the odometry moved nothing
    (it attached to the keyframe before the gap until 2026-12-05: 0.43 m off there), and
    the path between keyframes is bridged by the gap's variance too."""
    marks = {1: (2.0, 2.0), 2: (5.0, -2.0), 3: (8.0, 2.0), 4: (3.5, -1.5), 5: (6.5, 1.8)}
    sm = create("gtsam", WalkerCalibration(), initial_pose=(0.0, 0.0, 0.0))
    times, xs = [], []
    for k in range(201):
        t, x = round(0.1 * k, 6), 0.05 * k
        v = math.nan if 80 <= k < 100 else 0.5
        sm.process(VelocityOdometry(t, v, 0.0 if math.isfinite(v) else math.nan))
        times.append(t)
        xs.append(x)
        for lid, (lx, ly) in marks.items():
            if k % 5 == 0 and math.hypot(lx - x, ly) < 6.0:
                sm.process(RangeBearing(t, lid, math.hypot(lx - x, ly), math.atan2(ly, lx - x)))
    assert sm.diagnostics()["odometry_gaps"] == 20
    poses = sm.trajectory().interpolate(np.array(times))
    assert np.abs(poses[:, 0] - np.array(xs)).max() < 0.01
    assert np.abs(poses[:, 1:]).max() < 0.01


def test_a_gap_match_needs_a_candidate_to_refine():
    from slam.scan_graph import SequentialGate

    with pytest.raises(ValueError, match="unknown_candidates must be >= 1, got 0"):
        SequentialGate(unknown_candidates=0)


def test_the_smoother_offers_its_scan_half_what_it_uses():
    """slam.scan_graph.KeyframeGraph names what the scan half uses of the smoother: the
    smoother has each member, with the same signature."""
    import inspect

    from slam.gtsam_smoother import GtsamSmoother
    from slam.scan_graph import KeyframeGraph

    smoother = GtsamSmoother(GtsamConfig(scan_matching=True), WalkerCalibration())
    for name in KeyframeGraph.__annotations__:
        assert hasattr(smoother, name), name
    members = [n for n in vars(KeyframeGraph) if not n.startswith("_")]
    assert len(members) == 10
    for name in members:
        want, got = vars(KeyframeGraph)[name], inspect.getattr_static(GtsamSmoother, name)
        assert type(got) is type(want), name
        if isinstance(want, property):
            want, got = want.fget, got.fget
        assert inspect.signature(got) == inspect.signature(want), name
    assert smoother.scans.smoother is smoother
