"""The MTRX5700 importer: files, messages, the fitted dead-reckoning reference (on a
synthetic walker whose truth is known, and on the real files: the fixes and the compass
must scatter around it as their headers say), bad input."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from datasets_testdata import (
    MTRX_BEACONS,
    MTRX_SCALE,
    MTRX_START,
    data_dir,
    mtrx_truth,
    write_mtrx5700,
    write_text,
)

from experiments.config import configure
from hardware.datasets import DatasetError, open_dataset
from hardware.datasets.mtrx5700 import COMPASS_SIGMA_RAD, dead_reckon
from hardware.geometry import wrap_angle
from hardware.messages import CompassHeading, GroundTruthPose, PositionFix, VelocityOdometry
from slam.base import LOCALIZERS


def by_type(ds) -> dict[type, list]:
    out: dict[type, list] = {}
    for m in ds.messages():
        out.setdefault(type(m), []).append(m)
    return out


def test_messages_and_metadata(tmp_path):
    ds = open_dataset("mtrx5700", write_mtrx5700(tmp_path / "m", gz=True))
    msgs = by_type(ds)
    assert (
        {k.__name__: len(v) for k, v in msgs.items()}
        == ds.counts()
        == {
            "VelocityOdometry": 900,
            "GroundTruthPose": 900,
            "PositionFix": 113,
            "CompassHeading": 90,
        }
    )
    first = msgs[VelocityOdometry][0]
    assert first.t == pytest.approx(1115116000.462817, abs=1e-6)
    assert all(m.sigma_m == 0.5 for m in msgs[PositionFix])
    headings = np.array([m.heading_rad for m in msgs[CompassHeading]])
    assert np.all(np.abs(headings) <= math.pi) and np.any(headings < 0)  # wrapped
    assert all(m.sigma_rad == COMPASS_SIGMA_RAD for m in msgs[CompassHeading])
    rank = {VelocityOdometry: 0, GroundTruthPose: 1, PositionFix: 2, CompassHeading: 3}
    for a, b in itertools.pairwise(ds.messages()):
        assert a.t < b.t or (a.t == b.t and rank[type(a)] <= rank[type(b)])
    assert ds.metadata["landmarks"] == {str(i): list(xy) for i, xy in enumerate(MTRX_BEACONS)}
    truth = ds.metadata["groundtruth"]
    assert truth["kind"] == "reference" and "NOT ground truth" in truth["note"]
    assert ds.metadata["config"]["initial_pose"] == list(truth["fit"]["start"])


def test_reference_fit_recovers_the_synthetic_walker(tmp_path):
    """The walker moves 0.97× what its velocities say, from a known start; the fit finds
    both from the noisy fixes and headings, and the reference follows the true path."""
    ds = open_dataset("mtrx5700", write_mtrx5700(tmp_path / "m", seed=3))
    fit = ds.metadata["groundtruth"]["fit"]
    assert abs(fit["scale"] - MTRX_SCALE) < 4 * fit["scale_sigma"]
    for got, true, sigma in zip(fit["start"], MTRX_START, fit["start_sigma"], strict=True):
        assert abs(got - true) < 4 * sigma
    msgs = by_type(ds)
    vel = np.array([(m.t, m.v, m.omega) for m in msgs[VelocityOdometry]])
    truth = mtrx_truth(vel[:, 0] - vel[0, 0], vel[:, 1], vel[:, 2])
    ref = np.array([(m.x, m.y, m.theta) for m in msgs[GroundTruthPose]])
    error = np.hypot(*(ref[:, :2] - truth[:, :2]).T)
    assert np.sqrt(np.mean(error**2)) < 3 * fit["reference_sigma_rms_m"]
    assert np.max(np.abs(wrap_angle(ref[:, 2] - truth[:, 2]))) < 0.05
    assert 0.4 < np.mean(fit["fix_residual_std_m"]) < 0.6
    assert 0.2 < fit["compass_residual_std_rad"] < 0.3


def test_without_reference(tmp_path):
    ds = open_dataset("mtrx5700", write_mtrx5700(tmp_path / "m"), reference="none")
    assert GroundTruthPose not in by_type(ds)
    assert ds.metadata["groundtruth"]["kind"] == "none"
    assert ds.initial_pose == (0.0, 0.0, 0.0)
    with pytest.raises(DatasetError, match="reference must be one of"):
        open_dataset("mtrx5700", tmp_path / "m", reference="truth")


def test_it_proposes_compass_and_fix_fusion(tmp_path):
    ds = open_dataset("mtrx5700", write_mtrx5700(tmp_path / "m"))
    for name in ("ekf-slam", "particle-filter", "gtsam", "alpha-blend"):
        built = configure(LOCALIZERS, name, ds.metadata)
        assert built.config.absolute.use_compass and built.config.absolute.use_position, name
        assert built.config.absolute.position_sigma_m == 0.5
    assert configure(LOCALIZERS, "dead-reckoning", ds.metadata).skipped


@pytest.mark.parametrize(
    ("name", "text", "message"),
    [
        ("positionObs.txt", "% h\r\n1115116000 5 1.0\r\n", r"line 2: expected 4 columns, got 3"),
        ("compassObs.txt", "% h\r\n1115116000 1000000 1.0\r\n", r"line 2: time_us must be in"),
        ("compassObs.txt", "% h\r\n1115116000 0.5 1.0\r\n", r"line 2: time_us must be an integer"),
        ("velocityObs.txt", "% h\r\n1115116000 5 0.1 0.0\r\n", r"at least two velocity rows"),
        ("laserFeatures.txt", "% only a header\r\n", r"no data rows"),
    ],
)
def test_bad_files_name_the_file(tmp_path, name, text, message):
    folder = write_mtrx5700(tmp_path / "m")
    bad = write_text(folder / name, text)
    with pytest.raises(DatasetError, match=message) as e:
        open_dataset("mtrx5700", folder)
    assert str(bad) in str(e.value) and "\n" not in str(e.value)


def test_missing_file_and_folder(tmp_path):
    folder = write_mtrx5700(tmp_path / "m")
    (folder / "compassObs.txt").unlink()
    with pytest.raises(DatasetError, match=r"compassObs\.txt: missing file"):
        open_dataset("mtrx5700", folder)
    with pytest.raises(DatasetError, match="missing folder"):
        open_dataset("mtrx5700", tmp_path / "nowhere")


@pytest.mark.data
def test_real_files_scatter_around_the_reference_as_documented():
    """The fixes scatter around the reference with ≈ 0.5 m per axis and the compass with
    ≈ 0.25 rad (the files' headers), with no trend left; the unscaled velocities alone
    drift well beyond that (the reason for the fitted scale)."""
    ds = open_dataset("mtrx5700", data_dir("mtrx5700_stage_sim"))
    assert ds.counts() == {
        "VelocityOdometry": 2839,
        "GroundTruthPose": 2839,
        "PositionFix": 346,
        "CompassHeading": 284,
    }
    assert len(ds.metadata["landmarks"]) == 28
    fit = ds.metadata["groundtruth"]["fit"]
    assert fit["scale"] == pytest.approx(0.9766, abs=0.002)  # 2.3 % over-reported
    assert 0.45 < min(fit["fix_residual_std_m"]) and max(fit["fix_residual_std_m"]) < 0.58
    assert 0.22 < fit["compass_residual_std_rad"] < 0.29
    assert abs(fit["compass_residual_mean_rad"]) < 0.03
    assert fit["reference_sigma_rms_m"] < 0.08
    msgs = by_type(ds)
    ref = np.array([(m.t, m.x, m.y) for m in msgs[GroundTruthPose]])
    fixes = np.array([(m.t, m.x, m.y) for m in msgs[PositionFix]])
    d = fixes[:, 1:] - np.column_stack(
        [np.interp(fixes[:, 0], ref[:, 0], ref[:, i]) for i in (1, 2)]
    )
    for part in np.array_split(d, 8):  # no drift left: each eighth's mean within 4 SE
        assert np.all(np.abs(part.mean(axis=0)) < 4 * 0.5 / math.sqrt(len(part)))
    vel = np.array([(m.t, m.v, m.omega) for m in msgs[VelocityOdometry]])
    raw = dead_reckon(vel[:, 0], vel[:, 1], vel[:, 2], np.array(fit["start"]), 1.0)
    raw_d = fixes[:, 1:] - np.column_stack(
        [np.interp(fixes[:, 0], vel[:, 0], raw[:, i]) for i in (0, 1)]
    )
    assert np.sqrt(np.mean(np.sum(raw_d**2, axis=1))) > 1.5  # vs ≈ 0.75 around the reference
