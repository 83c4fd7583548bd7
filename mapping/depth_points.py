"""Depth image → obstacle points and free-space rays on the floor plane (thesis §4.1).

Each pixel (u, v) with z-depth z (the Kinect reports depth along the optical axis, not
ray length) is the optical-frame point z·((u−cx)/fx, (v−cy)/fy, 1), mapped into the
walker frame through the camera mount. Points are then sorted into:

- obstacles: z within the valid range and height within the obstacle band
  [floor_clearance_m, max_height_m] above the floor (walker z = 0 is the floor);
- ray ends (free space from the camera up to the end, projected onto the floor):
  every in-range ray whose hit is no higher than the band's top (floor hits and
  obstacle hits; a ray that hit the ceiling passed over unseen ground, so it clears
  nothing); readings beyond the range's far end are real returns, so their ray is
  cut at the far end and clears up to there; pixels with no return (0, NaN, ±inf,
  negative) clear up to the far end only with `no_return_as_free`, and only when
  the cut ray stays between the floor and the band's top.

Readings nearer than the range's near end are ignored.

Speed. The mapper calls `depth_to_compact_observation`, which computes each pixel's
point from per-camera pixel rays (cached) in one compiled pass (`mapping.kernels`) and
snaps the points to the compaction lattice through a fixed per-camera bitmap, without
building the float point lists; its result equals compacting `depth_to_observation`'s,
which stays the reference path.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from hardware.calibration import Mount, WalkerCalibration
from hardware.messages import CameraIntrinsics, DepthFrame
from mapping.kernels import compact_pixel_cells, depth_pixel_cells
from mapping.observation import PlanarObservation, ViewWedge


@dataclass(frozen=True)
class DepthConfig:
    """How depth pixels become floor-plane evidence.

    floor_clearance_m: lowest obstacle height above the floor (0.05 m: floor noise).
    max_height_m: highest obstacle height (2.0 m: the walker and its user pass below).
    stride: keep every stride-th pixel of every stride-th row, 1/stride² of the pixels
        (1: all 160×120; the thesis kept every 10th point, about stride 3).
    no_return_as_free: rays with no return clear free space up to the far range.
    depth_scale_m: metres per depth unit (0.001 for the uint16 millimetres of DepthFrame).
    """

    floor_clearance_m: float = 0.05
    max_height_m: float = 2.0
    stride: int = 1
    no_return_as_free: bool = False
    depth_scale_m: float = 0.001

    def __post_init__(self) -> None:
        if self.stride < 1:
            raise ValueError(f"stride must be >= 1, got {self.stride}")
        if not self.floor_clearance_m < self.max_height_m:
            raise ValueError("floor_clearance_m must be below max_height_m")


@lru_cache(maxsize=16)
def _pixel_rays(intrinsics: CameraIntrinsics, mount: Mount, stride: int) -> np.ndarray:
    """(3, H', W') float32 walker-frame displacement per metre of z-depth, per kept pixel."""
    u = np.arange(0, intrinsics.width, stride, dtype=np.float64)
    v = np.arange(0, intrinsics.height, stride, dtype=np.float64)
    a = np.broadcast_to(((u - intrinsics.cx) / intrinsics.fx)[None, :], (len(v), len(u)))
    b = np.broadcast_to(((v - intrinsics.cy) / intrinsics.fy)[:, None], (len(v), len(u)))
    rays_optical = np.stack([a, b, np.ones_like(a)])
    r = mount.walker_T_optical()[:3, :3]
    rays = np.einsum("ij,jhw->ihw", r, rays_optical).astype(np.float32)
    rays.setflags(write=False)
    return rays


@dataclass(frozen=True, eq=False)
class _Camera:
    """What every frame of one intrinsics, mount and stride shares; built once (cached).

    rays: (3, P) float32 walker-frame displacement per metre of z-depth of the P kept
    pixels, row-major; t: (3, 1) float32 camera position in the walker frame; sensor_xy,
    sensor_yaw: the camera on the floor and the heading of its optical axis.
    """

    rays: np.ndarray
    t: np.ndarray
    sensor_xy: np.ndarray
    sensor_yaw: float


@lru_cache(maxsize=16)
def _camera(intrinsics: CameraIntrinsics, mount: Mount, stride: int) -> _Camera:
    walker_T_optical = mount.walker_T_optical()  # ~40 µs: worth caching per frame
    t = walker_T_optical[:3, 3]
    axis = walker_T_optical[:3, 2]  # the optical z axis in the walker frame
    rays = _pixel_rays(intrinsics, mount, stride).reshape(3, -1)
    t32 = t.astype(np.float32)[:, None]
    for a in (rays, t32):
        a.setflags(write=False)
    return _Camera(rays, t32, t[:2].copy(), float(np.arctan2(axis[1], axis[0])))


def _check_depth(depth: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray:
    depth = np.asarray(depth)
    if depth.shape != (intrinsics.height, intrinsics.width):
        raise ValueError(
            f"depth must have shape ({intrinsics.height}, {intrinsics.width}) as the "
            f"intrinsics say, got {depth.shape}"
        )
    return depth


def _range_units(range_m: tuple[float, float], scale: float) -> tuple[float, float]:
    """The range in depth units, widened by a hair so that a reading of exactly 800 or
    3500 mm counts as in range whatever the rounding of 0.001."""
    return range_m[0] / scale * (1 - 1e-9), range_m[1] / scale * (1 + 1e-9)


@lru_cache(maxsize=16)
def _integer_range(
    dtype: np.dtype, range_m: tuple[float, float], scale: float
) -> tuple[np.generic, np.generic] | None:
    """The in-range readings of an integer dtype, lo..hi inclusive; None if out of its span."""
    near, far = _range_units(range_m, scale)
    lo, hi = math.ceil(near), math.floor(far)
    info = np.iinfo(dtype)
    if info.min <= lo <= info.max and info.min <= hi <= info.max:
        return dtype.type(lo), dtype.type(hi)
    return None


def _range_masks(
    d: np.ndarray, range_m: tuple[float, float], scale: float
) -> tuple[np.ndarray, np.ndarray]:
    """(in range, beyond the far range) masks of the readings `d` (any shape).

    Integer readings are compared with the integer bounds that the range implies (5×
    cheaper than comparing them with floats, same result).
    """
    if d.dtype.kind in "ui":
        bounds = _integer_range(d.dtype, tuple(range_m), scale)
        if bounds is not None:
            lo, hi = bounds
            return (d >= lo) & (d <= hi), d > hi
    near, far = _range_units(range_m, scale)
    with np.errstate(invalid="ignore"):
        in_range = (d >= near) & (d <= far)
        beyond = d > far
    if d.dtype.kind == "f":
        beyond &= np.isfinite(d)  # inf is no return, not a far one
    return in_range, beyond


def _no_return(d: np.ndarray) -> np.ndarray:
    """Readings without a return: 0, negative, NaN or ±inf."""
    with np.errstate(invalid="ignore"):
        returned = d > 0
    if d.dtype.kind == "f":
        returned &= np.isfinite(d)
    return ~returned


@dataclass(frozen=True, eq=False)
class _Hits:
    """The kept pixels of one depth image as walker-frame points, P of them, row-major.

    xyz: (3, P) float32 points at the pixels' z-depths (meaningless where not in range);
    in_range: pixels with a z-depth within the range; obstacle: in-range hits within the
    obstacle band; end: in-range hits no higher than the band's top, whose rays show free
    space (every obstacle pixel is an end pixel); cut: pixels whose ray is cut at the far
    range.

    All pixels are computed, not only the in-range ones: full-frame arithmetic is cheaper
    than gathering the in-range pixels' rays.
    """

    xyz: np.ndarray
    in_range: np.ndarray
    obstacle: np.ndarray
    end: np.ndarray
    cut: np.ndarray


def _hits(
    depth: np.ndarray, camera: _Camera, range_m: tuple[float, float], cfg: DepthConfig
) -> _Hits:
    d = depth[:: cfg.stride, :: cfg.stride].ravel()
    in_range, beyond = _range_masks(d, range_m, cfg.depth_scale_m)
    if d.dtype.kind == "f":
        d = np.where(in_range, d, 0.0)  # no NaN or inf in the arithmetic below
    z = d.astype(np.float32)
    z *= np.float32(cfg.depth_scale_m)
    xyz = camera.rays * z
    xyz += camera.t
    height = xyz[2]
    end = in_range & (height <= cfg.max_height_m)
    obstacle = end & (height >= cfg.floor_clearance_m)
    cut = (beyond | _no_return(d)) if cfg.no_return_as_free else beyond
    return _Hits(xyz, in_range, obstacle, end, cut)


def _cut_ends(
    camera: _Camera, cut: np.ndarray, range_m: tuple[float, float], cfg: DepthConfig
) -> tuple[np.ndarray, np.ndarray]:
    """(2, N) float32 x, y of the rays cut at the far range that stay between the floor and
    the band's top."""
    rays = camera.rays.take(np.flatnonzero(cut), axis=1)
    xyz = rays * np.float32(range_m[1])
    xyz += camera.t
    ok = (xyz[2] >= 0.0) & (xyz[2] <= cfg.max_height_m)
    return xyz[:2].compress(ok, axis=1)


