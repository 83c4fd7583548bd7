"""What one depth frame or laser scan contributes to a floor-plane map.

A `PlanarObservation` lives in the walker frame (x forward, y left, origin on the floor
below the rear-axle centre): the sensor's position and heading on the floor, the obstacle
points, and the end points of the rays that show free space. It is compact (float32 2-D
points, no images), which is what the mapper keeps of a keyframe so that the map can be
rebuilt when a smoother revises past poses.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from mapping.kernels import place_points
from mapping.lattice import as_points, quantise_points


def as_pose(pose: np.ndarray, name: str = "pose") -> np.ndarray:
    """`pose` as a float64 (x, y, θ); raises ValueError for any other shape."""
    p = np.asarray(pose, dtype=np.float64)
    if p.shape != (3,):
        raise ValueError(f"{name} must have shape (3,) as (x, y, theta), got {p.shape}")
    return p


def _coerce_arrays(obs: PlanarObservation | WorldObservation, dtype: type) -> None:
    """Check and convert an observation's arrays in place (frozen dataclass)."""
    xy = np.asarray(obs.sensor_xy, dtype=np.float64)
    if xy.shape != (2,):
        raise ValueError(f"sensor_xy must have shape (2,), got {xy.shape}")
    object.__setattr__(obs, "sensor_xy", xy)
    for name in ("obstacles", "ray_ends"):
        pts = as_points(getattr(obs, name), name).astype(dtype, copy=False)
        object.__setattr__(obs, name, pts)


@dataclass(frozen=True)
class ViewWedge:
    """The floor region a sensor sees: ranges r_min–r_max [m] within ±half_fov [rad] of its axis.

    Used by the view-count map model (thesis §4.1: 0.8–4.15 m, about ±0.5 rad).
    """

    r_min: float
    r_max: float
    half_fov: float

    def __post_init__(self) -> None:
        if not (0.0 <= self.r_min < self.r_max) or not (0.0 < self.half_fov <= np.pi):
            raise ValueError(
                f"need 0 <= r_min < r_max and 0 < half_fov <= pi, got {self.r_min}, "
                f"{self.r_max}, {self.half_fov}"
            )


@dataclass(frozen=True, eq=False)
class PlanarObservation:
    """One frame's evidence on the floor plane, in the walker frame.

    sensor_xy: (2,) where the rays start (the sensor projected onto the floor).
    sensor_yaw: heading of the sensor axis relative to the walker's x axis [rad].
    obstacles: (N, 2) float32 obstacle points.
    ray_ends: (M, 2) float32 end points of the rays that show free space from sensor_xy;
        a ray that ended on an obstacle has its end among `obstacles` as well.
    view: the sensor's view wedge, or None to take the traced rays as the region in view.
    points: the obstacle points, then the ray ends, in one (N + M, 2) array, of which
        `obstacles` and `ray_ends` are views (the two are placed in one pass).
    """

    sensor_xy: np.ndarray
    sensor_yaw: float
    obstacles: np.ndarray
    ray_ends: np.ndarray
    view: ViewWedge | None = None
    points: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        _coerce_arrays(self, np.float32)
        object.__setattr__(self, "sensor_yaw", float(self.sensor_yaw))
        points = np.concatenate([self.obstacles, self.ray_ends])
        n = len(self.obstacles)
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "obstacles", points[:n])
        object.__setattr__(self, "ray_ends", points[n:])

    @property
    def nbytes(self) -> int:
        """Memory held by the point arrays [bytes]."""
        return int(self.obstacles.nbytes + self.ray_ends.nbytes + self.sensor_xy.nbytes)

    def compacted(self, quantum: float) -> PlanarObservation:
        """The same observation with its points snapped to a `quantum` lattice, duplicates dropped.

        Points move by at most quantum/√2; quantum <= 0 returns self unchanged.
        """
        if quantum <= 0:
            return self
        return replace(
            self,
            obstacles=quantise_points(self.obstacles, quantum),
            ray_ends=quantise_points(self.ray_ends, quantum),
        )

    def in_world(self, world_T_walker: np.ndarray) -> WorldObservation:
        """This observation placed at the planar pose (x, y, θ) of the walker."""
        pose = as_pose(world_T_walker, "world_T_walker")
        c, s = np.cos(pose[2]), np.sin(pose[2])
        x, y = self.sensor_xy
        n = len(self.obstacles)  # both point sets in one pass: half the numpy calls
        points = _place(self.points, pose, c, s)
        return WorldObservation(
            # hardware.geometry.transform_points, operation for operation (same float64 values)
            sensor_xy=np.array([pose[0] + c * x - s * y, pose[1] + s * x + c * y]),
            heading=float(pose[2] + self.sensor_yaw),
            obstacles=points[:n],
            ray_ends=points[n:],
            view=self.view,
        )


def _place(points: np.ndarray, pose: np.ndarray, c: np.float64, s: np.float64) -> np.ndarray:
    """`hardware.geometry.transform_points(pose, points)` with cos/sin given, in the same float64
    operations (so the same values), by one compiled loop (`mapping.kernels.place_points`)."""
    out = np.empty((len(points), 2))
    place_points(points, float(pose[0]), float(pose[1]), float(c), float(s), out)
    return out


@dataclass(frozen=True, eq=False)
class WorldObservation:
    """A `PlanarObservation` in world coordinates (float64), ready for a grid update."""

    sensor_xy: np.ndarray
    heading: float
    obstacles: np.ndarray
    ray_ends: np.ndarray
    view: ViewWedge | None = None

    def __post_init__(self) -> None:
        _coerce_arrays(self, np.float64)
        object.__setattr__(self, "heading", float(self.heading))
