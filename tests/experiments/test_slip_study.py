"""`walkerslam slip-study` on a tiny study: every run stored with its metrics, the
paired ranking against none (on hand-made rows too), figures, one-line errors, and the
same numbers in this process and from Ray (the local process pool: test_corner_study)."""

import math
import sqlite3

import numpy as np
import pytest
from typer.testing import CliRunner

from experiments.cli import app
from experiments.studies.slip_report import mean_interval, ranking
from experiments.studies.slip_study import METRIC_COLUMNS, SlipStudy, run_slip_study

TINY = [
    "--surface",
    "clean,dusty",
    "--mitigations",
    "none,gyro",
    "--trials",
    "2",
    "--duration",
    "20",
    "--seed",
    "7",
]


def db_rows(path):
    db = sqlite3.connect(path)
    db.row_factory = sqlite3.Row
    rows = [dict(r) for r in db.execute("SELECT * FROM runs ORDER BY id")]
    db.close()
    return rows


@pytest.fixture(scope="module")
def tiny_study(tmp_path_factory):
    """2 users × clean/dusty × none/gyro, dead reckoning, open-loop braking, 20 s each."""
    out = tmp_path_factory.mktemp("slip-study")
    res = CliRunner().invoke(
        app, ["slip-study", *TINY, "--workers", "1", "--no-logs", "--out", str(out)]
    )
    assert res.exit_code == 0, res.output
    return out, res.output


def test_every_run_is_stored_with_its_metrics_and_the_report_ranks(tiny_study):
    out, output = tiny_study
    rows = db_rows(out / "results.db")
    assert len(rows) == 8
    assert {(r["surface"], r["mitigation"]) for r in rows} == {
        (s, m) for s in ("clean", "dusty") for m in ("none", "gyro")
    }
    for r in rows:
        for column in ("ate_rmse_m", "phantom_area_m2", "heading_error_braking_deg"):
            assert r[column] is not None and math.isfinite(r[column])
        assert r["slip_k"] == {"clean": 0.02, "dusty": 0.12}[r["surface"]]
        assert r["log"] is None  # --no-logs
    # the same users in every cell: a user's route is the same without braking changes,
    # and its seed is the study's seed + trial
    assert {(r["trial"], r["seed"]) for r in rows} == {(0, 7), (1, 8)}
    # the gyro removes the heading error that braking adds, on the dusty floor
    dusty = {(r["mitigation"], r["trial"]): r for r in rows if r["surface"] == "dusty"}
    for trial in (0, 1):
        assert (
            dusty[("gyro", trial)]["heading_error_braking_deg"]
            < 0.5 * dusty[("none", trial)]["heading_error_braking_deg"]
        )
    report = (out / "report.md").read_text()
    assert "Ranking of the mitigations" in report and "| dusty | dead-reckoning |" in report
    assert (out / "figures" / "phantom_area_m2.png").stat().st_size > 10_000
    assert "gyro" in output


def test_the_ranking_pairs_users_on_hand_made_rows():
    def row(surface, mitigation, trial, phantom):
        r = {c: None for c in METRIC_COLUMNS}
        r.update(
            surface=surface,
            localizer="dead-reckoning",
            controller="open-loop",
            mitigation=mitigation,
            trial=trial,
            phantom_area_m2=phantom,
        )
        return r

    rows = [
        row("dusty", "none", 0, 4.0),
        row("dusty", "none", 1, 6.0),
        row("dusty", "gyro", 0, 1.0),
        row("dusty", "gyro", 1, 2.0),
        row("dusty", "gyro", 2, 0.0),  # no baseline for this user: not paired
    ]
    (entry,) = ranking(rows)
    p = entry["phantom_area_m2"]
    assert entry["users"] == 2
    assert p["baseline"] == 5.0 and p["difference"] == -3.5 and p["percent"] == -70.0
    assert p["low"] == -4.0 and p["high"] == -3.0  # the two users' differences: −3, −4
    assert math.isnan(entry["ate_rmse_m"]["difference"])  # nothing measured
    m, lo, hi = mean_interval(np.array([1.0, 2.0, 3.0, np.nan]))
    assert m == 2.0 and 1.0 <= lo < 2.0 < hi <= 3.0


def test_bad_input_is_one_line(tmp_path):
    runner = CliRunner()
    for args, needle in (
        (["--mitigations", "none,gyr"], "unknown mitigation 'gyr'"),
        (["--localizers", "dead-reckoning", "--mitigations", "absolute-fix"], "does not apply"),
        (["--mitigations", "calibration"], "--calibration FILE"),
        (["--surface", "icy"], "unknown surface 'icy'"),
        (["--trials", "0"], "trials must be >= 1"),
    ):
        res = runner.invoke(app, ["slip-study", *args, "--out", str(tmp_path / "x")])
        assert res.exit_code == 2, res.output
        assert needle in res.output
        assert not (tmp_path / "x" / "results.db").exists()


@pytest.mark.slow
def test_ray_engine_gives_the_same_results_as_local(tiny_study, tmp_path):
    """One cell of the tiny study (dusty, gyro: its two users) on Ray: the same rows as
    the in-process run's for that cell (a run's numbers depend on its cell and trial only)."""
    study = SlipStudy(
        surfaces=("dusty",),
        mitigations=(("gyro",),),
        trials=2,
        duration_s=20.0,
        seed=7,
        keep_logs=False,
    )
    run_slip_study(study, tmp_path, engine="ray", workers=2)
    remote = db_rows(tmp_path / "results.db")
    local = [r for r in db_rows(tiny_study[0] / "results.db") if r["cell"] == remote[0]["cell"]]
    skip = {"id", "wall_time_s", "replay_realtime_factor", "log", "config"}
    assert len(local) == len(remote) == 2
    assert [r["mitigation"] for r in remote] == ["gyro", "gyro"]
    for a, b in zip(local, remote, strict=True):
        assert {k: v for k, v in a.items() if k not in skip} == {
            k: v for k, v in b.items() if k not in skip
        }
