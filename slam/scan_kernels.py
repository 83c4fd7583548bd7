"""Compiled inner loop of the scan matcher's correlative search (numba).

`grid_scores` scores every translation of a rotated query on the likelihood field: for
each point and each (row, column) offset one lookup. numpy does it as one gather into a
(points × rows × columns) temporary and a mean over the points, tens of MB for a wide
window; here the sum runs point by point into the (rows × columns) result, in the same
order as numpy's reduction over the first axis, so the scores are the same to the bit
(but for a single offset, where numpy sums the one column pairwise: within 1e-16).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def grid_scores(
    flat: np.ndarray,
    height: int,
    width: int,
    cells: np.ndarray,
    x_offs: np.ndarray,
    y_offs: np.ndarray,
) -> np.ndarray:
    """Mean over the points of a flattened field (height × width) at their cells (n, 2:
    column, row) shifted by every (y, x) cell offset: (len(y_offs), len(x_offs));
    lookups outside the field are clipped to its border."""
    n = cells.shape[0]
    ny, nx = len(y_offs), len(x_offs)
    out = np.zeros((ny, nx))
    cols = np.empty(nx, np.int64)
    for k in range(n):
        for b in range(nx):
            cols[b] = min(max(cells[k, 0] + x_offs[b], 0), width - 1)
        for a in range(ny):
            base = min(max(cells[k, 1] + y_offs[a], 0), height - 1) * width
            row = out[a]
            for b in range(nx):
                row[b] += flat[base + cols[b]]
    return out / n
