"""Real laser data: the Intel Research Lab log with its GMapping-corrected poses.

Maps built from the even and from the odd scans (455 each, same poses source) must agree:
of the cells occupied in either map, at least 90 % must be occupied in the other map
within one cell (its 3×3 neighbourhood). The full map's walls must be thin: fewer than
15 % of its occupied cells may belong to a fully occupied 3×3 block (a wall ≥ 3 cells,
15 cm, thick).
"""

from __future__ import annotations

import numpy as np
import pytest
from carmen_flaser import DATA, read_flaser
from scipy.ndimage import binary_dilation, binary_opening

from mapping.grid import GridExtent
from mapping.mapper import OccupancyMapper

INTEL = DATA / "intel_lab" / "intel.gfs.log.gz"
NO_RETURN_M = 81.83  # readings >= 81.83 m are "no return" (SOURCE.md)

pytestmark = [
    pytest.mark.data,
    pytest.mark.skipif(not INTEL.exists(), reason=f"Intel lab log not found at {INTEL}"),
]


@pytest.fixture(scope="module")
def intel():
    return read_flaser(INTEL, NO_RETURN_M)


def build(scans, poses, indices) -> GridExtent:
    mapper = OccupancyMapper()
    for i in indices:
        mapper.integrate_scan(scans[i], poses[i])
    return mapper.grid


def on_common_lattice(a: GridExtent, b: GridExtent) -> tuple[np.ndarray, np.ndarray]:
    """The two grids' occupied masks on one array covering both (same world lattice)."""
    offsets = np.array([a.lattice_offset, b.lattice_offset])
    ends = offsets + np.array([a.shape[::-1], b.shape[::-1]])
    lo, hi = offsets.min(axis=0), ends.max(axis=0)
    out = []
    for g, off in ((a, offsets[0]), (b, offsets[1])):
        m = np.zeros((hi[1] - lo[1], hi[0] - lo[0]), dtype=bool)
        i, j = off - lo
        m[j : j + g.shape[0], i : i + g.shape[1]] = g.occupied()
        out.append(m)
    return out[0], out[1]


def test_odd_and_even_scans_give_the_same_map(intel):
    scans, poses = intel
    assert len(scans) == 910 and len(scans[0].ranges) == 180
    even, odd = on_common_lattice(
        build(scans, poses, range(0, len(scans), 2)), build(scans, poses, range(1, len(scans), 2))
    )
    assert even.sum() > 8000 and odd.sum() > 8000
    near = np.ones((3, 3), dtype=bool)
    agree = (even & binary_dilation(odd, near)) | (odd & binary_dilation(even, near))
    agreement = agree.sum() / (even | odd).sum()
    assert agreement >= 0.90  # measured 0.955


def test_intel_walls_are_thin(intel, tmp_path):
    scans, poses = intel
    grid = build(scans, poses, range(len(scans)))
    occ = grid.occupied()
    thick = binary_opening(occ, np.ones((3, 3), dtype=bool))
    assert occ.sum() > 10000
    assert thick[occ].mean() < 0.15  # measured 0.067
    # The lab is about 30 m × 30 m: the occupied cells span that, not more.
    xy = grid.occupied_xy()
    span = np.percentile(xy, 99.5, axis=0) - np.percentile(xy, 0.5, axis=0)
    assert np.all((span > 20.0) & (span < 40.0))
