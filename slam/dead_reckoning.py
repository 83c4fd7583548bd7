"""Dead reckoning: exact differential-drive integration of encoder ticks (or v, ω odometry)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hardware.calibration import WalkerCalibration
from hardware.messages import Message
from hardware.registry import Spec
from slam.base import Localizer, LocalizerConfig, PoseEstimate
from slam.gyro import GyroFusion
from slam.motion import MotionNoise, OdometryModel, propagate
from slam.trajectory import Trajectory, TrajectoryRecorder


@dataclass(frozen=True)
class DeadReckoningConfig(LocalizerConfig):
    """Dead-reckoning settings.

    initial_pose: (x, y, θ) at the first message (defines the map frame).
    noise: odometry noise for the covariance (see slam.motion.MotionNoise); with the gyro
    (noise.gyro.enabled) its bias updates also correct the heading integrated so far
    (noise.gyro.correct_heading: nothing else corrects it here).
    """

    noise: MotionNoise = field(
        default_factory=lambda: MotionNoise(gyro=GyroFusion(correct_heading=True))
    )


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
            self._pose, self._cov, _ = propagate(self._pose, self._cov, inc.ds, inc.dtheta, inc.cov)
            self._record(msg.t)
        elif not self._started and self.odometry.has_odometry:
            self._started = True
            self._record(msg.t)

    def _record(self, t: float) -> None:
        self.track.record(t, self._pose)

    def diagnostics(self) -> dict:
        return self.odometry.diagnostics()

    def estimate(self) -> PoseEstimate:
        return PoseEstimate(self.track.last_t, np.array(self._pose), np.array(self._cov))

    def trajectory(self) -> Trajectory:
        return self.track.trajectory()


SPEC = Spec(
    "dead-reckoning",
    DeadReckoningConfig,
    DeadReckoning,
    "exact differential-drive integration of encoder ticks or velocity odometry",
)
