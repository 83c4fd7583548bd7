"""EKF-SLAM: one Gaussian over the pose and every landmark.

State [x, y, θ, u_1, v_1, …]; a landmark joins the state at its first observation
(inverse measurement model, with its covariance and cross-covariances); odometry
increments predict; range-bearing observations (tags seen by the camera, or range-bearing
datasets) update, one landmark at a time, after a Mahalanobis gate rejects outliers.
Observations without an ID (< 0: trees in a laser scan, corners) are associated with the
map's landmarks by joint compatibility (JCBB, or nearest neighbour: slam.association,
`association.method`) over the pose and the landmarks involved, then update like the
others; the ones that match no landmark become provisional landmarks, which join the
state once seen again (`association.confirm_sightings`) and are dropped otherwise
(`association_enabled=false`: observations without an ID are counted and not used).
Absolute observations (`absolute`, slam.absolute: a compass heading, a position fix),
when switched on, are Kalman updates of the pose block (heading innovation wrapped),
behind a Mahalanobis gate at the chi-squared quantile `absolute.gate_prob`.

With `slip.estimate` the state also holds each rear wheel's slip coefficient,
[x, y, θ, k_L, k_R, u_1, v_1, …] (slam.slip): odometry moves the pose by the
slip-corrected arc and k by its random walk, and the tag updates correct both.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hardware.calibration import WalkerCalibration
from hardware.choices import Choice, coerce
from hardware.geometry import wrap_angle
from hardware.messages import Message
from hardware.registry import Spec
from slam import ekf_kernels as kernels
from slam.absolute import (
    AbsoluteConfig,
    AbsoluteObservation,
    absolute_observation,
    fused_count,
)
from slam.association import (
    AssociationConfig,
    AssociationMethod,
    Discovery,
    jcbb,
    mahalanobis2,
    nearest_neighbour,
)
from slam.base import Localizer, LocalizerConfig, PoseEstimate
from slam.measurement import (
    BEARING_SIGMA_RAD,
    RANGE_SIGMA_FRAC,
    RANGE_SIGMA_M,
    LandmarkObservation,
    Sightings,
    landmark_from_range_bearing,
    landmark_from_range_bearing_jacobians,
    placed_sightings,
    range_bearing,
    range_bearing_jacobians,
    range_sigma,
)
from slam.motion import Cov3, Increment, MotionNoise, OdometryModel, propagate, split_increment
from slam.rts import rts_smooth
from slam.slip import SlipEstimation, predict_with_slip, slip_diagnostics
from slam.state_smoother import StateSmoother, StepOdometry, bridge, epoch_step
from slam.trajectory import Trajectory, TrajectoryRecorder


class EkfSmoother(Choice):
    """The EKF's trajectory: Rauch–Tung–Striebel smoothed over the whole run (the whole
    state, or the pose alone), or filtered."""

    RTS_FULL = "rts-full"
    RTS = "rts"
    NONE = "none"


@dataclass(frozen=True)
class EkfSlamConfig(LocalizerConfig):
    """EKF-SLAM settings.

    initial_pose: (x, y, θ), known exactly (it defines the map frame).
    noise: odometry noise (slam.motion.MotionNoise).
    range_sigma_m + range_sigma_frac·r: range noise; bearing_sigma_rad: bearing noise
    (defaults: an AprilTag camera, slam.measurement.RANGE_SIGMA_M and the others).
    gate_chi2: Mahalanobis gate for an update (13.8 = 99.9 % for 2 DOF); inf disables.
    association: data association for observations without IDs (slam.association.
    AssociationConfig) and `association_enabled` (False: they are not used).
    smoother: "rts-full": `trajectory()` is the whole state (pose and landmarks)
    RTS-smoothed over the run (slam.state_smoother), so every pose takes the final map's
    landmarks, and the pipeline rebuilds the map along it (`revises_past`); it keeps the
    state's covariance at every update epoch, within smoother_budget_mb (past it, as
    "rts", and the diagnostics say so). "rts": the pose track alone RTS-smoothed
    over the odometry (slam.rts), which carries a loop closure's correction back along
    the path that led to it, in constant memory per step; "none": the filtered poses,
    each fixed when it was recorded.
    absolute: compass / position-fix fusion (slam.absolute.AbsoluteConfig; off by
    default), gated at absolute.gate_prob.
    slip: per-wheel slip estimation (slam.slip.SlipEstimation; `slip.estimate=true`).
    align_observations: a landmark observation is held until the next odometry message,
    whose increment is split at the observation's time (slam.motion.split_increment),
    so that it updates the pose of its own time; otherwise the pose of the last
    odometry message (a tag frame comes 10 ms after a 50 Hz encoder message: in a turn
    the walker has turned on by then, which biases a slip estimate low).
    """

    noise: MotionNoise = field(default_factory=MotionNoise)
    range_sigma_m: float = RANGE_SIGMA_M
    range_sigma_frac: float = RANGE_SIGMA_FRAC
    bearing_sigma_rad: float = BEARING_SIGMA_RAD
    gate_chi2: float = 13.8
    association_enabled: bool = True
    association: AssociationConfig = field(default_factory=AssociationConfig)
    smoother: EkfSmoother = EkfSmoother.RTS_FULL
    smoother_budget_mb: float = 256.0
    absolute: AbsoluteConfig = field(default_factory=AbsoluteConfig)
    slip: SlipEstimation = field(default_factory=SlipEstimation)
    align_observations: bool = False

    def __post_init__(self) -> None:
        coerce(self, smoother=EkfSmoother)
        if not self.smoother_budget_mb > 0:
            raise ValueError(f"smoother_budget_mb must be > 0, got {self.smoother_budget_mb}")


class EkfSlam(Localizer):
    def __init__(self, config: EkfSlamConfig, calibration: WalkerCalibration) -> None:
        self.config = config
        self.calibration = calibration
        self.odometry = OdometryModel(calibration, config.noise)
        self._x = np.array(config.initial_pose, dtype=float)
        self._P = np.zeros((3, 3))
        self._slip = config.slip.estimate
        if self._slip:  # k after the pose; the landmarks then start at 5 (_sync)
            self._x = np.concatenate([self._x, config.slip.k_prior])
            self._P = np.zeros((5, 5))
            self._P[3:, 3:] = config.slip.prior_cov()
        self._k = self._x[3:5].copy()
        self._block = self._P[:5, :5].copy()  # (pose, k) covariance between updates
        self._bk = np.zeros((3, 2))  # ∂pose/∂k of the steps since the last update
        # Between updates, odometry moves only the pose and its 3×3 covariance (on floats,
        # slam.motion.propagate); the pose–landmark cross-covariance rows are moved once,
        # by the sum of the steps' (a, b), when the full state is next needed (_sync).
        self._pose = tuple(float(v) for v in self._x[:3])
        self._cov3 = tuple(tuple(r) for r in self._P[:3, :3].tolist())
        self._cross = [0.0, 0.0]
        self._stale = True  # the full state lags the pose predicted since the last sync
        self.index: dict[int, int] = {}  # landmark id → state offset
        self.counts = {"updates": 0, "new_landmarks": 0, "gated": 0, "without_id": 0}
        if config.association_enabled:
            self.counts.update(associated=0, jcbb_changed=0, jcbb_budget=0)
        self._discovery = Discovery(config.association)
        if config.absolute.enabled:
            self.counts.update(compass_updates=0, position_updates=0, absolute_gated=0)
        self._gates = {dof: config.absolute.gate(dof) for dof in (1, 2)}
        self.track = TrajectoryRecorder()
        self.revises_past = config.smoother != EkfSmoother.NONE
        full = config.smoother == EkfSmoother.RTS_FULL
        budget = config.smoother_budget_mb * 1e6
        self._full = StateSmoother(5 if self._slip else 3, budget) if full else None
        # per recorded step, for the smoother: the pose covariance (after the updates of
        # that time) and the odometry increment that led to it (ds, dθ, q00, q01, q11)
        self._f_cov: list[Cov3] = []
        self._f_inc = StepOdometry()
        self._path_cache: tuple[tuple[int, int], Trajectory] | None = None
        self._held: list[LandmarkObservation] = []  # align_observations: not yet used
        self.sightings = Sightings(calibration)

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
                self._observe(obs, between=True)
            self._held = []
            self._move(inc)
            self._record(msg.t)
        elif (fix := absolute_observation(msg, self.config.absolute)) is not None:
            self._absolute(fix)
        if not self.track and self.odometry.has_odometry:
            self._record(msg.t)

    def _sighted(self, obs: LandmarkObservation) -> None:
        """The landmark sightings of one time (slam.measurement.Sightings)."""
        if self.config.align_observations and self.track and obs.t > self.track.last_t:
            self._held.append(obs)  # placed when the next odometry message spans it
        else:
            self._observe(obs)

    def _move(self, inc: Increment) -> None:
        if self._slip:
            self._predict_slip(inc)
        else:
            self._predict(inc.ds, inc.dtheta, inc.cov)

    def _predict(self, ds: float, dth: float, q: np.ndarray) -> None:
        self._stale = True
        self._pose, self._cov3, (a, b) = propagate(self._pose, self._cov3, ds, dth, q)
        self._cross[0] += a
        self._cross[1] += b
        if self.revises_past:
            self._f_inc.add(ds, dth, q)

    def _predict_slip(self, inc) -> None:
        """The prediction with slip estimation: pose and k together (slam.slip), and the
        deferred cross-covariance of the pose with the landmarks, now
        P_pose,l ← F P_pose,l + F_k P_k,l (k's rows with the landmarks do not move)."""
        self._stale = True
        c = self.config
        step = predict_with_slip(
            np.array(self._pose),
            self._block,
            inc,
            self._k,
            self.calibration.track_m,
            c.slip.random_walk_per_s**2,
        )
        self._pose = tuple(step.pose.tolist())
        self._block = step.cov
        self._cov3 = tuple(tuple(r) for r in step.cov[:3, :3].tolist())
        self._bk = step.f @ self._bk + step.f_k
        self._cross[0] += float(step.f[0, 2])
        self._cross[1] += float(step.f[1, 2])
        if self.revises_past:
            self._f_inc.add(step.ds, step.dtheta, step.q)

    def _sync(self, between: bool = False) -> None:
        """Bring the full state up to date with the predictions since the last update;
        between: for an observation made after the last recorded step (its epoch leads
        to the next step)."""
        if not self._stale:
            return
        self._stale = False
        if self._full is not None:  # a new epoch: the last one's state, the prediction
            a, b = self._cross
            top = (
                (np.r_[self._pose, self._k], self._block)
                if self._slip
                else (self._pose, self._cov3)
            )
            bk = self._bk if self._slip else None
            step = epoch_step(len(self.track), between)
            self._full.begin(step, self._x, self._P, a, b, bk, *top)
        self._x[:3] = self._pose
        p = self._P
        n = 5 if self._slip else 3  # where the landmarks start
        if self._slip:
            p[:5, :5] = self._block
        else:
            p[:3, :3] = self._cov3
        a, b = self._cross
        if len(self._x) > n and (a or b or self._slip):
            p[0, n:] += a * p[2, n:]
            p[1, n:] += b * p[2, n:]
            if self._slip:
                p[:3, n:] += self._bk @ p[3:5, n:]
                p[n:, :3] = p[:3, n:].T
            else:
                p[3:, :2] = p[:2, 3:].T
        self._cross = [0.0, 0.0]
        self._bk = np.zeros((3, 2))

    def _unsync(self) -> None:
        """Take the pose and its covariance back from the full state after an update."""
        self._pose = tuple(self._x[:3].tolist())
        self._cov3 = tuple(tuple(r) for r in self._P[:3, :3].tolist())
        if self._slip:
            self._k = self._x[3:5].copy()
            self._block = self._P[:5, :5].copy()

    def _variances(self, range_m: float) -> tuple[float, float]:
        """Range and bearing variances of an observation at this range."""
        sr = range_sigma(self.config, range_m)
        return sr * sr, self.config.bearing_sigma_rad**2

    def _noise(self, z: np.ndarray) -> np.ndarray:
        return np.diag(self._variances(float(z[0])))

    def _observe(self, obs: LandmarkObservation, between: bool = False) -> None:
        """Update with one message's observations; between: made after the last
        recorded step (align_observations), which then keeps its pose and covariance."""
        self._sync(between)
        unknown = []
        for lid, z in zip(obs.ids, obs.z, strict=True):
            lid = int(lid)
            if lid < 0:
                self.counts["without_id"] += 1
                unknown.append(z)
            elif lid in self.index:
                self._update(self.index[lid], z, amend=not between)
            else:
                self._add_landmark(lid, z)
        if unknown and self.config.association_enabled:
            self._associate(obs.t, np.array(unknown, dtype=float), between)
        self._unsync()
        self._after_observation(between)

    def _after_observation(self, between: bool = False) -> None:
        """The smoother's last step takes the corrected covariance (unless the observation
        was made after it: align_observations); the past is revised."""
        if self.revises_past and self._f_cov:
            if not between:
                self._f_cov[-1] = self._cov3
            self.revision += 1

    def _absolute(self, obs: AbsoluteObservation) -> None:
        """A Kalman update of the pose by a compass heading or a position fix (gated)."""
        self._sync()
        h = obs.jacobian
        pht = self._P[:, :3] @ h.T
        s = h @ pht[:3] + obs.covariance
        if self._correct(pht, s, obs.residual(self._x[:3]), self._gates[len(obs.z)]):
            self.counts[f"{obs.kind}_updates"] += 1
        else:
            self.counts["absolute_gated"] += 1
        self._unsync()
        self._after_observation()

    def _associate(self, t: float, z: np.ndarray, between: bool) -> None:
        """Observations (n, 2) without IDs (slam.association): paired with the map's
        landmarks (JCBB or nearest neighbour) and used as theirs; the others new
        (provisional) or ambiguous (dropped)."""
        c = self.config.association
        var = np.array([self._variances(float(r)) for r in z[:, 0]])  # (n, 2)
        offsets = np.fromiter(self.index.values(), dtype=int, count=len(self.index))
        assignment = np.full(len(z), -1, dtype=int)
        d2_min = np.full(len(z), np.inf)
        if len(offsets):
            pose, p = self._x[:3], self._P
            lm = np.stack([self._x[offsets], self._x[offsets + 1]], axis=-1)
            g_s, g_l = range_bearing_jacobians(pose, lm)  # (m, 2, 3), (m, 2, 2)
            rows = offsets[:, None] + np.arange(2)  # (m, 2)
            p_sl = np.moveaxis(p[:3][:, rows], 1, 0)  # (m, 3, 2)
            cross = g_s @ p_sl @ np.swapaxes(g_l, 1, 2)
            s_base = (
                g_s @ p[:3, :3] @ np.swapaxes(g_s, 1, 2)
                + cross
                + np.swapaxes(cross, 1, 2)
                + g_l @ p[rows[:, :, None], rows[:, None, :]] @ np.swapaxes(g_l, 1, 2)
            )
            nu = z[:, None, :] - range_bearing(pose, lm)[None]
            nu[..., 1] = wrap_angle(nu[..., 1])
            s_all = s_base[None] + var[:, None, :, None] * np.eye(2)
            d2 = mahalanobis2(nu, s_all)
            d2_min = d2.min(axis=1)
            nn = nearest_neighbour(d2, c.gate())
            assignment = nn
            if c.method == AssociationMethod.JCBB:

                def joint(pairs):
                    cols = [0, 1, 2] + [int(v) for _, j in pairs for v in rows[j]]
                    h = np.zeros((2 * len(pairs), len(cols)))
                    for q, (_, j) in enumerate(pairs):
                        h[2 * q : 2 * q + 2, :3] = g_s[j]
                        h[2 * q : 2 * q + 2, 3 + 2 * q : 5 + 2 * q] = g_l[j]
                    noise = np.diag(np.concatenate([var[i] for i, _ in pairs]))
                    return h @ p[np.ix_(cols, cols)] @ h.T + noise

                res = jcbb(d2, nu, joint, c)
                assignment = res.assignment
                self.counts["jcbb_changed"] += int(np.count_nonzero(assignment != nn))
                self.counts["jcbb_budget"] += int(res.exhausted)
        for i in np.flatnonzero(assignment >= 0):
            self.counts["associated"] += 1
            self._update(int(offsets[assignment[i]]), z[i], amend=not between)
        new = self._discovery.new(assignment, d2_min)
        if not new.any():
            return
        zn = z[new]
        points, covs = placed_sightings(self._x[:3], zn, var[new], self._P[:3, :3])
        for k, lid in self._discovery.confirm(t, points, covs):
            self._add_landmark(lid, zn[k])

    def _add_landmark(self, lid: int, z: np.ndarray) -> None:
        pose = self._x[:3]
        j_s, j_z = landmark_from_range_bearing_jacobians(pose, z)
        n = len(self._x)
        p = np.zeros((n + 2, n + 2))
        p[:n, :n] = self._P
        cross = j_s @ self._P[:3, :]  # 2 × n
        p[n:, :n] = cross
        p[:n, n:] = cross.T
        p[n:, n:] = j_s @ self._P[:3, :3] @ j_s.T + j_z @ self._noise(z) @ j_z.T
        self._x = np.concatenate([self._x, landmark_from_range_bearing(pose, z)])
        self._P = p
        self.index[lid] = n
        self.counts["new_landmarks"] += 1

    def _update(self, j: int, z: np.ndarray, amend: bool = True) -> None:
        """The Kalman update by a range-bearing observation z of the landmark at state
        index j, in closed form and compiled (slam.ekf_kernels), unless gated."""
        var_r, var_b = self._variances(float(z[0]))
        z0, z1, gate = float(z[0]), float(z[1]), self.config.gate_chi2
        if not kernels.range_bearing_update(self._x, self._P, j, z0, z1, var_r, var_b, gate):
            self.counts["gated"] += 1
            return
        self._corrected(amend)
        self.counts["updates"] += 1

    def _correct(self, pht: np.ndarray, s: np.ndarray, nu: np.ndarray, gate: float) -> bool:
        """The Kalman correction with K = P Hᵀ S⁻¹ (pht = P Hᵀ, s = S), unless ν's squared
        Mahalanobis distance exceeds `gate` (then False)."""
        s_inv = np.linalg.inv(s)
        if float(nu @ s_inv @ nu) > gate:
            return False
        kernels.apply(self._x, self._P, pht @ s_inv, pht, nu)
        self._corrected()
        return True

    def _corrected(self, amend: bool = True) -> None:
        """amend: the trajectory's latest pose takes the corrected pose (not for an
        observation placed inside an odometry step, whose pose is not the latest)."""
        if amend:
            self.track.amend(tuple(self._x[:3].tolist()))

    def _record(self, t: float) -> None:
        n = len(self.track)
        self.track.record(t, self._pose)
        if not self.revises_past:
            return
        if len(self.track) > n:
            self._f_cov.append(self._cov3)
        else:  # the same time again: that step, moved further
            self._f_cov[-1] = self._cov3
        self._f_inc.close(len(self.track) > n)

    def _place_held(self) -> None:
        """An output is asked for: the sightings not yet complete taken as they are, and
        observations still waiting for the odometry after them (align_observations) used
        at the latest pose."""
        if (obs := self.sightings.take()) is not None:
            self._sighted(obs)
        held, self._held = self._held, []
        for obs in held:
            self._observe(obs)

    # -- outputs ----------------------------------------------------------------------
    def estimate(self) -> PoseEstimate:
        if (obs := self.sightings.take()) is not None:
            self._sighted(obs)
        return PoseEstimate(self.track.last_t, np.array(self._pose), np.array(self._cov3))

    def trajectory(self) -> Trajectory:
        """The RTS-smoothed pose track (config.smoother: of the whole state, or of the
        pose alone) or the filtered poses."""
        self._place_held()
        filtered = self.track.trajectory()
        if not self.revises_past or len(filtered) < 2:
            return filtered
        key = (self.revision, len(filtered))
        if self._path_cache is None or self._path_cache[0] != key:
            deltas, delta_covs = self._f_inc.deltas()
            means, covs = filtered.poses, np.array(self._f_cov)
            if self._full is not None and self._full.exceeded is None:
                epochs = self._full.smoothed(self._x, self._P)
                means, covs = bridge(means, covs, deltas, delta_covs, *epochs)
            poses = rts_smooth(means, covs, deltas, delta_covs)
            self._path_cache = (key, Trajectory(filtered.t, poses))
        return self._path_cache[1]

    def state(self) -> tuple[np.ndarray, np.ndarray]:
        """(mean, covariance) of the whole state [x, y, θ, u_1, v_1, …] (copies); with
        slip estimation [x, y, θ, k_L, k_R, u_1, v_1, …]."""
        self._place_held()
        self._sync()
        return self._x.copy(), self._P.copy()

    def slip_estimate(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(k_left, k_right) and their 2×2 covariance; None without slip estimation."""
        if not self._slip:
            return None
        self._place_held()
        return self._k.copy(), self._block[3:, 3:].copy()

    def landmarks(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """Landmark id → (mean (2,), covariance 2×2)."""
        self._place_held()
        self._sync()
        return {
            lid: (self._x[j : j + 2].copy(), self._P[j : j + 2, j : j + 2].copy())
            for lid, j in self.index.items()
        }

    def diagnostics(self) -> dict:
        self._place_held()
        notes: dict = {**self.counts, **self.odometry.diagnostics()}
        if self.config.association_enabled:
            notes["map_landmarks"] = len(self.index)
            notes.update(self._discovery.diagnostics())
        c = self.counts
        absolute = fused_count(c)
        if c["updates"] == 0 and c["new_landmarks"] == 0 and absolute == 0:
            notes["note"] = "no landmark observations in the map: odometry only"
        if self._full is not None and self._full.exceeded is not None:
            notes["note"] = (
                f"the whole state's smoothing went over smoother_budget_mb "
                f"({self.config.smoother_budget_mb:g} MB) at step {self._full.exceeded}: "
                "the pose alone is smoothed"
            )
        if (slip := self.slip_estimate()) is not None:
            notes.update(slip_diagnostics(*slip))
        return notes


SPEC = Spec(
    "ekf-slam",
    EkfSlamConfig,
    EkfSlam,
    "EKF over the pose and all landmarks (known IDs), range-bearing updates",
)
