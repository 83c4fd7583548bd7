"""Map files: ROS map_server PGM + YAML (and reading them back), pixel-exact PNG pictures.

Both show a grid's trinary map (`GridExtent.trinary()`), by default cropped to the
bounding box of the known cells (a growing grid keeps unknown margins): `map_raster`,
which the map figure (`experiments.report.map_figure`, a replay's `map.png`, with metric
axes and a legend) draws too, so figure and files show the same cells. Images have row 0
at the top, i.e. the highest y; the map_server YAML `origin` is the world pose of the
lower-left pixel. An empty grid exports as one unknown pixel.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from mapping.grid import GridExtent
from mapping.lattice import as_points

# map_server "trinary" pixel values.
PGM_OCCUPIED, PGM_FREE, PGM_UNKNOWN = 0, 254, 205
OCCUPIED_THRESH, FREE_THRESH = 0.65, 0.196
# PNG pixel values: free white, occupied black, unknown grey.
PNG_OCCUPIED, PNG_FREE, PNG_UNKNOWN = 0, 255, 160


@dataclass(frozen=True, eq=False)
class MapRaster:
    """What the map files show: trinary int8 (ny, nx) with row 0 = lowest y (1 occupied,
    0 free, −1 unknown), the world (x, y) of the lower-left corner of cell [0, 0] [m] and
    the cell side [m]."""

    trinary: np.ndarray
    origin: tuple[float, float]
    resolution: float

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) in world metres."""
        ny, nx = self.trinary.shape
        x0, y0 = self.origin
        return x0, x0 + nx * self.resolution, y0, y0 + ny * self.resolution


def map_raster(grid: GridExtent, crop: bool = True) -> MapRaster:
    """The grid's trinary map, cropped to the bounding box of its known cells (crop=True;
    all of a grid without known cells); an empty grid gives one unknown cell."""
    tri = grid.trinary()
    res = grid.resolution
    if tri.size == 0:  # nothing integrated yet: one unknown pixel (images cannot be empty)
        return MapRaster(np.full((1, 1), -1, dtype=np.int8), grid.origin, res)
    known = tri >= 0
    if not crop or not known.any():
        return MapRaster(tri, grid.origin, res)
    rows, cols = np.flatnonzero(known.any(axis=1)), np.flatnonzero(known.any(axis=0))
    r0, c0 = int(rows[0]), int(cols[0])
    i0, j0 = grid.lattice_offset
    origin = ((i0 + c0) * res, (j0 + r0) * res)
    return MapRaster(tri[r0 : rows[-1] + 1, c0 : cols[-1] + 1], origin, res)


def _image(trinary: np.ndarray, occupied: int, free: int, unknown: int) -> np.ndarray:
    """uint8 image (row 0 = highest y) of a trinary grid (row 0 = lowest y)."""
    img = np.full(trinary.shape, unknown, dtype=np.uint8)
    img[trinary == 0] = free
    img[trinary == 1] = occupied
    return np.ascontiguousarray(img[::-1])