def depth_to_walker_points(
    depth: np.ndarray,
    intrinsics: CameraIntrinsics,
    mount: Mount,
    range_m: tuple[float, float],
    *,
    stride: int = 1,
    depth_scale_m: float = 0.001,
) -> np.ndarray:
    """3-D walker-frame points (N×3 float32) of the pixels whose z-depth is within range_m."""
    cfg = DepthConfig(stride=stride, depth_scale_m=depth_scale_m)
    camera = _camera(intrinsics, mount, stride)
    hits = _hits(_check_depth(depth, intrinsics), camera, range_m, cfg)
    return np.column_stack([c[hits.in_range] for c in hits.xyz])


def depth_to_observation(
    depth: np.ndarray,
    intrinsics: CameraIntrinsics,
    mount: Mount,
    range_m: tuple[float, float],
    config: DepthConfig | None = None,
    view: ViewWedge | None = None,
) -> PlanarObservation:
    """Obstacle points and free-space ray ends (walker frame) of one depth image.

    `depth` is an (H, W) array in units of config.depth_scale_m (uint16 mm or float);
    `view` is attached to the observation for the view-count map model. Points are in
    pixel order, the cut rays' ends after the hits'.
    """
    cfg = config or DepthConfig()
    camera = _camera(intrinsics, mount, cfg.stride)
    hits = _hits(_check_depth(depth, intrinsics), camera, range_m, cfg)
    x, y = hits.xyz[0], hits.xyz[1]
    ends = [np.column_stack([x[hits.end], y[hits.end]])]
    if hits.cut.any():
        ends.append(_cut_ends(camera, hits.cut, range_m, cfg).T)
    return PlanarObservation(
        sensor_xy=camera.sensor_xy,
        sensor_yaw=camera.sensor_yaw,
        obstacles=np.column_stack([x[hits.obstacle], y[hits.obstacle]]),
        ray_ends=np.concatenate(ends),
        view=view,
    )


