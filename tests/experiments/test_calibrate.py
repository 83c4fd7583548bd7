"""`walkerslam calibrate` and `--calibration FILE`: the wheel geometry recovered from a
simulated UMBmark run (a sighted helper pushing the walker round the `umbmark` course's
taped 4 m square, four laps each way, clean floor, no brakes), the calibration it writes
taken by replay, compare and simulate, and what that does to dead reckoning.

The simulated walker has the dimension table's 0.68 m track and a right wheel 1 % larger
than its left (mean 204 mm), while its software believes the thesis code's 0.64 m and
equal 203 mm wheels: its odometry over-rotates every 90° turn by 5.1°, turns 3.5° right
along every 4 m side and measures distances 0.5 % short.
"""

import json
import math
import sqlite3
from dataclasses import replace

import pytest

from experiments.calibrate import Method, calibrate
from experiments.calibration_override import CalibrationOverride
from experiments.run import replay_log, simulate_trial
from hardware.calibration import WalkerCalibration, load_calibration, save_calibration
from hardware.log import read_log
from hardware.sim.dynamics import WalkerParams
from hardware.sim.simulator import SimConfig
from tests.experiments.test_cli import assert_one_line_error, walkerslam
from tests.slam.square_laps import TRUE, write_log

TRUE_TRACK, TRUE_RATIO, TRUE_MEAN = 0.68, 1.01, 0.204
# the true walker as above; the software's calibration is SimConfig's: 203 mm and 0.64 m.
# Calibration and dead reckoning read the encoders (and the ground truth) alone, and the
# cameras draw from streams of their own: at 1 Hz instead of 10 they change none of this
# file's numbers (the same calibrations to the bit) in ~40 % less time.
MISCALIBRATED = replace(
    SimConfig(),
    walker=replace(WalkerParams(), half_track_m=TRUE_TRACK / 2),
    track_error_m=0.64 - TRUE_TRACK,
    wheel_diameter_ratio_error=TRUE_RATIO - 1.0,
    depth_rate_hz=1,
    tag_rate_hz=1,
)


@pytest.fixture(scope="module")
def umbmark_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("umbmark") / "umbmark.mcap"
    res = simulate_trial(
        "umbmark", path, controller="none", surface="clean", seed=5, duration_s=600.0,
        sim_config=MISCALIBRATED,
    )  # fmt: skip
    assert res.finished_route and res.collisions["total"] == 0
    return path


def test_the_simulated_walker_and_its_software_disagree(umbmark_log):
    trial = read_log(umbmark_log)
    assert trial.calibration.track_m == pytest.approx(0.64)
    assert trial.calibration.wheel_diameter_ratio == 1.0
    assert trial.metadata["sim"]["wheel_diameter_ratio_error"] == pytest.approx(0.01)


@pytest.mark.parametrize("method", [Method.UMBMARK, Method.GROUND_TRUTH])
def test_calibration_recovers_the_true_walker(umbmark_log, tmp_path, method):
    """Measured (seed 5): UMBmark 1.01001 / 0.6804 m / 204.18 mm, ground truth 1.00999 /
    0.6800 m / 204.07 mm. What is left is the simulation's, not the method's: the helper
    keeps the middles of the sides 2.2 mm inside the tape (opposite sides 3.9978 m apart:
    the side's scale is 0.055 % long for UMBmark), and the clean floor's residual brake
    drag makes both wheels slip 0.035 % (every method sees the wheels 0.035 % larger).
    The tolerances are twice that: ratio 0.05 %, track and mean diameter 0.2 % for
    UMBmark (without ground truth), 0.02 % / 0.05 % / 0.1 % with it."""
    res = calibrate([umbmark_log], tmp_path / "cal.json", side_m=4.0, method=method)
    g = res.estimate
    tight = method == Method.GROUND_TRUTH
    assert g.diameter_ratio == pytest.approx(TRUE_RATIO, rel=2e-4 if tight else 5e-4)
    assert g.track_m == pytest.approx(TRUE_TRACK, rel=5e-4 if tight else 2e-3)
    assert g.mean_diameter_m == pytest.approx(TRUE_MEAN, rel=1e-3 if tight else 2e-3)
    # four laps each way, counted from every side that has a pass four corners later
    assert res.before[1].laps == res.before[-1].laps == 11
    # before: the corners' over-rotation closes both ways forward, the drift splits them
    assert res.before[1].mean[0] > 0.15 and res.before[-1].mean[0] > 0.7
    for d in (1, -1):
        assert abs(res.after[d].mean[0]) < 0.01 and abs(res.after[d].mean[2]) < 0.005
    written = load_calibration(res.path)
    assert written.track_m == pytest.approx(g.track_m, rel=1e-12)
    assert written.wheel_diameters_m == pytest.approx((g.left_diameter_m, g.right_diameter_m))
    # the rest is the log's calibration
    assert written.depth_intrinsics == read_log(umbmark_log).calibration.depth_intrinsics


