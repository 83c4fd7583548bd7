"""Which old scans saw what a new scan sees: coarse footprints and their overlap.

A scan's footprint is the set of `cell_m` cells its points fall in (in its own frame,
as cell centres). Placed at their poses, the share of the new scan's cells that an old
scan's cells cover is their overlap. A loop-closure submap chosen by overlap holds the
old scans that faced the same walls, where one chosen by time holds the scans that
stood nearby: on a revisit driven the other way those faced the other way (a forward
180° laser), and a match against them has little to hold on to (BENCHMARKS.md, "Laser
logs: loop submaps of the scans that saw the same walls").
"""

from __future__ import annotations

import math

import numpy as np

from hardware.geometry import transform_points


def footprint(points: np.ndarray, cell_m: float) -> np.ndarray:
    """The centres of the cell_m cells the N×2 points fall in (K×2, K ≤ N)."""
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    cells = np.unique(np.floor(pts / cell_m).astype(np.int64), axis=0)
    return (cells + 0.5) * cell_m


def _cell_id(x: np.ndarray, y: np.ndarray, cell_m: float) -> np.ndarray:
    """One int64 id per world point: the cell_m cell it falls in."""
    kx = np.floor(x / cell_m).astype(np.int64)
    ky = np.floor(y / cell_m).astype(np.int64)
    return (kx << 32) ^ (ky & 0xFFFFFFFF)


def _cell_ids(pose: np.ndarray, centres: np.ndarray, cell_m: float) -> np.ndarray:
    """The world cells (unique ids) of footprint centres placed at pose."""
    if len(centres) == 0:
        return np.zeros(0, dtype=np.int64)
    world = transform_points(pose, centres)
    return np.unique(_cell_id(world[:, 0], world[:, 1], cell_m))


def overlap(
    pose: np.ndarray,
    centres: np.ndarray,
    poses: np.ndarray,
    footprints: list[np.ndarray],
    cell_m: float,
) -> np.ndarray:
    """For each old footprint (placed at poses[i]): the share of the new footprint's
    cells (placed at `pose`) that it covers, in [0, 1]."""
    if len(poses) != len(footprints):
        raise ValueError(f"{len(poses)} poses for {len(footprints)} footprints")
    new = _cell_ids(pose, centres, cell_m)
    out = np.zeros(len(footprints))
    sizes = [len(fp) for fp in footprints]
    if len(new) == 0 or sum(sizes) == 0:
        return out
    pts = np.concatenate([fp for fp in footprints if len(fp)])
    owner = np.repeat(np.arange(len(footprints)), sizes)
    # each pose's cos and sin from math (as transform_points), the rest elementwise
    c = np.repeat([math.cos(float(p[2])) for p in poses], sizes)
    s = np.repeat([math.sin(float(p[2])) for p in poses], sizes)
    tx = np.repeat(np.asarray(poses, dtype=float)[:, 0], sizes)
    ty = np.repeat(np.asarray(poses, dtype=float)[:, 1], sizes)
    ids = _cell_id(
        (c * pts[:, 0] - s * pts[:, 1]) + tx, (s * pts[:, 0] + c * pts[:, 1]) + ty, cell_m
    )
    at = np.minimum(np.searchsorted(new, ids), len(new) - 1)
    hit = new[at] == ids
    # one count per (old scan, new cell), however many of its cells land there
    pairs = np.unique(owner[hit] * len(new) + at[hit])
    out += np.bincount(pairs // len(new), minlength=len(footprints))
    return out / len(new)


def chosen_by_overlap(shares: np.ndarray, anchor: int, span: int, count: int) -> list[int]:
    """The anchor and, of the indices within ± span of it (shares' positions), the
    count − 1 others with the highest shares (ties: nearest the anchor first), sorted."""
    lo, hi = max(0, anchor - span), min(len(shares), anchor + span + 1)
    others = [i for i in range(lo, hi) if i != anchor]
    others.sort(key=lambda i: (-shares[i], abs(i - anchor), i))
    return sorted([anchor, *others[: max(count - 1, 0)]])