@dataclass(frozen=True, eq=False)
class _LatticeBox:
    """The cells of the `quantum` lattice that a camera's points can fall in, row-major.

    Covers every point at a z-depth within the range (and so every ray cut at its far
    end), with a cell to spare, so that the points of any frame index one fixed bitmap
    without a bounds computation per frame. `centres` holds every cell's (x, y) centre as
    `quantise_points` computes it, so that points come out of the bitmap by one gather
    instead of a divmod of the indices.
    """

    quantum: float
    i0: int
    j0: int
    width: int
    height: int
    centres: np.ndarray  # (width·height, 2) float32

    @property
    def size(self) -> int:
        return self.width * self.height


_MAX_BOX_CELLS = 1 << 22  # 4 MB bitmap; also keeps float32 cell arithmetic exact


@lru_cache(maxsize=16)
def _lattice_box(
    camera: _Camera, range_m: tuple[float, float], quantum: float
) -> _LatticeBox | None:
    """The `_LatticeBox` of a camera's in-range points; None if over _MAX_BOX_CELLS."""
    rays = camera.rays.astype(np.float64)
    t = camera.t.astype(np.float64)
    lo = np.full(2, np.inf)
    hi = np.full(2, -np.inf)
    for z in (range_m[0] * (1 - 1e-6), range_m[1] * (1 + 1e-6)):
        xy = t[:2] + z * rays[:2]
        lo, hi = np.minimum(lo, xy.min(axis=1)), np.maximum(hi, xy.max(axis=1))
    i0, j0 = (int(np.floor(v / quantum)) - 1 for v in lo)
    i1, j1 = (int(np.floor(v / quantum)) + 1 for v in hi)
    width, height = i1 - i0 + 1, j1 - j0 + 1
    if width * height > _MAX_BOX_CELLS:
        return None
    j, i = np.divmod(np.arange(width * height), width)
    centres = np.column_stack([(i + i0 + 0.5) * quantum, (j + j0 + 0.5) * quantum])
    centres = centres.astype(np.float32)
    centres.setflags(write=False)
    return _LatticeBox(quantum, i0, j0, width, height, centres)


