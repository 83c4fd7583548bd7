"""The mapper: depth frames and scans at poses, keyframe memory and rebuild."""

from __future__ import annotations

import math

import numpy as np
import pytest
from synthetic_depth import FLOOR, Box, Plane, depth_frame

from hardware.calibration import WalkerCalibration
from hardware.messages import LaserScan
from mapping.grid import GridConfig, OccupancyGrid, ViewCountGrid
from mapping.mapper import MapperConfig, OccupancyMapper
from mapping.scan_points import ScanConfig

CAL = WalkerCalibration()
ROOM = [
    FLOOR,
    Plane((1.0, 0.0, 0.0), 4.0),
    Plane((0.0, 1.0, 0.0), 2.0),
    Plane((0.0, 1.0, 0.0), -2.0),
    Box((2.2, -0.4, 0.0), (2.8, 0.3, 0.9)),
]
TRUE_POSES = np.array(
    [[-1.0, 0.0, 0.0], [-0.6, 0.2, 0.3], [-0.2, 0.1, -0.4], [0.2, -0.3, 0.2], [0.5, 0.4, 0.9]]
)


def room_frames():
    return [depth_frame(CAL.depth_intrinsics, CAL.depth_mount, ROOM, tuple(p)) for p in TRUE_POSES]


def layers(mapper: OccupancyMapper) -> dict[str, np.ndarray]:
    g = mapper.grid
    if isinstance(g, OccupancyGrid):
        return {"log_odds": g.log_odds}
    assert isinstance(g, ViewCountGrid)
    return {"views": g.views, "hits": g.hits}


@pytest.mark.parametrize("model", ["log-odds", "view-count"])
def test_rebuild_at_corrected_poses_equals_the_map_built_at_them(model):
    rng = np.random.default_rng(11)
    config = MapperConfig(grid=GridConfig(model=model))
    frames = room_frames()
    wrong = TRUE_POSES + rng.normal(0.0, [0.15, 0.15, 0.1], TRUE_POSES.shape)
    direct, revised = OccupancyMapper(CAL, config), OccupancyMapper(CAL, config)
    for k, (f, good, bad) in enumerate(zip(frames, TRUE_POSES, wrong, strict=True)):
        direct.integrate_depth(f, good)
        revised.integrate_depth(f, bad, key=k)
    before = layers(revised)
    assert any(
        a.shape != b.shape or not np.array_equal(a, b)
        for a, b in zip(before.values(), layers(direct).values(), strict=True)
    )
    revised.rebuild({k: p for k, p in enumerate(TRUE_POSES)})
    assert revised.grid.origin == direct.grid.origin
    for name, want in layers(direct).items():
        np.testing.assert_array_equal(layers(revised)[name], want, err_msg=name)
    assert direct.grid.occupied().sum() > 100


def test_rebuild_keeps_unrevised_poses_and_forgets_unkeyed_frames():
    frames = room_frames()
    mapper = OccupancyMapper(CAL)
    mapper.integrate_depth(frames[0], TRUE_POSES[0], key="a")
    mapper.integrate_depth(frames[1], TRUE_POSES[1])  # unkeyed: integrated, not kept
    mapper.integrate_depth(frames[2], TRUE_POSES[2] + [0.3, 0.0, 0.0], key="c")
    mapper.rebuild({"c": TRUE_POSES[2]})
    only_kept = OccupancyMapper(CAL)
    only_kept.integrate_depth(frames[0], TRUE_POSES[0])
    only_kept.integrate_depth(frames[2], TRUE_POSES[2])
    np.testing.assert_array_equal(mapper.grid.log_odds, only_kept.grid.log_odds)
    np.testing.assert_array_equal(mapper.keyframe_pose("a"), TRUE_POSES[0])
    with pytest.raises(ValueError, match="'zzz'"):
        mapper.rebuild({"zzz": np.zeros(3)})
    with pytest.raises(ValueError, match=r"\(3,\)"):
        mapper.rebuild({"a": np.zeros(2)})
    np.testing.assert_array_equal(mapper.keyframe_pose("a"), TRUE_POSES[0])  # untouched


def test_keyframe_memory_is_compact_and_bounded():
    frames = room_frames()
    mapper = OccupancyMapper(CAL, MapperConfig(max_keyframes=3))
    for k, (f, p) in enumerate(zip(frames, TRUE_POSES, strict=True)):
        mapper.integrate_depth(f, p, key=k)
    assert list(mapper.keys()) == [2, 3, 4]
    # Snapped to 1.25 cm and deduplicated, a kept frame is smaller than its 38 kB depth
    # image (all 19200 rays as float32 points would take 154 kB).
    per_frame = mapper.keyframe_nbytes / 3
    assert per_frame < frames[0].depth_mm.nbytes
    mapper.forget(3)
    assert list(mapper.keys()) == [2, 4]


