"""Simulated depth camera (Kinect v1 style) rendering z-depth images of a World.

Depth is along the optical axis (as the Kinect reports it, not the ray length), in
millimetres as uint16 with 0 = invalid. Rays are cast against every box of the world and
the floor plane z = 0; readings get Gaussian noise growing with the square of the depth
(Kinect: σ_z ≈ 1.425e-3·z² m, Khoshelham & Elberink 2012), are quantised to millimetres,
and are invalid outside the usable range or, at random, with a small dropout probability.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hardware.calibration import Mount, WalkerCalibration
from hardware.frames import planar_pose_to_transform
from hardware.messages import CameraIntrinsics
from hardware.sim.raycast import BoxRayCaster
from hardware.sim.world import World

_LEVEL_TOL = 1e-9


@dataclass(frozen=True)
class DepthCameraConfig:
    """Simulated depth camera; None fields take the calibration's values.

    The true mount / intrinsics may differ from the calibration (extrinsic error).
    noise_coeff: σ_z = noise_coeff·z² [1/m]; dropout: probability a pixel reads 0.
    """

    noise_coeff: float = 1.425e-3
    dropout: float = 0.005
    intrinsics: CameraIntrinsics | None = None
    mount: Mount | None = None
    range_m: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if self.noise_coeff < 0:
            raise ValueError(f"noise_coeff must be >= 0, got {self.noise_coeff}")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {self.dropout}")
        if self.range_m is not None and not 0.0 < self.range_m[0] < self.range_m[1] <= 65.0:
            raise ValueError(
                f"range_m must be (min, max) with 0 < min < max <= 65, got {self.range_m}"
            )


class SimDepthCamera:
    """Renders depth frames of `world` from walker poses (x, y, θ)."""

    def __init__(
        self,
        world: World,
        calibration: WalkerCalibration,
        config: DepthCameraConfig,
        rng: np.random.Generator,
    ) -> None:
        self.world = world
        self.config = config
        self.rng = rng
        self.intrinsics = config.intrinsics or calibration.depth_intrinsics
        self.mount = config.mount or calibration.depth_mount
        self.range_m = tuple(config.range_m or calibration.depth_range_m)
        k = self.intrinsics
        self._xn = (np.arange(k.width) - k.cx) / k.fx
        self._yn = (np.arange(k.height) - k.cy) / k.fy
        self.walker_T_optical = self.mount.walker_T_optical()
        r = self.walker_T_optical[:3, :3]
        # Level: the optical y axis points straight down, so image columns are vertical.
        self.level = bool(np.allclose(r[:, 1], [0.0, 0.0, -1.0], atol=_LEVEL_TOL))
        self.caster = BoxRayCaster(world.box_array)

    def true_depth(self, pose: Sequence[float]) -> np.ndarray:
        """Noise-free z-depth [m] (H, W) float32; inf where nothing is hit within
        slightly beyond the maximum range."""
        world_T_opt = planar_pose_to_transform(*(float(p) for p in pose)) @ self.walker_T_optical
        r, c = world_T_opt[:3, :3], world_T_opt[:3, 3]
        # Cast a little past the range so noise can carry readings across its limit.
        t_max = self.range_m[1] * 1.05 + 0.05
        if self.level:
            return self.caster.depth_level(c, r[:2, 0], r[:2, 2], self._xn, self._yn, t_max)
        k = self.intrinsics
        return self.caster.depth_image(c, r, k.matrix, k.width, k.height, t_max)

    def render(self, pose: Sequence[float]) -> np.ndarray:
        """Depth image in millimetres (uint16, H×W), 0 = invalid."""
        z = self.true_depth(pose)
        z[~np.isfinite(z)] = 0.0  # nothing hit: stays invalid through the noise
        cfg = self.config
        if cfg.noise_coeff > 0:
            noise = self.rng.standard_normal(z.shape, dtype=np.float32)
            z = z + np.float32(cfg.noise_coeff) * z * z * noise
        lo, hi = self.range_m
        valid = (z >= lo) & (z <= hi)
        if cfg.dropout > 0:
            valid &= self.rng.random(z.shape, dtype=np.float32) >= cfg.dropout
        mm = np.rint(np.where(valid, z, 0.0) * 1000.0)
        return mm.astype(np.uint16)
