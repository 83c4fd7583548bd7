"""The braking-controller interface and its registry.

A controller maps (occupied map points, pose, velocities) to a brake command (torque
per wheel). It never reads the simulator's truth: only what the walker's software has.
"""

from __future__ import annotations

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
    pose: (x, y, θ) from the localizer; v, omega: forward speed and yaw rate from it.
    """

    t: float
    occupied_xy: np.ndarray
    pose: np.ndarray
    v: float
    omega: float


class Controller(ABC):
    @abstractmethod
    def command(self, inp: ControlInput) -> BrakeCommand: ...


def _load_builtin() -> None:
    import control.open_loop  # noqa: F401


CONTROLLERS: Registry[Controller] = Registry("controller", _load_builtin)


def create(name: str, calibration: WalkerCalibration, config: Any = None) -> Controller:
    return CONTROLLERS.create(name, calibration, config=config)
