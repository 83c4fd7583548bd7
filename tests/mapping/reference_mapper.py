"""A slow, straightforward re-implementation of the mapper's depth path, for equality tests.

It follows the documented semantics of `mapping` step by step — depth pixels → walker-frame
points → obstacle band and free-space ray ends → quarter-cell lattice → world cells →
bundled rays traced at half-cell steps → log-odds or view-count update — with sorting,
per-bin and per-ray Python loops and boolean maps over one fixed world window instead of
the mapper's bitmaps, caches, fused passes and growing grid. Every value that decides a
cell is computed in the same float operations as the mapper's definition, so its maps
must equal `OccupancyMapper`'s exactly (the mapper before its speed-up passes this too).

Scope: log-odds and view-count maps of uint16 depth frames, default DepthConfig, no
rolling grid.
"""

from __future__ import annotations

import numpy as np

from hardware.calibration import WalkerCalibration
from hardware.geometry import transform_points, wrap_angle
from hardware.messages import DepthFrame
from mapping.mapper import MapperConfig


class ReferenceMapper:
    """Map over the fixed world-lattice window [i0, i0 + nx) × [j0, j0 + ny)."""

    def __init__(
        self,
        calibration: WalkerCalibration,
        config: MapperConfig,
        lattice_lo: tuple[int, int],
        shape: tuple[int, int],
    ) -> None:
        self.cal, self.cfg = calibration, config
        self.res = config.grid.resolution_m
        self.i0, self.j0 = lattice_lo
        dtype = np.float32 if config.grid.model == "log-odds" else np.uint32
        self.layers = {
            name: np.zeros(shape, dtype=dtype)
            for name in (["log_odds"] if config.grid.model == "log-odds" else ["views", "hits"])
        }

    # --- depth frame → walker-frame points ------------------------------------------------
    def walker_points(self, frame: DepthFrame) -> tuple[np.ndarray, np.ndarray]:
        """(obstacles, ray ends), float32 walker-frame x, y, before compaction."""
        intr, mount, cfg = frame.intrinsics, self.cal.depth_mount, self.cfg.depth
        u = np.arange(intr.width, dtype=np.float64)
        v = np.arange(intr.height, dtype=np.float64)
        a = np.broadcast_to(((u - intr.cx) / intr.fx)[None, :], (len(v), len(u)))
        b = np.broadcast_to(((v - intr.cy) / intr.fy)[:, None], (len(v), len(u)))
        optical = np.stack([a, b, np.ones_like(a)])  # per metre of z-depth
        w_T_o = mount.walker_T_optical()
        rays = np.einsum("ij,jhw->ihw", w_T_o[:3, :3], optical).astype(np.float32)
        d = frame.depth_mm
        lo_m, hi_m = self.cal.depth_range_m
        scale = cfg.depth_scale_m
        in_range = (d >= lo_m / scale * (1 - 1e-9)) & (d <= hi_m / scale * (1 + 1e-9))
        assert not np.any(d > hi_m / scale * (1 + 1e-9)), "no returns beyond range here"
        z = d[in_range].astype(np.float32) * np.float32(scale)
        x, y, h = (np.float32(w_T_o[k, 3]) + z * rays[k][in_range] for k in range(3))
        band = (h >= cfg.floor_clearance_m) & (h <= cfg.max_height_m)
        clears = h <= cfg.max_height_m
        return np.column_stack([x[band], y[band]]), np.column_stack([x[clears], y[clears]])

    def compact(self, points: np.ndarray) -> np.ndarray:
        """Distinct quarter-cell lattice centres of walker-frame points (float32)."""
        q = self.res / 4.0
        ij = np.floor(points / q).astype(np.int64)
        ij = ij[np.lexsort((ij[:, 1], ij[:, 0]))]
        first = np.ones(len(ij), dtype=bool)
        first[1:] = np.any(ij[1:] != ij[:-1], axis=1)
        return ((ij[first] + 0.5) * q).astype(np.float32)

    # --- the map update -------------------------------------------------------------------
    def integrate_depth(self, frame: DepthFrame, pose: np.ndarray) -> None:
        pose = np.asarray(pose, dtype=np.float64)
        obstacles, ends = (self.compact(p) for p in self.walker_points(frame))
        w_T_o = self.cal.depth_mount.walker_T_optical()
        sensor = transform_points(pose, w_T_o[None, :2, 3])[0]
        occ = self.mask(transform_points(pose, obstacles))
        end_cells = self.mask(transform_points(pose, ends))
        if "log_odds" in self.layers:
            self.update_log_odds(occ, self.crossed(sensor, end_cells) | end_cells)
        else:
            axis = w_T_o[:3, 2]
            heading = float(pose[2] + np.arctan2(axis[1], axis[0]))
            self.update_views(occ, self.in_wedge(sensor, heading, frame))

    def mask(self, world_xy: np.ndarray) -> np.ndarray:
        """Boolean map of the cells holding the world points."""
        ij = np.floor(world_xy / self.res).astype(np.int64)
        out = np.zeros(self.shape, dtype=bool)
        out[ij[:, 1] - self.j0, ij[:, 0] - self.i0] = True
        return out

    @property
    def shape(self) -> tuple[int, int]:
        return next(iter(self.layers.values())).shape

    def crossed(self, sensor: np.ndarray, end_cells: np.ndarray) -> np.ndarray:
        """Cells sampled along the longest ray of each bearing bin (`bundle_rays`)."""
        res = self.res
        rows, cols = np.nonzero(end_cells)  # distinct end cells ordered by (j, i), as the grid
        targets = np.column_stack([cols + self.i0 + 0.5, rows + self.j0 + 0.5]) * res
        d = targets - sensor
        r = np.hypot(d[:, 0], d[:, 1])
        width = 0.5 * res / max(float(r.max()), res)
        bins = np.floor((np.arctan2(d[:, 1], d[:, 0]) + np.pi) / width).astype(np.int64)
        longest: dict[int, int] = {}
        for k, b in enumerate(bins.tolist()):
            if b not in longest or r[k] >= r[longest[b]]:  # the last of equally long ones
                longest[b] = k
        out = np.zeros(self.shape, dtype=bool)
        for k in longest.values():
            dx, dy = (targets[k] - sensor) / res
            n = max(int(np.ceil(2.0 * np.hypot(dx, dy))), 1)
            frac = np.arange(n, dtype=np.float64) / n
            x = np.floor(frac * dx + sensor[0] / res).astype(np.int64)
            y = np.floor(frac * dy + sensor[1] / res).astype(np.int64)
            out[y - self.j0, x - self.i0] = True
        return out

    def in_wedge(self, sensor: np.ndarray, heading: float, frame: DepthFrame) -> np.ndarray:
        """Cells whose centres lie in the view wedge (range and ±half FOV of the axis)."""
        res, (r_min, r_max) = self.res, self.cfg.view_range_m
        half_fov = self.cfg.view_half_fov_rad
        if half_fov is None:
            half_fov = float(np.arctan(frame.intrinsics.width / (2.0 * frame.intrinsics.fx)))
        lo = np.floor((sensor - r_max) / res).astype(np.int64) - 1
        hi = np.floor((sensor + r_max) / res).astype(np.int64) + 1
        i, j = np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1)
        x = (i + 0.5) * res - sensor[0]
        y = (j + 0.5) * res - sensor[1]
        r = np.hypot(x[None, :], y[:, None])
        bearing = wrap_angle(np.arctan2(y[:, None], x[None, :]) - heading)
        out = np.zeros(self.shape, dtype=bool)
        rows, cols = (
            slice(lo[1] - self.j0, hi[1] + 1 - self.j0),
            slice(lo[0] - self.i0, hi[0] + 1 - self.i0),
        )
        out[rows, cols] = (r >= r_min) & (r <= r_max) & (np.abs(bearing) <= half_fov)
        return out

    def update_log_odds(self, occ: np.ndarray, reached: np.ndarray) -> None:
        p, lo = self.cfg.grid.log_odds, self.layers["log_odds"]
        free = reached & ~occ
        lo[free] = np.maximum(lo[free] + np.float32(p.l_free), np.float32(p.l_min))
        lo[occ] = np.minimum(lo[occ] + np.float32(p.l_occ), np.float32(p.l_max))

    def update_views(self, occ: np.ndarray, in_view: np.ndarray) -> None:
        self.layers["views"][in_view | occ] += 1
        self.layers["hits"][occ] += 1
