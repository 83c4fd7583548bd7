"""`walkerslam corner-study`: controller parameter sweeps on the corner course (thesis
Figs 6.5–6.8), on a tiny sweep of the open-loop controller's d_max."""

import json
import os
import sqlite3

import numpy as np
import pytest
from typer.testing import CliRunner

import experiments.studies.corner as corner
from experiments.cli import app
from experiments.studies.corner import Pusher, Sweep, parse_sweep
from experiments.studies.engine import run_tasks
from experiments.studies.figures import average_path, resample_by_arclength
from experiments.studies.trial import run_trial
from hardware.sim.dynamics import WalkerParams


def one_line_error(res, needle):
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and needle in lines[0], res.output


@pytest.fixture(scope="module")
def tiny_sweep(tmp_path_factory):
    out = tmp_path_factory.mktemp("corner-study")
    args = ["--sweep", "open-loop.d_max_m=1.25,2.25", "--runs", "2", "--duration", "6"]
    res = CliRunner().invoke(app, ["corner-study", *args, "--workers", "1", "--out", str(out)])
    assert res.exit_code == 0, res.output
    return out, res.output


def test_cli_writes_table_db_figure_and_report(tiny_sweep):
    out, output = tiny_sweep
    db = sqlite3.connect(out / "results.db")
    db.row_factory = sqlite3.Row
    rows = [dict(r) for r in db.execute("SELECT * FROM runs ORDER BY id")]
    assert db.execute("SELECT COUNT(*) FROM paths").fetchone()[0] == 4
    db.close()
    assert len(rows) == 4
    assert [(r["value"], r["run"]) for r in rows] == [(1.25, 0), (1.25, 1), (2.25, 0), (2.25, 1)]
    assert [json.loads(r["controller_config"])["d_max_m"] for r in rows] == [1.25, 1.25, 2.25, 2.25]
    assert len((out / "results.csv").read_text().strip().splitlines()) == 5
    assert len((out / "table.md").read_text().strip().splitlines()) == 2 + 2
    assert (out / "figures" / "corner_open-loop_d_max_m.png").stat().st_size > 10_000
    assert len(list((out / "runs").rglob("*.mcap"))) == 4
    assert "corner_open-loop_d_max_m.png" in (out / "report.md").read_text()
    assert "open-loop.d_max_m" in output
    # each run is the same pusher in every setting: same seed, forces and start pose
    for j in (0, 1):
        same = [r for r in rows if r["run"] == j]
        for key in ("seed", "push_left_n", "push_right_n", "start_pose", "pusher"):
            assert same[0][key] == same[1][key]
        assert 0.9 <= same[0]["push_speed_mps"] <= 1.2
    # braking earlier (larger d_max) turns the walker more
    heading = {
        v: np.mean([r["final_heading_deg"] for r in rows if r["value"] == v]) for v in (1.25, 2.25)
    }
    assert heading[2.25] > heading[1.25]


def test_pusher_is_seeded_and_pushes_at_its_speed():
    assert Pusher.sample(3) == Pusher.sample(3) and Pusher.sample(3) != Pusher.sample(4)
    speeds = [Pusher.sample(s).speed_mps for s in range(200)]
    assert 0.9 <= min(speeds) and max(speeds) <= 1.2
    w = WalkerParams()
    left, right = Pusher(speed_mps=1.0).forces(w)
    assert left == right
    drag = 2 * w.brake_torque_off_nm / w.wheel_radius_m
    assert (left + right - drag) / w.damping == pytest.approx(1.0, abs=1e-4)
    left, right = Pusher(speed_mps=1.0, imbalance=0.02).forces(w)
    assert (right - left) / (right + left) == pytest.approx(0.02, abs=1e-4)


def test_sweep_parsing_types_values_by_the_config_field():
    s = parse_sweep("open-loop.d_max_m=0.75, 1.5")
    assert s == Sweep("open-loop", "d_max_m", (0.75, 1.5))
    assert parse_sweep("open-loop.n_arcs=16,32").values == (16, 32)
    with pytest.raises(ValueError, match=r"has no field 'D' in its config"):
        parse_sweep("open-loop.D=1")
    with pytest.raises(ValueError, match=r"NAME\.FIELD"):
        parse_sweep("d_max_m=1")


def test_average_path_by_arc_length():
    a = np.column_stack([np.linspace(0, 2, 21), np.zeros(21)])
    b = np.column_stack([np.linspace(0, 3, 31), np.full(31, 0.2)])
    avg = average_path([a, b], step=0.1)
    assert len(avg) == 21  # up to the shorter path's length
    assert np.allclose(avg[:, 1], 0.1) and np.allclose(avg[:, 0], np.arange(21) * 0.1)
    r = resample_by_arclength(np.array([[0, 0], [1, 0], [1, 1]]), 0.25)
    assert len(r) == 9 and np.allclose(r[4], [1, 0]) and np.allclose(r[-1], [1, 1])


def test_bad_sweeps_are_one_line_errors(tmp_path, monkeypatch):
    runner = CliRunner()
    out = ["--out", str(tmp_path / "x")]
    one_line_error(runner.invoke(app, ["corner-study", "--sweep", "magic.D=1", *out]), "magic")
    one_line_error(
        runner.invoke(app, ["corner-study", "--sweep", "open-loop.d_max_m=0.3", *out]), "d_max"
    )
    one_line_error(
        runner.invoke(
            app,
            ["corner-study", "--sweep", "open-loop.d_max_m=1", "--set", "none.x=1", *out],
        ),
        "none",
    )
    # default sweeps naming a controller that is not registered: one clear line
    monkeypatch.setattr(corner, "DEFAULT_SWEEPS", (Sweep("not-yet", "D", (9.0, 16.0)),))
    one_line_error(runner.invoke(app, ["corner-study", *out]), "not-yet")
    assert not (tmp_path / "x").exists()


def test_local_process_pool_matches_in_process(tmp_path):
    study = corner.CornerStudy(
        sweeps=(parse_sweep("open-loop.d_max_m=1.75"),), runs=2, duration_s=4.0, keep_logs=False
    )
    specs = corner.plan(study, tmp_path)
    serial = run_tasks(run_trial, specs, workers=1)
    pooled = run_tasks(run_trial, specs, workers=2)
    for a, b in zip(serial, pooled, strict=True):
        assert np.array_equal(a["path"], b["path"]) and a["collisions"] == b["collisions"]
        ma = {k: v for k, v in a["metrics"].items() if k != "wall_time_s"}
        mb = {k: v for k, v in b["metrics"].items() if k != "wall_time_s"}
        assert ma == mb


@pytest.mark.slow
def test_ray_engine_runs_its_local_workers_at_this_process_priority():
    """The local Ray instance's workers run at the caller's niceness, as the process
    pool's do (Ray's default is 15: beside other busy processes such a worker gets a few
    per cent of a core). (A local function: Ray sends it by value.)"""
    pytest.importorskip("ray")

    def niceness(_: int) -> int:
        return os.nice(0)

    assert run_tasks(niceness, [0, 1], engine="ray", workers=2) == [os.nice(0)] * 2
