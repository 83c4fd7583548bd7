import numpy as np
import pytest

from hardware.frames import invert_transform, make_transform, rot_rpy, transform_points
from hardware.geometry import (
    between,
    compose,
    from_matrix,
    inverse,
    rotation,
    to_matrix,
    wrap_angle,
)
from hardware.geometry import (
    transform_points as tp2,
)


def random_poses(rng, n):
    return np.column_stack(
        [rng.uniform(-5, 5, n), rng.uniform(-5, 5, n), rng.uniform(-np.pi, np.pi, n)]
    )


def test_wrap_angle_range():
    a = np.linspace(-20, 20, 1001)
    w = wrap_angle(a)
    assert np.all(w > -np.pi) and np.all(w <= np.pi)
    assert np.allclose(np.cos(w), np.cos(a)) and np.allclose(np.sin(w), np.sin(a))
    assert wrap_angle(-np.pi) == pytest.approx(np.pi)


def test_wrap_angle_of_a_large_array_has_the_bits_of_the_formula():
    """Large arrays skip the mod where it changes nothing: every bit is still that of
    π − ((π − a) mod 2π), at the edges of the range and beyond it too."""
    rng = np.random.default_rng(8)
    edges = [np.pi, -np.pi, 0.0, -0.0, 2 * np.pi, -2 * np.pi, 3 * np.pi, 1e20, -1e20]
    edges += [np.nextafter(np.pi, 4.0), np.nextafter(-np.pi, -4.0), np.inf, -np.inf, np.nan]
    for a in (rng.normal(0.0, 3.0, 5000), rng.uniform(-np.pi, np.pi, (40, 60)), edges * 300):
        a = np.asarray(a, dtype=float)
        with np.errstate(invalid="ignore"):
            want = np.pi - np.mod(np.pi - a, 2.0 * np.pi)
            got = wrap_angle(a)
        assert got.shape == a.shape
        np.testing.assert_array_equal(got.view(np.int64), want.view(np.int64))


def test_compose_inverse_is_identity():
    rng = np.random.default_rng(0)
    p = random_poses(rng, 100)
    assert np.allclose(compose(p, inverse(p)), 0, atol=1e-12)
    assert np.allclose(compose(inverse(p), p), 0, atol=1e-12)


def test_compose_matches_matrices_and_between_round_trips():
    rng = np.random.default_rng(1)
    a, b = random_poses(rng, 1)[0], random_poses(rng, 1)[0]
    assert np.allclose(from_matrix(to_matrix(a) @ to_matrix(b)), compose(a, b))
    assert np.allclose(compose(a, between(a, b)), b)


def test_transform_points_rotates_then_translates():
    pose = np.array([1.0, 2.0, np.pi / 2])
    assert np.allclose(tp2(pose, np.array([[1.0, 0.0]])), [[1.0, 3.0]])


def test_bad_shape_is_a_clear_error():
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        compose(np.zeros(2), np.zeros(3))


def test_se3_inverse_and_points():
    rng = np.random.default_rng(2)
    t = make_transform(rot_rpy(*rng.uniform(-1, 1, 3)), rng.uniform(-1, 1, 3))
    assert np.allclose(t @ invert_transform(t), np.eye(4))
    pts = rng.normal(size=(10, 3))
    assert np.allclose(transform_points(invert_transform(t), transform_points(t, pts)), pts)


def test_rotation_turns_points_as_a_pose_does_and_keeps_the_heading():
    rng = np.random.default_rng(4)
    pts = rng.uniform(-3, 3, (10, 2))
    for th in rng.uniform(-4, 4, 5):
        assert pts @ rotation(th).T == pytest.approx(tp2(np.array([0.0, 0.0, th]), pts))
        r3 = rotation(th, 3)
        assert r3[:2, :2] == pytest.approx(rotation(th)) and r3[2].tolist() == [0, 0, 1]
        assert r3[:, 2].tolist() == [0, 0, 1]
        assert rotation(th) @ rotation(-th) == pytest.approx(np.eye(2))
    with pytest.raises(ValueError, match="2 or 3"):
        rotation(0.1, 4)
