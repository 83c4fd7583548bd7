"""The simulated users against thesis Table 6.3's manual trials (no braking).

Ten blindfolded-goggle trials without braking had 5 front, 0 side and 20 rear-wheel
collisions: 2.5 per trial, 80 % rear-wheel. The simulated users are modelled from how
such users move (hardware/sim/user.py, user_vision.py), not fitted to that table; this
checks they land where the issue asks: within a factor of two of 2.5 per trial, mostly
rear-wheel, and no more side collisions than front ones (the thesis saw none).
"""

from collections import Counter

import pytest

from experiments.simulation import RunSpec, simulate
from hardware.sim.simulator import SimConfig
from hardware.sim.user import UserProfile

USERS = range(12)
# Without braking nothing the walker senses changes how they move (the cameras draw from
# streams of their own), so the cameras run at 1 Hz instead of 10: the same collisions at
# the same times (seeds 0-2 checked), in ~30 % less time.
CAMERAS_1HZ = SimConfig(depth_rate_hz=1, tag_rate_hz=1)


@pytest.mark.slow
def test_users_without_braking_collide_like_the_thesis_users() -> None:
    kinds: Counter[str] = Counter()
    for seed in USERS:
        run = simulate(
            RunSpec(
                course="thesis-course",
                controller="none",
                seed=seed,
                duration_s=400.0,
                user_profile=UserProfile.sample(seed),
            ),
            sim_config=CAMERAS_1HZ,
        )
        assert run.sim.user.finished, f"user {seed} did not finish the route"
        kinds.update(c.kind for c in run.pipeline.recorded.collisions)
    per_trial = sum(kinds.values()) / len(USERS)
    assert 1.25 <= per_trial <= 5.0, kinds
    assert kinds["rear-wheel"] > 0.5 * sum(kinds.values()), kinds
    assert kinds["side"] <= kinds["front"], kinds
