"""What a simulated user sees through the goggles, and how they choose their way."""

import math

import numpy as np
import pytest

from hardware.sim.user_vision import (
    GogglesVision,
    VisionParams,
    cast_rays,
    choose_offset,
    route_coordinates,
)
from hardware.sim.world import COLLISION_BAND_M, World


def world_with(*boxes: dict) -> World:
    """A world holding `boxes` ({"name", "x", "y", "sx", "sy", "height", "z0"})."""
    obstacles = [{"kind": "box", **b} for b in boxes]
    return World.from_dict(
        {
            "name": "w",
            "bounds": [-5, 5, -5, 5],
            "start_pose": [0, 0, 0],
            "route": [[0, 0], [1, 0]],
            "obstacles": obstacles,
        }
    )


EXACT = VisionParams(range_sigma=0.0, bearing_sigma_deg=0.0)


def sight(world: World, params: VisionParams = EXACT) -> list:
    """What a user with `params` can see of `world`."""
    return world.footprint_polygons(params.min_height_m, COLLISION_BAND_M[1])


def test_cast_rays_hits_the_nearest_face() -> None:
    # A 1 m square from x = 1.5 to 2.5 and y = -0.5 to 0.5; rays from the origin.
    sq = np.array([[1.5, -0.5], [2.5, -0.5], [2.5, 0.5], [1.5, 0.5]])
    starts, dirs = sq, np.roll(sq, -1, axis=0) - sq
    angles = np.array([0.0, math.atan2(0.4, 1.5), math.pi / 2, math.pi])
    dist, edge = cast_rays(np.zeros(2), angles, starts, dirs, 3.0)
    assert dist[0] == pytest.approx(1.5) and edge[0] == 3  # the x = 1.5 face
    assert dist[1] == pytest.approx(math.hypot(1.5, 0.4))
    assert np.isinf(dist[2]) and np.isinf(dist[3]) and edge[2] == edge[3] == -1
    # Out of range: nothing.
    assert np.isinf(cast_rays(np.zeros(2), angles[:1], starts, dirs, 1.4)[0][0])


def test_sees_what_is_ahead_in_the_window_above_the_floor_and_in_range() -> None:
    world = world_with(
        {"name": "ahead", "x": 2.0, "y": 0.0, "sx": 0.2, "sy": 1.0, "height": 0.9},
        {"name": "low", "x": 1.0, "y": 0.5, "sx": 0.2, "sy": 0.2, "height": 0.1},
        {"name": "far", "x": 0.0, "y": 4.0, "sx": 1.0, "sy": 0.2, "height": 0.9},
    )
    vision = GogglesVision(sight(world), EXACT, np.random.default_rng(0))
    assert vision.step(0.0, (0.0, 0.0, 0.0))
    pts = vision.points
    # Only the near face of "ahead" (x = 1.9 in the walker frame): the low box is not
    # seen, and nothing else is in the ±30° window.
    assert len(pts) > 10
    np.testing.assert_allclose(pts[:, 0], 1.9, atol=1e-9)
    assert np.abs(pts[:, 1]).max() <= 0.5 + 1e-9
    # Facing the far box (4 m away, beyond the 3 m range) shows nothing new.
    vision2 = GogglesVision(sight(world), EXACT, np.random.default_rng(0))
    vision2.step(0.0, (0.0, 0.0, math.pi / 2))
    assert len(vision2.points) == 0


def test_misjudged_distance_is_the_same_for_every_look_at_one_obstacle() -> None:
    world = world_with({"name": "a", "x": 2.0, "y": 0.0, "sx": 0.2, "sy": 1.0, "height": 0.9})
    vision = GogglesVision(sight(world), VisionParams(range_sigma=0.2), np.random.default_rng(1))
    vision.step(0.0, (0.0, 0.0, 0.0))
    first = vision.points.copy()
    vision.step(0.2, (0.0, 0.0, 0.0))
    second = vision.points[len(first) :]
    np.testing.assert_allclose(first, second)  # the same error on every look
    eye = np.array([EXACT.eye_offset_m, 0.0])
    ratio = np.hypot(*(first - eye).T) / np.hypot(*(np.array([1.9, 0.0]) - eye))
    assert ratio.min() > 0.0 and not np.allclose(ratio[0], 1.0)


