"""UMBmark for a pushed walker: wheel diameters and track from laps of a taped square.

Borenstein & Feng (1996) drive a robot around a square of side L by its own odometry,
clockwise (CW) and counter-clockwise (CCW), and measure where it really stops. Here the
roles are swapped: a helper pushes the walker along a square taped on the floor (the
truth is the square) and odometry shows the error. Two systematic errors dominate:

- E_b, the track: every true turn dθ is seen as (1 + ε)·dθ. At each 90° corner the
  odometry over-rotates by α = ε·π/2 (CCW: to the left; CW: to the right).
- E_d, the wheel diameter ratio: on every true metre the odometry turns left by κ; over
  a side it gains β = κ·L (the same way in both directions).

The closure of a lap: the pose where the walker passes the middle of a side again, in
the frame of its previous pass (x along the side, y to the left). To first order
(Δp = J ∫ δθ(s) u(s) ds over the lap, J the +90° rotation, δθ(s) the heading error
gathered since the start, u the true direction) a lap that starts and ends mid-side
gives

    x_ccw = 2L(α + β),   x_cw = 2L(α − β),   y ≈ 0,

so α = (x_cw + x_ccw) / 4L and β = (x_ccw − x_cw) / 4L — the paper's formulas with the
opposite sign, because here the odometry, not the robot, makes the error. The centres of
gravity of the CW and CCW closures give α and β. With c = true / assumed diameter, b the
assumed track and k the scale (true / odometric distance):

    1/c_R − 1/c_L = β·b / L,   (1/c_R + 1/c_L) / 2 = 1/k,   b_true = b·k·(1 + 2α/π).

k comes from a known distance: the square's side against the odometric distance between
the middles of opposite sides (which the corner fillets do not change; over-rotated
corners shorten it to L(1 − α), which is undone). Without it the scale is unknown and
the mean wheel diameter is kept.

The formulas assume sharp corners and small errors, so the estimate is iterated: the
counts are dead-reckoned again with the corrected geometry and the residual closures
corrected, until they vanish. The laps are found again in each step until the
corrections are small (1e-4), then kept (the same samples: `slam.square_run`) so that
the closures change smoothly and the iteration settles exactly. The laps themselves are
found without ground truth (`slam.square_run`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from hardware.errors import CalibrationError
from slam.square_run import SquareRun, analyse
from slam.wheel_odometry import WheelGeometry, dead_reckon

MAX_ITERATIONS = 50
TOLERANCE = 1e-10  # relative change of the geometry at which the iteration stops
FREEZE = 1e-4  # relative change below which the laps found are kept


@dataclass(frozen=True)
class UmbmarkErrors:
    """The systematic errors the closures show (module docstring): α [rad per corner],
    β [rad per side], the scale k (None: unknown) and the side length L used."""

    alpha_rad: float
    beta_rad: float
    scale: float | None
    side_m: float

    def corrected(self, geometry: WheelGeometry) -> WheelGeometry:
        """`geometry` corrected for these errors (an unknown scale keeps the mean
        diameter)."""
        k = 1.0 if self.scale is None else self.scale
        b = geometry.track_m
        c_right = 1.0 / (1.0 / k + 0.5 * self.beta_rad * b / self.side_m)
        c_left = 1.0 / (1.0 / k - 0.5 * self.beta_rad * b / self.side_m)
        track = k * (1.0 + 2.0 * self.alpha_rad / math.pi)
        if self.scale is None:
            d_left, d_right = geometry.left_diameter_m, geometry.right_diameter_m
            keep = (d_left + d_right) / (c_left * d_left + c_right * d_right)
            c_left, c_right, track = c_left * keep, c_right * keep, track * keep
        return geometry.scaled(c_left, c_right, track)


def systematic_errors(assumed: WheelGeometry, true: WheelGeometry, side_m: float) -> UmbmarkErrors:
    """The errors odometry with the `assumed` geometry makes on a walker of the `true`
    one: the over-rotation per 90° turn, the drift per `side_m` of path and the scale
    (the inverse of `UmbmarkErrors.corrected`)."""
    inv_left = assumed.left_diameter_m / true.left_diameter_m  # 1 / c_L
    inv_right = assumed.right_diameter_m / true.right_diameter_m
    mean = 0.5 * (inv_left + inv_right)
    return UmbmarkErrors(
        alpha_rad=0.5 * math.pi * (true.track_m / assumed.track_m * mean - 1.0),
        beta_rad=side_m * (inv_right - inv_left) / assumed.track_m,
        scale=1.0 / mean,
        side_m=side_m,
    )


def centre_of_gravity(runs: Sequence[SquareRun], direction: int) -> np.ndarray:
    """Mean closure (x, y, φ) of the laps in one direction over all runs."""
    errors = [c.error for r in runs for c in r.closures_of(direction)]
    if not errors:
        return np.full(3, np.nan)
    return np.mean(errors, axis=0)


def require_both_directions(runs: Sequence[SquareRun], where: str) -> None:
    """CalibrationError (naming `where`) unless `runs` have laps both ways."""
    counts = {d: sum(len(r.closures_of(d)) for r in runs) for d in (1, -1)}
    if not counts[1] or not counts[-1]:
        missing = "counter-clockwise" if not counts[1] else "clockwise"
        raise CalibrationError(
            f"{where}: no {missing} laps ({counts[1]} counter-clockwise, {counts[-1]} "
            "clockwise): UMBmark needs the square pushed both ways"
        )


def closed_form(runs: Sequence[SquareRun], side_m: float | None) -> UmbmarkErrors:
    """α, β and the scale from the closures and side distances of `runs`; CalibrationError
    without laps in both directions."""
    require_both_directions(runs, "the runs")
    x_ccw, x_cw = centre_of_gravity(runs, 1)[0], centre_of_gravity(runs, -1)[0]
    separation = float(np.mean([d for r in runs for d in r.side_separations_m]))
    # over-rotated corners bring the opposite side nearer by α·L (to first order)
    odometric_side = separation / (1.0 - (x_cw + x_ccw) / (4.0 * separation))
    side = side_m if side_m is not None else odometric_side
    return UmbmarkErrors(
        alpha_rad=float((x_cw + x_ccw) / (4.0 * side)),
        beta_rad=float((x_ccw - x_cw) / (4.0 * side)),
        scale=None if side_m is None else float(side / odometric_side),
        side_m=side,
    )


@dataclass(frozen=True)
class CountsRun:
    """One log's cumulative encoder counts ((N, 2): left, right) at times t."""

    t: np.ndarray
    counts: np.ndarray


