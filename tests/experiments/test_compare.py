"""`walkerslam compare`: one row per run in CSV and SQLite, a summary, a report."""

import csv
import json
import sqlite3

import pytest

from experiments.compare import COLUMNS, compare, is_stochastic, parse_localizers
from experiments.run import simulate_trial


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
