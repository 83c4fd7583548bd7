"""The localizer interface and the registry that maps names to localizers."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any, Protocol, runtime_checkable

import numpy as np

from hardware.calibration import WalkerCalibration
from hardware.messages import Message
from hardware.registry import Registry, UnknownNameError
from mapping.grid import GridExtent
from mapping.mapper import OccupancyMapper, Projection
from slam.trajectory import Trajectory

__all__ = [
    "LOCALIZERS",
    "FrameConsumer",
    "KnownMapConfig",
    "LandmarkMapper",
    "Localizer",
    "LocalizerConfig",
    "MapScorer",
    "PoseEstimate",
    "SlipEstimator",
    "UnknownNameError",
    "available",
    "create",
]


@dataclass(frozen=True, eq=False)
class PoseEstimate:
    """Pose (x, y, θ) at time t with its 3×3 covariance."""

    t: float
    pose: np.ndarray
    covariance: np.ndarray


class Localizer(ABC):
    """Consumes messages in time order; reports the current pose and the trajectory.

    Messages a localizer does not use are ignored. `revision` increases whenever past
    poses change (smoothers), so a mapper knows to rebuild from keyframes. Every
    localizer's config has an `initial_pose` (x, y, θ): the pose that defines the map
    frame (a trial log records it in its config as "initial_pose").
    """

    revision: int = 0
    revises_past: bool = False  # smoothers: the pipeline keeps frames to rebuild the map
    config: Any  # the typed config the localizer was built with

    @abstractmethod
    def process(self, msg: Message) -> None: ...

    @abstractmethod
    def estimate(self) -> PoseEstimate: ...

    @abstractmethod
    def trajectory(self) -> Trajectory: ...

    def diagnostics(self) -> dict:
        """What the localizer wants a researcher to know (counts, fallbacks); may be empty."""
        return {}

    def finish(self) -> None:
        """The source has ended (a log's last message, a live run's stop): a smoother may
        make a last pass over what it kept (gtsam's loop.final). Default: nothing."""
        return None  # a filter has nothing left to revise


@dataclass(frozen=True)
class LocalizerConfig:
    """What every localizer's config has: initial_pose (x, y, θ), the pose at the first
    message, which defines the map frame (a trial log records it in its config as
    "initial_pose"; `create` sets it)."""

    initial_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class KnownMapConfig(LocalizerConfig):
    """The config of a localizer that uses a known landmark map: landmark_map {id: (x,
    y)}, filled from the trial log by `create(..., landmark_map=...)` when not given;
    None: landmarks are not used."""

    landmark_map: dict[int, np.ndarray] | None = None


@runtime_checkable
class LandmarkMapper(Protocol):
    """A localizer that estimates landmark positions (ekf-slam, fastslam, gtsam)."""

    def landmarks(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """{landmark id: (mean (x, y), 2×2 covariance)} in the map frame."""
        ...


@runtime_checkable
class SlipEstimator(Protocol):
    """A localizer that can estimate each rear wheel's slip coefficient (slam.slip:
    ekf-slam, gtsam, fastslam with `slip.estimate`)."""

    def slip_estimate(self) -> tuple[np.ndarray, np.ndarray] | None:
        """((k_left, k_right), their 2×2 covariance), or None when not estimating."""
        ...


@runtime_checkable
class FrameConsumer(Protocol):
    """A localizer that uses depth frames or laser scans: the pipeline projects each frame
    once (`mapping.mapper.OccupancyMapper.project`) and hands the same projection to it
    and to the mappers, instead of `process(msg)`."""

    def process_frame(self, msg: Message, projection: Projection) -> None: ...


@runtime_checkable
class MapScorer(Protocol):
    """A localizer that scores frames against the shared occupancy map (particle-filter
    with scans; grid-rbpf takes its particles' maps' settings from it): the pipeline
    hands its mapper over with `attach_map`."""

    def attach_map(self, source: OccupancyMapper | GridExtent | None) -> None: ...


# Members: the entry points of group "walker_slam.localizers" (pyproject.toml).
LOCALIZERS: Registry[Localizer] = Registry("localizer", "walker_slam.localizers")


def available() -> list[str]:
    return LOCALIZERS.names()


def create(
    name: str,
    calibration: WalkerCalibration,
    config: Any = None,
    initial_pose: Sequence[float] | None = None,
    landmark_map: dict | None = None,
) -> Localizer:
    """Build the localizer registered as `name` with `config` (its defaults when None),
    starting at `initial_pose` when given (overrides the config's). `landmark_map`
    ({id: (x, y)}, e.g. from the trial log) fills the config's `landmark_map` field when
    the localizer has one and it is not set; other localizers ignore it."""
    cfg = config if config is not None else LOCALIZERS.spec(name).config_type()
    if not isinstance(cfg, LocalizerConfig):
        raise TypeError(f"{name}'s config {type(cfg).__name__} is not a LocalizerConfig")
    if initial_pose is not None:
        cfg = replace(cfg, initial_pose=tuple(float(v) for v in initial_pose))
    if landmark_map is not None and isinstance(cfg, KnownMapConfig) and cfg.landmark_map is None:
        cfg = replace(cfg, landmark_map=landmark_map)
    return LOCALIZERS.create(name, calibration, config=cfg)
