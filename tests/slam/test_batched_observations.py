"""One RangeBearings message per time gives every landmark localizer the same answer as the
same observations in one RangeBearing message each (the way MRCLAM feeds them)."""

import dataclasses

import numpy as np
import pytest

from experiments.metrics import ate
from hardware.calibration import WalkerCalibration
from hardware.sim.landmark_drive import DriveNoise, batched, landmark_drive
from slam.base import LOCALIZERS, create
from slam.trajectory import Trajectory

LANDMARKS = {0: (6.0, -1.0), 1: (8.0, 6.0), 2: (2.0, 9.0), 3: (-4.0, 4.0), 4: (-3.0, -3.0)}
NOISE = DriveNoise(v=0.1, omega=0.05, range_m=0.1, bearing_rad=0.02)


def run(name: str, steps, **config):
    cfg = dataclasses.replace(LOCALIZERS.spec(name).config_type(), **config)
    loc = create(name, WalkerCalibration(), cfg, landmark_map=LANDMARKS)
    for msgs in steps:
        for m in msgs:
            loc.process(m)
    return loc


@pytest.mark.parametrize(
    ("name", "config"),
    [
        ("fastslam", {"version": 2}),
        ("fastslam", {"version": 1}),
        ("ekf-slam", {}),
        ("particle-filter", {"n_particles": 200}),
        # the odometry's noise drawn at each sighting (one step's covariance has rank 2)
        ("particle-filter", {"n_particles": 200, "proposal": "scan"}),
        ("grid-rbpf", {}),
        ("gtsam", {}),
    ],
)
def test_batched_and_per_landmark_messages_give_the_same_answer(name, config):
    # a circle among five landmarks, those within 8 m seen every 0.1 s
    steps, truth = landmark_drive(LANDMARKS, 150, 0.1, 1.0, 0.25, NOISE, max_range_m=8.0)
    one_each = run(name, steps, **config)
    together = run(name, batched(steps), **config)
    a, b = one_each.trajectory(), together.trajectory()
    assert np.array_equal(a.t, b.t)
    np.testing.assert_allclose(b.poses, a.poses, rtol=0, atol=1e-9)
    # and the answer is a localization, not two equal failures
    assert ate(b, Trajectory(truth[:, 0], truth[:, 1:]))["ate_rmse_m"] < 0.3
