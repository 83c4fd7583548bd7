"""How sharp a laser map is at a trajectory's poses: a map-quality measure that needs no
ground truth.

Every scan's hits are placed at the trajectory's pose for that scan, all in one cloud.
Around each evaluated point, the hits of every scan within `radius_m` give a 2 × 2
covariance Σ. On a wall its smaller eigenvalue λ is the spread across the wall: the
range noise where the scans agree, and more where a wall was seen twice from poses that
disagree (a doubled wall d apart spreads by about d / 2). Reported:

- wall_spread_median_m: the median of √λ over the evaluated points;
- wall_spread_rms_m: √(mean λ);
- map_entropy: the mean of ½ ln det(2πe Σ), the mean map entropy of Droeschel and
  Behnke's registration studies (lower is sharper).

The same scans at two trajectories (a localizer's and a reference's, e.g. GMapping's
corrected poses) compare the two without taking either as truth: where they disagree,
the one with the thinner walls placed the scans more consistently.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit

from hardware.geometry import transform_points
from slam.trajectory import Trajectory


@dataclass(frozen=True)
class SharpnessConfig:
    """radius_m: the neighbourhood of a point [m] (a doubled wall is seen when its two
    copies are closer than this); min_neighbours: points with fewer hits within the
    radius (themselves included) are not evaluated; max_points: at most this many
    points are evaluated, an even stride through the cloud (all of it is searched)."""

    radius_m: float = 0.25
    min_neighbours: int = 8
    max_points: int = 200_000

    def __post_init__(self) -> None:
        if not self.radius_m > 0:
            raise ValueError(f"radius_m must be > 0, got {self.radius_m}")
        if self.min_neighbours < 3:
            raise ValueError(f"min_neighbours must be >= 3, got {self.min_neighbours}")
        if self.max_points < 1:
            raise ValueError(f"max_points must be >= 1, got {self.max_points}")


def place_hits(hits: Sequence[np.ndarray], poses: np.ndarray) -> np.ndarray:
    """One world cloud (N×2) of per-scan hits (each K×2, walker frame) at `poses` (S×3)."""
    poses = np.asarray(poses, dtype=float)
    if poses.shape != (len(hits), 3):
        raise ValueError(f"need one pose (x, y, θ) per scan: {len(hits)} scans, {poses.shape}")
    placed = [
        transform_points(p, np.asarray(h, dtype=float)) for h, p in zip(hits, poses, strict=True)
    ]
    return np.concatenate(placed) if placed else np.zeros((0, 2))


@dataclass(frozen=True, eq=False)
class LocalSpread:
    """Per evaluated point of a cloud: where it is (M×2), the spread across the wall
    around it (√λ, M) and the log-determinant of its neighbourhood's covariance (M);
    `points`, how many finite points the cloud had."""

    xy: np.ndarray
    spread_m: np.ndarray
    logdet: np.ndarray
    points: int


def local_spread(cloud: np.ndarray, config: SharpnessConfig | None = None) -> LocalSpread:
    """The spread around each evaluated point of a world cloud (N×2; module doc): at
    most config.max_points of them, an even stride through the cloud, those with
    min_neighbours within the radius."""
    cfg = config or SharpnessConfig()
    cloud = np.asarray(cloud, dtype=float).reshape(-1, 2)
    finite = cloud[np.all(np.isfinite(cloud), axis=1)]
    if len(finite) == 0:
        return LocalSpread(np.zeros((0, 2)), np.zeros(0), np.zeros(0), 0)
    cells = np.floor(finite / cfg.radius_m).astype(np.int64)
    lo = cells.min(axis=0) - 1
    span_y = int(cells[:, 1].max() - lo[1]) + 2
    keys = (cells[:, 0] - lo[0]) * span_y + (cells[:, 1] - lo[1])
    order = np.argsort(keys, kind="stable")
    stride = max(1, math.ceil(len(finite) / cfg.max_points))
    queries = finite[::stride]
    lam, logdet, ok = _spreads(
        finite[order], keys[order], queries, keys[::stride], span_y, cfg.radius_m,
        cfg.min_neighbours,
    )  # fmt: skip
    return LocalSpread(queries[ok], np.sqrt(lam[ok]), logdet[ok], len(finite))


def summary(local: LocalSpread) -> dict[str, float]:
    """Wall spread (median, rms) and map entropy of a cloud's local spreads (module doc);
    NaN when no point was evaluated."""
    spread, n = local.spread_m, len(local.spread_m)
    return {
        "wall_spread_median_m": float(np.median(spread)) if n else math.nan,
        "wall_spread_rms_m": float(math.sqrt(np.mean(spread**2))) if n else math.nan,
        "map_entropy": (
            float(np.mean(math.log(2.0 * math.pi * math.e) + 0.5 * local.logdet)) if n else math.nan
        ),
        "points": local.points,
        "evaluated": n,
    }


def sharpness(cloud: np.ndarray, config: SharpnessConfig | None = None) -> dict[str, float]:
    """Wall spread and map entropy of a world cloud (N×2; module doc). NaN when no
    point has min_neighbours within the radius."""
    return summary(local_spread(cloud, config))


def trajectory_sharpness(
    hits: Sequence[np.ndarray], poses: np.ndarray, config: SharpnessConfig | None = None
) -> dict[str, float]:
    """`sharpness` of the scans' hits placed at `poses` (one per scan)."""
    return sharpness(place_hits(hits, poses), config)


