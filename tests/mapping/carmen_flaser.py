"""Minimal reader of FLASER lines in CARMEN logs (for mapping tests only).

`FLASER n r_1 … r_n x y θ odom_x odom_y odom_θ ipc_timestamp ipc_hostname logger_timestamp`;
in the SLAM-corrected logs x y θ is the corrected pose. The beams span 180° from −90°:
step 180°/n for n = 180 or 360, 180°/(n−1) for n = 181 or 361 (CARMEN convention).
"""

from __future__ import annotations

import gzip
import math
from pathlib import Path

import numpy as np

from hardware.messages import LaserScan

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"


def read_flaser(path: Path, range_max: float) -> tuple[list[LaserScan], np.ndarray]:
    """Scans (in file order) and their corrected poses (N×3) from a gzipped CARMEN log.

    Readings >= range_max are "no return" (LaserScan's convention).
    """
    scans, poses = [], []
    with gzip.open(path, "rt") as f:
        for line in f:
            tok = line.split()
            if not tok or tok[0] != "FLASER":
                continue
            n = int(tok[1])
            ranges = np.array(tok[2 : 2 + n], dtype=float)
            x, y, theta = (float(v) for v in tok[2 + n : 5 + n])
            step = math.pi / (n - 1 if n % 2 else n)
            t = float(tok[8 + n])
            scans.append(LaserScan(t, -math.pi / 2, step, ranges, range_max))
            poses.append((x, y, theta))
    return scans, np.array(poses).reshape(-1, 3)
