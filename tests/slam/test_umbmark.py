"""UMBmark on synthetic laps of a square: the closed form's signs and sizes, exact
recovery of the wheel geometry without noise, and the runs it refuses."""

import math

import numpy as np
import pytest

from hardware.errors import CalibrationError
from slam.square_run import analyse
from slam.umbmark import (
    CountsRun,
    UmbmarkErrors,
    analyse_runs,
    centre_of_gravity,
    closed_form,
    fit_umbmark,
    systematic_errors,
)
from slam.wheel_odometry import WheelGeometry, dead_reckon
from tests.slam.square_laps import ASSUMED, CPR, TRUE, counts, square_steps

SIDE = 4.0


def runs(truth, directions=(1, -1), laps=3, radius=0.5, whole=False):
    out = []
    for d in directions:
        ds, dth = square_steps(SIDE, laps, d, radius=radius)
        c = counts(ds, dth, truth, whole=whole)
        out.append(CountsRun(np.arange(len(c)) * 0.02, c))
    return out


def test_the_true_geometry_closes_every_lap_and_finds_the_square():
    """Dead-reckoned with the geometry that drove it, every lap returns exactly to its
    start, opposite sides are the side apart and each lap is counted from every side."""
    analysed = analyse_runs(runs(TRUE, laps=3), TRUE, CPR, SIDE)
    for r, direction in zip(analysed, (1, -1), strict=True):
        assert len(r.corners) == 12
        assert all(
            math.isclose(c.turn_rad, direction * math.pi / 2, abs_tol=1e-9) for c in r.corners
        )
        # 11 sides between 12 corners; a lap from each side that has one 4 sides later
        assert len(r.closures_of(direction)) == 7 and not r.closures_of(-direction)
        np.testing.assert_allclose([c.error for c in r.closures], 0.0, atol=1e-9)
        np.testing.assert_allclose(r.side_separations_m, SIDE, atol=1e-9)


@pytest.mark.parametrize("direction", [1, -1])
def test_closed_form_signs_and_sizes_for_small_errors(direction):
    """With sharp corners and small errors the closures are the first-order formulas:
    a track error alone closes both directions the same way (x = 2Lα), a wheel ratio
    error alone opposite ways (x = ±2Lβ), and the closed form returns α and β."""
    eps, ratio = 2e-3, 1.0 + 1e-3
    wide = WheelGeometry(0.203, 0.203, 0.64 * (1 + eps))  # over-rotates by ε per turn
    alpha = eps * math.pi / 2  # per 90° corner
    uneven = WheelGeometry(2 * 0.203 / (1 + ratio), 2 * 0.203 * ratio / (1 + ratio), 0.64)
    # the right wheel is larger than assumed: it counts less, the odometry curves right
    beta = SIDE * (1 / uneven.right_diameter_m - 1 / uneven.left_diameter_m) * 0.203 / 0.64
    for truth, a, b in ((wide, alpha, 0.0), (uneven, 0.0, beta)):
        (ccw, cw) = analyse_runs(runs(truth, radius=0.02), ASSUMED, CPR, SIDE)
        x = centre_of_gravity([ccw if direction == 1 else cw], direction)[0]
        assert x == pytest.approx(2 * SIDE * (a + direction * b), rel=0.03, abs=1e-5)
        errors = closed_form([ccw, cw], SIDE)
        size = abs(a) + abs(b)  # the other error is 0 only to first order
        assert errors.alpha_rad == pytest.approx(a, rel=0.03, abs=0.01 * size)
        assert errors.beta_rad == pytest.approx(b, rel=0.03, abs=0.01 * size)


def test_recovers_diameters_and_track_exactly_without_noise():
    """The thesis walker's software (203 mm, 0.64 m) on a walker with 0.68 m track and a
    1 % larger right wheel (mean 204 mm), rounded corners: the iteration lands on the
    true geometry."""
    fit = fit_umbmark(runs(TRUE), ASSUMED, CPR, SIDE)
    g = fit.geometry
    assert g.left_diameter_m == pytest.approx(TRUE.left_diameter_m, rel=1e-7)
    assert g.right_diameter_m == pytest.approx(TRUE.right_diameter_m, rel=1e-7)
    assert g.track_m == pytest.approx(TRUE.track_m, rel=1e-7)
    assert fit.iterations < 20
    for r in fit.after:
        np.testing.assert_allclose([c.error[0] for c in r.closures], 0.0, atol=1e-6)
    # the first, plain closed-form step already points the right way
    assert fit.first_step.alpha_rad > 0 and fit.first_step.beta_rad < 0
    assert fit.first_step.scale == pytest.approx(0.204 / 0.203, rel=0.01)


