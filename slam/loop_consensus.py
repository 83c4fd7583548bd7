"""Loop closures accepted together when each alone would be turned away.

A scan-based graph (slam.scan_graph) searches each new scan's loop closures around
its estimate and accepts one when its match is strong enough (the loop gate's inlier
fraction) and agrees with the estimate (a chi-squared gate on the graph's relative
covariance). On a revisit after a stretch that drifted, the matches against the old
scans can be right and still be turned away: the overlap is partial (inlier fractions
of 0.3-0.5) and the graph, which has not seen the drift, is sure of itself (fhw's
revisit at t ≈ 1670 s: a dozen matches against five old scans, all saying the walker
is 0.8 m and 1-3° from its estimate, rejected one by one; BENCHMARKS.md). The same
holds for the matches of candidates chosen by what they saw (slam.scan_overlap) rather
than by how near they are: found through the estimate's picture of the walls, each
alone could be a look-alike (seattle: one 1.15 m and 16° off broke the map), so they
are only ever added this way.

Such matches are held instead of dropped when a looser `gate` accepts them, each with
the correction C it implies (the SE(2) transform with implied pose = C ∘ estimate). When
at least `min_matches` held matches, from at least `min_scans` new scans and
`min_candidates` old submaps, imply the same correction — each moves the newest scan's
estimate to within agree_m and agree_rad of where their median moves it — they are
added together: independent matches agreeing with each other is the evidence a single
match lacked (the idea of pairwise consistency maximisation, Mangelson et al. 2018,
for a graph that grows online). Held matches older than `window` kept scans are
dropped, and all of them once a loop closure has moved the estimate they were measured
against.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from hardware.geometry import compose, inverse, wrap_angle
from slam.scan_matching import Acceptance, MatchResult


@dataclass(frozen=True)
class LoopConsensus:
    """Settings (module docstring); min_matches 0 turns it off."""

    min_matches: int = 3
    min_scans: int = 2
    min_candidates: int = 2
    agree_m: float = 0.15
    agree_rad: float = math.radians(2.0)
    window: int = 10
    # looser than the loop gate on inliers (0.3 against 0.5), stricter on ambiguity
    # (0.5 against 0.9) and on how well the match pins the position (0.1 against 0)
    gate: Acceptance = field(
        default_factory=lambda: Acceptance(
            min_inlier_fraction=0.3,
            max_conflict_fraction=0.1,
            max_ambiguity=0.5,
            min_constraint=0.1,
        )
    )

    def __post_init__(self) -> None:
        if self.min_matches < 0 or self.min_scans < 1 or self.min_candidates < 1:
            raise ValueError("need min_matches >= 0, min_scans >= 1 and min_candidates >= 1")
        if not (self.agree_m > 0 and self.agree_rad > 0 and self.window >= 1):
            raise ValueError("need agree_m > 0, agree_rad > 0 and window >= 1")


@dataclass(frozen=True, eq=False)
class HeldMatch:
    """A loop match turned away by the loop gates and held: the old and new kept scans
    (their indices and keyframes), the match, and the correction it implies."""

    old_scan: int
    new_scan: int
    old_kf: int
    new_kf: int
    result: MatchResult
    correction: np.ndarray


def correction(old_pose: np.ndarray, match_pose: np.ndarray, new_pose: np.ndarray) -> np.ndarray:
    """C with C ∘ new_pose = old_pose ∘ match_pose: how the match says the estimate of the
    new scan (world pose new_pose) must move."""
    return compose(compose(old_pose, match_pose), inverse(new_pose))


class HeldMatches:
    """The held matches of a graph's recent scans and the test for their consensus."""

    def __init__(self, config: LoopConsensus) -> None:
        self.config = config
        self._held: list[HeldMatch] = []

    def __len__(self) -> int:
        return len(self._held)

    def hold(self, match: HeldMatch) -> None:
        self._held.append(match)

    def clear(self) -> None:
        self._held.clear()

    def consensus(self, newest_scan: int, newest_pose: np.ndarray) -> list[HeldMatch]:
        """The held matches that agree (module docstring), or [] when too few do; drops
        the ones older than the window first. The agreeing ones leave the buffer."""
        cfg = self.config
        self._held = [h for h in self._held if newest_scan - h.new_scan <= cfg.window]
        if cfg.min_matches == 0 or len(self._held) < cfg.min_matches:
            return []
        moved = np.array([compose(h.correction, newest_pose) for h in self._held])
        centre = np.median(moved[:, :2], axis=0)
        heading = float(np.angle(np.mean(np.exp(1j * moved[:, 2]))))
        near = (np.hypot(*(moved[:, :2] - centre).T) <= cfg.agree_m) & (
            np.abs(wrap_angle(moved[:, 2] - heading)) <= cfg.agree_rad
        )
        agreeing = [h for h, ok in zip(self._held, near, strict=True) if ok]
        if (
            len(agreeing) < cfg.min_matches
            or len({h.new_scan for h in agreeing}) < cfg.min_scans
            or len({h.old_scan for h in agreeing}) < cfg.min_candidates
        ):
            return []
        self._held = [h for h, ok in zip(self._held, near, strict=True) if not ok]
        return agreeing
