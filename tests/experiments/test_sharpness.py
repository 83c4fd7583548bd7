"""A laser map's sharpness at a trajectory (experiments.sharpness): the spread across
walls of every scan's hits placed at its pose, a measure that needs no ground truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from experiments.sharpness import (
    SharpnessConfig,
    local_spread,
    place_hits,
    scan_clouds,
    scan_sharpness,
    sharpness,
    trajectory_sharpness,
)
from hardware.geometry import transform_points
from slam.trajectory import Trajectory

ROOM = (-3.0, 5.0, -2.0, 4.0)  # x0, x1, y0, y1 of a rectangular room [m]


def _wall(rng, n=4000, sigma=0.01, offset=0.0):
    """Points along y = offset, x in [0, 10], with Gaussian spread σ across the wall."""
    x = rng.uniform(0.0, 10.0, n)
    return np.column_stack([x, offset + sigma * rng.standard_normal(n)])


def _room_hits(pose, rng, beams=360, noise_m=0.01):
    """A full-turn laser's hits on the room's walls from pose, in the walker frame."""
    x, y, th = pose
    x0, x1, y0, y1 = ROOM
    a = th + np.linspace(-math.pi, math.pi, beams, endpoint=False)
    dx, dy = np.cos(a), np.sin(a)
    with np.errstate(divide="ignore"):
        tx = np.where(dx > 0, (x1 - x) / dx, (x0 - x) / dx)
        ty = np.where(dy > 0, (y1 - y) / dy, (y0 - y) / dy)
    r = np.minimum(np.abs(tx), np.abs(ty)) + noise_m * rng.standard_normal(beams)
    b = a - th
    return np.column_stack([r * np.cos(b), r * np.sin(b)])


def _lap(n=60):
    """Poses around the room's middle: an ellipse, heading along it."""
    s = np.linspace(0.0, 2 * math.pi, n, endpoint=False)
    return np.column_stack([1.0 + 2.0 * np.cos(s), 1.0 + 1.5 * np.sin(s), s + math.pi / 2])


def test_a_wall_is_as_thick_as_its_noise_wherever_it_lies():
    rng = np.random.default_rng(0)
    wall = _wall(rng, sigma=0.01)
    s = sharpness(wall)
    assert s["evaluated"] == len(wall)
    assert s["wall_spread_median_m"] == pytest.approx(0.01, rel=0.1)
    # the same wall turned and moved: the same numbers (the grid's cells do not matter)
    moved = sharpness(transform_points(np.array([3.7, -12.2, 0.8]), wall))
    for key in ("wall_spread_median_m", "wall_spread_rms_m", "map_entropy"):
        assert moved[key] == pytest.approx(s[key], rel=0.02)


def test_a_wall_seen_twice_a_decimetre_apart_spreads_by_half_of_it():
    rng = np.random.default_rng(1)
    doubled = np.concatenate([_wall(rng, sigma=0.0), _wall(rng, sigma=0.0, offset=0.1)])
    s = sharpness(doubled)
    assert s["wall_spread_median_m"] == pytest.approx(0.05, rel=0.05)
    assert s["map_entropy"] > sharpness(_wall(rng, sigma=0.01))["map_entropy"]


def test_scans_at_the_true_poses_are_sharper_than_at_perturbed_ones():
    rng = np.random.default_rng(2)
    truth = _lap()
    hits = [_room_hits(p, rng) for p in truth]
    at_truth = trajectory_sharpness(hits, truth)
    assert at_truth["wall_spread_median_m"] == pytest.approx(0.01, abs=0.003)
    previous = at_truth
    for sigma in (0.02, 0.05):
        noisy = truth + rng.normal(0.0, [sigma, sigma, sigma / 4], truth.shape)
        s = trajectory_sharpness(hits, noisy)
        assert s["wall_spread_median_m"] > previous["wall_spread_median_m"] + 0.005
        assert s["map_entropy"] > previous["map_entropy"]
        previous = s
    # the whole trajectory moved rigidly: the same map, moved
    frame = np.array([10.0, -4.0, 1.1])
    moved = np.column_stack([transform_points(frame, truth[:, :2]), truth[:, 2] + frame[2]])
    assert trajectory_sharpness(hits, moved)["wall_spread_median_m"] == pytest.approx(
        at_truth["wall_spread_median_m"], rel=0.02
    )


