"""The laps of a square in a dead-reckoned path, found without ground truth (for UMBmark,
`slam.umbmark`).

Corners are where the heading turns by more than 45° within 1 m of path; a corner's
centre is where half of its turn is done. A side is the path between two corners of
60–120° whose length (centre to centre) is within 25 % of the square's side; its anchor
is its mid point, with the direction of the line through its middle half (so neither the
corner fillets nor a wobble of the heading count). A lap closes when a side is passed
again four corners later, all turning the same way (the sign is the direction); its
closure is the second pass's anchor in the frame of the first (x along the side, y to
the left, heading). Two sides two such corners apart are opposite: their distance
(anchor to the other's line, both ways, averaged) is the side as the odometry measures
it. Anything else — where a run starts and ends mid-side, a turnaround, a stop — is
skipped.

The passes are kept as sample positions (fractional indices into the path), so that the
same passes can be measured again on the same counts dead-reckoned with another wheel
geometry (`SquareRun.measured`): the closures then change smoothly with the geometry,
which a calibration's iteration needs to settle, while finding the corners again on
quantised counts would move them by fractions of a millimetre.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from hardware.geometry import between

GRID_M = 0.02  # arc-length step at which corners are looked for
CORNER_WINDOW_M = 1.0  # a corner turns by more than CORNER_MIN_RAD within this much path
CORNER_MIN_RAD = math.pi / 4
SQUARE_CORNER_RAD = (math.radians(60.0), math.radians(120.0))
SIDE_TOLERANCE = 0.25  # a side's length (corner to corner) within this share of the side
ANCHOR_SAMPLES = 101  # points of a side's middle half its direction is fitted to (odd)


@dataclass(frozen=True)
class Corner:
    """A turn of the path: arc length where half of it is done, and its signed angle."""

    centre_s: float
    turn_rad: float

    @property
    def square(self) -> bool:
        return SQUARE_CORNER_RAD[0] <= abs(self.turn_rad) <= SQUARE_CORNER_RAD[1]


@dataclass(frozen=True)
class Side:
    """One pass along a side: the fractional sample indices of its middle half (the
    middle one is its mid point)."""

    at: np.ndarray

    def anchor(self, path: np.ndarray) -> np.ndarray:
        """(x, y, φ) of this pass on `path` ((N, 3) poses): mid point, line direction."""
        idx = np.arange(len(path))
        part = np.column_stack([np.interp(self.at, idx, path[:, k]) for k in (0, 1)])
        direction = np.linalg.svd(part - part.mean(axis=0), full_matrices=False)[2][0]
        if direction @ (part[-1] - part[0]) < 0:
            direction = -direction
        x, y = part[len(part) // 2]
        return np.array([x, y, math.atan2(direction[1], direction[0])])


@dataclass(frozen=True)
class Closure:
    """One lap: the next pass of a side in the frame of this pass (x, y, φ)."""

    direction: int  # +1 counter-clockwise, -1 clockwise
    error: np.ndarray
    t: float  # when the lap started


@dataclass(frozen=True)
class Pair:
    """Two passes: a lap (the same side again; direction ±1) or opposite sides (0)."""

    first: Side
    second: Side
    direction: int
    t: float


@dataclass(frozen=True)
class SquareRun:
    """What one path shows of the square: its corners, the pairs of passes, and measured
    on the path: the laps' closures and the opposite sides' distances."""

    corners: list[Corner]
    pairs: list[Pair]
    closures: list[Closure]
    side_separations_m: list[float]

    def closures_of(self, direction: int) -> list[Closure]:
        return [c for c in self.closures if c.direction == direction]

    def measured(self, path: np.ndarray) -> SquareRun:
        """The same passes measured on `path` (the same samples, another geometry)."""
        return SquareRun(self.corners, self.pairs, *_measure(self.pairs, path))


def _measure(pairs: list[Pair], path: np.ndarray) -> tuple[list[Closure], list[float]]:
    closures, separations = [], []
    for p in pairs:
        a, b = p.first.anchor(path), p.second.anchor(path)
        there = between(a, b)
        if p.direction:
            closures.append(Closure(p.direction, there, p.t))
        else:
            separations.append(0.5 * (abs(there[1]) + abs(between(b, a)[1])))
    return closures, separations


def find_corners(theta: np.ndarray) -> list[Corner]:
    """Corners of a heading sampled every GRID_M of path (module docstring)."""
    k = round(0.5 * CORNER_WINDOW_M / GRID_M)
    n = len(theta)
    if n < 2 * k + 2:
        return []
    turn = np.zeros(n)
    turn[k : n - k] = theta[2 * k :] - theta[: n - 2 * k]
    mask = np.abs(turn) > CORNER_MIN_RAD
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(int), [0]])))
    corners = []
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        lo, hi = max(a - k, 0), min(b - 1 + k, n - 1)
        total = theta[hi] - theta[lo]
        done = (theta[lo : hi + 1] - theta[lo]) / total
        j = int(np.argmax(done >= 0.5))  # the half turn, between samples j - 1 and j
        frac = (0.5 - done[j - 1]) / (done[j] - done[j - 1]) if j > 0 else 0.0
        corners.append(Corner((lo + j - 1 + frac) * GRID_M, float(total)))
    return corners


def _turning_one_way(corners: list[Corner], first: int, last: int) -> int:
    """+1 / -1 when corners first..last are all square corners turning left / right,
    else 0."""
    turns = [c.turn_rad if c.square else 0.0 for c in corners[first : last + 1]]
    if all(v > 0 for v in turns):
        return 1
    return -1 if all(v < 0 for v in turns) else 0


def analyse(path: np.ndarray, t: np.ndarray, side_m: float | None) -> SquareRun:
    """The corners, laps and opposite sides of one dead-reckoned path ((N, 3) poses at
    times t); side_m: the side in the path's units (None: the median of the paths
    between square corners)."""
    path, t = np.asarray(path, float), np.asarray(t, float)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(path[:, :2], axis=0).T))])
    grid = np.arange(0.0, s[-1], GRID_M)
    corners = find_corners(np.interp(grid, s, path[:, 2]))
    spans = {
        i: (a.centre_s, b.centre_s)
        for i, (a, b) in enumerate(itertools.pairwise(corners))
        if a.square and b.square
    }
    if not spans:
        return SquareRun(corners, [], [], [])
    side = side_m if side_m is not None else float(np.median([b - a for a, b in spans.values()]))
    index = np.arange(len(path), dtype=float)
    sides = {}
    for i, (s0, s1) in spans.items():
        if abs((s1 - s0) / side - 1.0) <= SIDE_TOLERANCE:
            at = 0.5 * (s0 + s1) + 0.25 * (s1 - s0) * np.linspace(-1.0, 1.0, ANCHOR_SAMPLES)
            sides[i] = Side(np.interp(at, s, index))
    pairs = []
    for i, first in sides.items():
        if i + 2 in sides and _turning_one_way(corners, i + 1, i + 2):
            pairs.append(Pair(first, sides[i + 2], 0, 0.0))
        way = _turning_one_way(corners, i + 1, i + 4)
        if i + 4 in sides and way:
            start = float(np.interp(first.at[ANCHOR_SAMPLES // 2], index, t))
            pairs.append(Pair(first, sides[i + 4], way, start))
    return SquareRun(corners, pairs, *_measure(pairs, path))
