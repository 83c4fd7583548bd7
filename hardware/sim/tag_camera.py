"""Simulated AprilTag camera: which tags of a World a camera sees, with realistic noise.

A tag is detected when its four corners project inside the image, it is within range,
seen at no more than the maximum incidence angle, its projected side is large enough,
and the ray from the camera to its centre is not blocked by any box other than the one
the tag is on (same ray caster as the depth camera). The reported pose is what a real
detector would produce: the true corners are projected (pinhole, no distortion), get
Gaussian pixel noise, and the pose is solved from them with OpenCV's IPPE_SQUARE on the
object points and corner order of pupil-apriltags (tag frame x right, y down, z into the
tag; corners_px[0] is the tag's (−s/2, +s/2) corner and they wrap counter-clockwise).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from hardware.calibration import Mount, WalkerCalibration
from hardware.frames import invert_transform, make_transform, planar_pose_to_transform
from hardware.messages import CameraIntrinsics, TagDetection
from hardware.sim.raycast import BoxRayCaster
from hardware.sim.world import World

_OCCLUSION_MARGIN_M = 0.01


def tag_object_points(tag_size_m: float) -> np.ndarray:
    """Tag corners (4×3) in the tag frame, in pupil-apriltags / IPPE_SQUARE order."""
    h = 0.5 * tag_size_m
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


@dataclass(frozen=True)
class TagCameraConfig:
    """Simulated tag camera; None fields take the calibration's values.

    pixel_noise_px: σ of the Gaussian noise on each corner coordinate; range_m: detection
    range (camera to tag centre); max_incidence_rad: largest angle between the tag normal
    and the direction to the camera; min_side_px: smallest projected tag side.
    """

    pixel_noise_px: float = 0.5
    range_m: tuple[float, float] = (0.3, 4.0)
    max_incidence_rad: float = math.radians(60.0)
    min_side_px: float = 12.0
    intrinsics: CameraIntrinsics | None = None
    mount: Mount | None = None
    tag_size_m: float | None = None

    def __post_init__(self) -> None:
        if self.pixel_noise_px < 0:
            raise ValueError(f"pixel_noise_px must be >= 0, got {self.pixel_noise_px}")
        if not 0.0 <= self.range_m[0] < self.range_m[1]:
            raise ValueError(f"range_m must be (min, max) with 0 <= min < max, got {self.range_m}")
        if not 0.0 < self.max_incidence_rad < math.pi / 2:
            raise ValueError(f"max_incidence_rad must be in (0, π/2), got {self.max_incidence_rad}")


@dataclass(frozen=True, eq=False)
class TagView:
    """Noise-free geometry of a tag the camera can detect."""

    tag_id: int
    camera_T_tag: np.ndarray
    corners_px: np.ndarray


class SimTagCamera:
    """Detects the tags of `world` from walker poses (x, y, θ)."""

    def __init__(
        self,
        world: World,
        calibration: WalkerCalibration,
        config: TagCameraConfig,
        rng: np.random.Generator,
    ) -> None:
        self.world = world
        self.config = config
        self.rng = rng
        self.intrinsics = config.intrinsics or calibration.tag_intrinsics
        self.mount = config.mount or calibration.tag_mount
        self.tag_size_m = config.tag_size_m or calibration.tag_size_m
        self.walker_T_optical = self.mount.walker_T_optical()
        self.caster = BoxRayCaster(world.box_array)
        self.object_points = tag_object_points(self.tag_size_m)
        tags = world.tags
        self.tag_ids = np.array([t.tag_id for t in tags], dtype=int)
        self.world_T_tags = np.array([world.world_T_tag(t) for t in tags]).reshape(-1, 4, 4)
        self.centres = self.world_T_tags[:, :3, 3]
        self.normals = -self.world_T_tags[:, :3, 2]
        self.corners_world = (
            np.einsum("tij,kj->tki", self.world_T_tags[:, :3, :3], self.object_points)
            + self.centres[:, None, :]
        )
        self.host_boxes = world.tag_host_boxes
        self._k = self.intrinsics.matrix

    def visible(self, pose: Sequence[float]) -> list[TagView]:
        """Tags detectable from the pose, with their true pose and corners (no noise)."""
        if len(self.tag_ids) == 0:
            return []
        cfg, k = self.config, self.intrinsics
        world_T_cam = planar_pose_to_transform(*(float(p) for p in pose)) @ self.walker_T_optical
        r, c = world_T_cam[:3, :3], world_T_cam[:3, 3]
        to_cam = c - self.centres
        rng_m = np.linalg.norm(to_cam, axis=1)
        cos_inc = (self.normals * to_cam).sum(axis=1) / np.maximum(rng_m, 1e-12)
        ok = (rng_m >= cfg.range_m[0]) & (rng_m <= cfg.range_m[1])
        ok &= cos_inc >= math.cos(cfg.max_incidence_rad)
        corners_cam = (self.corners_world - c) @ r  # (T, 4, 3): Rᵀ(p − c)
        z = corners_cam[..., 2]
        ok &= (z > 1e-3).all(axis=1)
        zs = np.where(z > 1e-3, z, 1.0)
        u = k.fx * corners_cam[..., 0] / zs + k.cx
        v = k.fy * corners_cam[..., 1] / zs + k.cy
        ok &= ((u >= 0) & (u <= k.width - 1) & (v >= 0) & (v <= k.height - 1)).all(axis=1)
        side = np.hypot(np.diff(u, axis=1, append=u[:, :1]), np.diff(v, axis=1, append=v[:, :1]))
        ok &= side.min(axis=1) >= cfg.min_side_px
        idx = np.flatnonzero(ok)
        if len(idx):
            t, _ = self.caster.cast(c, -to_cam[idx], 1.0, exclude=self.host_boxes[idx])
            blocked = t < 1.0 - _OCCLUSION_MARGIN_M / rng_m[idx]
            idx = idx[~blocked]
        cam_T_world = invert_transform(world_T_cam)
        return [
            TagView(
                int(self.tag_ids[i]),
                cam_T_world @ self.world_T_tags[i],
                np.column_stack([u[i], v[i]]),
            )
            for i in idx
        ]

    def detect(self, pose: Sequence[float]) -> tuple[TagDetection, ...]:
        """Detections as a real detector would report them: noisy corners and the
        IPPE_SQUARE pose solved from them."""
        out = []
        sigma = self.config.pixel_noise_px
        for view in self.visible(pose):
            corners = view.corners_px
            if sigma > 0:
                corners = corners + sigma * self.rng.standard_normal(corners.shape)
            ok, rvec, tvec = cv2.solvePnP(
                self.object_points,
                corners.astype(np.float64),
                self._k,
                None,
                flags=cv2.SOLVEPNP_IPPE_SQUARE,
            )
            if not ok:
                continue
            rot, _ = cv2.Rodrigues(rvec)
            out.append(TagDetection(view.tag_id, make_transform(rot, tvec.ravel()), corners))
        return tuple(out)
