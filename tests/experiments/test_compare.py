"""`walkerslam compare`: one row per run in CSV and SQLite, a summary, a report."""

import csv
import json
import sqlite3

import numpy as np
import pytest

from experiments.compare import COLUMNS, compare, is_stochastic, parse_localizers
from experiments.run import simulate_trial
from slam.measurement import BEARING_SIGMA_RAD


@pytest.fixture(scope="module")
def two_logs(tmp_path_factory):
    d = tmp_path_factory.mktemp("cmp")
    paths = []
    for seed in (0, 1):
        p = d / f"trial{seed}.mcap"
        simulate_trial("corner", p, seed=seed, duration_s=8.0)
        paths.append(p)
    return paths


def test_compare_writes_csv_db_and_report(two_logs, tmp_path):
    res = compare(two_logs, ["dead-reckoning", "ekf-slam"], seeds=3, out_dir=tmp_path)
    # deterministic localizers run once per log, whatever --seeds says
    assert len(res.rows) == 4
    with open(tmp_path / "results.csv") as f:
        rows = list(csv.DictReader(f))
    assert tuple(rows[0]) == COLUMNS
    assert {(r["log"], r["localizer"]) for r in rows} == {
        (f"trial{s}", loc) for s in (0, 1) for loc in ("dead-reckoning", "ekf-slam")
    }
    assert all(float(r["ate_rmse_m"]) >= 0 for r in rows)
    assert all(r["relations_trans_mean_m"] == "" for r in rows)  # no relations in these logs
    db = sqlite3.connect(tmp_path / "results.db")
    stored = db.execute("SELECT localizer, config, ate_rmse_m FROM runs").fetchall()
    assert len(stored) == 4
    assert json.loads(stored[0][1])["localizer"] == stored[0][0]
    report = (tmp_path / "report.md").read_text()
    assert "| trial0 | ekf-slam | 1 |" in report
    # a second comparison into the same folder replaces, not appends
    compare(two_logs[:1], ["dead-reckoning"], seeds=1, out_dir=tmp_path)
    db = sqlite3.connect(tmp_path / "results.db")
    assert db.execute("SELECT COUNT(*) FROM runs").fetchone()[0] == 1


def test_localizer_names():
    assert "dead-reckoning" in parse_localizers("all")
    assert parse_localizers("gtsam, dead-reckoning") == ["gtsam", "dead-reckoning"]
    with pytest.raises(ValueError, match="valid:"):
        parse_localizers("dead-reckoning,magic")
    assert not is_stochastic("dead-reckoning")


