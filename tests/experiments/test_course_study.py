"""`walkerslam course-study`: Table 6.3 with simulated users, on a tiny study; the paired
design; the change-vs-baseline statistics on hand-made numbers; local and Ray engines."""

import csv
import itertools
import json
import math
import sqlite3

import numpy as np
import pytest
from typer.testing import CliRunner

from experiments.cli import app
from experiments.studies.course import CourseStudy, run_course_study
from experiments.studies.tables import collision_table, percent_change
from hardware.log import read_log
from hardware.sim.user import UserProfile

TINY = ["--controllers", "none,open-loop", "--trials", "2", "--duration", "12", "--seed", "5"]


def db_rows(path):
    db = sqlite3.connect(path)
    db.row_factory = sqlite3.Row
    rows = [dict(r) for r in db.execute("SELECT * FROM runs ORDER BY id")]
    paths = db.execute("SELECT COUNT(*) FROM paths").fetchone()[0]
    db.close()
    return rows, paths


@pytest.fixture(scope="module")
def tiny_study(tmp_path_factory):
    """2 users × none/open-loop × dusty, 12 s each, in this process (the local
    process pool: test_corner_study)."""
    out = tmp_path_factory.mktemp("course-study")
    res = CliRunner().invoke(app, ["course-study", *TINY, "--workers", "1", "--out", str(out)])
    assert res.exit_code == 0, res.output
    return out, res.output


def test_cli_writes_table_db_csv_figures_and_logs(tiny_study):
    out, output = tiny_study
    rows, paths = db_rows(out / "results.db")
    assert len(rows) == 4 and paths == 4
    with (out / "results.csv").open() as f:
        assert len(list(csv.DictReader(f))) == 4
    table = (out / "table.md").read_text().strip().splitlines()
    assert len(table) == 2 + 2  # header, rule, one row per controller
    assert "baseline" in table[2] and "%" in table[3]
    for cell in ("none_dead-reckoning_dusty", "open-loop_dead-reckoning_dusty"):
        assert (out / "figures" / f"paths_{cell}.png").stat().st_size > 10_000
        logs = sorted((out / "runs" / cell).glob("trial*.mcap"))
        assert len(logs) == 2
    assert (out / "figures" / "paths_all.png").exists()
    report = (out / "report.md").read_text()
    assert "Table 6.3" in report and "paired" in report
    assert "open-loop" in output and "vs none (95% CI)" in output
    # every row carries its configuration, seed, user profile and metrics
    r = rows[-1]
    assert r["controller"] == "open-loop" and r["trial"] == 1 and r["seed"] == 6
    assert json.loads(r["controller_config"])["d_max_m"] == 1.25
    assert (
        r["collisions_total"]
        == r["collisions_front"] + r["collisions_side"] + r["collisions_rear_wheel"]
    )
    assert r["sim_time_s"] == pytest.approx(12.0)
    # the kept trial log replays: it has the run's config, user profile and world
    trial = read_log(r["log"])
    assert trial.metadata["config"]["sim"]["user_profile"] == json.loads(r["user_profile"])
    assert "world" in trial.metadata


def test_users_are_the_same_in_every_cell(tiny_study):
    rows, _ = db_rows(tiny_study[0] / "results.db")
    for trial in (0, 1):
        same = [r for r in rows if r["trial"] == trial]
        assert len(same) == 2
        assert len({r["user_profile"] for r in same}) == 1
        assert len({r["seed"] for r in same}) == 1
        profile = json.loads(same[0]["user_profile"])
        assert UserProfile(**profile) == UserProfile.sample(5 + trial)
    assert rows[0]["user_profile"] != rows[1]["user_profile"]


def test_percent_change_on_hand_made_numbers():
    halved = percent_change([1, 2, 1, 3], [2, 4, 2, 6])
    assert halved.percent == pytest.approx(-50.0)
    assert halved.low == pytest.approx(-50.0) and halved.high == pytest.approx(-50.0)
    assert halved.text() == "-50% [-50, -50]"
    assert math.isnan(percent_change([1, 2], [0, 0]).percent)
    assert percent_change([1, 2], [0, 0]).text() == "n/a"
    single = percent_change([1], [2])
    assert single.percent == pytest.approx(-50.0) and math.isnan(single.low)
    assert single.text() == "-50% [no CI: 1 user]"
    with pytest.raises(ValueError):
        percent_change([1, 2], [1])


