"""`gtsam`: an iSAM2 incremental smoother over keyframe poses and landmarks.

Odometry increments accumulate (with their covariance, propagated through the exact-arc
Jacobians) into a keyframe-to-keyframe `BetweenFactorPose2`; a new keyframe starts when
the walker has moved `keyframe_distance_m`, turned `keyframe_angle_rad` or
`keyframe_time_s` has passed, and also when landmarks are seen `obs_keyframe_dt_s`
after the last keyframe. Landmark observations become `BearingRangeFactor2D` factors on
their keyframe with a Huber-robust noise model (a moderate outlier loses its pull);
a sighting with an ID that the current estimate finds implausible (`gate_chi2`: a χ²
gate on the pose's and the landmark's marginals) is left out. Sightings without an ID
(−1: Victoria Park's trees) are paired with the landmarks found so far by nearest
neighbour on the current estimate (slam.association: the sighting placed at the current
pose with its measurement covariance, the squared Mahalanobis distance divided by
`association.inflation` for the pose and landmark errors the estimate carries no
covariance for; the χ² gate of `association.gate_prob`), and become factors like the
others, robust, so that a wrong pairing can be outvoted by the right ones; a sighting
that matches none is a provisional landmark until it is seen again
(`association.confirm_sightings`).
With `observation="tag-pose"` a tag detection's full planar pose is used:
each tag is a `Pose2` variable (T(id)) and each detection a `BetweenFactorPose2` from
its keyframe to the tag — position noise from the range and bearing σ, rotated into the
tag's frame, and yaw σ = yaw_sigma_rad + yaw_sigma_per_m2·r² — also Huber-robust (far
tags' yaw flips); observations without a yaw (range-bearing datasets) are skipped and
counted. Every update revises the past: `trajectory()` is the smoothed estimate,
every odometry message placed relative to its (smoothed) keyframe.

Absolute observations (`absolute`, slam.absolute; off by default) attach to the latest
keyframe as landmarks do (a new keyframe starts at them when they come
`obs_keyframe_dt_s` or more after it and the walker has moved): a compass heading is a
`PoseRotationPrior2D` on the keyframe (the heading measured, less the turn since the
keyframe), a position fix a GPS-like factor (`position_factor`, a CustomFactor: the
map-frame position of the walker's point at the offset it has moved since the keyframe,
in the keyframe's frame; with no offset it is `PoseTranslationPrior2D`); both Huber-
robust at `absolute.robust_k` σ when that is > 0.

Scan matching (`scan_matching=True`, off by default; laser scans and depth frames kept as
keyframes, matched sequentially and for loop closures, a final pass when the source
ends) is the smoother's scan half, slam.scan_graph, with its settings `scan` and `loop`.

Odometry covariance with scan matching. Between scan keyframes the trajectory is the
odometry (relative poses at other times are interpolated along it), and how the
smoother spreads a scan-matching correction over the intermediate keyframes follows the
odometry factors' covariance. `odometry_cov`: "model" uses the odometry model's
(slam.motion); "distance" a random walk in path length L and turn R since the keyframe,
var(x) = var(y) = k₁L + k₂R, var(θ) = k₃L + k₄R (`odometry_walk`, defaults 0.0025 m²/m:
σ 5 cm per metre, the thesis's encoder error; 0.001 m²/rad; 0.006 rad²/m; 0.1
rad²/rad), which does not depend on the message rate or timing; "auto" (default):
"distance" with scan matching, "model" without. With `odometry_adaptive` the
smoother then fits the odometry's scale to the data (covariance matching): the
odometry's error against each accepted sequential scan match, normalised per axis by
that variance, averages to the variance multiplier (σ multipliers clipped to
`odometry_adaptive_range`, reported as `odometry_sigma_scale`); from the
`odometry_adaptive_min_matches`-th match on it applies to new odometry factors, and the
factors added before are replaced once with the scaled ones. The adaptation scales
each axis as a whole, so what the defaults set is how the heading's variance divides
between path and turn: the laser logs' odometry errs in turns (its heading error
against GMapping's poses fits 0.003–0.04 rad² per rad turned and ~0 per metre), and
k₄ 0.1 (was 0.01) was chosen on the acapulco, edmonton, fhw and csail logs over three
voxel sizes each (`benchmarks/bench_laser_logs.py --spread`; BENCHMARKS.md): better
beyond the spread on acapulco and edmonton, the same on fhw and csail, and on the logs
not used to choose it better on belgioioso and freiburg-101, the same on seattle. On
the walker's depth frames it is no help (scan correction without tags 2.70 → 2.56 m
with the other defaults, 0.97 → 2.06 m with the old submap and ICP settings; there the
sequential matches, not the odometry, are what errs: BENCHMARKS.md).

Slip estimation (`slip.estimate`, slam.slip): each keyframe also has the wheels' slip
coefficients k = (k_left, k_right) as a Point2 S(i), with a prior on S(0) and a random
walk between successive ones; the odometry factor from keyframe i to i+1 is then a
function of S(i) (slam.gtsam_slip), so the tags that pin the poses also estimate k, and
the odometry is integrated with the latest estimate of k between them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, S, T, X

from hardware.calibration import WalkerCalibration
from hardware.choices import Choice, coerce
from hardware.geometry import compose, compose1, rotation, transform_points, wrap1, wrap_angle
from hardware.messages import DepthFrame, LaserScan, Message
from hardware.registry import Spec
from hardware.small_linalg import congruence, matmul
from slam.absolute import (
    AbsoluteConfig,
    AbsoluteObservation,
    absolute_observation,
    fused_count,
)
from slam.association import (
    CHI2_999,
    AssociationConfig,
    Discovery,
    mahalanobis2,
    nearest_neighbour,
)
from slam.base import Localizer, LocalizerConfig, PoseEstimate
from slam.gtsam_factors import position_factor, robust_noise
from slam.gtsam_slip import slip_odometry_factor, slip_walk_factor
from slam.measurement import (
    BEARING_SIGMA_RAD,
    RANGE_SIGMA_FRAC,
    RANGE_SIGMA_M,
    LandmarkObservation,
    ObservationModel,
    Sightings,
    placed_sightings,
    range_bearing,
    range_bearing_jacobians,
    range_sigma,
)
from slam.motion import (
    Increment,
    MotionNoise,
    OdometryModel,
    carry_increment,
    split_increment,
)
from slam.scan_graph import LoopClosures, ScanGraph, SequentialScans
from slam.scan_matching import MatchResult, ScanMatchConfig, relative_guess
from slam.slip import SlipEstimation, increment_with_slip, slip_diagnostics
from slam.trajectory import Trajectory, spread_corrections


class Factorization(Choice):
    """iSAM2's linear solver."""

    QR = "QR"
    CHOLESKY = "CHOLESKY"


