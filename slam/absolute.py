"""Absolute observations — a compass heading and a position fix in the map frame — and
the one config group (`AbsoluteConfig`, field `absolute` of ekf-slam, particle-filter,
gtsam and alpha-blend) that switches their fusion on and sets their noise.

Measurement models of the pose p = (x, y, θ) (map frame), with residual r = z ⊖ h(p):

    heading   h(p) = θ        r = wrap(z − θ)    H = ∂h/∂p = [0 0 1]
    position  h(p) = (x, y)   r = z − (x, y)     H = [[1 0 0], [0 1 0]]

The position is that of the walker's reference point (a GPS antenna elsewhere on the
walker would need a lever arm, not modelled). A smoother that attaches an observation
to a keyframe pose k = (x_k, y_k, θ_k) while the walker has since moved d = (dx, dy, dθ)
in k's frame measures

    heading   θ_k + dθ
    position  (x_k, y_k) + R(θ_k)·(dx, dy),

whose Jacobian with respect to a body-frame perturbation ξ of k (k ∘ Exp(ξ), gtsam's
Pose2 retract) is [R(θ_k) | R(θ_k)·(−dy, dx)ᵀ] (`offset_position_jacobian`).

Noise: a message's own σ when it carries a finite positive one, else the config's
(compass_sigma_rad, position_sigma_m). Robustness, per localizer: the EKF gates an
update whose squared Mahalanobis distance exceeds the chi-squared quantile at
gate_prob (1 degree of freedom for heading, 2 for position); the particle filter's
likelihood is the mixture (1 − ε)·N + ε·u with a uniform u over all headings or over a
disc of radius outlier_radius_m (as its landmark likelihood, slam.measurement
`robust_log_likelihood`); gtsam wraps the factor's noise in a Huber kernel at robust_k
standard deviations (0: plain Gaussian).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hardware.geometry import rotation, wrap_angle
from hardware.messages import CompassHeading, Message, PositionFix
from slam.measurement import chi2_quantile, robust_log_likelihood


@dataclass(frozen=True)
class AbsoluteConfig:
    """Which absolute observations a localizer fuses and how (module docstring).

    use_compass, use_position: fuse CompassHeading / PositionFix messages (off: they are
        ignored, the localizer behaves as without them).
    compass_sigma_rad, position_sigma_m: σ for a message that carries none (NaN).
    gate_prob: ekf-slam rejects an observation beyond this chi-squared quantile of its
        innovation (1.0: no gate).
    outlier_prob, outlier_radius_m: particle-filter's robust likelihood (0: Gaussian).
    robust_k: gtsam's Huber threshold in σ (0: plain Gaussian factors).
    alpha-blend reads only the use_* switches and the σ (for its covariance).
    """

    use_compass: bool = False
    use_position: bool = False
    compass_sigma_rad: float = 0.1
    position_sigma_m: float = 1.0
    gate_prob: float = 0.999
    outlier_prob: float = 0.01
    outlier_radius_m: float = 10.0
    robust_k: float = 0.0

    def __post_init__(self) -> None:
        if not (self.compass_sigma_rad > 0 and self.position_sigma_m > 0):
            raise ValueError("compass_sigma_rad and position_sigma_m must be > 0")
        if not 0.0 < self.gate_prob <= 1.0:
            raise ValueError(f"gate_prob must be in (0, 1], got {self.gate_prob}")
        if not 0.0 <= self.outlier_prob < 1.0 or self.outlier_radius_m <= 0:
            raise ValueError("outlier_prob must be in [0, 1) and outlier_radius_m > 0")
        if self.robust_k < 0:
            raise ValueError(f"robust_k must be >= 0, got {self.robust_k}")

    @property
    def enabled(self) -> bool:
        return self.use_compass or self.use_position

    def gate(self, dof: int) -> float:
        """The squared-Mahalanobis threshold for an innovation of `dof` dimensions."""
        return math.inf if self.gate_prob >= 1.0 else chi2_quantile(self.gate_prob, dof)


@dataclass(frozen=True, eq=False)
class AbsoluteObservation:
    """One absolute observation: z (1,) heading or (2,) position, isotropic σ."""

    t: float
    z: np.ndarray
    sigma: float

    @property
    def is_heading(self) -> bool:
        return len(self.z) == 1

    @property
    def kind(self) -> str:
        return "compass" if self.is_heading else "position"

    @property
    def jacobian(self) -> np.ndarray:
        """H = ∂h/∂(x, y, θ), (1, 3) or (2, 3)."""
        return np.eye(3)[2:] if self.is_heading else np.eye(3)[:2]

    @property
    def covariance(self) -> np.ndarray:
        return self.sigma**2 * np.eye(len(self.z))

    def residual(self, poses: np.ndarray) -> np.ndarray:
        """z ⊖ h(pose) for poses (..., 3) → (..., dim); heading differences wrapped."""
        poses = np.asarray(poses, dtype=float)
        if self.is_heading:
            return wrap_angle(self.z[0] - poses[..., 2:3])
        return self.z - poses[..., :2]

    def log_likelihood(self, poses: np.ndarray, cfg: AbsoluteConfig) -> np.ndarray:
        """Robust log-likelihood of the observation at each of poses (N, 3) → (N,), up to
        a constant shared by all poses (module docstring)."""
        r = self.residual(poses)
        dim = r.shape[-1]
        log_gauss = -0.5 * np.sum(r * r, axis=-1) / self.sigma**2
        if cfg.outlier_prob <= 0.0:
            return log_gauss
        log_norm = -0.5 * dim * math.log(2.0 * math.pi) - dim * math.log(self.sigma)
        area = 2.0 * math.pi if self.is_heading else math.pi * cfg.outlier_radius_m**2
        log_outlier = math.log(cfg.outlier_prob / area)
        return robust_log_likelihood(log_gauss, log_norm, cfg.outlier_prob, log_outlier)


def absolute_observation(msg: Message, cfg: AbsoluteConfig) -> AbsoluteObservation | None:
    """The observation of `msg` when it is one `cfg` fuses, else None."""
    if isinstance(msg, CompassHeading) and cfg.use_compass:
        z = np.array([wrap_angle(msg.heading_rad)], dtype=float)
        sigma, fallback = msg.sigma_rad, cfg.compass_sigma_rad
    elif isinstance(msg, PositionFix) and cfg.use_position:
        z, sigma, fallback = np.array([msg.x, msg.y]), msg.sigma_m, cfg.position_sigma_m
    else:
        return None
    if not (math.isfinite(sigma) and sigma > 0.0):
        sigma = fallback
    return AbsoluteObservation(msg.t, z, float(sigma))


FUSED_COUNTERS = (
    "compass_updates",
    "position_updates",
    "compass_factors",
    "position_factors",
)


def fused_count(counts: dict) -> int:
    """How many absolute observations a localizer's diagnostics counts say it used (its
    "compass_…" and "position_…" counters; 0 when fusion is off)."""
    return sum(v for k, v in counts.items() if k in FUSED_COUNTERS)


def offset_position(pose: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Map-frame position of the point `offset` (dx, dy) in the frame of pose (x, y, θ)."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.array(
        [pose[0] + c * offset[0] - s * offset[1], pose[1] + s * offset[0] + c * offset[1]]
    )


def offset_position_jacobian(pose: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """∂offset_position/∂ξ (2×3) for the body-frame perturbation pose ∘ Exp(ξ), ξ = (vx,
    vy, ω) as gtsam's Pose2 tangent: [R(θ) | R(θ)·(−dy, dx)ᵀ]."""
    rot = rotation(pose[2])
    return np.column_stack([rot, rot @ np.array([-offset[1], offset[0]])])
