"""Dead reckoning: exact differential-drive integration of encoder ticks (or v, ω odometry)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from hardware.calibration import WalkerCalibration
from hardware.messages import Message
from slam.base import Localizer, PoseEstimate, register
from slam.motion import MotionNoise, OdometryModel, arc_increment
from slam.trajectory import Trajectory, TrajectoryRecorder


@dataclass(frozen=True)
class DeadReckoningConfig:
    """Dead-reckoning settings.

    initial_pose: (x, y, θ) at the first message (defines the map frame).
    noise: odometry noise for the covariance (see slam.motion.MotionNoise).
    """

    initial_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    noise: MotionNoise = field(default_factory=MotionNoise)


class DeadReckoning(Localizer):
    def __init__(self, config: DeadReckoningConfig, calibration: WalkerCalibration) -> None:
        self.config = config
        self.calibration = calibration
        self.odometry = OdometryModel(calibration, config.noise)
        x0, y0, th0 = (float(v) for v in config.initial_pose)
        self._pose = (x0, y0, th0)
        self._cov = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
        self._started = False
        self.track = TrajectoryRecorder()

    def process(self, msg: Message) -> None:
        inc = self.odometry.increment(msg)
        if inc is not None:
            self._advance(inc.ds, inc.dtheta, inc.cov)
            self._record(msg.t)
        elif not self._started and self.odometry.has_odometry:
            self._started = True
            self._record(msg.t)

    def _advance(self, ds: float, dth: float, q: np.ndarray) -> None:
        """Pose += exact arc; P = F P Fᵀ + G Q Gᵀ, in closed form on floats (this runs for
        every odometry message): F = [[1, 0, a], [0, 1, b], [0, 0, 1]], G = ∂pose'/∂(ds, dθ)."""
        x, y, th = self._pose
        dx, dy = arc_increment(ds, dth, th)
        (p00, p01, p02), (_, p11, p12), (_, _, p22) = self._cov
        a, b = -dy, dx
        n00 = p00 + 2 * a * p02 + a * a * p22
        n01 = p01 + a * p12 + b * p02 + a * b * p22
        n02 = p02 + a * p22
        n11 = p11 + 2 * b * p12 + b * b * p22
        n12 = p12 + b * p22
        # G for the exact arc, written out (see slam.motion.increment_jacobians)
        half = 0.5 * dth
        s = math.sin(half) / half if abs(half) > 1e-4 else 1.0 - half * half / 6.0
        sp = (half * math.cos(half) - math.sin(half)) / half**2 if abs(half) > 1e-4 else -half / 3.0
        chord, dchord = ds * s, 0.5 * ds * sp
        h = th + half
        c, sn = math.cos(h), math.sin(h)
        g = (
            (s * c, dchord * c - 0.5 * chord * sn),
            (s * sn, dchord * sn + 0.5 * chord * c),
            (0.0, 1.0),
        )
        q00, q01, q11 = float(q[0, 0]), float(q[0, 1]), float(q[1, 1])
        gq = [(r[0] * q00 + r[1] * q01, r[0] * q01 + r[1] * q11) for r in g]
        add = [[gq[i][0] * g[j][0] + gq[i][1] * g[j][1] for j in range(3)] for i in range(3)]
        self._cov = (
            (n00 + add[0][0], n01 + add[0][1], n02 + add[0][2]),
            (n01 + add[1][0], n11 + add[1][1], n12 + add[1][2]),
            (n02 + add[2][0], n12 + add[2][1], p22 + add[2][2]),
        )
        self._pose = (x + dx, y + dy, math.remainder(th + dth, 2.0 * math.pi))

    def _record(self, t: float) -> None:
        self.track.record(t, self._pose)

    def estimate(self) -> PoseEstimate:
        return PoseEstimate(self.track.last_t, np.array(self._pose), np.array(self._cov))

    def trajectory(self) -> Trajectory:
        return self.track.trajectory()


register(
    "dead-reckoning",
    DeadReckoningConfig,
    "exact differential-drive integration of encoder ticks or velocity odometry",
)(DeadReckoning)
