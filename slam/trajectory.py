"""Timestamped planar trajectories, interpolation and TUM file I/O."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hardware.geometry import wrap_angle


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Poses (N×3, x y θ) at strictly increasing times t (N,)."""

    t: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        t = np.asarray(self.t, dtype=float)
        p = np.asarray(self.poses, dtype=float).reshape(-1, 3)
        if t.shape != (len(p),):
            raise ValueError(f"trajectory has {len(t)} times but {len(p)} poses")
        if len(t) > 1 and np.any(np.diff(t) <= 0):
            raise ValueError("trajectory times must be strictly increasing")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "poses", p)

    def __len__(self) -> int:
        return len(self.t)

    def interpolate(self, times: np.ndarray) -> np.ndarray:
        """Poses at `times` (linear in x, y and in unwrapped θ); clamps outside the span."""
        times = np.asarray(times, dtype=float)
        if len(self) == 0:
            raise ValueError("cannot interpolate an empty trajectory")
        th = np.unwrap(self.poses[:, 2])
        x = np.interp(times, self.t, self.poses[:, 0])
        y = np.interp(times, self.t, self.poses[:, 1])
        return np.column_stack([x, y, wrap_angle(np.interp(times, self.t, th))])

    def write_tum(self, path: str | Path) -> None:
        """TUM format: `t x y z qx qy qz qw`, one pose a line (readable by evo)."""
        half = self.poses[:, 2] / 2.0
        rows = np.column_stack(
            [
                self.t,
                self.poses[:, 0],
                self.poses[:, 1],
                np.zeros(len(self)),
                np.zeros(len(self)),
                np.zeros(len(self)),
                np.sin(half),
                np.cos(half),
            ]
        )
        np.savetxt(path, rows, fmt="%.9f", header="timestamp x y z qx qy qz qw")

    @classmethod
    def read_tum(cls, path: str | Path) -> Trajectory:
        rows = np.loadtxt(path, comments="#", ndmin=2)
        if rows.shape[1] != 8:
            raise ValueError(f"{path}: a TUM file has 8 columns, found {rows.shape[1]}")
        qx, qy, qz, qw = rows[:, 4], rows[:, 5], rows[:, 6], rows[:, 7]
        yaw = np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
        return cls(rows[:, 0], np.column_stack([rows[:, 1], rows[:, 2], yaw]))


class TrajectoryRecorder:
    """A localizer's pose history: one pose per time, the newest estimate at each time.

    `record(t, pose)` appends at a later time, replaces the last pose at the same time and
    ignores an earlier time; `amend(pose)` replaces the last pose (after a measurement
    update between two odometry messages).
    """

    def __init__(self) -> None:
        self._times: list[float] = []
        self._poses: list = []

    def __len__(self) -> int:
        return len(self._times)

    @property
    def last_t(self) -> float:
        return self._times[-1] if self._times else float("nan")

    def record(self, t: float, pose) -> None:
        if self._times and t <= self._times[-1]:
            if t == self._times[-1]:
                self._poses[-1] = pose
            return
        self._times.append(t)
        self._poses.append(pose)

    def amend(self, pose) -> None:
        if self._poses:
            self._poses[-1] = pose

    def trajectory(self) -> Trajectory:
        poses = np.array(self._poses, dtype=float).reshape(-1, 3)
        return Trajectory(np.array(self._times), poses)


def spread_corrections(
    path: np.ndarray, corrections: np.ndarray, accumulated: np.ndarray, totals: np.ndarray
) -> np.ndarray:
    """`path` (N, 3) with the correction each pose is heading towards (N, 3: world x, y,
    θ; the move that the next observation made to the odometry's prediction) spread
    back over the odometry that accumulated it: + f·δ, f the odometry variance
    accumulated by that pose over the stretch's total (N, 2 each: x + y, θ), clipped to
    [0, 1] and 0 where nothing accumulated. The mean of a random walk's path given its
    end point (a Brownian bridge), per axis; used by the smoothers that place
    observations only at some of the times a path is read at (slam.grid_rbpf,
    slam.gtsam_smoother)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        f = np.clip(np.nan_to_num(accumulated / totals), 0.0, 1.0)
    out = path.copy()
    out[:, 0] += f[:, 0] * corrections[:, 0]
    out[:, 1] += f[:, 0] * corrections[:, 1]
    out[:, 2] = wrap_angle(out[:, 2] + f[:, 1] * corrections[:, 2])
    return out
