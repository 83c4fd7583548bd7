"""Ray casting against upright boxes (walls, furniture) and the floor, vectorised.

Every box is a rectangle in the plane extruded between z0 and z1, so a ray meets it
where the plan-view slab interval (the ray's horizontal part against the rotated
rectangle) overlaps the interval in which the ray's height lies within [z0, z1]. Rays
are parameterised as origin + t·direction; the depth camera uses directions with unit
optical-z component so that t is the z-depth directly.

`BoxRayCaster.cast` handles any set of rays (tag occlusion); `depth_image` renders a
camera in any orientation, testing each box only against the pixels inside its projected
bounding rectangle; `depth_level` is the fast path for a level camera, whose image
columns are vertical planes: the plan-view slab is computed once per (column, box) and
only the vertical interval per row.
"""

from __future__ import annotations

import numpy as np

_TINY = 1e-30  # stands in for a zero direction component: 1/_TINY stays finite


def _nonzero(a: np.ndarray) -> np.ndarray:
    return np.where(np.abs(a) < _TINY, _TINY, a)


def _slab(o: np.ndarray, d: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Entry/exit parameters of o + t·d through [-half, half] (broadcasting arrays)."""
    inv = 1.0 / _nonzero(d)
    t1 = (-half - o) * inv
    t2 = (half - o) * inv
    return np.minimum(t1, t2), np.maximum(t1, t2)


def _floor_depth(height: float, dz: np.ndarray, t_max: float) -> np.ndarray:
    """Parameter t at which rays from `height` with world-z components dz (per unit t)
    reach the floor z = 0; inf for rays that do not go down or get there beyond t_max."""
    down = dz < 0
    t = np.where(down, -height / np.where(down, dz, -1.0), np.inf)
    return np.where(t <= t_max, t, np.inf)


class BoxRayCaster:
    """First hits of rays with a fixed set of upright boxes (rows [cx, cy, yaw, sx, sy, z0, z1])."""

    def __init__(self, boxes: np.ndarray) -> None:
        b = np.asarray(boxes, dtype=float).reshape(-1, 7)
        self.boxes = b
        self.cx, self.cy = b[:, 0], b[:, 1]
        self.cos, self.sin = np.cos(b[:, 2]), np.sin(b[:, 2])
        self.hx, self.hy = 0.5 * b[:, 3], 0.5 * b[:, 4]
        self.z0, self.z1 = b[:, 5], b[:, 6]
        self.radius = np.hypot(self.hx, self.hy)

    def __len__(self) -> int:
        return len(self.boxes)

    def cast(
        self,
        origins: np.ndarray,
        dirs: np.ndarray,
        t_max: float = np.inf,
        exclude: np.ndarray | None = None,
        chunk: int = 4096,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Nearest hit parameter t in [0, t_max] and box index per ray (inf, -1 if none).

        origins: (3,) or (N, 3); dirs: (N, 3), any length; exclude: (N,) box index per
        ray to ignore (-1 for none). A ray starting inside a box hits it at t = 0.
        """
        dirs = np.atleast_2d(np.asarray(dirs, dtype=float))
        n = len(dirs)
        origins = np.broadcast_to(np.asarray(origins, dtype=float), (n, 3))
        t_best = np.full(n, np.inf)
        i_best = np.full(n, -1, dtype=int)
        if n == 0 or len(self) == 0:
            return t_best, i_best
        # Cull boxes no ray can reach within t_max.
        reach = t_max * np.hypot(dirs[:, 0], dirs[:, 1]).max() if np.isfinite(t_max) else np.inf
        lo_xy, hi_xy = origins[:, :2].min(axis=0), origins[:, :2].max(axis=0)
        gap = np.maximum(
            0.0,
            np.maximum(lo_xy - np.column_stack([self.cx, self.cy]), 0.0)
            + np.maximum(np.column_stack([self.cx, self.cy]) - hi_xy, 0.0),
        )
        keep = np.flatnonzero(np.hypot(gap[:, 0], gap[:, 1]) - self.radius <= reach)
        if len(keep) == 0:
            return t_best, i_best
        for a in range(0, n, chunk):
            o, d = origins[a : a + chunk], dirs[a : a + chunk]
            t_hit = self._hit(
                o[:, :1], o[:, 1:2], o[:, 2:3], d[:, :1], d[:, 1:2], d[:, 2:3], keep[None, :], t_max
            )
            if exclude is not None:
                t_hit[keep[None, :] == np.asarray(exclude)[a : a + chunk, None]] = np.inf
            j = np.argmin(t_hit, axis=1)
            tj = t_hit[np.arange(len(j)), j]
            t_best[a : a + chunk] = tj
            i_best[a : a + chunk] = np.where(np.isfinite(tj), keep[j], -1)
        return t_best, i_best

    def _hit(
        self,
        ox: np.ndarray | float,
        oy: np.ndarray | float,
        oz: np.ndarray | float,
        dx: np.ndarray,
        dy: np.ndarray,
        dz: np.ndarray,
        b: np.ndarray,
        t_max: float,
    ) -> np.ndarray:
        """First-hit t of rays o + t·d with boxes b (all broadcast together), inf if none
        within [0, t_max]: the plan-view slab test in each box's frame, intersected with
        the interval in which the ray's height is within [z0, z1]."""
        c, s = self.cos[b], self.sin[b]
        rx, ry = ox - self.cx[b], oy - self.cy[b]
        tx0, tx1 = _slab(c * rx + s * ry, c * dx + s * dy, self.hx[b])
        ty0, ty1 = _slab(-s * rx + c * ry, -s * dx + c * dy, self.hy[b])
        tz0, tz1 = _slab(oz - 0.5 * (self.z0[b] + self.z1[b]), dz, 0.5 * (self.z1[b] - self.z0[b]))
        t_in = np.maximum(np.maximum(tx0, ty0), tz0)
        t_out = np.minimum(np.minimum(tx1, ty1), tz1)
        t_hit = np.maximum(t_in, 0.0)
        return np.where((t_hit <= t_out) & (t_hit <= t_max), t_hit, np.inf)

    def depth_image(
        self,
        centre: np.ndarray,
        rotation: np.ndarray,
        intrinsics_k: np.ndarray,
        width: int,
        height: int,
        t_max: float,
        floor: bool = True,
    ) -> np.ndarray:
        """Z-depth image (H, W) float32 of a pinhole camera in any orientation; inf where
        nothing is hit within t_max (t_max is a z-depth).

        centre (3,) and rotation (3×3, columns = optical axes in the world) give the
        camera pose; intrinsics_k is the 3×3 pinhole matrix.
        """
        cam = np.asarray(centre, dtype=float)
        r = np.asarray(rotation, dtype=float)
        fx, fy, cx, cy = (
            intrinsics_k[0, 0],
            intrinsics_k[1, 1],
            intrinsics_k[0, 2],
            intrinsics_k[1, 2],
        )
        xn = (np.arange(width) - cx) / fx
        yn = (np.arange(height) - cy) / fy
        xs, ys = np.meshgrid(xn, yn)
        dirs = np.stack([xs, ys, np.ones_like(xs)], axis=-1).reshape(-1, 3) @ r.T  # (N, 3)
        depth = np.full(width * height, np.inf)
        if len(self):
            rect = self._pixel_rects(cam, r, fx, fy, cx, cy, width, height, t_max)
            keep = np.flatnonzero(rect[:, 0] <= rect[:, 1])
            if len(keep):
                u0, u1, v0, v1 = rect[keep].T
                w_ = u1 - u0 + 1
                counts = w_ * (v1 - v0 + 1)
                b = np.repeat(keep, counts)
                off = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
                wr = np.repeat(w_, counts)
                pix = (np.repeat(v0, counts) + off // wr) * width + np.repeat(u0, counts) + off % wr
                d = dirs[pix]
                t = self._hit(cam[0], cam[1], cam[2], d[:, 0], d[:, 1], d[:, 2], b, t_max)
                hit = np.isfinite(t)
                np.minimum.at(depth, pix[hit], t[hit])
        if floor and cam[2] > 0:
            depth = np.minimum(depth, _floor_depth(cam[2], dirs[:, 2], t_max))
        return depth.reshape(height, width).astype(np.float32)

    def _pixel_rects(
        self,
        cam: np.ndarray,
        r: np.ndarray,
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        width: int,
        height: int,
        t_max: float,
    ) -> np.ndarray:
        """Per box the inclusive pixel rectangle [u0, u1, v0, v1] that contains its
        projection (u0 > u1 when it cannot be seen within t_max)."""
        near = 1e-3
        sx = np.array([-1, 1, 1, -1, -1, 1, 1, -1])
        sy = np.array([-1, -1, 1, 1, -1, -1, 1, 1])
        lx, ly = sx[None, :] * self.hx[:, None], sy[None, :] * self.hy[:, None]
        corners = np.stack(
            [
                self.cx[:, None] + self.cos[:, None] * lx - self.sin[:, None] * ly,
                self.cy[:, None] + self.sin[:, None] * lx + self.cos[:, None] * ly,
                np.where(np.arange(8) < 4, self.z0[:, None], self.z1[:, None]),
            ],
            axis=-1,
        )  # (B, 8, 3)
        pc = (corners - cam) @ r  # camera frame
        # Box edges crossing the near plane contribute their crossing points.
        ea = np.array([0, 1, 2, 3, 4, 5, 6, 7, 0, 1, 2, 3])
        eb = np.array([1, 2, 3, 0, 5, 6, 7, 4, 4, 5, 6, 7])
        za, zb = pc[:, ea, 2], pc[:, eb, 2]
        cross = (za - near) * (zb - near) < 0
        f = np.where(cross, (near - za) / np.where(cross, zb - za, 1.0), 0.0)
        pe = pc[:, ea] + f[..., None] * (pc[:, eb] - pc[:, ea])
        pe[~cross] = np.nan
        pts = np.concatenate([np.where((pc[..., 2:] >= near), pc, np.nan), pe], axis=1)
        with np.errstate(invalid="ignore"):
            u = fx * pts[..., 0] / pts[..., 2] + cx
            v = fy * pts[..., 1] / pts[..., 2] + cy
            zmin = np.nanmin(np.where(np.isnan(pts[..., 2]), np.inf, pts[..., 2]), axis=1)
        visible = np.isfinite(zmin) & (zmin <= t_max)
        u = np.where(np.isnan(u), np.nan, np.clip(u, -1e6, 1e6))
        v = np.where(np.isnan(v), np.nan, np.clip(v, -1e6, 1e6))
        u_lo = np.where(visible, np.nanmin(np.where(visible[:, None], u, 0.0), axis=1), 1.0)
        u_hi = np.where(visible, np.nanmax(np.where(visible[:, None], u, 0.0), axis=1), 0.0)
        v_lo = np.where(visible, np.nanmin(np.where(visible[:, None], v, 0.0), axis=1), 1.0)
        v_hi = np.where(visible, np.nanmax(np.where(visible[:, None], v, 0.0), axis=1), 0.0)
        rect = np.stack(
            [
                np.clip(np.floor(u_lo), 0, width),
                np.clip(np.ceil(u_hi), -1, width - 1),
                np.clip(np.floor(v_lo), 0, height),
                np.clip(np.ceil(v_hi), -1, height - 1),
            ],
            axis=1,
        ).astype(int)
        rect[~visible] = (1, 0, 1, 0)
        empty = (rect[:, 0] > rect[:, 1]) | (rect[:, 2] > rect[:, 3])
        rect[empty] = (1, 0, 1, 0)
        return rect

    def depth_level(
        self,
        centre: np.ndarray,
        x_axis_xy: np.ndarray,
        z_axis_xy: np.ndarray,
        xn: np.ndarray,
        yn: np.ndarray,
        t_max: float,
        floor: bool = True,
    ) -> np.ndarray:
        """Z-depth image (H, W) float32 of a level camera; inf where nothing is hit
        within t_max.

        centre: camera position (3,); x_axis_xy / z_axis_xy: the optical x (right) and z
        (forward) axes, both horizontal unit 2-vectors; optical y points straight down.
        xn (W,) and yn (H,) are the normalised image coordinates (u − cx)/fx, (v − cy)/fy.
        """
        xn = np.asarray(xn, dtype=float)
        yn = np.asarray(yn, dtype=float)
        cam = np.asarray(centre, dtype=float)
        # Horizontal part of every column's ray per unit z-depth: (W, 2).
        hd = xn[:, None] * np.asarray(x_axis_xy, float) + np.asarray(z_axis_xy, float)
        depth = np.full((len(xn), len(yn)), np.inf, dtype=np.float32)
        if len(self):
            keep = self._in_level_view(cam, x_axis_xy, z_axis_xy, xn, hd, t_max)
            if len(keep):
                cols, kk, t_in, t_out = self._column_spans(cam, hd, keep, t_max)
                if len(cols):
                    hit_cols, nearest = self._column_depths(
                        cam, yn, keep, cols, kk, t_in, t_out, t_max
                    )
                    depth[hit_cols] = nearest
        if floor:
            t_floor = _floor_depth(cam[2], -yn, t_max).astype(np.float32)
            np.minimum(depth, t_floor[None, :], out=depth)
        return depth.T

    def _in_level_view(
        self,
        cam: np.ndarray,
        x_axis_xy: np.ndarray,
        z_axis_xy: np.ndarray,
        xn: np.ndarray,
        hd: np.ndarray,
        t_max: float,
    ) -> np.ndarray:
        """Indices of the boxes a level camera can see: within reach of its longest ray
        (hd: the columns' horizontal ray parts) and not entirely outside the horizontal
        field of view."""
        rx, ry = self.cx - cam[0], self.cy - cam[1]
        dist = np.hypot(rx, ry)
        ray_len = np.hypot(hd[:, 0], hd[:, 1])
        fwd = rx * z_axis_xy[0] + ry * z_axis_xy[1]
        side = rx * x_axis_xy[0] + ry * x_axis_xy[1]
        # A box is outside the view when it is entirely behind the left edge plane or
        # entirely behind the right edge plane (planes through the camera, vertical).
        nl = np.array([1.0, -xn[0]]) / np.hypot(1.0, xn[0])  # (side, fwd) inward normals
        nr = np.array([-1.0, xn[-1]]) / np.hypot(1.0, xn[-1])
        inside_l = side * nl[0] + fwd * nl[1] >= -self.radius
        inside_r = side * nr[0] + fwd * nr[1] >= -self.radius
        return np.flatnonzero((dist - self.radius <= t_max * ray_len.max()) & inside_l & inside_r)

    def _column_spans(
        self, cam: np.ndarray, hd: np.ndarray, keep: np.ndarray, t_max: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The (column, box) pairs whose vertical ray plane crosses box keep[kk] in plan
        view within [0, t_max]: (cols, kk, t_in, t_out), sorted by column, with the
        z-depth interval of each crossing (the plan-view slab test, once per pair)."""
        rx, ry = self.cx[keep] - cam[0], self.cy[keep] - cam[1]
        c, s = self.cos[keep], self.sin[keep]
        lox = -(c * rx + s * ry)
        loy = s * rx - c * ry
        dlx = hd[:, :1] * c + hd[:, 1:2] * s  # (W, K)
        dly = -hd[:, :1] * s + hd[:, 1:2] * c
        tx0, tx1 = _slab(lox, dlx, self.hx[keep])
        ty0, ty1 = _slab(loy, dly, self.hy[keep])
        t_in, t_out = np.maximum(tx0, ty0), np.minimum(tx1, ty1)
        pair = (t_out >= 0.0) & (t_in <= t_out) & (t_in <= t_max)
        cols, kk = np.nonzero(pair)  # row-major: sorted by column
        return cols, kk, t_in[cols, kk], t_out[cols, kk]

    def _column_depths(
        self,
        cam: np.ndarray,
        yn: np.ndarray,
        keep: np.ndarray,
        cols: np.ndarray,
        kk: np.ndarray,
        t_in: np.ndarray,
        t_out: np.ndarray,
        t_max: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(columns, (C, H) float32 nearest hits) of the pairs from `_column_spans`: per
        row, the plan-view interval intersected with the one in which the ray's height is
        within the box's [z0, z1], the nearest over each column's boxes (inf if none)."""
        # Height along a ray of row v: cam_z − yn[v]·t must lie in [z0, z1].
        inv = (-1.0 / _nonzero(yn)).astype(np.float32)  # (H,)
        za = (self.z0[keep] - cam[2]).astype(np.float32)[:, None] * inv
        zb = (self.z1[keep] - cam[2]).astype(np.float32)[:, None] * inv
        zlo, zhi = np.minimum(za, zb), np.maximum(za, zb)  # (K, H)
        tin = np.maximum(t_in, 0.0).astype(np.float32)[:, None]
        tout = np.minimum(t_out, t_max).astype(np.float32)[:, None]
        t_hit = np.maximum(zlo[kk], tin)
        t_hit[t_hit > np.minimum(zhi[kk], tout)] = np.inf
        starts = np.flatnonzero(np.r_[True, cols[1:] != cols[:-1]])
        return cols[starts], np.minimum.reduceat(t_hit, starts, axis=0)
