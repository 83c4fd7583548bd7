"""2-D scan matching (slam.scan_matching) and scan-matching factors in the gtsam smoother.

Synthetic scans are ray-cast in rooms made of wall segments; every random generator is
seeded. The Intel-lab test reads ../shared/data/intel_lab and skips when it is absent.
"""

from __future__ import annotations

import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from laser_worlds import HALL, ROOM, loop_messages, render_scan, without_odometry

from experiments.metrics import ate, relation_errors
from hardware.calibration import WalkerCalibration
from hardware.geometry import between, compose, transform_points
from hardware.messages import LaserScan, VelocityOdometry
from slam.base import create
from slam.gtsam_smoother import GtsamConfig
from slam.scan_matching import (
    REJECTIONS,
    Acceptance,
    MatchResult,
    Reference,
    ScanMatchConfig,
    correlative_search,
    depth_points,
    icp,
    laser_points,
    match,
    place,
    voxel_downsample,
)

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
INTEL = DATA / "intel_lab" / "intel.gfs.log.gz"
INTEL_RELATIONS = DATA / "intel_lab" / "intel.relations"


def _err(a, b) -> tuple[float, float]:
    e = between(np.asarray(a, float), np.asarray(b, float))
    return float(math.hypot(e[0], e[1])), float(abs(e[2]))


CFG = ScanMatchConfig()
# the loop gate's thresholds (slam.scan_graph.LoopClosures.gate)
GATE = Acceptance(min_inlier_fraction=0.5, max_conflict_fraction=0.1, max_ambiguity=0.9)

# ---------------------------------------------------------------------------------------
# the matcher


def test_voxel_downsample_keeps_one_centroid_per_cell():
    pts = np.array([[0.01, 0.01], [0.03, 0.04], [0.26, 0.0], [0.27, 0.02]])
    out = voxel_downsample(pts, 0.05)
    assert len(out) == 2
    assert sorted(map(tuple, np.round(out, 3))) == [(0.02, 0.025), (0.265, 0.01)]


@pytest.mark.parametrize("noise_m", [0.0, 0.01])
def test_icp_recovers_a_known_rigid_transform(noise_m):
    rng = np.random.default_rng(1)
    a, b = np.array([2.0, 2.0, 0.3]), np.array([2.6, 2.3, 0.45])
    ref = Reference(laser_points(render_scan(ROOM, a, noise_m=noise_m, rng=rng)), CFG)
    query = laser_points(render_scan(ROOM, b, noise_m=noise_m, rng=rng), voxel_m=CFG.voxel_m)
    true = between(a, b)
    guess = compose(true, np.array([0.12, -0.08, math.radians(4.0)]))
    res = icp(ref, query, guess, CFG)
    trans, rot = _err(true, res.pose)
    tol = 0.01 if noise_m == 0 else 0.03
    assert res.converged
    assert trans < tol and rot < math.radians(0.5)
    assert res.inlier_fraction > 0.8
    assert np.all(np.linalg.eigvalsh(res.covariance) > 0)


def test_match_finds_a_far_start_with_partial_overlap_and_noise():
    rng = np.random.default_rng(2)
    a, b = np.array([2.0, 1.5, 0.2]), np.array([5.0, 4.0, 1.4])  # 3.9 m, 69° apart
    fov = math.radians(180.0)
    ref = Reference(laser_points(render_scan(ROOM, a, fov=fov, noise_m=0.01, rng=rng)), CFG)
    q_scan = render_scan(ROOM, b, fov=fov, noise_m=0.01, rng=rng)
    query = laser_points(q_scan, voxel_m=CFG.voxel_m)
    true = between(a, b)
    guess = compose(true, np.array([-0.8, 0.7, math.radians(-25.0)]))
    # ICP alone from that far falls into a wrong minimum; the correlative search does not
    assert _err(true, icp(ref, query, guess, CFG).pose)[0] > 0.5
    res = match(ref, query, guess, window_xy=1.2, window_theta=0.55, config=CFG)
    trans, rot = _err(true, res.pose)
    assert trans < 0.02 and rot < math.radians(0.5)
    assert GATE.accepts(res)


