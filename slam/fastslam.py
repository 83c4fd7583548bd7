"""FastSLAM 1.0 and 2.0 (thesis Appendix A; Montemerlo et al.), with known data association
or each particle its own.

Each of N particles holds a walker pose and, per landmark, a small EKF (mean and
covariance). Everything is stored as arrays; the motion is numpy on all particles at
once, the observation step one compiled loop per stage (slam.fastslam_kernels: at 100
particles numpy's per-call cost was most of the step):

    poses        (N, 3)        x, y, θ
    log_weights  (N,)          normalised (logsumexp = 0)
    means        (N, L, D)     landmark means (D = 2: u, v; D = 3 with the tag's yaw ψ)
    covs         (N, L, D, D)  landmark covariances
    seen         (N, L)        whether the particle has initialised landmark column l
    index        {id: column}  grows with new ids; the arrays re-allocate by doubling
    reserved     (L,)          the columns of `index` (a known ID's column is the same in
                               every particle)
    hits, born   (N, L)        sightings of, and time of the first sighting of, a landmark
                               a particle found itself (below)
    pending      (N, 3, 3)     2.0 only: motion covariance since the particle's last sample

Memory is N·L·(D + D²) floats for the map (100 particles × 32 tags × 6 = 150 kB) and one
pose per odometry message for the filtered track (the weighted mean pose, revised in
place when an observation at that time moves it, as EKF-SLAM does); the smoothers keep
the particles' poses every path_snapshot_s (slam.particle_paths) and the state's moments
at every update (below, "Smoothing"). Resampling copies the
landmark arrays by fancy indexing, O(N·L) each time (no shared landmark trees): fine for
tens of tags, the thing to change for maps of thousands of landmarks.

Motion. 1.0 samples every odometry increment: (ds, dθ) + L·ε with L the Cholesky factor
of the increment's 2×2 covariance, moved along the exact arc (`apply_increment`).
2.0 moves each particle by the noise-free increment and accumulates the linearised motion
covariance in pose space, P ← F P Fᵀ + G Q Gᵀ (F, G at each particle's heading); the pose
is sampled at the next observation, from the proposal that includes it. With odometry at
50 Hz and tags at 10 Hz, P is thus "the motion covariance of the increment" since the
previous sample, which is what the proposal needs; without any observation the particles
stay on the dead-reckoned path and P is its covariance.

Observation z of landmark l from pose s (range-bearing, or tag pose = range, bearing and
the tag's yaw in the walker frame; the tag-pose model and its inverse are defined here,
beside the range-bearing ones of slam.measurement), with G_s = ∂h/∂s, G_l = ∂h/∂l and
noise R(z):

    Q = R + G_l Σ_l G_lᵀ,  S = G_s P G_sᵀ + Q,  ν = z − h(ŝ, l)
    2.0 proposal  Σ = [G_sᵀ Q⁻¹ G_s + P⁻¹]⁻¹ = P − K S Kᵀ,  μ = ŝ + Σ G_sᵀ Q⁻¹ ν = ŝ + K ν,
                  K = P G_sᵀ S⁻¹ (the same Gaussian in Kalman form: no P⁻¹, so a singular P,
                  e.g. a walker standing still, needs no special case)
    weight        w ← w · N(ν; 0, S)            (1.0: P = 0, so S = Q and μ = ŝ)

Several observations of one time — in one message (a frame's tags), or in consecutive
messages with the same timestamp (range-bearing datasets such as MRCLAM give each its
own message: slam.measurement.Sightings holds them until a message of another time or
kind, or until an output is asked for) — refine the proposal one after another (each
linearised at the refined mean, each weighting the particle by its predictive density,
whose product is the joint likelihood); then the pose is sampled once, every landmark
seen is updated with an EKF step at the sampled pose, and new landmarks are initialised
from the inverse model with covariance J_z R J_zᵀ (weight unchanged).

Gate: an observation is dropped (and counted) when it is implausible under the filter's
predictive distribution of z, the weighted mixture Σ w_i N(ẑ_i, S_i) matched to one
Gaussian: (ν̄ᵀ C⁻¹ ν̄ > gate_chi2). A per-particle gate would let a drifted particle
ignore exactly the observation that should remove it.

What to expect (BENCHMARKS.md; five simulated course trials with slip, defaults and the
trials' proposed odometry noise, 3 seeds): 2.0 aligned ATE 0.073 m, unaligned 0.108 m
(dead reckoning 0.58 / 1.26 m), phantom area −91 %; 1.0 is far behind (seed 2: 0.27 /
0.52 m, −35 %): sampling the motion model alone, its particles rarely land where the
tags say, and the weights then pick from a poor set.

Sightings without an ID (ID −1: Victoria Park's trees, laser corners; range-bearing
only) are associated by each particle against its own map (slam.fastslam_kernels.
associate: maximum likelihood with mutual exclusion, the χ² gates of slam.association,
a particle that pairs nothing weighted by the density of a new landmark at the gate), so
that the particles carry different associations and resampling keeps the ones the
sightings agree with (Montemerlo et al. 2003). The gates to a confirmed landmark are
widened by `association.inflation` (slam.association: a particle's own covariances do
not hold the drift since a landmark was last seen; on the issue-13 drive without IDs
13 landmarks for 8 without it, exactly 8 with it); the weights and the updates use the
particle's own covariances. A sighting farther than `new_prob` from
every landmark of a particle starts a landmark in a free column of that particle; the
landmark is provisional until seen `confirm_sightings` times and is dropped (its column
freed) when it is not within `provisional_max_age_s` — the particle's own version of
slam.association.Provisional. `landmarks()` gives the best particle's confirmed ones
with IDs FIRST_ASSOCIATED_ID + column (beside the known IDs); the diagnostics'
association counts (associated, new, ambiguous, provisional_dropped, provisional_pending)
are averages over the particles, map_landmarks the size of the best particle's map (as
`landmarks()`, and as EKF-SLAM's and gtsam's count).

The map (`landmarks()`) of a known ID is the particles' weighted mean of that landmark
(over the particles that have seen it, their weights renormalised), with the weighted
mean of their covariances plus the spread of their means: the estimate that goes with
the weighted-mean path, as EKF-SLAM's map goes with its mean. A single particle's map
carries that particle's own path noise: with the weight gain, whose weights select
slowly, the highest-weight particle's map was 3–5× further from the truth than the mean
(BENCHMARKS.md). Landmarks a particle found itself have no common column, so those are
the highest-weight particle's.

Smoothing (`smoother="rts-full"`, the default). Each pose is filtered against its
particles' maps of the time; the final map, built from all the sightings, is better, and
the ancestry paths (`"ancestry"`) carry one particle's motion noise in the old past. The
particles at each update are summarised by their weighted moments over the state [pose
(and slip coefficients), the known IDs' landmarks (u, v, and ψ with "tag-pose")]: the
mean, and the covariance of the particles' spread plus their motion covariance not yet
sampled (2.0) and their landmark covariances. Between two updates the same particles
only move, so the prediction's relation to the state before is the particles' own
cross-covariance (statistical linearisation). The Rauch–Tung–Striebel pass of
slam.state_smoother (EKF-SLAM's, in its form for moments) then carries the final map
back to every update's pose, and the odometry between updates is bridged as EKF-SLAM's.
MRCLAM dataset 7, robots 1–5 (seed 0): ATE 0.138 m by the ancestry paths, 0.115 m smoothed
(filtered means 0.248 m; EKF-SLAM's filtered means 0.148 m, smoothed 0.064 m); issue 13's
landmark drive: 0.079–0.106 m against 0.100–0.130 m (tests/slam/test_fastslam.py). It
needs the landmarks' columns common to all particles: once sightings without an ID are
used, and past smoother_budget_mb, the trajectory is the ancestry paths' (kept alongside)
and the diagnostics say so.

Resampling: systematic (as `filterpy.monte_carlo.systematic_resample`, but drawing its
one uniform from the filter's generator so a run is reproducible from `seed`) when the
effective sample size 1 / Σ w² falls below resample_threshold · N.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from hardware.calibration import WalkerCalibration
from hardware.choices import Choice, coerce
from hardware.geometry import wrap_angle
from hardware.messages import Message
from hardware.registry import Spec
from slam import fastslam_kernels as kernels
from slam.association import CHI2_999, FIRST_ASSOCIATED_ID, AssociationConfig
from slam.base import Localizer, LocalizerConfig, PoseEstimate
from slam.measurement import (
    BEARING_SIGMA_RAD,
    RANGE_SIGMA_FRAC,
    RANGE_SIGMA_M,
    LandmarkObservation,
    ObservationModel,
    Sightings,
    landmark_from_range_bearing,
    landmark_from_range_bearing_jacobians,
    range_bearing,
    range_bearing_jacobians,
    range_sigma,
)
from slam.motion import (
    Increment,
    MotionNoise,
    OdometryModel,
    apply_increment,
    sinc_and_derivative,
    split_increment,
)
from slam.particle_paths import ParticlePaths
from slam.rts import rts_smooth
from slam.slip import SlipEstimation, increment_with_slip, slip_diagnostics
from slam.state_smoother import (
    StateSmoother,
    StepOdometry,
    bridge,
    bridge_covariances,
    epoch_step,
)
from slam.trajectory import Trajectory, TrajectoryRecorder

__all__ = [
    "FastSlam",
    "FastSlamConfig",
    "FastSlamSmoother",
    "landmark_from_tag_pose",
    "landmark_from_tag_pose_jacobians",
    "propagate_linearised",
    "systematic_resample",
    "tag_pose",
    "tag_pose_jacobians",
]


class FastSlamSmoother(Choice):
    """FastSLAM's trajectory: its whole state RTS-smoothed over the particles' moments,
    the particles' ancestry paths, or the filtered means."""

    RTS_FULL = "rts-full"
    ANCESTRY = "ancestry"
    NONE = "none"