def test_a_replay_is_compared_with_its_reference_over_the_scans_both_have():
    rng = np.random.default_rng(3)
    truth = _lap()
    t = np.arange(len(truth), dtype=float)
    hits = [_room_hits(p, rng) for p in truth]
    shifted = truth.copy()
    shifted[::2, 1] += 0.08  # every other scan 8 cm off: doubled walls
    est = Trajectory(t, shifted)
    partial = truth.copy()
    partial[:10] = math.nan  # no reference pose for the first ten scans
    clouds = scan_clouds(t, hits, est, partial)
    assert clouds.scans == len(truth) - 10
    assert clouds.reference is not None
    assert len(clouds.estimated) == len(clouds.reference) == 360 * (len(truth) - 10)
    out = scan_sharpness(clouds).metrics()
    assert out["radius_m"] == [0.25, 0.5]
    for ours, theirs in zip(out["estimated"], out["reference"], strict=True):
        assert ours["wall_spread_median_m"] > theirs["wall_spread_median_m"] + 0.02
    alone = scan_sharpness(scan_clouds(t, hits, est, None)).metrics()
    assert "reference" not in alone and alone["scans"] == len(truth)


def test_the_local_spread_shows_where_a_wall_is_doubled():
    rng = np.random.default_rng(4)
    single = _wall(rng, sigma=0.005)
    doubled = _wall(rng, sigma=0.005, offset=0.2) + np.array([20.0, 0.0])
    doubled = np.concatenate([doubled, _wall(rng, sigma=0.005) + np.array([20.0, 0.0])])
    local = local_spread(np.concatenate([single, doubled]), SharpnessConfig(radius_m=0.5))
    far = local.xy[:, 0] > 21.0  # well inside the doubled stretch
    near = local.xy[:, 0] < 9.0
    assert np.median(local.spread_m[near]) < 0.01 < 0.09 < np.median(local.spread_m[far])


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="one pose"):
        place_hits([np.zeros((3, 2))], np.zeros((2, 3)))
    with pytest.raises(ValueError, match="radius_m"):
        SharpnessConfig(radius_m=0.0)
    # nothing to evaluate: NaN, not an error
    s = sharpness(np.array([[0.0, 0.0], [5.0, 5.0]]))
    assert s["evaluated"] == 0 and math.isnan(s["wall_spread_median_m"])


def test_a_laser_log_replay_reports_its_map_sharpness_at_both_sets_of_poses(tmp_path):
    """Through a real CARMEN file: every scan's every hit at the localizer's poses and at
    the log's corrected ones."""
    from experiments.run import replay_log
    from hardware.datasets import open_dataset
    from hardware.messages import LaserScan
    from mapping.scan_points import scan_hits
    from tests.hardware.datasets.datasets_testdata import write_carmen

    path = write_carmen(tmp_path / "s.log", scans=6, beams=180)
    res = replay_log(
        open_dataset("carmen", path), tmp_path / "out", localizer="dead-reckoning",
        drag_metrics=False,
    )  # fmt: skip
    m = res.metrics
    sharp = m["map_sharpness"]
    assert sharp["scans"] == m["messages"]["LaserScan"] == 6
    # the log's longest reading is its range_max, a no-return by the importer's rule
    hits = sum(int(scan_hits(s).sum()) for s in open_dataset("carmen", path).messages([LaserScan]))
    assert hits == 6 * 180 - 1
    for ours, theirs in zip(sharp["estimated"], sharp["reference"], strict=True):
        assert ours["points"] == theirs["points"] == hits
    assert m["wall_spread_m"] == sharp["estimated"][0]["wall_spread_median_m"] > 0
    assert m["reference_wall_spread_coarse_m"] == sharp["reference"][1]["wall_spread_median_m"]
    # and the figure of where the walls spread, at both sets of poses
    assert res.files["sharpness_png"].stat().st_size > 10_000