@dataclass
class UmbmarkFit:
    """The geometry UMBmark settles on, the errors it removed in its first step (the
    plain closed form), and the laps as seen with the assumed geometry and the result."""

    geometry: WheelGeometry
    first_step: UmbmarkErrors
    iterations: int
    before: list[SquareRun] = field(default_factory=list)
    after: list[SquareRun] = field(default_factory=list)


def analyse_runs(
    runs: Sequence[CountsRun], geometry: WheelGeometry, counts_per_rev: int, side_m
) -> list[SquareRun]:
    """Every run dead-reckoned with `geometry` and its laps found (`square_run.analyse`)."""
    return [analyse(dead_reckon(r.counts, geometry, counts_per_rev), r.t, side_m) for r in runs]


def _relative_change(a: WheelGeometry, b: WheelGeometry) -> float:
    return max(
        abs(b.left_diameter_m / a.left_diameter_m - 1.0),
        abs(b.right_diameter_m / a.right_diameter_m - 1.0),
        abs(b.track_m / a.track_m - 1.0),
    )


def fit_umbmark(
    runs: Sequence[CountsRun],
    assumed: WheelGeometry,
    counts_per_rev: int,
    side_m: float | None,
) -> UmbmarkFit:
    """The UMBmark estimate from laps of a square (module docstring), iterated from the
    `assumed` geometry; side_m: the square's side (None: the scale is not calibrated)."""
    before = analyse_runs(runs, assumed, counts_per_rev, side_m)
    first = closed_form(before, side_m)
    geometry, analysed, frozen, change = assumed, before, False, math.inf
    for iteration in range(1, MAX_ITERATIONS + 1):
        new = closed_form(analysed, side_m).corrected(geometry)
        change, geometry = _relative_change(geometry, new), new
        if change < TOLERANCE:
            after = analyse_runs(runs, geometry, counts_per_rev, side_m)
            return UmbmarkFit(geometry, first, iteration, before, after)
        frozen = frozen or change < FREEZE
        if frozen:
            paths = [dead_reckon(r.counts, geometry, counts_per_rev) for r in runs]
            analysed = [a.measured(p) for a, p in zip(analysed, paths, strict=True)]
        else:
            analysed = analyse_runs(runs, geometry, counts_per_rev, side_m)
    raise CalibrationError(
        f"the UMBmark estimate did not settle in {MAX_ITERATIONS} iterations "
        f"(last change {change:.1e}): the laps do not look like one square"
    )
