"""Floor-plane occupancy grids that grow (or roll) with the walker.

Two map models share one extent mechanism (`GridExtent`):

- `OccupancyGrid` (model "log-odds"): each frame adds l_occ to the cells holding
  obstacle points and l_free to the cells its rays crossed (sensor to end, end cell
  excluded when it holds an obstacle), each cell at most once per frame, clamped.
- `HitCentroidGrid` (model "log-odds-hits"): the log-odds grid that also keeps, per
  cell, the mean of the obstacle points it held (GMapping's cell model), which places a
  surface within its cell for a scan matcher (slam.grid_rbpf).
- `ViewCountGrid` (model "view-count", thesis §4.1): per cell, the number of frames in
  which it was in view and the number in which it held obstacle points; occupied when
  hits / views > 0.5. "In view" is the sensor's view wedge when the observation has one
  (depth camera: 0.8–4.15 m, ±half FOV), else the cells the rays reached. A cell that
  held points counts as in view too.

Cells and extent. Cells are 5 cm squares by default on a lattice anchored at the world
origin (cell boundaries at integer multiples of the resolution), so the same world point
always falls in the same lattice cell, however the array grows. Arrays are indexed
[iy, ix] with row 0 at the lowest y; `origin` is the world (x, y) of the lower-left corner
of cell [0, 0]. `world_to_cell` / `cell_to_world` use array indices (ix, iy), which stay
valid until the grid next grows or rolls.

The grid starts empty and grows when a frame reaches outside it, by at least
`grow_chunk_m` and at least a quarter of its current size on each side that needs it
(amortised O(1) copying per cell; at most about 1.5× the mapped extent per axis).

With `max_size_m` set, the grid never exceeds a square of that side: when a frame does
not fit together with what is already mapped, the grid *rolls* to a window of that side
centred on the walker, and whatever falls outside is dropped for good (the thesis
instead cleared its whole map every 100 steps). Choose max_size_m well above twice the
sensor's reach (e.g. ≥ 12 m for the Kinect's 3.5 m), or the grid rolls, copying
itself, on nearly every frame.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from functools import lru_cache
from typing import ClassVar

import numpy as np

from hardware.geometry import wrap_angle
from mapping.kernels import (
    accumulate_hits,
    floor_bounds,
    integrate_log_odds,
    mark_cells,
    mark_end_rays,
    place_frame,
    update_log_odds,
)
from mapping.lattice import as_points, cell_centres, cells_of
from mapping.observation import PlanarObservation, ViewWedge, WorldObservation, as_pose


class MapModel(StrEnum):
    LOG_ODDS = "log-odds"
    VIEW_COUNT = "view-count"
    LOG_ODDS_HITS = "log-odds-hits"


@dataclass(frozen=True)
class LogOddsConfig:
    """Log-odds increments and clamps (OctoMap's defaults).

    l_occ = logit(0.7) ≈ 0.85 per frame with a hit, l_free = logit(0.4) ≈ −0.41 per frame
    a ray crossed the cell; clamped to [l_min, l_max] = [logit(0.12), logit(0.97)] so
    that the map can still change its mind about a cell it has seen many times.
    """

    l_occ: float = 0.85
    l_free: float = -0.41
    l_min: float = -2.0
    l_max: float = 3.5

    def __post_init__(self) -> None:
        if not (self.l_free < 0.0 < self.l_occ and self.l_min < 0.0 < self.l_max):
            raise ValueError("need l_free < 0 < l_occ and l_min < 0 < l_max")


@dataclass(frozen=True)
class GridConfig:
    """resolution_m: cell side (0.05 m, as the thesis).
    model: "log-odds" or "view-count".
    log_odds: increments for the log-odds model.
    grow_chunk_m: least growth per side when a frame reaches outside the grid.
    max_size_m: side of the largest (square) grid before it rolls; None: unbounded.
    bundle_rays: trace one ray per bearing bin (see lattice.bundle_rays) instead of one
        per distinct end cell; same free space within half a cell, far fewer samples.
    """

    resolution_m: float = 0.05
    model: MapModel = MapModel.LOG_ODDS
    log_odds: LogOddsConfig = field(default_factory=LogOddsConfig)
    grow_chunk_m: float = 2.0
    max_size_m: float | None = None
    bundle_rays: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "model", MapModel(self.model))
        if self.resolution_m <= 0 or self.grow_chunk_m < 0:
            raise ValueError("resolution_m must be > 0 and grow_chunk_m >= 0")
        if self.max_size_m is not None and self.max_size_m < 2 * self.resolution_m:
            raise ValueError(f"max_size_m must be at least two cells, got {self.max_size_m}")


class GridExtent(ABC):
    """Extent bookkeeping, frame rasterisation and thresholds shared by the map models.

    Subclasses name their per-cell layers in LAYERS (all zero-initialised) and implement
    `_update` (one frame) and `probability`.
    """

    LAYERS: ClassVar[dict[str, type]]
    OCCUPIED_THRESHOLD: ClassVar[float]
    FREE_THRESHOLD: ClassVar[float]

    def __init__(self, config: GridConfig | None = None) -> None:
        self.config = config or GridConfig()
        self.reset()

    def copy(self) -> GridExtent:
        """An independent copy (same config, extent and layers)."""
        out = type(self)(self.config)
        out._offset = self._offset.copy()
        out._layers = {name: layer.copy() for name, layer in self._layers.items()}
        return out

    def reset(self) -> None:
        """Forget everything: an empty grid."""
        self._offset = np.zeros(2, dtype=np.int64)  # lattice (i, j) of array cell [0, 0]
        self._layers = {name: np.zeros((0, 0), dtype=dt) for name, dt in self.LAYERS.items()}

    def decay(self, factor: float) -> None:
        """Fade all evidence toward unknown by `factor` in (0, 1] (stale cells fade; cells
        seen again are renewed by the new evidence). Only the log-odds models can."""
        raise ValueError(f"{type(self).__name__} has no evidence that can decay")

    # --- geometry -----------------------------------------------------------------------
    @property
    def resolution(self) -> float:
        return self.config.resolution_m

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) = (ny, nx)."""
        return next(iter(self._layers.values())).shape

    @property
    def nbytes(self) -> int:
        """Bytes held by the layers."""
        return sum(layer.nbytes for layer in self._layers.values())

    @property
    def lattice_offset(self) -> tuple[int, int]:
        """World-lattice cell (i, j) of array cell [0, 0]; origin = offset · resolution."""
        return int(self._offset[0]), int(self._offset[1])

    @property
    def origin(self) -> tuple[float, float]:
        """World (x, y) of the lower-left corner of array cell [0, 0]."""
        return float(self._offset[0] * self.resolution), float(self._offset[1] * self.resolution)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) in world metres."""
        ox, oy = self.origin
        ny, nx = self.shape
        return ox, ox + nx * self.resolution, oy, oy + ny * self.resolution

    def world_to_cell(self, xy: np.ndarray) -> np.ndarray:
        """Array indices (ix, iy) (N×2 int64) of world points; may lie outside the array."""
        return cells_of(as_points(np.atleast_2d(xy), "xy"), self.resolution) - self._offset

    def cell_to_world(self, cells: np.ndarray) -> np.ndarray:
        """World centres (N×2) of array cells (ix, iy)."""
        return cell_centres(
            as_points(np.atleast_2d(cells), "cells") + self._offset, self.resolution
        )

    def layer(self, name: str) -> np.ndarray:
        """The (ny, nx) layer `name` (one of LAYERS; read it, do not write it)."""
        return self._layers[name]

    # --- what the map says --------------------------------------------------------------
    @abstractmethod
    def probability(self) -> np.ndarray:
        """Occupancy probability per cell, (ny, nx); 0.5 where nothing is known."""

    @abstractmethod
    def known(self) -> np.ndarray:
        """Boolean (ny, nx): cells with any evidence."""

    def occupied(self, threshold: float | None = None) -> np.ndarray:
        """Boolean (ny, nx): probability > threshold (default: the model's)."""
        thr = self.OCCUPIED_THRESHOLD if threshold is None else threshold
        return self.probability() > thr

    def free(self, threshold: float | None = None) -> np.ndarray:
        """Boolean (ny, nx): known cells with probability < threshold (default: the model's)."""
        thr = self.FREE_THRESHOLD if threshold is None else threshold
        return self.known() & (self.probability() < thr)

    def occupied_xy(self, threshold: float | None = None) -> np.ndarray:
        """World centres (N×2) of the occupied cells."""
        iy, ix = np.nonzero(self.occupied(threshold))
        return self.cell_to_world(np.column_stack([ix, iy]))

    def trinary(self) -> np.ndarray:
        """int8 (ny, nx): 1 occupied, 0 free, −1 unknown (default thresholds)."""
        out = np.full(self.shape, -1, dtype=np.int8)
        out[self.free()] = 0
        out[self.occupied()] = 1
        return out

    # --- integration --------------------------------------------------------------------
    def integrate(self, obs: WorldObservation, centre_xy: np.ndarray | None = None) -> None:
        """Add one frame. `centre_xy` (default: the sensor) centres the window when rolling."""
        res = self.resolution
        si, sj = (int(v) for v in np.floor(obs.sensor_xy / res).tolist())
        box = _Box(si, sj, si, sj)
        if len(obs.obstacles) or len(obs.ray_ends):
            box = box.union(_Box(*floor_bounds(obs.obstacles, obs.ray_ends, res)))
        for extra in self._extra_cells(obs):
            box = box.union(extra)
        # The part of the frame's box that the grid holds (all of it unless it rolled).
        window = self._fit(box, obs.sensor_xy if centre_xy is None else centre_xy)
        if window is None:
            return
        frame = _Frame(self, obs, box, window)
        rows, cols = window.slices(self._box())
        self._update({k: v[rows, cols] for k, v in self._layers.items()}, frame)

    def integrate_at(
        self, obs: PlanarObservation, pose: np.ndarray, centre_xy: np.ndarray | None = None
    ) -> None:
        """Add one walker-frame frame placed at the walker's `pose`: the same as
        `integrate(obs.in_world(pose), centre_xy)` (the log-odds models do it in one
        compiled call, mapping.kernels.integrate_log_odds, to the same cells and values)."""
        update = self.update_at(obs, pose, centre_xy)
        if update is not None:
            update()

    def update_at(
        self, obs: PlanarObservation, pose: np.ndarray, centre_xy: np.ndarray | None = None
    ) -> Callable[[], None] | None:
        """`integrate_at` in two steps: the grid grows (or rolls) for the frame now, and
        the returned call adds it (None: nothing to add). For the log-odds models that
        call is compiled code that releases the GIL, so the frames of several grids can
        be added on threads while the grids' memory is only ever allocated by the
        caller's thread."""
        world = obs.in_world(pose)
        return lambda: self.integrate(world, centre_xy)

    def _fit(self, box: _Box, centre_xy: np.ndarray) -> _Box | None:
        """Grow (or roll, centred on centre_xy) so that the frame's `box` fits, if it can;
        the part of it the grid then holds (None: nothing)."""
        if self.shape[0]:
            held = self._box()
            if held.i0 <= box.i0 and held.j0 <= box.j0 and box.i1 <= held.i1 and box.j1 <= held.j1:
                return box  # most frames fit as is
        centre = cells_of(np.asarray(centre_xy, dtype=float)[None], self.resolution)[0]
        self._ensure(np.array(box.lo), np.array(box.hi), centre)
        return box.intersection(self._box())

    def _box(self) -> _Box:
        """The lattice cells the grid holds."""
        (oi, oj), (ny, nx) = self._offset.tolist(), self.shape
        return _Box(oi, oj, oi + nx - 1, oj + ny - 1)

    def _extra_cells(self, obs: WorldObservation) -> list[_Box]:
        """Boxes of cells beyond the observation's points that the update touches (e.g. a
        view wedge)."""
        return []

    @abstractmethod
    def _update(self, layers: dict[str, np.ndarray], frame: _Frame) -> None:
        """Apply one frame to the window views `layers` (each (h, w), writable)."""

    def _ensure(self, lo: np.ndarray, hi: np.ndarray, centre: np.ndarray) -> None:
        """Grow (or roll) so that lattice cells lo..hi (inclusive) fit, if they can."""
        ny, nx = self.shape
        size = np.array([nx, ny], dtype=np.int64)
        cur_lo, cur_hi = self._offset, self._offset + size - 1
        empty = nx == 0 or ny == 0
        if not empty and np.all(lo >= cur_lo) and np.all(hi <= cur_hi):
            return
        need_lo = lo if empty else np.minimum(lo, cur_lo)
        need_hi = hi if empty else np.maximum(hi, cur_hi)
        pad = np.maximum(int(np.ceil(self.config.grow_chunk_m / self.resolution)), size // 4)
        new_lo = np.where(empty | (need_lo < cur_lo), need_lo - pad, cur_lo)
        new_hi = np.where(empty | (need_hi > cur_hi), need_hi + pad, cur_hi)
        if self.config.max_size_m is not None:
            n_max = max(round(self.config.max_size_m / self.resolution), 2)
            for k in range(2):
                if new_hi[k] - new_lo[k] + 1 <= n_max:
                    continue
                if need_hi[k] - need_lo[k] + 1 <= n_max:  # fits: trim the padding
                    new_lo[k] = min(max(new_lo[k], need_hi[k] - n_max + 1), need_lo[k])
                else:  # roll: a window centred on the walker; the rest is dropped
                    new_lo[k] = centre[k] - n_max // 2
                new_hi[k] = new_lo[k] + n_max - 1
        self._resize(new_lo, new_hi)

    def _resize(self, new_lo: np.ndarray, new_hi: np.ndarray) -> None:
        new_size = new_hi - new_lo + 1
        ny, nx = self.shape
        old_lo, old_hi = self._offset, self._offset + np.array([nx, ny]) - 1
        keep_lo, keep_hi = np.maximum(old_lo, new_lo), np.minimum(old_hi, new_hi)
        for name, old in self._layers.items():
            new = np.zeros((new_size[1], new_size[0]), dtype=old.dtype)
            if np.all(keep_hi >= keep_lo):
                a, b = keep_lo - new_lo, keep_lo - old_lo
                h, w = (keep_hi - keep_lo + 1)[::-1]
                new[a[1] : a[1] + h, a[0] : a[0] + w] = old[b[1] : b[1] + h, b[0] : b[0] + w]
            self._layers[name] = new
        self._offset = np.asarray(new_lo, dtype=np.int64).copy()


@dataclass(frozen=True)
class _Box:
    """The lattice cells i0..i1 × j0..j1 (inclusive), as Python ints: the per-frame
    bookkeeping of a few numbers costs less in ints than in 2-element arrays."""

    i0: int
    j0: int
    i1: int
    j1: int

    def union(self, other: _Box) -> _Box:
        return _Box(
            min(self.i0, other.i0),
            min(self.j0, other.j0),
            max(self.i1, other.i1),
            max(self.j1, other.j1),
        )

    @property
    def as_kernel_box(self) -> tuple[int, int, int, int]:
        """(i0, j0, width, height), as `mapping.kernels` takes a box."""
        return self.i0, self.j0, self.width, self.height

    @property
    def lo(self) -> tuple[int, int]:
        return self.i0, self.j0

    @property
    def hi(self) -> tuple[int, int]:
        return self.i1, self.j1

    @property
    def width(self) -> int:
        return self.i1 - self.i0 + 1

    @property
    def height(self) -> int:
        return self.j1 - self.j0 + 1

    def intersection(self, other: _Box) -> _Box | None:
        i0, j0 = max(self.i0, other.i0), max(self.j0, other.j0)
        i1, j1 = min(self.i1, other.i1), min(self.j1, other.j1)
        return _Box(i0, j0, i1, j1) if i0 <= i1 and j0 <= j1 else None

    def slices(self, outer: _Box) -> tuple[slice, slice]:
        """(rows, cols) of this box in an [iy, ix] array covering `outer`."""
        return (
            slice(self.j0 - outer.j0, self.j1 - outer.j0 + 1),
            slice(self.i0 - outer.i0, self.i1 - outer.i0 + 1),
        )


class _Frame:
    """One observation rasterised onto the lattice.

    Masks are built over the frame's own box of cells, which holds every cell the frame
    touches — its points, the sensor, and every traced ray sample (a ray runs from the
    sensor to an end cell's centre) — so no per-sample bounds checks are needed, and are
    then cropped to the `window` that the grid holds (the whole box unless it rolled).
    """

    def __init__(self, grid: GridExtent, obs: WorldObservation, box: _Box, window: _Box) -> None:
        self.grid, self.obs, self.box, self.window = grid, obs, box, window
        self._crop = window.slices(box)
        res, kbox = grid.resolution, box.as_kernel_box
        self._ends = np.zeros(box.width * box.height, dtype=bool)
        mark_cells(obs.ray_ends, res, kbox, self._ends)
        occupied = np.zeros(box.width * box.height, dtype=bool)
        mark_cells(obs.obstacles, res, kbox, occupied)
        self.occupied = occupied.reshape(box.height, box.width)[self._crop]

    def rays(self) -> np.ndarray:
        """Cells the rays crossed or ended in (the frame's obstacle cells included): rays
        from the sensor to the centres of the distinct end cells, or with
        `GridConfig.bundle_rays` to the farthest of each bearing bin (`lattice.bundle_rays`),
        traced by `lattice.mark_rays`'s sampling."""
        crossed = self._ends.copy()
        sx, sy = self.obs.sensor_xy.tolist()
        res, bundle = self.grid.resolution, self.grid.config.bundle_rays
        mark_end_rays(self._ends, sx, sy, res, bundle, self.box.as_kernel_box, crossed)
        return crossed.reshape(self.box.height, self.box.width)[self._crop]

    def wedge(self, view: ViewWedge) -> np.ndarray:
        """Cells of the window whose centres lie in the view wedge of the sensor."""
        res, win = self.grid.resolution, self.window
        x = (np.arange(win.width) + win.i0 + 0.5) * res - self.obs.sensor_xy[0]
        y = (np.arange(win.height) + win.j0 + 0.5) * res - self.obs.sensor_xy[1]
        return _in_wedge(x, y, self.obs.heading, view)


def _in_wedge_exact(x: np.ndarray, y: np.ndarray, heading: float, view: ViewWedge) -> np.ndarray:
    """The view wedge's definition, at offsets (x, y) from the sensor (broadcast): range
    hypot(x, y) within [r_min, r_max], bearing wrap(atan2(y, x) − heading) within ±half_fov."""
    r = np.hypot(x, y)
    bearing = wrap_angle(np.arctan2(y, x) - heading)
    return (r >= view.r_min) & (r <= view.r_max) & (np.abs(bearing) <= view.half_fov)


_WEDGE_MARGIN = 1e-9  # relative; float errors of either test are ~1e-15


def _in_wedge(x: np.ndarray, y: np.ndarray, heading: float, view: ViewWedge) -> np.ndarray:
    """`_in_wedge_exact(x[None, :], y[:, None], ...)`, (len(y), len(x)), 5× cheaper.

    arctan2 and hypot over the whole window dominate a view-count update, so cells are
    first sorted with cheaper arithmetic: r = √(x² + y²), and the bearing test as
    cos(bearing) ≥ cos(half_fov), i.e. x·cos h + y·sin h ≥ r·cos(half_fov) (cos falls
    on [0, π]). That decides every cell more than 1e-9 (relative) from the wedge's edges,
    where both forms agree despite rounding; the few cells nearer an edge, if any, get
    the exact test, so the result is the exact test's.
    """
    r = np.sqrt(np.add.outer(y * y, x * x))
    along = np.add.outer(y * np.sin(heading), x * np.cos(heading))
    along -= r * np.cos(view.half_fov)  # > 0: inside the bearing limits
    tol = r * (_WEDGE_MARGIN * (1.0 + abs(heading)))
    r_tol = _WEDGE_MARGIN * max(view.r_max, 1.0)
    inside = (along > tol) & (r > view.r_min + r_tol) & (r < view.r_max - r_tol)
    outside = (along < -tol) | (r < view.r_min - r_tol) | (r > view.r_max + r_tol)
    undecided = ~(inside | outside)
    rows = np.flatnonzero(undecided.any(axis=1))
    if len(rows):  # same broadcast layout as the definition, row by row
        exact = _in_wedge_exact(x[None, :], y[rows, None], heading, view)
        inside[rows] = np.where(undecided[rows], exact, inside[rows])
    return inside


_NO_HITS = tuple(np.zeros((0, 0), dtype=np.float32) for _ in range(3))


class OccupancyGrid(GridExtent):
    """Log-odds occupancy grid (float32 layer "log_odds"; 0 = unknown)."""

    LAYERS: ClassVar[dict[str, type]] = {"log_odds": np.float32}
    OCCUPIED_THRESHOLD: ClassVar[float] = 0.65
    FREE_THRESHOLD: ClassVar[float] = 0.196

    @property
    def log_odds(self) -> np.ndarray:
        """The (ny, nx) log-odds array (read it, do not write it)."""
        return self._layers["log_odds"]

    def probability(self) -> np.ndarray:
        return 1.0 / (1.0 + np.exp(-self.log_odds.astype(np.float64)))

    def known(self) -> np.ndarray:
        return self.log_odds != 0.0

    def occupied(self, threshold: float | None = None) -> np.ndarray:
        # Same as probability() > threshold, without exponentiating the whole grid.
        thr = self.OCCUPIED_THRESHOLD if threshold is None else threshold
        if not 0.0 < thr < 1.0:
            raise ValueError(f"threshold must be in (0, 1), got {thr}")
        return self.log_odds > np.log(thr / (1.0 - thr))

    def decay(self, factor: float) -> None:
        if not 0.0 < factor <= 1.0:
            raise ValueError(f"decay factor must be in (0, 1], got {factor}")
        self._layers["log_odds"] *= np.float32(factor)

    def _update(self, layers: dict[str, np.ndarray], frame: _Frame) -> None:
        update_log_odds(layers["log_odds"], frame.occupied, frame.rays(), *self._increments())

    def _increments(self) -> tuple[np.float32, np.float32, np.float32, np.float32]:
        p = self.config.log_odds
        f32 = np.float32
        return f32(p.l_occ), f32(p.l_free), f32(p.l_min), f32(p.l_max)

    def _hit_layers(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The layers the obstacle points are added to (none: empty arrays)."""
        return _NO_HITS

    def update_at(
        self, obs: PlanarObservation, pose: np.ndarray, centre_xy: np.ndarray | None = None
    ) -> Callable[[], None] | None:
        pose = as_pose(pose)
        c, s = np.cos(pose[2]), np.sin(pose[2])
        res = self.resolution
        world = np.empty((len(obs.points), 2))
        sx, sy, *bounds = place_frame(
            obs.points, float(pose[0]), float(pose[1]), float(c), float(s),
            float(obs.sensor_xy[0]), float(obs.sensor_xy[1]), res, world,
        )  # fmt: skip
        box = _Box(*bounds)
        window = self._fit(box, np.array([sx, sy]) if centre_xy is None else centre_xy)
        if window is None:
            return None
        args = (
            world, len(obs.obstacles), sx, sy, res, self.config.bundle_rays,
            box.as_kernel_box, window.as_kernel_box, self.lattice_offset,
            self._layers["log_odds"], *self._increments(), *self._hit_layers(),
        )  # fmt: skip
        return lambda: integrate_log_odds(*args)


class HitCentroidGrid(OccupancyGrid):
    """Log-odds grid plus, per cell, the obstacle points it held: float32 layers "hit_x",
    "hit_y" (sums of the points' offsets from the cell's centre [m]) and "hits" (their
    count); `hit_centroids()` gives their mean. Occupancy is the log-odds grid's."""

    LAYERS: ClassVar[dict[str, type]] = {
        "log_odds": np.float32,
        "hit_x": np.float32,
        "hit_y": np.float32,
        "hits": np.float32,
    }

    def _update(self, layers: dict[str, np.ndarray], frame: _Frame) -> None:
        super()._update(layers, frame)
        accumulate_hits(
            frame.obs.obstacles,
            self.resolution,
            frame.window.as_kernel_box,
            layers["hit_x"],
            layers["hit_y"],
            layers["hits"],
        )

    def _hit_layers(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self._layers["hit_x"], self._layers["hit_y"], self._layers["hits"]

    def hit_centroids(self) -> np.ndarray:
        """(ny, nx, 2) mean offset of each cell's points from its centre (0 where none)."""
        n = np.maximum(self._layers["hits"], 1.0)
        return np.stack([self._layers["hit_x"] / n, self._layers["hit_y"] / n], axis=-1)


class ViewCountGrid(GridExtent):
    """The thesis's counting model: uint32 layers "views" and "hits" per cell."""

    LAYERS: ClassVar[dict[str, type]] = {"views": np.uint32, "hits": np.uint32}
    OCCUPIED_THRESHOLD: ClassVar[float] = 0.5
    FREE_THRESHOLD: ClassVar[float] = 0.5

    @property
    def views(self) -> np.ndarray:
        return self._layers["views"]

    @property
    def hits(self) -> np.ndarray:
        return self._layers["hits"]

    def probability(self) -> np.ndarray:
        p = np.full(self.shape, 0.5)
        seen = self.views > 0
        p[seen] = self.hits[seen] / self.views[seen]
        return p

    def known(self) -> np.ndarray:
        return self.views > 0

    def _extra_cells(self, obs: WorldObservation) -> list[_Box]:
        if obs.view is None:
            return []
        # Bounding box of the wedge from its arcs, sampled finely (the arcs bulge past the
        # chords by < 1 cm for any wedge) and padded by one cell.
        v = obs.view
        angles = obs.heading + _arc_offsets(v.half_fov)
        cos, sin = np.cos(angles), np.sin(angles)
        lo, hi = [], []
        for k, c in enumerate((cos, sin)):  # k = 0: x, 1: y
            ends = np.concatenate([v.r_min * c, v.r_max * c])
            ends += obs.sensor_xy[k]
            cells = np.floor(ends / self.resolution)
            lo.append(int(cells.min()) - 1)
            hi.append(int(cells.max()) + 1)
        return [_Box(lo[0], lo[1], hi[0], hi[1])]

    def _update(self, layers: dict[str, np.ndarray], frame: _Frame) -> None:
        occ = frame.occupied
        view = frame.rays() if frame.obs.view is None else frame.wedge(frame.obs.view)
        layers["views"] += view | occ  # adding booleans: no index arrays
        layers["hits"] += occ


@lru_cache(maxsize=8)
def _arc_offsets(half_fov: float) -> np.ndarray:
    """65 bearings across ±half_fov, sampling the wedge's arcs for its bounding box."""
    return np.linspace(-half_fov, half_fov, 65)


def make_grid(config: GridConfig | None = None) -> GridExtent:
    """The grid class of config.model."""
    cfg = config or GridConfig()
    classes = {
        MapModel.LOG_ODDS: OccupancyGrid,
        MapModel.VIEW_COUNT: ViewCountGrid,
        MapModel.LOG_ODDS_HITS: HitCentroidGrid,
    }
    return classes[cfg.model](cfg)