def test_a_wide_window_is_searched_on_two_levels_to_the_same_optimum():
    """A 2.5 m × full-turn window (25 coarse steps either way: above multires_offsets)
    goes through the block bound; its best pose is the exhaustive search's, and the
    match from it is the truth."""
    rng = np.random.default_rng(4)
    a, b = np.array([2.0, 2.0, 0.0]), np.array([3.8, 3.4, 1.1])  # 2.3 m, 63° apart
    ref = Reference(laser_points(render_scan(ROOM, a, noise_m=0.01, rng=rng)), CFG)
    query = laser_points(render_scan(ROOM, b, noise_m=0.01, rng=rng), voxel_m=CFG.voxel_m)
    wide = (2.5, math.pi)
    two_levels = correlative_search(ref, query, np.zeros(3), *wide, CFG, count=1)
    one_level = correlative_search(
        ref, query, np.zeros(3), *wide, replace(CFG, multires_offsets=100), count=1
    )
    np.testing.assert_allclose(two_levels[0][0], one_level[0][0])
    assert two_levels[0][1] == pytest.approx(one_level[0][1])
    res = match(ref, query, np.zeros(3), *wide, CFG)
    trans, rot = _err(between(a, b), res.pose)
    assert trans < 0.02 and rot < math.radians(0.5)


def test_unrelated_scans_are_rejected():
    rng = np.random.default_rng(3)
    ref = Reference(laser_points(render_scan(ROOM, (4.0, 4.5, 0.0), noise_m=0.01, rng=rng)), CFG)
    query = laser_points(render_scan(HALL, (6.0, 1.5, 0.4), noise_m=0.01, rng=rng), voxel_m=0.05)
    res = match(ref, query, np.zeros(3), window_xy=1.0, window_theta=0.4, config=CFG)
    assert not GATE.accepts(res)
    # ... while the same thresholds accept the right place
    good = laser_points(render_scan(ROOM, (4.3, 4.2, 0.2), noise_m=0.01, rng=rng), voxel_m=0.05)
    ok = match(ref, good, np.array([0.1, -0.1, 0.1]), 1.0, 0.4, CFG)
    assert GATE.accepts(ok)
    assert GATE.failures(ok) == ()


def test_a_rejected_match_names_every_test_it_fails():
    res = MatchResult(
        pose=np.zeros(3), covariance=np.eye(3), inlier_fraction=0.2, inliers=20, points=100,
        rmse_m=0.05, iterations=10, converged=True, conflict_fraction=0.3, constraint=0.5,
        ambiguity=0.95,
    )  # fmt: skip
    gate = Acceptance(min_inlier_fraction=0.3, max_conflict_fraction=0.2, max_ambiguity=0.9)
    assert gate.failures(res) == ("inliers", "conflict", "ambiguity")
    assert not gate.accepts(res)
    assert Acceptance(0.1, 0.5, 1.0).failures(res) == () and Acceptance(0.1, 0.5, 1.0).accepts(res)
    # a NaN fails its test, as does a covariance that is not finite or an ICP that stopped
    odd = replace(
        res, inlier_fraction=math.nan, converged=False, covariance=np.full((3, 3), np.inf)
    )
    assert Acceptance(0.1, 0.5, 1.0).failures(odd) == ("unconverged", "inliers", "covariance")
    assert set(gate.failures(odd)) <= set(REJECTIONS)


def test_a_corridor_is_degenerate_along_its_axis():
    corridor = np.array([(0.0, 0.0, 40.0, 0.0), (0.0, 2.0, 40.0, 2.0)])
    rng = np.random.default_rng(4)
    a, b = (15.0, 1.0, 0.0), (15.5, 1.1, 0.05)
    ref = Reference(
        laser_points(render_scan(corridor, a, noise_m=0.01, rng=rng), max_range_m=10), CFG
    )
    query = laser_points(render_scan(corridor, b, noise_m=0.01, rng=rng), max_range_m=10)
    res = icp(ref, query, between(np.array(a), np.array(b)), CFG)
    assert res.constraint < CFG.degenerate_constraint
    assert abs(res.weak_axis[0]) > 0.99  # along the corridor
    assert math.sqrt(res.covariance[0, 0]) > 0.5  # position along it: not measured
    assert math.sqrt(res.covariance[1, 1]) < 0.05  # across it: measured


