"""Rao-Blackwellized particle filter with an occupancy grid per particle (grid FastSLAM).

The localizer `grid-rbpf`: each of `n_particles` particles carries
its own path and its own occupancy grid built along that path, as GMapping does
(Grisetti, Stachniss and Burgard, IEEE T-RO 2007). Where one map shared by every particle
cannot undo a drift that has been mapped (a loop comes back to walls mapped twice), the
particles whose maps closed the loop correctly survive it.

Per scored frame (a laser scan or depth frame, after `scan_every_m` / `scan_every_rad`
of odometry), for each particle:

1. its odometry prediction since the last frame (deterministic; the odometry's
   covariance accumulates meanwhile, as in the "scan" proposal of slam.particle_filter)
   starts a hill-climbing scan match against the particle's own map
   (slam.grid_kernels: GMapping's endpoint model and optimizer); after an odometry gap
   (motion unknown) every start is first moved as a full-turn correlative match of the
   frame against the most probable particle's map moves that particle
   (`GridMatch.gap_window`);
2. when at least `min_points` of the frame's points found an occupied cell there, the
   improved proposal: likelihood × odometry prior on a 3×3×3 lattice around the match
   (`match.fit_step_m`, `match.fit_step_rad`), a Gaussian fitted to it
   (slam.scan_proposal.gaussian_fit), the new pose drawn from it, the weight multiplied by
   the product's mass η; otherwise the pose is drawn from the odometry prior and weighted
   by the frame's likelihood there;
3. weights normalised, resampled when N_eff < resample_threshold·N (maps are shared by
   the copies until one of them is written: copy on write);
4. the frame integrated into each particle's map at its new pose.

The estimate is the pose of the most probable particle; the trajectory its whole path,
read back through resampling (slam.particle_paths), so the past changes whenever another
particle becomes the most probable (`revises_past`; the pipeline then rebuilds the shared
map along it). Known landmarks (and position fixes), when given, weight the particles as
in the shared-map filter, once the odometry noise of the steps since the last frame or
sighting is drawn (slam.particle_filter). Between two frames or sightings a particle
follows the odometry, and a frame (or a sighting's draw) moves it by a correction δ (the
drawn pose minus the odometry's prediction): in the trajectory the correction is spread
over the stretch of odometry that accumulated it, at each odometry message in proportion
to the odometry variance accumulated by then (the mean of a random walk's path given its
end point, a Brownian bridge; for x, y and θ separately), so that the path does not jump
at frames or sightings while its poses there stay those of the filter. Particle maps use
the attached mapper's configuration (grid, depth, scan).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, fields, replace

import numpy as np

from hardware.calibration import WalkerCalibration
from hardware.errors import ConfigError
from hardware.geometry import wrap_angle
from hardware.messages import DepthFrame, LaserScan
from hardware.registry import Spec
from mapping.grid import GridExtent, HitCentroidGrid, make_grid
from mapping.mapper import MapperConfig, OccupancyMapper, Projection
from slam.base import PoseEstimate
from slam.grid_kernels import draw, propose
from slam.motion import Increment
from slam.particle_filter import ParticleFilter, ParticleFilterConfig, ParticleSettings
from slam.particle_paths import ParticlePaths, path_end
from slam.scan_matching import Reference
from slam.scan_matching import match as scan_match
from slam.scan_proposal import ProposalLattice
from slam.trajectory import Trajectory, spread_corrections


@dataclass(frozen=True)
class GridMatch:
    """The scan match of each particle against its own map (slam.grid_kernels): a point
    scores against the hit centroid of the nearest occupied cell within ± kernel_cells,
    a Gaussian of σ = sigma_m, times beam_weight; step_m / step_rad: the hill climb's
    first steps, halved `refinements` times (3: the climb ends at 6 mm and 0.006 rad,
    finer than the fit lattice that then places the proposal; GMapping's 5 gave the
    same Intel relations error, 0.0674 against 0.0675 m over seeds 0-2, at 0.8× the
    speed: BENCHMARKS.md); turn_starts_sigma: when this many of the odometry's heading
    σ since the last frame reach two step_rad (a sharp turn between scans), the match
    also starts from the odometry pose turned by ± that much and keeps the best of the
    three climbs (on the Intel log a 10° odometry error in one turn is beyond the
    climb's reach: 2 of 3 seeds broke there without it); 0 disables;
    shared_turn_starts: the most probable particle tries both turned starts and the
    others only the one it chose (none when its own start won): the odometry's heading
    error is the same for every particle, and two extra climbs per particle were most
    of the filter's time on Intel; False: every particle tries both;
    fit_step_m / fit_step_rad: the lattice the proposal's Gaussian is fitted on.
    gap_window (m, rad): after an odometry gap (motion unknown, e.g. Seattle's laser log
    turns 81° in its one gap) the climbs cannot reach the pose from the odometry's: the
    frame is first matched against the most probable particle's map by the correlative
    search and ICP (slam.scan_matching.match, as gtsam searches a gap) within ± this of
    its pose, and every particle climbs from its own pose moved as that match moved it;
    an ICP fit with fewer than gap_min_inliers of the points within 5 cm of the map, or
    not converged, leaves the starts as they were (above 1: the search is never used)."""

    kernel_cells: int = 1
    sigma_m: float = 0.03
    beam_weight: float = 1.0
    step_m: float = 0.05
    step_rad: float = 0.05
    refinements: int = 3
    turn_starts_sigma: float = 1.5
    shared_turn_starts: bool = True
    fit_step_m: float = 0.02
    fit_step_rad: float = 0.01
    gap_window: tuple[float, float] = (1.0, math.pi)
    gap_min_inliers: float = 0.5

    def __post_init__(self) -> None:
        if self.kernel_cells < 0 or self.refinements < 0:
            raise ValueError("kernel_cells and refinements must be >= 0")
        if self.turn_starts_sigma < 0:
            raise ValueError(f"turn_starts_sigma must be >= 0, got {self.turn_starts_sigma}")
        if self.sigma_m <= 0 or self.beam_weight <= 0:
            raise ValueError("sigma_m and beam_weight must be > 0")
        if min(self.step_m, self.step_rad, self.fit_step_m, self.fit_step_rad) <= 0:
            raise ValueError("the match's steps must be > 0")
        if len(self.gap_window) != 2 or min(self.gap_window) < 0 or self.gap_min_inliers < 0:
            raise ValueError("gap_window must be two values >= 0 and gap_min_inliers >= 0")


@dataclass(frozen=True)
class GridRbpfConfig(ParticleSettings):
    """Per-particle-map filter settings (the module docstring has the algorithm):
    slam.particle_filter.ParticleSettings (the machinery this filter reuses; n_particles
    are particles each with its own grid), and

    sigma_floor (x, y, θ): added to the odometry prior's σ of each particle (in
        quadrature) before its match.
    match: the scan match per particle (GridMatch), with z_hit, z_rand.
    weight_gain: a frame's log-weights are divided by it (GMapping's "ogain"): the
        proposal follows the sharp likelihood while the weights, which decide which
        particles (and maps) survive, are smoothed, so that resampling does not deplete
        the particles at every frame.
    map_memory_gb: the particles' maps (each map shared after resampling counted once)
        may hold at most this many GB; a run whose maps grow past it stops with a
        ConfigError naming the remedies, rather than exhausting the machine's memory
        (the process's peak was 2.6 times its maps' bytes on the Seattle laser log);
        0: a quarter of this machine's memory.
    threads: the particles' scan matches and map updates (compiled, run without the
        GIL) are spread over this many threads; 0: one per core the process may run on
        (1 under `taskset -c 0`). The answers are the same for any number: each particle's match
        reads only its own map and draws, and the most probable particle, whose turned
        start the others share, is matched first.
    The defaults were chosen on the Intel lab log (BENCHMARKS.md: 60 particles, σ 0.03 m,
    gain 20; 30 particles fail a late loop on some seeds).
    """

    n_particles: int = 60
    sigma_floor: tuple[float, float, float] = (0.01, 0.01, 0.005)
    match: GridMatch = field(default_factory=lambda: GridMatch())
    weight_gain: float = 20.0
    map_memory_gb: float = 0.0
    threads: int = 0

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.threads < 0:
            raise ValueError(f"threads must be >= 0, got {self.threads}")
        if self.map_memory_gb < 0:
            raise ValueError(f"map_memory_gb must be >= 0, got {self.map_memory_gb}")
        if self.weight_gain < 1.0:
            raise ValueError(f"weight_gain must be >= 1, got {self.weight_gain}")
        if len(self.sigma_floor) != 3 or min(self.sigma_floor) < 0:
            raise ValueError(f"sigma_floor must be three values >= 0, got {self.sigma_floor}")

    def machinery(self) -> ParticleFilterConfig:
        """The shared-map filter's parameters for the machinery this filter reuses
        (prediction, landmark weighting, resampling, the scan proposal's odometry)."""
        shared = {f.name: getattr(self, f.name) for f in fields(ParticleSettings)}
        return ParticleFilterConfig(
            **shared,
            use_scans=True,
            proposal="scan",
            smoother="none",
            lattice=ProposalLattice(sigma_floor=self.sigma_floor),
        )


class GridRbpf(ParticleFilter):
    """See the module docstring; the localizer `grid-rbpf`."""

    revises_past = True

    def __init__(self, config: GridRbpfConfig, calibration: WalkerCalibration) -> None:
        super().__init__(config.machinery(), calibration)
        self.config = config  # (self.pf: the machinery's parameters)
        self.revises_past = True  # the best particle's path (the base's smoothers unused)
        self._maps: list[GridExtent] = []
        self._map_config = MapperConfig()
        # the particles' poses at every odometry message and frame (a frame's correction is
        # spread over the odometry messages before it)
        self.paths = ParticlePaths(0.0)
        # every frame's and sighting's per-particle corrections, read back through
        # resampling like the paths, and the odometry variance (x+y, θ) accumulated at each
        # odometry message since the last correction, with each correction's total
        self.corrections = ParticlePaths(0.0, replace_same_time=False)
        self._variance: list[tuple[float, float, float]] = []  # (t, var xy, var θ)
        self._segment_totals: list[tuple[float, float]] = []  # at each correction
        self._correction_t = -math.inf
        self._path_cache: tuple[tuple[int, float], Trajectory] | None = None
        self.counts.update(
            scan_matches=0, unmatched=0, map_copies=0, turn_starts=0, turn_wins=0,
            gap_searches=0, gap_matches=0,
        )  # fmt: skip
        self._gap = False  # an odometry gap since the last scored frame
        threads = config.threads or len(os.sched_getaffinity(0))
        self._pool = ThreadPoolExecutor(threads) if threads > 1 else None
        self._threads = threads
        self.attach_map(None)

    # -- the particles' maps --------------------------------------------------------------
    def attach_map(self, source: OccupancyMapper | GridExtent | None) -> None:
        """Particle maps are built with the configuration of `source` (an OccupancyMapper:
        the pipeline's shared mapper) when it has one; they start empty."""
        super().attach_map(source)
        if isinstance(source, OccupancyMapper):
            self._map_config = source.config
        # the score reads log-odds and the cells' hit centroids
        grid_cfg = replace(self._map_config.grid, model="log-odds-hits")
        self._map_config = replace(self._map_config, grid=grid_cfg)
        self._projector = None
        empty = make_grid(grid_cfg)
        self._maps = [empty] * len(self.particles)

    def _resampled(self, parents: np.ndarray) -> None:
        self._maps = [self._maps[k] for k in parents]
        self.paths.resampled(parents)
        self.corrections.resampled(parents)

    def _project(self, msg: DepthFrame | LaserScan) -> Projection:
        """A frame given to `process` (no pipeline): projected as the particles' maps are
        configured (the attached mapper's settings)."""
        if self._projector is None:
            self._projector = OccupancyMapper(self.calibration, self._map_config)
        return self._projector.project(msg)

    def _integrate(self, obs, t: float) -> None:
        """The frame into every particle's map at its pose, copying shared maps first:
        the maps grow on this thread, and the compiled updates (which release the GIL)
        run on the threads."""
        users: dict[int, int] = {}
        for m in self._maps:
            users[id(m)] = users.get(id(m), 0) + 1
        updates = []
        for i, pose in enumerate(self.particles):
            grid = self._maps[i]
            if users[id(grid)] > 1:
                users[id(grid)] -= 1
                grid = self._maps[i] = grid.copy()
                users[id(grid)] = 1
                self.counts["map_copies"] += 1
            if (update := grid.update_at(obs, pose, centre_xy=pose[:2])) is not None:
                updates.append(update)
        self._check_memory(t)
        self._on_threads(lambda part: [update() for update in part], updates)

    def _check_memory(self, t: float) -> None:
        """A ConfigError when the maps (grown for this frame) hold more than the budget
        (`map_memory_gb`)."""
        budget = self.config.map_memory_gb * 1e9 or _machine_memory() / 4
        maps = {id(m): m for m in self._maps}.values()
        held = sum(m.nbytes for m in maps)
        if held <= budget:
            return
        x0, x1, y0, y1 = max(maps, key=lambda m: m.nbytes).extent
        raise ConfigError(
            f"grid-rbpf: its {len(maps)} particle maps (up to {x1 - x0:.0f} x {y1 - y0:.0f} m) "
            f"outgrew their memory budget of {budget / 1e9:.3g} GB at t = {t:.1f} s; "
            "use fewer particles (--set grid-rbpf.n_particles=N), "
            "a coarser grid (--resolution) or a larger budget (--set grid-rbpf.map_memory_gb=G)"
        )

    def _on_threads(self, work: Callable[[Sequence], object], items: Sequence) -> None:
        """work(part) for every part of `items`: one part per thread (work must release
        the GIL to gain), or all of them here without threads."""
        if self._pool is None:
            work(items)
        else:
            list(self._pool.map(work, [items[k :: self._threads] for k in range(self._threads)]))

    # -- frames ---------------------------------------------------------------------------
    def _observe_frame(self, msg: DepthFrame | LaserScan, projection: Projection) -> None:
        """The frame's scan match per particle: scored with its points as projected (a
        laser scan's own end points), integrated compacted (as the mapper does)."""
        c = self.config
        if self._moved[0] < c.scan_every_m and self._moved[1] < c.scan_every_rad:
            return
        obs = projection.compact
        points = self._scoring_points(projection.raw)
        prior = self._prior_cov()
        params, fit_steps = self._match_params()
        e = self.rng.standard_normal((len(self.particles), 3))
        new = np.empty_like(self.particles)
        log_eta = np.zeros(len(self.particles))
        matched = np.full(len(self.particles), -1)  # 1 matched, 0 not, -1 not scored
        turns = self._turns(prior[0])
        # the most probable particle first: with shared turned starts, the start it
        # chose is the only one the others try besides their own
        order = np.argsort(-self._weights, kind="stable")
        starts = self.particles
        if self._gap and (shift := self._gap_shift(points, order[0])) is not None:
            starts = self.particles + shift
            starts[:, 2] = wrap_angle(starts[:, 2])
            turns = turns[:0]
        self._gap = False

        def match(order: np.ndarray, turns: np.ndarray) -> np.ndarray:
            """Propose each particle of `order`; returns the winning starts."""
            won = np.zeros(len(order), dtype=int)
            for k, i in enumerate(order):
                args = self._score_args(self._maps[i])
                if args is None or len(points) < c.min_points:
                    new[i] = draw(starts[i], prior[i], e[i])
                    continue
                new[i], log_eta[i], matched[i], won[k] = propose(
                    *args, points, starts[i], prior[i], turns, params, fit_steps,
                    c.min_points, e[i],
                )  # fmt: skip
            return won

        if len(turns) > 1 and c.match.shared_turn_starts:
            (won,) = match(order[:1], turns)
            if matched[order[0]] >= 0:
                turns = turns[won - 1 : won] if won else turns[:0]
                self.counts["turn_wins"] += bool(won)
            order = order[1:]
        self._on_threads(lambda part: match(part, turns), order)  # (propose releases the GIL)
        scored = bool(np.any(matched >= 0))
        self.counts["scan_matches"] += int(np.sum(matched == 1))
        self.counts["unmatched"] += int(np.sum(matched == 0))
        self._correct(msg.t, new)
        self._reset_odometry()
        if scored:
            self._update(log_eta / c.weight_gain, msg.t)
            self.counts["scan_updates"] += 1
        self._integrate(obs, msg.t)
        self._moved = (0.0, 0.0)
        self.revision += 1
        self._snapshot(msg.t)

    def _predict(self, inc: Increment) -> None:
        self._gap = self._gap or inc.unknown
        super()._predict(inc)

    def _gap_shift(self, points: np.ndarray, best: int) -> np.ndarray | None:
        """After an odometry gap: how the correlative match of the frame's `points`
        against particle `best`'s map (its occupied cells within reach) moves that
        particle's pose (world dx, dy, dθ), or None when it finds no good fit
        (`GridMatch.gap_window`)."""
        m = self.config.match
        grid, guess = self._maps[best], self.particles[best]
        if grid.shape[0] == 0 or len(points) < self.config.min_points:
            return None
        mapped = grid.occupied_xy()
        reach = self.config.max_range_m + m.gap_window[0]
        d = mapped - guess[:2]
        ref = Reference(mapped[np.einsum("ij,ij->i", d, d) <= reach * reach])
        self.counts["gap_searches"] += 1
        res = scan_match(ref, points, guess, *m.gap_window)
        if not res.converged or res.inlier_fraction < m.gap_min_inliers:
            return None
        self.counts["gap_matches"] += 1
        shift = res.pose - guess
        shift[2] = wrap_angle(shift[2])
        return shift

    def _draw_odometry_noise(self, t: float) -> None:
        """A landmark sighting's or a position fix's draw of the odometry noise moves the
        particles as a frame's match does: a correction, spread back the same way."""
        before = self.particles
        totals = self._accumulated()
        super()._draw_odometry_noise(t)
        if self.particles is not before:
            new, self.particles = self.particles, before
            self._correct(t, new, totals)
            self._snapshot(self._correction_t)

    def _correct(
        self, t: float, new: np.ndarray, totals: tuple[float, float] | None = None
    ) -> None:
        """The particles move to `new` at time t (not before the last recorded pose or
        correction); the move is kept as a correction with the odometry variance that
        accumulated it (`totals`, default: since the last correction)."""
        t = max(t, self.track.last_t, self._correction_t) if self.track else t
        correction = new - self.particles
        correction[:, 2] = wrap_angle(correction[:, 2])
        self.corrections.snapshot(t, correction)
        self._segment_totals.append(self._accumulated() if totals is None else totals)
        self._correction_t = t
        self.particles = new

    def _match_params(self) -> tuple[tuple, np.ndarray]:
        """The match's parameters as slam.grid_kernels.propose takes them, and the
        lattice steps of the proposal's fit."""
        c, m = self.config, self.config.match
        params = (m.step_m, m.step_rad, m.refinements, m.kernel_cells, m.sigma_m)
        fit_steps = np.array([m.fit_step_m, m.fit_step_m, m.fit_step_rad])
        return (*params, c.z_hit, c.z_rand, m.beam_weight), fit_steps

    def _turns(self, prior: np.ndarray) -> np.ndarray:
        """The turned starts of this frame's match: ± turn_starts_sigma heading σ of the
        odometry prior (the same for every particle) when that is at least two first
        angular steps, else none."""
        c = self.config.match
        offset = c.turn_starts_sigma * math.sqrt(max(float(prior[2, 2]), 0.0))
        if offset < 2.0 * c.step_rad:  # nearer starts the climb reaches by itself
            return np.zeros(0)
        self.counts["turn_starts"] += 1
        return np.array([offset, -offset])

    def _scoring_points(self, obs) -> np.ndarray:
        """Up to max_beams of the frame's obstacle points within max_range_m (walker frame),
        contiguous for the compiled score."""
        return np.ascontiguousarray(self._points_in_range(obs))

    def _score_args(self, grid: GridExtent) -> tuple | None:
        """The grid as the compiled score reads it (slam.grid_kernels); None while empty."""
        if not isinstance(grid, HitCentroidGrid) or grid.shape[0] == 0:
            return None
        i0, j0 = grid.lattice_offset
        threshold = math.log(grid.OCCUPIED_THRESHOLD / (1.0 - grid.OCCUPIED_THRESHOLD))
        layers = (grid.log_odds, *(grid.layer(n) for n in ("hit_x", "hit_y", "hits")))
        return ((*layers, i0, j0, grid.resolution, threshold),)

    # -- outputs --------------------------------------------------------------------------
    def _best(self) -> int:
        return int(np.argmax(self._weights))

    def _record(self, t: float) -> None:
        self.track.record(t, self.particles[self._best()].copy())
        self._snapshot(t)
        self._variance.append((t, *self._accumulated()))

    def _accumulated(self) -> tuple[float, float]:
        """The odometry variance (x + y, θ) accumulated since the last correction."""
        cov = self._odo_cov
        return cov[0][0] + cov[1][1], cov[2][2]

    def _snapshot(self, t: float) -> None:
        self.paths.snapshot(t, self.particles)

    def estimate(self) -> PoseEstimate:
        est = super().estimate()
        return PoseEstimate(est.t, self.particles[self._best()].copy(), est.covariance)

    def trajectory(self) -> Trajectory:
        """The whole path of the most probable particle, read back through resampling,
        with each frame's correction spread over the odometry before it (module doc)."""
        self._use_held()
        if not self.track:
            return self.track.trajectory()
        key = (self.revision, self.track.last_t)
        if self._path_cache is None or self._path_cache[0] != key:
            best = self._best()
            times, paths = self.paths.paths(self.particles)
            path = paths[:, best, :] if len(times) else np.empty((0, 3))
            times, path, t_now = path_end(times, path, self.track.last_t)
            times = np.append(times, t_now)
            path = np.vstack([path, self.particles[best]])
            self._path_cache = (key, Trajectory(times, self._spread(times, path, best)))
        return self._path_cache[1]

    def _spread(self, times: np.ndarray, path: np.ndarray, best: int) -> np.ndarray:
        """`path` (of particle `best`) with each correction spread back (module
        docstring): at a time s before correction k and after correction k − 1, + f(s)·δ_k
        with f = accumulated variance at s / accumulated variance at correction k, per axis
        (two corrections at one time: the first is spread, the second, with nothing
        accumulated, is not)."""
        c_times, deltas = self.corrections.paths(self.particles)
        if not len(c_times):
            return path
        delta = deltas[:, best, :]
        var = np.array(self._variance).reshape(-1, 3)
        totals = np.array(self._segment_totals).reshape(-1, 2)
        k = np.searchsorted(c_times, times, side="left")  # the next correction at or after s
        inside = (k < len(c_times)) & (times < c_times[np.minimum(k, len(c_times) - 1)])
        k = k[inside]
        accumulated = np.column_stack(
            [np.interp(times[inside], var[:, 0], var[:, 1 + a]) for a in range(2)]
        )
        out = path.copy()
        out[inside] = spread_corrections(path[inside], delta[k], accumulated, totals[k])
        return out

    def particle_maps(self) -> list[GridExtent]:
        """Each particle's own map (shared objects where resampling copied a particle)."""
        return list(self._maps)

    def diagnostics(self) -> dict:
        notes = super().diagnostics()
        notes["distinct_maps"] = len({id(m) for m in self._maps})
        return notes


def _machine_memory() -> int:
    """This machine's physical memory [bytes]."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


SPEC = Spec(
    "grid-rbpf",
    GridRbpfConfig,
    GridRbpf,
    "Rao-Blackwellized particle filter with an occupancy grid per particle (grid FastSLAM "
    "/ GMapping style): scan-matched improved proposal on laser scans or depth frames",
)