def test_memory_moves_with_the_walker_and_fades() -> None:
    world = world_with({"name": "a", "x": 2.0, "y": 0.0, "sx": 0.2, "sy": 0.2, "height": 0.9})
    params = VisionParams(range_sigma=0.0, bearing_sigma_deg=0.0, period_s=10.0)
    vision = GogglesVision(sight(world, params), params, np.random.default_rng(0))
    vision.step(0.0, (0.0, 0.0, 0.0))
    i = int(np.argmin(np.abs(vision.points[:, 1])))
    near = vision.points[i].copy()
    assert near[0] == pytest.approx(1.9)
    vision.carry(1.0, 0.0)  # a metre forward
    vision.carry(0.0, math.pi / 2)  # then a quarter turn left: ahead is now on the right
    np.testing.assert_allclose(vision.points[i], [near[1], -0.9], atol=1e-9)
    vision.step(1.9, (0.0, 0.0, 0.0))  # within memory, no glimpse due
    assert len(vision.points) > 0
    vision.step(2.1, (0.0, 0.0, 0.0))  # past memory_s = 2 s
    assert len(vision.points) == 0


def test_route_coordinates_straight_and_round_a_bend() -> None:
    route = np.column_stack([np.arange(0.0, 2.01, 0.1), np.zeros(21)])
    along, across = route_coordinates(np.array([[1.0, 0.3], [0.5, -0.2], [-0.5, 0.0]]), route, 0.1)
    np.testing.assert_allclose(along[:2], [1.0, 0.5], atol=1e-9)
    np.testing.assert_allclose(across[:2], [0.3, -0.2], atol=1e-9)
    assert np.isnan(along[2]) and np.isnan(across[2])  # behind the route's start
    # An L: along x to (1, 0), then up. A point off the outside of the corner is its
    # distance away, not on the route's line.
    up = np.column_stack([np.ones(10), np.arange(0.1, 1.01, 0.1)])
    bend = np.vstack([route[:11], up])
    _, across = route_coordinates(np.array([[1.4, -0.3]]), bend, 0.1)
    assert across[0] == pytest.approx(-0.5, abs=1e-9)


def test_choose_offset_keeps_to_the_route_and_centres_in_a_tight_gap() -> None:
    hw, margin = 0.325, 0.3
    nothing = np.zeros(0)
    assert choose_offset(nothing, nothing, hw, margin) == (0.0, math.inf)
    # A wall 0.5 m to the left: move right until 0.3 m clear of the corridor's edge.
    off, free = choose_offset(np.array([1.0]), np.array([0.5]), hw, margin)
    assert off == pytest.approx(0.5 - hw - margin) and free == math.inf
    # A wide way: stay on the route.
    off, _ = choose_offset(np.array([1.0, 1.0]), np.array([1.5, -1.5]), hw, margin)
    assert off == 0.0
    # A 0.9 m gap off-centre: its middle.
    off, free = choose_offset(np.array([1.0, 1.0]), np.array([0.5, -0.4]), hw, margin)
    assert off == pytest.approx(0.05) and free == math.inf
    # Narrower than the corridor: the middle, free up to the first point in the way.
    off, free = choose_offset(np.array([1.0, 1.5]), np.array([0.2, -0.2]), hw, margin)
    assert off == pytest.approx(0.0) and free == pytest.approx(1.0)
    # Points beyond the route's ends (NaN) do not count.
    off, _ = choose_offset(np.array([np.nan]), np.array([np.nan]), hw, margin)
    assert off == 0.0