def depth_to_compact_observation(
    depth: np.ndarray,
    intrinsics: CameraIntrinsics,
    mount: Mount,
    range_m: tuple[float, float],
    quantum: float,
    config: DepthConfig | None = None,
    view: ViewWedge | None = None,
) -> PlanarObservation:
    """`depth_to_observation(...).compacted(quantum)`, without the intermediate points.

    For integer (e.g. uint16 millimetre) images, compiled passes over the pixels
    (`mapping.kernels.depth_pixel_cells`, `compact_pixel_cells`) put their lattice cells
    straight into a bitmap over the camera's lattice box; one scan of the bitmap yields
    the distinct ends ordered by (j, i), as `quantise_points` orders them, and the
    obstacles are the ends whose cell holds an obstacle point (every obstacle pixel is an
    end pixel). The result
    is identical to compacting `depth_to_observation`'s points, which is what other images
    (float depths) and lattices too fine for a bitmap get.
    """
    cfg = config or DepthConfig()
    depth = _check_depth(depth, intrinsics)
    camera = _camera(intrinsics, mount, cfg.stride)
    box = _lattice_box(camera, tuple(range_m), quantum) if quantum > 0 else None
    bounds = (
        _integer_range(depth.dtype, tuple(range_m), cfg.depth_scale_m)
        if depth.dtype.kind in "ui"
        else None
    )
    if box is None or bounds is None:
        obs = depth_to_observation(depth, intrinsics, mount, range_m, cfg, view)
        return obs.compacted(quantum)
    f32 = np.float32
    pixels = depth[:: cfg.stride, :: cfg.stride].reshape(-1)
    cells = np.empty(len(pixels), dtype=np.int32)
    obstacle = np.empty(len(pixels), dtype=bool)
    depth_pixel_cells(
        pixels,
        camera.rays,
        camera.t[:, 0],
        int(bounds[0]),
        int(bounds[1]),
        cfg.no_return_as_free,
        f32(cfg.depth_scale_m),
        f32(cfg.floor_clearance_m),
        f32(cfg.max_height_m),
        f32(range_m[1]),
        f32(quantum),
        (box.i0, box.j0, box.width, box.height),
        cells,
        obstacle,
    )
    obstacles, ends = compact_pixel_cells(cells, obstacle, box.size, box.centres)
    return PlanarObservation(
        sensor_xy=camera.sensor_xy,
        sensor_yaw=camera.sensor_yaw,
        obstacles=obstacles,
        ray_ends=ends,
        view=view,
    )


def project_depth_frame(
    frame: DepthFrame,
    calibration: WalkerCalibration,
    config: DepthConfig | None = None,
    view: ViewWedge | None = None,
    quantum: float = 0.0,
) -> PlanarObservation:
    """`depth_to_observation` for a DepthFrame with the walker's depth mount and range.

    quantum > 0: the observation compacted to that lattice (`depth_to_compact_observation`).
    """
    args = (frame.depth_mm, frame.intrinsics, calibration.depth_mount, calibration.depth_range_m)
    if quantum > 0:
        return depth_to_compact_observation(*args, quantum, config, view)
    return depth_to_observation(*args, config, view)
