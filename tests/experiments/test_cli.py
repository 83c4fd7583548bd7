"""The CLI as a user meets it: one-line errors on bad input, and the demo end to end."""

import contextlib
import importlib
import io
import json
import subprocess
import sys
import traceback

import pytest

from experiments.cli import main
from hardware.calibration import WalkerCalibration
from hardware.log import LogWriter
from hardware.messages import EncoderTicks


def walkerslam(*args, cwd=None, process=False) -> subprocess.CompletedProcess:
    """The `walkerslam` command with `args`: its exit code, standard output and error.

    By default it runs in this process, as `python -m experiments` does (`cli.main` with
    the output captured; an exception main lets out is a traceback on stderr and exit
    code 1, as Python gives): a new process would spend 3-5 s of this machine importing
    and loading compiled kernels before the command starts. process=True runs it as a
    real `python -m experiments` (the tests of what only a process shows)."""
    argv = [str(a) for a in args]
    if process:
        return subprocess.run(
            [sys.executable, "-m", "experiments", *argv],
            capture_output=True,
            text=True,
            cwd=cwd,
            timeout=600,
            check=False,
        )
    out, err = io.StringIO(), io.StringIO()
    with contextlib.ExitStack() as stack:
        if cwd is not None:
            stack.enter_context(contextlib.chdir(cwd))
        stack.enter_context(contextlib.redirect_stdout(out))
        stack.enter_context(contextlib.redirect_stderr(err))
        try:
            code = main(argv)
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
        except Exception:  # a bug: what Python prints for it
            traceback.print_exc()
            code = 1
    return subprocess.CompletedProcess(["walkerslam", *argv], code, out.getvalue(), err.getvalue())


