"""Which contacts count as collisions (thesis §6.4) and which parts meet what heights."""

import math

import pytest

from hardware.messages import Collision
from hardware.sim.simulator import HELD_S, SimConfig, Simulator
from hardware.sim.user import ConstantPush
from hardware.sim.world import World


def world(*boxes: dict, start=(0.0, 0.0, 0.0)) -> World:
    return World.from_dict(
        {
            "name": "w",
            "bounds": [-2, 8, -3, 3],
            "start_pose": list(start),
            "route": [[0, 0], [1, 0]],
            "obstacles": [{"kind": "box", **b} for b in boxes],
        }
    )


def run(w: World, push: tuple[float, float], seconds: float, speed: float = 0.0):
    sim = Simulator(w, SimConfig(seed=0, duration_s=seconds), user=ConstantPush(*push))
    sim.state.v = speed
    msgs = sim.poll(seconds)
    return sim, [m for m in msgs if isinstance(m, Collision)]


WALL_AHEAD = {"name": "wall", "x": 2.0, "y": 0.0, "sx": 0.1, "sy": 3.0, "height": 2.0}


def test_walking_into_a_wall_is_a_front_collision() -> None:
    sim, hits = run(world(WALL_AHEAD), (15.0, 15.0), 4.0)
    assert [(c.kind, c.obstacle) for c in hits] == [("front", "wall")]
    assert sim.scrapes == 0


def test_a_glancing_contact_is_a_scrape_not_a_collision() -> None:
    # A wall along the walker's left, 6 cm beyond the rear wheel; the walker heads 1.5°
    # toward it, so it meets the wall at about 2 cm/s and slides along it.
    side = {"name": "side", "x": 3.0, "y": 0.455, "sx": 6.0, "sy": 0.1, "height": 2.0}
    sim, hits = run(world(side, start=(0.0, 0.0, math.radians(1.5))), (10.0, 10.0), 8.0, 0.6)
    assert hits == []
    assert sim.scrapes == 1
    assert sim.state.x > 3.0  # it kept going


def test_pressing_slowly_against_a_wall_is_a_collision_once_it_holds_the_walker() -> None:
    # Starts 1 cm short of the wall at 6 cm/s (a touch, not a bump), then keeps pushing
    # gently: the wall holds it, and after HELD_S that counts as a collision.
    wall = dict(WALL_AHEAD, x=0.64 + 0.01 + 0.05)
    _, hits = run(world(wall), (1.0, 1.0), 3.0, 0.06)
    assert [c.kind for c in hits] == ["front"]
    assert hits[0].t >= HELD_S


@pytest.mark.parametrize(("z0", "height", "hit"), [(0.5, 0.75, False), (0.0, 0.1, True)])
def test_a_rear_wheel_passes_under_a_table_top_but_catches_on_what_is_low(z0, height, hit):
    # A box beside the walker's path that only the left rear wheel (y 0.28–0.345 m)
    # reaches: at table-top height the wheel passes under it; at floor level it catches.
    box = {"name": "b", "x": 1.5, "y": 0.45, "sx": 1.0, "sy": 0.3, "height": height, "z0": z0}
    _, hits = run(world(box), (12.0, 12.0), 4.0)
    assert [(c.kind, c.obstacle) for c in hits] == ([("rear-wheel", "b")] if hit else [])
