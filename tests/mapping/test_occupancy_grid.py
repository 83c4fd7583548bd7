"""Occupancy grids: ray carving, per-frame dedupe, extent growth and rolling, view counts."""

from __future__ import annotations

import math

import numpy as np
import pytest
from synthetic_depth import FLOOR, Box, depth_frame, wall_at_x

from hardware.calibration import WalkerCalibration
from hardware.messages import LaserScan
from mapping.depth_points import project_depth_frame
from mapping.grid import GridConfig, LogOddsConfig, OccupancyGrid, ViewCountGrid, make_grid
from mapping.lattice import bundle_rays, trace_rays
from mapping.mapper import MapperConfig, OccupancyMapper
from mapping.observation import ViewWedge, WorldObservation

RES = 0.05
LO = LogOddsConfig()


def wall_scan(x_wall: float, half_angle_deg: float = 45.0, step_deg: float = 0.5) -> LaserScan:
    """Scan from the sensor origin of a wall x = x_wall, beams within ±half_angle_deg."""
    half_angle, step = math.radians(half_angle_deg), math.radians(step_deg)
    a = np.arange(-half_angle, half_angle + 1e-9, step)
    return LaserScan(0.0, float(a[0]), step, x_wall / np.cos(a), 30.0)


def cells_set(mask: np.ndarray, grid) -> set[tuple[int, int]]:
    """World-lattice cells (i, j) of a boolean grid mask."""
    iy, ix = np.nonzero(mask)
    oi, oj = grid.lattice_offset
    return set(zip((ix + oi).tolist(), (iy + oj).tolist(), strict=True))


def value_at(grid: OccupancyGrid, xy) -> float:
    ix, iy = grid.world_to_cell(np.asarray(xy, dtype=float))[0]
    return float(grid.log_odds[iy, ix])


def test_one_scan_of_a_wall_marks_the_wall_and_the_free_space_before_it():
    mapper = OccupancyMapper(config=MapperConfig(grid=GridConfig(bundle_rays=False)))
    # The wall x = 2.025 is the middle of lattice column i = 40 (x in [2.00, 2.05)).
    mapper.integrate_scan(wall_scan(2.025), np.zeros(3))
    g = mapper.grid
    y_end = 2.025 * math.tan(math.radians(45))
    want = {(40, j) for j in range(math.floor(-y_end / RES), math.floor(y_end / RES) + 1)}
    assert cells_set(g.occupied(), g) == want
    # Each cell is updated once per frame: hit cells hold exactly l_occ, free ones l_free.
    lo = g.log_odds
    assert set(np.unique(lo).tolist()) == {np.float32(LO.l_free), 0.0, np.float32(LO.l_occ)}
    # Free: every cell whose centre lies at least a cell inside the ±45° wedge before the wall.
    centres = g.cell_to_world(np.argwhere(np.ones(g.shape, bool))[:, ::-1])
    x, y = centres[:, 0], centres[:, 1]
    inside = (x > RES) & (x < 2.0 - RES) & (np.abs(y) < x - 1.5 * RES)
    assert inside.sum() > 1000
    assert np.all(lo.ravel()[inside] == np.float32(LO.l_free))
    # Nothing behind the wall or outside the wedge is known.
    outside = (x > 2.05) | (np.abs(y) > x + 1.5 * RES)
    assert np.all(lo.ravel()[outside] == 0.0)


def test_bundled_rays_carve_the_same_free_space_within_half_a_cell():
    cal = WalkerCalibration()
    scene = [FLOOR, wall_at_x(3.4), Box((1.6, -0.4, 0.0), (2.0, 0.1, 0.8))]
    obs = project_depth_frame(depth_frame(cal.depth_intrinsics, cal.depth_mount, scene), cal)
    world = obs.in_world(np.array([0.3, -0.2, 0.4]))
    grids = [OccupancyGrid(GridConfig(bundle_rays=b)) for b in (False, True)]
    for g in grids:
        g.integrate(world)
    exact, bundled = (cells_set(g.log_odds < 0, g) for g in grids)
    assert len(exact) > 1500
    assert len(exact ^ bundled) <= 0.03 * len(exact | bundled)
    assert cells_set(grids[0].occupied(), grids[0]) == cells_set(grids[1].occupied(), grids[1])
    # Bundling keeps one ray per bearing bin: far fewer rays than distinct end cells.
    ends = np.unique(np.floor(world.ray_ends / RES), axis=0)
    assert len(bundle_rays(world.sensor_xy, (ends + 0.5) * RES, RES)) < len(ends) / 4


def test_trace_rays_follows_the_segment():
    diag = trace_rays(np.array([0.025, 0.025]), np.array([[1.025, 1.025]]), RES)
    # Samples stop short of the end point but may fall in its cell (the grid adds end
    # cells anyway).
    assert {tuple(c) for c in diag.tolist()} == {(k, k) for k in range(21)}
    flat = trace_rays(np.array([0.01, -0.02]), np.array([[-1.0, -0.02]]), RES)
    assert {tuple(c) for c in flat.tolist()} == {(k, -1) for k in range(-20, 1)}


