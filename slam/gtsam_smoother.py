"""`gtsam`: an iSAM2 incremental smoother over keyframe poses and landmarks.

Odometry increments accumulate (with their covariance, propagated through the exact-arc
Jacobians) into a keyframe-to-keyframe `BetweenFactorPose2`; a new keyframe starts when
the walker has moved `keyframe_distance_m`, turned `keyframe_angle_rad` or
`keyframe_time_s` has passed, and also when landmarks are seen `obs_keyframe_dt_s`
after the last keyframe. Landmark observations become `BearingRangeFactor2D` factors on
their keyframe with a Huber-robust noise model (outliers lose their pull rather than
being gated). Every update revises the past: `trajectory()` is the smoothed estimate,
every odometry message placed relative to its (smoothed) keyframe.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from hardware.calibration import WalkerCalibration
from hardware.messages import Message
from slam.base import Localizer, PoseEstimate, register
from slam.geometry import compose
from slam.measurement import LandmarkObservation, landmark_observation
from slam.motion import MotionNoise, OdometryModel, apply_increment, increment_jacobians
from slam.trajectory import Trajectory


@dataclass(frozen=True)
class GtsamConfig:
    """iSAM2 smoother settings.

    initial_pose: prior mean of the first keyframe (the map frame), with prior_sigma.
    keyframe_*: when a new keyframe starts; obs_keyframe_dt_s: landmarks seen this long
    after the last keyframe start a new one (else they attach to it).
    range_sigma_m + range_sigma_frac·r, bearing_sigma_rad: landmark measurement noise;
    huber_k: robust kernel threshold in standard deviations.
    odometry_sigma_floor: added to each between-keyframe odometry covariance (x, y, θ):
    wheel odometry has no lateral noise of its own (the axle cannot slide), and a
    rank-deficient covariance makes the system ill-conditioned.
    """

    initial_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    prior_sigma: tuple[float, float, float] = (1e-3, 1e-3, 1e-4)
    noise: MotionNoise = field(default_factory=MotionNoise)
    keyframe_distance_m: float = 0.25
    keyframe_angle_rad: float = 0.2
    keyframe_time_s: float = 1.0
    obs_keyframe_dt_s: float = 0.2
    range_sigma_m: float = 0.05
    range_sigma_frac: float = 0.02
    bearing_sigma_rad: float = 0.03
    huber_k: float = 1.345
    relinearize_threshold: float = 0.01
    odometry_sigma_floor: tuple[float, float, float] = (1e-3, 1e-3, 1e-3)


class GtsamSmoother(Localizer):
    revises_past = True

    def __init__(self, config: GtsamConfig, calibration: WalkerCalibration) -> None:
        self.config = config
        self.calibration = calibration
        self.odometry = OdometryModel(calibration, config.noise)
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(config.relinearize_threshold)
        self.isam = gtsam.ISAM2(params)
        self._graph = gtsam.NonlinearFactorGraph()
        self._values = gtsam.Values()
        self._kf = -1  # index of the latest keyframe
        self._kf_t: list[float] = []
        self._kf_pose = np.array(config.initial_pose, dtype=float)  # its current estimate
        self._delta = np.zeros(3)  # motion since the latest keyframe, in its frame
        self._delta_cov = np.zeros((3, 3))
        self._records: list[tuple[float, int, np.ndarray]] = []  # (t, keyframe, delta)
        self._landmarks: set[int] = set()
        self._marginal: np.ndarray | None = None
        self._cache: tuple[int, Trajectory] | None = None
        self.counts = {"keyframes": 0, "landmark_factors": 0, "without_id": 0, "updates": 0}
        self._t: float | None = None

    # -- inputs -----------------------------------------------------------------------
    def process(self, msg: Message) -> None:
        inc = self.odometry.increment(msg)
        if inc is not None:
            self._integrate(inc.ds, inc.dtheta, inc.cov)
            self._note(msg.t)
            if self._keyframe_due(msg.t):
                self._new_keyframe(msg.t)
        elif (obs := landmark_observation(msg, self.calibration)) is not None:
            self._observe(obs)
        if self._kf < 0 and self.odometry.has_odometry:
            self._start(msg.t)

    def _start(self, t: float) -> None:
        c = self.config
        pose = gtsam.Pose2(*c.initial_pose)
        self._graph.add(
            gtsam.PriorFactorPose2(
                X(0), pose, gtsam.noiseModel.Diagonal.Sigmas(np.array(c.prior_sigma))
            )
        )
        self._values.insert(X(0), pose)
        self._kf, self._kf_t = 0, [t]
        self._flush()
        self._note(t)

    def _note(self, t: float) -> None:
        if self._kf < 0:
            return
        if self._records and t <= self._records[-1][0]:
            return
        self._t = t
        self._records.append((t, self._kf, self._delta.copy()))

    def _integrate(self, ds: float, dth: float, q: np.ndarray) -> None:
        f, g = increment_jacobians(self._delta[2], ds, dth)
        self._delta = apply_increment(self._delta, ds, dth)
        self._delta_cov = f @ self._delta_cov @ f.T + g @ q @ g.T

    def _keyframe_due(self, t: float) -> bool:
        c = self.config
        return self._kf >= 0 and (
            math.hypot(self._delta[0], self._delta[1]) >= c.keyframe_distance_m
            or abs(self._delta[2]) >= c.keyframe_angle_rad
            or t - self._kf_t[-1] >= c.keyframe_time_s
        )

    def _new_keyframe(self, t: float) -> None:
        k = self._kf + 1
        cov = self._delta_cov + np.diag(np.square(self.config.odometry_sigma_floor))
        self._graph.add(
            gtsam.BetweenFactorPose2(
                X(self._kf),
                X(k),
                gtsam.Pose2(*self._delta),
                gtsam.noiseModel.Gaussian.Covariance(cov),
            )
        )
        self._values.insert(X(k), gtsam.Pose2(*compose(self._kf_pose, self._delta)))
        self._kf = k
        self._kf_t.append(t)
        self._delta = np.zeros(3)
        self._delta_cov = np.zeros((3, 3))
        self.counts["keyframes"] += 1
        self._flush()
        self._note(t)

    def _observe(self, obs: LandmarkObservation) -> None:
        if self._kf < 0 or len(obs) == 0:
            return
        if obs.t - self._kf_t[-1] >= self.config.obs_keyframe_dt_s and np.any(self._delta != 0):
            self._new_keyframe(obs.t)
        c = self.config
        for lid, z in zip(obs.ids, obs.z, strict=True):
            lid = int(lid)
            if lid < 0:
                self.counts["without_id"] += 1
                continue
            # The landmark as seen from the keyframe (the walker moved self._delta since).
            p = np.array([z[0] * math.cos(z[1]), z[0] * math.sin(z[1])])
            c_, s_ = math.cos(self._delta[2]), math.sin(self._delta[2])
            q = self._delta[:2] + np.array([c_ * p[0] - s_ * p[1], s_ * p[0] + c_ * p[1]])
            r, b = float(np.hypot(*q)), float(math.atan2(q[1], q[0]))
            sr = c.range_sigma_m + c.range_sigma_frac * r
            noise = gtsam.noiseModel.Robust.Create(
                gtsam.noiseModel.mEstimator.Huber.Create(c.huber_k),
                gtsam.noiseModel.Diagonal.Sigmas(np.array([c.bearing_sigma_rad, sr])),
            )
            self._graph.add(
                gtsam.BearingRangeFactor2D(X(self._kf), L(lid), gtsam.Rot2(b), r, noise)
            )
            if lid not in self._landmarks:
                self._landmarks.add(lid)
                a = self._kf_pose[2] + b
                guess = self._kf_pose[:2] + r * np.array([math.cos(a), math.sin(a)])
                self._values.insert(L(lid), gtsam.Point2(*guess))
            self.counts["landmark_factors"] += 1
        self._flush()

    def _flush(self) -> None:
        if self._graph.size() == 0 and self._values.size() == 0:
            return
        self.isam.update(self._graph, self._values)
        self._graph = gtsam.NonlinearFactorGraph()
        self._values = gtsam.Values()
        est = self.isam.calculateEstimatePose2(X(self._kf))
        self._kf_pose = np.array([est.x(), est.y(), est.theta()])
        self._marginal = None
        self.revision += 1
        self.counts["updates"] += 1

    # -- outputs ----------------------------------------------------------------------
    def estimate(self) -> PoseEstimate:
        t = self._t if self._t is not None else float("nan")
        if self._kf < 0:
            return PoseEstimate(t, np.array(self.config.initial_pose, float), np.zeros((3, 3)))
        if self._marginal is None:
            self._marginal = self.isam.marginalCovariance(X(self._kf))
        # Covariance of kf ⊕ delta to first order: rotate the keyframe's into the world
        # frame is already done by GTSAM (Pose2 tangent is body-frame); add delta's.
        c, s = math.cos(self._kf_pose[2]), math.sin(self._kf_pose[2])
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        cov = rot @ (self._marginal + self._delta_cov) @ rot.T
        return PoseEstimate(t, compose(self._kf_pose, self._delta), cov)

    def trajectory(self) -> Trajectory:
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
        traj = Trajectory(t, compose(kf[which], delta))
        self._cache = (self.revision, traj)
        return traj

    def landmarks(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        values = self.isam.calculateEstimate()
        out = {}
        for lid in sorted(self._landmarks):
            p = values.atPoint2(L(lid))
            out[lid] = (np.array(p, dtype=float).reshape(2), self.isam.marginalCovariance(L(lid)))
        return out

    def diagnostics(self) -> dict:
        notes = dict(self.counts)
        if self.counts["landmark_factors"] == 0:
            notes["note"] = "no landmark observations with an ID: odometry only"
        return notes


register(
    "gtsam",
    GtsamConfig,
    "iSAM2 smoother over keyframes and landmarks (BetweenFactorPose2, BearingRangeFactor2D)",
)(GtsamSmoother)
