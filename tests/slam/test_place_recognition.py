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
from slam.gtsam_smoother import GtsamConfig
from slam.place_recognition import PlaceKeys, nearest_places, polar_key, similarities
from slam.scan_graph import LoopClosures, PlaceRecognition
from slam.trajectory import Trajectory


def test_a_polar_key_is_as_similar_as_can_be_to_itself_turned():
    """Turning the sensor by whole sectors (5° at 72) shifts the key's columns: the best
    shift finds it again (similarity 1); a different place is less similar, and the
    shifted comparison equals a brute-force one over every np.roll."""
    scan = render_scan(ROOM, (4.0, 2.0, 0.3), fov=2 * math.pi, beams=720, range_max=30.0)
    turned = replace(scan, angle_min=scan.angle_min + math.radians(35.0))
    key = polar_key(scan, rings=20, sectors=72, range_m=20.0)
    assert key.shape == (20, 72)
    seen = key.any(axis=0)
    np.testing.assert_allclose(np.linalg.norm(key[:, seen], axis=0), 1.0, rtol=1e-6)
    hall = polar_key(render_scan(HALL, (7.0, 1.5, 0.0), fov=2 * math.pi, beams=720), 20, 72, 20.0)
    keys = np.stack([key, hall])
    score = similarities(keys, polar_key(turned, 20, 72, 20.0))
    assert score[0] == pytest.approx(1.0, abs=1e-5) and score[1] < 0.8
    brute = [
        max(
            float((k * np.roll(q, s, axis=1)).sum())
            / max(int((k.any(axis=0) | np.roll(q, s, axis=1).any(axis=0)).sum()), 1)
            for s in range(72)
        )
        for k, q in ((key, hall), (hall, key))
    ]
    np.testing.assert_allclose(similarities(keys[:1], hall)[0], brute[0], rtol=1e-5)
    np.testing.assert_allclose(similarities(keys[1:], key)[0], brute[1], rtol=1e-5)


def test_a_polar_key_counts_only_returns_within_its_range():
    far = LaserScan(0.0, -math.pi / 2, math.pi / 180, np.full(181, 50.0, np.float32), 81.0)
    none = LaserScan(0.0, -math.pi / 2, math.pi / 180, np.full(181, 81.0, np.float32), 81.0)
    assert not polar_key(far, range_m=40.0).any() and not polar_key(none).any()
    key = polar_key(far, rings=20, sectors=72, range_m=80.0)  # 50 m: ring 12 of 4 m rings
    assert set(np.flatnonzero(key.any(axis=1))) == {12}
    assert np.count_nonzero(key.any(axis=0)) == 37  # 180° of 5° sectors, both ends
    assert similarities(np.stack([key]), polar_key(none))[0] == 0.0


def test_nearest_places_most_similar_first():
    rng = np.random.default_rng(3)
    keys = (rng.random((6, 10, 36)) < 0.2).astype(np.float32)
    keys /= np.maximum(np.sqrt(keys.sum(axis=1, keepdims=True)), 1.0)
    query = np.roll(keys[4], 5, axis=1)
    order = nearest_places(keys, query, 3)
    assert order[0] == 4 and len(order) == 3
    score = similarities(keys, query)
    assert list(order) == list(np.argsort(-score, kind="stable")[:3])
    assert len(nearest_places(keys[:0], query, 3)) == 0
    assert len(nearest_places(keys, query, 10)) == 6


def test_stored_keys_answer_as_the_keys_themselves():
    """PlaceKeys keeps each key's spectra from when it was added (past its first
    capacity of 64): any subset of its rows ranks, against a stored query, as
    nearest_places ranks those keys."""
    rng = np.random.default_rng(5)
    keys = (rng.random((150, 10, 36)) < 0.2).astype(np.float32)
    keys /= np.maximum(np.sqrt(keys.sum(axis=1, keepdims=True)), 1.0)
    keys[3] = 0.0  # a scan without returns
    query = np.roll(keys[97], 7, axis=1)
    store = PlaceKeys()
    assert [store.add(k) for k in [*keys, query]] == list(range(151)) and len(store) == 151
    for rows in (np.arange(150), np.arange(0, 150, 3), np.array([97, 2, 140])):
        got = store.nearest(rows, 150, 5)
        np.testing.assert_array_equal(got, nearest_places(keys[rows], query, 5))
    assert store.nearest(np.arange(150), 150, 1)[0] == 97
    assert len(store.nearest(np.zeros(0, int), 150, 5)) == 0
    assert store.saw_anything(150) and not store.saw_anything(3)
    with pytest.raises(IndexError, match="rows must lie in"):
        store.nearest(np.array([151]), 150, 1)
    with pytest.raises(IndexError, match="rows must lie in"):
        store.nearest(np.array([0]), 151, 1)
    with pytest.raises(ValueError, match="does not match the stored keys"):
        store.add(np.zeros((10, 72), np.float32))


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
