"""Lines and corners from a laser scan (mapping.scan_features) in a synthetic room with a
box, where the corners are known."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hardware.messages import LaserScan
from mapping.scan_features import FeatureConfig, corner_sightings, extract

# a room x ∈ [−2, 4], y ∈ [−3, 2.5] and a 0.4 m box, the laser at the origin facing +x
ROOM = [(-2.0, -3.0), (4.0, -3.0), (4.0, 2.5), (-2.0, 2.5)]
BOX = [(1.5, -0.9), (1.9, -0.9), (1.9, -0.5), (1.5, -0.5)]
# seen over 180°: the room's two far corners and the box's one corner whose both faces
# show; the box's other visible ends are occlusion edges, not corners
CORNERS = np.array([(4.0, 2.5), (4.0, -3.0), (1.5, -0.5)])


def _segments():
    for poly in (ROOM, BOX):
        for a, b in zip(poly, poly[1:] + poly[:1], strict=True):
            yield np.array(a), np.array(b)


def room_scan(pose=(0.0, 0.0, 0.0), noise_m=0.0, seed=0, beams=361) -> LaserScan:
    """A 180° scan by ray casting from pose (x, y, θ), Gaussian range noise."""
    x, y, th = pose
    angles = np.linspace(-math.pi / 2, math.pi / 2, beams)
    ranges = np.full(beams, np.inf)
    o = np.array([x, y])
    for k, a in enumerate(angles):
        d = np.array([math.cos(th + a), math.sin(th + a)])
        for p, q in _segments():
            e = q - p
            m = np.column_stack([d, -e])
            if abs(np.linalg.det(m)) < 1e-12:
                continue
            t, u = np.linalg.solve(m, p - o)
            if t > 0 and 0 <= u <= 1:
                ranges[k] = min(ranges[k], t)
    ranges += noise_m * np.random.default_rng(seed).standard_normal(beams)
    return LaserScan(0.0, -math.pi / 2, math.pi / (beams - 1), ranges.astype(np.float32), 30.0)


def _match(found: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Distance from each true corner to the nearest found one."""
    return np.array([np.min(np.hypot(*(found - c).T)) for c in true])


def test_the_room_corners_are_found_and_nothing_else():
    features = extract(room_scan())
    assert len(features.corners) == 3
    assert np.all(_match(features.corners, CORNERS) < 0.01)
    # lines: the top wall, the right wall in two (the box's shadow), the bottom wall
    # and the box's two faces, each as long as it shows
    lengths = sorted(round(line.length, 1) for line in features.lines)
    assert len(features.lines) == 6
    assert lengths[:2] == [0.4, 0.4] and lengths[-1] == pytest.approx(4.0, abs=0.1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_with_range_noise_the_corners_stay_within_centimetres(seed):
    features = extract(room_scan(noise_m=0.01, seed=seed))
    assert len(features.corners) == 3
    assert np.all(_match(features.corners, CORNERS) < 0.05)


def test_from_another_pose_the_corners_move_with_it():
    pose = (-0.5, 0.5, math.radians(-10.0))
    rb = corner_sightings(room_scan(pose), sensor_offset=(0.0, 0.0, 0.0))
    assert np.all(rb.landmark_ids == -1)
    a = pose[2] + rb.bearings_rad
    world = np.column_stack([pose[0] + rb.ranges_m * np.cos(a), pose[1] + rb.ranges_m * np.sin(a)])
    assert len(world) == 3 and np.all(_match(world, CORNERS) < 0.01)


def test_a_mounted_laser_gives_ranges_from_the_walker():
    # the laser 0.2 m ahead of the walker's reference point: a corner ahead is 0.2 m
    # farther from the walker than from the laser
    scan = room_scan()
    from_laser = corner_sightings(scan)
    from_walker = corner_sightings(scan, sensor_offset=(0.2, 0.0, 0.0))
    pts_l = np.column_stack(
        [from_laser.ranges_m * np.cos(from_laser.bearings_rad),
         from_laser.ranges_m * np.sin(from_laser.bearings_rad)]
    )  # fmt: skip
    pts_w = np.column_stack(
        [from_walker.ranges_m * np.cos(from_walker.bearings_rad),
         from_walker.ranges_m * np.sin(from_walker.bearings_rad)]
    )  # fmt: skip
    np.testing.assert_allclose(pts_w, pts_l + np.array([0.2, 0.0]), atol=1e-9)


def test_an_empty_scan_and_bad_settings():
    empty = LaserScan(0.0, -1.0, 0.01, np.full(200, np.inf, dtype=np.float32), 30.0)
    f = extract(empty)
    assert f.lines == [] and f.corners.shape == (0, 2)
    with pytest.raises(ValueError, match="corner_angle_rad"):
        FeatureConfig(corner_angle_rad=(1.0, 0.5))


def test_replay_gives_a_laser_logs_corners_to_ekf_slam(tmp_path):
    """`walkerslam replay --scan-corners` on a real laser log: each scan's corners reach
    the localizer as sightings without IDs, and EKF-SLAM maps and re-finds them."""
    import json

    from experiments.run import replay_log
    from hardware.datasets import open_dataset
    from tests.hardware.datasets.datasets_testdata import data_dir

    log = data_dir("carmen_corrected_logs") / "freiburg-101-corrected.log.gz"
    res = replay_log(
        open_dataset("carmen", log), tmp_path, localizer="ekf-slam", figures=False,
        map_figure=False, drag_metrics=False, reference_map=False, scan_corners=True,
    )  # fmt: skip
    m, d = res.metrics, res.metrics["localizer_diagnostics"]
    assert m["messages"]["LaserScan"] == 292 and m["messages"]["scan_corners"] > 300
    assert d["without_id"] == m["messages"]["scan_corners"]
    assert d["new_landmarks"] >= 20 and d["associated"] > 150
    assert json.loads((tmp_path / "config.json").read_text())["scan_corners"] is True