def _final_heading_error_deg(res) -> float:
    est = res.pipeline.localizer.trajectory().poses[-1, 2]
    true = res.pipeline.recorded.groundtruth_trajectory().poses[-1, 2]
    return math.degrees(math.remainder(est - true, 2 * math.pi))


def test_the_calibration_removes_dead_reckonings_systematic_error(umbmark_log, tmp_path):
    """The same miscalibrated walker on thesis-course, clean floor, no brakes (seed 0):
    the log's calibration ends 4.2 m and 51° off (ATE 1.06 m); with the UMBmark file
    0.06 m and 0.1° (ATE 0.03 m) — the error left is the floor's, not the walker's.
    (Measured on the whole route; asserted on its first 100 s.)"""
    cal = calibrate([umbmark_log], tmp_path / "cal.json", side_m=4.0, method=Method.UMBMARK)
    log = tmp_path / "course.mcap"
    simulate_trial(
        "thesis-course", log, controller="none", surface="clean", seed=0, duration_s=100.0,
        sim_config=MISCALIBRATED,
    )  # fmt: skip
    kw = {"figures": False, "reference_map": False, "drag_metrics": False}
    raw = replay_log(log, tmp_path / "raw", **kw)
    fixed = replay_log(
        log, tmp_path / "fixed", calibration=CalibrationOverride.load(cal.path), **kw
    )
    assert raw.metrics["ate_rmse_m"] > 0.3 and abs(_final_heading_error_deg(raw)) > 20
    assert fixed.metrics["ate_rmse_m"] < 0.1 * raw.metrics["ate_rmse_m"]
    assert abs(_final_heading_error_deg(fixed)) < 1.0
    assert fixed.metrics["final_position_error_m"] < 0.1 * raw.metrics["final_position_error_m"]


def test_calibrate_end_to_end_on_a_log(umbmark_log, tmp_path):
    out = tmp_path / "walker.json"
    res = walkerslam("calibrate", umbmark_log, "--side", "4", "-o", out, "--method", "umbmark")
    assert res.returncode == 0, res.stderr
    assert "11 counter-clockwise and 11 clockwise laps; UMBmark closed form" in res.stdout
    assert f"wrote {out}" in res.stdout
    cal = load_calibration(out)
    assert cal.track_m == pytest.approx(TRUE_TRACK, rel=2e-3)
    assert cal.wheel_diameter_ratio == pytest.approx(TRUE_RATIO, rel=5e-4)
    # a log with ground truth is fitted to it unless told otherwise
    res = walkerslam("calibrate", umbmark_log, "-o", tmp_path / "gt.json")
    assert res.returncode == 0 and "least squares against the ground truth" in res.stdout


def test_replay_takes_the_calibration_and_records_it(tmp_path):
    """Synthetic laps (no camera) of the true walker, logged with the thesis calibration:
    replayed with a file of the true geometry, dead reckoning follows the truth."""
    log = tmp_path / "laps.mcap"
    write_log(log, (1, -1), laps=2)
    cal = tmp_path / "walker.json"
    save_calibration(TRUE.applied_to(WalkerCalibration()), cal)
    res = walkerslam("replay", log, "--out", tmp_path / "r", "--calibration", cal)
    assert res.returncode == 0, res.stderr
    config = json.loads((tmp_path / "r" / "config.json").read_text())
    assert config["calibration_override"] == {
        "file": str(cal),
        "odometry": {
            "wheel_diameter_m": TRUE.mean_diameter_m,
            "wheel_diameter_ratio": TRUE.diameter_ratio,
            "track_m": 0.68,
        },
        "replaced": {"wheel_diameter_m": 0.203, "wheel_diameter_ratio": 1.0, "track_m": 0.64},
    }
    plain = walkerslam("replay", log, "--out", tmp_path / "p")
    assert plain.returncode == 0, plain.stderr
    assert json.loads((tmp_path / "p" / "config.json").read_text())["calibration_override"] is None
    with_file = json.loads((tmp_path / "r" / "metrics.json").read_text())
    without = json.loads((tmp_path / "p" / "metrics.json").read_text())
    assert without["ate_rmse_m"] > 0.5 and with_file["ate_rmse_m"] < 0.01


