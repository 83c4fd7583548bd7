"""Every localizer's trajectory when a landmark sighting comes after the last odometry
message (a log whose odometry ends first: e.g. an MRCLAM twin cut to the ground truth's
span). grid-rbpf's path then had the sighting's snapshot past the track's end and gave
two poses at one time (ValueError from Trajectory)."""

from __future__ import annotations

import numpy as np
import pytest

from hardware.calibration import WalkerCalibration
from hardware.messages import RangeBearing, VelocityOdometry
from slam.base import LOCALIZERS, create
from slam.measurement import range_bearing

LANDMARKS = {6: (2.0, 1.0), 7: (1.0, -1.5), 8: (3.0, -0.5)}


@pytest.mark.parametrize("name", LOCALIZERS.names())
def test_a_sighting_after_the_last_odometry_message(name):
    loc = create(name, WalkerCalibration(), initial_pose=(0.0, 0.0, 0.0), landmark_map=LANDMARKS)
    for k in range(21):  # 2 s at 0.2 m/s
        loc.process(VelocityOdometry(0.1 * k, 0.2, 0.0))
        if k % 5 == 4:
            pose = np.array([0.02 * k, 0.0, 0.0])
            for lid, xy in LANDMARKS.items():
                r, b = range_bearing(pose, np.array(xy))
                loc.process(RangeBearing(0.1 * k, lid, float(r), float(b)))
    pose = np.array([0.4, 0.0, 0.0])
    for lid, xy in LANDMARKS.items():  # 0.15 s after the last odometry message
        r, b = range_bearing(pose, np.array(xy))
        loc.process(RangeBearing(2.15, lid, float(r), float(b)))
    traj = loc.trajectory()
    assert np.all(np.diff(traj.t) > 0)
    assert 2.0 <= traj.t[-1] <= 2.15
    # it stayed on the straight line it drove (2 s at 0.2 m/s)
    assert np.max(np.abs(traj.poses[:, 1])) < 0.05
    assert traj.poses[-1, 0] == pytest.approx(0.4, abs=0.05)
