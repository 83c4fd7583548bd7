"""The Rao-Blackwellized particle filter with a map per particle (slam.grid_rbpf), its
compiled scan score and hill climbing (slam.grid_kernels) and the improved proposal's
Gaussian fit (slam.scan_proposal). Synthetic laser worlds are seeded; the Intel-lab test
reads ../shared/data/intel_lab and skips when it is absent."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from laser_worlds import ROOM, loop_messages, render_scan, without_odometry

from experiments.config import configure
from experiments.metrics import ate, relation_errors
from experiments.pipeline import Pipeline
from hardware.calibration import WalkerCalibration
from hardware.geometry import between
from hardware.messages import LaserScan, RangeBearing, VelocityOdometry
from hardware.sim.landmark_drive import DriveNoise, landmark_drive
from mapping.grid import HitCentroidGrid, OccupancyGrid
from mapping.scan_points import scan_to_observation
from slam.base import LOCALIZERS, create
from slam.grid_kernels import frame_log_likelihood, hill_climb, propose
from slam.grid_rbpf import GridMatch, GridRbpf, GridRbpfConfig
from slam.particle_filter import ParticleFilterConfig
from slam.scan_proposal import gaussian_fit, lattice
from slam.trajectory import Trajectory

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
INTEL = DATA / "intel_lab" / "intel.gfs.log.gz"
INTEL_RELATIONS = DATA / "intel_lab" / "intel.relations"
KERNEL = (1, 0.1, 0.9, 0.1)  # cells, σ, z_hit, z_rand


def _room_map(pose=(4.0, 4.5, 0.3), centroids=True):
    """The compiled score's grid argument for a map of ROOM from 20 noisy scans at `pose`
    (with or without the cells' hit centroids), and a fresh scan's points."""
    rng = np.random.default_rng(3)
    grid = HitCentroidGrid() if centroids else OccupancyGrid()
    for _ in range(20):
        obs = scan_to_observation(render_scan(ROOM, pose, noise_m=0.01, rng=rng))
        grid.integrate(obs.compacted(0.0125).in_world(np.array(pose)))
    pts = scan_to_observation(render_scan(ROOM, pose, noise_m=0.01, rng=rng)).obstacles
    i0, j0 = grid.lattice_offset
    none = np.zeros((0, 0), dtype=np.float32)
    hits = [grid.layer(n) for n in ("hit_x", "hit_y", "hits")] if centroids else [none] * 3
    args = ((grid.log_odds, *hits, i0, j0, grid.resolution, math.log(0.65 / 0.35)),)
    return args, np.ascontiguousarray(pts[::3], dtype=float)


def test_scan_score_peaks_at_the_true_pose():
    args, pts = _room_map()
    true = np.array([4.0, 4.5, 0.3])
    at_truth, matched = frame_log_likelihood(*args, pts, true, *KERNEL)
    assert matched > 0.95 * len(pts)
    for offset in ([0.05, 0, 0], [0, -0.05, 0], [0, 0, 0.02], [0.1, 0.1, -0.03]):
        score, _ = frame_log_likelihood(*args, pts, true + np.array(offset), *KERNEL)
        assert score < at_truth
    # far off, nothing matches and every point scores the floor log(z_rand)
    score, matched = frame_log_likelihood(*args, pts, np.array([30.0, 30.0, 0.0]), *KERNEL)
    assert matched == 0 and score == pytest.approx(len(pts) * math.log(0.1))


@pytest.mark.parametrize("offset", [(0.12, -0.08, 0.06), (-0.1, 0.15, -0.08)])
@pytest.mark.parametrize("centroids", [True, False])
def test_hill_climbing_recovers_the_pose(offset, centroids):
    args, pts = _room_map(centroids=centroids)
    true = np.array([4.0, 4.5, 0.3])
    pose, _, matched = hill_climb(*args, pts, true + np.array(offset), 0.05, 0.05, 6, *KERNEL)
    err = between(true, pose)
    # From a start 14 cm and 3-5° off. Scored against cell centres, points are pulled
    # onto the centres of the 5 cm cells they hit (the walls here lie on cell boundaries,
    # the worst case): within the resolution. Against the cells' hit centroids, within
    # the scans' own 1 cm noise.
    tol = 0.01 if centroids else 0.03
    assert math.hypot(err[0], err[1]) < tol and abs(err[2]) < math.radians(0.5)
    assert matched > 0.9 * len(pts)


@pytest.mark.parametrize("error_deg", [20.0, -30.0])
def test_a_sharp_turn_is_matched_from_turned_starts(error_deg):
    """The hill climb alone stays at these heading errors in ROOM (local maxima); when
    the odometry's heading σ since the last scan is large (0.2 rad here), the match also
    starts ± 1.5 σ turned and keeps the best climb, which finds the truth."""
    args, pts = _room_map()
    true = np.array([4.0, 4.5, 0.3])
    start = true + np.array([0.05, -0.05, math.radians(error_deg)])
    prior = np.diag([0.05**2, 0.05**2, 0.2**2])

    def match(sigmas: float) -> np.ndarray:
        cfg = GridRbpfConfig(match=GridMatch(turn_starts_sigma=sigmas))
        rbpf = create("grid-rbpf", WalkerCalibration(), cfg)
        params, fit_steps = rbpf._match_params()
        turns = rbpf._turns(prior)
        min_points = rbpf.config.min_points
        pose, _, matched, _ = propose(
            *args, pts, start, prior, turns, params, fit_steps, min_points, np.zeros(3)
        )
        assert rbpf.counts["turn_starts"] == (1 if sigmas else 0)
        assert matched or not sigmas  # without the turned starts it may match nothing
        return between(true, pose)

    alone, turned = match(0.0), match(1.5)
    assert abs(alone[2]) > math.radians(10.0)
    assert math.hypot(turned[0], turned[1]) < 0.01 and abs(turned[2]) < math.radians(0.5)
    with pytest.raises(ValueError, match="turn_starts_sigma"):
        GridMatch(turn_starts_sigma=-1.0)


def test_gaussian_fit_is_the_product_of_two_gaussians():
    """Likelihood N(a, A) times prior N(b, B) on a fine lattice: mean and covariance of
    the normalised product, and log η = log ∫ exp(log L) N(x; b, B) dx."""
    a, b = np.array([0.02, -0.01, 0.005]), np.array([-0.01, 0.015, -0.004])
    big_a = np.diag([0.02, 0.015, 0.01]) ** 2
    big_b = np.array([[0.03**2, 0.0002, 0.0], [0.0002, 0.025**2, 0.0001], [0.0, 0.0001, 0.012**2]])
    steps = np.array([0.004, 0.004, 0.002])
    g = lattice(np.zeros(3), (25, 25, 25), steps)
    d = g - a
    log_l = -0.5 * np.einsum("mi,ij,mj->m", d, np.linalg.inv(big_a), d)
    mu, cov, log_eta = gaussian_fit(g, log_l, b[None], big_b[None], steps)
    want_cov = np.linalg.inv(np.linalg.inv(big_a) + np.linalg.inv(big_b))
    want_mu = want_cov @ (np.linalg.solve(big_a, a) + np.linalg.solve(big_b, b))
    np.testing.assert_allclose(mu[0], want_mu, atol=2e-4)
    np.testing.assert_allclose(cov[0], want_cov, rtol=0.02, atol=2e-7)
    # ∫ exp(−½ (x−a)ᵀA⁻¹(x−a)) N(x; b, B) dx = √(det A / det(A + B)) exp(−½ (a−b)ᵀ(A+B)⁻¹(a−b))
    s = big_a + big_b
    want = 0.5 * (np.linalg.slogdet(big_a)[1] - np.linalg.slogdet(s)[1]) - 0.5 * (a - b) @ (
        np.linalg.solve(s, a - b)
    )
    got = log_eta[0] + np.log(steps).sum() - 1.5 * math.log(2 * math.pi)
    assert got == pytest.approx(want, abs=0.01)


def _run(msgs, cfg: ParticleFilterConfig | GridRbpfConfig, start):
    cal = WalkerCalibration()
    name = "grid-rbpf" if isinstance(cfg, GridRbpfConfig) else "particle-filter"
    loc = create(name, cal, cfg, initial_pose=start)
    pipe = Pipeline(loc, cal, reference_map=False)
    for m in msgs:
        pipe.feed(m)
    return loc, pipe


RBPF = GridRbpfConfig(n_particles=10, max_range_m=20.0, max_beams=120)


def test_a_map_per_particle_removes_the_drift_of_biased_odometry():
    msgs, truth = loop_messages()
    start = tuple(truth.poses[0])
    dr, _ = _run(msgs, ParticleFilterConfig(), start)
    rbpf, pipe = _run(msgs, RBPF, start)
    assert isinstance(rbpf, GridRbpf) and rbpf.revises_past
    d = rbpf.diagnostics()
    assert d["scan_matches"] > 0.9 * d["scan_updates"] * 10 and d["unmatched"] == 0
    final_dr = between(truth.poses[-1], dr.trajectory().poses[-1])
    final = between(truth.poses[-1], rbpf.trajectory().poses[-1])
    assert math.hypot(*final_dr[:2]) > 1.0  # the biased odometry drifts
    assert math.hypot(*final[:2]) < 0.1 and abs(final[2]) < math.radians(2.0)
    # the whole path of the best particle, not only its end
    est = rbpf.trajectory().interpolate(truth.t[::20])
    err = np.hypot(*(est[:, :2] - truth.poses[::20, :2]).T)
    assert np.sqrt(np.mean(err**2)) < 0.1
    assert pipe.rebuild_map()  # the past was revised: the shared map is re-made along it


def test_same_seed_same_path():
    msgs, truth = loop_messages(laps=1)
    start = tuple(truth.poses[0])
    a, _ = _run(msgs, RBPF, start)
    b, _ = _run(msgs, RBPF, start)
    np.testing.assert_array_equal(a.trajectory().poses, b.trajectory().poses)


def test_threads_give_the_same_path():
    # the proposals spread over threads: the same draws, maps and turned starts
    msgs, truth = loop_messages(laps=1)
    # turns over-reported by a fifth: beyond the climb's reach, a turned start wins
    msgs = [replace(m, omega=1.2 * m.omega) if isinstance(m, VelocityOdometry) else m for m in msgs]
    start = tuple(truth.poses[0])
    cfg = replace(RBPF, match=GridMatch(step_rad=0.01))  # turned starts at most frames
    runs = [_run(msgs, replace(cfg, threads=n), start)[0] for n in (1, 2, 3)]
    d = runs[0].diagnostics()
    assert d["turn_starts"] > 10 and d["turn_wins"] > 0
    for other in runs[1:]:
        np.testing.assert_array_equal(other.trajectory().poses, runs[0].trajectory().poses)
        assert other.diagnostics() == d


def test_a_sightings_draw_is_spread_over_the_odometry_before_it():
    # known landmarks only, seen once a second while the odometry comes every 0.1 s: the
    # odometry noise drawn at a sighting is a correction, spread back like a frame's (it
    # was a jump of up to 0.15 m in one step); and the path is better than the odometry
    lm = {0: (6.0, -1.0), 1: (8.0, 6.0), 2: (2.0, 9.0), 3: (-4.0, 4.0), 4: (-3.0, -3.0)}
    noise = DriveNoise(v=0.1, omega=0.05, range_m=0.1, bearing_rad=0.02)
    steps, truth = landmark_drive(lm, 300, 0.1, 1.0, 0.25, noise, max_range_m=8.0, seed=1)
    msgs = [
        m for k, s in enumerate(steps) for m in s if k % 10 == 0 or not isinstance(m, RangeBearing)
    ]
    sensor = {"range_sigma_m": 0.1, "range_sigma_frac": 0.0, "bearing_sigma_rad": 0.02}
    gt = Trajectory(truth[:, 0], truth[:, 1:])
    runs = {}
    for name, cfg in (("grid-rbpf", GridRbpfConfig(**sensor)), ("dead-reckoning", None)):
        runs[name] = loc = create(name, WalkerCalibration(), cfg, landmark_map=lm)
        for m in msgs:
            loc.process(m)
    path = runs["grid-rbpf"].trajectory()
    assert runs["grid-rbpf"].diagnostics()["landmark_updates"] == 30
    true = gt.interpolate(path.t)

    step = between(path.poses[:-1], path.poses[1:]) - between(true[:-1], true[1:])
    step_error = np.hypot(step[:, 0], step[:, 1])
    assert max(step_error) < 0.08
    dead_reckoning = ate(runs["dead-reckoning"].trajectory(), gt)["ate_rmse_m"]
    assert ate(path, gt)["ate_rmse_m"] < 0.5 * dead_reckoning


def test_resampled_particles_share_a_map_until_they_write_it():
    msgs, truth = loop_messages(laps=1)
    rbpf, _ = _run(msgs[:200], RBPF, tuple(truth.poses[0]))
    maps = rbpf.particle_maps()
    rbpf._resampled(np.zeros(len(maps), dtype=int))  # every particle a copy of particle 0
    assert len({id(m) for m in rbpf.particle_maps()}) == 1
    original = maps[0].copy()
    scan = next(m for m in msgs[200:] if type(m).__name__ == "LaserScan")
    obs = scan_to_observation(scan).compacted(0.0125)
    rbpf._integrate(obs, 0.0)
    after = rbpf.particle_maps()
    assert len({id(m) for m in after}) == len(after)  # each wrote into its own copy
    assert sum(m is maps[0] for m in after) == 1  # the last user keeps the original
    for m, pose in zip(after, rbpf.particles, strict=True):
        want = original.copy()
        want.integrate(obs.in_world(pose), centre_xy=pose[:2])
        for name in want.LAYERS:
            np.testing.assert_array_equal(m.layer(name), want.layer(name))


@pytest.mark.data
@pytest.mark.slow
@pytest.mark.skipif(not INTEL.exists(), reason=f"Intel lab log not found at {INTEL}")
def test_intel_lab_subset_relations_beat_dead_reckoning():
    from hardware.datasets import open_dataset

    ds = open_dataset("carmen", INTEL, relations=INTEL_RELATIONS)
    msgs = [m for m in ds.messages() if m.t <= 500.0]  # out of the start room and back
    start = ds.metadata["config"]["initial_pose"]
    rel = np.array(ds.metadata["relations"]["rows"])
    # as `walkerslam replay --format carmen ... --localizer grid-rbpf` builds it: the
    # log's proposed settings (distance-based odometry noise, the laser's beams and range)
    built = configure(LOCALIZERS, "grid-rbpf", ds.metadata)
    assert built.proposed["noise.velocity_model"] == "distance"
    assert built.proposed["max_beams"] == 180
    cfg = built.config
    dr = create("dead-reckoning", ds.calibration, initial_pose=start)
    for m in msgs:
        dr.process(m)
    rbpf = create("grid-rbpf", ds.calibration, cfg, initial_pose=start)
    pipe = Pipeline(rbpf, ds.calibration, reference_map=False)
    for m in msgs:
        pipe.feed(m)
    e_dr = relation_errors(dr.trajectory(), rel)
    e = relation_errors(rbpf.trajectory(), rel)
    assert e["relations_used"] > 400
    # measured: 0.046 m and 0.76° against dead reckoning's 2.74 m and 27°
    assert e["relations_trans_mean_m"] < 0.06
    assert e["relations_trans_mean_m"] < 0.05 * e_dr["relations_trans_mean_m"]
    assert e["relations_rot_mean_deg"] < 0.1 * e_dr["relations_rot_mean_deg"]


def test_maps_past_their_memory_budget_stop_the_run_with_a_clear_error(tmp_path):
    """The particles' maps are counted once per shared map; past `map_memory_gb` the run
    stops with a ConfigError naming the remedies (a laser log's 60 maps had taken 24 GB
    and the kernel killed the process), and from the CLI it is one line, exit 2."""
    from hardware.errors import ConfigError
    from hardware.log import LogWriter
    from tests.experiments.test_cli import walkerslam

    msgs, truth = loop_messages(laps=1)
    start = tuple(truth.poses[0])
    loc, _ = _run(msgs, RBPF, start)
    held = sum(m.nbytes for m in {id(m): m for m in loc.particle_maps()}.values())
    assert held > 10 * 4 * 100 * 100  # ten maps of four float32 layers, a 5 x 5 m room or more
    with pytest.raises(ConfigError, match=r"grid-rbpf: its \d+ particle maps .*map_memory_gb=G"):
        _run(msgs, replace(RBPF, map_memory_gb=0.5 * held / 1e9), start)

    log = tmp_path / "room.mcap"
    with LogWriter(log, WalkerCalibration()) as w:
        for m in msgs:
            w.write(m)
    res = walkerslam(
        "replay", log, "--localizer", "grid-rbpf", "--set", "grid-rbpf.map_memory_gb=0.0001",
        "--out", tmp_path / "out",
    )  # fmt: skip
    lines = [ln for ln in res.stderr.splitlines() if ln.strip() and "note:" not in ln]
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert len(lines) == 1 and "map_memory_gb" in lines[0], res.stderr


def _with_gap_in_turn(msgs, turn: int):
    """`msgs` with the odometry of the `turn`-th turn in place unknown (NaN, as the
    CARMEN importer emits a gap) and no scan during it: the frame after it must find a
    90° turn that the odometry does not report."""
    turning = [
        isinstance(m, VelocityOdometry) and m.v == 0.0 and m.omega != 0.0 for m in msgs
    ]  # fmt: skip
    starts = [k for k in range(1, len(msgs)) if turning[k] and not any(turning[k - 3 : k])]
    k0 = starts[turn]
    odometry = [k for k in range(k0, len(msgs)) if isinstance(msgs[k], VelocityOdometry)]
    k1 = next(k for k in odometry if not turning[k])
    out = msgs[:k0]
    for m in msgs[k0:k1]:
        if isinstance(m, VelocityOdometry):
            out.append(VelocityOdometry(m.t, math.nan, math.nan))
    return out + msgs[k1:]


def test_a_frame_after_motion_the_odometry_did_not_measure_is_scored():
    """A frame is scored once the odometry has moved `scan_every_m` or turned
    `scan_every_rad`; across a gap it measured nothing, and until 2026-12-05 no frame of
    a log without odometry (orebro's: one message of unknown motion before each scan)
    was scored at all. A lap of the test room that way: 3.2 m before, now every frame is
    scored after its gap's search and the lap is centimetres from the truth."""
    msgs, truth = loop_messages(laps=1)
    scans = [m for m in msgs if isinstance(m, LaserScan)]
    blind = without_odometry(msgs)
    rbpf, _ = _run(blind, RBPF, tuple(truth.poses[0]))
    d = rbpf.diagnostics()
    assert d["scan_updates"] == d["gap_searches"] == len(scans) - 1
    assert ate(rbpf.trajectory(), truth)["ate_rmse_m"] < 0.05


def test_a_turn_hidden_by_an_odometry_gap_is_found_by_the_correlative_search():
    """Seattle's laser log turns 81° in its one odometry gap: the climbs from the
    odometry's pose could not reach it (4.5 m ATE against GMapping's poses); the frame
    after a gap is first matched against the best particle's map over a full turn, and
    the particles climb from there."""
    msgs, truth = loop_messages(laps=1)
    gapped = _with_gap_in_turn(msgs, turn=2)
    assert sum(isinstance(m, VelocityOdometry) and math.isnan(m.v) for m in gapped) >= 15
    start = tuple(truth.poses[0])
    rbpf, _ = _run(gapped, RBPF, start)
    d = rbpf.diagnostics()
    assert d["gap_searches"] == 1 and d["gap_matches"] == 1
    err = ate(rbpf.trajectory(), truth)["ate_rmse_m"]
    assert err < 0.1, err
    blind, _ = _run(gapped, replace(RBPF, match=GridMatch(gap_min_inliers=1.01)), start)
    assert blind.diagnostics()["gap_matches"] == 0
    assert ate(blind.trajectory(), truth)["ate_rmse_m"] > 3 * err
