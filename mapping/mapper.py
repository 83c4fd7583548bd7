"""The shared occupancy mapper: depth frames and laser scans at localizer poses → one grid.

Every frame goes through the same path: sensor data → `PlanarObservation` in the walker
frame → compacted (points snapped to a quarter-cell lattice in the walker frame,
duplicates dropped, float32) → placed at the walker's pose → integrated into the grid.
Depth frames take the first two steps in one (`depth_points.depth_to_compact_observation`,
same result, a fraction of the time).

Keyframe memory. A frame integrated with a `key` (any hashable, e.g. a keyframe index)
is kept in its compact walker-frame form with the pose it was integrated at, so that
`rebuild(poses)` can re-create the map from the kept frames at revised poses — what a
smoother that revises the past needs. Frames without a key are integrated and forgotten
(a rebuilt map does not contain them). A kept 160×120 depth frame takes a few tens of kB
(see `keyframe_nbytes`); with `max_keyframes` set, the oldest kept frame is forgotten
when the limit is exceeded. Re-using a key replaces the frame kept under it (and makes it
the newest).
"""

from __future__ import annotations

import threading
from collections.abc import Hashable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hardware.calibration import WalkerCalibration
from hardware.messages import CameraIntrinsics, DepthFrame, LaserScan
from mapping.depth_points import DepthConfig, project_depth_frame
from mapping.grid import GridConfig, GridExtent, make_grid
from mapping.hygiene import HygieneConfig
from mapping.observation import PlanarObservation, ViewWedge, as_pose
from mapping.scan_points import ScanConfig, scan_to_observation


@dataclass(frozen=True)
class MapperConfig:
    """grid: cell size, map model, growth/rolling.
    depth: obstacle band, stride, no-return handling of depth frames.
    scan: usable range and no-return handling of laser scans.
    view_range_m: depth camera's view wedge range for the view-count model (thesis:
        0.8–4.15 m).
    view_half_fov_rad: half-width of that wedge; None: half the depth camera's horizontal
        field of view (28.5° for the Kinect; the thesis used ±0.5 rad).
    point_quantum_m: lattice the walker-frame points are snapped to before integrating and
        keeping; None: resolution/4 (1.25 cm at 5 cm cells); 0: no snapping.
    max_keyframes: most keyframes kept for `rebuild`; None: all.
    hygiene: periodic reset, decay and gating of what is mapped (`mapping.hygiene`,
        applied by the pipeline); off by default.
    """

    grid: GridConfig = field(default_factory=GridConfig)
    depth: DepthConfig = field(default_factory=DepthConfig)
    scan: ScanConfig = field(default_factory=ScanConfig)
    view_range_m: tuple[float, float] = (0.8, 4.15)
    view_half_fov_rad: float | None = None
    point_quantum_m: float | None = None
    max_keyframes: int | None = None
    hygiene: HygieneConfig = field(default_factory=HygieneConfig)


@dataclass(frozen=True, eq=False)
class _Keyframe:
    obs: PlanarObservation
    pose: np.ndarray


_warmed_up = False


