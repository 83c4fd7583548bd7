"""The CLI as a user meets it: one-line errors on bad input, and the demo end to end."""

import json
import subprocess
import sys

import pytest

from hardware.calibration import WalkerCalibration
from hardware.log import LogWriter
from hardware.messages import EncoderTicks


def walkerslam(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "experiments", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=600,
        check=False,
    )


def assert_one_line_error(res, *needles):
    assert res.returncode == 2, res.stderr
    assert "Traceback" not in res.stderr
    lines = [ln for ln in res.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, res.stderr
    for n in needles:
        assert n in lines[0]


def test_missing_log(tmp_path):
    res = walkerslam("replay", tmp_path / "nope.mcap", "--out", tmp_path / "o")
    assert_one_line_error(res, "nope.mcap")


def test_not_an_mcap_file(tmp_path):
    bad = tmp_path / "notes.mcap"
    bad.write_text("this is not a log\n")
    assert_one_line_error(walkerslam("replay", bad, "--out", tmp_path / "o"), "notes.mcap")


def test_directory_instead_of_file(tmp_path):
    assert_one_line_error(walkerslam("info", tmp_path), str(tmp_path.name))


def _tiny_log(path):
    with LogWriter(path, WalkerCalibration()) as w:
        for k in range(50):
            w.write(EncoderTicks(0.02 * k, 3 * k, 3 * k))


def test_unknown_localizer_lists_valid_names(tmp_path):
    log = tmp_path / "t.mcap"
    _tiny_log(log)
    res = walkerslam("replay", log, "--localizer", "magic", "--out", tmp_path / "o")
    assert_one_line_error(res, "magic", "dead-reckoning")


def test_unknown_course_lists_valid_names(tmp_path):
    res = walkerslam("simulate", "--course", "moon", "-o", tmp_path / "x.mcap")
    assert_one_line_error(res, "moon", "thesis-course", "corner")


def test_truncated_log_replays_what_was_recovered(tmp_path):
    log = tmp_path / "t.mcap"
    with LogWriter(log, WalkerCalibration(), background_flush=False) as w:
        for k in range(500):  # 10 s of log time: a chunk every 0.5 s
            w.write(EncoderTicks(0.02 * k, 3 * k, 3 * k))
    data = log.read_bytes()
    log.write_bytes(data[: int(len(data) * 0.6)])  # cut inside the data section
    res = walkerslam("replay", log, "--out", tmp_path / "o")
    assert res.returncode == 0, res.stderr
    assert "Traceback" not in res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("warning: t.mcap"), res.stderr
    recovered = int(lines[0].split("recovered ")[1].split()[0])
    metrics = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert metrics["messages"]["EncoderTicks"] == recovered
    assert 200 <= recovered < 500


@pytest.mark.slow
def test_demo_end_to_end(tmp_path):
    res = walkerslam("demo", "--out", tmp_path / "demo", "--duration", "40")
    assert res.returncode == 0, res.stderr
    out = tmp_path / "demo"
    for name in (
        "trial.mcap",
        "trajectory.tum",
        "groundtruth.tum",
        "map.png",
        "map.pgm",
        "map.yaml",
        "metrics.json",
        "config.json",
        "maps_side_by_side.png",
        "trajectory.png",
        "errors.png",
    ):
        assert (out / name).stat().st_size > 0, name
    m = json.loads((out / "metrics.json").read_text())
    for key in (
        "ate_rmse_m",
        "ate_rmse_unaligned_m",
        "rpe_trans_m",
        "final_position_error_m",
        "map_precision",
        "phantom_area_m2",
        "collisions",
        "braking_impulse_nms",
    ):
        assert key in m, key
    # Mapping the same frames at the true poses is at least as precise as at the estimate.
    assert m["reference_map"]["map_precision"] >= m["map_precision"] - 0.02
    assert "maps_side_by_side.png" in res.stdout


def test_a_localizer_without_observations_falls_back_and_says_so(tmp_path):
    """A log with odometry only, replayed with EKF-SLAM: it runs (dead reckoning), says
    so on one warning line and in metrics.json."""
    log = tmp_path / "odo.mcap"
    with LogWriter(log, WalkerCalibration(), background_flush=False) as w:
        for k in range(100):
            w.write(EncoderTicks(0.02 * k, 3 * k, 4 * k))
    res = walkerslam("replay", log, "--localizer", "ekf-slam", "--out", tmp_path / "o")
    assert res.returncode == 0, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "odometry only" in lines[0] and "odo.mcap" in lines[0], res.stderr
    metrics = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert "odometry only" in metrics["localizer_diagnostics"]["note"]