def test_depth_frames_flatten_to_points_that_match():
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "mapping"))
    from synthetic_depth import FLOOR, Box, depth_frame

    cal = WalkerCalibration()
    scene = [
        FLOOR,
        Box((2.6, -2.0, 0.0), (3.0, 2.0, 1.5)),  # a wall ahead
        Box((1.6, 0.3, 0.0), (2.0, 0.7, 1.0)),  # a box in front of it
        Box((1.2, -1.3, 0.0), (2.6, -1.0, 1.0)),  # a side wall
    ]
    a, b = (0.0, 0.0, 0.0), (0.15, -0.05, 0.06)
    fa = depth_frame(cal.depth_intrinsics, cal.depth_mount, scene, a)
    fb = depth_frame(cal.depth_intrinsics, cal.depth_mount, scene, b)
    sa = depth_points(fa, cal, voxel_m=0.05)
    # the wall's face at x = 2.6 (walker frame, pose a is the origin)
    assert np.any(np.abs(sa.points[:, 0] - 2.6) < 0.05)
    assert np.all(sa.points[:, 0] > 1.1)
    res = match(Reference(sa, CFG), depth_points(fb, cal, voxel_m=0.05), np.zeros(3), 0.3, 0.15)
    trans, rot = _err(between(np.array(a), np.array(b)), res.pose)
    assert trans < 0.04 and rot < math.radians(1.0)


def _walker_match_errors(trial_path: Path, cfg: ScanMatchConfig, pairs: int) -> np.ndarray:
    """Sequential matches of a simulated trial's depth frames, as gtsam keeps them (every
    0.3 m or 0.2 rad of true motion; each against the three kept before it, placed at their
    true poses), searched ± 0.1 m, 0.05 rad around the true relative pose: each converged
    match's (translation, heading) error against it."""
    from hardware.log import read_log
    from hardware.messages import DepthFrame, GroundTruthPose

    trial = read_log(trial_path)
    truth_t, truth, frames = [], [], []
    for m in trial.messages():
        if isinstance(m, GroundTruthPose):
            truth_t.append(m.t)
            truth.append((m.x, m.y, m.theta))
        elif isinstance(m, DepthFrame):
            frames.append(m)
    truth_t, truth = np.array(truth_t), np.array(truth)
    kept: list[tuple[DepthFrame, np.ndarray]] = []
    for f in frames:
        pose = truth[min(np.searchsorted(truth_t, f.t), len(truth) - 1)]
        if not kept or (
            math.hypot(*(pose[:2] - kept[-1][1][:2])) > 0.3 or abs(pose[2] - kept[-1][1][2]) > 0.2
        ):
            kept.append((f, pose))
    errors = []
    for k in range(3, len(kept), 2):
        prev = kept[k - 3 : k]
        scans = [depth_points(f, trial.calibration, voxel_m=cfg.voxel_m) for f, _ in prev]
        ref = Reference(place(np.array([p for _, p in prev]), scans, prev[-1][1]), cfg)
        query = depth_points(kept[k][0], trial.calibration, voxel_m=cfg.voxel_m)
        rel = between(prev[-1][1], kept[k][1])
        res = match(ref, query, rel, 0.1, 0.05, cfg)
        if res.converged:
            errors.append(_err(rel, res.pose))
        if len(errors) == pairs:
            break
    return np.array(errors)


def test_depth_frames_match_better_with_their_own_settings(course_trial):
    """gtsam matches depth frames with `depth_match` (points every 2 cm, paired within
    5 cm), laser scans with `scan_match` (5 cm, 30 cm). With the laser's pairing, points
    of surfaces that only the new frame sees are paired with the nearest other surface
    and pull the match: on the simulated course its error against the truth is about
    twice as large in translation and 2.5 times in heading."""
    gtsam = GtsamConfig()
    laser = _walker_match_errors(course_trial, gtsam.scan_match, pairs=60)
    depth = _walker_match_errors(course_trial, gtsam.depth_match, pairs=60)
    assert len(laser) == len(depth) == 60
    rms = lambda e: np.sqrt(np.mean(e**2, axis=0))  # noqa: E731
    (laser_m, laser_rad), (depth_m, depth_rad) = rms(laser), rms(depth)
    assert depth_m < 0.7 * laser_m and depth_rad < 0.5 * laser_rad
    assert np.median(depth[:, 0]) < 0.04 and depth_rad < math.radians(1.5)