class OdometryCovariance(Choice):
    """The between-keyframe odometry covariance (module docstring): the motion model's,
    a distance walk, or auto (the walk when scan matching, else the model)."""

    AUTO = "auto"
    MODEL = "model"
    DISTANCE = "distance"


@dataclass(frozen=True)
class GtsamConfig(LocalizerConfig):
    """iSAM2 smoother settings.

    initial_pose: prior mean of the first keyframe (the map frame), with prior_sigma.
    keyframe_*: when a new keyframe starts; obs_keyframe_dt_s: landmarks seen this long
    after the last keyframe start a new one (else they attach to it).
    range_sigma_m + range_sigma_frac·r, bearing_sigma_rad: landmark measurement noise;
    huber_k: robust kernel threshold in standard deviations.
    gate_chi2: a range-bearing sighting with an ID, of a landmark already in the
    estimate, is left out (counted: `gated`) when its squared Mahalanobis distance to
    the prediction from the current estimate exceeds this; the prediction's covariance
    holds the pose's and the landmark's marginals (their correlation left out, which
    only widens the gate) and the measurement noise. None: the 99.9 % χ² quantile
    (13.8, FastSLAM's gate); 0: no gate. (Sightings without an ID have the
    association's gates instead.) The Huber kernel bounds an outlier's pull but does
    not remove it: MRCLAM robot 3's three sightings read with the wrong ID (bearing ~π
    off) turned its keyframe by 150° for ~10 s without the gate (BENCHMARKS.md).
    association_enabled, association: sightings without IDs (module docstring);
    association.method is EKF-SLAM's (gtsam pairs by nearest neighbour), its gates,
    inflation and provisional landmarks apply.
    update_per_sighting: iSAM2 updates at every landmark sighting (the estimate uses
    them at once); False: they wait for the next keyframe's update (a fast vehicle with
    a laser that sees trees in every scan: Victoria Park proposes it).
    use_landmarks: False ignores landmark observations (tags, range-bearing): the
    smoother then runs on odometry, absolute fixes and scan matching alone (to study
    scan correction without tags on a log that has them).
    observation: "range-bearing" (BearingRangeFactor2D to a point landmark) or
    "tag-pose" (BetweenFactorPose2 to a Pose2 tag; module docstring), with
    yaw_sigma_rad + yaw_sigma_per_m2·r² the tag-yaw noise (as FastSlamConfig's: they fit
    the simulated tag camera).
    odometry_sigma_floor: added to each between-keyframe odometry covariance (x, y, θ):
    wheel odometry has no lateral noise of its own (the axle cannot slide), and a
    rank-deficient covariance makes the system ill-conditioned.
    factorization: iSAM2's, "QR" or "CHOLESKY".
    odometry_cov, odometry_walk, odometry_adaptive*: see the module docstring.
    Scan matching (slam.scan_graph): scan_matching switches it on; scan_match: the
    matcher's settings for laser scans (slam.scan_matching.ScanMatchConfig), depth_match
    for depth frames (slam.scan_graph: finer points, pairs within 5 cm); laser_offset: the laser's
    (x, y, yaw) on the walker (the CARMEN logs' front laser sits at the robot centre:
    Intel's robot_frontlaser_offset is 0); scan (SequentialScans): which scans are kept
    and how each is matched to the ones before it; loop (LoopClosures): loop closures;
    both accept a match through a MatchGate.
    absolute: compass / position-fix factors (slam.absolute.AbsoluteConfig; off by
    default; module docstring).
    slip: per-wheel slip estimation (slam.slip.SlipEstimation; `slip.estimate=true`).
    align_observations: a landmark observation is held until the next odometry message
    and placed at the pose of its own time (slam.motion.split_increment); otherwise at
    the last odometry message's pose. A tag frame falls between encoder messages (10 ms
    after one at 50 Hz): in a turn the walker has turned on by then, and that heading
    error, correlated with braking, biases a slip estimate low (by ~15 % on simulated
    trials).
    """

    prior_sigma: tuple[float, float, float] = (1e-3, 1e-3, 1e-4)
    noise: MotionNoise = field(default_factory=MotionNoise)
    keyframe_distance_m: float = 0.25
    keyframe_angle_rad: float = 0.2
    keyframe_time_s: float = 1.0
    obs_keyframe_dt_s: float = 0.2
    range_sigma_m: float = RANGE_SIGMA_M
    range_sigma_frac: float = RANGE_SIGMA_FRAC
    bearing_sigma_rad: float = BEARING_SIGMA_RAD
    huber_k: float = 1.345
    gate_chi2: float | None = None
    association_enabled: bool = True
    association: AssociationConfig = field(default_factory=AssociationConfig)
    update_per_sighting: bool = True
    use_landmarks: bool = True
    observation: ObservationModel = ObservationModel.RANGE_BEARING
    yaw_sigma_rad: float = 0.02
    yaw_sigma_per_m2: float = 0.03
    relinearize_threshold: float = 0.01
    odometry_sigma_floor: tuple[float, float, float] = (1e-3, 1e-3, 1e-3)
    # QR: a long odometry-only chain (Intel lab, 3000 keyframes, tens of metres of
    # drift) makes iSAM2's Cholesky factorization fail as indeterminate; QR does not.
    factorization: Factorization = Factorization.QR
    odometry_cov: OdometryCovariance = OdometryCovariance.AUTO
    odometry_walk: tuple[float, float, float, float] = (0.0025, 0.001, 0.006, 0.1)
    # -- scan matching (slam.scan_graph) --------------------------------------------------
    scan_matching: bool = False
    scan_match: ScanMatchConfig = field(default_factory=ScanMatchConfig)
    depth_match: ScanMatchConfig = field(
        default_factory=lambda: ScanMatchConfig(voxel_m=0.02, max_correspondence_m=0.05)
    )
    laser_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scan: SequentialScans = field(default_factory=lambda: SequentialScans())
    odometry_adaptive: bool = True
    odometry_adaptive_min_matches: int = 10
    odometry_adaptive_range: tuple[float, float] = (0.1, 100.0)
    loop: LoopClosures = field(default_factory=lambda: LoopClosures())
    absolute: AbsoluteConfig = field(default_factory=AbsoluteConfig)
    slip: SlipEstimation = field(default_factory=SlipEstimation)
    align_observations: bool = False

    def __post_init__(self) -> None:
        coerce(
            self,
            observation=ObservationModel,
            factorization=Factorization,
            odometry_cov=OdometryCovariance,
        )
        if self.yaw_sigma_rad <= 0 or self.yaw_sigma_per_m2 < 0:
            raise ValueError("yaw_sigma_rad must be > 0 and yaw_sigma_per_m2 >= 0")
        if self.gate_chi2 is not None and not self.gate_chi2 >= 0:
            raise ValueError(f"gate_chi2 must be >= 0 (or None), got {self.gate_chi2}")


