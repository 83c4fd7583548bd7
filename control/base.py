"""The braking-controller interface and its registry.

A controller maps (occupied map points, pose, velocities) to a brake command (torque
per wheel). It never reads the simulator's truth: only what the walker's software has.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

import numpy as np

from hardware.calibration import WalkerCalibration
from hardware.messages import BrakeCommand
from hardware.registry import Registry


@dataclass(frozen=True, eq=False)
class ControlInput:
    """Everything a controller may use at one tick.

    occupied_xy: occupied map cell centres in the world frame (N×2);
    pose: (x, y, θ) from the localizer; v, omega: forward speed and yaw rate from it;
    brake_nm: (left, right) brake torques currently applied, i.e. the last command sent
    to the brakes [N·m] (NaN: unknown; the closed loop then uses its own last command);
    pose_t, map_t, sensor_t: time of the localizer's latest update, of the latest depth
    frame / scan integrated into the map, and of the latest odometry (encoder) message.
    The safety layer ramps the brakes off when any of them is too old. NaN means "not
    reported" (not checked); -inf means "reported, but nothing received yet" (stale).
    """

    t: float
    occupied_xy: np.ndarray
    pose: np.ndarray
    v: float
    omega: float
    brake_nm: tuple[float, float] = (math.nan, math.nan)
    pose_t: float = math.nan
    map_t: float = math.nan
    sensor_t: float = math.nan


class Controller(ABC):
    @abstractmethod
    def command(self, inp: ControlInput) -> BrakeCommand: ...


# Members: the entry points of group "walker_slam.controllers" (pyproject.toml).
CONTROLLERS: Registry[Controller] = Registry("controller", "walker_slam.controllers")


def create(name: str, calibration: WalkerCalibration, config: Any = None) -> Controller:
    return CONTROLLERS.create(name, calibration, config=config)
