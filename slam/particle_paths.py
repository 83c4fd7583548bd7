"""Particle genealogies: each particle's whole path, read back through resampling.

A particle filter over paths (FastSLAM) carries, in every particle, one hypothesis of
the whole trajectory; resampling copies some particles' pasts and drops others'. Keeping
periodic snapshots of the particles' poses and every resampling's parent indices lets
the path of any current particle be read back: walk the events from the newest to the
oldest, replacing each particle index by its parent at each resampling, and take its
pose at each snapshot. Weighting the current particles' paths by their weights gives the
smoothed (fixed-interval) path estimate of the filter, which unlike the filtered mean
does not jump when weights shift: old snapshots converge to one common ancestor.
"""

from __future__ import annotations

import math

import numpy as np

from slam.trajectory import Trajectory


def path_end(
    times: np.ndarray, rows: np.ndarray, t_now: float
) -> tuple[np.ndarray, np.ndarray, float]:
    """Where a path read from the snapshots ends with the current poses: at t_now (the
    last odometry message), or at the last snapshot's time if that is later (an
    observation after the last odometry message). Returns the snapshots before the end,
    their rows, and the end's time (a snapshot at the end is left out: the current poses
    take its place)."""
    if len(times):
        t_now = max(t_now, float(times[-1]))
        if times[-1] >= t_now:
            times, rows = times[:-1], rows[:-1]
    return times, rows, t_now


class ParticlePaths:
    """Snapshots of particle poses (float32, at most one per `every_s` seconds) and the
    resampling events between them. replace_same_time=False keeps every snapshot of one
    time, in order (for per-particle values that add up rather than replace one another,
    such as grid-rbpf's corrections)."""

    def __init__(self, every_s: float, replace_same_time: bool = True) -> None:
        if not every_s >= 0.0:
            raise ValueError(f"snapshot interval must be >= 0 s, got {every_s}")
        self.every_s = float(every_s)
        self.replace_same_time = replace_same_time
        self._events: list[tuple[float, np.ndarray] | np.ndarray] = []  # snapshot | parents
        self._last_t = -math.inf
        self._last_snapshot = -1  # its index in _events
        self.snapshots = 0

    def snapshot(self, t: float, poses: np.ndarray) -> None:
        """Keep the poses (N×3) at time t if `every_s` has passed since the last one; at
        the time of the last one, they replace it (an observation at the time of an
        odometry message corrects the poses there), unless replace_same_time is False."""
        if t == self._last_t and self.replace_same_time:
            del self._events[self._last_snapshot]  # resamplings after it stay, before the new one
            self.snapshots -= 1
        elif t - self._last_t < self.every_s or t < self._last_t:
            return
        self._last_snapshot = len(self._events)
        self._events.append((float(t), np.asarray(poses, dtype=np.float32).copy()))
        self._last_t = float(t)
        self.snapshots += 1

    def resampled(self, parents: np.ndarray) -> None:
        """The new particle k is a copy of the old particle parents[k]."""
        self._events.append(np.asarray(parents, dtype=np.intp).copy())

    def paths(self, current: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(times (T,), poses (T, N, 3)) of the ancestors of the current particles at every
        snapshot, oldest first."""
        n = len(current)
        idx = np.arange(n)
        times: list[float] = []
        poses: list[np.ndarray] = []
        for event in reversed(self._events):
            if isinstance(event, tuple):
                t, snap = event
                if len(snap) != n:
                    raise ValueError("particle count changed between snapshots")
                times.append(t)
                poses.append(snap[idx])
            else:
                idx = event[idx]
        if not times:
            return np.empty(0), np.empty((0, n, 3))
        return np.array(times[::-1]), np.array(poses[::-1], dtype=float)

    def mean_path(self, weights: np.ndarray, t_now: float, poses_now: np.ndarray) -> Trajectory:
        """The weighted mean of the current particles' paths (circular mean of θ), ending
        with their current poses (`path_end`)."""
        w = np.asarray(weights, dtype=float)
        times, paths, t_now = path_end(*self.paths(poses_now), t_now)
        times = np.append(times, t_now)
        paths = np.concatenate([paths, np.asarray(poses_now, dtype=float)[None]])
        xy = np.einsum("n,tnk->tk", w, paths[:, :, :2])
        th = np.arctan2(np.sin(paths[:, :, 2]) @ w, np.cos(paths[:, :, 2]) @ w)
        return Trajectory(times, np.column_stack([xy, th]))