# ---------------------------------------------------------------------------------------
# scan-matching factors in the smoother


def _run(msgs, cfg: GtsamConfig, start):
    loc = create("gtsam", WalkerCalibration(), cfg, initial_pose=start)
    for m in msgs:
        loc.process(m)
    return loc


def test_loop_closures_remove_most_of_the_drift_of_biased_odometry():
    msgs, truth = loop_messages()
    start = tuple(truth.poses[0])
    plain = _run(msgs, GtsamConfig(), start)
    scans = _run(msgs, GtsamConfig(scan_matching=True), start)
    d = scans.diagnostics()
    assert d["scan_factors"] > 0.9 * d["scans_kept"] - 1
    assert d["loop_closures"] >= 5
    final_plain = _err(plain.trajectory().poses[-1], truth.poses[-1])[0]
    final_scan = _err(scans.trajectory().poses[-1], truth.poses[-1])[0]
    assert final_plain > 1.0  # the biased odometry drifts
    assert final_scan < final_plain / 10
    assert ate(scans.trajectory(), truth)["ate_rmse_unaligned_m"] < 0.1


def test_a_turn_the_odometry_missed_is_found_by_a_full_turn_search():
    """The odometry stops during the first corner's 90° turn (a gap: velocity odometry
    of NaN until it resumes, as the CARMEN importer emits it): dead reckoning stands
    still there and is 90° off ever after; the smoother gives that motion a full turn's
    uncertainty, searches a full turn for the next scan's match and finds it."""
    msgs, truth = loop_messages(laps=1)
    odo = [k for k, m in enumerate(msgs) if isinstance(m, VelocityOdometry)]
    turn = [k for k in odo if msgs[k].omega != 0.0 and msgs[k].v == 0.0][:20]  # corner 1
    first = turn[0]
    msgs[first] = VelocityOdometry(msgs[first].t, math.nan, math.nan)
    missed = set(turn[1:])
    msgs = [m for k, m in enumerate(msgs) if k not in missed]
    start = tuple(truth.poses[0])
    dr = create("dead-reckoning", WalkerCalibration(), initial_pose=start)
    for m in msgs:
        dr.process(m)
    sm = _run(msgs, GtsamConfig(scan_matching=True), start)
    assert sm.diagnostics()["odometry_gaps"] == 1
    assert ate(dr.trajectory(), truth)["ate_rmse_unaligned_m"] > 1.0
    assert ate(sm.trajectory(), truth)["ate_rmse_unaligned_m"] < 0.1


def test_a_log_without_odometry_is_localized_by_its_scans_alone():
    """Orebro's laser log has no odometry: one message of unknown motion before each
    scan, at the scan's time. Every scan then needs a keyframe of its own, though the
    odometry moved nothing (until 2026-12-05 it shared the last one's: 5.4 m off), and
    the trajectory at a scan's time is the pose its match found, not the pose before it
    (a keyframe made at an odometry message's time replaces that message's pose)."""
    msgs, truth = loop_messages(laps=1)
    scans = [m for m in msgs if isinstance(m, LaserScan)]
    blind = without_odometry(msgs)
    sm = _run(blind, GtsamConfig(scan_matching=True), tuple(truth.poses[0]))
    d = sm.diagnostics()
    assert d["odometry_gaps"] == len(scans) - 1 and d["scan_factors"] == len(scans) - 1
    t = np.array([s.t for s in scans])
    err = np.hypot(*(sm.trajectory().interpolate(t)[:, :2] - truth.interpolate(t)[:, :2]).T)
    assert np.sqrt(np.mean(err**2)) < 0.02 and err.max() < 0.05


def test_the_path_between_keyframes_joins_both():
    """Each odometry message's pose is its keyframe's estimate and the odometry since,
    with the next keyframe's correction spread back over the stretch in proportion to
    the odometry variance accumulated (slam.trajectory.spread_corrections): from one
    message to the next the path moves as the truth does, to within a few millimetres of
    the odometry's own error, where reading the keyframe before without the correction
    jumped up to 16 mm at every keyframe."""
    msgs, truth = loop_messages()
    sm = _run(msgs, GtsamConfig(scan_matching=True), tuple(truth.poses[0]))
    tr = sm.trajectory()
    moved = np.diff(tr.poses[:, :2], axis=0) - np.diff(truth.interpolate(tr.t)[:, :2], axis=0)
    assert len(tr.t) > 1000
    assert np.hypot(*moved.T).max() < 0.005


