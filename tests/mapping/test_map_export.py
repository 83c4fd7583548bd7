"""Map export: map_server PGM + YAML round trip, PNG pictures with overlays."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import yaml

from hardware.messages import LaserScan
from mapping.export import load_map_yaml, save_map_server, save_png
from mapping.grid import GridConfig
from mapping.mapper import MapperConfig, OccupancyMapper


def room_map(model: str = "log-odds") -> OccupancyMapper:
    """A room (walls x = −1.525, 2.525, y = −1.025, 2.025: mid-cell) scanned from a few poses."""
    mapper = OccupancyMapper(config=MapperConfig(grid=GridConfig(model=model)))
    a = np.linspace(-math.pi, math.pi, 720, endpoint=False)
    for x, y in [(0.0, 0.0), (0.8, 0.5), (-0.6, 1.2)]:
        c, s = np.cos(a), np.sin(a)
        with np.errstate(divide="ignore"):
            tx = np.where(c > 0, (2.525 - x) / c, (-1.525 - x) / c)
            ty = np.where(s > 0, (2.025 - y) / s, (-1.025 - y) / s)
        for _ in range(3):
            scan = LaserScan(0.0, float(a[0]), float(a[1] - a[0]), np.minimum(tx, ty), 30.0)
            mapper.integrate_scan(scan, np.array([x, y, 0.0]))
    return mapper


@pytest.mark.parametrize("model", ["log-odds", "view-count"])
@pytest.mark.parametrize("crop", [True, False])
def test_map_server_round_trip(tmp_path, model, crop):
    grid = room_map(model).grid
    yaml_path, pgm_path = save_map_server(grid, tmp_path / "room", crop=crop)
    meta = yaml.safe_load(yaml_path.read_text())
    assert meta["image"] == "room.pgm" and meta["mode"] == "trinary" and meta["negate"] == 0
    assert (meta["occupied_thresh"], meta["free_thresh"]) == (0.65, 0.196)
    loaded = load_map_yaml(yaml_path)
    tri = grid.trinary()
    assert {-1, 0, 1} <= set(np.unique(tri).tolist())
    if crop:  # the known cells' bounding box: the room, walls included
        assert loaded.trinary.shape == (62, 82)  # cells i −31..50, j −21..40
        assert loaded.origin == pytest.approx((-1.55, -1.05, 0.0))
        (r, c) = (
            np.flatnonzero((tri >= 0).any(axis=1))[0],
            np.flatnonzero((tri >= 0).any(axis=0))[0],
        )
        tri = tri[r : r + 62, c : c + 82]
    else:
        assert loaded.origin == pytest.approx((*grid.origin, 0.0))
    np.testing.assert_array_equal(loaded.trinary, tri)
    assert loaded.resolution == grid.resolution
    # Independently of the reader: P5 header, and row 0 of the image is the top (max y),
    # where the wall y = 2.025 runs: occupied (0) in the map_server convention.
    raw = pgm_path.read_bytes()
    assert raw.startswith(b"P5\n")
    header_end = raw.index(b"\n255\n") + 5
    h, w = tri.shape
    img = np.frombuffer(raw[header_end:], dtype=np.uint8).reshape(h, w)
    assert set(np.unique(img).tolist()) <= {0, 205, 254}
    np.testing.assert_array_equal(img, np.where(tri == 1, 0, np.where(tri == 0, 254, 205))[::-1])
    if crop:
        assert np.mean(img[0, 1:-1] == 0) > 0.9  # the y = 2.025 wall, cell row j = 40
        assert np.mean(img[h // 2, 2:-2] == 254) > 0.9  # free inside


def test_png_has_the_expected_size_and_colours(tmp_path):
    grid = room_map().grid
    outline = np.array([[-1.525, -1.025], [2.525, -1.025], [2.525, 2.025], [-1.525, 2.025]])
    path = save_png(grid, tmp_path / "room.png", scale=3)
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img.shape == (62 * 3, 82 * 3, 3)
    assert np.all(img[img.shape[0] // 2, 30:-30] == 255)  # free: white
    assert np.all(img[1, 6:-6] == 0)  # the top wall: black
    plain = save_png(grid, tmp_path / "full.png", crop=False)
    assert cv2.imread(str(plain)).shape[:2] == grid.shape
    over = save_png(
        grid,
        tmp_path / "overlay.png",
        scale=3,
        outlines=[outline],
        trajectory=np.array([[0.0, 0.0], [0.8, 0.5], [-0.6, 1.2]]),
    )
    img = cv2.imread(str(over), cv2.IMREAD_COLOR).astype(int)
    coloured = (np.abs(img[..., 0] - img[..., 2]) > 60) | (np.abs(img[..., 1] - img[..., 2]) > 60)
    red = coloured & (img[..., 2] > img[..., 0])
    blue = coloured & (img[..., 0] > img[..., 2])
    assert red.sum() > 500 and blue.sum() > 50
    # The outline runs along the walls: red pixels sit on the outer cell rows/columns.
    rows, cols = np.nonzero(red)
    edge = (np.minimum(rows, img.shape[0] - 1 - rows) <= 4) | (
        np.minimum(cols, img.shape[1] - 1 - cols) <= 4
    )
    assert edge.mean() > 0.95


def test_an_empty_map_exports_as_one_unknown_pixel(tmp_path):
    grid = OccupancyMapper().grid
    yaml_path, _ = save_map_server(grid, tmp_path / "empty.yaml")
    loaded = load_map_yaml(yaml_path)
    np.testing.assert_array_equal(loaded.trinary, [[-1]])
    assert loaded.origin == (0.0, 0.0, 0.0)
    assert cv2.imread(str(save_png(grid, tmp_path / "empty.png"))).shape == (1, 1, 3)


def test_load_map_yaml_rejects_incomplete_files(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("image: x.pgm\n")
    with pytest.raises(ValueError, match="resolution"):
        load_map_yaml(p)