def warm_up() -> None:
    """Load (or compile) the mapper's compiled loops (`mapping.kernels`) now, once per
    process, by mapping a small synthetic depth frame (writable and read-only, as frames
    come from sensors and from logs) and laser scan with both map models: the first use
    of a compiled loop costs ~0.5–1 s (a few seconds when nothing is cached yet), which
    should not land in the middle of a replay or a control loop. Every mapper calls this
    when it is created."""
    global _warmed_up
    if _warmed_up:
        return
    _warmed_up = True
    cal = WalkerCalibration()
    k = cal.depth_intrinsics
    depth = np.full((k.height, k.width), 1500, dtype=np.uint16)
    depth[: k.height // 2] = 0
    read_only = depth.copy()
    read_only.setflags(write=False)
    scan = LaserScan(0.0, -0.5, 0.1, np.full(11, 2.0), 10.0)
    for model in ("log-odds", "view-count"):
        mapper = OccupancyMapper(cal, MapperConfig(grid=GridConfig(model=model)))
        for d in (depth, read_only):
            mapper.integrate_depth(DepthFrame(0.0, d, k), np.zeros(3), key=0)
        mapper.integrate_scan(scan, np.zeros(3))
        mapper.rebuild()


@dataclass(frozen=True, eq=False)
class Projection:
    """One frame projected onto the floor plane (walker frame): `raw` its points as
    projected (a laser scan's own end points; a depth frame's, already on the mapper's
    lattice), `compact` what a map integrates (snapped to the lattice, duplicates
    dropped)."""

    raw: PlanarObservation
    compact: PlanarObservation


@dataclass(eq=False)
class RebuildJob:
    """A map rebuild running in a thread (`OccupancyMapper.start_rebuild`)."""

    snapshot: list[tuple[Hashable, PlanarObservation, np.ndarray]]
    grid: Any
    thread: threading.Thread | None = None
    error: BaseException | None = None

    @property
    def done(self) -> bool:
        return self.thread is not None and not self.thread.is_alive()

    def run(self) -> None:
        try:
            for _, obs, pose in self.snapshot:
                self.grid.integrate_at(obs, pose, centre_xy=pose[:2])
        except BaseException as e:  # re-raised by finish_rebuild in the caller's thread
            self.error = e


class OccupancyMapper:
    """Integrates depth frames and laser scans into one floor-plane grid (see module doc)."""

    def __init__(
        self, calibration: WalkerCalibration | None = None, config: MapperConfig | None = None
    ) -> None:
        warm_up()
        self.calibration = calibration or WalkerCalibration()
        self.config = config or MapperConfig()
        self._grid = make_grid(self.config.grid)
        self._keyframes: dict[Hashable, _Keyframe] = {}
        self._views: dict[CameraIntrinsics, ViewWedge] = {}  # per depth stream, built once
        q = self.config.point_quantum_m
        self._quantum = self.config.grid.resolution_m / 4.0 if q is None else q
        # occupied_xy by threshold, until the map changes: a closed loop asks for it at
        # every control step, several times per frame
        self._occupied: dict[float | None, np.ndarray] = {}

    @property
    def grid(self) -> GridExtent:
        """The current map (an OccupancyGrid or a ViewCountGrid, after config.grid.model),
        to read: it changes through the mapper's methods, which keep occupied_xy current."""
        return self._grid

    def occupied_xy(self, threshold: float | None = None) -> np.ndarray:
        """World centres (N×2, read-only) of the occupied cells (the grid's default
        threshold); computed once per change of the map."""
        xy = self._occupied.get(threshold)
        if xy is None:
            xy = self._occupied[threshold] = self._grid.occupied_xy(threshold)
            xy.setflags(write=False)
        return xy

    def decay(self, factor: float) -> None:
        """Fade the map's evidence by `factor` (mapping.hygiene)."""
        self._grid.decay(factor)
        self._occupied.clear()

    def project(
        self,
        frame: DepthFrame | LaserScan,
        sensor_offset: tuple[float, float, float] | np.ndarray = (0.0, 0.0, 0.0),
    ) -> Projection:
        """A depth frame's or laser scan's evidence as this mapper integrates it (its
        depth / scan config and point lattice), once per frame: the pipeline hands the
        same projection to the localizer and the mappers. sensor_offset: (x, y, yaw) of a
        laser on the walker."""
        if isinstance(frame, DepthFrame):
            view = self._views.get(frame.intrinsics)
            if view is None:
                view = self._views[frame.intrinsics] = self._view_wedge(frame.intrinsics)
            obs = project_depth_frame(
                frame, self.calibration, self.config.depth, view, quantum=self._quantum
            )
            return Projection(obs, obs)
        raw = scan_to_observation(frame, sensor_offset, self.config.scan)
        return Projection(raw, raw.compacted(self._quantum))

    def integrate_projection(
        self, projection: Projection, pose: np.ndarray, key: Hashable | None = None
    ) -> None:
        """Add a frame projected by `project` (this mapper's or one of the same config)
        at the walker pose (x, y, θ)."""
        self._integrate_compact(projection.compact, pose, key)

    def integrate_depth(
        self, frame: DepthFrame, world_T_walker: np.ndarray, key: Hashable | None = None
    ) -> None:
        """Add a depth frame taken at the walker pose (x, y, θ)."""
        self.integrate_projection(self.project(frame), world_T_walker, key)

    def _view_wedge(self, intrinsics: CameraIntrinsics) -> ViewWedge:
        """The depth camera's view wedge (config.view_*; half FOV from the intrinsics)."""
        half_fov = self.config.view_half_fov_rad
        if half_fov is None:
            half_fov = float(np.arctan(intrinsics.width / (2.0 * intrinsics.fx)))
        return ViewWedge(*self.config.view_range_m, half_fov)

    def integrate_scan(
        self,
        scan: LaserScan,
        pose: np.ndarray,
        sensor_offset: tuple[float, float, float] | np.ndarray = (0.0, 0.0, 0.0),
        key: Hashable | None = None,
    ) -> None:
        """Add a planar laser scan taken at the walker pose (x, y, θ).

        sensor_offset = (x, y, yaw) of the laser on the walker.
        """
        self.integrate_projection(self.project(scan, sensor_offset), pose, key)

    def integrate_observation(
        self, obs: PlanarObservation, pose: np.ndarray, key: Hashable | None = None
    ) -> None:
        """Add any walker-frame observation at the walker pose (x, y, θ)."""
        self._integrate_compact(obs.compacted(self._quantum), pose, key)

    def _integrate_compact(
        self, obs: PlanarObservation, pose: np.ndarray, key: Hashable | None
    ) -> None:
        """`integrate_observation` of an observation already compacted to self._quantum."""
        pose = as_pose(pose, "pose")
        if key is not None:
            self._keyframes.pop(key, None)
            self._keyframes[key] = _Keyframe(obs, pose)
            limit = self.config.max_keyframes
            if limit is not None and len(self._keyframes) > limit:
                del self._keyframes[next(iter(self._keyframes))]
        self._grid.integrate_at(obs, pose, centre_xy=pose[:2])
        self._occupied.clear()

    def rebuild(self, poses: Mapping[Hashable, np.ndarray] | None = None) -> None:
        """Re-create the map from the kept keyframes, in the order they were kept.

        `poses` gives revised walker poses by key; keyframes not in it keep their pose.
        Unkeyed frames are not in the rebuilt map. Raises ValueError for unknown keys.
        """
        poses = poses or {}
        unknown = [k for k in poses if k not in self._keyframes]
        if unknown:
            raise ValueError(f"no keyframe kept under keys {unknown[:5]}")
        revised = {key: as_pose(pose, f"poses[{key!r}]") for key, pose in poses.items()}
        for key, pose in revised.items():
            self._keyframes[key] = _Keyframe(self._keyframes[key].obs, pose)
        self._grid.reset()
        self._occupied.clear()
        for kf in self._keyframes.values():
            self._grid.integrate_at(kf.obs, kf.pose, centre_xy=kf.pose[:2])

    def start_rebuild(self, poses: Mapping[Hashable, np.ndarray]) -> RebuildJob:
        """`rebuild(poses)` in a thread of its own, for a loop that must not wait for it:
        the new grid is built from a snapshot of the keyframes (their projected points
        never change) while this mapper goes on integrating; `finish_rebuild(job)` then
        adds the frames integrated meanwhile and switches to it. The result is the grid
        `rebuild` would have given at the snapshot, plus those frames."""
        unknown = [k for k in poses if k not in self._keyframes]
        if unknown:
            raise ValueError(f"no keyframe kept under keys {unknown[:5]}")
        snapshot = [
            (key, kf.obs, as_pose(poses[key], f"poses[{key!r}]") if key in poses else kf.pose)
            for key, kf in self._keyframes.items()
        ]
        job = RebuildJob(snapshot, make_grid(self.config.grid))
        job.thread = threading.Thread(target=job.run, name="map-rebuild", daemon=True)
        job.thread.start()
        return job

    def finish_rebuild(self, job: RebuildJob) -> None:
        """Wait for `job`, add what was integrated since it started, switch to its grid."""
        assert job.thread is not None
        job.thread.join()
        if job.error is not None:
            raise job.error
        done = set()
        for key, obs, pose in job.snapshot:
            done.add(key)
            if key in self._keyframes:
                self._keyframes[key] = _Keyframe(obs, pose)
        for key, kf in self._keyframes.items():
            if key not in done:
                job.grid.integrate_at(kf.obs, kf.pose, centre_xy=kf.pose[:2])
        self._grid = job.grid
        self._occupied.clear()

    def keys(self) -> Iterator[Hashable]:
        """Keys of the kept keyframes, oldest first."""
        return iter(list(self._keyframes))

    def keyframe_pose(self, key: Hashable) -> np.ndarray:
        """The pose the keyframe `key` was last integrated at."""
        return self._keyframes[key].pose.copy()

    def forget(self, key: Hashable) -> None:
        """Stop keeping keyframe `key` (the current map is unchanged)."""
        del self._keyframes[key]

    @property
    def keyframe_nbytes(self) -> int:
        """Memory held by the kept keyframes' points [bytes]."""
        return sum(kf.obs.nbytes for kf in self._keyframes.values())

    def reset(self) -> None:
        """Empty map, no keyframes."""
        self._grid.reset()
        self._occupied.clear()
        self._keyframes.clear()
