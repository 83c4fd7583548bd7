"""The optimised mapper makes exactly the maps its documented semantics define.

A 300-frame replay along the simulator's thesis course is mapped by `OccupancyMapper` and
by `reference_mapper.ReferenceMapper`, a slow, straightforward re-implementation; the maps
must agree cell for cell. The fast paths that have exact slow definitions (the compacted
depth projection, the view wedge test) are also checked against them on edge cases.
"""

from __future__ import annotations

import numpy as np
import pytest
from reference_mapper import ReferenceMapper
from synthetic_depth import FLOOR, Box, depth_frame, wall_at_x

from hardware.messages import DepthFrame
from hardware.sim.depth_camera import DepthCameraConfig, SimDepthCamera
from hardware.sim.simulator import SimConfig
from hardware.sim.world import load_world
from mapping.depth_points import DepthConfig, depth_to_compact_observation, depth_to_observation
from mapping.grid import GridConfig, OccupancyGrid, _in_wedge, _in_wedge_exact
from mapping.mapper import MapperConfig, OccupancyMapper
from mapping.observation import ViewWedge

N_FRAMES = 300


def route_poses(route: np.ndarray, n: int) -> np.ndarray:
    """n poses evenly spaced along the route polyline, heading along its tangent."""
    seg = np.diff(route, axis=0)
    length = np.hypot(seg[:, 0], seg[:, 1])
    start = np.concatenate([[0.0], np.cumsum(length)])
    s = np.linspace(0.0, start[-1], n, endpoint=False)
    k = np.clip(np.searchsorted(start, s, side="right") - 1, 0, len(seg) - 1)
    xy = route[k] + ((s - start[k]) / length[k])[:, None] * seg[k]
    return np.column_stack([xy, np.arctan2(seg[k, 1], seg[k, 0])])


@pytest.fixture(scope="module")
def replay():
    """(calibration, frames, poses) of a simulated walk along the thesis course."""
    world = load_world("thesis-course")
    cal = SimConfig().calibration()
    camera = SimDepthCamera(world, cal, DepthCameraConfig(), np.random.default_rng(0))
    poses = route_poses(np.asarray(world.route), N_FRAMES)
    frames = [
        DepthFrame(0.1 * k, camera.render(p), cal.depth_intrinsics) for k, p in enumerate(poses)
    ]
    return cal, frames, poses


@pytest.mark.slow
@pytest.mark.parametrize("model", ["log-odds", "view-count"])
def test_replay_map_equals_the_straightforward_reference(replay, model):
    cal, frames, poses = replay
    config = MapperConfig(grid=GridConfig(model=model))
    mapper = OccupancyMapper(cal, config)
    for k, (frame, pose) in enumerate(zip(frames, poses, strict=True)):
        mapper.integrate_depth(frame, pose, key=k)
    grid = mapper.grid
    # The reference maps a fixed window with a margin around everything the grid holds.
    (oi, oj), (ny, nx) = grid.lattice_offset, grid.shape
    margin = 20
    ref = ReferenceMapper(
        cal, config, (oi - margin, oj - margin), (ny + 2 * margin, nx + 2 * margin)
    )
    for frame, pose in zip(frames, poses, strict=True):
        ref.integrate_depth(frame, pose)
    inner = (slice(margin, margin + ny), slice(margin, margin + nx))
    for name, want in ref.layers.items():
        got = getattr(grid, name)  # the log_odds / views / hits layer
        assert np.count_nonzero(want) == np.count_nonzero(want[inner]), f"{name} beyond the grid"
        if name == "log_odds":
            np.testing.assert_allclose(got, want[inner], rtol=0, atol=1e-6)
            want_grid = OccupancyGrid(config.grid)  # same thresholds on the reference values
            want_grid._layers["log_odds"] = want[inner]
            np.testing.assert_array_equal(grid.trinary(), want_grid.trinary())
        else:
            np.testing.assert_array_equal(got, want[inner], err_msg=name)
    assert grid.occupied().sum() > 2000 and grid.free().sum() > 20000
    # Re-integrating the kept (compact) keyframes gives the same map again.
    before = {name: getattr(grid, name).copy() for name in ref.layers}
    mapper.rebuild()
    for name, want in before.items():
        np.testing.assert_array_equal(getattr(mapper.grid, name), want, err_msg=name)


def _scene_depths():
    """Depth images (uint16 and float) with returns beyond the range, holes and NaN."""
    cal = SimConfig().calibration()
    scene = [FLOOR, wall_at_x(5.5), Box((1.6, -0.6, 0.0), (2.2, 0.2, 0.9))]
    mm = depth_frame(cal.depth_intrinsics, cal.depth_mount, scene, (0.0, 0.0, 0.2)).depth_mm
    rng = np.random.default_rng(4)
    metres = mm / 1000.0
    metres[rng.random(mm.shape) < 0.1] = np.nan
    metres[rng.random(mm.shape) < 0.05] = np.inf
    return cal, [mm, metres]


@pytest.mark.parametrize("no_return_as_free", [False, True])
@pytest.mark.parametrize("stride", [1, 3])
def test_compact_projection_equals_compacting_the_points(no_return_as_free, stride):
    cal, (mm, metres) = _scene_depths()
    for depth, scale in ((mm, 0.001), (metres, 1.0)):
        cfg = DepthConfig(stride=stride, no_return_as_free=no_return_as_free, depth_scale_m=scale)
        args = (depth, cal.depth_intrinsics, cal.depth_mount, cal.depth_range_m)
        for quantum in (0.0125, 0.05, 1e-4):  # 1e-4: too fine for a bitmap, sorted instead
            fast = depth_to_compact_observation(*args, quantum, cfg)
            slow = depth_to_observation(*args, cfg).compacted(quantum)
            np.testing.assert_array_equal(fast.obstacles, slow.obstacles)
            np.testing.assert_array_equal(fast.ray_ends, slow.ray_ends)
            assert len(fast.obstacles) > 10 and len(fast.ray_ends) > 100


@pytest.mark.parametrize("heading", [0.0, np.pi / 4, -3.0, 2.0 * np.pi + 0.3, 1e4])
@pytest.mark.parametrize("half_fov", [0.5, np.pi / 4, np.pi / 2, 2.5, np.pi])
def test_wedge_test_equals_its_definition(heading, half_fov):
    rng = np.random.default_rng(1)
    view = ViewWedge(1.0, 2.0, half_fov)
    # A lattice through the sensor, with cells on the edges: ranges of exactly 1 and 2,
    # bearings of exactly ±π/4 and ±π/2 from a heading of 0 or π/4, and the sensor itself.
    x = np.concatenate([np.arange(-12, 13) * 0.25, rng.uniform(-2.5, 2.5, 40)])
    y = np.concatenate([np.arange(-12, 13) * 0.25, rng.uniform(-2.5, 2.5, 40)])
    want = _in_wedge_exact(x[None, :], y[:, None], heading, view)
    np.testing.assert_array_equal(_in_wedge(x, y, heading, view), want)
    assert want.any() and not want.all()