# the scales a replay reports: 25 cm (pose noise; walls doubled up to ~25 cm apart) and
# 50 cm (decimetre offsets, e.g. a revisit's walls where a loop was not closed)
SCALES = (SharpnessConfig(), SharpnessConfig(radius_m=0.5))


@dataclass(frozen=True, eq=False)
class ScanClouds:
    """A replay's scan hits placed at the estimate's poses and, when there is one, at
    the reference's, over the same scans (those with a reference pose)."""

    estimated: np.ndarray
    reference: np.ndarray | None
    scans: int


def scan_clouds(
    t: np.ndarray, hits: Sequence[np.ndarray], estimate: Trajectory, truth: np.ndarray | None
) -> ScanClouds:
    """The scans (times t, hits) at the estimate's poses and, where `truth` (S×3, NaN
    rows where none) has poses, at those too — then both over just those scans, so the
    two compare."""
    t = np.asarray(t, dtype=float)
    keep = np.ones(len(t), dtype=bool)
    if truth is not None and len(t):
        truth = np.asarray(truth, dtype=float).reshape(len(t), 3)
        keep = np.all(np.isfinite(truth), axis=1)
    if not keep.any():  # no reference pose at all: the estimate over every scan
        keep, truth = np.ones(len(t), dtype=bool), None
    kept = [h for h, k in zip(hits, keep, strict=True) if k]
    reference = None if truth is None else place_hits(kept, truth[keep])
    return ScanClouds(place_hits(kept, estimate.interpolate(t[keep])), reference, len(kept))


@dataclass(frozen=True, eq=False)
class ScanSharpness:
    """A replay's scan clouds' local spreads at each of `scales` (the estimate's, and the
    reference's when there is one): computed once, for the metrics and the figure."""

    scans: int
    scales: tuple[SharpnessConfig, ...]
    estimated: list[LocalSpread]
    reference: list[LocalSpread] | None

    def metrics(self) -> dict[str, Any]:
        """{"radius_m": [...], "estimated": [a `summary` per scale], "reference": [...]
        (with a reference), "scans", "note"}."""
        out: dict[str, Any] = {
            "note": "the scans' hits at the poses; lower wall spread and entropy: a sharper map",
            "scans": self.scans,
            "radius_m": [c.radius_m for c in self.scales],
            "estimated": [summary(local) for local in self.estimated],
        }
        if self.reference is not None:
            out["reference"] = [summary(local) for local in self.reference]
        return out


def scan_sharpness(clouds: ScanClouds, scales: Sequence[SharpnessConfig] = SCALES) -> ScanSharpness:
    """The local spreads of both clouds at each scale."""
    scales = tuple(scales)
    reference = None
    if clouds.reference is not None:
        reference = [local_spread(clouds.reference, c) for c in scales]
    estimated = [local_spread(clouds.estimated, c) for c in scales]
    return ScanSharpness(clouds.scans, scales, estimated, reference)


@njit(cache=True)
def _first_at_least(keys: np.ndarray, key: int) -> int:
    lo, hi = 0, len(keys)
    while lo < hi:
        mid = (lo + hi) // 2
        if keys[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True)
def _spreads(pts, keys, queries, q_keys, span_y, radius, min_n):
    """Per query: the smaller eigenvalue and log-determinant of the covariance of the
    points within `radius` (the 3 × 3 cells of side `radius` around it), and whether
    it had min_n of them."""
    n = len(queries)
    lam = np.zeros(n)
    logdet = np.zeros(n)
    ok = np.zeros(n, dtype=np.bool_)
    r2 = radius * radius
    for i in range(n):
        qx, qy = queries[i, 0], queries[i, 1]
        count, sx, sy, sxx, sxy, syy = 0, 0.0, 0.0, 0.0, 0.0, 0.0
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                key = q_keys[i] + dx * span_y + dy
                j = _first_at_least(keys, key)
                while j < len(keys) and keys[j] == key:
                    ex, ey = pts[j, 0] - qx, pts[j, 1] - qy
                    if ex * ex + ey * ey <= r2:
                        count += 1
                        sx += ex
                        sy += ey
                        sxx += ex * ex
                        sxy += ex * ey
                        syy += ey * ey
                    j += 1
        if count < min_n:
            continue
        mx, my = sx / count, sy / count
        a = sxx / count - mx * mx
        b = sxy / count - mx * my
        c = syy / count - my * my
        half = 0.5 * (a + c)
        root = math.sqrt(max(0.25 * (a - c) * (a - c) + b * b, 0.0))
        lam[i] = max(half - root, 0.0)
        logdet[i] = math.log(max(a * c - b * b, 1e-16))
        ok[i] = True
    return lam, logdet, ok