def assert_one_line_error(res, *needles):
    assert res.returncode == 2, res.stderr
    assert "Traceback" not in res.stderr
    lines = [ln for ln in res.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, res.stderr
    for n in needles:
        assert n in lines[0]


def test_missing_log(tmp_path):
    res = walkerslam("replay", tmp_path / "nope.mcap", "--out", tmp_path / "o", process=True)
    assert_one_line_error(res, "nope.mcap")


def test_not_an_mcap_file(tmp_path):
    bad = tmp_path / "notes.mcap"
    bad.write_text("this is not a log\n")
    assert_one_line_error(walkerslam("replay", bad, "--out", tmp_path / "o"), "notes.mcap")


def test_directory_instead_of_file(tmp_path):
    assert_one_line_error(walkerslam("info", tmp_path), str(tmp_path.name))


def _tiny_log(path):
    with LogWriter(path, WalkerCalibration()) as w:
        for k in range(50):
            w.write(EncoderTicks(0.02 * k, 3 * k, 3 * k))


def test_unknown_localizer_lists_valid_names(tmp_path):
    log = tmp_path / "t.mcap"
    _tiny_log(log)
    res = walkerslam("replay", log, "--localizer", "magic", "--out", tmp_path / "o")
    assert_one_line_error(res, "magic", "dead-reckoning")


def test_unknown_course_lists_valid_names(tmp_path):
    res = walkerslam("simulate", "--course", "moon", "-o", tmp_path / "x.mcap")
    assert_one_line_error(res, "moon", "thesis-course", "corner")


def test_truncated_log_replays_what_was_recovered(tmp_path):
    log = tmp_path / "t.mcap"
    with LogWriter(log, WalkerCalibration(), background_flush=False) as w:
        for k in range(500):  # 10 s of log time: a chunk every 0.5 s
            w.write(EncoderTicks(0.02 * k, 3 * k, 3 * k))
    data = log.read_bytes()
    log.write_bytes(data[: int(len(data) * 0.6)])  # cut inside the data section
    res = walkerslam("replay", log, "--out", tmp_path / "o")
    assert res.returncode == 0, res.stderr
    assert "Traceback" not in res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("warning: t.mcap"), res.stderr
    recovered = int(lines[0].split("recovered ")[1].split()[0])
    metrics = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert metrics["messages"]["EncoderTicks"] == recovered
    assert 200 <= recovered < 500


@pytest.mark.slow
def test_demo_end_to_end(tmp_path):
    res = walkerslam("demo", "--out", tmp_path / "demo", "--duration", "40", process=True)
    assert res.returncode == 0, res.stderr
    out = tmp_path / "demo"
    for name in (
        "trial.mcap",
        "trajectory.tum",
        "groundtruth.tum",
        "map.png",
        "map.pgm",
        "map.yaml",
        "metrics.json",
        "config.json",
        "maps_side_by_side.png",
        "trajectory.png",
        "errors.png",
    ):
        assert (out / name).stat().st_size > 0, name
    m = json.loads((out / "metrics.json").read_text())
    for key in (
        "ate_rmse_m",
        "ate_rmse_unaligned_m",
        "rpe_trans_m",
        "final_position_error_m",
        "map_precision",
        "phantom_area_m2",
        "collisions",
        "braking_impulse_nms",
    ):
        assert key in m, key
    # Mapping the same frames at the true poses is at least as precise as at the estimate.
    assert m["reference_map"]["map_precision"] >= m["map_precision"] - 0.02
    assert "maps_side_by_side.png" in res.stdout


def test_a_localizer_without_observations_falls_back_and_says_so(tmp_path):
    """A log with odometry only, replayed with EKF-SLAM: it runs (dead reckoning), says
    so on one warning line and in metrics.json."""
    log = tmp_path / "odo.mcap"
    with LogWriter(log, WalkerCalibration(), background_flush=False) as w:
        for k in range(100):
            w.write(EncoderTicks(0.02 * k, 3 * k, 4 * k))
    res = walkerslam("replay", log, "--localizer", "ekf-slam", "--out", tmp_path / "o")
    assert res.returncode == 0, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "odometry only" in lines[0] and "odo.mcap" in lines[0], res.stderr
    metrics = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert "odometry only" in metrics["localizer_diagnostics"]["note"]


# -- the front door, as a new user found it (issue 11) ---------------------------------


@pytest.fixture(scope="module")
def short_log(tmp_path_factory):
    from experiments.run import simulate_trial

    path = tmp_path_factory.mktemp("front") / "short.mcap"
    simulate_trial("thesis-course", path, seed=1, duration_s=4.0)
    return path


@pytest.mark.parametrize(
    ("sets", "needles"),
    [
        (["gtsam.prior_sigma=1"], ["gtsam.prior_sigma", "3 values"]),
        (["ekf-slam.noise=1"], ["ekf-slam.noise is a group", "noise.wheel_m"]),
        (["gtsam.scan_matching=maybe"], ["gtsam.scan_matching", "maybe"]),
        (["gtsam.nope=1"], ["no field 'nope'"]),
    ],
)
def test_bad_settings_are_one_line_before_the_replay(short_log, tmp_path, sets, needles):
    name = sets[0].split(".")[0]
    args = [a for s in sets for a in ("--set", s)]
    res = walkerslam("replay", short_log, "--localizer", name, "--out", tmp_path / "o", *args)
    assert_one_line_error(res, *needles)
    assert not (tmp_path / "o").exists()  # nothing was run


def test_a_tuple_setting_is_taken_and_recorded(short_log, tmp_path):
    res = walkerslam(
        "replay", short_log, "--localizer", "gtsam", "--out", tmp_path / "o",
        "--set", "gtsam.prior_sigma=0.1,0.1,0.05",
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    cfg = json.loads((tmp_path / "o" / "config.json").read_text())
    assert cfg["localizer_config"]["prior_sigma"] == [0.1, 0.1, 0.05]
    assert cfg["localizer_overrides"] == {"prior_sigma": [0.1, 0.1, 0.05]}
    # the trial's proposal (its encoders' noise) applied, and recorded
    assert "noise.wheel_m" in cfg["source_localizer_settings"]
    assert cfg["source_localizer_settings_skipped"] == {}


def test_an_output_folder_that_is_a_file(short_log, tmp_path):
    taken = tmp_path / "taken"
    taken.write_text("not a folder")
    res = walkerslam("replay", short_log, "--out", taken)
    assert_one_line_error(res, "taken", "is a file")


def test_dataset_options_without_a_format_are_an_error(short_log, tmp_path):
    res = walkerslam("replay", short_log, "--out", tmp_path / "r", "--robot", "2")
    assert_one_line_error(res, "need --format")
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("duration", ["-5", "0"])
def test_simulate_needs_a_positive_duration(tmp_path, duration):
    out = tmp_path / "t.mcap"
    res = walkerslam("simulate", "-o", out, "--duration", duration)
    assert_one_line_error(res, "duration must be > 0")
    assert not out.exists()


def test_simulate_slip_scale_reaches_the_log(tmp_path):
    """Each wheel's slip coefficient is the surface's times its --slip-scale factor; the
    log's metadata has the factors ("sim") and the run's true slip ("slip")."""
    from hardware.log import read_log

    out = tmp_path / "t.mcap"
    res = walkerslam("simulate", "-o", out, "--duration", "3", "--slip-scale", "1.5,0.5")
    assert res.returncode == 0, res.stderr
    meta = read_log(out).metadata
    assert meta["sim"]["slip_scale"] == [1.5, 0.5]
    assert meta["slip"]["k_wheel"] == pytest.approx([0.18, 0.06])
    assert len(meta["slip"]["k_effective"]) == 2
    bad = walkerslam("simulate", "-o", tmp_path / "b.mcap", "--slip-scale", "1,x")
    assert_one_line_error(bad, "--slip-scale")
    bad = walkerslam("simulate", "-o", tmp_path / "b.mcap", "--slip-scale", "1,9")
    assert_one_line_error(bad, "slip_scale right 9.0")
    assert not (tmp_path / "b.mcap").exists()


def test_typer_usage_errors_are_one_line(tmp_path):
    res = walkerslam("simulate", "-o", tmp_path / "t.mcap", "--seed", "abc")
    assert_one_line_error(res, "--seed", "see walkerslam simulate --help")
    assert_one_line_error(walkerslam("replay"), "Missing argument")
    assert_one_line_error(walkerslam("nosuchcommand"), "nosuchcommand")


def test_list_shows_a_configs_settings():
    res = walkerslam("list", "gtsam")
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert any(ln.split()[:3] == ["gtsam.prior_sigma", "(0.001,", "0.001,"] for ln in lines), (
        res.stdout
    )
    assert any("gtsam.noise.brake_aware" in ln and "bool" in ln for ln in lines)
    # below the settings: where each group is explained, classes that exist with docstrings
    start = lines.index("explained in (python -m pydoc CLASS):")
    groups = dict(ln.split() for ln in lines[start + 1 :])
    assert groups["gtsam.*"] == "slam.gtsam_smoother.GtsamConfig"
    assert groups["gtsam.scan.*"] == "slam.scan_graph.SequentialScans"
    assert groups["gtsam.loop.final.gate.*"] == "slam.scan_matching.Acceptance"
    assert len(groups) == 18
    for where in groups.values():
        module, cls = where.rsplit(".", 1)
        assert getattr(importlib.import_module(module), cls).__doc__, where
    assert "grid-rbpf" in walkerslam("list").stdout
    assert_one_line_error(walkerslam("list", "nope"), "nope", "gtsam")


def test_compare_table_is_not_cut_when_piped(short_log, tmp_path):
    res = walkerslam(
        "compare", short_log, "--localizers", "dead-reckoning,particle-filter", "--seeds", "1",
        "--out", tmp_path / "c",
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert "dead-reckoning" in res.stdout and "particle-filter" in res.stdout
    assert "…" not in res.stdout


def test_a_bug_keeps_its_traceback():
    """Only a user's errors are one line: a bug in a command shows the whole traceback."""
    code = (
        "import sys; import experiments.cli as c; from experiments.cli_common import friendly;"
        "f = friendly(lambda: 1 / 0); f()"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 1 and "Traceback" in res.stderr and "ZeroDivisionError" in res.stderr


def test_replay_says_what_it_does_after_the_messages(short_log, tmp_path):
    """The progress display shows the metrics and figures phases instead of stopping at
    the end of the messages for seconds."""
    from experiments.run import replay_log

    phases, times = [], []
    replay_log(short_log, tmp_path / "o", progress=times.append, phase=phases.append)
    assert phases == ["metrics", "figures and files"]
    assert times and times == sorted(times)


def test_info_shows_each_topics_counts_and_the_calibration(short_log):
    res = walkerslam("info", short_log)
    assert res.returncode == 0, res.stderr
    rows = {ln.split()[0]: ln.split() for ln in res.stdout.splitlines() if ln.startswith(" /")}
    # 4 s of the simulator: encoders and ground truth at 50 Hz, depth and tags at 10 Hz
    assert rows["/encoders"][1:4] == ["EncoderTicks", "201", "50.0"]
    assert rows["/depth/image"][1:3] == ["DepthFrame", "41"]
    assert "calibration: wheel 203.0 mm, track 0.640 m, 256 counts/rev" in res.stdout
    assert res.stdout.count("calibration") >= 2  # and in the metadata list


def test_a_slam_replays_landmarks_are_a_map_to_localize_in(short_log, tmp_path):
    """replay writes the landmarks a SLAM localizer made (landmarks.json); --landmark-map
    gives such a file to the particle filter in place of the log's map; one line for a
    localizer that makes its own map and for a file that is not a map."""
    res = walkerslam("replay", short_log, "--localizer", "ekf-slam", "--out", tmp_path / "slam")
    assert res.returncode == 0, res.stderr
    made = tmp_path / "slam" / "landmarks.json"
    tags = json.loads(made.read_text())
    assert tags and all(int(k) >= 0 and len(v) == 2 for k, v in tags.items())

    def pf(map_file, out):
        res = walkerslam(
            "replay", short_log, "--localizer", "particle-filter", "--landmark-map", map_file,
            "--out", tmp_path / out,
        )  # fmt: skip
        assert res.returncode == 0, res.stderr
        config = json.loads((tmp_path / out / "config.json").read_text())
        assert config["landmark_map"] == str(map_file)
        return json.loads((tmp_path / out / "metrics.json").read_text())["localizer_diagnostics"]

    d = pf(made, "pf")
    assert d["landmark_observations"] > 0 and d["unknown_ids"] == 0
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"999": [0.0, 0.0]}))  # none of the log's tags
    d = pf(other, "pf-other")
    assert d["landmark_observations"] == 0 and d["unknown_ids"] > 0
    res = walkerslam(
        "replay", short_log, "--localizer", "ekf-slam", "--landmark-map", made, "--out",
        tmp_path / "o",
    )  # fmt: skip
    assert_one_line_error(res, "landmarks.json", "builds its own map")
    bad = tmp_path / "bad.json"
    bad.write_text("{")
    res = walkerslam(
        "replay", short_log, "--localizer", "particle-filter", "--landmark-map", bad, "--out",
        tmp_path / "o2",
    )  # fmt: skip
    assert_one_line_error(res, "bad.json", "not JSON")


def test_replay_says_when_its_errors_are_against_a_stand_in_for_ground_truth(short_log, tmp_path):
    from tests.hardware.datasets.datasets_testdata import write_carmen

    path = write_carmen(tmp_path / "s.log", scans=6, beams=180)
    res = walkerslam(
        "replay", path, "--format", "carmen", "--localizer", "dead-reckoning",
        "--out", tmp_path / "c",
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    row = [ln for ln in res.stdout.splitlines() if "errors against" in ln]
    assert len(row) == 1 and "corrected poses (SLAM output, not ground truth)" in row[0]
    res = walkerslam("replay", short_log, "--out", tmp_path / "s")
    assert res.returncode == 0, res.stderr
    assert "errors against" not in res.stdout  # a simulation's poses are the true ones
