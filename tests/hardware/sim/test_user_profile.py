"""Seeded user profiles: deterministic per seed, within their documented ranges, and no
change at all to the simulated user when no profile is given."""

from dataclasses import asdict

import numpy as np

from hardware.messages import GroundTruthPose
from hardware.sim.simulator import SimConfig, Simulator
from hardware.sim.user import RouteFollower, UserParams, UserProfile
from hardware.sim.world import COLLISION_BAND_M, load_world


def truth(sim, seconds):
    return np.array(
        [(m.t, m.x, m.y, m.theta) for m in sim.poll(seconds) if isinstance(m, GroundTruthPose)]
    )


def test_sampling_is_deterministic_per_seed():
    assert UserProfile.sample(7) == UserProfile.sample(7)
    assert UserProfile.sample(7) != UserProfile.sample(8)
    assert len({UserProfile.sample(s) for s in range(50)}) == 50


def test_sampled_values_stay_in_their_ranges():
    ps = [UserProfile.sample(s) for s in range(300)]
    get = lambda k: np.array([getattr(p, k) for p in ps])  # noqa: E731
    assert np.all(np.abs(get("route_offset_m")) <= 0.1)
    assert np.all((get("route_wander_m") >= 0) & (get("route_wander_m") <= 0.08))
    assert np.all((get("speed_scale") >= 0.85) & (get("speed_scale") <= 1.15))
    assert np.all((get("push_scale") >= 0.8) & (get("push_scale") <= 1.25))
    assert np.all((get("heading_drift_scale") >= 0.5) & (get("heading_drift_scale") <= 1.5))
    assert abs(get("route_offset_m").mean()) < 0.01  # centred: no side preferred overall


def test_identity_profile_changes_nothing_in_the_parameters():
    p = UserParams()
    assert UserProfile().apply(p) == p
    q = UserProfile(speed_scale=1.2, push_scale=0.5, heading_drift_scale=2.0).apply(p)
    assert q.speed_mps == p.speed_mps * 1.2 and q.max_push_n == p.max_push_n * 0.5
    assert q.heading_drift_rad_per_sqrt_m == 2 * p.heading_drift_rad_per_sqrt_m


def test_route_offset_is_sideways_and_tapered():
    route = np.array([[0.0, 0.0], [10.0, 0.0]])
    walked = UserProfile(route_offset_m=0.1).walk_route(route)
    assert np.allclose(walked[0], route[0]) and np.allclose(walked[-1], route[-1])
    middle = walked[(walked[:, 0] > 1.01) & (walked[:, 0] < 8.99)]
    assert np.allclose(middle[:, 1], 0.1)  # left of the direction of travel
    assert np.allclose(UserProfile().walk_route(route)[:, 1], 0.0)
    wander = UserProfile(route_wander_m=0.05, wander_seed=3).walk_route(route)
    assert 0.03 < np.std(wander[(wander[:, 0] > 1) & (wander[:, 0] < 9), 1]) < 0.08


def test_no_profile_is_exactly_the_old_user():
    """Without a profile the simulator's user is UserParams on World.route, drawing from
    the same random streams as before profiles existed (and the goggles' own)."""
    world = load_world("thesis-course")
    cfg = SimConfig(seed=3)
    a = truth(Simulator(world, cfg), 15.0)
    ref = Simulator(world, cfg)
    streams = np.random.SeedSequence(3).spawn(6)
    rng_user, rng_vision = (np.random.default_rng(streams[i]) for i in (1, 5))
    w = cfg.walker
    sight = world.footprint_polygons(cfg.user.vision.min_height_m, COLLISION_BAND_M[1])
    ref.user = RouteFollower(
        world.route, ref.state, w, cfg.user, rng_user, sight, rng_vision, world.route
    )
    assert np.array_equal(a, truth(ref, 15.0))
    assert asdict(cfg)["user_profile"] is None


def test_a_profile_changes_the_walk_and_is_reproducible():
    world = load_world("thesis-course")
    cfg = SimConfig(seed=3, user_profile=UserProfile.sample(3))
    a = truth(Simulator(world, cfg), 15.0)
    assert np.array_equal(a, truth(Simulator(world, cfg), 15.0))
    assert not np.array_equal(a, truth(Simulator(world, SimConfig(seed=3)), 15.0))
    assert cfg.to_dict()["user_profile"] == asdict(UserProfile.sample(3))