def save_png(
    grid: GridExtent,
    path: str | Path,
    *,
    outlines: Sequence[np.ndarray] = (),
    trajectory: np.ndarray | None = None,
    scale: int = 1,
    crop: bool = True,
    outline_bgr: tuple[int, int, int] = (0, 0, 230),
    trajectory_bgr: tuple[int, int, int] = (220, 120, 0),
) -> Path:
    """Write the map as a PNG of (ny·scale) × (nx·scale) pixels (after cropping): scale
    pixels per cell, no axes or legend (for a figure: `experiments.report.map_figure`).

    outlines: true obstacle outlines, each an N×2 polygon in world metres (drawn closed).
    trajectory: N×2 world points drawn as a polyline. Colours are BGR.
    """
    if scale < 1:
        raise ValueError(f"scale must be >= 1, got {scale}")
    raster = map_raster(grid, crop)
    grey = _image(raster.trinary, PNG_OCCUPIED, PNG_FREE, PNG_UNKNOWN)
    img = cv2.cvtColor(np.kron(grey, np.ones((scale, scale), dtype=np.uint8)), cv2.COLOR_GRAY2BGR)
    xmin = raster.origin[0]
    ymax = raster.origin[1] + raster.trinary.shape[0] * grid.resolution
    px_per_m = scale / grid.resolution
    shift = 4  # cv2 draws at 1/16-pixel precision

    def pixels(xy: np.ndarray, name: str) -> np.ndarray:
        xy = as_points(xy, name)
        uv = np.column_stack([(xy[:, 0] - xmin) * px_per_m, (ymax - xy[:, 1]) * px_per_m])
        return np.round((uv - 0.5) * (1 << shift)).astype(np.int32).reshape(-1, 1, 2)

    for k, poly in enumerate(outlines):
        cv2.polylines(
            img, [pixels(poly, f"outlines[{k}]")], True, outline_bgr, 1, cv2.LINE_AA, shift
        )
    if trajectory is not None:
        cv2.polylines(
            img, [pixels(trajectory, "trajectory")], False, trajectory_bgr, 1, cv2.LINE_AA, shift
        )
    path = Path(path)
    if not cv2.imwrite(str(path), img):
        raise OSError(f"could not write {path}")
    return path


def save_map_server(grid: GridExtent, path: str | Path, *, crop: bool = True) -> tuple[Path, Path]:
    """Write `<stem>.pgm` (P5, 8-bit, trinary) and `<stem>.yaml` for ROS map_server.

    `path` is the YAML path or the common stem; returns (yaml_path, pgm_path).
    """
    yaml_path = Path(path).with_suffix(".yaml")
    pgm_path = yaml_path.with_suffix(".pgm")
    raster = map_raster(grid, crop)
    img = _image(raster.trinary, PGM_OCCUPIED, PGM_FREE, PGM_UNKNOWN)
    header = f"P5\n# walker-slam occupancy map\n{img.shape[1]} {img.shape[0]}\n255\n"
    pgm_path.write_bytes(header.encode("ascii") + img.tobytes())
    meta = {
        "image": pgm_path.name,
        "resolution": float(grid.resolution),
        "origin": [raster.origin[0], raster.origin[1], 0.0],
        "negate": 0,
        "occupied_thresh": OCCUPIED_THRESH,
        "free_thresh": FREE_THRESH,
        "mode": "trinary",
    }
    yaml_path.write_text(yaml.safe_dump(meta, sort_keys=False))
    return yaml_path, pgm_path


@dataclass(frozen=True, eq=False)
class LoadedMap:
    """A map_server map read back: trinary int8 (ny, nx) with row 0 = lowest y (as a grid:
    1 occupied, 0 free, −1 unknown), resolution [m], origin (x, y, yaw) of cell [0, 0]."""

    trinary: np.ndarray
    resolution: float
    origin: tuple[float, float, float]
    image_path: Path


def load_map_yaml(path: str | Path) -> LoadedMap:
    """Read a map_server YAML and its image, classifying pixels as map_server does."""
    path = Path(path)
    meta = yaml.safe_load(path.read_text())
    missing = {"image", "resolution", "origin"} - set(meta)
    if missing:
        raise ValueError(f"{path}: map YAML lacks {sorted(missing)}")
    mode = meta.get("mode", "trinary")
    if mode not in ("trinary", "scale"):
        raise ValueError(f"{path}: mode {mode!r} not supported (trinary or scale)")
    image_path = path.parent / meta["image"]
    img = cv2.imread(str(image_path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise ValueError(f"{path}: cannot read image {image_path}")
    v = img.astype(np.float64)
    p = v / 255.0 if meta.get("negate", 0) else (255.0 - v) / 255.0
    tri = np.full(img.shape, -1, dtype=np.int8)
    tri[p < float(meta.get("free_thresh", FREE_THRESH))] = 0
    tri[p > float(meta.get("occupied_thresh", OCCUPIED_THRESH))] = 1
    origin = tuple(float(c) for c in meta["origin"])
    if len(origin) != 3:
        raise ValueError(f"{path}: origin must be [x, y, yaw], got {meta['origin']}")
    return LoadedMap(tri[::-1].copy(), float(meta["resolution"]), origin, image_path)