def test_depth_frame_lands_at_the_walker_pose():
    wall = [FLOOR, Plane((1.0, 0.0, 0.0), 2.41)]
    frame = depth_frame(CAL.depth_intrinsics, CAL.depth_mount, wall)
    for pose in ([0.0, 0.0, 0.0], [1.0, 2.0, math.pi / 2], [-3.0, 0.5, -2.5]):
        mapper = OccupancyMapper(CAL)
        for _ in range(2):
            mapper.integrate_depth(frame, np.array(pose))
        xy = mapper.occupied_xy()
        assert len(xy) > 15
        # Back in the walker frame, every occupied cell is within a cell of x = 2.41.
        c, s = math.cos(pose[2]), math.sin(pose[2])
        d = xy - pose[:2]
        x_walker = c * d[:, 0] + s * d[:, 1]
        assert np.all(np.abs(x_walker - 2.41) <= 0.05 * math.sqrt(2) / 2 + 0.025)


def test_view_count_mapper_counts_frames_in_the_kinect_wedge():
    wall = [FLOOR, Plane((1.0, 0.0, 0.0), 2.425)]
    frame = depth_frame(CAL.depth_intrinsics, CAL.depth_mount, wall)
    mapper = OccupancyMapper(CAL, MapperConfig(grid=GridConfig(model="view-count")))
    for _ in range(3):
        mapper.integrate_depth(frame, np.zeros(3))
    g = mapper.grid

    def at(layer, x, y):
        ix, iy = g.world_to_cell(np.array([[x, y]]))[0]
        return int(layer[iy, ix])

    camera_x = 0.41
    assert at(g.views, camera_x + 1.5, 0.0) == 3 and at(g.hits, camera_x + 1.5, 0.0) == 0
    assert at(g.views, 2.425, 0.0) == 3 and at(g.hits, 2.425, 0.0) == 3  # the wall
    assert at(g.views, camera_x + 0.5, 0.0) == 0  # nearer than 0.8 m
    assert at(g.views, camera_x + 2.0, 1.5) == 0  # outside ±28.5°
    assert at(g.views, camera_x + 4.0, 0.0) == 3  # behind the wall, but in the wedge
    wall_cells = g.occupied_xy()
    assert len(wall_cells) > 15 and np.all(np.abs(wall_cells[:, 0] - 2.425) < 1e-9)


def test_scan_returns_no_returns_and_range_cap():
    # Beams k = 0…6 at −0.3 + 0.1·k rad: hits at 2 m (k = 0) and 12 m (k = 6); k = 1…5
    # are no returns (inf, nan, 0, negative, = range_max).
    ranges = np.array([2.0, np.inf, np.nan, 0.0, -1.0, 30.0, 12.0])
    scan = LaserScan(0.0, -0.3, 0.1, ranges, 30.0)

    def beam(k: int, r: float) -> np.ndarray:
        return np.array([[r * math.cos(-0.3 + 0.1 * k), r * math.sin(-0.3 + 0.1 * k)]])

    def log_odds(mapper: OccupancyMapper, xy: np.ndarray) -> float:
        ix, iy = mapper.grid.world_to_cell(xy)[0]
        return float(mapper.grid.log_odds[iy, ix])

    def mapped(config: ScanConfig) -> OccupancyMapper:
        mapper = OccupancyMapper(config=MapperConfig(scan=config))
        mapper.integrate_scan(scan, np.zeros(3))
        return mapper

    plain = mapped(ScanConfig())
    hits = np.vstack([beam(0, 2.0), beam(6, 12.0)])
    np.testing.assert_allclose(plain.occupied_xy(), (np.floor(hits / 0.05) + 0.5) * 0.05)
    for k in (1, 2, 3, 4, 5):
        assert log_odds(plain, beam(k, 5.0)) == 0.0  # no return: nothing known
    capped = mapped(ScanConfig(max_range_m=10.0))
    assert len(capped.occupied_xy()) == 1  # the 12 m hit is beyond the cap…
    assert log_odds(capped, beam(6, 9.5)) < 0 and log_odds(capped, beam(6, 11.0)) == 0.0
    free = mapped(ScanConfig(no_return_as_free=True, max_range_m=10.0))
    for k in (1, 2, 3, 4, 5):  # …and no returns clear up to the cap when asked to
        assert log_odds(free, beam(k, 9.5)) < 0 and log_odds(free, beam(k, 10.5)) == 0.0


