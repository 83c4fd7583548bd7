"""Particle genealogies read back through resampling (slam.particle_paths)."""

import numpy as np
import pytest

from slam.particle_paths import ParticlePaths


def test_paths_follow_parents_through_resampling():
    paths = ParticlePaths(every_s=0.0)
    p0 = np.array([[0.0, 0, 0], [10, 0, 0], [20, 0, 0]])
    paths.snapshot(0.0, p0)
    paths.resampled(np.array([2, 2, 0]))  # new 0, 1 are copies of old 2; new 2 of old 0
    p1 = np.array([[21.0, 0, 0], [22, 0, 0], [1, 0, 0]])
    paths.snapshot(1.0, p1)
    paths.resampled(np.array([1, 2, 2]))
    p2 = np.array([[23.0, 0, 0], [2, 0, 0], [3, 0, 0]])
    t, got = paths.paths(p2)
    assert t.tolist() == [0.0, 1.0]
    # particle 0 now descends from old 1 (x 22) at t=1, which descends from 2 (x 20) at t=0
    assert got[:, 0, 0].tolist() == [20.0, 22.0]
    assert got[:, 1, 0].tolist() == [0.0, 1.0]
    assert got[:, 2, 0].tolist() == [0.0, 1.0]


def test_mean_path_weights_the_current_particles_and_ends_now():
    paths = ParticlePaths(every_s=0.5)
    paths.snapshot(0.0, np.array([[0.0, 0, np.pi - 0.1], [2, 0, -np.pi + 0.1]]))
    paths.snapshot(0.2, np.array([[9.0, 9, 0], [9, 9, 0]]))  # within every_s: skipped
    traj = paths.mean_path(np.array([0.75, 0.25]), 1.0, np.array([[4.0, 0, 0], [0, 4, 0]]))
    assert traj.t.tolist() == [0.0, 1.0]
    assert traj.poses[0, :2] == pytest.approx([0.5, 0.0])
    assert abs(abs(traj.poses[0, 2]) - np.pi) < 0.06  # circular mean across ±π
    assert traj.poses[1, :2] == pytest.approx([3.0, 1.0])
    assert paths.snapshots == 1


def test_rejects_a_negative_interval():
    with pytest.raises(ValueError, match="interval"):
        ParticlePaths(-1.0)


@pytest.mark.parametrize("replace", [True, False])
def test_a_second_snapshot_at_one_time_replaces_the_first_or_follows_it(replace):
    paths = ParticlePaths(every_s=0.0, replace_same_time=replace)
    paths.snapshot(1.0, np.array([[1.0, 0, 0], [2, 0, 0]]))
    paths.resampled(np.array([1, 1]))
    paths.snapshot(1.0, np.array([[3.0, 0, 0], [4, 0, 0]]))
    t, got = paths.paths(np.zeros((2, 3)))
    if replace:  # the poses at t = 1 s corrected; the resampling before them stays
        assert t.tolist() == [1.0] and got[0, :, 0].tolist() == [3.0, 4.0]
    else:  # both, in order, each read back through the resampling after it
        assert t.tolist() == [1.0, 1.0]
        assert got[:, 0, 0].tolist() == [2.0, 3.0] and got[:, 1, 0].tolist() == [2.0, 4.0]
