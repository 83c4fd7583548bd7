"""Dead reckoning: exact differential-drive integration of encoder ticks (or v, ω odometry)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hardware.calibration import WalkerCalibration
from hardware.messages import EncoderTicks, Message, VelocityOdometry
from slam.base import Localizer, PoseEstimate, register
from slam.motion import arc_increment, wheel_increment, wheel_increment_jacobian
from slam.trajectory import Trajectory


@dataclass(frozen=True)
class DeadReckoningConfig:
    """Dead-reckoning settings.

    initial_pose: (x, y, θ) at the first message.
    wheel_noise_m: per-wheel distance noise as a random walk, σ² = wheel_noise_m·|distance
        rolled| [m²/m]; 0.0025 gives σ = 5 cm after 1 m (the thesis's 5 % encoder error).
    velocity_noise: for velocity odometry, σ_v = velocity_noise·|v| and
        σ_ω = velocity_noise·|ω| + 0.01.
    """

    initial_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    wheel_noise_m: float = 0.0025
    velocity_noise: float = 0.1


class DeadReckoning(Localizer):
    def __init__(self, config: DeadReckoningConfig, calibration: WalkerCalibration) -> None:
        self.config = config
        self.calibration = calibration
        x0, y0, th0 = (float(v) for v in config.initial_pose)
        self._pose = (x0, y0, th0)
        self._cov = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
        self._t: float | None = None
        self._last_ticks: tuple[int, int] | None = None
        self._last_velocity: VelocityOdometry | None = None
        self._times: list[float] = []
        self._poses: list[np.ndarray] = []

    # -- inputs -----------------------------------------------------------------------
    def process(self, msg: Message) -> None:
        if isinstance(msg, EncoderTicks):
            self._on_ticks(msg)
        elif isinstance(msg, VelocityOdometry):
            self._on_velocity(msg)

    def _on_ticks(self, msg: EncoderTicks) -> None:
        if self._last_ticks is None:
            self._last_ticks = (msg.left, msg.right)
            self._record(msg.t)
            return
        m = self.calibration.metres_per_count
        ds_l = (msg.left - self._last_ticks[0]) * m
        ds_r = (msg.right - self._last_ticks[1]) * m
        self._last_ticks = (msg.left, msg.right)
        ds, dth = wheel_increment(ds_l, ds_r, self.calibration.track_m)
        k = self.config.wheel_noise_m
        g = wheel_increment_jacobian(self._pose[2], ds, dth, self.calibration.track_m)
        self._advance(ds, dth, g, (k * abs(ds_l), k * abs(ds_r)))
        self._record(msg.t)

    def _on_velocity(self, msg: VelocityOdometry) -> None:
        prev = self._last_velocity
        self._last_velocity = msg
        if prev is None:
            self._record(msg.t)
            return
        dt = msg.t - prev.t
        if dt <= 0:
            return
        ds, dth = prev.v * dt, prev.omega * dt
        k = self.config.velocity_noise
        sv, sw = k * abs(prev.v) * dt, (k * abs(prev.omega) + 0.01) * dt
        h = self._pose[2] + 0.5 * dth
        g = ((math.cos(h), 0.0), (math.sin(h), 0.0), (0.0, 1.0))
        self._advance(ds, dth, g, (sv * sv, sw * sw))
        self._record(msg.t)

    def _advance(self, ds: float, dth: float, g, q: tuple[float, float]) -> None:
        """Pose += arc; P = F P Fᵀ + G diag(q) Gᵀ with F = ∂pose'/∂pose (closed form on
        floats: this runs for every encoder message)."""
        x, y, th = self._pose
        dx, dy = arc_increment(ds, dth, th)
        (p00, p01, p02), (_, p11, p12), (_, _, p22) = self._cov
        a, b = -dy, dx  # F = [[1, 0, a], [0, 1, b], [0, 0, 1]]
        n00 = p00 + 2 * a * p02 + a * a * p22
        n01 = p01 + a * p12 + b * p02 + a * b * p22
        n02 = p02 + a * p22
        n11 = p11 + 2 * b * p12 + b * b * p22
        n12 = p12 + b * p22
        gq = [[g[i][k] * q[k] for k in (0, 1)] for i in range(3)]
        add = [[gq[i][0] * g[j][0] + gq[i][1] * g[j][1] for j in range(3)] for i in range(3)]
        self._cov = (
            (n00 + add[0][0], n01 + add[0][1], n02 + add[0][2]),
            (n01 + add[1][0], n11 + add[1][1], n12 + add[1][2]),
            (n02 + add[2][0], n12 + add[2][1], p22 + add[2][2]),
        )
        self._pose = (x + dx, y + dy, math.remainder(th + dth, 2.0 * math.pi))

    def _record(self, t: float) -> None:
        if self._times and t <= self._times[-1]:
            # Same or earlier stamp: keep one pose per time (the newest).
            if t == self._times[-1]:
                self._poses[-1] = self._pose
            return
        self._t = t
        self._times.append(t)
        self._poses.append(self._pose)

    # -- outputs ----------------------------------------------------------------------
    def estimate(self) -> PoseEstimate:
        t = self._t if self._t is not None else float("nan")
        return PoseEstimate(t, np.array(self._pose), np.array(self._cov))

    def trajectory(self) -> Trajectory:
        poses = np.array(self._poses, dtype=float).reshape(-1, 3)
        return Trajectory(np.array(self._times), poses)


register(
    "dead-reckoning",
    DeadReckoningConfig,
    "exact differential-drive integration of encoder ticks or velocity odometry",
)(DeadReckoning)
