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
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from hardware.calibration import Mount, WalkerCalibration
from hardware.messages import CameraIntrinsics, DepthFrame
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


def _points(
    z: np.ndarray | float, rays: np.ndarray, t: np.ndarray, mask: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Walker-frame x, y, height of the masked pixels at z-depth z (one per pixel, or one)."""
    zf = z if isinstance(z, np.ndarray) else np.float32(z)
    x, y, h = (np.float32(t[k]) + zf * rays[k][mask] for k in range(3))
    return x, y, h


def _check_depth(depth: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray:
    depth = np.asarray(depth)
    if depth.shape != (intrinsics.height, intrinsics.width):
        raise ValueError(
            f"depth must have shape ({intrinsics.height}, {intrinsics.width}) as the "
            f"intrinsics say, got {depth.shape}"
        )
    return depth


@dataclass(frozen=True, eq=False)
class _Pixels:
    """The kept pixels of a depth image sorted by their reading (boolean (H', W') masks)."""

    in_range: np.ndarray
    beyond: np.ndarray  # a return farther than the far range
    z: np.ndarray  # z-depth [m] (float32) of the in-range pixels, in mask order
    raw: np.ndarray  # the kept readings

    @classmethod
    def of(
        cls, depth: np.ndarray, stride: int, range_m: tuple[float, float], scale: float
    ) -> _Pixels:
        d = depth[::stride, ::stride]
        # Compare in depth units, the range ends widened by a hair so that a reading of
        # exactly 800 or 3500 mm counts as in range whatever the rounding of 0.001.
        near, far = range_m[0] / scale * (1 - 1e-9), range_m[1] / scale * (1 + 1e-9)
        with np.errstate(invalid="ignore"):
            in_range = (d >= near) & (d <= far)
            beyond = d > far
        if d.dtype.kind == "f":
            beyond &= np.isfinite(d)  # inf is no return, not a far one
        z = d[in_range].astype(np.float32) * np.float32(scale)
        return cls(in_range, beyond, z, d)

    def no_return(self) -> np.ndarray:
        """Pixels without a return: 0, negative, NaN or ±inf."""
        with np.errstate(invalid="ignore"):
            returned = self.raw > 0
        if self.raw.dtype.kind == "f":
            returned &= np.isfinite(self.raw)
        return ~returned


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
    px = _Pixels.of(_check_depth(depth, intrinsics), stride, range_m, depth_scale_m)
    rays = _pixel_rays(intrinsics, mount, stride)
    return np.column_stack(_points(px.z, rays, mount.walker_T_optical()[:3, 3], px.in_range))


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
    `view` is attached to the observation for the view-count map model.
    """
    cfg = config or DepthConfig()
    px = _Pixels.of(_check_depth(depth, intrinsics), cfg.stride, range_m, cfg.depth_scale_m)
    rays = _pixel_rays(intrinsics, mount, cfg.stride)
    walker_T_optical = mount.walker_T_optical()
    t = walker_T_optical[:3, 3]

    # In-range hits: full 3-D points.
    hx, hy, hz = _points(px.z, rays, t, px.in_range)
    band = (hz >= cfg.floor_clearance_m) & (hz <= cfg.max_height_m)
    clears = hz <= cfg.max_height_m
    obstacles = np.column_stack([hx[band], hy[band]])
    ends = [np.column_stack([hx[clears], hy[clears]])]

    # Rays cut at the far range: returns beyond it, and (optionally) no returns.
    cut = (px.beyond | px.no_return()) if cfg.no_return_as_free else px.beyond
    if np.any(cut):
        fx, fy, fz = _points(range_m[1], rays, t, cut)
        ok = (fz >= 0.0) & (fz <= cfg.max_height_m)
        ends.append(np.column_stack([fx[ok], fy[ok]]))

    axis = walker_T_optical[:3, 2]  # the optical z axis in the walker frame
    return PlanarObservation(
        sensor_xy=t[:2],
        sensor_yaw=float(np.arctan2(axis[1], axis[0])),
        obstacles=obstacles,
        ray_ends=np.concatenate(ends),
        view=view,
    )


def project_depth_frame(
    frame: DepthFrame,
    calibration: WalkerCalibration,
    config: DepthConfig | None = None,
    view: ViewWedge | None = None,
) -> PlanarObservation:
    """`depth_to_observation` for a DepthFrame with the walker's depth mount and range."""
    return depth_to_observation(
        frame.depth_mm,
        frame.intrinsics,
        calibration.depth_mount,
        calibration.depth_range_m,
        config,
        view,
    )