def test_each_cell_is_updated_at_most_once_per_frame():
    g = OccupancyGrid()
    hits = np.tile([[2.01, 0.01]], (50, 1))  # 50 points in one cell
    ends = np.vstack([hits, np.tile([[1.01, 0.01]], (50, 1))])  # 100 rays through (0..1, 0)
    g.integrate(WorldObservation(np.zeros(2), 0.0, hits, ends))
    assert value_at(g, [2.01, 0.01]) == pytest.approx(LO.l_occ)
    assert value_at(g, [0.51, 0.01]) == pytest.approx(LO.l_free)
    assert value_at(g, [1.01, 0.01]) == pytest.approx(LO.l_free)  # a floor-like end cell
    for _ in range(20):  # clamped after many frames
        g.integrate(WorldObservation(np.zeros(2), 0.0, hits, ends))
    assert value_at(g, [2.01, 0.01]) == pytest.approx(LO.l_max)
    assert value_at(g, [0.51, 0.01]) == pytest.approx(LO.l_min)


def test_cell_world_round_trip():
    rng = np.random.default_rng(7)
    g = OccupancyGrid()
    g.integrate(WorldObservation(np.array([-3.2, 4.1]), 0.0, np.empty((0, 2)), [[2.3, -1.7]]))
    cells = np.column_stack([rng.integers(0, g.shape[1], 100), rng.integers(0, g.shape[0], 100)])
    np.testing.assert_array_equal(g.world_to_cell(g.cell_to_world(cells)), cells)
    xmin, xmax, ymin, ymax = g.extent
    pts = rng.uniform([xmin, ymin], [xmax, ymax], size=(1000, 2))
    back = g.cell_to_world(g.world_to_cell(pts))
    assert np.all(np.abs(back - pts) <= RES / 2 + 1e-12)
    assert g.origin == pytest.approx((xmin, ymin))
    assert (xmax - xmin, ymax - ymin) == pytest.approx((g.shape[1] * RES, g.shape[0] * RES))


def test_growth_keeps_earlier_cells_at_their_world_coordinates():
    mapper = OccupancyMapper()
    mapper.integrate_scan(wall_scan(2.025), np.zeros(3))
    g = mapper.grid
    first_xy, first_origin = g.occupied_xy(), g.origin
    first_values = [value_at(g, p) for p in first_xy]
    shapes = {g.shape}
    # Walk 30 m towards −x and −y, scanning a wall ahead every 10 cm.
    for k in range(1, 301):
        pose = np.array([-0.1 * k, -0.05 * k, math.pi])
        mapper.integrate_scan(wall_scan(1.5, step_deg=2.0), pose)
        shapes.add(g.shape)
    assert g.origin[0] < first_origin[0] - 25 and g.origin[1] < first_origin[1] - 10
    assert [value_at(g, p) for p in first_xy] == first_values
    assert cells_set(g.occupied(), g) >= {tuple(c) for c in np.floor(first_xy / RES).astype(int)}
    assert len(shapes) <= 20  # grows by chunks (≥ 1/4 of its size), not frame by frame


def test_rolling_window_drops_what_falls_off():
    mapper = OccupancyMapper(config=MapperConfig(grid=GridConfig(max_size_m=8.0)))
    mapper.integrate_scan(wall_scan(2.025), np.zeros(3))
    first_xy = mapper.grid.occupied_xy()
    for k in range(1, 301):
        mapper.integrate_scan(wall_scan(1.525), np.array([0.1 * k, 0.0, 0.0]))
    g = mapper.grid
    assert max(g.shape) <= 160
    # The first wall fell off; the latest (x = 31.525) is there; the walker is well inside.
    ix, iy = g.world_to_cell(first_xy).T
    assert np.all((ix < 0) | (ix >= g.shape[1]) | (iy < 0) | (iy >= g.shape[0]))
    latest = np.column_stack([np.full(29, 31.525), np.linspace(-1.4, 1.4, 29)])
    assert all(value_at(g, p) == pytest.approx(LO.l_occ) for p in latest)
    xmin, xmax, ymin, ymax = g.extent
    assert xmin + 2.0 < 30.0 < xmax - 2.0 and ymin + 2.0 < 0.0 < ymax - 2.0