def test_compare_datasets_per_robot_with_mean_over_robots(tmp_path):
    """`compare --format mrclam --robot 1,2` runs each robot as a log and adds a row with
    the mean over robots of each localizer."""
    from typer.testing import CliRunner

    from experiments.cli import app
    from tests.hardware.datasets.datasets_testdata import write_mrclam

    folder = write_mrclam(tmp_path / "mrclam")
    out = tmp_path / "cmp"
    args = ["compare", str(folder), "--format", "mrclam", "--robot", "1,2"]
    res = CliRunner().invoke(app, [*args, "--localizers", "dead-reckoning", "--out", str(out)])
    assert res.exit_code == 0, res.output
    with open(out / "results.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["log"] for r in rows] == ["mrclam_robot1", "mrclam_robot2"]
    ates = [float(r["ate_rmse_m"]) for r in rows]
    report = (out / "report.md").read_text()
    mean_row = next(line for line in report.splitlines() if line.startswith("| mean over logs"))
    assert f"| {np.mean(ates):.3f} ± {np.std(ates):.3f} |" in mean_row
    # dataset options without --format are refused in one line
    res = CliRunner().invoke(app, ["compare", str(folder), "--robot", "1", "--out", str(out)])
    assert res.exit_code == 2 and "need --format" in res.output


def test_set_changes_a_nested_localizer_field_in_compare_and_replay(two_logs, tmp_path):
    """`--set ekf-slam.noise.brake_aware=true` reaches the localizer's config (recorded per
    run); a field that does not exist is a one-line error naming the fields there are."""
    from typer.testing import CliRunner

    from experiments.cli import app

    args = ["compare", str(two_logs[0]), "--localizers", "ekf-slam", "--out", str(tmp_path)]
    res = CliRunner().invoke(app, [*args, "--set", "ekf-slam.noise.brake_aware=true"])
    assert res.exit_code == 0, res.output
    db = sqlite3.connect(tmp_path / "results.db")
    config = json.loads(db.execute("SELECT config FROM runs").fetchone()[0])
    assert config["localizer_config"]["noise"]["brake_aware"] is True
    out = tmp_path / "replay"
    res = CliRunner().invoke(
        app,
        [
            "replay",
            str(two_logs[0]),
            "--localizer",
            "ekf-slam",
            "--out",
            str(out),
            "--set",
            "ekf-slam.noise.wheel_m=0.01",
        ],
    )
    assert res.exit_code == 0, res.output
    replay_config = json.loads((out / "config.json").read_text())
    assert replay_config["localizer_config"]["noise"]["wheel_m"] == 0.01
    res = CliRunner().invoke(app, [*args, "--set", "ekf-slam.noise.bogus=1"])
    assert res.exit_code == 2 and "no field 'bogus'" in res.output


def test_settings_a_dataset_proposes_come_before_set_and_dataset_options_reach_it(tmp_path):
    """MRCLAM's importer proposes its fitted noise levels (metadata "localizer_settings"):
    compare and replay apply them to the fields a localizer has, then --set on top;
    `--dataset-option calibration=none` gives the files' values and no proposals."""
    from typer.testing import CliRunner

    from experiments.cli import app
    from hardware.datasets.mrclam import DATASET1_LOCALIZER_SETTINGS as PROPOSED
    from tests.hardware.datasets.datasets_testdata import write_mrclam

    folder = write_mrclam(tmp_path / "mrclam")
    base = ["--format", "mrclam", "--robot", "1", "--localizers", "ekf-slam,dead-reckoning"]
    out = tmp_path / "cmp"
    args = ["compare", str(folder), *base, "--out", str(out)]
    res = CliRunner().invoke(app, [*args, "--set", "ekf-slam.bearing_sigma_rad=0.02"])
    assert res.exit_code == 0, res.output
    db = sqlite3.connect(out / "results.db")
    configs = {
        loc: json.loads(cfg)["localizer_config"]
        for loc, cfg in db.execute("SELECT localizer, config FROM runs")
    }
    ekf, dr = configs["ekf-slam"], configs["dead-reckoning"]
    assert ekf["bearing_sigma_rad"] == 0.02  # --set wins
    assert ekf["range_sigma_frac"] == PROPOSED["range_sigma_frac"]
    assert (
        ekf["noise"]["omega_floor"] == dr["noise"]["omega_floor"] == PROPOSED["noise.omega_floor"]
    )
    assert "bearing_sigma_rad" not in dr  # only the fields a localizer has
    raw = tmp_path / "raw"
    replay = ["replay", str(folder), "--format", "mrclam", "--robot", "1", "--out", str(raw)]
    res = CliRunner().invoke(
        app, [*replay, "--localizer", "ekf-slam", "--dataset-option", "calibration=none"]
    )
    assert res.exit_code == 0, res.output
    config = json.loads((raw / "config.json").read_text())
    assert config["source_localizer_settings"] == {}
    assert config["recorded_config"]["calibration"] == "none"
    assert config["localizer_config"]["bearing_sigma_rad"] == BEARING_SIGMA_RAD  # the default
    res = CliRunner().invoke(app, [*args, "--dataset-option", "calibration"])
    assert res.exit_code == 2 and "NAME=VALUE" in res.output


def test_a_source_with_scans_and_no_landmarks_proposes_the_scan_modes(tmp_path):
    """An MCAP log of odometry and laser scans (no tags, no range-bearing): replay and
    compare configure gtsam with scan matching and the particle filter with its scans;
    one with tags as well keeps the defaults."""
    from experiments.config import configure
    from experiments.run import source_metadata
    from hardware.calibration import WalkerCalibration
    from hardware.log import LogWriter, read_log
    from hardware.messages import LaserScan, TagDetections, VelocityOdometry
    from slam.base import LOCALIZERS

    def write(path, with_tags):
        with LogWriter(path, WalkerCalibration()) as w:
            for k in range(5):
                w.write(VelocityOdometry(0.1 * k, 0.2, 0.0))
                w.write(LaserScan(0.1 * k + 0.05, -1.0, 0.01, np.full(200, 2.0, np.float32), 20.0))
                if with_tags:
                    w.write(TagDetections(0.1 * k + 0.06))
        return read_log(path)

    laser = source_metadata(write(tmp_path / "laser.mcap", with_tags=False))
    tagged = source_metadata(write(tmp_path / "tagged.mcap", with_tags=True))
    assert configure(LOCALIZERS, "gtsam", laser).config.scan_matching
    assert configure(LOCALIZERS, "particle-filter", laser).config.use_scans
    assert not configure(LOCALIZERS, "gtsam", tagged).config.scan_matching
    assert not configure(LOCALIZERS, "particle-filter", tagged).config.use_scans
    # a --set still wins over the proposal
    assert not configure(LOCALIZERS, "gtsam", laser, {"scan_matching": False}).config.scan_matching
