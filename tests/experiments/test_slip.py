"""Thesis Fig 6.1: dead reckoning curves toward the braked wheel, far more on a dusty floor."""

import pytest

from experiments.slip import straight_push


@pytest.fixture(scope="module")
def pushes():
    return {
        (surface, brakes): straight_push(surface, brakes, seed=3)
        for surface in ("clean", "dusty")
        for brakes in ("none", "left", "right")
    }


@pytest.mark.parametrize("surface", ["clean", "dusty"])
def test_unbraked_push_stays_straight(pushes, surface):
    r = pushes[(surface, "none")]
    end = r.end_in_start_frame(r.truth)
    assert end[0] > 5.9 and abs(end[1]) < 0.01
    assert abs(r.lateral_drift_m) < 0.03


@pytest.mark.parametrize("surface", ["clean", "dusty"])
def test_dead_reckoning_curves_toward_the_braked_wheel(pushes, surface):
    left, right = pushes[(surface, "left")], pushes[(surface, "right")]
    # the walker really went (nearly) straight: it was pushed along the line
    assert abs(left.end_in_start_frame(left.truth)[1]) < 0.1
    assert left.lateral_drift_m > 0.1
    assert right.lateral_drift_m < -0.1
    assert left.end_in_start_frame(left.dead_reckoning)[2] > 0.03  # heading turned left


def test_dusty_floor_slips_several_times_more_than_clean(pushes):
    for brakes in ("left", "right"):
        dusty = abs(pushes[("dusty", brakes)].lateral_drift_m)
        clean = abs(pushes[("clean", brakes)].lateral_drift_m)
        assert dusty > 3.0 * clean


def test_unknown_brake_setting():
    with pytest.raises(ValueError, match="valid: none, left, right, both"):
        straight_push("clean", "front")