def test_scan_sensor_offset_is_applied():
    scan = LaserScan(0.0, 0.0, 0.1, np.array([1.0]), 30.0)
    mapper = OccupancyMapper()
    # Laser 0.2 m ahead and 0.1 m left, looking left; walker at (1, 1) facing +y.
    mapper.integrate_scan(
        scan, np.array([1.0, 1.0, math.pi / 2]), sensor_offset=(0.2, 0.1, math.pi / 2)
    )
    # Sensor in the world: (1 − 0.1, 1 + 0.2) facing −x; the hit is 1 m further along −x.
    np.testing.assert_allclose(mapper.occupied_xy(), [[-0.125, 1.225]])


def test_bad_poses_raise():
    mapper = OccupancyMapper()
    scan = LaserScan(0.0, 0.0, 0.1, np.array([1.0]), 30.0)
    with pytest.raises(ValueError, match=r"\(3,\)"):
        mapper.integrate_scan(scan, np.zeros(2))
    with pytest.raises(ValueError, match=r"\(3,\)"):
        mapper.integrate_scan(scan, np.zeros(3), sensor_offset=(0.0, 0.0))


def test_a_background_rebuild_gives_the_map_a_rebuild_would():
    """start_rebuild/finish_rebuild: the grid of rebuild() at the snapshot, plus the
    frames integrated while it ran, cell for cell."""
    from hardware.messages import DepthFrame

    rng = np.random.default_rng(5)
    cal = WalkerCalibration()
    k = cal.depth_intrinsics

    def frame(i):
        d = np.full((k.height, k.width), 1200 + 40 * (i % 7), np.uint16)
        d[: k.height // 3] = 0
        return DepthFrame(0.1 * i, d, k)

    poses = {i: np.array([0.05 * i, 0.02 * i, 0.03 * i]) for i in range(30)}
    revised = {i: p + rng.normal(0.0, 0.02, 3) for i, p in poses.items()}
    sync, bg = OccupancyMapper(cal), OccupancyMapper(cal)
    for m in (sync, bg):
        for i in range(20):
            m.integrate_depth(frame(i), poses[i], key=i)
    sync.rebuild({i: revised[i] for i in range(20)})
    job = bg.start_rebuild({i: revised[i] for i in range(20)})
    for m in (sync, bg):  # frames that come while the rebuild runs
        for i in range(20, 30):
            m.integrate_depth(frame(i), poses[i], key=i)
    bg.finish_rebuild(job)
    assert job.done
    assert bg.grid.origin == sync.grid.origin
    np.testing.assert_array_equal(bg.grid.probability(), sync.grid.probability())
    np.testing.assert_array_equal(bg.occupied_xy(), sync.occupied_xy())
    assert len(sync.occupied_xy()) > 50
    for i in range(20):
        np.testing.assert_array_equal(bg.keyframe_pose(i), sync.keyframe_pose(i))


def test_occupied_cells_follow_every_change_of_the_map():
    """occupied_xy is computed once per change of the map (a closed loop asks at every
    control step) and is the grid's own after each kind of change; it is read-only, so
    a caller cannot change what the next caller gets."""
    rng = np.random.default_rng(4)
    frames = room_frames()
    mapper = OccupancyMapper(CAL)

    def check() -> np.ndarray:
        xy = mapper.occupied_xy()
        np.testing.assert_array_equal(xy, mapper.grid.occupied_xy())
        assert mapper.occupied_xy() is xy and not xy.flags.writeable
        np.testing.assert_array_equal(mapper.occupied_xy(0.9), mapper.grid.occupied_xy(0.9))
        return xy

    assert len(check()) == 0
    for k, (f, pose) in enumerate(zip(frames[:3], TRUE_POSES, strict=False)):
        before = len(check())
        mapper.integrate_depth(f, pose, key=k)
        assert len(check()) > before  # each frame adds the walls it sees
    with pytest.raises(ValueError):
        mapper.occupied_xy()[0, 0] = 0.0
    moved = check()
    mapper.rebuild({k: TRUE_POSES[k] + rng.normal(0.0, 0.2, 3) for k in range(3)})
    assert not np.array_equal(check(), moved)
    faded = len(check())
    mapper.decay(0.1)
    assert len(check()) < faded
    mapper.integrate_depth(frames[3], TRUE_POSES[3], key=3)
    job = mapper.start_rebuild({k: TRUE_POSES[k] for k in range(4)})
    mapper.finish_rebuild(job)
    check()
    mapper.reset()
    assert len(check()) == 0