def test_whole_counts_recover_the_geometry_to_a_fraction_of_a_millimetre():
    fit = fit_umbmark(runs(TRUE, whole=True), ASSUMED, CPR, SIDE)
    assert fit.geometry.mean_diameter_m == pytest.approx(TRUE.mean_diameter_m, abs=5e-5)
    assert fit.geometry.diameter_ratio == pytest.approx(TRUE.diameter_ratio, abs=2e-4)
    assert fit.geometry.track_m == pytest.approx(TRUE.track_m, abs=5e-4)


def test_without_the_side_the_mean_diameter_is_kept():
    fit = fit_umbmark(runs(TRUE), ASSUMED, CPR, None)
    g = fit.geometry
    assert g.mean_diameter_m == pytest.approx(ASSUMED.mean_diameter_m, rel=1e-9)
    assert g.diameter_ratio == pytest.approx(TRUE.diameter_ratio, rel=1e-6)
    # the track in the units of the assumed wheels: true track × assumed / true diameter
    scale = ASSUMED.mean_diameter_m / TRUE.mean_diameter_m
    assert g.track_m == pytest.approx(TRUE.track_m * scale, rel=1e-6)


def test_one_direction_only_is_refused():
    with pytest.raises(CalibrationError, match="no clockwise laps"):
        fit_umbmark(runs(TRUE, directions=(1,)), ASSUMED, CPR, SIDE)


def test_a_path_that_is_no_square_has_no_laps():
    """A circle and a square of another side give no laps (the side is checked)."""
    n = 5000
    circle = np.column_stack([np.full(n, 10.0), np.full(n, 10.0 + 0.64 * 2 * np.pi / 1000)])
    c = np.vstack([[0.0, 0.0], np.cumsum(circle, axis=0)])
    path = dead_reckon(c, ASSUMED, CPR)
    assert not analyse(path, np.arange(len(c)), SIDE).closures
    ds, dth = square_steps(2.5, 3, 1)
    path = dead_reckon(counts(ds, dth, ASSUMED), ASSUMED, CPR)
    assert not analyse(path, np.arange(len(path)), SIDE).closures
    assert len(analyse(path, np.arange(len(path)), 2.5).closures) == 7


def test_systematic_errors_undo_the_correction():
    """The errors a geometry makes against the one its correction gives are the errors."""
    errors = UmbmarkErrors(alpha_rad=0.07, beta_rad=-0.03, scale=1.005, side_m=SIDE)
    corrected = errors.corrected(ASSUMED)
    back = systematic_errors(ASSUMED, corrected, SIDE)
    assert back.alpha_rad == pytest.approx(0.07, rel=1e-12)
    assert back.beta_rad == pytest.approx(-0.03, rel=1e-12)
    assert back.scale == pytest.approx(1.005, rel=1e-12)
    # the thesis walker's software on the true walker: 5.6 deg per turn, 1 % diameters
    truth = systematic_errors(ASSUMED, TRUE, SIDE)
    assert math.degrees(truth.alpha_rad) == pytest.approx(90 * (0.68 / 0.64 / truth.scale - 1))


def test_one_run_both_ways_with_a_turn_on_the_spot():
    """The procedure on the walker: laps counter-clockwise, stop on the mark, turn the
    walker round on the spot (a 180° turn without travel: no corner of a square), laps
    clockwise round the same square, all in one log."""
    ccw, cw = square_steps(SIDE, 3, 1), square_steps(SIDE, 3, -1)
    ds = np.concatenate([ccw[0], np.zeros(100), cw[0]])
    dth = np.concatenate([ccw[1], np.full(100, math.pi / 100), cw[1]])
    c = counts(ds, dth, TRUE)
    fit = fit_umbmark([CountsRun(np.arange(len(c)) * 0.02, c)], ASSUMED, CPR, SIDE)
    (run,) = fit.before
    assert len(run.closures_of(1)) == len(run.closures_of(-1)) == 7
    assert fit.geometry.track_m == pytest.approx(TRUE.track_m, rel=1e-7)
    assert fit.geometry.diameter_ratio == pytest.approx(TRUE.diameter_ratio, rel=1e-7)