def test_bootstrap_interval_matches_exact_enumeration():
    """With 4 users all 4⁴ resamples can be enumerated: the bootstrap's percentiles must
    match the exact distribution's (up to the Monte Carlo error of 10 000 draws)."""
    treated, baseline = np.array([0, 1, 2, 3.0]), np.array([2, 1, 3, 2.0])
    ch = percent_change(treated, baseline)
    assert ch.percent == pytest.approx(100 * (6 / 8 - 1))
    exact = [
        100 * (treated[list(i)].sum() / baseline[list(i)].sum() - 1)
        for i in itertools.product(range(4), repeat=4)
    ]
    assert np.percentile(exact, 1.5) <= ch.low <= np.percentile(exact, 3.5)
    assert np.percentile(exact, 96.5) <= ch.high <= np.percentile(exact, 98.5)
    assert ch.low <= ch.percent <= ch.high
    assert percent_change(treated, baseline) == ch  # seeded: reproducible


def test_collision_table_pairs_users_by_trial():
    def row(ctl, trial, f, s, r, surface="dusty"):
        return {
            "controller": ctl,
            "localizer": "dead-reckoning",
            "surface": surface,
            "trial": trial,
            "collisions_front": f,
            "collisions_side": s,
            "collisions_rear_wheel": r,
            "collisions_total": f + s + r,
            "finished_route": trial == 0,
        }

    rows = [
        row("open-loop", 1, 0, 1, 1),
        row("none", 0, 1, 0, 3),
        row("open-loop", 0, 0, 0, 2),
        row("none", 1, 0, 0, 4),
        row("none", 0, 0, 0, 1, surface="clean"),
    ]
    table = collision_table(rows)
    assert [(e["surface"], e["controller"]) for e in table] == [
        ("dusty", "open-loop"),
        ("dusty", "none"),
        ("clean", "none"),
    ]
    ol, none = table[0], table[1]
    assert ol["trials"] == 2 and ol["front"] == 0 and ol["side"] == 0.5 and ol["total"] == 2.0
    assert (ol["sum_front"], ol["sum_side"], ol["sum_rear_wheel"]) == (0, 1, 3)
    assert none["total"] == 4.0 and none["change"] is None and none["finished"] == 0.5
    assert ol["change"].percent == pytest.approx(-50.0)
    assert ol["change"] == percent_change([2, 2], [4, 4])  # paired by trial, not by order
    assert table[2]["change"] is None


def test_bad_input_is_one_line(tmp_path):
    runner = CliRunner()
    for args, needle in (
        (["--controllers", "none,magic"], "magic"),
        (["--set", "open-loop.d_max_m=abc"], "abc"),
        (["--set", "open-loop.nope=1"], "nope"),
        (["--surface", "mud"], "mud"),
        (["--engine", "spark"], "spark"),
        (["--trials", "0"], "trials"),
    ):
        res = runner.invoke(app, ["course-study", *args, "--out", str(tmp_path / "x")])
        assert res.exit_code == 2, res.output
        lines = [ln for ln in res.output.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("error:") and needle in lines[0]
        assert not (tmp_path / "x" / "results.db").exists()


@pytest.mark.slow
def test_ray_engine_gives_the_same_results_as_local(tiny_study, tmp_path):
    """One cell of the tiny study (open-loop: its two users) on Ray: the same rows as the
    in-process run's for that cell (a run's numbers depend on its cell and trial only)."""
    study = CourseStudy(
        controllers=("open-loop",), trials=2, duration_s=12.0, seed=5, keep_logs=False
    )
    res = run_course_study(study, tmp_path, engine="ray", workers=2)
    remote, _ = db_rows(tmp_path / "results.db")
    local = [r for r in db_rows(tiny_study[0] / "results.db")[0] if r["cell"] == remote[0]["cell"]]
    assert len(remote) == len(local) == len(res.rows) == 2
    assert [r["controller"] for r in remote] == ["open-loop", "open-loop"]
    skip = {"id", "wall_time_s", "log", "config"}
    for a, b in zip(local, remote, strict=True):
        assert {k: v for k, v in a.items() if k not in skip} == {
            k: v for k, v in b.items() if k not in skip
        }
