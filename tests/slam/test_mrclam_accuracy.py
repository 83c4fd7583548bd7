"""Real data: MRCLAM dataset 7, robot 1 (15 min, 15 landmarks, commanded-velocity
odometry that dead-reckons 2.9 m off). A filter whose odometry noise is too small for
such odometry gates away nearly every landmark and stays on the dead-reckoned path; this
guards the velocity noise model and the filters' use of it on real data."""

import pytest

from experiments.run import replay_log
from hardware.datasets import open_dataset
from tests.hardware.datasets.datasets_testdata import data_dir


@pytest.fixture(scope="module")
def robot1():
    return open_dataset("mrclam", data_dir("mrclam_dataset7"), robot=1)


def test_ekf_slam_corrects_mrclam_odometry(robot1, tmp_path):
    dr = replay_log(robot1, tmp_path / "dr", figures=False, reference_map=False).metrics
    ekf = replay_log(
        robot1, tmp_path / "ekf", localizer="ekf-slam", figures=False, reference_map=False
    ).metrics
    diag = ekf["localizer_diagnostics"]
    assert dr["ate_rmse_m"] > 2.0  # the data README: dead reckoning drifts 1-3 m
    assert ekf["ate_rmse_m"] < 0.4  # measured 0.30 m
    assert ekf["landmark_rmse_m"] < 0.3  # measured 0.15 m
    assert diag["gated"] < 0.05 * diag["updates"]  # measured 39 of 2524
