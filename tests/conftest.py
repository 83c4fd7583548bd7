"""Shared fixtures: a simulated trial with slip, recorded once per test session."""

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
