"""Landmark measurement models: range-bearing and planar tag pose, with their Jacobians.

A landmark is a point l = (u, v) in the world (a tag's centre, a barcode, a tree). From
the walker pose s = (x, y, θ):

    range-bearing  z = h(s, l) = [√((u−x)² + (v−y)²), atan2(v−y, u−x) − θ]    (thesis App. A)
    tag pose       z = (tag x, tag y, tag yaw) in the walker frame (full tag observation)

Tag detections (camera-frame 4×4 poses) become walker-frame observations through the
camera mount. All functions are vectorised over leading dimensions (particles, landmarks).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache, lru_cache

import numpy as np
from scipy.special import gammaincinv

from hardware.calibration import Mount, WalkerCalibration
from hardware.choices import Choice
from hardware.geometry import wrap_angle
from hardware.messages import (
    LANDMARK_MESSAGES,
    Message,
    RangeBearing,
    RangeBearings,
    TagDetections,
)


@cache
def chi2_quantile(p: float, dof: int) -> float:
    """The p quantile of χ² with `dof` degrees of freedom: a squared-Mahalanobis gate.

    scipy.stats.chi2.ppf's own formula (2·P⁻¹(dof/2, p), P the regularised lower
    incomplete gamma function), the same bits, without importing scipy.stats (1–2 s,
    paid by every command-line call that loads a localizer)."""
    return float(2.0 * gammaincinv(dof / 2.0, p))


# Default landmark noise of the localizers: range σ = RANGE_SIGMA_M + RANGE_SIGMA_FRAC·r,
# bearing σ = BEARING_SIGMA_RAD. They describe an AprilTag camera (the walker's tag
# camera, real or simulated): a tag's bearing is read from its centre pixel and is
# precise, its range comes from the PnP solution and is neither precise nor unbiased.
# Measured on the simulated camera (0.5 px corner noise, 0.165 m tags, 640×480) against
# the true geometry: bearing σ ≈ 0.2° (incl. the ground truth's 20 ms sampling); range
# σ 0.009 / 0.021 / 0.039 / 0.061 m at 1.3 / 2.0 / 2.8 / 3.5 m, biased short by up to
# 1.4 % (IPPE on small noisy tags). The range σ is inflated well past that because the
# bias and the noise are correlated over the 10 Hz frames of a pass: trusted as
# independent, they shrink the map and drag its frame. Chosen on simulated trials of
# seeds 1 and 2 (BENCHMARKS.md, "tag noise"); datasets propose their own
# (metadata "localizer_settings", e.g. MRCLAM's fitted barcode-camera noise).
RANGE_SIGMA_M = 0.1
RANGE_SIGMA_FRAC = 0.05
BEARING_SIGMA_RAD = 0.005


def range_sigma(config, r):
    """The range σ of sightings at range(s) r by a localizer's config: its range_sigma_m +
    range_sigma_frac · r (a float, or an array like r)."""
    return config.range_sigma_m + config.range_sigma_frac * r


def robust_log_likelihood(
    log_gauss: np.ndarray, log_norm: np.ndarray | float, outlier_prob: float, log_outlier: float
) -> np.ndarray:
    """log[(1 − ε)·N + ε·u] − log_norm: an observation's robust log-density (a Gaussian
    N = exp(log_norm + log_gauss) mixed with a uniform outlier density u, ε =
    outlier_prob, log_outlier = log(ε·u)) less the Gaussian's normaliser, so that as ε → 0
    it becomes log_gauss (the particle filter's landmark and absolute likelihoods)."""
    log_in = math.log1p(-outlier_prob) + log_norm + log_gauss
    return np.logaddexp(log_in, log_outlier) - log_norm


class ObservationModel(Choice):
    """What a landmark-based localizer takes from a landmark observation: its range and
    bearing (to a point landmark) or, for a tag, its full planar pose."""

    RANGE_BEARING = "range-bearing"
    TAG_POSE = "tag-pose"


def range_bearing(pose: np.ndarray, landmark: np.ndarray) -> np.ndarray:
    """h(s, l) → (..., 2) range and bearing; broadcasts over leading dimensions."""
    dx = landmark[..., 0] - pose[..., 0]
    dy = landmark[..., 1] - pose[..., 1]
    return np.stack([np.hypot(dx, dy), wrap_angle(np.arctan2(dy, dx) - pose[..., 2])], axis=-1)


def range_bearing_jacobians(
    pose: np.ndarray, landmark: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(∂h/∂s (..., 2, 3), ∂h/∂l (..., 2, 2)) of `range_bearing` (G_s and G_θ of App. A)."""
    dx = landmark[..., 0] - pose[..., 0]
    dy = landmark[..., 1] - pose[..., 1]
    q = np.maximum(dx * dx + dy * dy, 1e-12)
    r = np.sqrt(q)
    g_l = np.empty((*np.shape(dx), 2, 2))
    g_l[..., 0, 0] = dx / r
    g_l[..., 0, 1] = dy / r
    g_l[..., 1, 0] = -dy / q
    g_l[..., 1, 1] = dx / q
    g_s = np.empty((*np.shape(dx), 2, 3))
    g_s[..., :2] = -g_l
    g_s[..., 0, 2] = 0.0
    g_s[..., 1, 2] = -1.0
    return g_s, g_l


def landmark_from_range_bearing(pose: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Inverse model: the landmark position (..., 2) that explains z from pose."""
    a = pose[..., 2] + z[..., 1]
    return np.stack(
        [pose[..., 0] + z[..., 0] * np.cos(a), pose[..., 1] + z[..., 0] * np.sin(a)], axis=-1
    )


def landmark_from_range_bearing_jacobians(
    pose: np.ndarray, z: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(∂l/∂s (..., 2, 3), ∂l/∂z (..., 2, 2)) of the inverse model (landmark initialisation)."""
    a = pose[..., 2] + z[..., 1]
    c, s = np.cos(a), np.sin(a)
    r = z[..., 0]
    one, zero = np.ones_like(r), np.zeros_like(r)
    j_s = np.stack(
        [np.stack([one, zero, -r * s], axis=-1), np.stack([zero, one, r * c], axis=-1)], axis=-2
    )
    j_z = np.stack([np.stack([c, -r * s], axis=-1), np.stack([s, r * c], axis=-1)], axis=-2)
    return j_s, j_z


def placed_sightings(
    pose: np.ndarray, z: np.ndarray, variances: np.ndarray, pose_cov: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Range-bearing sightings z (k, 2) from `pose` as world points (k, 2) with their
    covariances (k, 2, 2): J_z R J_zᵀ, R = diag(variances (k, 2): range, bearing), plus
    J_s P J_sᵀ when the pose's covariance P is given (first order, inverse model)."""
    j_s, j_z = landmark_from_range_bearing_jacobians(pose, z)
    noise = np.asarray(variances, dtype=float)[:, :, None] * np.eye(2)
    covs = j_z @ noise @ np.swapaxes(j_z, 1, 2)
    if pose_cov is not None:
        covs = covs + j_s @ pose_cov @ np.swapaxes(j_s, 1, 2)
    return landmark_from_range_bearing(pose, z), covs


@dataclass(frozen=True, eq=False)
class LandmarkObservation:
    """Observations of landmarks with known IDs at one time, in the walker frame.

    z: (N, 2) range [m] and bearing [rad]; yaw: (N,) the landmark's own yaw in the walker
    frame when the sensor measures it (a tag's pose), NaN otherwise.
    """

    t: float
    ids: np.ndarray
    z: np.ndarray
    yaw: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)


def tag_observations(msg: TagDetections, calibration: WalkerCalibration) -> LandmarkObservation:
    """Tag detections → range, bearing and yaw of each tag centre in the walker frame.

    The tag's yaw is the heading of its outward normal (−z of the tag frame), projected
    on the floor plane, so it compares directly with `TagPose.yaw` of the world.
    """
    walker_T_optical = _walker_T_optical(calibration.tag_mount)
    ids, zs, yaws = [], [], []
    for d in msg.detections:
        walker_T_tag = walker_T_optical @ np.asarray(d.camera_T_tag, dtype=float)
        x, y = walker_T_tag[0, 3], walker_T_tag[1, 3]
        normal = -walker_T_tag[:3, 2]
        ids.append(d.tag_id)
        zs.append((np.hypot(x, y), np.arctan2(y, x)))
        yaws.append(np.arctan2(normal[1], normal[0]))
    return LandmarkObservation(
        msg.t, np.array(ids, dtype=int), np.array(zs, dtype=float).reshape(-1, 2), np.array(yaws)
    )


@lru_cache(maxsize=8)
def _walker_T_optical(mount: Mount) -> np.ndarray:
    """The mount's transform, computed once (~40 µs) and shared read-only."""
    t = mount.walker_T_optical()
    t.setflags(write=False)
    return t


def landmark_observation(
    msg: Message, calibration: WalkerCalibration
) -> LandmarkObservation | None:
    """The landmark observations a message carries (tag detections or a range-bearing
    measurement), or None when it carries none."""
    if isinstance(msg, TagDetections):
        return tag_observations(msg, calibration) if msg.detections else None
    if isinstance(msg, RangeBearing):
        return range_bearing_observation(msg)
    if isinstance(msg, RangeBearings):
        return range_bearings_observation(msg) if len(msg) else None
    return None


def range_bearing_observation(msg: RangeBearing) -> LandmarkObservation:
    return LandmarkObservation(
        msg.t,
        np.array([msg.landmark_id]),
        np.array([[msg.range_m, wrap_angle(msg.bearing_rad)]]),
        np.array([np.nan]),
    )


def range_bearings_observation(msg: RangeBearings) -> LandmarkObservation:
    return LandmarkObservation(
        msg.t,
        np.asarray(msg.landmark_ids, dtype=int),
        np.stack([msg.ranges_m, wrap_angle(msg.bearings_rad)], axis=-1),
        np.full(len(msg), np.nan),
    )


class Sightings:
    """The landmark sightings of one time, gathered from however many messages bring them
    (one RangeBearing per landmark, as MRCLAM; one RangeBearings or TagDetections per
    frame), so that a localizer uses them once, as one LandmarkObservation, whichever way
    they came.

    `offer(msg)` before a localizer handles a message: it returns the sightings held so
    far when `msg` ends them (a message of another time, or not a sighting), else None;
    and keeps `msg` when it is itself a sighting (then `taken` is True and the localizer
    has nothing else to do with it). `take()` returns what is held (an output is asked
    for). A RangeBearing is kept as four numbers until then, a lone frame as it is, so
    the per-landmark form costs little more than the batched one (issue 13)."""

    __slots__ = ("_calibration", "_items", "_t", "taken")

    def __init__(self, calibration: WalkerCalibration) -> None:
        self._calibration = calibration
        self._t = math.nan
        # (id, range, bearing, yaw) of each RangeBearing, or an observation as it came
        self._items: list[tuple[int, float, float, float] | LandmarkObservation] = []
        self.taken = False

    def __bool__(self) -> bool:
        return bool(self._items)

    @property
    def t(self) -> float:
        """Time of the sightings held (NaN when none)."""
        return self._t

    def offer(self, msg: Message) -> LandmarkObservation | None:
        if isinstance(msg, RangeBearing):
            ready = self.take() if self._items and msg.t != self._t else None
            b = math.pi - ((math.pi - msg.bearing_rad) % (2.0 * math.pi))  # wrap_angle
            self._items.append((msg.landmark_id, msg.range_m, b, math.nan))
            self._t = msg.t
            self.taken = True
            return ready
        obs = landmark_observation(msg, self._calibration)
        self.taken = obs is not None or isinstance(msg, LANDMARK_MESSAGES)
        ready = self.take() if self._items and (not self.taken or msg.t != self._t) else None
        if obs is not None:
            self._items.append(obs)  # kept whole while it is alone
            self._t = msg.t
        return ready

    def take(self) -> LandmarkObservation | None:
        """The sightings held (in the order they came), as one observation; None if none."""
        items, self._items = self._items, []
        if not items:
            return None
        if len(items) == 1 and isinstance(items[0], LandmarkObservation):
            self._t = math.nan
            return items[0]
        rows = []
        for it in items:
            if isinstance(it, LandmarkObservation):
                rows.extend(zip(it.ids.tolist(), *it.z.T.tolist(), it.yaw.tolist(), strict=True))
            else:
                rows.append(it)
        ids, r, b, yaw = zip(*rows, strict=True)
        obs = LandmarkObservation(
            self._t, np.array(ids, dtype=int), np.column_stack([r, b]), np.array(yaw, dtype=float)
        )
        self._t = math.nan
        return obs
