"""Loop matches turned away one by one, added together when they agree
(slam.loop_consensus)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hardware.geometry import compose, inverse, wrap_angle
from slam.loop_consensus import HeldMatch, HeldMatches, LoopConsensus, correction
from slam.scan_matching import MatchResult

DRIFT = np.array([0.5, -0.3, math.radians(2.0)])  # the stretch's estimate is this far off


def _result() -> MatchResult:
    return MatchResult(np.zeros(3), np.eye(3) * 1e-4, 0.4, 40, 100, 0.02, 10, True)


def _held(old_scan, new_scan, new_pose, drift=DRIFT, seed=0):
    """A match of new scan (estimated at new_pose) against an old scan that says the
    truth is drift ∘ new_pose, with a little noise."""
    rng = np.random.default_rng(seed)
    old_pose = np.array([3.0 * old_scan, 1.0, 0.1 * old_scan])
    truth = compose(drift, new_pose) + rng.normal(0.0, [0.01, 0.01, 0.002])
    match_pose = compose(inverse(old_pose), truth)
    fix = correction(old_pose, match_pose, new_pose)
    return HeldMatch(old_scan, new_scan, old_scan, 100 + new_scan, _result(), fix)


def _pose(k):
    return np.array([20.0 + 0.5 * k, 5.0 + 0.1 * k, 0.3 + 0.01 * k])


def test_the_correction_moves_the_estimate_to_where_the_match_puts_it():
    old, new = np.array([2.0, -1.0, 0.4]), np.array([7.0, 3.0, -1.2])
    match_pose = np.array([4.0, 2.5, -1.5])
    fix = correction(old, match_pose, new)
    np.testing.assert_allclose(compose(fix, new), compose(old, match_pose), atol=1e-12)


def test_matches_that_agree_from_several_scans_and_submaps_are_taken_together():
    held = HeldMatches(LoopConsensus())
    for k, (old, new) in enumerate([(10, 40), (15, 40), (10, 41)]):
        held.hold(_held(old, new, _pose(new), seed=k))
    # one that disagrees (the wrong corridor) is left behind
    held.hold(_held(20, 41, _pose(41), drift=np.array([1.5, 0.0, 0.0])))
    agreeing = held.consensus(41, _pose(41))
    assert sorted((h.old_scan, h.new_scan) for h in agreeing) == [(10, 40), (10, 41), (15, 40)]
    assert len(held) == 1
    # each says the newest scan's estimate must move by the drift
    for h in agreeing:
        moved = compose(h.correction, _pose(41))
        np.testing.assert_allclose(moved[:2], compose(DRIFT, _pose(41))[:2], atol=0.05)
        assert abs(wrap_angle(moved[2] - compose(DRIFT, _pose(41))[2])) < 0.01


@pytest.mark.parametrize(
    ("pairs", "why"),
    [
        ([(10, 40), (15, 40), (20, 40)], "one new scan"),
        ([(10, 40), (10, 41), (10, 42)], "one old scan"),
        ([(10, 40), (15, 41)], "two matches"),
    ],
)
def test_too_little_agreement_adds_nothing(pairs, why):
    held = HeldMatches(LoopConsensus())
    for k, (old, new) in enumerate(pairs):
        held.hold(_held(old, new, _pose(new), seed=k))
    assert held.consensus(42, _pose(42)) == [], why
    assert len(held) == len(pairs)


def test_held_matches_expire_after_the_window():
    held = HeldMatches(LoopConsensus(window=10))
    for k, (old, new) in enumerate([(10, 40), (15, 40), (10, 41)]):
        held.hold(_held(old, new, _pose(new), seed=k))
    assert held.consensus(52, _pose(52)) == [] and len(held) == 0


def test_off_and_bad_settings():
    held = HeldMatches(LoopConsensus(min_matches=0))
    for k, (old, new) in enumerate([(10, 40), (15, 40), (10, 41)]):
        held.hold(_held(old, new, _pose(new), seed=k))
    assert held.consensus(41, _pose(41)) == []
    with pytest.raises(ValueError, match="agree_m"):
        LoopConsensus(agree_m=0.0)