def test_compare_and_simulate_take_the_calibration(tmp_path):
    log = tmp_path / "laps.mcap"
    write_log(log, (1, -1), laps=2)
    cal = tmp_path / "walker.json"
    save_calibration(WalkerCalibration(track_m=0.7), cal)
    res = walkerslam(
        "compare", log, "--localizers", "dead-reckoning", "--out", tmp_path / "c",
        "--calibration", cal,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    with sqlite3.connect(tmp_path / "c" / "results.db") as db:
        (config,) = db.execute("SELECT config FROM runs").fetchone()
    assert json.loads(config)["calibration_override"]["odometry"]["track_m"] == 0.7
    sim = tmp_path / "sim.mcap"
    res = walkerslam(
        "simulate", "-o", sim, "--course", "corner", "--duration", "2", "--calibration", cal
    )
    assert res.returncode == 0, res.stderr
    trial = read_log(sim)
    assert trial.calibration.track_m == 0.7  # what the software believed ...
    assert trial.metadata["sim"]["walker"]["half_track_m"] == 0.32  # ... not the walker
    assert trial.metadata["config"]["calibration_override"]["replaced"]["track_m"] == 0.64


def test_one_line_errors(tmp_path):
    one_way = tmp_path / "ccw.mcap"
    write_log(one_way, (1,))
    assert_one_line_error(
        walkerslam("calibrate", one_way, "-o", tmp_path / "x.json"), "no clockwise laps"
    )
    # the same laps are no laps of a 6 m square
    assert_one_line_error(
        walkerslam("calibrate", one_way, "--side", "6", "-o", tmp_path / "x.json"),
        "ccw.mcap: no laps of a square found",
    )
    no_truth = tmp_path / "no_truth.mcap"
    write_log(no_truth, (1, -1), groundtruth=False)
    assert_one_line_error(
        walkerslam("calibrate", no_truth, "--method", "ground-truth", "-o", tmp_path / "x.json"),
        "no_truth.mcap: no ground truth",
    )
    assert_one_line_error(
        walkerslam("calibrate", no_truth, "--method", "magic", "-o", tmp_path / "x.json"),
        "--method must be one of auto, umbmark, ground-truth",
    )
    assert_one_line_error(
        walkerslam("calibrate", no_truth, "--side", "-4", "-o", tmp_path / "x.json"),
        "--side must be > 0",
    )
    assert_one_line_error(walkerslam("calibrate", tmp_path / "nope.mcap"), "nope.mcap")
    other_encoders = tmp_path / "cpr.json"
    save_calibration(WalkerCalibration(counts_per_rev=1024), other_encoders)
    assert_one_line_error(
        walkerslam("calibrate", no_truth, "--base", other_encoders, "-o", tmp_path / "x.json"),
        "cpr.json: calibrated for 1024 counts per revolution",
    )
    assert_one_line_error(
        walkerslam("replay", no_truth, "--out", tmp_path / "r", "--calibration", other_encoders),
        "cpr.json: calibrated for 1024 counts per revolution",
    )
    bad = tmp_path / "bad.json"
    bad.write_text('{"wheel_diameter_ratio": -1}')
    assert_one_line_error(
        walkerslam("replay", no_truth, "--out", tmp_path / "r", "--calibration", bad),
        "bad.json: not a walker calibration",
    )
    # the synthetic laps without ground truth calibrate by UMBmark alone
    res = walkerslam("calibrate", no_truth, "--side", "4", "-o", tmp_path / "ok.json")
    assert res.returncode == 0 and "UMBmark closed form" in res.stdout, res.stderr
