"""The localizer interface and the registry that maps names to localizers."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from hardware.calibration import WalkerCalibration
from hardware.messages import Message
from slam.trajectory import Trajectory


@dataclass(frozen=True, eq=False)
class PoseEstimate:
    """Pose (x, y, θ) at time t with its 3×3 covariance."""

    t: float
    pose: np.ndarray
    covariance: np.ndarray


class Localizer(ABC):
    """Consumes messages in time order; reports the current pose and the trajectory.

    Messages a localizer does not use are ignored. `revision` increases whenever past
    poses change (smoothers), so a mapper knows to rebuild from keyframes.
    """

    revision: int = 0

    @abstractmethod
    def process(self, msg: Message) -> None: ...

    @abstractmethod
    def estimate(self) -> PoseEstimate: ...

    @abstractmethod
    def trajectory(self) -> Trajectory: ...


@dataclass(frozen=True)
class LocalizerSpec:
    name: str
    config_type: type
    factory: Callable[[Any, WalkerCalibration], Localizer]
    summary: str


class UnknownNameError(ValueError):
    """A name that is not registered; the message lists the valid names."""

    def __init__(self, kind: str, name: str, valid: list[str]) -> None:
        super().__init__(f"unknown {kind} '{name}'; valid: {', '.join(valid)}")
        self.valid = valid


LOCALIZERS: dict[str, LocalizerSpec] = {}


def register(name: str, config_type: type, summary: str):
    """Class/function decorator registering a localizer factory under `name`."""

    def deco(factory):
        LOCALIZERS[name] = LocalizerSpec(name, config_type, factory, summary)
        return factory

    return deco


def _load_builtin() -> None:
    # Importing the modules runs their @register decorators.
    import slam.dead_reckoning  # noqa: F401


def available() -> list[str]:
    _load_builtin()
    return sorted(LOCALIZERS)


def create(name: str, calibration: WalkerCalibration, config: Any = None) -> Localizer:
    """Build the localizer registered as `name` with `config` (defaults when None)."""
    _load_builtin()
    spec = LOCALIZERS.get(name)
    if spec is None:
        raise UnknownNameError("localizer", name, sorted(LOCALIZERS))
    cfg = spec.config_type() if config is None else config
    if not isinstance(cfg, spec.config_type):
        raise TypeError(f"{name} takes a {spec.config_type.__name__}, got {type(cfg).__name__}")
    return spec.factory(cfg, calibration)
