"""Measurement models against numerical Jacobians, inverses and the simulated tag camera."""

import math

import numpy as np
import pytest
from helpers import numerical_jacobian

from hardware.calibration import WalkerCalibration
from hardware.messages import EncoderTicks, RangeBearing, RangeBearings, TagDetections
from hardware.sim.simulator import SimConfig
from hardware.sim.tag_camera import SimTagCamera, TagCameraConfig
from hardware.sim.world import load_world
from slam.measurement import (
    Sightings,
    chi2_quantile,
    landmark_from_range_bearing,
    landmark_from_range_bearing_jacobians,
    range_bearing,
    range_bearing_jacobians,
    tag_observations,
)


@pytest.fixture
def cases():
    rng = np.random.default_rng(11)
    poses = np.column_stack(
        [rng.uniform(-5, 5, 30), rng.uniform(-5, 5, 30), rng.uniform(-3, 3, 30)]
    )
    lms = rng.uniform(-6, 6, (30, 2))
    return poses, lms


def test_range_bearing_jacobians_match_numerical(cases):
    for pose, lm in zip(*cases, strict=True):
        g_s, g_l = range_bearing_jacobians(pose, lm)
        assert np.allclose(
            g_s,
            numerical_jacobian(lambda p, lm=lm: range_bearing(p, lm), pose, wrap=(1,)),
            atol=1e-6,
        )
        assert np.allclose(
            g_l,
            numerical_jacobian(lambda m, pose=pose: range_bearing(pose, m), lm, wrap=(1,)),
            atol=1e-6,
        )


def test_range_bearing_vectorised_equals_loop(cases):
    poses, lms = cases
    g_s, g_l = range_bearing_jacobians(poses, lms)
    for i in range(len(poses)):
        a, b = range_bearing_jacobians(poses[i], lms[i])
        assert np.allclose(g_s[i], a) and np.allclose(g_l[i], b)
    assert np.allclose(range_bearing(poses, lms)[3], range_bearing(poses[3], lms[3]))


def test_inverse_model_round_trip_and_jacobians(cases):
    for pose, lm in zip(*cases, strict=True):
        z = range_bearing(pose, lm)
        assert np.allclose(landmark_from_range_bearing(pose, z), lm)
        j_s, j_z = landmark_from_range_bearing_jacobians(pose, z)
        assert np.allclose(
            j_s,
            numerical_jacobian(lambda p, z=z: landmark_from_range_bearing(p, z), pose),
            atol=1e-6,
        )
        num_z = numerical_jacobian(lambda zz, pose=pose: landmark_from_range_bearing(pose, zz), z)
        assert np.allclose(j_z, num_z, atol=1e-6)


def test_known_values():
    z = range_bearing(np.array([1.0, 1.0, math.pi / 2]), np.array([1.0, 3.0]))
    assert z == pytest.approx([2.0, 0.0])
    z = range_bearing(np.array([0.0, 0.0, 0.0]), np.array([-1.0, -1e-12]))
    assert abs(z[1]) == pytest.approx(math.pi)


def test_tag_observations_agree_with_the_world():
    """Noise-free simulated detections, turned into walker-frame observations and placed at
    the true pose, land on the world's tag positions and normals."""
    world = load_world("thesis-course")
    cal = SimConfig().calibration()
    cam = SimTagCamera(world, cal, TagCameraConfig(pixel_noise_px=0.0), np.random.default_rng(0))
    seen = 0
    for i in range(0, len(world.route) - 1, 7):
        p, q = world.route[i], world.route[i + 1]
        pose = np.array([p[0], p[1], math.atan2(q[1] - p[1], q[0] - p[0])])
        obs = tag_observations(TagDetections(0.0, tuple(cam.detect(pose))), cal)
        for tag_id, z, yaw in zip(obs.ids, obs.z, obs.yaw, strict=True):
            tag = world.tag(int(tag_id))
            lm = landmark_from_range_bearing(pose, z)
            # tag centres are 0.35 m high; the planar position ignores height
            assert np.allclose(lm, [tag.x, tag.y], atol=0.01)
            assert abs(math.remainder(pose[2] + yaw - tag.yaw, 2 * math.pi)) < 0.02
            seen += 1
    assert seen > 20


def test_sightings_of_one_time_come_out_together_in_order():
    buf = Sightings(WalkerCalibration())
    assert buf.offer(RangeBearing(1.0, 4, 2.0, 0.5)) is None and buf.taken
    assert buf.offer(RangeBearings.of(1.0, [7, -1], [3.0, 4.0], [3.5, -0.1])) is None
    assert buf.offer(RangeBearing(1.0, 5, 6.0, -4.0)) is None
    # a message of another time ends them; it is held in turn
    obs = buf.offer(RangeBearing(1.5, 4, 2.1, 0.4))
    assert obs.t == 1.0 and obs.ids.tolist() == [4, 7, -1, 5]
    assert obs.z[:, 0].tolist() == [2.0, 3.0, 4.0, 6.0]
    np.testing.assert_allclose(obs.z[:, 1], [0.5, 3.5 - 2 * math.pi, -0.1, 2 * math.pi - 4.0])
    assert np.isnan(obs.yaw).all() and buf.t == 1.5
    # a message that is not a sighting ends them too, and is not taken
    obs = buf.offer(EncoderTicks(1.5, 10, 12))
    assert not buf.taken and obs.ids.tolist() == [4] and buf.take() is None
    # a lone frame comes out as it was given; an empty one is taken but holds nothing
    frame = RangeBearings.of(2.0, [1, 2], [1.0, 2.0], [0.0, 0.1])
    assert buf.offer(frame) is None and buf.offer(TagDetections(2.0)) is None and buf.taken
    obs = buf.take()
    assert obs.ids.tolist() == [1, 2] and np.allclose(obs.z, [[1.0, 0.0], [2.0, 0.1]])
    assert not buf and math.isnan(buf.t)


def test_chi2_quantile_is_scipy_stats_to_the_bit():
    from scipy.stats import chi2

    from slam.association import CHI2_999

    for p in (0.5, 0.9, 0.95, 0.99, 0.999, 0.9999):
        for dof in (1, 2, 3, 4, 6):
            assert chi2_quantile(p, dof) == float(chi2.ppf(p, dof)), (p, dof)
    assert CHI2_999 == {k: float(chi2.ppf(0.999, k)) for k in (2, 3)}
    assert CHI2_999 == {2: 13.815510557964274, 3: 16.26623619623813}  # the gates as they were
