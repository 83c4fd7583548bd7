"""Monte Carlo localization: a particle filter over the walker pose, vectorised over particles.

Each particle is a pose (x, y, θ) with a log-weight. Odometry increments predict: every
particle moves along the exact arc of its own (ds, dθ), drawn from N(increment,
increment.cov) (`slam.motion`; brake commands feed its brake-aware option). Two
measurement models weight the particles:

- landmarks with known IDs (tags seen by the camera, range-bearing datasets) against a
  known landmark map {id: (x, y)}: Gaussian range-bearing likelihood, range σ =
  range_sigma_m + range_sigma_frac·r, bearing σ = bearing_sigma_rad (difference wrapped);
  IDs not in the map are skipped and counted; a sighting without an ID (−1: a tree in
  a laser scan, a corner) is paired by each particle with the map landmark that explains
  it best (its own maximum-likelihood association, as FastSLAM's; `association_enabled`),
  among the landmarks within reach of the cloud (farther ones would score below the
  outlier floor for every particle);
- depth frames (or laser scans) against an occupancy grid (a likelihood field, Thrun et
  al., Probabilistic Robotics §6.4): a distance transform of the grid's occupied surface
  cells gives each cell p(d) = z_hit·N(d; 0, σ_hit) + z_rand/max_range; up to max_beams of
  the frame's obstacle points that land in mapped cells are placed at every particle and
  their log p summed, times beam_weight (< 1: neighbouring points are correlated). The
  grid comes from `map_source` (`ParticleFilter.attach_map`), normally the pipeline's
  shared mapper; the pipeline feeds the localizer before the mapper, so a frame is scored
  against the map without itself. Against a map from elsewhere (e.g. mapped at known
  poses) this localises to a few centimetres; against the shared map, which this
  filter's own estimates build, it drifts (frame-to-recent-map errors accumulate), so
  `use_scans` is off by default.

Proposal (`proposal`). "motion" (default): particles are drawn from the odometry's noise
at every increment, and frames and landmarks only reweight them. "scan": between scored
frames particles move by the odometry alone while the odometry's covariance accumulates
(in the frame of the last scored pose); a scored frame then draws each particle from
odometry prior × scan likelihood (`slam.scan_proposal`, the improved proposal of
GMapping on the one shared map) and weights it by that product's mass. A frame that
cannot be scored (empty map, too few points in mapped cells) and a landmark update first
draw the odometry noise of the steps since the last draw, each step's along its arc as
"motion" would have (with the same seed, the same particles).

Landmark likelihood is robust: each observation's density is the mixture
(1 − ε)·N(z; ẑ, R) + ε·u of the Gaussian and a uniform u = 1/(outlier_range_m·2π) over
the sensor's range and all bearings (ε = outlier_prob), so one wrong-ID or misread
measurement (MRCLAM has a few, π off in bearing) cannot wipe out the particles that are
right; the uniform floor is the z_rand of Thrun et al.'s beam model.

Absolute observations (`absolute`, slam.absolute: a compass heading, a position fix),
when switched on, weight the particles by the same kind of robust likelihood: a
Gaussian in the (wrapped) residual mixed with a uniform over all headings or over a
disc of positions (`absolute.outlier_prob`, `absolute.outlier_radius_m`).

Weights live in log space, normalised with logsumexp; systematic resampling (as
filterpy.monte_carlo.systematic_resample, vectorised and drawing from the filter's own
generator) runs when N_eff = 1/Σw² falls below resample_threshold·N, checked before the
next motion or an observation at a later time: the observations that share a timestamp
(several landmarks in one image) are all weighted in before the particles are resampled.
The estimate is the weighted mean (circular mean for θ) with the weighted covariance.

Trajectory (`smoother`): an observation also tells where the walker was before it, so
the smoothers revise the past (`revises_past`: the pipeline rebuilds the map along it):

- "rts" (default): a Rauch–Tung–Striebel backward pass over the filtered mean and
  covariance after every odometry message (slam.rts), the odometry between them the
  motion model: a correction is spread back over the stretch that led to it in
  proportion to the odometry's uncertainty. It is as good as the filter's noise models
  are consistent: on MRCLAM (fitted noise) ATE 0.108 → 0.085 m over robots 1-5; on the
  simulated course, whose tag camera measures bearing ~50× (rms 0.0006 rad) and range
  ~2× (0.04 m) more precisely than the default noise says, the filtered covariance is
  too wide and the smoother leans on the odometry too much (0.013 → 0.017 m; RPE
  0.012 → 0.007 m);
- "ancestry": the weighted mean of the particles' whole paths read back through
  resampling (slam.particle_paths, as FastSLAM does), every path_snapshot_s. The old past
  degenerates to one particle's path, which carries that particle's motion noise
  (simulated course 0.026 m; MRCLAM 0.090 m);
- "none": the filtered estimate after every odometry message.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from hardware.calibration import WalkerCalibration
from hardware.choices import Choice, coerce
from hardware.geometry import compose, inverse, wrap_angle
from hardware.messages import DepthFrame, LaserScan, Message
from hardware.registry import Spec
from mapping.grid import GridExtent
from mapping.mapper import OccupancyMapper, Projection
from slam.absolute import (
    AbsoluteConfig,
    AbsoluteObservation,
    absolute_observation,
    fused_count,
)
from slam.association import AssociationConfig
from slam.base import KnownMapConfig, Localizer, PoseEstimate
from slam.grid_kernels import field_log_likelihood, log_likelihood_field
from slam.measurement import (
    BEARING_SIGMA_RAD,
    RANGE_SIGMA_FRAC,
    RANGE_SIGMA_M,
    LandmarkObservation,
    Sightings,
    range_bearing,
    range_sigma,
    robust_log_likelihood,
)
from slam.motion import (
    Increment,
    MotionNoise,
    OdometryModel,
    apply_increment,
    increment_jacobians,
    propagate,
)
from slam.particle_paths import ParticlePaths
from slam.rts import rts_smooth
from slam.scan_proposal import (
    ProposalLattice,
    gaussian_fit,
    lattice,
    rotate_covariance,
    sample_gaussians,
)
from slam.trajectory import Trajectory, TrajectoryRecorder

ODOMETRY_ONLY_NOTE = "no landmark observations and no map: odometry only"
# A scored frame refreshes the likelihood field only once it is this many map_refresh_s
# old: a frame that is not scored refreshes it when due, so a scored one seldom pays
# for both (the per-frame cost's tail)
SCORED_REFRESH = 1.5
# The likelihood field covers the map within max_range_m + this of the walker when it is
# computed: room for the walker to move until the next refresh, and for the camera's
# offset from the walker origin.
FIELD_MARGIN_M = 1.5
_CROSS = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], dtype=np.uint8)


class PathSmoother(Choice):
    """The filter's trajectory: RTS-smoothed, the best particle's ancestry, or filtered."""

    RTS = "rts"
    ANCESTRY = "ancestry"
    NONE = "none"


class Proposal(Choice):
    """Where particles are drawn from: the motion model, or a scan match (module docstring)."""

    MOTION = "motion"
    SCAN = "scan"


@dataclass(frozen=True)
class ParticleSettings(KnownMapConfig):
    """What the particle filters here share (this one and slam.grid_rbpf's, which reuses
    its machinery: prediction, landmark weighting, resampling).

    initial_pose: (x, y, θ) at the first message (defines the map frame).
    initial_sigma: (σx [m], σy [m], σθ [rad]) of the initial particle cloud around it
        (0: the start is known exactly, as it is when it defines the map frame).
    n_particles: number of particles.
    noise: odometry noise the particles are drawn with (slam.motion.MotionNoise).
    range_sigma_m + range_sigma_frac·r, bearing_sigma_rad: landmark range-bearing noise
        (as EkfSlamConfig: an AprilTag camera's, slam.measurement.RANGE_SIGMA_M...).
    landmark_map: known landmarks {id: (x, y)}; filled from the trial log by
        `slam.base.create(..., landmark_map=...)`; None: landmarks are not used.
    use_landmarks: False ignores the landmark map (scans only, e.g. to study
        localization without tags on a trial whose log knows them).
    z_hit, z_rand: weights of a frame point's Gaussian around the map's occupied cells
        and of a uniform over max_range_m (z_rand keeps one stray point from vetoing a
        particle).
    max_beams: obstacle points scored per frame, subsampled at random (seeded).
    max_range_m: points farther than this from the sensor are not scored.
    min_points: score a frame only when at least this many of its points land in mapped
        cells (known to the grid); only those points are scored.
    scan_every_m, scan_every_rad: score a frame only once the odometry has moved this far
        or turned this much since the last scored frame (as AMCL's update_min_d/a):
        consecutive frames repeat the same evidence; 0, 0: every frame.
    seed: every random draw comes from numpy.random.default_rng(seed).
    resample_threshold: resample when N_eff < resample_threshold·n_particles.
    outlier_prob, outlier_range_m: the robust landmark likelihood (module docstring): the
        share ε of observations that are outliers, uniform over outlier_range_m of range
        and all bearings; 0 = the plain Gaussian.
    association_enabled: sightings without an ID are paired with the map's landmarks by
        each particle (module docstring); False: counted (`unknown_ids`) and not used.
    """

    initial_sigma: tuple[float, float, float] = (0.0, 0.0, 0.0)
    n_particles: int = 500
    noise: MotionNoise = field(default_factory=MotionNoise)
    range_sigma_m: float = RANGE_SIGMA_M
    range_sigma_frac: float = RANGE_SIGMA_FRAC
    bearing_sigma_rad: float = BEARING_SIGMA_RAD
    use_landmarks: bool = True
    z_hit: float = 0.9
    z_rand: float = 0.1
    max_beams: int = 60
    max_range_m: float = 3.5
    min_points: int = 10
    scan_every_m: float = 0.2
    scan_every_rad: float = 0.2
    seed: int = 0
    resample_threshold: float = 0.5
    outlier_prob: float = 0.01
    outlier_range_m: float = 10.0
    association_enabled: bool = True

    def __post_init__(self) -> None:
        if not 0.0 <= self.outlier_prob < 1.0 or self.outlier_range_m <= 0:
            raise ValueError("outlier_prob must be in [0, 1) and outlier_range_m > 0")
        if self.n_particles < 1:
            raise ValueError(f"n_particles must be >= 1, got {self.n_particles}")
        if len(self.initial_sigma) != 3 or min(self.initial_sigma) < 0:
            raise ValueError(f"initial_sigma must be three values >= 0, got {self.initial_sigma}")
        if not 0.0 <= self.resample_threshold <= 1.0:
            raise ValueError(f"resample_threshold must be in [0, 1], got {self.resample_threshold}")
        if self.max_range_m <= 0 or self.max_beams < 1:
            raise ValueError("max_range_m must be > 0, max_beams >= 1")
        if self.z_hit < 0 or self.z_rand <= 0:
            raise ValueError("need z_hit >= 0 and z_rand > 0 (the field's floor)")
        if self.scan_every_m < 0 or self.scan_every_rad < 0:
            raise ValueError("scan_every_m and scan_every_rad must be >= 0")


@dataclass(frozen=True)
class ParticleFilterConfig(ParticleSettings):
    """Particle filter (Monte Carlo localization) settings: ParticleSettings, and

    use_scans: weight by depth frames / laser scans against the attached occupancy map
        (`ParticleFilter.attach_map`). Off by default: against the shared map, which is
        built at this filter's own estimates, each frame's small matching error becomes
        part of the map the next frame is matched to, and on the simulated course that
        drifts more than the odometry does (see tests/slam/test_particle_filter.py).
    sigma_hit_m: σ of the likelihood field's Gaussian around occupied cells.
    beam_weight: exponent of each point's likelihood (< 1: neighbouring points are
        correlated). 0.3 makes the spread of one frame's likelihood about match the
        scatter of its best pose on the simulated course (60 points: σθ ≈ 0.85° at 1 vs
        1.4° measured).
    surfaces_only: measure distances to the surface cells of occupied regions (occupied
        cells next to non-occupied ones), not to their filled insides.
    map_refresh_s: recompute the distance transform when the one in use is this old
        (message time); the map changes a little with every frame. A frame that is not
        scored recomputes it when due; a scored one only once it is SCORED_REFRESH times
        as old, so that a scored frame seldom pays for both (BENCHMARKS.md).
    min_map_cells: score frames only once the map has at least this many occupied cells.
    smoother: "rts" | "ancestry" | "none": what `trajectory()` is (module docstring);
        path_snapshot_s: the ancestry's sampling interval.
    proposal: "motion" or "scan" (module docstring); for "scan", lattice: its search
        lattices and prior floor (slam.scan_proposal.ProposalLattice).
    absolute: compass / position-fix fusion (slam.absolute.AbsoluteConfig; off by
        default; module docstring).
    Frames are scored against the attached map, the one map that the pipeline builds at
    this filter's estimates (Monte Carlo localization); slam.grid_rbpf (`grid-rbpf`) is
    the Rao-Blackwellized filter with a map per particle.
    """

    use_scans: bool = False
    sigma_hit_m: float = 0.1
    beam_weight: float = 0.3
    surfaces_only: bool = True
    map_refresh_s: float = 0.5
    min_map_cells: int = 20
    smoother: PathSmoother = PathSmoother.RTS
    path_snapshot_s: float = 0.1
    proposal: Proposal = Proposal.MOTION
    lattice: ProposalLattice = field(default_factory=ProposalLattice)
    absolute: AbsoluteConfig = field(default_factory=AbsoluteConfig)

    def __post_init__(self) -> None:
        super().__post_init__()
        coerce(self, smoother=PathSmoother, proposal=Proposal)
        if self.sigma_hit_m <= 0:
            raise ValueError(f"sigma_hit_m must be > 0, got {self.sigma_hit_m}")
        if self.map_refresh_s < 0:
            raise ValueError(f"map_refresh_s must be >= 0, got {self.map_refresh_s}")


def systematic_resample(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Indices drawn by systematic resampling: one offset u ~ U[0, 1), positions
    (u + k)/N, index = the first j with cumsum(w)[j] > position. The algorithm of
    filterpy.monte_carlo.systematic_resample without its Python loop, drawing u from
    `rng` (filterpy draws from numpy's global generator)."""
    n = len(weights)
    cumulative = np.cumsum(weights)
    cumulative[-1] = 1.0  # no index past the end from rounding
    positions = (rng.random() + np.arange(n)) / n
    return np.searchsorted(cumulative, positions, side="right")


def _cholesky_2x2(cov: np.ndarray) -> tuple[float, float, float]:
    """(l00, l10, l11) of the lower Cholesky factor of a 2×2 PSD matrix; zero rows allowed
    (no motion, no noise)."""
    a, b, c = float(cov[0, 0]), float(cov[0, 1]), float(cov[1, 1])
    l00 = math.sqrt(max(a, 0.0))
    l10 = b / l00 if l00 > 0.0 else 0.0
    return l00, l10, math.sqrt(max(c - l10 * l10, 0.0))


def _drawn_step(
    poses: np.ndarray, ds: float, dtheta: float, cov: np.ndarray, z: np.ndarray
) -> np.ndarray:
    """poses (N, 3) moved along one odometry step's arc with its noise drawn: (ds, dθ) +
    L·z, L the Cholesky factor of its 2×2 covariance, z (2, N) standard normals."""
    l00, l10, l11 = _cholesky_2x2(cov)
    return apply_increment(poses, ds + l00 * z[0], dtheta + l10 * z[0] + l11 * z[1])


@dataclass(frozen=True, eq=False)
class _Field:
    """Per-cell log-likelihood of an obstacle point and whether the grid knows the cell,
    flattened, each with a last entry for points outside the grid; the grid's origin,
    resolution and shape when it was made."""

    log_p: np.ndarray
    known: np.ndarray
    origin: tuple[float, float]
    resolution: float
    shape: tuple[int, int]


class ParticleFilter(Localizer):
    """Monte Carlo localization (see the module docstring).

    map_source: the occupancy map the scan likelihood scores frames against — an
    `OccupancyMapper` (its `.grid` is read) or a grid itself; None: frames are not used.
    Set it with `attach_map` (the pipeline does, for its shared mapper).
    """

    def __init__(self, config: ParticleFilterConfig, calibration: WalkerCalibration) -> None:
        self.config = config
        # the parameters the filter machinery reads (the per-particle-map filter, which
        # reuses it, keeps its own config in `config`)
        self.pf: ParticleFilterConfig = config
        self.calibration = calibration
        self.odometry = OdometryModel(calibration, config.noise)
        self.rng = np.random.default_rng(config.seed)
        self.map_source: OccupancyMapper | GridExtent | None = None
        self._projector: OccupancyMapper | None = None  # frames given without the pipeline
        n = config.n_particles
        self.particles = np.array(config.initial_pose, dtype=float) + self.rng.standard_normal(
            (n, 3)
        ) * np.array(config.initial_sigma, dtype=float)
        self.particles[:, 2] = wrap_angle(self.particles[:, 2])
        self.log_weights = np.full(n, -math.log(n))
        self._weights = np.full(n, 1.0 / n)
        lm = (config.landmark_map or {}) if config.use_landmarks else {}
        self._landmark_index = {int(k): i for i, k in enumerate(lm)}
        self._landmarks = np.array([np.asarray(v, dtype=float)[:2] for v in lm.values()])
        self._landmarks = self._landmarks.reshape(-1, 2)
        self._gate = AssociationConfig().gate()
        self._field: _Field | None = None
        self._field_t = -math.inf  # message time the field was computed at
        self._field_table: tuple[float, int, np.ndarray] | None = None  # _log_p_table
        self._moved = (math.inf, math.inf)  # odometry (|ds|, |dθ|) since the last scored frame
        # proposal "scan": odometry since the particles were last drawn, in the frame of
        # the pose they were drawn at, and its covariance (slam.motion.propagate)
        self._odo_delta: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._odo_cov = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
        self._steps: list[tuple[float, float, np.ndarray]] = []  # each (ds, dθ, 2×2 cov)
        self.counts: dict[str, Any] = {
            "landmark_updates": 0,
            "landmark_observations": 0,
            "unknown_ids": 0,
            "associated": 0,
            "scan_updates": 0,
            "resamples": 0,
            "n_eff_min": float(n),
        }
        if self.pf.absolute.enabled:
            self.counts.update(compass_updates=0, position_updates=0)
        self.track = TrajectoryRecorder()
        self._resample_due = False  # weights changed since the last resampling check
        self._obs_t = -math.inf  # time of the observations weighted in since then
        self.sightings = Sightings(calibration)
        self.revises_past = config.smoother != "none"
        self.paths = ParticlePaths(config.path_snapshot_s)
        self._path_cache: tuple[tuple[int, float], Trajectory] | None = None
        # "rts": per recorded pose, the filtered mean and covariance and the odometry since
        # the previous one (in its frame, with its covariance)
        self._rts = config.smoother == "rts"
        self._f_cov: list[np.ndarray] = []
        self._f_delta: list[np.ndarray] = []
        self._f_delta_cov: list[np.ndarray] = []
        self._delta = np.zeros(3)
        self._delta_cov = np.zeros((3, 3))

    # -- the map the scan likelihood uses ------------------------------------------------
    def attach_map(self, source: OccupancyMapper | GridExtent | None) -> None:
        """Score depth frames / laser scans against `source`: an OccupancyMapper (its
        `.grid` is read at every frame, so the map may grow) or a fixed grid. None
        detaches."""
        self.map_source = source
        self._field, self._field_t = None, -math.inf

    def _grid(self) -> GridExtent | None:
        src = self.map_source
        return src.grid if isinstance(src, OccupancyMapper) else src

    # -- inputs ---------------------------------------------------------------------------
    def process(self, msg: Message) -> None:
        if (obs := self.sightings.offer(msg)) is not None:
            self._observe_landmarks(obs)  # the sightings of one time weigh them once
        if self.sightings.taken:
            pass  # held, to be used with the other sightings of its time
        elif (inc := self.odometry.increment(msg)) is not None:
            self._predict(inc)
            self._record(msg.t)
        elif (fix := absolute_observation(msg, self.pf.absolute)) is not None:
            self._observe_absolute(fix)
        elif isinstance(msg, DepthFrame | LaserScan):
            self._observe_frame(msg, self._project(msg))
        if not self.track and self.odometry.has_odometry:
            self._record(msg.t)

    def process_frame(self, msg: DepthFrame | LaserScan, projection: Projection) -> None:
        """A frame the pipeline projected already (as its mapper does)."""
        self._observe_frame(msg, projection)
        if not self.track and self.odometry.has_odometry:
            self._record(msg.t)

    def _project(self, msg: DepthFrame | LaserScan) -> Projection:
        """A frame given to `process` (no pipeline): projected as the attached mapper
        projects it, or with the mapper's defaults."""
        if isinstance(self.map_source, OccupancyMapper):
            return self.map_source.project(msg)
        if self._projector is None:
            self._projector = OccupancyMapper(self.calibration)
        return self._projector.project(msg)

    def _predict(self, inc: Increment) -> None:
        self._maybe_resample()
        if self.pf.proposal == "scan":
            self.particles = apply_increment(self.particles, inc.ds, inc.dtheta)
            self._odo_delta, self._odo_cov, _ = propagate(
                self._odo_delta, self._odo_cov, inc.ds, inc.dtheta, inc.cov
            )
            self._steps.append((inc.ds, inc.dtheta, inc.cov))
        else:
            z = self.rng.standard_normal((2, len(self.particles)))
            self.particles = _drawn_step(self.particles, inc.ds, inc.dtheta, inc.cov, z)
        if inc.unknown:  # it may have moved any distance: the next frame is scored
            self._moved = (math.inf, math.inf)
        else:
            self._moved = (self._moved[0] + abs(inc.ds), self._moved[1] + abs(inc.dtheta))
        if self._rts:
            f, g = increment_jacobians(float(self._delta[2]), inc.ds, inc.dtheta)
            self._delta = apply_increment(self._delta, inc.ds, inc.dtheta)
            self._delta_cov = f @ self._delta_cov @ f.T + g @ inc.cov @ g.T

    def _use_held(self) -> None:
        """An output is asked for: the sightings held are used as they are."""
        if (obs := self.sightings.take()) is not None:
            self._observe_landmarks(obs)

    def _observe_landmarks(self, obs: LandmarkObservation) -> None:
        if not len(obs):
            return
        known = [self._landmark_index.get(int(i)) for i in obs.ids]
        rows = [k for k, j in enumerate(known) if j is not None]
        pair = self.pf.association_enabled and len(self._landmarks) > 0
        unknown = [k for k, i in enumerate(obs.ids) if i < 0] if pair else []
        self.counts["unknown_ids"] += len(known) - len(rows) - len(unknown)
        if not rows and not unknown:
            return
        self._draw_odometry_noise(obs.t)
        c = self.pf
        z = obs.z[rows + unknown]  # (M, 2)
        sr = range_sigma(c, z[:, 0])  # (M,)
        log_gauss = np.empty((len(self.particles), len(z)))  # (N, M), without the normaliser
        k = len(rows)
        if rows:
            lm = self._landmarks[[known[i] for i in rows]]  # (M, 2)
            log_gauss[:, :k] = self._log_gauss(lm[None], z[:k], sr[:k])[:, 0]
        if unknown:
            log_gauss[:, k:] = self._paired(z[k:], sr[k:])
        if c.outlier_prob > 0.0:
            log_norm = -np.log(2.0 * math.pi * sr * c.bearing_sigma_rad)  # (M,)
            log_u = math.log(c.outlier_prob / (2.0 * math.pi * c.outlier_range_m))
            log_lik = robust_log_likelihood(log_gauss, log_norm, c.outlier_prob, log_u)
        else:
            log_lik = log_gauss
        self._update(np.sum(log_lik, axis=1), obs.t)
        self.counts["landmark_updates"] += 1
        self.counts["landmark_observations"] += len(z)

    def _log_gauss(self, lm: np.ndarray, z: np.ndarray, sr: np.ndarray) -> np.ndarray:
        """−½ of the squared normalised innovations of sightings z (M, 2) (range σ sr (M,))
        of landmarks lm (K, M or 1, 2) from every particle: (N, K, M)."""
        zhat = range_bearing(self.particles[:, None, None, :], lm[None])  # (N, K, M, 2)
        dr = (z[:, 0] - zhat[..., 0]) / sr
        db = wrap_angle(z[:, 1] - zhat[..., 1]) / self.pf.bearing_sigma_rad
        return -0.5 * (dr * dr + db * db)

    def _paired(self, z: np.ndarray, sr: np.ndarray) -> np.ndarray:
        """Sightings without an ID (M, 2): each particle's best map landmark for each,
        as −½ its squared normalised innovation (N, M); `associated` counts the sightings
        the heaviest particle pairs within the χ²(2) 99 % gate."""
        mean = self._mean()[:2]
        reach = float(np.max(np.hypot(*(self.particles[:, :2] - mean).T)))
        dist = np.hypot(*(self._landmarks - mean).T)
        slack = reach + 5.0 * float(sr.max())
        near = (dist <= z[:, 0].max() + slack) & (dist >= z[:, 0].min() - slack)
        if not near.any():
            return np.full((len(self.particles), len(z)), -np.inf)
        cand = self._landmarks[near][:, None, :]  # (K, 1, 2)
        best = self._log_gauss(cand, z, sr).max(axis=1)  # (N, M)
        heaviest = best[int(np.argmax(self.log_weights))]
        self.counts["associated"] += int(np.count_nonzero(-2.0 * heaviest <= self._gate))
        return best

    def _observe_absolute(self, obs: AbsoluteObservation) -> None:
        """Weight the particles by a compass heading's or a position fix's robust
        likelihood (slam.absolute)."""
        self._draw_odometry_noise(obs.t)
        self._update(obs.log_likelihood(self.particles, self.pf.absolute), obs.t)
        self.counts[f"{obs.kind}_updates"] += 1

    def _observe_frame(self, msg: DepthFrame | LaserScan, projection: Projection) -> None:
        c = self.pf
        if not c.use_scans or self.map_source is None:
            return
        scored = self._moved[0] >= c.scan_every_m or self._moved[1] >= c.scan_every_rad
        due = c.map_refresh_s * (SCORED_REFRESH if scored else 1.0)
        if (scored and self._field is None) or msg.t - self._field_t >= due:
            self._field = self._likelihood_field(self._grid(), self._mean())
            self._field_t = msg.t
        if not scored:
            return
        f = self._field
        if f is None:
            self._draw_odometry_noise(msg.t)
            return  # the map is still (nearly) empty
        points = self._points_in_range(projection.raw)
        # Only the points that land in mapped cells at the mean pose are scored, for every
        # particle alike: a point in unmapped space says nothing, and scoring it would
        # favour the particles that pull the frame's new parts onto what is already mapped.
        points = points[f.known[self._cells(self._mean()[None], points, f)[0]]]
        if len(points) < c.min_points:
            self._draw_odometry_noise(msg.t)
            return
        if c.proposal == "scan":
            self._scan_proposal(points, f, msg.t)
        else:
            self._update(self._score(self.particles, points, f), msg.t)
        self._moved = (0.0, 0.0)
        self.counts["scan_updates"] += 1

    def _score(self, poses: np.ndarray, points: np.ndarray, f: _Field) -> np.ndarray:
        """The frame's log-likelihood (times beam_weight) at each of the poses (M,)."""
        ny, nx = f.shape
        ox, oy = f.origin
        poses = np.ascontiguousarray(poses, dtype=float)
        points = np.ascontiguousarray(points, dtype=float)
        inv = 1.0 / f.resolution
        total = field_log_likelihood(f.log_p, ox, oy, inv, nx, ny, points, poses)
        return self.pf.beam_weight * total

    def _prior_cov(self) -> np.ndarray:
        """(N, 3, 3) world-frame covariance of each particle's accumulated odometry, with
        the floor: the odometry frame is the pose the particle was last drawn at."""
        floor = np.diag(np.square(self.pf.lattice.sigma_floor))
        anchor_heading = self.particles[:, 2] - self._odo_delta[2]
        return rotate_covariance(np.array(self._odo_cov) + floor, anchor_heading)

    def _draw_odometry_noise(self, t: float) -> None:
        """Proposal "scan": draw the odometry noise of every step since the last draw, for
        an observation of time t (grid-rbpf keeps the draw as a correction of its path), as
        "motion" would have drawn it: each step's own noise along its arc, from the pose
        of the last draw. Over a long stretch without observations the cloud bends with
        the heading's uncertainty, which one Gaussian of the accumulated covariance does
        not (MRCLAM robot 3's 40 s without a landmark: BENCHMARKS.md)."""
        if self.pf.proposal != "scan" or not any(self._odo_cov[i][i] for i in range(3)):
            return
        poses = compose(self.particles, inverse(np.array(self._odo_delta)))
        z = self.rng.standard_normal((len(self._steps), 2, len(poses)))
        for (ds, dtheta, cov), z_step in zip(self._steps, z, strict=True):
            poses = _drawn_step(poses, ds, dtheta, cov, z_step)
        self.particles = poses
        self._reset_odometry()

    def _reset_odometry(self) -> None:
        self._steps = []
        self._odo_delta = (0.0, 0.0, 0.0)
        self._odo_cov = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))

    def _scan_proposal(self, points: np.ndarray, f: _Field, t: float) -> None:
        """Draw every particle from odometry prior × frame likelihood (slam.scan_proposal)."""
        c = self.pf.lattice
        prior = self._prior_cov()
        mean = self._mean()
        spread = np.sqrt(np.diagonal(prior, axis1=1, axis2=2).max(axis=0))
        d = self.particles - mean
        d[:, 2] = wrap_angle(d[:, 2])
        spread = 3.0 * spread + np.abs(d).max(axis=0)
        steps = np.array([c.step_m, c.step_m, c.step_rad])
        lo = np.array([c.window_m[0]] * 2 + [c.window_rad[0]])
        hi = np.array([c.window_m[1]] * 2 + [c.window_rad[1]])
        half = np.ceil(np.clip(spread, lo, hi) / steps).astype(int)
        coarse = lattice(mean, tuple(half), steps)
        best = coarse[int(np.argmax(self._score(coarse, points, f)))]
        k = c.fine_steps
        fine = lattice(best, (k, k, k), steps / k)
        mu, cov, log_eta = gaussian_fit(
            fine, self._score(fine, points, f), self.particles, prior, steps / k
        )
        self.particles = sample_gaussians(mu, cov, self.rng)
        self._reset_odometry()
        self._update(log_eta, t)

    def _points_in_range(self, obs) -> np.ndarray:
        """Up to max_beams of an observation's obstacle points within max_range_m of its
        sensor (a random subset, from the filter's generator, when there are more)."""
        pts = np.asarray(obs.obstacles, dtype=float)
        rel = pts - obs.sensor_xy
        pts = pts[np.einsum("ij,ij->i", rel, rel) <= self.pf.max_range_m**2]
        k = self.pf.max_beams
        if len(pts) > k:
            pts = pts[np.sort(self.rng.choice(len(pts), size=k, replace=False))]
        return pts

    def _likelihood_field(self, grid: Any, centre: np.ndarray) -> _Field | None:
        """The field of the part of `grid` within FIELD_MARGIN_M + max_range_m of `centre`
        (all a frame scored before the next refresh can reach), or None when that part
        has fewer than min_map_cells occupied cells."""
        c = self.pf
        occupied = np.asarray(grid.occupied())
        ny, nx = occupied.shape
        res = float(grid.resolution)
        reach = c.max_range_m + FIELD_MARGIN_M
        ox, oy = grid.origin
        ix0, ix1 = (
            int(np.clip(math.floor((centre[0] + d - ox) / res), 0, nx)) for d in (-reach, reach)
        )
        iy0, iy1 = (
            int(np.clip(math.floor((centre[1] + d - oy) / res), 0, ny)) for d in (-reach, reach)
        )
        window = (slice(iy0, iy1 + 1), slice(ix0, ix1 + 1))
        occupied = occupied[window]
        if occupied.size == 0 or np.count_nonzero(occupied) < c.min_map_cells:
            return None
        if c.surfaces_only:
            # A depth or laser point lies on an obstacle's surface, not inside it: measure
            # the distance to the occupied cells that border non-occupied ones. (Scored
            # against filled obstacles, e.g. box tops seen from above, a point pushed into
            # an obstacle costs nothing and one pulled out costs, a bias.)
            # (OpenCV's erosion by the 4-neighbour cross, outside counted as occupied: the
            # same cells as scipy's binary_erosion(border_value=True), 13x faster)
            inner = cv2.erode(occupied.view(np.uint8), _CROSS, borderType=cv2.BORDER_CONSTANT,
                              borderValue=1)  # fmt: skip
            occupied = occupied & (inner == 0)
        cap, table = self._log_p_table(res)
        flat = log_likelihood_field(occupied, table, cap)  # last: outside the window
        known = np.asarray(grid.known())[window]
        return _Field(
            flat,
            np.append(known.ravel(), False),
            (ox + ix0 * res, oy + iy0 * res),
            res,
            occupied.shape,
        )

    def _log_p_table(self, res: float) -> tuple[int, np.ndarray]:
        """(cap, table) for grid_kernels.log_likelihood_field on a grid of `res` [m]:
        table[k] = log(p_hit·N(d; 0, σ_hit) + p_rand) at d = √k cells (√ rounded to
        float32, as OpenCV's exact distance transform gives it to within its last bit),
        for k up to cap², where cap [cells]
        is the least distance from which the Gaussian no longer changes the sum's last
        bit: every cell further out is log(p_rand) exactly, so its distance is not
        needed. Made once per resolution."""
        if self._field_table is None or self._field_table[0] != res:
            c = self.pf
            p_hit = c.z_hit / (math.sqrt(2.0 * math.pi) * c.sigma_hit_m)
            p_rand = c.z_rand / c.max_range_m

            def log_p(d2: np.ndarray) -> np.ndarray:
                dist = np.sqrt(np.asarray(d2, dtype=np.float32)).astype(float) * res
                return np.log(p_hit * np.exp(-0.5 * (dist / c.sigma_hit_m) ** 2) + p_rand)

            cap = 1
            while log_p(np.array([cap * cap]))[0] != math.log(p_rand):
                cap += 1
            self._field_table = (res, cap, log_p(np.arange(cap * cap + 1)))
        return self._field_table[1], self._field_table[2]

    def _cells(self, poses: np.ndarray, points: np.ndarray, f: _Field) -> np.ndarray:
        """Flat field indices (N, K) of K walker-frame points placed at N poses."""
        p = poses
        c, s = np.cos(p[:, 2:3]), np.sin(p[:, 2:3])
        px, py = points[None, :, 0], points[None, :, 1]
        inv = 1.0 / f.resolution
        fx = (p[:, 0:1] + c * px - s * py - f.origin[0]) * inv  # (N, K), in cells
        fy = (p[:, 1:2] + s * px + c * py - f.origin[1]) * inv
        ix = np.floor(fx).astype(np.intp)
        iy = np.floor(fy).astype(np.intp)
        ny, nx = f.shape
        inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        return np.where(inside, iy * nx + ix, ny * nx)

    def _update(self, log_likelihood: np.ndarray, t: float) -> None:
        """Add per-particle log-likelihoods and normalise; the pose recorded at time t (if
        any) becomes the updated estimate. Resampling waits until the observations of
        time t are all in (`_maybe_resample`: before the next motion or a later one)."""
        if t != self._obs_t:
            self._maybe_resample()
            self._obs_t = t
        lw = self.log_weights + log_likelihood
        top = lw.max()  # normalised by log Σ exp (scipy's logsumexp: 150 µs on 500)
        w = np.exp(lw - top)
        total = w.sum()
        lw -= top + math.log(total)
        w /= total
        n_eff = 1.0 / float(np.dot(w, w))
        self.counts["n_eff_min"] = min(self.counts["n_eff_min"], n_eff)
        self.log_weights, self._weights = lw, w
        self._resample_due = True
        self.revision += 1
        if self.track.last_t == t:
            mean, cov = self._moments()
            self.track.amend(mean)
            if self._rts:
                self._f_cov[-1] = cov

    def _maybe_resample(self) -> None:
        """Systematic resampling when N_eff < resample_threshold·N (after observations)."""
        if not self._resample_due:
            return
        self._resample_due = False
        n = len(self._weights)
        if self.n_eff >= self.pf.resample_threshold * n:
            return
        idx = systematic_resample(self._weights, self.rng)
        if self.pf.smoother == "ancestry":
            self.paths.resampled(idx)
        self.particles = self.particles[idx]
        self._resampled(idx)
        self.log_weights = np.full(n, -math.log(n))
        self._weights = np.full(n, 1.0 / n)
        self.counts["resamples"] += 1

    def _resampled(self, parents: np.ndarray) -> None:
        """After resampling: the new particle k is a copy of the old particle parents[k]
        (for what subclasses keep per particle)."""

    @property
    def weights(self) -> np.ndarray:
        """Normalised particle weights (N,)."""
        self._use_held()
        return self._weights.copy()

    @property
    def n_eff(self) -> float:
        """Effective sample size 1/Σw²."""
        self._use_held()
        return 1.0 / float(np.dot(self._weights, self._weights))

    # -- outputs -------------------------------------------------------------------------
    def _mean(self) -> np.ndarray:
        w, p = self._weights, self.particles
        th = math.atan2(float(w @ np.sin(p[:, 2])), float(w @ np.cos(p[:, 2])))
        return np.array([float(w @ p[:, 0]), float(w @ p[:, 1]), th])

    def _moments(self) -> tuple[np.ndarray, np.ndarray]:
        """Weighted mean (circular in θ) and covariance of the particles."""
        mean = self._mean()
        d = self.particles - mean
        d[:, 2] = wrap_angle(d[:, 2])
        cov = (d * self._weights[:, None]).T @ d
        if self.pf.proposal == "scan":  # the odometry noise not drawn yet
            cov = cov + rotate_covariance(np.array(self._odo_cov), mean[2:3])[0]
        return mean, 0.5 * (cov + cov.T)

    def _record(self, t: float) -> None:
        if not self._rts:
            self.track.record(t, self._mean())
        else:
            mean, cov = self._moments()
            n = len(self.track)
            self.track.record(t, mean)
            if len(self.track) > n:  # a new time: a new step of the smoother
                self._f_cov.append(cov)
                self._f_delta.append(self._delta)
                self._f_delta_cov.append(self._delta_cov)
                self._delta, self._delta_cov = np.zeros(3), np.zeros((3, 3))
            elif self.track.last_t == t:  # the same time again: the last step, updated
                self._f_cov[-1] = cov
        if self.pf.smoother == "ancestry":
            self.paths.snapshot(t, self.particles)

    def estimate(self) -> PoseEstimate:
        self._use_held()
        mean, cov = self._moments()
        return PoseEstimate(self.track.last_t, mean, cov)

    def trajectory(self) -> Trajectory:
        """The smoothed path (config.smoother) or the filtered means."""
        self._use_held()
        if not self.revises_past or not self.track:
            return self.track.trajectory()
        key = (self.revision, self.track.last_t)
        if self._path_cache is None or self._path_cache[0] != key:
            if self._rts:
                filtered = self.track.trajectory()
                poses = rts_smooth(
                    filtered.poses,
                    np.array(self._f_cov),
                    np.array(self._f_delta),
                    np.array(self._f_delta_cov),
                )
                traj = Trajectory(filtered.t, poses)
            else:
                traj = self.paths.mean_path(self._weights, self.track.last_t, self.particles)
            self._path_cache = (key, traj)
        return self._path_cache[1]

    def diagnostics(self) -> dict:
        self._use_held()
        notes = {**self.counts, **self.odometry.diagnostics()}
        notes["particles"] = len(self.particles)
        c = self.counts
        absolute = fused_count(c)
        if c["landmark_observations"] == 0 and c["scan_updates"] == 0 and absolute == 0:
            notes["note"] = ODOMETRY_ONLY_NOTE
        return notes


SPEC = Spec(
    "particle-filter",
    ParticleFilterConfig,
    ParticleFilter,
    "Monte Carlo localization: known landmark map and/or a likelihood field of the shared "
    "map (the per-particle-map filter is grid-rbpf)",
)
