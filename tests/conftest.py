"""Shared fixtures: a simulated trial with slip, recorded once per test session, and a
local Ray instance for the studies' Ray engine."""

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def course_trial(tmp_path_factory) -> Path:
    """The whole thesis-course route (about 3 minutes: out around the room, into the
    centre and back past the same tags) on a dusty floor with open-loop braking, seed 2."""
    from experiments.run import simulate_trial

    path = tmp_path_factory.mktemp("trial") / "course.mcap"
    simulate_trial(
        "thesis-course", path, controller="open-loop", surface="dusty", seed=2, duration_s=300.0
    )
    return path


@pytest.fixture
def local_ray(monkeypatch):
    """A local Ray instance of two CPUs for one test, shut down after it. Its workers run
    at the test's priority: Ray starts them at niceness 15, and beside the other test
    workers on two cores they then get a few per cent of a core (the course study's two
    runs: 1.9 s on an idle machine, 66 s beside three busy loops, 8 s at niceness 0)."""
    ray = pytest.importorskip("ray")
    monkeypatch.setenv("RAY_worker_niceness", "0")  # read by the raylet ray.init starts
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        yield ray
    finally:
        ray.shutdown()
