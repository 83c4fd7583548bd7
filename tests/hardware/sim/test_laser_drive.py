"""The laser drive (hardware.sim.laser_drive): its scans measure the walls where they
are, its odometry is the truth plus the stated noise, and it follows its route."""

import math

import numpy as np

from hardware.messages import LaserScan, VelocityOdometry
from hardware.sim.laser_drive import PICO_MAZE, PICO_ROUTE, LaserNoise, laser_drive


def test_the_first_scan_sees_the_walls_at_their_distances():
    steps, truth = laser_drive(PICO_MAZE, PICO_ROUTE, 1, noise=LaserNoise(0.0, 0.0, 0.0))
    scan = next(m for m in steps[0] if isinstance(m, LaserScan))
    assert truth[0, 1:].tolist() == [-2.0, -1.0, 0.0]  # the route's start, facing +x
    assert len(scan.ranges) == 541 and math.isclose(scan.angle_min, -0.75 * math.pi)
    ahead, right, left = scan.ranges[270], scan.ranges[90], scan.ranges[450]  # 0°, ∓90°
    assert abs(scan.angles[270]) < 1e-12
    assert abs(ahead - 4.95) < 1e-9  # the far wall's inner face, below the block
    assert abs(right - 0.95) < 1e-9  # the near wall (inner face at y = −1.95)
    assert abs(left - 2.95) < 1e-9  # the far wall (y = 1.95): the block starts at x = −1


def test_the_route_is_followed_and_the_odometry_is_the_truth_with_its_noise():
    steps, truth = laser_drive(PICO_MAZE, PICO_ROUTE, 720, seed=3)
    # about three laps of the rectangle at 0.5 m/s, never near a wall or the block
    turned = np.unwrap(truth[:, 3])[-1] - truth[0, 3]
    assert 2.5 * 2 * math.pi < turned < 3.5 * 2 * math.pi
    assert np.all(np.abs(truth[:, 1]) < 2.6) and np.all(np.abs(truth[:, 2]) < 1.6)
    assert not np.any((np.abs(truth[:, 1]) < 1.2) & (np.abs(truth[:, 2]) < 0.7))
    v = np.array([m.v for s in steps for m in s if isinstance(m, VelocityOdometry)])
    assert abs(v.mean() - 0.5) < 0.005 and abs(v.std() - 0.05 * 0.5) < 0.003
    assert sum(isinstance(m, LaserScan) for s in steps for m in s) == 360