def test_scans_are_ignored_unless_scan_matching_is_on():
    msgs, _ = loop_messages(laps=1)
    msgs = msgs[:200]
    plain = _run(msgs, GtsamConfig(), (1.5, 1.5, 0.0))
    assert "scans_kept" not in plain.diagnostics()
    odo_only = _run(
        [m for m in msgs if not isinstance(m, LaserScan)], GtsamConfig(), (1.5, 1.5, 0.0)
    )
    assert np.allclose(plain.trajectory().poses, odo_only.trajectory().poses)


@pytest.mark.data
@pytest.mark.skipif(not INTEL.exists(), reason=f"Intel lab log not found at {INTEL}")
def test_intel_lab_subset_relations_clearly_beat_dead_reckoning():
    from hardware.datasets import open_dataset

    ds = open_dataset("carmen", INTEL, relations=INTEL_RELATIONS)
    # the first 500 s (150 scans): the robot leaves its start room, goes round the
    # corridors and comes back; dead reckoning is metres off by then
    msgs = [m for m in ds.messages() if m.t <= 500.0]
    start = ds.metadata["config"]["initial_pose"]
    rel = np.array(ds.metadata["relations"]["rows"])
    dr = create("dead-reckoning", ds.calibration, initial_pose=start)
    for m in msgs:
        dr.process(m)
    sm = _run(msgs, GtsamConfig(scan_matching=True), start)
    e_dr = relation_errors(dr.trajectory(), rel)
    e_sm = relation_errors(sm.trajectory(), rel)
    assert e_sm["relations_used"] > 400
    # measured: 0.046 m and 0.83° against dead reckoning's 2.7 m and 27°
    assert e_sm["relations_trans_mean_m"] < 0.07
    assert e_sm["relations_trans_mean_m"] < 0.05 * e_dr["relations_trans_mean_m"]
    assert e_sm["relations_rot_mean_deg"] < 0.1 * e_dr["relations_rot_mean_deg"]
    assert sm.diagnostics()["loop_closures"] > 20


def test_compiled_grid_scores_equal_numpys_gather_and_mean():
    """The correlative search's scores (slam.scan_kernels.grid_scores) equal numpy's
    one gather and mean over the points to the bit, lookups off the field clipped."""
    from slam.scan_kernels import grid_scores

    rng = np.random.default_rng(21)
    for _ in range(60):
        h, w = (int(v) for v in rng.integers(5, 200, 2))
        flat = rng.random(h * w) - 1.0 * (rng.random(h * w) < 0.05)
        n = int(rng.integers(1, 300))
        cells = np.column_stack([rng.integers(-20, w + 20, n), rng.integers(-20, h + 20, n)])
        k = int(rng.integers(1, 30))
        x_offs = np.arange(-k, k + 1) * int(rng.integers(1, 4))
        y_offs = np.arange(-k, k + 2)
        cols = np.clip(cells[:, 0, None] + x_offs[None, :], 0, w - 1)
        rows = np.clip(cells[:, 1, None] + y_offs[None, :], 0, h - 1)
        expected = flat[rows[:, :, None] * w + cols[:, None, :]].mean(axis=0)
        got = grid_scores(flat, h, w, cells.astype(np.int64), x_offs, y_offs)
        assert got.shape == (len(y_offs), len(x_offs))
        np.testing.assert_array_equal(got, expected)


