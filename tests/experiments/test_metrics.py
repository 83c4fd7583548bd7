import math

import numpy as np
import pytest

from experiments.metrics import (
    align_se2,
    ate,
    braking_impulse,
    distance_to_outlines,
    gps_errors,
    heading_errors,
    map_scores,
    rpe,
    screen_gps,
)
from hardware.geometry import compose
from hardware.messages import BrakeCommand
from slam.trajectory import Trajectory


def gt_traj():
    t = np.linspace(0, 20, 401)
    return Trajectory(t, np.column_stack([np.cos(t / 3) * 3, np.sin(t / 2) * 2, np.sin(t / 5)]))


def test_ate_is_zero_for_a_rigidly_moved_copy():
    gt = gt_traj()
    moved = Trajectory(gt.t, compose(np.array([1.0, -2.0, 0.7]), gt.poses))
    m = ate(moved, gt)
    assert m["ate_rmse_m"] == pytest.approx(0.0, abs=1e-9)
    assert m["ate_rmse_unaligned_m"] > 1.0


def test_ate_of_known_offset_noise():
    gt = gt_traj()
    noisy = gt.poses.copy()
    noisy[::2, 0] += 0.1
    noisy[1::2, 0] -= 0.1
    m = ate(Trajectory(gt.t, noisy), gt)
    assert m["ate_rmse_m"] == pytest.approx(0.1, rel=0.01)


def test_alignment_recovers_rotation():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 2))
    th = 0.4
    r = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    r_est, t_est = align_se2(src, src @ r.T + [1, 2])
    assert np.allclose(r_est, r) and np.allclose(t_est, [1, 2])


def test_heading_errors_wrap_and_grow_with_a_known_drift():
    """A heading that drifts by 0.01 rad/s from a true one that wraps past ±π."""
    t = np.linspace(0, 20, 401)
    true = np.remainder(3.0 + 0.2 * t + np.pi, 2 * np.pi) - np.pi
    gt = Trajectory(t, np.column_stack([t, 0 * t, true]))
    est = Trajectory(
        t, np.column_stack([t, 0 * t, np.remainder(true - 0.01 * t + np.pi, 2 * np.pi) - np.pi])
    )
    m = heading_errors(est, gt)
    assert m["final_heading_error_deg"] == pytest.approx(np.degrees(0.2), abs=1e-9)
    assert m["heading_error_max_deg"] == pytest.approx(np.degrees(0.2), abs=1e-9)
    assert m["heading_error_median_deg"] == pytest.approx(np.degrees(0.1), abs=1e-9)


def test_rpe_zero_for_rigid_copy_and_positive_for_drift():
    gt = gt_traj()
    moved = Trajectory(gt.t, compose(np.array([1.0, -2.0, 0.7]), gt.poses))
    assert rpe(moved, gt)["rpe_trans_m"] == pytest.approx(0.0, abs=1e-9)
    drift = gt.poses.copy()
    drift[:, 0] += 0.05 * gt.t  # 5 cm/s
    assert rpe(Trajectory(gt.t, drift), gt)["rpe_trans_m"] == pytest.approx(0.05, rel=0.05)


def test_distances_to_square():
    sq = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    d = distance_to_outlines(np.array([[0.5, 0.5], [2.0, 0.5], [-0.3, -0.4]]), [sq])
    assert d == pytest.approx([0.0, 1.0, 0.5])
    s = map_scores(np.array([[0.5, 0.5], [1.05, 0.5], [3.0, 3.0]]), 0.0025, [sq])
    assert s["map_precision"] == pytest.approx(2 / 3)
    assert s["phantom_area_m2"] == pytest.approx(0.0025)


def test_braking_impulse_above_residual():
    cmds = [
        BrakeCommand(0.0, 0.068, 0.068),
        BrakeCommand(1.0, 2.068, 0.068),
        BrakeCommand(3.0, 0.068, 0.068),
    ]
    assert braking_impulse(cmds, 0.068, 10.0) == pytest.approx(4.0)


def test_landmark_rmse():
    from experiments.metrics import landmark_rmse

    truth = {1: np.array([0.0, 0.0]), 2: np.array([1.0, 1.0]), 3: np.array([5.0, 5.0])}
    est = {1: np.array([0.3, 0.4]), 2: np.array([1.0, 1.0]), 9: np.array([0.0, 0.0])}
    assert landmark_rmse(est, truth) == pytest.approx(np.sqrt(0.25 / 2))
    assert np.isnan(landmark_rmse({}, truth))
    # rotated by 90° about the origin and aligned back
    rot = np.array([[0.0, -1.0], [1.0, 0.0]])
    turned = {i: rot @ p for i, p in truth.items()}
    assert landmark_rmse(turned, truth, (rot.T, np.zeros(2))) == pytest.approx(0.0)