@dataclass(frozen=True)
class FastSlamConfig(LocalizerConfig):
    """FastSLAM settings.

    initial_pose: (x, y, θ), known exactly (it defines the map frame).
    n_particles: number of particles (the thesis ran 100). 300 was chosen from 100 / 200 /
    300 / 500 on ten simulated dusty trials and MRCLAM dataset 1 (BENCHMARKS.md,
    "FastSLAM's particle count"): with 100 the particles that survive the first
    resamplings carry one heading for the map, and the map's frame turns with it.
    version: 1 (sample the motion model, weight by the observation) or 2 (sample from the
    observation-informed proposal).
    noise: odometry noise (slam.motion.MotionNoise).
    range_sigma_m + range_sigma_frac·r: range noise; bearing_sigma_rad: bearing noise (as
    EkfSlamConfig: defaults an AprilTag camera's, slam.measurement.RANGE_SIGMA_M...).
    observation: "range-bearing" uses (r, b) of every observation; "tag-pose" also uses the
    tag's yaw in the walker frame (TagDetections), each landmark then carries its yaw ψ;
    observations without a yaw (RangeBearing messages) are skipped and counted.
    yaw_sigma_rad + yaw_sigma_per_m2·r²: tag-yaw noise ("tag-pose" only). The defaults
    fit the simulated tag camera (0.5 px corner noise, 0.165 m tags: σ ≈ 0.03 rad at 1 m,
    0.13 at 2 m, 0.3 at 3 m; heavy-tailed, with pose flips of up to 1.7 rad far away).
    gate_chi2: Mahalanobis gate of an observation; None = the 99.9 % χ² quantile for the
    observation's dimension (13.8 for range-bearing, 16.3 for tag pose); inf disables.
    resample_threshold: resample when N_eff < resample_threshold · n_particles.
    weight_gain: each observation's log-likelihood is divided by it before it enters the
    weights (GMapping's "ogain"; the proposal uses the full likelihood). A tag seen at
    10 Hz for seconds has errors shared by its frames (PnP bias, the same viewpoint), so
    multiplying the frames' likelihoods as independent makes the weights far too sure;
    resampling then keeps one particle's frame of the map early, and the map inherits its
    heading error (BENCHMARKS.md, "Simulated course"). 1: the textbook weights. 20 was
    chosen on simulated trials of seeds 1–2 (from 1, 3, 5, 10, 20, 40).
    seed: seed of the numpy Generator behind every random draw.
    smoother: what `trajectory()` is (the past then changes with every update:
    `revises_past`, and the pipeline rebuilds the map along it):
    "rts-full" (default): the whole state — pose (and slip coefficients) and the known
    IDs' landmarks — RTS-smoothed over the run (slam.state_smoother) from the particles'
    weighted moments at each update: every pose takes the final map, as EKF-SLAM's
    smoother gives it (module docstring, "Smoothing"); "ancestry": the weighted mean of
    the particles' whole paths, read back through resampling (slam.particle_paths),
    sampled every path_snapshot_s, whose old past is one particle's path with that
    particle's motion noise; "none": the filtered mean at each odometry message, which
    jumps whenever the weights shift.
    smoother_budget_mb: memory for "rts-full"'s moments (one n × n covariance per update,
    n = 3 + 2 · landmarks); past it, and once sightings without an ID are used (each
    particle's own landmarks have no common column), the trajectory is "ancestry"'s.
    slip: per-wheel slip estimation (slam.slip.SlipEstimation; `slip.estimate=true`):
    each particle carries its own (k_left, k_right), drawn from the prior and moved by
    the random walk with every odometry message; it moves the particle by its slip-
    corrected arc, so the weights select the k that the tags agree with; the estimate is
    the particles' weighted mean.
    align_observations: the observations held for the next odometry message (see above)
    are used part way through its increment, at their own time
    (slam.motion.split_increment), not at the pose of the message before them.
    association_enabled, association: sightings without an ID, each particle's own
    association (module docstring; slam.association.AssociationConfig: its gate_prob,
    new_prob, confirm_sightings, provisional_max_age_s and inflation; `method` is
    EKF-SLAM's). False: they are counted and not used.
    """

    n_particles: int = 300
    version: int = 2
    noise: MotionNoise = field(default_factory=MotionNoise)
    range_sigma_m: float = RANGE_SIGMA_M
    range_sigma_frac: float = RANGE_SIGMA_FRAC
    bearing_sigma_rad: float = BEARING_SIGMA_RAD
    observation: ObservationModel = ObservationModel.RANGE_BEARING
    yaw_sigma_rad: float = 0.02
    yaw_sigma_per_m2: float = 0.03
    gate_chi2: float | None = None
    resample_threshold: float = 0.5
    seed: int = 0
    smoother: FastSlamSmoother = FastSlamSmoother.RTS_FULL
    smoother_budget_mb: float = 256.0
    path_snapshot_s: float = 0.1
    weight_gain: float = 20.0
    slip: SlipEstimation = field(default_factory=SlipEstimation)
    align_observations: bool = False
    association_enabled: bool = True
    association: AssociationConfig = field(default_factory=AssociationConfig)

    def __post_init__(self) -> None:
        if self.version not in (1, 2):
            raise ValueError(f"version must be 1 or 2, got {self.version!r}")
        if int(self.n_particles) != self.n_particles or self.n_particles < 1:
            raise ValueError(f"n_particles must be a positive integer, got {self.n_particles!r}")
        coerce(self, observation=ObservationModel, smoother=FastSlamSmoother)
        if not self.smoother_budget_mb > 0:
            raise ValueError(f"smoother_budget_mb must be > 0, got {self.smoother_budget_mb}")
        if not self.weight_gain >= 1.0:
            raise ValueError(f"weight_gain must be >= 1, got {self.weight_gain}")
        if not 0.0 <= self.resample_threshold <= 1.0:
            raise ValueError(f"resample_threshold must be in [0, 1], got {self.resample_threshold}")
        if self.gate_chi2 is not None and not self.gate_chi2 > 0:
            raise ValueError(f"gate_chi2 must be > 0 (or None), got {self.gate_chi2}")
        sigmas = (self.range_sigma_m, self.bearing_sigma_rad, self.yaw_sigma_rad)
        if min(sigmas) <= 0 or min(self.range_sigma_frac, self.yaw_sigma_per_m2) < 0:
            raise ValueError("observation noise must be positive")


