"""The model twin (hardware.datasets.model_twin; MRCLAM `twin=SEED`): the recorded
schedule, values that follow the localizers' models."""

from __future__ import annotations

import numpy as np
import pytest
from datasets_testdata import assert_same_messages, data_dir, write_mrclam

from experiments.config import configure
from experiments.metrics import ate, landmark_rmse, trajectory_alignment
from hardware.datasets import DatasetError, open_dataset
from hardware.datasets.base import interpolate_poses
from hardware.datasets.model_twin import TwinNoise, true_velocities, twin_odometry
from hardware.datasets.mrclam_fit import truth_table
from hardware.geometry import wrap_angle
from hardware.messages import GroundTruthPose, RangeBearing, VelocityOdometry
from slam.base import LOCALIZERS, create
from slam.motion import apply_increment
from slam.trajectory import Trajectory

QUIET = TwinNoise(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def integrate(odo: np.ndarray, start: np.ndarray) -> np.ndarray:
    """The poses at each row's time, row i's velocities held until row i + 1."""
    poses = [np.asarray(start, float)]
    for (t0, v, w), t1 in zip(odo[:-1].tolist(), odo[1:, 0].tolist(), strict=True):
        poses.append(apply_increment(poses[-1], v * (t1 - t0), w * (t1 - t0)))
    return np.array(poses)


def test_true_velocities_retrace_a_path_of_arcs():
    # arcs of constant speed and turn rate (forward, backward, turning in place, a full
    # turn and more), sampled at 100 Hz; the odometry rows at those times and repeated
    t = np.arange(0.0, 40.0, 0.01)
    v = np.select([t < 10, t < 20, t < 25], [0.3, -0.2, 0.0], 0.25)
    w = np.select([t < 10, t < 20, t < 25], [0.1, 0.0, 1.5], -0.8)
    truth = integrate(np.column_stack([t, v, w]), np.array([1.0, -2.0, 0.5]))
    rows = np.sort(np.concatenate([t, t[::7]]))  # zero-length rows move nothing
    odo = twin_odometry(rows, (t, truth), QUIET, np.random.default_rng(0))
    assert np.array_equal(odo[:, 0], rows)
    again = integrate(odo, truth[0])
    there = interpolate_poses(t, truth, rows)
    assert np.max(np.abs(again[:, :2] - there[:, :2])) < 1e-9
    assert np.max(np.abs(wrap_angle(again[:, 2] - there[:, 2]))) < 1e-9
    turned = np.sum(odo[:-1, 2] * np.diff(rows))  # 7.5 rad in place: more than a turn
    assert turned == pytest.approx(np.unwrap(truth[:, 2])[-1] - truth[0, 2], abs=1e-9)
    # rows outside the truth's span are left out
    rng = np.random.default_rng(0)
    outside = twin_odometry(np.array([-1.0, 0.0, 1.0, 50.0]), (t, truth), QUIET, rng)
    assert outside[:, 0].tolist() == [0.0, 1.0]


@pytest.fixture(scope="module")
def robot1():
    folder = data_dir("mrclam_dataset7")
    return (
        open_dataset("mrclam", folder, robot=1),
        open_dataset("mrclam", folder, robot=1, twin=0),
    )


@pytest.mark.data
def test_twin_keeps_the_recorded_schedule(robot1):
    real, twin = robot1
    truth_t, _ = truth_table(real, "")
    inside = lambda m: truth_t[0] <= m.t <= truth_t[-1]  # noqa: E731
    real_rb = [m for m in real.messages([RangeBearing]) if inside(m)]
    twin_rb = list(twin.messages([RangeBearing]))
    assert [(m.t, m.landmark_id) for m in twin_rb] == [(m.t, m.landmark_id) for m in real_rb]
    real_odo = [m.t for m in real.messages([VelocityOdometry]) if inside(m)]
    assert [m.t for m in twin.messages([VelocityOdometry])] == real_odo
    assert [m.t for m in twin.messages([GroundTruthPose])] == truth_t.tolist()
    counts = {k: len(list(twin.messages([k]))) for k in (VelocityOdometry, RangeBearing)}
    assert twin.counts()["VelocityOdometry"] == counts[VelocityOdometry]
    assert twin.counts()["RangeBearing"] == counts[RangeBearing] == len(real_rb)
    meta = twin.metadata["twin"]
    assert meta["seed"] == 0
    assert meta["sightings_left_out"] == real.counts()["RangeBearing"] - len(real_rb)
    assert meta["odometry_rows_left_out"] == real.counts()["VelocityOdometry"] - len(real_odo)
    assert twin.name.endswith("robot1_twin0")
    # the noise it was drawn with is what the localizers are told, with or without the
    # calibration of the recorded values
    bare = open_dataset("mrclam", data_dir("mrclam_dataset7"), robot=1, calibration="none", twin=0)
    assert bare.metadata["localizer_settings"] == twin.metadata["localizer_settings"]
    assert (
        meta["noise"]["range_sigma_frac"] == twin.metadata["localizer_settings"]["range_sigma_frac"]
    )


@pytest.mark.data
def test_twin_noise_has_the_models_size(robot1):
    _, twin = robot1
    noise = TwinNoise(**twin.metadata["twin"]["noise"])
    truth = truth_table(twin, "")
    rb = list(twin.messages([RangeBearing]))
    pose = interpolate_poses(*truth, np.array([m.t for m in rb]))
    xy = np.array([twin.metadata["landmarks"][str(m.landmark_id)] for m in rb])
    d = xy - pose[:, :2]
    r = np.hypot(d[:, 0], d[:, 1])
    b = np.arctan2(d[:, 1], d[:, 0]) - pose[:, 2]
    zr = (np.array([m.range_m for m in rb]) - r) / (
        noise.range_sigma_m + noise.range_sigma_frac * r
    )
    zb = wrap_angle(np.array([m.bearing_rad for m in rb]) - b) / noise.bearing_sigma_rad
    # 2578 sightings (the sd's standard error 0.014): measured means 0.018 / -0.022, sds
    # 1.007 / 1.025
    for z in (zr, zb):
        assert abs(z.mean()) < 0.06 and abs(z.std() - 1.0) < 0.05
    odo = np.array([(m.t, m.v, m.omega) for m in twin.messages([VelocityOdometry])])
    v, w = true_velocities(odo[:, 0], *truth)
    dt = np.diff(odo[:, 0])
    moving = (dt > 0) & (np.abs(v[:-1]) > 0.01)
    root = np.sqrt(dt[moving])
    zv = (
        (odo[:-1, 1][moving] - v[:-1][moving])
        * root
        / (noise.velocity_frac * np.abs(v[:-1][moving]))
    )
    sw = noise.omega_frac * np.abs(w[:-1][moving]) + noise.omega_floor
    zw = (odo[:-1, 2][moving] - w[:-1][moving]) * root / sw
    # 57024 moving rows: measured means 0.002 / -0.005, sds 0.998 / 0.996
    for z in (zv, zw):
        assert len(z) > 50_000 and abs(z.mean()) < 0.03 and abs(z.std() - 1.0) < 0.02


@pytest.mark.data
def test_twin_is_seeded(robot1):
    _, twin = robot1
    folder = data_dir("mrclam_dataset7")
    again = open_dataset("mrclam", folder, robot=1, twin=0)
    other = open_dataset("mrclam", folder, robot=1, twin=1)
    first = [(m.range_m, m.bearing_rad) for m in twin.messages([RangeBearing])]
    assert [(m.range_m, m.bearing_rad) for m in again.messages([RangeBearing])] == first
    assert [(m.range_m, m.bearing_rad) for m in other.messages([RangeBearing])] != first


@pytest.mark.data
def test_ekf_slam_on_robot3s_twin_is_as_good_as_its_model():
    """On the twin, whose data follow EKF-SLAM's model, the map and the path come out as
    the model's noise allows. Measured (twin seeds 0 / 1): ATE 0.049 / 0.039 m, landmark
    RMSE 0.014 / 0.025 m; on the recorded values 0.047 / 0.032 m (0.074 / 0.054 with
    the speed noise of before 2026-12-03, which the recorded odometry broke)."""
    ds = open_dataset("mrclam", data_dir("mrclam_dataset7"), robot=3, twin=0)
    config = configure(LOCALIZERS, "ekf-slam", ds.metadata).config
    loc = create("ekf-slam", ds.calibration, config, initial_pose=ds.initial_pose)
    truth_t, truth = [], []
    for m in ds.messages():
        if isinstance(m, GroundTruthPose):
            truth_t.append(m.t)
            truth.append((m.x, m.y, m.theta))
        else:
            loc.process(m)
    est, gt = loc.trajectory(), Trajectory(np.array(truth_t), np.array(truth))
    assert ate(est, gt)["ate_rmse_m"] < 0.06
    surveyed = {int(i): xy for i, xy in ds.metadata["landmarks"].items()}
    mapped = {lid: mean for lid, (mean, _) in loc.landmarks().items()}
    seen = {m.landmark_id for m in ds.messages([RangeBearing])}
    assert set(mapped) == seen
    assert landmark_rmse(mapped, surveyed, trajectory_alignment(est, gt)) < 0.03


@pytest.mark.data
@pytest.mark.parametrize("values", ["odometry", "sightings"])
def test_a_partial_twin_keeps_the_other_recorded_values(robot1, values):
    real, twin = robot1
    part = open_dataset("mrclam", data_dir("mrclam_dataset7"), robot=1, twin=0, twin_values=values)
    assert part.name.endswith(f"robot1_twin0_{values}")
    assert part.metadata["twin"]["values"] == values
    kept, new = (
        (RangeBearing, VelocityOdometry)
        if values == "odometry"
        else (VelocityOdometry, RangeBearing)
    )
    assert_same_messages(list(part.messages([kept])), list(real.messages([kept])))
    assert_same_messages(list(part.messages([new])), list(twin.messages([new])))
    assert (
        part.metadata["twin"][
            "sightings_left_out" if values == "odometry" else "odometry_rows_left_out"
        ]
        == 0
    )


def test_twin_needs_ground_truth_and_an_integer_seed(tmp_path):
    folder = write_mrclam(tmp_path)
    with pytest.raises(DatasetError, match="twin needs ground truth"):
        open_dataset("mrclam", folder, robot=1, groundtruth="none", twin=0)
    with pytest.raises(DatasetError, match="twin must be an integer"):
        open_dataset("mrclam", folder, robot=1, twin="x")
    with pytest.raises(DatasetError, match="twin_values"):
        open_dataset("mrclam", folder, robot=1, twin=0, twin_values="ranges")
    with pytest.raises(DatasetError, match="twin_values=odometry needs twin=SEED"):
        open_dataset("mrclam", folder, robot=1, twin_values="odometry")
    assert open_dataset("mrclam", folder, robot=1, twin="none").metadata.get("twin") is None
    # the synthetic folder's truth spans 999.9-1001.1 s: both landmark sightings are
    # kept; of the odometry, shifted by the calibration's 0.22 s, the rows at 1001.22 not
    ds = open_dataset("mrclam", folder, robot=1, twin=3)
    assert [m.t for m in ds.messages([RangeBearing])] == [1000.2, 1000.9]
    assert [m.t for m in ds.messages([VelocityOdometry])] == pytest.approx([1000.22, 1000.72])
    assert ds.metadata["twin"]["odometry_rows_left_out"] == 2
    assert ds.metadata["twin"]["sightings_left_out"] == 0