def test_view_count_model_occupied_in_more_than_half_of_views():
    g = ViewCountGrid()
    a, b = np.array([[2.025, 0.025]]), np.array([[3.025, 0.525]])  # 2.03 m and 3.07 m away
    wide, short = ViewWedge(0.8, 4.15, 0.5), ViewWedge(0.8, 2.5, 0.5)
    none = np.empty((0, 2))
    frames = [(np.vstack([a, b]), wide), (a, wide), (a, wide), (none, short)]
    for obstacles, view in frames:
        g.integrate(WorldObservation(np.zeros(2), 0.0, obstacles, np.empty((0, 2)), view))

    def at(layer, xy):
        ix, iy = g.world_to_cell(xy)[0]
        return layer[iy, ix]

    assert (at(g.views, a), at(g.hits, a)) == (4, 3)
    assert (at(g.views, b), at(g.hits, b)) == (3, 1)
    assert at(g.occupied(), a) and not at(g.occupied(), b)
    assert at(g.probability(), a) == pytest.approx(0.75)
    assert at(g.probability(), b) == pytest.approx(1 / 3)
    assert at(g.free(), b) and not at(g.free(), a)
    # The wedge: nothing nearer than 0.8 m, beyond ±0.5 rad or behind is in view.
    for xy in ([0.5, 0.0], [2.0, 1.3], [-2.0, 0.0]):
        assert at(g.views, np.array([xy])) == 0
    assert at(g.views, np.array([[4.0, 0.0]])) == 3
    assert at(g.views, np.array([[2.0, 1.0]])) == 4  # bearing 0.46 rad


def test_view_count_without_a_wedge_counts_the_cells_the_rays_reached():
    g = make_grid(GridConfig(model="view-count"))
    hits = np.array([[2.025, 0.025]])
    g.integrate(WorldObservation(np.zeros(2), 0.0, hits, hits))
    g.integrate(WorldObservation(np.zeros(2), 0.0, np.empty((0, 2)), [[3.025, 0.025]]))
    ix, iy = g.world_to_cell(np.array([[2.025, 0.025], [1.025, 0.025], [3.025, 0.025]])).T
    np.testing.assert_array_equal(g.views[iy, ix], [2, 2, 1])
    np.testing.assert_array_equal(g.hits[iy, ix], [1, 0, 0])


def test_bad_inputs_raise():
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        WorldObservation(np.zeros(2), 0.0, np.zeros((3, 3)), np.zeros((0, 2)))
    with pytest.raises(ValueError, match=r"\(2,\)"):
        WorldObservation(np.zeros(3), 0.0, np.zeros((0, 2)), np.zeros((0, 2)))
    with pytest.raises(ValueError):
        GridConfig(model="histogram")
    with pytest.raises(ValueError):
        LogOddsConfig(l_occ=-1.0)


def test_compiled_loops_refuse_to_write_outside_their_box():
    # The compiled loops index raw bitmaps: a point or ray sample outside the box must
    # raise, not write past the array.
    from mapping.kernels import mark_cells, mark_ray_samples

    marks = np.zeros(4 * 3, dtype=bool)  # box of 4 × 3 cells from cell (10, 20)
    mark_cells(np.array([[0.525, 1.025], [0.675, 1.125]]), RES, (10, 20, 4, 3), marks)
    assert marks.reshape(3, 4)[0, 0] and marks.reshape(3, 4)[2, 3] and marks.sum() == 2
    for outside in ([[0.475, 1.025]], [[0.725, 1.025]], [[0.525, 1.175]]):
        with pytest.raises(IndexError):
            mark_cells(np.array(outside), RES, (10, 20, 4, 3), marks)
    with pytest.raises(IndexError):  # a ray from cell (0, 0) out to x = 5 cells
        mark_ray_samples(
            0.5,
            0.5,
            np.array([4.5]),
            np.array([0.0]),
            np.array([9]),
            (0, 0, 4, 1),
            np.zeros(4, dtype=bool),
        )


@pytest.mark.parametrize("model", ["log-odds", "log-odds-hits"])
@pytest.mark.parametrize("max_size_m", [None, 3.0])
def test_integrating_a_frame_at_a_pose_equals_integrating_it_placed(model, max_size_m):
    """`integrate_at(obs, pose)` (one compiled call for the log-odds models) leaves every
    layer and the extent exactly as `integrate(obs.in_world(pose))` does, through growth
    and, with a 3 m window, rolling; also for frames with no points or only ray ends."""
    from mapping.observation import PlanarObservation

    rng = np.random.default_rng(7)
    cfg = GridConfig(model=model, max_size_m=max_size_m)
    placed, fused = make_grid(cfg), make_grid(cfg)
    pose = np.array([0.3, -0.2, 0.4])
    for k in range(40):
        n_obs, n_free = [(0, 0), (0, 30)][k % 2] if k % 7 == 3 else (60, 120)
        r = rng.uniform(0.5, 2.5, n_obs + n_free)
        a = rng.uniform(-0.5, 0.5, n_obs + n_free)
        pts = np.column_stack([0.2 + r * np.cos(a), r * np.sin(a)]).astype(np.float32)
        obs = PlanarObservation(np.array([0.2, 0.01]), 0.0, pts[:n_obs], pts[n_obs:])
        pose = pose + np.array([0.25 * math.cos(pose[2]), 0.25 * math.sin(pose[2]), 0.15])
        placed.integrate(obs.in_world(pose), centre_xy=pose[:2])
        fused.integrate_at(obs, pose, centre_xy=pose[:2])
        assert placed.lattice_offset == fused.lattice_offset
        for name in type(placed).LAYERS:
            np.testing.assert_array_equal(fused.layer(name), placed.layer(name))
    assert np.count_nonzero(fused.occupied()) > 20
