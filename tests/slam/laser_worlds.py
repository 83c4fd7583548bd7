"""Synthetic laser worlds for the scan-based localizer tests: rooms of wall segments, a
ray-cast laser scan, and a drive around a room with biased odometry."""

from __future__ import annotations

import math

import numpy as np

from hardware.geometry import wrap_angle
from hardware.messages import LaserScan, VelocityOdometry
from slam.trajectory import Trajectory


def box_walls(x0, y0, x1, y1):
    """The four walls (x0, y0, x1, y1 segments) of an axis-aligned box."""
    c = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    return [(*c[i], *c[(i + 1) % 4]) for i in range(4)]


# A 10 × 8 m room with a pillar, a cabinet and a wall stub: no symmetry to alias on.
ROOM = np.array(
    box_walls(0, 0, 10, 8)
    + box_walls(3.0, 3.0, 3.6, 3.6)
    + box_walls(7.0, 5.5, 8.5, 6.2)
    + [(6.0, 0.0, 6.0, 2.0)]
    + box_walls(1.0, 6.0, 1.4, 7.2)
)
# A different place: a long narrow hall with a few alcoves.
HALL = np.array(
    box_walls(0, 0, 14, 3)
    + box_walls(4.0, 2.4, 4.3, 3.0)
    + box_walls(9.0, 0.0, 9.6, 0.5)
    + [(12.0, 3.0, 12.0, 2.2)]
)


def render_scan(
    world: np.ndarray,
    pose,
    t: float = 0.0,
    beams: int = 361,
    fov: float = math.radians(270.0),
    range_max: float = 30.0,
    noise_m: float = 0.0,
    rng: np.random.Generator | None = None,
) -> LaserScan:
    """A laser scan from the walker pose (x, y, θ): each beam's nearest wall hit."""
    x, y, th = pose
    a = -0.5 * fov + np.arange(beams) * fov / (beams - 1)
    d = np.stack([np.cos(th + a), np.sin(th + a)], axis=1)  # (B, 2)
    p, q = world[:, :2], world[:, 2:]
    e = q - p  # (S, 2)
    # o + t d = p + u e  →  solve for t, u per beam and segment
    w = p[None] - np.array([x, y])[None, None]  # (1, S, 2)
    den = d[:, None, 0] * -e[None, :, 1] - d[:, None, 1] * -e[None, :, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_hit = (w[..., 0] * -e[None, :, 1] - w[..., 1] * -e[None, :, 0]) / den
        u = (d[:, None, 0] * w[..., 1] - d[:, None, 1] * w[..., 0]) / den
    ok = np.isfinite(t_hit) & (t_hit > 1e-9) & (u >= 0) & (u <= 1)
    r = np.where(ok, t_hit, np.inf).min(axis=1)
    if noise_m > 0:
        r = r + (rng or np.random.default_rng(0)).normal(0.0, noise_m, r.shape)
    r = np.where(np.isfinite(r) & (r < range_max), r, range_max)
    return LaserScan(t, float(a[0]), float(a[1] - a[0]), r.astype(np.float32), range_max)


def loop_messages(laps: int = 2, seed: int = 5):
    """Drive twice around the room (1.5 m from its walls) at 0.5 m/s; velocity odometry
    at 10 Hz with a 4 % speed error and a 0.03 rad/s yaw-rate bias; a 270° laser scan
    (1 cm noise, drawn with `seed`) every 0.5 s. Returns messages and the true
    trajectory."""
    corners = np.array([(1.5, 1.5), (8.5, 1.5), (8.5, 4.2), (5.0, 4.2), (5.0, 6.5), (1.5, 6.5)])
    return drive_messages(ROOM, np.vstack([corners] * laps + [corners[:1]]), seed=seed)


def without_odometry(msgs) -> list:
    """The laser scans of `msgs`, each after one velocity odometry of NaN at its time
    (the motion since the last unknown): a log without odometry, as orebro's is."""
    out = []
    for m in msgs:
        if isinstance(m, LaserScan):
            out += [VelocityOdometry(m.t, math.nan, math.nan), m]
    return out


def drive_messages(
    world: np.ndarray,
    path: np.ndarray,
    seed: int = 5,
    fov: float = math.radians(270.0),
    speed_error: float = 0.04,
    yaw_bias: float = 0.03,
):
    """Drive through `world` along the corners of `path` (turning in place at each, the
    first facing the second) at 0.5 m/s; velocity odometry at 10 Hz with a speed error
    (a fraction) and a yaw-rate bias [rad/s]; a laser scan of `fov` (1 cm noise, drawn
    with `seed`) every 0.5 s. Returns messages and the true trajectory."""
    rng = np.random.default_rng(seed)
    dt, v, w_turn = 0.1, 0.5, 0.8
    d0 = path[1] - path[0]
    pose = np.array([*path[0], math.atan2(d0[1], d0[0])])
    t = 0.0
    msgs, truth = [], [(t, *pose)]
    last_scan = -1.0

    def emit(v_true, w_true):
        nonlocal pose, t, last_scan
        msgs.append(VelocityOdometry(t, (1 + speed_error) * v_true, w_true + yaw_bias))
        if t - last_scan >= 0.5 - 1e-9:
            msgs.append(render_scan(world, pose, t=t, fov=fov, noise_m=0.01, rng=rng))
            last_scan = t
        h = pose[2] + 0.5 * w_true * dt
        pose = np.array(
            [
                pose[0] + v_true * dt * math.cos(h),
                pose[1] + v_true * dt * math.sin(h),
                wrap_angle(pose[2] + w_true * dt),
            ]
        )
        t = round(t + dt, 6)
        truth.append((t, *pose))

    for target in path[1:]:
        d = target - pose[:2]
        heading = math.atan2(d[1], d[0])
        while abs(wrap_angle(heading - pose[2])) > 1e-6:
            turn = wrap_angle(heading - pose[2])
            emit(0.0, math.copysign(min(w_turn, abs(turn) / dt), turn))
        while (dist := float(np.hypot(*(target - pose[:2])))) > 1e-6:
            emit(min(v, dist / dt), 0.0)
    msgs.append(VelocityOdometry(t, 0.0, 0.0))
    tr = np.array(truth)
    return msgs, Trajectory(tr[:, 0], tr[:, 1:])
