"""Place recognition (slam.place_recognition) and the loop closures it finds in gtsam."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from laser_worlds import HALL, ROOM, loop_messages, render_scan

from experiments.metrics import ate
from hardware.calibration import WalkerCalibration
from hardware.messages import LaserScan, VelocityOdometry
from slam.base import create
from slam.gtsam_smoother import GtsamConfig, LoopClosures, PlaceRecognition
from slam.place_recognition import nearest_keys, ring_key
from slam.trajectory import Trajectory


def test_a_ring_key_does_not_change_when_the_sensor_turns():
    """Turning the sensor by whole sectors (5° at 72) shifts the returns' bearings, not
    their rings: the same key; a different place gives a different one."""
    scan = render_scan(ROOM, (4.0, 2.0, 0.3), fov=2 * math.pi, beams=720, range_max=30.0)
    turned = replace(scan, angle_min=scan.angle_min + math.radians(35.0))
    key = ring_key(scan, rings=20, sectors=72, range_m=20.0)
    assert np.linalg.norm(key) == pytest.approx(1.0)
    np.testing.assert_allclose(ring_key(turned, 20, 72, 20.0), key, atol=1e-12)
    hall = ring_key(render_scan(HALL, (7.0, 1.5, 0.0), fov=2 * math.pi, beams=720), 20, 72, 20.0)
    assert np.linalg.norm(hall - key) > 0.2


def test_a_ring_key_counts_only_returns_within_its_range():
    far = LaserScan(0.0, -math.pi / 2, math.pi / 180, np.full(181, 50.0, np.float32), 81.0)
    none = LaserScan(0.0, -math.pi / 2, math.pi / 180, np.full(181, 81.0, np.float32), 81.0)
    assert not ring_key(far, range_m=40.0).any() and not ring_key(none).any()
    key = ring_key(far, rings=20, range_m=80.0)  # 50 m: ring 12 of 4 m rings
    assert key.argmax() == 12 and np.count_nonzero(key) == 1


def test_nearest_keys_nearest_first():
    keys = np.array([[1.0, 0.0], [0.0, 1.0], [0.6, 0.8], [0.8, 0.6]])
    np.testing.assert_array_equal(nearest_keys(keys, np.array([1.0, 0.0]), 3), [0, 3, 2])
    assert len(nearest_keys(keys[:0], np.array([1.0, 0.0]), 3)) == 0
    assert len(nearest_keys(keys, np.array([1.0, 0.0]), 10)) == 4


def _kidnapped():
    """A lap of the room; then four minutes with the laser blind while the wheels slip:
    the odometry reports 120 m straight ahead where the walker only turns back to the
    lap's start; then a second lap (other scan noise). Messages, and the true path of
    the second lap."""
    lap1, truth1 = loop_messages(laps=1)
    lap2, truth2 = loop_messages(laps=1, seed=6)
    t1 = float(truth1.t[-1])
    blind = [VelocityOdometry(round(t1 + 0.1 * (k + 1), 6), 0.5, 0.0) for k in range(2400)]
    shift = round(blind[-1].t + 0.1, 6)
    lap2 = [replace(m, t=round(m.t + shift, 6)) for m in lap2]
    return lap1 + blind + lap2, Trajectory(truth2.t + shift, truth2.poses)


def _run(msgs, cfg: GtsamConfig):
    loc = create("gtsam", WalkerCalibration(), cfg, initial_pose=(1.5, 1.5, 0.0))
    for m in msgs:
        loc.process(m)
    return loc


def test_a_revisit_the_estimate_is_far_from_is_closed_by_place_recognition():
    """After the blind stretch the estimate is ~120 m from the room, far beyond the loop
    search around it; place recognition finds the first lap's scans from the second's,
    verifies the match and closes the loop: the second lap lands on the true path. The
    walker turned 90° unseen, 5 σ from the graph's heading, so the first search's
    matches are held until a later search's match agrees (a corridor matched the wrong
    way round would not be taken on its own)."""
    msgs, truth2 = _kidnapped()
    on = _run(msgs, GtsamConfig(scan_matching=True))
    off = _run(
        msgs,
        GtsamConfig(scan_matching=True, loop=LoopClosures(place=PlaceRecognition(enabled=False))),
    )
    d = on.diagnostics()
    assert d["place_searches"] >= 2 and d["place_doubted"] >= 1 and d["place_closures"] >= 2
    assert off.diagnostics()["place_closures"] == 0
    # (over the second lap: the truth's times)
    assert ate(off.trajectory(), truth2)["ate_rmse_unaligned_m"] > 20.0
    assert ate(on.trajectory(), truth2)["ate_rmse_unaligned_m"] < 0.2


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("every", 0, "every must be >= 1"),
        ("window_m", 0.0, "window_m and range_m must be > 0"),
        ("heading_sigmas", 0.0, "heading_sigmas > 0"),
        ("doubt_searches", 0, "doubt_searches >= 1"),
    ],
)
def test_bad_place_recognition_settings_are_refused(field, value, message):
    with pytest.raises(ValueError, match=message):
        PlaceRecognition(**{field: value})