def test_bucketed_nearest_neighbour_is_the_k_d_trees_within_the_gate():
    """ICP's compiled nearest neighbour (slam.scan_kernels: the reference points sorted
    into cells as wide as the gate) finds the k-d tree's nearest point, and none beyond
    the gate, including for queries off the points' extent."""
    from scipy.spatial import cKDTree

    from slam.scan_kernels import buckets, nearest

    rng = np.random.default_rng(5)
    for _ in range(20):
        pts = rng.uniform(-5, 5, (int(rng.integers(1, 400)), 2))
        gate = float(rng.uniform(0.05, 1.0))
        order, starts, grid = buckets(pts, gate)
        q = rng.uniform(-7, 7, (300, 2))
        d, idx = cKDTree(pts).query(q, distance_upper_bound=gate)
        got = np.array([nearest(pts, order, starts, grid, x, y, gate * gate) for x, y in q])
        np.testing.assert_array_equal(got, np.where(np.isfinite(d), idx, -1))
    # a gate small against the extent: wider cells, the same answers
    pts = rng.uniform(-500, 500, (2000, 2))
    order, starts, grid = buckets(pts, 0.01)
    assert grid[2] > 0.9 and grid[3] * grid[4] < 1100**2
    q = pts[:50] + rng.normal(0, 0.004, (50, 2))
    d, idx = cKDTree(pts).query(q, distance_upper_bound=0.01)
    got = [nearest(pts, order, starts, grid, x, y, 1e-4) for x, y in q]
    np.testing.assert_array_equal(got, np.where(np.isfinite(d), idx, -1))


def _numpy_icp(ref: Reference, query: np.ndarray, x: np.ndarray, cfg: ScanMatchConfig):
    """ICP written plainly on arrays (the k-d tree, stacked rows, np.linalg.solve): the
    oracle of the compiled loop."""
    x = np.array(x, dtype=float)
    for it in range(1, cfg.icp_iterations + 1):
        q = transform_points(x, query)
        d, idx = ref.tree.query(q, distance_upper_bound=cfg.max_correspondence_m)
        ok = np.isfinite(d)
        if ok.sum() < cfg.min_points:
            return x, it, False
        q, p = q[ok], ref.points[idx[ok]]
        line = ref.has_normal[idx[ok]]
        dq = np.column_stack([-(q[:, 1] - x[1]), q[:, 0] - x[0]])
        n = ref.normals[idx[ok]][line]
        rows = [np.column_stack([n, (n * dq[line]).sum(1)])]
        res = [(n * (q[line] - p[line])).sum(1)]
        for axis in range(2):
            j = np.zeros((int((~line).sum()), 3))
            j[:, axis], j[:, 2] = 1.0, dq[~line, axis]
            rows.append(j)
            res.append(q[~line, axis] - p[~line, axis])
        jac, r = np.vstack(rows), np.concatenate(res)
        w = np.where(np.abs(r) <= cfg.huber_m, 1.0, cfg.huber_m / np.abs(r))
        step = -np.linalg.solve(jac.T @ (jac * w[:, None]) + 1e-9 * np.eye(3), jac.T @ (w * r))
        x = x + step
        x[2] = math.remainder(x[2], 2 * math.pi)
        if math.hypot(*step[:2]) < cfg.icp_tolerance[0] and abs(step[2]) < cfg.icp_tolerance[1]:
            return x, it, True
    return x, cfg.icp_iterations, False


def test_compiled_icp_equals_plain_numpy_gauss_newton():
    """slam.scan_kernels.icp_steps (one compiled loop per ICP) takes the same steps as
    the plainly written oracle above: the same iterations and convergence, and where it
    converges the pose within round-off, over a room and a hall from starts ~0.3 m /
    0.15 rad off."""
    rng = np.random.default_rng(11)
    checked = 0
    for world, (x1, y1) in ((ROOM, (9.0, 2.5)), (HALL, (13.0, 2.0))):
        for _ in range(12):
            a = np.array([rng.uniform(1.0, x1), rng.uniform(1.0, y1), rng.uniform(-3, 3)])
            b = compose(a, np.array([*rng.normal(0, 0.2, 2), rng.normal(0, 0.1)]))
            ref = Reference(laser_points(render_scan(world, a, noise_m=0.01, rng=rng)), CFG)
            query = laser_points(render_scan(world, b, noise_m=0.01, rng=rng))
            guess = between(a, b) + np.array([*rng.normal(0, 0.1, 2), rng.normal(0, 0.05)])
            got = icp(ref, query, guess, CFG)
            want, iterations, converged = _numpy_icp(ref, query.points, guess, CFG)
            assert (got.iterations, got.converged) == (iterations, converged)
            if converged:  # (a run cut short with a few points is ill-conditioned)
                np.testing.assert_allclose(got.pose, want, atol=1e-9)
                checked += 1
    assert checked >= 16