def test_relation_errors_zero_for_exact_and_known_for_scaled():
    from experiments.metrics import relation_errors
    from hardware.geometry import between

    gt = gt_traj()
    i, j = np.arange(0, 380, 7), np.arange(20, 400, 7)
    rel = np.column_stack([gt.t[i], gt.t[j], between(gt.poses[i], gt.poses[j])])
    out = relation_errors(gt, rel)
    assert out["relations_trans_mean_m"] == pytest.approx(0.0, abs=1e-9)
    assert out["relations_used"] == len(i)
    # an estimate that walks 10 % too far: each relation's translation error is 10 % of it
    scaled = Trajectory(gt.t, np.column_stack([gt.poses[:, :2] * 1.1, gt.poses[:, 2]]))
    out = relation_errors(scaled, rel)
    expected = 0.1 * np.hypot(*(gt.poses[j, :2] - gt.poses[i, :2]).T).mean()
    assert out["relations_trans_mean_m"] == pytest.approx(expected, rel=1e-6)
    assert out["relations_rot_mean_deg"] == pytest.approx(0.0, abs=1e-9)
    # the distribution of the same errors
    each = 0.1 * np.hypot(*(gt.poses[j, :2] - gt.poses[i, :2]).T)
    assert out["relations_trans_median_m"] == pytest.approx(np.median(each), rel=1e-6)
    assert out["relations_trans_p90_m"] == pytest.approx(np.percentile(each, 90), rel=1e-6)
    assert out["relations_trans_max_m"] == pytest.approx(each.max(), rel=1e-6)
    assert out["relations_rot_p99_deg"] == pytest.approx(0.0, abs=1e-9)
    # no relation inside the estimate's span: counted, and NaN rather than a number
    none = relation_errors(Trajectory(gt.t[:2], gt.poses[:2]), rel[5:])
    assert none["relations_used"] == 0 and math.isnan(none["relations_trans_median_m"])


def test_slip_errors_against_the_true_effective_k():
    from experiments.metrics import slip_errors

    cov = np.diag([0.01**2, 0.02**2])
    out = slip_errors(np.array([0.11, 0.05]), cov, {"k_effective": [0.1, None]})
    assert out["k"] == pytest.approx([0.11, 0.05]) and out["k_sigma"] == pytest.approx([0.01, 0.02])
    assert out["relative_error"][0] == pytest.approx(0.1) and out["relative_error"][1] is None
    assert "relative_error" not in slip_errors(np.zeros(2), cov, None)


def test_gps_errors_by_hand_with_a_jump_and_a_dropout():
    # the estimate drives along x at 1 m/s for 10 s; the GPS reads it 0.5 m to the left
    # (y + 0.5), at 5 fixes/s, but has nothing from 4 s to 6 s (a dropout) and one fix
    # 30 m off at t = 8 s (a jump: 150 m/s from the fix before)
    t = np.linspace(0.0, 10.0, 101)
    est = Trajectory(t, np.column_stack([t, np.zeros_like(t), np.zeros_like(t)]))
    tg = np.round(np.arange(0.0, 10.0 + 1e-9, 0.2), 6)
    tg = tg[(tg <= 4.0) | (tg >= 6.0)]
    rows = np.column_stack([tg, tg, np.full_like(tg, 0.5)])
    rows[tg == 8.0, 2] = 30.5
    m = gps_errors(est, rows)
    assert m["gps_jumps_left_out"] == 1 and m["gps_dropouts"] == 1
    assert m["gps_dropout_s"] == pytest.approx(2.0)
    assert m["gps_fixes_used"] == len(tg) - 1
    assert m["gps_rmse_unaligned_m"] == pytest.approx(0.5)  # every kept fix 0.5 m off
    assert m["gps_rmse_m"] == pytest.approx(0.0, abs=1e-9)  # a shift: aligned away
    assert m["gps_max_m"] == pytest.approx(0.0, abs=1e-9)
    # the fix after the jump is measured from the last kept one, so it stays
    screen = screen_gps(rows)
    assert screen.kept.tolist() == (tg != 8.0).tolist()
    # with the jump kept (a looser speed limit) the RMSE would carry it
    loose = gps_errors(est, rows, max_speed_mps=1000.0)
    assert loose["gps_jumps_left_out"] == 0 and loose["gps_rmse_unaligned_m"] > 4.0


def test_gps_errors_outside_the_estimate_are_not_used():
    t = np.linspace(0.0, 2.0, 21)
    est = Trajectory(t, np.column_stack([t, np.zeros_like(t), np.zeros_like(t)]))
    rows = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 1.0, 0.0], [5.0, 9.0, 9.0]])
    m = gps_errors(est, rows)
    assert m["gps_fixes_used"] == 2 and m["gps_rmse_unaligned_m"] == pytest.approx(0.0)
    assert math.isnan(gps_errors(est, rows[:1])["gps_rmse_m"])