# -- the tag-pose measurement model ---------------------------------------------------------
# (range-bearing lives in slam.measurement; these extend it by the tag's yaw ψ, the heading
# of its outward normal, seen in the walker frame as ψ − θ.)


def tag_pose(pose: np.ndarray, landmark: np.ndarray) -> np.ndarray:
    """h(s, l) for a tag l = (u, v, ψ): (..., 3) range, bearing and yaw in the walker frame."""
    rb = range_bearing(pose, landmark)
    yaw = wrap_angle(landmark[..., 2] - pose[..., 2])
    return np.concatenate([rb, np.asarray(yaw)[..., None]], axis=-1)


def tag_pose_jacobians(pose: np.ndarray, landmark: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(∂h/∂s (..., 3, 3), ∂h/∂l (..., 3, 3)) of `tag_pose`."""
    g_s2, g_l2 = range_bearing_jacobians(pose, landmark)
    shape = g_s2.shape[:-2]
    g_s = np.zeros((*shape, 3, 3))
    g_l = np.zeros((*shape, 3, 3))
    g_s[..., :2, :] = g_s2
    g_s[..., 2, 2] = -1.0
    g_l[..., :2, :2] = g_l2
    g_l[..., 2, 2] = 1.0
    return g_s, g_l


def landmark_from_tag_pose(pose: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Inverse of `tag_pose`: the tag (u, v, ψ) (..., 3) that explains z from pose."""
    uv = landmark_from_range_bearing(pose, z)
    psi = wrap_angle(pose[..., 2] + z[..., 2])
    return np.concatenate([uv, np.asarray(psi)[..., None]], axis=-1)


def landmark_from_tag_pose_jacobians(
    pose: np.ndarray, z: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(∂l/∂s (..., 3, 3), ∂l/∂z (..., 3, 3)) of `landmark_from_tag_pose`."""
    j_s2, j_z2 = landmark_from_range_bearing_jacobians(pose, z)
    shape = j_s2.shape[:-2]
    j_s = np.zeros((*shape, 3, 3))
    j_z = np.zeros((*shape, 3, 3))
    j_s[..., :2, :] = j_s2
    j_s[..., 2, 2] = 1.0
    j_z[..., :2, :2] = j_z2
    j_z[..., 2, 2] = 1.0
    return j_s, j_z


# -- vectorised helpers ---------------------------------------------------------------------


def _sinc_half(dtheta: float) -> tuple[float, float]:
    """S(u) = sin(u)/u and S'(u) at u = dθ/2 (as slam.motion, on a float)."""
    u = 0.5 * dtheta
    if abs(u) < 1e-4:
        return 1.0 - u * u / 6.0, -u / 3.0
    return math.sin(u) / u, (u * math.cos(u) - math.sin(u)) / (u * u)


def propagate_linearised(
    poses: np.ndarray,
    pending: np.ndarray,
    ds: float | np.ndarray,
    dtheta: float | np.ndarray,
    q: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Move poses (N, 3) along the noise-free arc (ds, dθ) (one for all, or (N,) each) and
    their motion covariances (N, 3, 3) by P ← F P Fᵀ + G Q Gᵀ, with F, G of
    `slam.motion.increment_jacobians` at each pose's heading. Written out on the entries
    (this runs for every odometry message): F is the identity but for F[0, 2] = −dy and
    F[1, 2] = dx."""
    n = len(poses)
    if np.ndim(dtheta) == 0:
        s, s_prime = _sinc_half(dtheta)
    else:  # one increment per particle (slip estimation)
        s, s_prime = sinc_and_derivative(0.5 * np.asarray(dtheta))
    chord, dchord = ds * s, 0.5 * ds * s_prime
    h = poses[:, 2] + 0.5 * dtheta
    c, sn = np.cos(h), np.sin(h)
    dx, dy = chord * c, chord * sn
    a, b = -dy, dx
    f = pending.reshape(n, 9)
    p22 = f[:, 8]
    n02 = f[:, 2] + a * p22
    n12 = f[:, 5] + b * p22
    out = np.empty((n, 9))
    out[:, 0] = f[:, 0] + a * (f[:, 2] + n02)
    out[:, 4] = f[:, 4] + b * (f[:, 5] + n12)
    out[:, 1] = out[:, 3] = f[:, 1] + a * f[:, 5] + b * n02
    out[:, 2] = out[:, 6] = n02
    out[:, 5] = out[:, 7] = n12
    out[:, 8] = p22
    p = out.reshape(n, 3, 3)
    # G Q Gᵀ with the columns u = ∂pose'/∂ds and v = ∂pose'/∂dθ of G
    u = np.zeros((n, 3))
    v = np.ones((n, 3))
    u[:, 0], u[:, 1] = s * c, s * sn
    v[:, 0], v[:, 1] = dchord * c - 0.5 * dy, dchord * sn + 0.5 * dx
    uq = q[0, 0] * u + q[0, 1] * v
    vq = q[0, 1] * u + q[1, 1] * v
    p += uq[:, :, None] * u[:, None, :] + vq[:, :, None] * v[:, None, :]
    moved = np.empty_like(poses)
    moved[:, 0] = poses[:, 0] + dx
    moved[:, 1] = poses[:, 1] + dy
    moved[:, 2] = wrap_angle(poses[:, 2] + dtheta)
    return moved, p


def systematic_resample(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Indices drawn by systematic resampling of normalised `weights`.

    The algorithm of `filterpy.monte_carlo.systematic_resample` (positions (u + i) / N
    with one uniform u; index i takes the first j whose cumulative weight exceeds it),
    vectorised, with u from `rng` rather than numpy's global state.
    """
    n = len(weights)
    positions = (rng.random() + np.arange(n)) / n
    cumulative = np.cumsum(weights)
    cumulative[-1] = 1.0  # guard against round-off leaving the last position uncovered
    return np.minimum(np.searchsorted(cumulative, positions, side="right"), n - 1)


def _cholesky2(cov: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor of a 2×2 positive semi-definite matrix (zero rows allowed)."""
    a, b, d = float(cov[0, 0]), float(cov[0, 1]), float(cov[1, 1])
    l00 = math.sqrt(max(a, 0.0))
    l10 = b / l00 if l00 > 0.0 else 0.0
    return np.array([[l00, 0.0], [l10, math.sqrt(max(d - l10 * l10, 0.0))]])


def _symmetric(a: np.ndarray) -> np.ndarray:
    return 0.5 * (a + np.swapaxes(a, -1, -2))


class FastSlam(Localizer):
    def __init__(self, config: FastSlamConfig, calibration: WalkerCalibration) -> None:
        self.config = config
        self.calibration = calibration
        self.odometry = OdometryModel(calibration, config.noise)
        self.rng = np.random.default_rng(config.seed)
        n = int(config.n_particles)
        self.n = n
        self.dim = 3 if config.observation == "tag-pose" else 2
        self.gate = config.gate_chi2 if config.gate_chi2 is not None else CHI2_999[self.dim]
        pose0 = np.array(config.initial_pose, dtype=float)
        pose0[2] = wrap_angle(pose0[2])
        self.poses = np.tile(pose0, (n, 1))
        self.log_weights = np.full(n, -math.log(n))
        self._w = np.full(n, 1.0 / n)  # normalised linear weights, kept in step
        self.pending = np.zeros((n, 3, 3))
        self.index: dict[int, int] = {}
        cap = 8
        self.means = np.zeros((n, cap, self.dim))
        self.covs = np.zeros((n, cap, self.dim, self.dim))
        self.seen = np.zeros((n, cap), dtype=bool)
        self.reserved = np.zeros(cap, dtype=bool)
        self.hits = np.zeros((n, cap), dtype=np.int32)
        self.born = np.zeros((n, cap))
        self.counts = {
            "updates": 0,
            "new_landmarks": 0,
            "gated": 0,
            "without_id": 0,
            "resamples": 0,
        }
        if self.dim == 3:
            self.counts["without_yaw"] = 0
        self._associates = config.association_enabled and self.dim == 2
        self._found = {"associated": 0, "ambiguous": 0, "new": 0, "provisional_dropped": 0}
        self.n_eff = float(n)
        self.n_eff_min = float(n)
        self.track = TrajectoryRecorder()
        self.revises_past = config.smoother != FastSlamSmoother.NONE
        self.paths = ParticlePaths(config.path_snapshot_s)
        self._path_cache: tuple[tuple[int, float], Trajectory] | None = None
        self.sightings = Sightings(calibration)
        self._aligned: list[LandmarkObservation] = []  # align_observations: not yet used
        slip = config.slip
        self.k: np.ndarray | None = None  # (N, 2) each particle's slip coefficients
        if slip.estimate:
            self.k = np.asarray(slip.k_prior) + slip.k_sigma * self.rng.standard_normal((n, 2))
        # "rts-full": the moments at every update, and the odometry of every step
        self._full: StateSmoother | None = None
        self._full_stopped = ""  # why the run fell back to the ancestry paths
        if config.smoother == FastSlamSmoother.RTS_FULL:
            top = 3 if self.k is None else 5
            self._full = StateSmoother(top, config.smoother_budget_mb * 1e6, self.dim)
            self._steps = StepOdometry()
            self._end = self._moments()  # the state the next prediction starts from

    # -- inputs -----------------------------------------------------------------------
    def process(self, msg: Message) -> None:
        if (obs := self.sightings.offer(msg)) is not None:
            self._sighted(obs)
        if self.sightings.taken:
            self.revision += 1  # held; the past will change when they are used
        elif (inc := self.odometry.increment(msg)) is not None:
            for obs in self._aligned:  # sightings made since the last odometry message
                part, inc = split_increment(inc, obs.t)
                self._move(part)
                self._use(obs, between=True)
            self._aligned = []
            self._move(inc)
            self._record(msg.t)
        if not self.track and self.odometry.has_odometry:
            self._record(msg.t)

    def _sighted(self, obs: LandmarkObservation) -> None:
        """The landmark sightings of one time (slam.measurement.Sightings)."""
        if self.config.align_observations and self.track and obs.t > self.track.last_t:
            self._aligned.append(obs)  # used part way through the next odometry step
        else:
            self._use(obs)

    def _flush(self) -> None:
        """An output is asked for: every sighting held is used now."""
        if (obs := self.sightings.take()) is not None:
            self._sighted(obs)
        aligned, self._aligned = self._aligned, []
        for obs in aligned:
            self._use(obs)

    def _move(self, inc: Increment) -> None:
        q = inc.cov
        if inc.ds == 0.0 and inc.dtheta == 0.0 and not np.any(q):
            return  # standing still, exactly
        ds, dth = inc.ds, inc.dtheta
        if self.k is not None:  # each particle's own slip, then its random walk
            ds, dth, _ = increment_with_slip(inc, self.k, self.calibration.track_m)
            walk = self.config.slip.random_walk_per_s * math.sqrt(max(inc.dt, 0.0))
            self.k = self.k + walk * self.rng.standard_normal(self.k.shape)
        if self._full is not None:  # the step's odometry (with slip, the weighted mean's)
            if self.k is None:
                self._steps.add(ds, dth, q)
            else:
                self._steps.add(float(self._w @ ds), float(self._w @ dth), q)
        if self.config.version == 1:
            e = self.rng.standard_normal((self.n, 2)) @ _cholesky2(q).T
            self.poses = apply_increment(self.poses, ds + e[:, 0], dth + e[:, 1])
            return
        self.poses, self.pending = propagate_linearised(self.poses, self.pending, ds, dth, q)

    def _noise(self, z: np.ndarray) -> list[float]:
        """The variances of z's components (R is diagonal)."""
        c = self.config
        sr = range_sigma(c, z[0])
        diag = [sr * sr, c.bearing_sigma_rad**2]
        if self.dim == 3:
            sy = c.yaw_sigma_rad + c.yaw_sigma_per_m2 * z[0] ** 2
            diag.append(sy * sy)
        return diag

    def _column(self, lid: int) -> int:
        """A known ID's column: the first that no particle uses (len(index) while every
        landmark has a known ID)."""
        col = self.index.get(lid)
        if col is not None:
            return col
        free = np.flatnonzero(~(self.reserved | self.seen.any(axis=0)))
        if not len(free):
            self._grow(1)
            free = np.flatnonzero(~(self.reserved | self.seen.any(axis=0)))
        col = int(free[0])
        self.reserved[col] = True
        self.index[lid] = col
        self.counts["new_landmarks"] += 1
        return col

    def _grow(self, free: int) -> None:
        """Double the landmark arrays until every particle has `free` columns that
        neither it nor a known ID uses (amortised O(1) per new landmark)."""
        taken = self.reserved.sum() + (self.seen & ~self.reserved).sum(axis=1).max()
        cap = self.seen.shape[1]
        new_cap = cap
        while new_cap - taken < free:
            new_cap *= 2
        if new_cap == cap:
            return

        def grown(a: np.ndarray) -> np.ndarray:
            out = np.zeros((*a.shape[:1], new_cap, *a.shape[2:]), dtype=a.dtype)
            out[:, :cap] = a
            return out

        self.means, self.covs, self.seen = grown(self.means), grown(self.covs), grown(self.seen)
        self.hits, self.born = grown(self.hits), grown(self.born)
        self.reserved = np.concatenate([self.reserved, np.zeros(new_cap - cap, dtype=bool)])

    def _use(self, obs: LandmarkObservation, between: bool = False) -> None:
        """Update with one message's sightings; between: made after the last recorded
        step (align_observations)."""
        items: list[tuple[int, np.ndarray]] = []
        unknown: list[np.ndarray] = []
        for lid, z, yaw in zip(obs.ids, obs.z, obs.yaw, strict=True):
            if lid < 0:
                self.counts["without_id"] += 1
                if self._associates:
                    unknown.append(np.asarray(z, dtype=float))
            elif self.dim == 3 and not np.isfinite(yaw):
                self.counts["without_yaw"] += 1
            else:
                zz = np.array([z[0], z[1], yaw]) if self.dim == 3 else np.asarray(z, dtype=float)
                items.append((int(lid), zz))
        if items or unknown:
            self._update(obs.t, items, np.array(unknown).reshape(-1, 2), between)

    def _update(
        self,
        t: float,
        items: list[tuple[int, np.ndarray]],
        unknown: np.ndarray,
        between: bool = False,
    ) -> None:
        """The landmark observations of one time (`_update_particles`): the trajectory's
        latest pose takes the corrected mean (not when they were made after it: between);
        for "rts-full" an epoch of the state smoother: the prediction into it from the
        particles' moments before, the filtered state after."""
        if self._full is not None and len(unknown):
            self._stop_full("sightings without an ID were used")
        pred = self._prediction() if self._full is not None else None
        if not self._update_particles(t, items, unknown):
            return
        if not between:
            self.track.amend(self._mean_pose())
        if self._full is not None:
            x, p, _ = self._end
            self._full.begin_sampled(epoch_step(len(self.track), between), x, p, *pred)
            if self._full.exceeded is not None:
                budget = self.config.smoother_budget_mb
                self._stop_full(f"its moments went over smoother_budget_mb ({budget:g} MB)")
            else:
                self._end = self._moments()

    def _stop_full(self, why: str) -> None:
        """The whole-state smoothing stops for the run: the trajectory is the ancestry's."""
        self._full, self._steps, self._end = None, None, None
        self._full_stopped = why

    def _top_rows(self) -> np.ndarray:
        """The particles' top of the state (N, 3 or 5): pose, and k with slip estimation."""
        return self.poses if self.k is None else np.concatenate([self.poses, self.k], axis=1)

    def _moments(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The filtered state for the smoother: (mean, covariance, the particles'
        deviations (N, n)) of [top, the known IDs' landmarks in the order first seen]: the
        weighted moments of the particles, with their motion covariance not yet sampled
        (2.0) and their landmark covariances added (compiled: kernels.state_moments)."""
        top = self._top_rows()
        cols = np.fromiter(self.index.values(), dtype=np.int64, count=len(self.index))
        size = top.shape[1] + self.dim * len(cols)
        x, p, dev = np.empty(size), np.empty((size, size)), np.empty((self.n, size))
        kernels.state_moments(top, self.pending, self.means, self.covs, cols, self._w, x, p, dev)
        return x, p, dev

    def _prediction(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The prediction since the last update, from the same particles moved on: (the
        predicted top, Cov(state then, top now) (n × t), Cov(top now, state now) (t × n))
        (compiled: kernels.prediction_moments)."""
        _, _, before = self._end
        top = self._top_rows()
        t, n = top.shape[1], before.shape[1]
        mean, cross, rows = np.empty(t), np.empty((n, t)), np.empty((t, n))
        kernels.prediction_moments(top, self.pending, self._w, before, mean, cross, rows)
        return mean, cross, rows

    def _update_particles(
        self, t: float, items: list[tuple[int, np.ndarray]], unknown: np.ndarray
    ) -> bool:
        """The landmark observations of one time: FastSLAM's four steps (compiled:
        slam.fastslam_kernels; the random draws here). items: (ID, z) of known landmarks;
        unknown (M, 2): sightings without an ID. False when none was used."""
        n, gain = self.n, self.config.weight_gain
        cols = np.array([self._column(lid) for lid, _ in items], dtype=np.int64)
        z = np.array([zz for _, zz in items]).reshape(-1, self.dim)
        r = np.array([self._noise(zz) for _, zz in items]).reshape(-1, self.dim)
        v2 = self.config.version == 2
        logw = self.log_weights.copy()
        mu = self.poses.copy()
        sigma = self.pending.copy() if v2 else self.pending
        had_seen = np.empty((len(items), n), dtype=bool)
        # 1. fold the observations of known landmarks into the proposal and the weights
        used = kernels.fold(
            mu, sigma, self.means, self.covs, self.seen, self._w, cols, z, r,
            self.gate, gain, v2, logw, had_seen,
        )  # fmt: skip
        self.counts["gated"] += int(np.sum(used == 0))
        self.counts["updates"] += int(np.sum(used == 1))
        # ... and the sightings without an ID, each particle pairing them itself
        m = len(unknown)
        cols_u = np.full((m, n), -1, dtype=np.int64)
        status = np.zeros((m, n), dtype=np.int8)
        r_u = np.array([self._noise(zz) for zz in unknown]).reshape(-1, 2)
        if m:
            a = self.config.association
            self._grow(m)
            kernels.associate(
                mu, sigma, self.means, self.covs, self.seen, self._confirmed() | self.reserved,
                unknown, r_u, a.inflation, a.gate(),
                a.new_threshold(), gain, v2, logw, cols_u, status,
            )  # fmt: skip
        if not used.any() and not m:
            return False
        if v2:  # 2. sample the poses from the proposal (1.0 sampled them with the motion)
            kernels.sample(mu, sigma, self.rng.standard_normal((n, 3)), self.poses)
            self.pending[:] = 0.0
        # 3. landmark EKF updates at the sampled poses, new landmarks initialised
        for c, zz, rr, st, had in (
            (np.repeat(cols[:, None], n, axis=1), z, r, np.repeat(used[:, None], n, axis=1),
             had_seen),
            (cols_u, unknown, r_u, status, np.ones((m, n), dtype=bool)),
        ):  # fmt: skip
            if len(zz):
                kernels.update_landmarks(
                    self.poses, self.means, self.covs, self.seen, self.reserved, c, zz, rr,
                    st, had, gain, logw,
                )  # fmt: skip
        if m:
            self._found_landmarks(t, cols_u, status)
        self._normalise(logw)  # 4.
        self.revision += 1
        return True

    def _found_landmarks(self, t: float, cols: np.ndarray, status: np.ndarray) -> None:
        """Book-keeping of the landmarks the particles found themselves: sightings
        counted, new ones born at t, provisional ones past their age dropped."""
        o, i = np.nonzero(status == 1)
        np.add.at(self.hits, (i, cols[o, i]), 1)
        o, i = np.nonzero(status == 2)
        self.hits[i, cols[o, i]] = 1
        self.born[i, cols[o, i]] = t
        a = self.config.association
        stale = (
            self.seen
            & ~self.reserved
            & (self.hits < a.confirm_sightings)
            & (t - self.born > a.provisional_max_age_s)
        )
        self.seen &= ~stale
        found = self._found
        found["associated"] += int(np.count_nonzero(status == 1))
        found["new"] += int(np.count_nonzero(status == 2))
        found["ambiguous"] += int(np.count_nonzero(status == 0))
        found["provisional_dropped"] += int(np.count_nonzero(stale))

    def _normalise(self, logw: np.ndarray) -> None:
        """4. Normalise the weights; resample when they have degenerated."""
        logw -= logw.max()
        w = np.exp(logw)
        total = w.sum()
        w /= total
        self.log_weights, self._w = logw - math.log(total), w
        self.n_eff = float(1.0 / np.sum(w * w))
        self.n_eff_min = min(self.n_eff_min, self.n_eff)
        if self.n_eff < self.config.resample_threshold * self.n:
            self._resample()

    def _resample(self) -> None:
        idx = systematic_resample(self._w, self.rng)
        if self.revises_past:
            self.paths.resampled(idx)
        self.poses = self.poses[idx]
        self.pending = self.pending[idx]
        self.means = self.means[idx]
        self.covs = self.covs[idx]
        self.seen = self.seen[idx]
        self.hits = self.hits[idx]
        self.born = self.born[idx]
        if self.k is not None:
            self.k = self.k[idx]
        self._w = np.full(self.n, 1.0 / self.n)
        self.log_weights = np.full(self.n, -math.log(self.n))
        self.counts["resamples"] += 1

    def _mean_pose(self) -> np.ndarray:
        w, p = self._w, self.poses
        th = math.atan2(float(w @ np.sin(p[:, 2])), float(w @ np.cos(p[:, 2])))
        return np.array([float(w @ p[:, 0]), float(w @ p[:, 1]), th])

    def _record(self, t: float) -> None:
        n = len(self.track)
        self.track.record(t, self._mean_pose())
        if self.revises_past:
            self.paths.snapshot(t, self.poses)
        if self._full is not None:
            self._steps.close(len(self.track) > n)

    # -- outputs ----------------------------------------------------------------------
    def estimate(self) -> PoseEstimate:
        """Weighted mean pose (circular mean of θ) and covariance: the particles' weighted
        spread plus (2.0) their weighted motion covariance not yet sampled."""
        self._flush()
        t = self.track.last_t
        mean = self._mean_pose()
        d = self.poses - mean
        d[:, 2] = wrap_angle(d[:, 2])
        w = self._w
        cov = (d * w[:, None]).T @ d + np.einsum("n,nij->ij", w, self.pending)
        return PoseEstimate(t, mean, _symmetric(cov))

    def trajectory(self) -> Trajectory:
        """The smoothed path (config.smoother) or the filtered means."""
        self._flush()
        if not self.revises_past or not self.track:
            return self.track.trajectory()
        key = (self.revision, self.track.last_t)
        if self._path_cache is None or self._path_cache[0] != key:
            if self._full is not None:
                traj = self._smoothed()
            else:
                traj = self.paths.mean_path(self._w, self.track.last_t, self.poses)
            self._path_cache = (key, traj)
        return self._path_cache[1]

    def _smoothed(self) -> Trajectory:
        """ "rts-full": the epochs' smoothed poses, and the odometry between them
        (slam.state_smoother.bridge; before the first update the covariance grows from
        the known start)."""
        filtered = self.track.trajectory()
        deltas, delta_covs = self._steps.deltas()
        x, p, _ = self._end
        epochs = self._full.smoothed(x, p)
        # grown from the start up to the first epoch (bridge grows them from there on)
        k = int(epochs[0][0]) + 1 if len(epochs[0]) else len(deltas)
        covs = np.zeros((len(deltas), 3, 3))
        start = np.zeros(k, dtype=np.bool_)
        start[0] = True
        bridge_covariances(filtered.poses[:k], deltas[:k], delta_covs[:k], start, covs[:k])
        means, covs = bridge(filtered.poses, covs, deltas, delta_covs, *epochs)
        return Trajectory(filtered.t, rts_smooth(means, covs, deltas, delta_covs))

    def landmarks(self, full: bool = False) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """Landmark id → (mean (2,), covariance 2×2): of a known ID the particles' weighted
        mean, of a landmark found without an ID the highest-weight particle's (module
        docstring); with full=True and observation "tag-pose", (u, v, ψ) and its 3×3
        covariance."""
        self._flush()
        best = int(np.argmax(self.log_weights))
        k = self.dim if full else 2
        ids = [lid for lid, col in self.index.items() if self.seen[:, col].any()]
        means, covs = self._weighted_map(np.array([self.index[i] for i in ids], dtype=int), k)
        out = {lid: (means[j], covs[j]) for j, lid in enumerate(ids)}
        for col in np.flatnonzero(self._confirmed()[best]):
            out[FIRST_ASSOCIATED_ID + int(col)] = (
                self.means[best, col, :k].copy(),
                self.covs[best, col, :k, :k].copy(),
            )
        return out

    def _weighted_map(self, cols: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(C, k) weighted means and (C, k, k) covariances of landmark columns `cols` over
        the particles that have seen each (ψ, the third component, a circular mean)."""
        seen = self.seen[:, cols]  # (N, C)
        w = np.where(seen, self._w[:, None], 0.0)
        total = w.sum(axis=0)
        w = np.where(total > 0.0, w / np.where(total > 0.0, total, 1.0), seen / seen.sum(axis=0))
        m = self.means[:, cols, :k]  # (N, C, k)
        mean = np.einsum("nc,nck->ck", w, m)
        if k == 3:
            mean[:, 2] = np.arctan2(
                np.einsum("nc,nc->c", w, np.sin(m[..., 2])),
                np.einsum("nc,nc->c", w, np.cos(m[..., 2])),
            )
        d = np.where(seen[..., None], m - mean, 0.0)
        if k == 3:
            d[..., 2] = wrap_angle(d[..., 2])
        cov = np.einsum("nc,ncij->cij", w, self.covs[:, cols, :k, :k])
        cov += np.einsum("nc,nci,ncj->cij", w, d, d)
        return mean, cov

    def _confirmed(self) -> np.ndarray:
        """(N, L): the landmarks each particle found itself and saw often enough."""
        confirm = self.config.association.confirm_sightings
        return self.seen & ~self.reserved & (self.hits >= confirm)

    def slip_estimate(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The particles' weighted mean (k_left, k_right) and weighted covariance; None
        without slip estimation."""
        if self.k is None:
            return None
        self._flush()
        mean = self._w @ self.k
        d = self.k - mean
        return mean, (d * self._w[:, None]).T @ d

    def diagnostics(self) -> dict:
        self._flush()
        notes: dict = {**self.counts, **self.odometry.diagnostics()}
        if (slip := self.slip_estimate()) is not None:
            notes.update(slip_diagnostics(*slip))
        notes["version"] = self.config.version
        notes["particles"] = self.n
        notes["landmarks"] = len(self.index)
        if self._associates:
            confirmed = self._confirmed()
            notes["map_landmarks"] = len(self.landmarks())  # the best particle's, as EKF-SLAM's
            for key, v in self._found.items():
                notes[key] = round(v / self.n, 1)
            pending = self.seen & ~self.reserved & ~confirmed
            notes["provisional_pending"] = round(float(pending.sum()) / self.n, 1)
        notes["n_eff"] = self.n_eff
        notes["n_eff_min"] = self.n_eff_min
        if self._full_stopped:
            notes["note"] = (
                f"the whole state's smoothing stopped ({self._full_stopped}): "
                "the trajectory is the ancestry paths"
            )
        if (
            self.counts["updates"] == 0
            and self.counts["new_landmarks"] == 0
            and not any(self._found.values())
        ):
            notes["note"] = "no landmark observations: odometry only"
        return notes


SPEC = Spec(
    "fastslam",
    FastSlamConfig,
    FastSlam,
    "FastSLAM 1.0/2.0 particle filter, per-landmark EKFs (known IDs or per-particle association)",
)
