"""The gyro end to end: `simulate --gyro` records it, a replay fuses it when asked (and
refuses a log without it), and on a dusty open-loop trial gyro-aided dead reckoning
keeps its heading where plain dead reckoning loses it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from experiments.run import replay_log
from experiments.simulation import RunSpec, simulate
from hardware.log import read_log
from hardware.messages import EncoderTicks, GroundTruthPose, GyroRate
from hardware.sim.gyro import GyroSimConfig
from hardware.sim.simulator import SimConfig
from tests.experiments.test_cli import assert_one_line_error, walkerslam

GYRO_ON = "dead-reckoning.noise.gyro.enabled=true"
# what these replays check is the localizer's: no figures, no map metrics
NO_MAP_METRICS = {"figures": False, "drag_metrics": False, "reference_map": False}


def test_simulate_gyro_records_it_and_replay_fuses_it(tmp_path):
    log = tmp_path / "gyro.mcap"
    res = walkerslam("simulate", "-o", log, "--gyro", "--duration", "3", "--seed", "4")
    assert res.returncode == 0, res.stderr
    trial = read_log(log)
    assert trial.topics["/imu/gyro"] is GyroRate
    counts = {}
    for m in trial.messages():
        counts[type(m)] = counts.get(type(m), 0) + 1
    assert counts[GyroRate] == 301 and counts[EncoderTicks] == 151  # 100 Hz and 50 Hz, 3 s
    assert trial.metadata["sim"]["gyro"]["enabled"] is True
    assert set(trial.metadata["gyro"]) == {"part", "turn_on_bias_rad_s", "scale_error"}
    res = walkerslam("replay", log, "--out", tmp_path / "r", "--set", GYRO_ON)
    assert res.returncode == 0, res.stderr
    cfg = json.loads((tmp_path / "r" / "config.json").read_text())
    assert cfg["localizer_config"]["noise"]["gyro"]["enabled"] is True
    metrics = json.loads((tmp_path / "r" / "metrics.json").read_text())
    assert metrics["localizer_diagnostics"]["gyro"]["encoder_fallbacks"] == 0


def test_a_log_without_a_gyro_is_refused_when_the_gyro_is_asked_for(tmp_path):
    log = tmp_path / "plain.mcap"
    res = walkerslam("simulate", "-o", log, "--duration", "1")
    assert res.returncode == 0, res.stderr
    res = walkerslam("replay", log, "--out", tmp_path / "r", "--set", GYRO_ON)
    assert_one_line_error(res, str(log), "no gyro messages", "noise.gyro.enabled")
    assert not (tmp_path / "r").exists()  # nothing was run


@pytest.mark.slow
def test_gyro_aided_dead_reckoning_keeps_its_heading_on_a_dusty_braked_trial(tmp_path):
    """60 s of the thesis course, dusty floor, open-loop braking, seed 0. Measured with
    the blind users: plain dead reckoning 20.8° off at the end, gyro-aided 3.5°, bias to
    4e-4 rad/s; with the goggle-wearing users of 2026-12-02 the final errors are 6.9° and
    5.2° (errors of both signs partly cancel by then), so this checks what the gyro is
    for: the heading error added during braked turns."""
    log = tmp_path / "trial.mcap"
    spec = RunSpec(
        "thesis-course", "open-loop", surface="dusty", seed=0, duration_s=60.0,
        seed_localizer=False, log_path=str(log),
    )  # fmt: skip
    simulate(spec, sim_config=SimConfig(gyro=GyroSimConfig(enabled=True)))
    trial = read_log(log)
    plain = replay_log(trial, tmp_path / "plain", **NO_MAP_METRICS)
    fused = replay_log(
        trial, tmp_path / "gyro", localizer_overrides={"noise.gyro.enabled": True},
        **NO_MAP_METRICS,
    )  # fmt: skip
    # the heading error braking adds (slip over-rotating the odometry), which the gyro's
    # turn does not have
    plain_err = plain.metrics["heading_error_braking_deg"]
    fused_err = fused.metrics["heading_error_braking_deg"]
    assert plain_err > 5.0  # there is slip's heading error to remove
    assert fused_err < 0.4 * plain_err
    assert fused.metrics["ate_rmse_m"] < 0.7 * plain.metrics["ate_rmse_m"]  # 0.22 vs 0.38 m
    gyro = fused.metrics["localizer_diagnostics"]["gyro"]
    bias = trial.metadata["gyro"]["turn_on_bias_rad_s"]
    assert gyro["bias_rad_s"] == pytest.approx(bias, abs=1e-3)
    assert np.isfinite(gyro["scale_error"]) and gyro["encoder_fallbacks"] == 0


def test_a_still_start_holds_the_walker_and_gives_the_gyro_its_bias(tmp_path):
    """`simulate --start-still 2`: the walker stays where it starts for 2 s, then walks;
    the gyro-aided replay learns the turn-on bias from that standstill (no encoder noise
    at rest) to within three times the gyro's white noise over its 1.7 s of windows
    (6.7e-5 rad/s each) plus the bias instability (3.4e-5 rad/s): 2.5e-4 rad/s; the same
    2.4 s walked from the start learn it from moving windows, whose encoder turns are
    quantised (seed 3: 1.0e-4 off after the standstill, 9.4e-4 without)."""
    log = tmp_path / "still.mcap"
    res = walkerslam(
        "simulate", "-o", log, "--gyro", "--duration", "2.4", "--seed", "3", "--start-still", "2"
    )
    assert res.returncode == 0, res.stderr
    trial = read_log(log)
    assert trial.metadata["sim"]["start_still_s"] == 2.0
    truth = np.array(
        [(m.t, m.x, m.y, m.theta) for m in trial.messages() if isinstance(m, GroundTruthPose)]
    )
    still, walking = truth[truth[:, 0] < 2.0], truth[truth[:, 0] > 2.3]
    assert len(still) == 100 and np.ptp(still[:, 1:], axis=0).max() == 0.0
    assert np.hypot(*(walking[-1, 1:3] - still[0, 1:3])) > 0.01  # then the user walks
    fused = replay_log(
        trial, tmp_path / "r", localizer_overrides={"noise.gyro.enabled": True},
        **NO_MAP_METRICS,
    )  # fmt: skip
    gyro = fused.metrics["localizer_diagnostics"]["gyro"]
    bias = trial.metadata["gyro"]["turn_on_bias_rad_s"]
    assert abs(bias) > 0.01  # a bias worth learning (seed 3: -0.04 rad/s)
    assert gyro["bias_rad_s"] == pytest.approx(bias, abs=2.5e-4)
    walked = tmp_path / "walked.mcap"
    assert (
        walkerslam(
            "simulate", "-o", walked, "--gyro", "--duration", "2.4", "--seed", "3"
        ).returncode
        == 0
    )
    moving = replay_log(
        read_log(walked),
        tmp_path / "w",
        localizer_overrides={"noise.gyro.enabled": True},
        **NO_MAP_METRICS,
    ).metrics["localizer_diagnostics"]["gyro"]
    assert abs(moving["bias_rad_s"] - bias) > 3 * abs(gyro["bias_rad_s"] - bias)


def test_a_still_start_longer_than_the_trial_is_a_one_line_error(tmp_path):
    res = walkerslam("simulate", "-o", tmp_path / "x.mcap", "--duration", "2", "--start-still", "5")
    assert_one_line_error(res, "start_still_s", "shorter than the trial")
    assert not (tmp_path / "x.mcap").exists()
