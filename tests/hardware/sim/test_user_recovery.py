"""A user caught again on what they touched goes round it wider (UserParams.detour_*),
instead of stepping back and walking into the same corner again and again."""

from __future__ import annotations

import numpy as np
import pytest

from hardware.sim.dynamics import WalkerParams, WalkerState
from hardware.sim.user import ROUTE_STEP_M, RouteFollower, UserParams


def _user() -> RouteFollower:
    route = np.array([[0.0, 0.0], [10.0, 0.0]])  # straight along +x
    start = WalkerState(0.0, 0.0, 0.0)
    return RouteFollower(
        route, start, WalkerParams(), UserParams(vision=None), np.random.default_rng(0)
    )


def test_a_first_collision_leaves_the_path_alone():
    user = _user()
    state = WalkerState(2.0, 0.0, 0.0)
    user.on_collision(state, np.array([2.0, -0.35]))  # right rear wheel
    assert user._detour == 0.0
    before, _ = user._route_aim()
    user._t += 30.0  # long after: not the same catch
    user.on_collision(state, np.array([2.0, -0.35]))
    after, _ = user._route_aim()
    assert user._detour == 0.0 and after == pytest.approx(before)


def test_caught_again_they_go_round_it_wider_and_longer():
    user = _user()
    state = WalkerState(2.0, 0.0, 0.0)
    p = user.p
    aim, _ = user._route_aim()
    for repeat in range(1, 5):
        user._t += 3.0
        user.on_collision(state, np.array([2.0, -0.35]))  # the same corner, on the right
        if repeat == 1:
            continue
        detour = min(p.detour_step_m * (repeat - 1), p.detour_max_m)
        assert user._detour == pytest.approx(detour)  # away from it: to the left
        assert user._backoff_left_s == pytest.approx(p.backoff_s * repeat)
        shifted, _ = user._route_aim()
        assert shifted[1] - aim[1] == pytest.approx(detour, abs=1e-9)
    # on the left, the detour is to the right
    user._contacts.clear()
    for _ in range(2):
        user.on_collision(state, np.array([2.0, 0.35]))
    assert user._detour == pytest.approx(-p.detour_step_m)
    # it lasts detour_length_m of the route
    user._progress = user._detour_until
    plain, _ = user._route_aim()
    assert plain[1] == pytest.approx(0.0, abs=1e-9)
    assert user._detour_until * ROUTE_STEP_M == pytest.approx(p.detour_length_m, abs=0.05)


def test_a_collision_elsewhere_is_not_a_repeat():
    user = _user()
    state = WalkerState(2.0, 0.0, 0.0)
    user.on_collision(state, np.array([2.0, -0.35]))
    user._t += 2.0
    user.on_collision(state, np.array([2.5, 0.35]))  # another obstacle, 0.8 m away
    assert user._detour == 0.0


@pytest.mark.slow
def test_the_user_who_was_stuck_at_a_box_walks_on():
    """The course and slip studies' user 8 (dusty, open-loop braking on dead reckoning)
    caught a rear wheel on box-n6 49 times in 200 s and never finished; going round it
    wider, they finish with 4 collisions, 2 of them at the box."""
    from experiments.simulation import RunSpec, simulate
    from hardware.sim.user import UserProfile

    spec = RunSpec("thesis-course", "open-loop", seed=8, user_profile=UserProfile.sample(8))
    res = simulate(spec)
    assert res.sim.user.finished and res.sim.t < 200.0
    collisions = res.pipeline.recorded.collisions
    assert len(collisions) <= 6
    assert sum(c.obstacle == "box-n6" for c in collisions) <= 3
