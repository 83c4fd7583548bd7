"""Separating-axis penetration, distances and batched contacts on hand-computed shapes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hardware.sim.collision import (
    PolygonSet,
    body_rectangle,
    clip_convex,
    contact_point,
    penetration,
    polygon_distance,
    rectangle,
)


def box(x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=float)


def test_axis_aligned_overlap_exact_depth_and_normal() -> None:
    a = box(0.0, 2.0, 0.0, 1.0)
    b = box(1.5, 3.0, -1.0, 2.0)
    depth, normal = penetration(a, b)
    # a overlaps b by 0.5 in x (shortest way out: move a by -0.5 in x); in y it is 2.
    assert depth == pytest.approx(0.5, abs=1e-12)
    np.testing.assert_allclose(normal, [-1.0, 0.0], atol=1e-12)
    depth_b, normal_b = penetration(b, a)
    assert depth_b == pytest.approx(0.5, abs=1e-12)
    np.testing.assert_allclose(normal_b, [1.0, 0.0], atol=1e-12)


def test_shallow_vertical_overlap_pushes_along_y() -> None:
    a = box(0.0, 2.0, 0.0, 1.0)
    b = box(1.0, 3.0, 0.5, 2.0)
    depth, normal = penetration(a, b)
    assert depth == pytest.approx(0.5, abs=1e-12)  # x overlap is 1.0, y overlap 0.5
    np.testing.assert_allclose(normal, [0.0, -1.0], atol=1e-12)
    np.testing.assert_allclose(contact_point(a, b), [1.5, 0.75], atol=1e-12)


def test_rotated_square_corner_into_a_wall() -> None:
    diamond = rectangle(0.0, 0.0, math.pi / 4, 1.0, 1.0)  # right corner at x = 1/√2
    wall = box(0.5, 2.0, -1.0, 1.0)
    depth, normal = penetration(diamond, wall)
    assert depth == pytest.approx(1 / math.sqrt(2) - 0.5, abs=1e-12)
    np.testing.assert_allclose(normal, [-1.0, 0.0], atol=1e-12)
    # The overlap is the triangle (0.5, ±0.2071), (0.7071, 0): centroid at x = (2·0.5 + 0.7071)/3.
    np.testing.assert_allclose(
        contact_point(diamond, wall), [(1.0 + 1 / math.sqrt(2)) / 3, 0.0], atol=1e-12
    )


def test_separated_and_touching_rectangles_do_not_penetrate() -> None:
    a = box(0.0, 1.0, 0.0, 1.0)
    assert penetration(a, box(1.3, 2.0, 0.0, 1.0)) is None
    assert penetration(a, box(1.0, 2.0, 0.0, 1.0)) is None  # touching along an edge
    # Bounding boxes overlap but a separating diagonal axis exists.
    diamond = rectangle(2.0, 2.0, math.pi / 4, 1.0, 1.0)
    assert penetration(box(0.0, 1.6, 0.0, 1.6), diamond) is None


def test_polygon_distance_gap_and_penetration() -> None:
    a = box(0.0, 1.0, 0.0, 1.0)
    assert polygon_distance(a, box(1.3, 2.0, 0.0, 1.0)) == pytest.approx(0.3, abs=1e-12)
    assert polygon_distance(a, box(1.3, 2.0, 1.4, 2.0)) == pytest.approx(0.5, abs=1e-12)
    assert polygon_distance(a, box(0.75, 2.0, 0.2, 0.5)) == pytest.approx(-0.25, abs=1e-12)


def test_clip_convex_intersection_area() -> None:
    overlap = clip_convex(box(0.0, 2.0, 0.0, 1.0), box(1.0, 3.0, 0.5, 2.0))
    x, y = overlap[:, 0], overlap[:, 1]
    area = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    assert area == pytest.approx(0.5, abs=1e-12)
    assert len(clip_convex(box(0, 1, 0, 1), box(2, 3, 0, 1))) == 0


def test_body_rectangle_pose() -> None:
    r = body_rectangle((1.0, 2.0, math.pi / 2), -0.1, 0.64, -0.345, 0.345)
    # Heading +y: the front edge (x_body = 0.64) is at y = 2.64, the right side at x = 1.345.
    np.testing.assert_allclose(r.max(axis=0), [1.345, 2.64], atol=1e-12)
    np.testing.assert_allclose(r.min(axis=0), [0.655, 1.9], atol=1e-12)


def test_polygon_set_contacts_one_per_obstacle_and_part() -> None:
    # A "table": top covering the footprint and a leg inside it, both named table-1.
    polys = np.array([box(1.0, 2.0, -0.5, 0.5), box(1.0, 1.05, -0.5, -0.45), box(-1, 3, 0.6, 0.7)])
    ps = PolygonSet(["table-1", "table-1", "wall"], polys)
    frame = box(0.5, 1.2, -0.3, 0.3)  # 0.2 m into the table top, clear of the wall
    wheel = box(0.9, 1.1, 0.3, 0.62)  # in the table top (0.1 deep) and the wall (0.02)
    contacts = ps.contacts([("frame", frame), ("wheel", wheel)])
    got = {(c.part, c.obstacle): c for c in contacts}
    assert set(got) == {("frame", "table-1"), ("wheel", "table-1"), ("wheel", "wall")}
    c = got[("frame", "table-1")]
    assert c.depth == pytest.approx(0.2, abs=1e-12)
    np.testing.assert_allclose(c.normal, [-1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(c.point, [1.1, 0.0], atol=1e-12)
    assert got[("wheel", "wall")].depth == pytest.approx(0.02, abs=1e-12)
    np.testing.assert_allclose(got[("wheel", "wall")].normal, [0.0, -1.0], atol=1e-12)
    assert ps.contacts([("frame", box(5, 6, 5, 6))]) == []


def test_polygon_set_matches_pairwise_penetration() -> None:
    rng = np.random.default_rng(7)
    polys = np.array(
        [
            rectangle(*rng.uniform(0, 5, 2), rng.uniform(-3, 3), *rng.uniform(0.05, 1.5, 2))
            for _ in range(30)
        ]
    )
    names = [f"o{i}" for i in range(30)]
    ps = PolygonSet(names, polys)
    for _ in range(40):
        pose = (*rng.uniform(0, 5, 2), rng.uniform(-3, 3))
        part = body_rectangle(pose, -0.1, 0.64, -0.345, 0.345)
        got = {c.obstacle: c for c in ps.contacts([("frame", part)])}
        want = {n: penetration(part, p) for n, p in zip(names, polys, strict=True)}
        want = {n: v for n, v in want.items() if v is not None}
        assert set(got) == set(want)
        for n, (depth, normal) in want.items():
            assert got[n].depth == pytest.approx(depth, abs=1e-12)
            np.testing.assert_allclose(got[n].normal, normal, atol=1e-12)
        d, name = ps.clearance(part)
        ref = min((polygon_distance(part, p), n) for n, p in zip(names, polys, strict=True))
        assert d == pytest.approx(ref[0], abs=1e-12)
        assert name == ref[1] or d == pytest.approx(
            polygon_distance(part, polys[names.index(name)]), abs=1e-12
        )


def test_penetration_rejects_bad_shapes() -> None:
    with pytest.raises(ValueError, match="shape"):
        penetration(np.zeros((2, 2)), box(0, 1, 0, 1))


def test_least_gap_is_the_distance_when_apart_and_zero_when_touching() -> None:
    """The broad phase's bound: for parts apart from every polygon, their least distance
    capped at the horizon (exactly what `clearances` gives); 0 whenever a part overlaps a
    polygon, so that the simulator never skips a contact."""
    rng = np.random.default_rng(4)
    polys = np.array(
        [
            rectangle(*rng.uniform(0, 8, 2), rng.uniform(-3, 3), *rng.uniform(0.05, 1.0, 2))
            for _ in range(12)
        ]
    )
    ps = PolygonSet([f"o{i}" for i in range(12)], polys)
    seen = {"apart": 0, "overlap": 0, "beyond": 0}
    for _ in range(300):
        parts = np.array(
            [
                body_rectangle((*rng.uniform(0, 8, 2), rng.uniform(-3, 3)), -0.1, 0.64, -0.3, 0.3),
                rectangle(*rng.uniform(0, 8, 2), rng.uniform(-3, 3), 0.1, 0.2),
            ]
        )
        gap = ps.least_gap(parts, 0.3)
        dist, _ = ps.clearances(parts)
        if dist.min() <= 0.0:
            seen["overlap"] += 1
            assert gap == 0.0
        elif dist.min() >= 0.3:
            seen["beyond"] += 1
            assert gap == 0.3
        else:
            seen["apart"] += 1
            assert gap == pytest.approx(dist.min(), abs=1e-12)
    assert min(seen.values()) >= 20, seen
    # touching along an edge counts as maybe touching: the contacts decide
    assert PolygonSet(["a"], box(0, 1, 0, 1)[None]).least_gap(box(1, 2, 0, 1)[None], 0.3) == 0.0
    with pytest.raises(ValueError, match="shape"):
        ps.least_gap(np.zeros((2, 2)), 0.3)
