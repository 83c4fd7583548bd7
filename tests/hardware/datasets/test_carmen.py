"""CARMEN importer: synthetic GMapping-style logs and the real Intel / corrected logs."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from datasets_testdata import (
    assert_same_messages,
    chain_of,
    data_dir,
    scans_of,
    write_carmen,
    write_text,
)

from hardware.datasets import DatasetError, import_to_log, open_dataset
from hardware.datasets.carmen import exact_pieces, isotonic, spread_ties
from hardware.log import read_log
from hardware.messages import GroundTruthPose, LaserScan, VelocityOdometry
from slam.base import create
from slam.motion import MotionNoise, OdometryModel, arc_increment


def relative(a, b):
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, math.remainder(b[2] - a[2], 2 * math.pi)])


def dead_reckon(ds, initial=(0.0, 0.0, 0.0)):
    loc = create("dead-reckoning", ds.calibration, initial_pose=initial)
    for m in ds.messages([VelocityOdometry]):
        loc.process(m)
    return loc.trajectory()


def pose_at(traj, t):
    i = int(np.searchsorted(traj.t, t))
    assert traj.t[i] == t, "no odometry message at the scan time"
    return traj.poses[i]


def assert_scan_to_scan_exact(ds, path, tol=1e-9):
    """Dead reckoning from scan k to k+1 = the ODOM chain from the reset after scan k to
    the last ODOM line before scan k+1 (as printed in the file)."""
    resets, ends = chain_of(path)
    traj = dead_reckon(ds)
    times = ds.arrays["scan_times"]
    checked = 0
    for k in range(len(times) - 1):
        want = relative(resets[k], ends[k + 1])
        got = relative(pose_at(traj, times[k]), pose_at(traj, times[k + 1]))
        d = got - want
        d[2] = math.remainder(d[2], 2 * math.pi)
        assert np.max(np.abs(d)) < tol, (k, got, want)
        checked += 1
    return checked


# ---------------------------------------------------------------------------------------
# synthetic


@pytest.mark.parametrize("gz", [False, True])
@pytest.mark.parametrize("odometry", ["smooth", "exact"])
def test_synthetic_scan_to_scan_odometry_is_exact(tmp_path, gz, odometry):
    path = write_carmen(tmp_path / "s.log", gz=gz)
    ds = open_dataset("carmen", path, odometry=odometry)
    assert assert_scan_to_scan_exact(ds, path) == 5
    stats = ds.metadata["dataset"]["odometry"]
    assert stats["mode"] == odometry and stats["gaps"] == 0


def test_exact_mode_reproduces_every_odom_line(tmp_path):
    """In "exact" mode every ODOM line of a segment is reached exactly."""
    path = write_carmen(tmp_path / "s.log", backsteps=False)
    ds = open_dataset("carmen", path, odometry="exact")
    traj = dead_reckon(ds)
    lines = [ln.split() for ln in path.read_text().splitlines()]
    # segment after the 2nd scan: reset pose, then ODOM lines until the next FLASER
    start = [i for i, tok in enumerate(lines) if tok[0] == "FLASER"][1]
    reset = tuple(float(v) for v in lines[start + 1][1:4])
    t_reset = float(lines[start][-1])
    odo = []
    for tok in lines[start + 3 :]:
        if tok[0] != "ODOM":
            break
        odo.append((float(tok[7]), tuple(float(v) for v in tok[1:4])))
    p0 = pose_at(traj, t_reset)
    for t, pose in odo:
        got = relative(p0, pose_at(traj, t))
        assert np.allclose(got, relative(reset, pose), atol=1e-9, rtol=0)


def test_smooth_mode_is_close_between_scans_and_has_no_heading_swings(tmp_path):
    path = write_carmen(tmp_path / "s.log", backsteps=False, lines_per_scan=12)
    smooth = open_dataset("carmen", path)
    stats = smooth.metadata["dataset"]["odometry"]
    assert stats["heading_swings"] == 0
    assert stats["max_length_change_m"] < 0.01 and stats["max_heading_change_rad"] < 0.05
    # one message per ODOM interval (plus the final stop) instead of two
    exact = open_dataset("carmen", path, odometry="exact")
    assert smooth.counts()["VelocityOdometry"] == stats["intervals"] + 1
    assert exact.counts()["VelocityOdometry"] > smooth.counts()["VelocityOdometry"]


def test_synthetic_scans_poses_and_metadata(tmp_path):
    path = write_carmen(tmp_path / "s.log.gz", gz=True)
    ds = open_dataset("carmen", path)
    msgs = list(ds.messages())
    scans = scans_of(msgs)
    gt = [m for m in msgs if isinstance(m, GroundTruthPose)]
    assert len(scans) == len(gt) == 6
    s = scans[0]
    assert s.angle_min == -math.pi / 2 and s.angle_increment == pytest.approx(math.pi / 180)
    assert s.ranges.dtype == np.float32 and s.ranges.shape == (180,)
    assert not s.ranges.flags.writeable
    assert [g.t for g in gt] == [sc.t for sc in scans]
    assert np.allclose([(g.x, g.y) for g in gt], ds.arrays["corrected_poses"][:, :2])
    md = ds.metadata
    assert md["groundtruth"]["kind"] == "slam-corrected"
    assert "not independent ground truth" in md["groundtruth"]["note"]
    assert md["dataset"]["reset_lines"] == 6 and md["dataset"]["corrected"]
    assert md["dataset"]["params"] == {"robot_frontlaser_offset": "0.0"}
    assert md["dataset"]["ignored_records"] == {"NEFF": 6}
    assert md["config"]["format"] == "carmen" and md["config"]["odometry"] == "smooth"
    # range_max: the largest reading, as float32, so that reading counts as "no return"
    largest = max(float(np.max(sc.ranges)) for sc in scans)
    assert md["dataset"]["range_max"] == largest == float(np.float32(largest))
    assert md["dataset"]["largest_reading"] == largest


def test_initial_pose_reaches_the_first_corrected_pose(tmp_path):
    path = write_carmen(tmp_path / "s.log")
    ds = open_dataset("carmen", path)
    traj = dead_reckon(ds, ds.initial_pose)
    p = pose_at(traj, ds.arrays["scan_times"][0])
    assert np.allclose(p, ds.arrays["corrected_poses"][0], atol=1e-9)


def test_timestamps_that_step_back_are_repaired(tmp_path):
    path = write_carmen(tmp_path / "s.log", backsteps=True)
    ds = open_dataset("carmen", path)
    odo = [m.t for m in ds.messages([VelocityOdometry])]
    assert all(b > a for a, b in itertools.pairwise(odo))
    repair = ds.metadata["dataset"]["time_repair"]
    assert repair["mode"] == "log" and repair["logged_backsteps"] == 3
    assert repair["odom_lines_retimed"] > 0 and repair["scans_retimed"] == 0
    # scans in order keep their logged timestamps
    assert np.array_equal(ds.arrays["scan_times"], ds.arrays["scan_times_logged"])


def test_scan_timestamps_that_step_back_are_pooled(tmp_path):
    path = write_carmen(tmp_path / "s.log", backsteps=False)
    lines = path.read_text().splitlines()
    flaser = [i for i, ln in enumerate(lines) if ln.startswith("FLASER")]
    # scan 3 logged 0.5 s too late: scans 3 and 4 step back
    i = flaser[3]
    tok = lines[i].split()
    late = f"{float(tok[-1]) + 2.0:.6g}"
    tok[-1] = tok[-3] = late
    lines[i] = " ".join(tok)
    odom = lines[i - 1].split()
    odom[7] = odom[9] = late
    lines[i - 1] = " ".join(odom)
    write_text(path, "\n".join(lines) + "\n")
    ds = open_dataset("carmen", path)
    t = ds.arrays["scan_times"]
    assert np.all(np.diff(t) > 0)
    assert ds.metadata["dataset"]["time_repair"]["scans_retimed"] == 2
    assert assert_scan_to_scan_exact(ds, path) == 5


def test_all_zero_timestamps_become_synthetic(tmp_path):
    path = write_carmen(tmp_path / "s.log", backsteps=False)
    text = []
    for ln in path.read_text().splitlines():
        tok = ln.split()
        if tok and tok[0] in ("ODOM", "FLASER"):
            tok[-1] = tok[-3] = "0"
        text.append(" ".join(tok))
    write_text(path, "\n".join(text) + "\n")
    ds = open_dataset("carmen", path, scan_period=2.0)
    assert ds.arrays["scan_times"].tolist() == [2.0, 4.0, 6.0, 8.0, 10.0, 12.0]
    assert ds.metadata["dataset"]["time_repair"]["mode"] == "synthetic"
    assert "100%" in ds.metadata["dataset"]["time_repair"]["reason"]
    assert assert_scan_to_scan_exact(ds, path) == 5


def test_segment_without_odometry_is_a_gap(tmp_path):
    log = (
        "ODOM 0 0 0 0 0 0 0.5 h 0.5\n"
        "ODOM 0.1 0 0 0 0 0 1 h 1\n"
        "FLASER 3 1 2 3 0.1 0 0 0.1 0 0 1 h 1\n"
        "ODOM 0.1 0 0 0 0 0 0 h 0\n"
        "FLASER 3 1 2 3 0.5 0.1 0 0.5 0.1 0 2 h 2\n"
        "ODOM 0.5 0.1 0 0 0 0 0 h 0\n"
        "ODOM 0.6 0.1 0 0 0 0 2.5 h 2.5\n"
    )
    ds = open_dataset("carmen", write_text(tmp_path / "g.log", log))
    odo = [(m.t, m.v, m.omega) for m in ds.messages([VelocityOdometry])]
    assert odo[0] == (0.5, pytest.approx(0.2), 0.0)
    assert odo[1][0] == 1.0 and math.isnan(odo[1][1]) and math.isnan(odo[1][2])  # unknown
    assert odo[2:] == [(2.0, pytest.approx(0.2), 0.0), (2.5, 0.0, 0.0)]  # the log's end
    # dead reckoning stands still over the gap; a motion model knows it does not know
    model = OdometryModel(ds.calibration, MotionNoise())
    incs = [model.increment(m) for m in ds.messages([VelocityOdometry])][1:]
    assert [i.unknown for i in incs] == [False, True, False]
    assert incs[1].ds == 0.0 and incs[1].dtheta == 0.0
    assert np.sqrt(np.diag(incs[1].cov)).tolist() == [1.0, math.pi]
    assert ds.metadata["dataset"]["odometry"]["gaps"] == 1
    assert ds.metadata["dataset"]["odometry"]["scans_without_odometry"] == 1
    # 3 beams over 180°: 90° steps
    assert next(iter(ds.messages([LaserScan]))).angle_increment == pytest.approx(math.pi / 2)


def test_relations_with_an_offset(tmp_path):
    path = write_carmen(tmp_path / "s.log", backsteps=False)
    rel = write_text(
        tmp_path / "s.relations",
        "1000.4 1001.2 0.5 -0.1 0 0 0 0.3\n1001.2 1002.0 1.0 0.0 0 0 0 -0.1\n",
    )
    ds = open_dataset("carmen", path, relations=rel, time_offset=999.0)
    r = ds.metadata["relations"]
    assert r["columns"] == ["t1", "t2", "x", "y", "yaw"]
    assert r["rows"] == [
        [pytest.approx(1.4), pytest.approx(2.2), 0.5, -0.1, 0.3],
        [pytest.approx(2.2), pytest.approx(3.0), 1.0, 0.0, -0.1],
    ]
    assert r["time_offset_s"] == 999.0 and r["time_offset_source"] == "option time_offset"
    with pytest.raises(DatasetError, match=r"give time_offset, or put one \*timestamps\.csv"):
        open_dataset("carmen", path, relations=rel)
    # a timestamp CSV beside the relations gives the offset (it must match the scans)
    scans = ds.arrays["scan_times_logged"]
    csv = "# gfs,clf,offset\n" + "".join(f"{t},{t + 999.001},999.001\n" for t in scans)
    write_text(tmp_path / "s_timestamps.csv", csv)
    ds2 = open_dataset("carmen", path, relations=rel)
    assert ds2.metadata["relations"]["time_offset_s"] == pytest.approx(999.001)
    write_text(tmp_path / "s_timestamps.csv", "1.0,1000.0,999.0\n")
    with pytest.raises(DatasetError, match="do not match this log's 6 scans"):
        open_dataset("carmen", path, relations=rel)


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("ODOM 1 2 3", r"line 3: ODOM needs 9 fields after the tag, got 3"),
        ("ODOM 1 2 x 0 0 0 1 h 1", r"line 3: not a number: 'x'"),
        ("FLASER abc", r"line 3: FLASER beam count is not an integer: 'abc'"),
        ("FLASER 4 1 2 3 4 0 0 0", r"line 3: FLASER with 4 beams needs 14 fields"),
        ("FLASER 2 1 2 0 0 0 0 0 0 9 h 9", r"line 3: FLASER with 2 beams, earlier scans have 3"),
    ],
)
def test_malformed_lines_name_file_and_line(tmp_path, line, message):
    text = "ODOM 0 0 0 0 0 0 1 h 1\nFLASER 3 1 2 3 0 0 0 0 0 0 1 h 1\n" + line + "\n"
    path = write_text(tmp_path / "bad.log.gz", text, gz=True)
    with pytest.raises(DatasetError, match=message) as e:
        open_dataset("carmen", path)
    assert str(path) in str(e.value)


def test_not_a_laser_log(tmp_path):
    with pytest.raises(DatasetError, match="no FLASER lines"):
        open_dataset("carmen", write_text(tmp_path / "o.log", "ODOM 0 0 0 0 0 0 1 h 1\n"))
    with pytest.raises(DatasetError, match="missing file"):
        open_dataset("carmen", tmp_path / "none.log")
    with pytest.raises(DatasetError, match="is a folder"):
        open_dataset("carmen", tmp_path)


def test_exact_pieces_reach_any_relative_motion():
    rng = np.random.default_rng(7)
    for _ in range(500):
        dx, dy = rng.normal(0, 0.1, 2) * rng.choice([1e-4, 1.0])
        dth = rng.uniform(-3.0, 3.0) * rng.choice([0.0, 0.01, 1.0])
        x = y = th = 0.0
        for ds, da in exact_pieces(dx, dy, dth):
            ix, iy = arc_increment(ds, da, th)
            x, y, th = x + ix, y + iy, th + da
        assert np.allclose([x, y, th], [dx, dy, dth], atol=1e-12)


def test_isotonic_and_spread_ties():
    y = np.array([1.0, 3.0, 2.0, 2.0, 5.0, 4.0])
    assert isotonic(y).tolist() == pytest.approx([1.0, 7 / 3, 7 / 3, 7 / 3, 4.5, 4.5])
    out = spread_ties(np.array([1.0, 1.0, 1.0, 2.0]), 0.9, 2.0, 1e-3)
    assert np.all(np.diff(out) > 0) and out[0] > 0.9 and out[-1] < 2.0
    assert out.tolist() == pytest.approx([1.0, 1.001, 1.002, 1.999])


# ---------------------------------------------------------------------------------------
# Intel and the corrected logs (data)

INTEL = "intel_lab"


@pytest.fixture(scope="module")
def intel():
    folder = data_dir(INTEL)
    return open_dataset("carmen", folder / "intel.gfs.log.gz", relations=folder / "intel.relations")


@pytest.mark.data
def test_intel_counts_and_scans(intel):
    md = intel.metadata["dataset"]
    assert md["scans"] == 910 and md["beams"] == 180
    assert md["odom_lines"] == 14541 and md["reset_lines"] == 910
    assert intel.counts()["LaserScan"] == intel.counts()["GroundTruthPose"] == 910
    assert md["range_max"] == float(np.float32(81.83))
    s = next(iter(intel.messages([LaserScan])))
    assert s.t == 32.9068 and s.angle_increment == pytest.approx(math.pi / 180)
    assert md["odometry"]["gaps"] == 0 and md["odometry"]["heading_swings"] == 0
    # logged timestamps step back (SOURCE.md): repaired, scans nearly untouched
    assert md["time_repair"]["logged_backsteps"] > 600
    assert md["time_repair"]["scans_retimed"] == 8
    assert md["time_repair"]["max_scan_shift_s"] < 0.5


@pytest.mark.data
def test_intel_raw_odometry_between_scans_is_exact(intel):
    path = data_dir(INTEL) / "intel.gfs.log.gz"
    assert assert_scan_to_scan_exact(intel, path) == 909


@pytest.mark.data
def test_intel_relations_inside_the_log(intel):
    rel = intel.metadata["relations"]
    rows = np.array(rel["rows"])
    assert rows.shape == (2984, 5)
    assert rel["time_offset_s"] == pytest.approx(976052857.337, abs=0.005)
    span = intel.metadata["dataset"]
    assert rows[:, :2].min() >= span["t_first"] and rows[:, :2].max() <= span["t_last"]
    # relations with both ends on a scan: GMapping's corrected poses agree with them
    # (Kümmerle et al. 2009: 0.070 ± 0.083 m mean translational error for GMapping)
    t = intel.arrays["scan_times_logged"]
    poses = intel.arrays["corrected_poses"]
    errs = []
    for t1, t2, x, y, _ in rows:
        i, j = np.argmin(np.abs(t - t1)), np.argmin(np.abs(t - t2))
        if abs(t[i] - t1) < 2e-3 and abs(t[j] - t2) < 2e-3:
            r = relative(poses[i], poses[j])
            errs.append(math.hypot(r[0] - x, r[1] - y))
    assert len(errs) > 30 and np.mean(errs) < 0.1


@pytest.mark.data
def test_intel_initial_pose_and_dead_reckoning(intel):
    traj = dead_reckon(intel, intel.initial_pose)
    times = intel.arrays["scan_times"]
    assert np.allclose(pose_at(traj, times[0]), intel.arrays["corrected_poses"][0], atol=1e-9)
    # Intel's raw odometry is poor: per scan step GMapping corrects its rotation by
    # 0.03 rad on average (82.0 rad net rotation corrected vs 53.3 rad raw over the log);
    # after a minute dead reckoning is 3.0 m off, a bound that proves it is not garbage
    k = np.searchsorted(times, times[0] + 60.0)
    d = pose_at(traj, times[k])[:2] - intel.arrays["corrected_poses"][k, :2]
    assert np.hypot(*d) < 5.0


@pytest.mark.data
def test_orebro_imports_with_synthetic_times_and_gaps():
    path = data_dir("carmen_corrected_logs") / "orebro-corrected.log.gz"
    ds = open_dataset("carmen", path)
    md = ds.metadata["dataset"]
    assert md["scans"] == 237 and md["beams"] == 181
    assert md["range_max"] == float(np.float32(32.767))
    assert md["time_repair"]["mode"] == "synthetic"
    assert ds.arrays["scan_times"][:3].tolist() == [1.0, 2.0, 3.0]
    # most segments hold only the reset line: no raw motion between those scans
    assert md["odometry"]["gaps"] == 219
    assert ds.metadata["groundtruth"]["kind"] == "slam-corrected"
    s = next(iter(ds.messages([LaserScan])))
    assert s.angle_increment == pytest.approx(math.pi / 180)  # 181 beams over 180°


@pytest.mark.data
@pytest.mark.slow
def test_intel_full_import(tmp_path, intel):
    summary = import_to_log(intel, tmp_path / "intel.mcap")
    trial = read_log(summary.path)
    assert trial.metadata["relations"]["rows"][0] == intel.metadata["relations"]["rows"][0]
    assert trial.metadata["groundtruth"]["kind"] == "slam-corrected"
    assert_same_messages(list(trial.messages()), list(intel.messages()))


def test_hits_beyond_the_mapped_range_are_not_mapped(tmp_path):
    """A CARMEN log proposes its usable range (20 m) to the occupancy mapper as well as
    to the localizers: a replay maps no hit farther than that from the scan (readings
    here reach 60 m), through the dataset and through its MCAP import alike, and a
    mapper range the caller chose stands."""
    from experiments.run import replay_log
    from hardware.datasets.carmen import USABLE_RANGE_M
    from mapping.mapper import MapperConfig
    from mapping.scan_points import ScanConfig

    path = write_carmen(tmp_path / "far.log", scans=4, ranges_m=(2.0, 60.0))
    mcap = tmp_path / "far.mcap"
    import_to_log(open_dataset("carmen", path), mcap)
    for name, source in (("dataset", open_dataset("carmen", path)), ("mcap", read_log(mcap))):
        res = replay_log(
            source, tmp_path / name, localizer="dead-reckoning", figures=False, map_figure=False,
            reference_map=False, drag_metrics=False,
        )  # fmt: skip
        mapper = res.pipeline.mapper
        assert mapper.config.scan.max_range_m == USABLE_RANGE_M
        hits = mapper.grid.occupied_xy()
        scans = res.pipeline.localizer.trajectory().poses  # the robot stays within ~1 m
        far = np.min(np.hypot(*(hits[:, None, :2] - scans[None, :, :2]).transpose(2, 0, 1)), axis=1)
        assert len(hits) > 100 and far.max() < USABLE_RANGE_M + 0.2, far.max()
    chosen = MapperConfig(scan=ScanConfig(max_range_m=40.0))
    res = replay_log(
        open_dataset("carmen", path), tmp_path / "chosen", localizer="dead-reckoning",
        mapper_config=chosen, figures=False, map_figure=False, reference_map=False,
        drag_metrics=False,
    )  # fmt: skip
    assert res.pipeline.mapper.config.scan.max_range_m == 40.0
