"""`walkerslam replay LOG --controller NAME`: recompute the brake commands on a recorded
trial. With the controller and localizer the trial was recorded with, the replay sees
the messages in the order the closed loop did, so the commands come out the same."""

import json

import numpy as np
import pytest

from experiments.run import replay_log, simulate_trial
from hardware.calibration import WalkerCalibration
from hardware.log import LogWriter
from hardware.messages import EncoderTicks
from tests.experiments.test_cli import walkerslam

OFF = WalkerCalibration().brake.torque_off_nm


@pytest.fixture(scope="module")
def trial(tmp_path_factory):
    path = tmp_path_factory.mktemp("ctl") / "dusty.mcap"
    simulate_trial(
        "thesis-course",
        path,
        controller="open-loop",
        localizer="dead-reckoning",
        surface="dusty",
        seed=1,
        duration_s=30.0,
    )
    return path


def test_round_trip_reproduces_the_logged_commands(trial, tmp_path):
    out = tmp_path / "replay"
    res = walkerslam("replay", trial, "--controller", "open-loop", "--out", out)
    assert res.returncode == 0, res.stderr
    assert "controller replay (open-loop)" in res.stdout
    c = json.loads((out / "metrics.json").read_text())["controller_replay"]
    assert c["controller"] == c["recorded_controller"] == "open-loop"
    assert c["localizer"] == c["recorded_localizer"] == "dead-reckoning"
    assert c["commands"] > 250
    assert c["rms_diff_nm"] < 1e-9 and c["max_abs_diff_nm"] < 1e-9
    assert c["same_side_fraction"] == 1.0
    assert c["recomputed_braking_impulse_nms"] == pytest.approx(c["logged_braking_impulse_nms"])
    assert c["logged_braking_impulse_nms"] > 1.0  # the trial did brake
    rows = np.genfromtxt(out / "controller_replay.csv", delimiter=",", names=True)
    assert len(rows) == c["commands"]
    np.testing.assert_allclose(rows["recomputed_left_nm"], rows["logged_left_nm"], atol=1e-4)
    np.testing.assert_allclose(rows["recomputed_right_nm"], rows["logged_right_nm"], atol=1e-4)
    assert (out / "controller_replay.png").stat().st_size > 0


def test_another_controller_gives_other_commands(trial, tmp_path):
    m = replay_log(trial, tmp_path, controller="none", figures=False, map_figure=False).metrics
    c = m["controller_replay"]
    assert c["controller"] == "none" and c["recorded_controller"] == "open-loop"
    assert c["rms_diff_nm"] > 0.1
    assert c["same_side_fraction"] < 1.0
    assert c["recomputed_braking_impulse_nms"] == pytest.approx(0.0, abs=1e-9)
    rows = np.genfromtxt(tmp_path / "controller_replay.csv", delimiter=",", names=True)
    np.testing.assert_allclose(rows["recomputed_left_nm"], OFF)
    # over-steer compares the recomputed commands with the same controller's at the
    # true pose: a controller that never brakes never requires braking either
    o = m["over_steer"]
    assert o["commands"] == "recomputed" and o["controller"] == "none"
    assert o["over_steer_deg"] == o["under_steer_deg"] == o["required_deg"] == 0.0


def test_unknown_controller_is_a_one_line_error(tmp_path):
    log = tmp_path / "t.mcap"
    with LogWriter(log, WalkerCalibration()) as w:
        for k in range(50):
            w.write(EncoderTicks(0.02 * k, 3 * k, 3 * k))
    res = walkerslam("replay", log, "--controller", "magic", "--out", tmp_path / "o")
    assert res.returncode == 2, res.stderr
    assert "Traceback" not in res.stderr
    lines = [ln for ln in res.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, res.stderr
    assert "magic" in lines[0] and "open-loop" in lines[0]
    assert not (tmp_path / "o").exists()


def test_a_log_without_brake_commands(tmp_path):
    log = tmp_path / "t.mcap"
    with LogWriter(log, WalkerCalibration()) as w:
        for k in range(50):
            w.write(EncoderTicks(0.02 * k, 3 * k, 3 * k))
    m = replay_log(
        log, tmp_path / "o", controller="open-loop", figures=False, map_figure=False
    ).metrics
    assert m["controller_replay"]["commands"] == 0
    assert "over_steer" not in m and "drag" not in m