class GtsamSmoother(Localizer):
    revises_past = True

    def __init__(self, config: GtsamConfig, calibration: WalkerCalibration) -> None:
        self.config = config
        self.calibration = calibration
        self.odometry = OdometryModel(calibration, config.noise)
        self._walk = config.odometry_cov == "distance" or (
            config.odometry_cov == "auto" and config.scan_matching
        )
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(config.relinearize_threshold)
        params.setFactorization(config.factorization)
        self.isam = gtsam.ISAM2(params)
        self._graph = gtsam.NonlinearFactorGraph()
        self._values = gtsam.Values()
        self._kf = -1  # index of the latest keyframe
        self._kf_t: list[float] = []
        self._kf_pose = np.array(config.initial_pose, dtype=float)  # its current estimate
        self._delta = np.zeros(3)  # motion since the latest keyframe, in its frame
        self._delta_cov = np.zeros((3, 3))
        # (t, keyframe, delta, its odometry variance: x + y, θ), and each keyframe's
        # motion from the one before with that variance (the trajectory spreads a
        # keyframe's correction back over it: `trajectory`)
        self._records: list[tuple[float, int, np.ndarray, tuple[float, float]]] = []
        self._segments: list[tuple[np.ndarray, tuple[float, float]]] = []
        self._landmarks: set[int] = set()
        self._marginal: np.ndarray | None = None
        self._cache: tuple[int, Trajectory] | None = None
        self.counts = {
            "keyframes": 0, "landmark_factors": 0, "gated": 0, "without_id": 0, "updates": 0
        }  # fmt: skip
        self._gate = config.gate_chi2 if config.gate_chi2 is not None else CHI2_999[2]
        if config.association_enabled:
            self.counts["associated"] = 0
        self._discovery = Discovery(config.association)
        # landmarks: their last known position and the revision it was read at
        self._found_xy: dict[int, tuple[np.ndarray, int]] = {}
        self.counts["odometry_gaps"] = 0
        if config.absolute.enabled:
            self.counts.update(compass_factors=0, position_factors=0)
        self._tags = config.observation == "tag-pose"
        if self._tags:
            self.counts["without_yaw"] = 0
        self._t: float | None = None
        self._unknown = np.zeros((3, 3))  # motion not measured since the keyframe: its cov
        self._odo_scale = np.ones(3)  # adaptive σ multipliers of the odometry (x, y, θ)
        self._odo_z: list[np.ndarray] = []  # normalised squared odometry errors
        self._adapted = not (config.scan_matching and config.odometry_adaptive)
        # [keyframe, delta, model cov, slip (or None), factor index]
        self._early_odometry: list[list] = []
        self._pending: list[tuple[int, list]] = []  # (position in self._graph, record)
        # slip estimation: the latest estimate of k, and ∂delta/∂k since the keyframe
        self._slip = config.slip.estimate
        self._k = np.array(config.slip.k_prior, dtype=float)
        self._delta_jk = np.zeros((3, 2))
        self._held: list[LandmarkObservation] = []  # align_observations: not yet placed
        self.sightings = Sightings(calibration)
        self.scans = ScanGraph(self)  # the scan half (slam.scan_graph)

    # -- inputs -----------------------------------------------------------------------
    def process(self, msg: Message) -> None:
        if (obs := self.sightings.offer(msg)) is not None:
            self._sighted(obs)
        if self.sightings.taken:
            pass  # held, to be used with the other sightings of its time
        elif (inc := self.odometry.increment(msg)) is not None:
            for obs in self._held:  # observations made since the last odometry message
                part, inc = split_increment(inc, obs.t)
                self._move(part)
                self._observe(obs)
            self._held = []
            self._move(inc)
            self._note(msg.t)
            if self._keyframe_due(msg.t):
                self.new_keyframe(msg.t)
        elif (fix := absolute_observation(msg, self.config.absolute)) is not None:
            self._absolute(fix)
        elif self.config.scan_matching and isinstance(msg, LaserScan | DepthFrame):
            self.scans.add(msg)
        if self._kf < 0 and self.odometry.has_odometry:
            self._start(msg.t)

    def _sighted(self, obs: LandmarkObservation) -> None:
        """The landmark sightings of one time (slam.measurement.Sightings): one iSAM2
        update for them, however many messages brought them."""
        if not self.config.use_landmarks:
            return
        if self.config.align_observations and self._t is not None and obs.t > self._t:
            self._held.append(obs)  # placed when the next odometry message spans it
        else:
            self._observe(obs)

    def _move(self, inc: Increment) -> None:
        """Integrate an odometry increment (slip-corrected with the latest k); a motion the
        odometry did not measure adds its covariance, unscaled, to the next odometry
        factor, and widens the next sequential scan match's search."""
        if inc.unknown:
            var_s, var_th = np.diag(inc.cov)
            self._unknown += np.diag([var_s, var_s, var_th])
            self.scans.unmeasured()
            self.counts["odometry_gaps"] += 1
            return
        if self._slip:
            ds, dth, jk = increment_with_slip(inc, self._k, self.calibration.track_m)
            self._integrate(float(ds), float(dth), inc.cov, jk)
        else:
            self._integrate(inc.ds, inc.dtheta, inc.cov)

    def _place_held(self) -> None:
        """An output is asked for: the sightings held taken as they are, and observations
        still waiting for the odometry after them (align_observations) placed at the
        latest pose."""
        if (obs := self.sightings.take()) is not None:
            self._sighted(obs)
        for obs in self._held:
            self._observe(obs)
        self._held = []

    def _start(self, t: float) -> None:
        c = self.config
        pose = gtsam.Pose2(*c.initial_pose)
        self._graph.add(
            gtsam.PriorFactorPose2(
                X(0), pose, gtsam.noiseModel.Diagonal.Sigmas(np.array(c.prior_sigma))
            )
        )
        self._values.insert(X(0), pose)
        if self._slip:
            sigma = gtsam.noiseModel.Isotropic.Sigma(2, c.slip.k_sigma)
            self._graph.add(gtsam.PriorFactorPoint2(S(0), self._k, sigma))
            self._values.insert(S(0), self._k)
        self._kf, self._kf_t = 0, [t]
        self._flush()
        self._note(t)

    def _note(self, t: float) -> None:
        """The pose at t (the latest keyframe and the motion since) into the trajectory; a
        second note at the same time (a keyframe made at an odometry message's time)
        replaces the first: the trajectory holds the state after each time's messages."""
        if self._kf < 0:
            return
        if self._records and t <= self._records[-1][0]:
            if t < self._records[-1][0]:
                return
            self._records.pop()
        self._t = t
        self._records.append((t, self._kf, self._delta.copy(), self._variance()))

    def _variance(self) -> tuple[float, float]:
        """The odometry variance (x + y, θ) accumulated since the latest keyframe, that of
        motion it did not measure included."""
        d, u = self._delta_cov, self._unknown  # (every odometry message: no temporaries)
        return (d[0, 0] + u[0, 0]) + (d[1, 1] + u[1, 1]), d[2, 2] + u[2, 2]

    def _integrate(
        self, ds: float, dth: float, q: np.ndarray, jk: np.ndarray | None = None
    ) -> None:
        """Add an increment to the motion since the keyframe; jk: ∂(ds, dθ)/∂k (slip)."""
        c = self.config
        added = None  # the increment's covariance: the random walk's, or propagated from q
        if self._walk:
            kxy, kxy_turn, kth, kturn = c.odometry_walk
            vxy = kxy * abs(ds) + kxy_turn * abs(dth)
            added = np.diag([vxy, vxy, kth * abs(ds) + kturn * abs(dth)])
        self._delta, self._delta_cov, f, g = carry_increment(
            self._delta, self._delta_cov, ds, dth, q, added
        )
        if jk is not None:
            self._delta_jk = matmul(f, self._delta_jk) + matmul(g, jk)
        if c.scan_matching:
            self.scans.integrate(ds, dth, q, added)

    def _keyframe_due(self, t: float) -> bool:
        c = self.config
        return self._kf >= 0 and (
            math.hypot(self._delta[0], self._delta[1]) >= c.keyframe_distance_m
            or abs(self._delta[2]) >= c.keyframe_angle_rad
            or t - self._kf_t[-1] >= c.keyframe_time_s
        )

    def _odometry_cov(self, model_cov: np.ndarray, keyframes: int = 1) -> np.ndarray:
        """An odometry factor's covariance: the motion model's plus the floor per
        keyframe, scaled per axis by the adaptive σ multipliers."""
        floor = keyframes * np.diag(np.square(self.config.odometry_sigma_floor))
        s = self._odo_scale
        return (model_cov + floor) * np.outer(s, s)

    def _odometry_factor(
        self, a: int, delta: np.ndarray, model_cov: np.ndarray, slip=None, unknown=None
    ):
        """Keyframe a → a + 1; slip: (∂delta/∂k, the k it was integrated with), making
        it a function of S(a) (slam.gtsam_slip), or None; unknown: the covariance of
        motion the odometry did not measure (added unscaled)."""
        cov = self._odometry_cov(model_cov) + (0.0 if unknown is None else unknown)
        noise = gtsam.noiseModel.Gaussian.Covariance(cov)
        if slip is not None:
            return slip_odometry_factor(X(a), X(a + 1), S(a), delta, *slip, noise)
        return gtsam.BetweenFactorPose2(X(a), X(a + 1), gtsam.Pose2(*delta), noise)

    def new_keyframe(self, t: float, flush: bool = True) -> None:
        """A keyframe at t, at the motion since the latest. flush=False leaves it for the
        caller's iSAM2 update (one update for the keyframe and the factors on it), with
        its predicted pose as the latest keyframe's until then."""
        k = self._kf + 1
        slip = (self._delta_jk, self._k.copy()) if self._slip else None
        if self.config.scan_matching and not self._adapted:
            # kept until the odometry noise is adapted, then replaced (see adapt_odometry)
            unknown = self._unknown.copy()
            record = [self._kf, self._delta.copy(), self._delta_cov.copy(), slip, unknown]
            self._early_odometry.append(record)
            self._pending.append((self._graph.size(), self._early_odometry[-1]))
        factor = self._odometry_factor(self._kf, self._delta, self._delta_cov, slip, self._unknown)
        self._graph.add(factor)
        self._segments.append((self._delta.copy(), self._variance()))
        self._unknown = np.zeros((3, 3))
        predicted = compose(self._kf_pose, self._delta)
        self._values.insert(X(k), gtsam.Pose2(*predicted))
        if self._slip:
            walk = self.config.slip.random_walk_per_s * math.sqrt(max(t - self._kf_t[-1], 0.0))
            self._graph.add(slip_walk_factor(S(self._kf), S(k), max(walk, 1e-6)))
            self._values.insert(S(k), self._k)
            self._delta_jk = np.zeros((3, 2))
        self._kf = k
        self._kf_t.append(t)
        self._delta = np.zeros(3)
        self._delta_cov = np.zeros((3, 3))
        self.counts["keyframes"] += 1
        if flush:
            self._flush()
        else:
            self._kf_pose, self._marginal = predicted, None
        self._note(t)

    def moved(self) -> bool:
        """Whether the walker moved since the latest keyframe, or the odometry could not
        tell (a gap: its motion unknown, not zero)."""
        return bool(np.any(self._delta != 0) or np.any(self._unknown != 0))

    def _attach(self, t: float, flush: bool) -> None:
        """An observation at t attaches to the latest keyframe, or starts a new one at t
        when it comes obs_keyframe_dt_s or more after it and the walker has moved (its
        iSAM2 update left to the caller when flush is False)."""
        if t - self._kf_t[-1] >= self.config.obs_keyframe_dt_s and self.moved():
            self.new_keyframe(t, flush)

    def _absolute(self, obs: AbsoluteObservation) -> None:
        """A compass heading or a position fix as a factor on its keyframe (module
        docstring)."""
        if self._kf < 0:
            return
        self._attach(obs.t, flush=False)  # updated with the fix below
        a = self.config.absolute
        base = gtsam.noiseModel.Isotropic.Sigma(len(obs.z), obs.sigma)
        noise = robust_noise("huber" if a.robust_k > 0 else "none", a.robust_k, base)
        if obs.is_heading:
            measured = gtsam.Rot2(float(obs.z[0] - self._delta[2]))
            self._graph.add(gtsam.PoseRotationPrior2D(X(self._kf), measured, noise))
        else:
            self._graph.add(position_factor(X(self._kf), obs.z, self._delta[:2], noise))
        self.counts[f"{obs.kind}_factors"] += 1
        self._flush()

    def _observe(self, obs: LandmarkObservation) -> None:
        if self._kf < 0 or len(obs) == 0:
            return
        c = self.config
        self._attach(obs.t, flush=not c.update_per_sighting)  # else with the sightings
        unknown = []
        for lid, z, yaw in zip(obs.ids, obs.z, obs.yaw, strict=True):
            lid = int(lid)
            if lid < 0:
                self.counts["without_id"] += 1
                unknown.append(z)
                continue
            if self._tags:
                if not math.isfinite(yaw):
                    self.counts["without_yaw"] += 1
                    continue
                q, r, b, sr = self._from_keyframe(z)
                self._tag_factor(lid, q, r, b, sr, float(wrap_angle(yaw + self._delta[2])))
                continue
            if self._gate and self.isam.valueExists(L(lid)) and self._implausible(lid, z):
                self.counts["gated"] += 1
                continue
            self._range_bearing_factor(lid, z)
        if unknown and c.association_enabled and not self._tags:
            self._associate(obs.t, np.array(unknown, dtype=float))
        if c.update_per_sighting:
            self._flush()

    def _from_keyframe(self, z: np.ndarray) -> tuple[np.ndarray, float, float, float]:
        """A sighting (range, bearing from the walker now) as seen from the latest
        keyframe (the walker moved self._delta since): the point q, its range, bearing
        and range σ."""
        p = np.array([[z[0] * math.cos(z[1]), z[0] * math.sin(z[1])]])
        q = transform_points(self._delta, p)[0]
        r, b = float(np.hypot(*q)), float(math.atan2(q[1], q[0]))
        return q, r, b, self._range_sigma(r)

    def _range_sigma(self, r: float | np.ndarray) -> float | np.ndarray:
        """The range σ of sightings at range(s) r."""
        return range_sigma(self.config, r)

    def _range_bearing_factor(self, lid: int, z: np.ndarray) -> None:
        """A Huber-robust BearingRangeFactor2D from the latest keyframe to L(lid)."""
        c = self.config
        _, r, b, sr = self._from_keyframe(z)
        noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(c.huber_k),
            gtsam.noiseModel.Diagonal.Sigmas(np.array([c.bearing_sigma_rad, sr])),
        )
        self._graph.add(gtsam.BearingRangeFactor2D(X(self._kf), L(lid), gtsam.Rot2(b), r, noise))
        if lid not in self._landmarks:
            self._landmarks.add(lid)
            a = self._kf_pose[2] + b
            guess = self._kf_pose[:2] + r * np.array([math.cos(a), math.sin(a)])
            self._values.insert(L(lid), gtsam.Point2(*guess))
            self._found_xy[lid] = (guess, -1)
        self.counts["landmark_factors"] += 1

    def _implausible(self, lid: int, z: np.ndarray) -> bool:
        """Whether the sighting z (range, bearing) of landmark lid fails `gate_chi2`
        against the current estimate (GtsamConfig). The pose's and the landmark's
        marginals only widen the innovation's covariance beyond the sighting's own
        noise, so a sighting within the gate on that noise alone is within it: their
        marginals, which cost iSAM2 more than its update, are computed only for the
        others (at a keyframe that waits for its update, against its predicted pose)."""
        sr = self._range_sigma(float(z[0]))
        if self._within_noise(lid, z, sr):
            return False
        pose, pose_cov = self._pose_now()  # updates iSAM2 first if a keyframe waits
        landmark = np.asarray(self.isam.calculateEstimatePoint2(L(lid)), dtype=float)
        h_pose, h_landmark = range_bearing_jacobians(pose, landmark)
        s_ = (
            congruence(h_pose, pose_cov)
            + congruence(h_landmark, self.isam.marginalCovariance(L(lid)))
            + np.diag([sr * sr, self.config.bearing_sigma_rad**2])
        )
        nu = z - range_bearing(pose, landmark)
        nu[1] = wrap_angle(nu[1])
        return float(mahalanobis2(nu, s_)) > self._gate

    def _within_noise(self, lid: int, z: np.ndarray, sr: float) -> bool:
        """Whether the sighting z of landmark lid (range σ sr) is within the gate on its
        own noise, from the latest keyframe's pose ⊕ the motion since (in scalars: it
        runs for every sighting)."""
        x, y, th = compose1(self._kf_pose.tolist(), self._delta.tolist())
        landmark = self.isam.calculateEstimatePoint2(L(lid))
        ex, ey = float(landmark[0]) - x, float(landmark[1]) - y
        dr = (float(z[0]) - math.hypot(ex, ey)) / sr
        db = wrap1(float(z[1]) - (math.atan2(ey, ex) - th)) / self.config.bearing_sigma_rad
        return dr * dr + db * db <= self._gate

    def _associate(self, t: float, z: np.ndarray) -> None:
        """Sightings (n, 2) without IDs paired by nearest neighbour with the landmarks
        found so far, at their current estimates (module docstring); the others new
        (provisional) or ambiguous."""
        c = self.config
        a = c.association
        pose = compose(self._kf_pose, self._delta)
        sr = self._range_sigma(z[:, 0])
        var = np.column_stack([sr * sr, np.full(len(z), c.bearing_sigma_rad**2)])
        world, covs = placed_sightings(pose, z, var)
        sigma_r = math.sqrt(float(var[:, 0].max()))
        ids, xy = self._found_near(
            pose, float(z[:, 0].max()) + 5.0 * math.sqrt(a.inflation) * sigma_r
        )
        pairs = np.full(len(z), -1, dtype=int)
        d2_min = np.full(len(z), np.inf)
        if ids:
            d2 = mahalanobis2(world[:, None, :] - xy[None], covs[:, None]) / a.inflation
            d2_min = d2.min(axis=1)
            pairs = nearest_neighbour(d2, a.gate())
        for i in np.flatnonzero(pairs >= 0):
            self.counts["associated"] += 1
            self._range_bearing_factor(ids[pairs[i]], z[i])
        new = self._discovery.new(pairs, d2_min)
        zn = z[new]
        for k, lid in self._discovery.confirm(t, world[new], covs[new]):
            self._range_bearing_factor(lid, zn[k])

    def _found_near(self, pose: np.ndarray, reach: float) -> tuple[list[int], np.ndarray]:
        """The associated landmarks whose last known position is within reach of the
        pose, at their current estimates (refreshed from iSAM2 once per update)."""
        near = [
            lid
            for lid, (p, _) in self._found_xy.items()
            if math.hypot(p[0] - pose[0], p[1] - pose[1]) <= reach
        ]
        xy = np.empty((len(near), 2))
        for k, lid in enumerate(near):
            p, rev = self._found_xy[lid]
            if rev != self.revision and self.isam.valueExists(L(lid)):
                p = np.asarray(self.isam.calculateEstimatePoint2(L(lid)), dtype=float)
                self._found_xy[lid] = (p, self.revision)
            xy[k] = p
        return near, xy

    def _tag_factor(self, lid: int, q: np.ndarray, r: float, b: float, sr: float, psi: float):
        """BetweenFactorPose2 keyframe → tag T(lid) seen at q (keyframe frame), range r,
        bearing b, tag yaw ψ. Pose2's between error is in the tag's own frame: the range /
        across-range covariance is rotated by b − ψ into it."""
        c = self.config
        cov_rb = np.diag([sr * sr, (r * c.bearing_sigma_rad) ** 2])
        a = b - psi
        cov = np.zeros((3, 3))
        cov[:2, :2] = congruence(rotation(a), cov_rb)
        cov[2, 2] = (c.yaw_sigma_rad + c.yaw_sigma_per_m2 * r * r) ** 2
        noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(c.huber_k),
            gtsam.noiseModel.Gaussian.Covariance(cov),
        )
        rel = gtsam.Pose2(float(q[0]), float(q[1]), psi)
        self._graph.add(gtsam.BetweenFactorPose2(X(self._kf), T(lid), rel, noise))
        if lid not in self._landmarks:
            self._landmarks.add(lid)
            kf = gtsam.Pose2(*(float(v) for v in self._kf_pose))
            self._values.insert(T(lid), kf.compose(rel))
        self.counts["landmark_factors"] += 1

    def poses(self) -> np.ndarray:
        """Current estimates of all keyframe poses (kf × 3)."""
        self._flush()
        poses = gtsam.utilities.extractPose2(self.isam.calculateEstimate())
        return np.asarray(poses, dtype=float).reshape(-1, 3)

    def adapt_odometry(self, odo: np.ndarray, model: np.ndarray, res: MatchResult) -> None:
        """Covariance matching: the odometry's error against an accepted scan match,
        normalised per axis by the model's variance; once there are enough, their mean
        sets the variance multipliers, so that the model's variance matches the
        odometry's mean squared error (σ multipliers clipped to odometry_adaptive_range)."""
        e = relative_guess(res.pose, odo)  # odometry in the frame of the match
        self._odo_z.append(e * e / np.maximum(np.diag(model), 1e-12))
        if len(self._odo_z) >= self.config.odometry_adaptive_min_matches:
            z = np.mean(np.array(self._odo_z), axis=0)
            self._odo_scale = np.clip(np.sqrt(z), *self.config.odometry_adaptive_range)
            if not self._adapted:
                # the odometry factors so far had the unadapted noise: swap them
                self._adapted = True
                self._flush()
                graph = gtsam.NonlinearFactorGraph()
                for a, delta, cov, slip, unknown, _ in self._early_odometry:
                    graph.add(self._odometry_factor(a, delta, cov, slip, unknown))
                remove = [rec[5] for rec in self._early_odometry]
                self.isam.update(graph, gtsam.Values(), remove)
                self._early_odometry = []
                self._after_update()

    def relative_covariance(self, a: int, b: int, rel: np.ndarray) -> np.ndarray:
        """Covariance of the relative pose a⁻¹·b (tangent space at it, as a
        BetweenFactorPose2 measures it) from the joint marginal of keyframes a and b."""
        joint = self.isam.jointMarginalCovariance([X(a), X(b)])
        saa, sab, sbb = joint.at(X(a), X(a)), joint.at(X(a), X(b)), joint.at(X(b), X(b))
        inv = gtsam.Pose2(*rel).inverse()
        j = -inv.AdjointMap()  # ∂(a⁻¹b)/∂a; ∂(a⁻¹b)/∂b = I
        j_sab = matmul(j, sab)
        cov = congruence(j, saa) + j_sab + j_sab.T + sbb
        return 0.5 * (cov + cov.T)

    # -- what the scan half (slam.scan_graph) uses ------------------------------------
    @property
    def keyframe(self) -> int:
        """The latest keyframe's index (-1 before the first)."""
        return self._kf

    @property
    def odometry_scale(self) -> np.ndarray:
        """The adaptive σ multipliers of the odometry (x, y, θ)."""
        return self._odo_scale

    def add_factor(self, factor: gtsam.NonlinearFactor) -> None:
        """A factor for the next update."""
        self._graph.add(factor)

    def update(self, settle: int = 0) -> None:
        """The factors and keyframes added since into iSAM2, then `settle` more iSAM2
        updates (each relinearises what moved: a loop closure's correction settles)."""
        self._flush()
        if settle > 0:
            for _ in range(settle):
                self.isam.update()
            self._after_update()

    def keyframe_covariance(self, k: int) -> np.ndarray:
        """Keyframe k's marginal covariance (body frame: Pose2's tangent)."""
        return self.isam.marginalCovariance(X(k))

    def finish(self) -> None:
        """The source has ended: the scan half's final pass (slam.scan_graph.FinalPass)."""
        self.scans.finish()

    def _flush(self) -> None:
        if self._graph.size() == 0 and self._values.size() == 0:
            return
        result = self.isam.update(self._graph, self._values)
        if self._pending:
            indices = result.getNewFactorsIndices()
            for pos, record in self._pending:
                record.append(int(indices[pos]))
            self._pending = []
        self._graph = gtsam.NonlinearFactorGraph()
        self._values = gtsam.Values()
        self._after_update()

    def _after_update(self) -> None:
        est = self.isam.calculateEstimatePose2(X(self._kf))
        self._kf_pose = np.array([est.x(), est.y(), est.theta()])
        if self._slip:
            self._k = np.array(self.isam.calculateEstimatePoint2(S(self._kf)), dtype=float)
        self._marginal = None
        self.revision += 1
        self.counts["updates"] += 1

    # -- outputs ----------------------------------------------------------------------
    def estimate(self) -> PoseEstimate:
        if (obs := self.sightings.take()) is not None:
            self._sighted(obs)
        t = self._t if self._t is not None else float("nan")
        if self._kf < 0:
            return PoseEstimate(t, np.array(self.config.initial_pose, float), np.zeros((3, 3)))
        return PoseEstimate(t, *self._pose_now())

    def _pose_now(self) -> tuple[np.ndarray, np.ndarray]:
        """The latest keyframe's estimate ⊕ the odometry since, and its world-frame
        covariance to first order: the keyframe's marginal (body-frame: Pose2's
        tangent) plus the odometry's since, rotated into the world frame."""
        if self._marginal is None:
            if not self.isam.valueExists(X(self._kf)):
                self._flush()  # a keyframe left for the update of its sightings
            self._marginal = self.isam.marginalCovariance(X(self._kf))
        rot = rotation(self._kf_pose[2], 3)
        cov = congruence(rot, self._marginal + self._delta_cov + self._unknown)
        return compose(self._kf_pose, self._delta), cov

    def trajectory(self) -> Trajectory:
        """Each recorded time's pose: its keyframe's estimate and the odometry since, with
        the move the next keyframe's estimate makes to the odometry's prediction of it
        spread back over the stretch (slam.trajectory.spread_corrections), so that the
        path between two keyframes joins both instead of jumping at the second."""
        self._place_held()
        if self._cache is not None and self._cache[0] == self.revision:
            return self._cache[1]
        if not self._records:
            return Trajectory(np.zeros(0), np.zeros((0, 3)))
        values = self.isam.calculateEstimate()
        kf = np.array(
            [[p.x(), p.y(), p.theta()] for p in (values.atPose2(X(k)) for k in range(self._kf + 1))]
        )
        t = np.array([r[0] for r in self._records])
        which = np.array([r[1] for r in self._records])
        delta = np.array([r[2] for r in self._records])
        accumulated = np.array([r[3] for r in self._records])
        poses = compose(kf[which], delta)
        if self._segments:
            # the correction of each stretch k → k + 1: the estimate of k + 1 against
            # the odometry's motion carried from the estimate of k
            seg_delta = np.array([d for d, _ in self._segments])
            totals = np.array([v for _, v in self._segments])
            correction = kf[1:] - compose(kf[:-1], seg_delta)
            correction[:, 2] = wrap_angle(correction[:, 2])
            inner = which < self._kf
            k = which[inner]
            poses[inner] = spread_corrections(
                poses[inner], correction[k], accumulated[inner], totals[k]
            )
        traj = Trajectory(t, poses)
        self._cache = (self.revision, traj)
        return traj

    def landmarks(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        self._place_held()
        values = self.isam.calculateEstimate()
        out = {}
        for lid in sorted(self._landmarks):
            if self._tags:  # a Pose2: its position and that block of the marginal
                tag = values.atPose2(T(lid))
                rot = rotation(tag.theta())  # the marginal is in the tag's frame
                cov = congruence(rot, self.isam.marginalCovariance(T(lid))[:2, :2])
                out[lid] = (np.array([tag.x(), tag.y()]), cov)
            else:
                p = values.atPoint2(L(lid))
                out[lid] = (
                    np.array(p, dtype=float).reshape(2),
                    self.isam.marginalCovariance(L(lid)),
                )
        return out

    def slip_estimate(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(k_left, k_right) of the latest keyframe and their 2×2 marginal covariance;
        None without slip estimation (or before the first keyframe)."""
        if not self._slip or self._kf < 0:
            return None
        self._place_held()
        return self._k.copy(), self.isam.marginalCovariance(S(self._kf))

    def diagnostics(self) -> dict:
        self._place_held()
        notes: dict = {**self.counts, **self.odometry.diagnostics()}
        if self.config.association_enabled:
            notes["map_landmarks"] = len(self._landmarks)
            notes.update(self._discovery.diagnostics())
        if (slip := self.slip_estimate()) is not None:
            notes.update(slip_diagnostics(*slip))
        if self.config.scan_matching:
            notes["odometry_sigma_scale"] = [round(float(v), 3) for v in self._odo_scale]
            if self.counts["scan_factors"] + self.counts["loop_closures"] == 0:
                notes["note"] = "scan matching on, but no scan was matched: odometry only"
        elif self.counts["landmark_factors"] == 0 and fused_count(self.counts) == 0:
            notes["note"] = "no landmark observations in the map: odometry only"
        return notes


SPEC = Spec(
    "gtsam",
    GtsamConfig,
    GtsamSmoother,
    "iSAM2 smoother over keyframes and landmarks (BetweenFactorPose2, BearingRangeFactor2D)",
)
