"""Per-wheel odometry: the vectorised dead reckoning against the localizer, the least-
squares fit to ground truth, and the geometry's round trip through a calibration."""

import numpy as np
import pytest

from hardware.calibration import WalkerCalibration
from hardware.messages import EncoderTicks
from slam.base import create
from slam.wheel_odometry import GroundTruthRun, WheelGeometry, dead_reckon, fit_to_groundtruth
from tests.slam.square_laps import ASSUMED, CPR, TRUE, counts, square_steps, true_poses


def test_dead_reckon_is_the_dead_reckoning_localizer():
    """Random wheel motion with unequal wheels: the same poses as the localizer."""
    rng = np.random.default_rng(4)
    cal = WalkerCalibration(wheel_diameter_m=0.2041, wheel_diameter_ratio=1.013, track_m=0.66)
    c = np.vstack([[0, 0], np.cumsum(rng.integers(-3, 12, size=(400, 2)), axis=0)])
    loc = create("dead-reckoning", cal, initial_pose=(1.0, -2.0, 0.3))
    for k, (left, right) in enumerate(c):
        loc.process(EncoderTicks(0.02 * k, int(left), int(right)))
    expected = loc.trajectory().poses
    got = dead_reckon(c, WheelGeometry.of(cal), cal.counts_per_rev, (1.0, -2.0, 0.3))
    np.testing.assert_allclose(got[:, :2], expected[:, :2], atol=1e-12)
    np.testing.assert_allclose(np.angle(np.exp(1j * (got[:, 2] - expected[:, 2]))), 0, atol=1e-12)


def test_unequal_wheels_in_a_calibration():
    """The mean and ratio give the two diameters; equal wheels are exactly the mean."""
    cal = WalkerCalibration(wheel_diameter_m=0.204, wheel_diameter_ratio=1.01)
    left, right = cal.wheel_diameters_m
    assert (left + right) / 2 == pytest.approx(0.204, rel=1e-15)
    assert right / left == pytest.approx(1.01, rel=1e-15)
    ml, mr = cal.metres_per_count_per_wheel
    assert ml == pytest.approx(np.pi * left / 256) and mr == pytest.approx(np.pi * right / 256)
    equal = WalkerCalibration()
    assert equal.wheel_diameters_m == (equal.wheel_diameter_m, equal.wheel_diameter_m)
    assert equal.metres_per_count_per_wheel == (equal.metres_per_count, equal.metres_per_count)
    g = WheelGeometry.of(cal)
    back = g.applied_to(WalkerCalibration())
    assert back.wheel_diameter_m == pytest.approx(0.204, rel=1e-15)
    assert back.wheel_diameter_ratio == pytest.approx(1.01, rel=1e-15)


@pytest.mark.parametrize("ratio", [0.0, -1.0, float("nan"), True])
def test_a_bad_ratio_is_refused(ratio):
    with pytest.raises(ValueError, match="wheel_diameter_ratio"):
        WalkerCalibration(wheel_diameter_ratio=ratio)


def test_fit_to_groundtruth_recovers_the_geometry():
    """Counts of the true walker driven round a square (one way suffices here: heading
    against distance separates the wheels), fitted to the true poses."""
    ds, dth = square_steps(4.0, 2, 1)
    truth = true_poses(ds, dth)
    exact = fit_to_groundtruth([GroundTruthRun(counts(ds, dth), truth)], ASSUMED, CPR)
    for name in ("left_diameter_m", "right_diameter_m", "track_m"):
        assert getattr(exact, name) == pytest.approx(getattr(TRUE, name), rel=1e-6)
    whole = fit_to_groundtruth([GroundTruthRun(counts(ds, dth, whole=True), truth)], ASSUMED, CPR)
    assert whole.diameter_ratio == pytest.approx(TRUE.diameter_ratio, abs=1e-4)
    assert whole.track_m == pytest.approx(TRUE.track_m, abs=2e-4)
    assert whole.mean_diameter_m == pytest.approx(TRUE.mean_diameter_m, abs=2e-5)


def test_calibration_files_and_logs_without_the_ratio(tmp_path):
    """Calibrations written before the ratio existed read as equal wheels; a file round-
    trips exactly; another file's odometry replaces a log's, but not for other encoders."""
    from hardware.calibration import load_calibration, save_calibration, with_odometry
    from hardware.errors import ConfigError

    old = WalkerCalibration().to_dict()
    del old["wheel_diameter_ratio"]
    assert WalkerCalibration.from_dict(old).wheel_diameter_ratio == 1.0
    cal = WalkerCalibration(wheel_diameter_m=0.2041, wheel_diameter_ratio=1.0123, track_m=0.67)
    assert load_calibration(save_calibration(cal, tmp_path / "c.json")) == cal
    log = WalkerCalibration(tag_size_m=0.2)
    merged = with_odometry(log, cal, "c.json")
    assert WheelGeometry.of(merged) == WheelGeometry.of(cal) and merged.tag_size_m == 0.2
    with pytest.raises(ConfigError, match=r"c\.json: calibrated for 1024 counts per revolution"):
        with_odometry(log, WalkerCalibration(counts_per_rev=1024), "c.json")
