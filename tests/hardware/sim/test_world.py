"""Worlds: JSON format and loading, furniture, tag frames, and the built-in courses'
geometry (route clearance, passage width, obstacles near the route, tags on surfaces)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from hardware.calibration import WalkerCalibration
from hardware.sim.collision import body_rectangle, point_polygon_distance
from hardware.sim.tag_camera import SimTagCamera, TagCameraConfig
from hardware.sim.world import (
    COLLISION_BAND_M,
    Box,
    Obstacle,
    TagPose,
    World,
    available_courses,
    chair_boxes,
    desk_boxes,
    load_world,
    office_chair_boxes,
    smooth_route,
    table_boxes,
)

# Walker footprint about its reference point (rear-axle centre): 0.10 m behind to 0.64 m
# ahead, 0.69 m wide (rear wheels included).
WALKER = (-0.10, 0.64, -0.345, 0.345)
CLEARANCE_M = 0.08
PASSAGE_M = 0.9
ABOVE_BASES_M = 0.2  # above an office chair's star base (0.1 m high)


def minimal_world(**kw) -> dict:
    d = {
        "name": "tiny",
        "bounds": [-1, 5, -1, 5],
        "start_pose": [0.0, 0.0, 0.0],
        "route": [[0.0, 0.0], [2.0, 0.0]],
        "obstacles": [
            {"kind": "table", "name": "t", "x": 3.0, "y": 0.0, "width": 1.2, "depth": 0.8}
        ],
        "tags": [],
    }
    d.update(kw)
    return d


# -- format and loading -------------------------------------------------------------------
def test_available_courses() -> None:
    assert {"thesis-course", "corner"} <= set(available_courses())


@pytest.mark.parametrize("name", ["thesis-course", "corner"])
def test_json_round_trip(name: str) -> None:
    w = load_world(name)
    d = w.to_dict()
    w2 = World.from_dict(json.loads(json.dumps(d)))
    assert w2.to_dict() == d
    np.testing.assert_array_equal(w2.box_array, w.box_array)
    np.testing.assert_array_equal(w2.route, w.route)
    assert w2.tags == w.tags and w2.obstacles == w.obstacles and w2.start_pose == w.start_pose


def test_load_by_path(tmp_path: Path) -> None:
    w = load_world("corner")
    p = tmp_path / "saved.json"
    p.write_text(json.dumps(w.to_dict()))
    assert load_world(p).to_dict() == w.to_dict()
    assert load_world(str(p)).to_dict() == w.to_dict()


def test_unknown_name_lists_valid_names() -> None:
    with pytest.raises(ValueError, match="unknown course 'nope'") as e:
        load_world("nope")
    assert "thesis-course" in str(e.value) and "corner" in str(e.value)


def test_malformed_files_name_the_file_and_the_problem(tmp_path: Path) -> None:
    bad_json = tmp_path / "broken.json"
    bad_json.write_text('{"name": "x",')
    with pytest.raises(ValueError) as e:
        load_world(bad_json)
    msg = str(e.value)
    assert str(bad_json) in msg and "not valid JSON" in msg and "\n" not in msg

    d = minimal_world()
    del d["obstacles"][0]["width"]
    missing = tmp_path / "missing.json"
    missing.write_text(json.dumps(d))
    with pytest.raises(ValueError) as e:
        load_world(missing)
    msg = str(e.value)
    assert str(missing) in msg and "obstacles[0]" in msg and "'width'" in msg and "\n" not in msg

    d = minimal_world()
    d["obstacles"][0]["colour"] = "red"
    typo = tmp_path / "typo.json"
    typo.write_text(json.dumps(d))
    with pytest.raises(ValueError, match=r"typo\.json.*unknown keys \['colour'\]"):
        load_world(typo)

    with pytest.raises(ValueError, match=r"missing.*cannot read"):
        load_world(tmp_path / "missing-file.json")


def test_tag_must_be_on_a_surface() -> None:
    # The front face of a table's outline at 0.35 m is the gap between its legs.
    d = minimal_world(tags=[{"id": 0, "on": "t", "face": "back", "z": 0.35}])
    with pytest.raises(ValueError, match=r"tag 0 .* is not on a box face"):
        World.from_dict(d)
    d = minimal_world(tags=[{"id": 0, "on": "t", "face": "back", "z": 0.735}])  # table-top edge
    w = World.from_dict(d)
    assert w.tags[0] == pytest.approx(TagPose(0, 2.6, 0.0, 0.735, math.pi))


def test_route_spec_is_smoothed_and_resampled() -> None:
    pts = [[0.0, 0.0], [3.0, 0.0], [3.0, 4.0]]
    route = smooth_route(pts, corner_radius=0.5, spacing=0.5)
    np.testing.assert_allclose(route[0], [0, 0])
    np.testing.assert_allclose(route[-1], [3, 4])
    assert np.hypot(*np.diff(route, axis=0).T).max() <= 0.5 + 1e-12
    # Fillet: points between the tangent points lie on the circle about (2.5, 0.5).
    arc = route[(route[:, 0] > 2.5) & (route[:, 1] < 0.5)]
    assert len(arc) >= 8
    np.testing.assert_allclose(np.hypot(arc[:, 0] - 2.5, arc[:, 1] - 0.5), 0.5, atol=1e-12)
    # A plain list is only split, so saved routes load back unchanged.
    w = World.from_dict(minimal_world(route=[[0, 0], [1.2, 0], [1.2, 0.4]]))
    np.testing.assert_allclose(w.route, [[0, 0], [0.4, 0], [0.8, 0], [1.2, 0], [1.2, 0.4]])


# -- geometry -------------------------------------------------------------------------
def test_furniture_boxes() -> None:
    table = table_boxes(1.0, 2.0, 0.0, width=1.2, depth=0.8, height=0.75)
    top, legs = table[0], table[1:]
    assert (top.sx, top.sy, top.z0, top.z1) == pytest.approx((0.8, 1.2, 0.72, 0.75))
    assert len(legs) == 4 and all(leg.z0 == 0 and leg.z1 == pytest.approx(0.72) for leg in legs)
    xs = sorted({round(leg.cx, 6) for leg in legs})
    assert xs == pytest.approx([1.0 - 0.4 + 0.055, 1.0 + 0.4 - 0.055])  # 5 cm legs, 3 cm inset
    desk = desk_boxes(0.0, 0.0, math.pi / 2, width=1.2, depth=0.6)
    panel = desk[-1]  # modesty panel on the front edge: facing +y for yaw 90°
    assert panel.cy + panel.sx / 2 == pytest.approx(0.3) and panel.z0 == pytest.approx(0.10)
    chair = chair_boxes(0.0, 0.0, 0.0)
    assert chair[0].z1 == pytest.approx(0.45)  # seat height
    back = chair[-1]
    assert back.cx < 0 and back.z1 == pytest.approx(0.85)


def test_office_chair_has_a_star_base_wider_than_its_seat() -> None:
    boxes = office_chair_boxes(1.0, 2.0, math.radians(30.0))
    seat, _column, back, *spokes = boxes
    assert seat.z1 == pytest.approx(0.47) and back.cx < 1.0 and back.z1 == pytest.approx(0.95)
    assert len(spokes) == 5 and all(b.z0 == 0.0 and b.z1 == pytest.approx(0.10) for b in spokes)
    # Spokes 72° apart, the first along the chair's heading, each reaching 0.33 m out.
    tips = [np.array([b.cx, b.cy]) - [1.0, 2.0] for b in spokes]
    angles = sorted(math.degrees(math.atan2(t[1], t[0])) % 360 for t in tips)
    np.testing.assert_allclose(np.diff(angles), 72.0, atol=1e-9)
    assert angles[0] == pytest.approx(30.0)
    reach = max(np.abs(b.corners() - [1.0, 2.0]).max() for b in spokes)
    assert reach > seat.sx / 2 + 0.05  # the base sticks out beyond the seat
    # What a user sees (above 0.2 m) is the seat and back, not the base.
    w = World.from_dict(
        minimal_world(obstacles=[{"kind": "office-chair", "name": "c", "x": 3, "y": 0}])
    )
    assert len(w.footprint_polygons(0.2, COLLISION_BAND_M[1])) == 3
    assert len(w.footprint_polygons()) == 8


def test_footprint_polygons_height_band() -> None:
    w = World.from_dict(
        minimal_world(
            obstacles=[
                {"kind": "table", "name": "t", "x": 3, "y": 0, "width": 1.2, "depth": 0.8},
                {
                    "kind": "box",
                    "name": "shelf",
                    "x": 0,
                    "y": 3,
                    "sx": 1,
                    "sy": 0.3,
                    "height": 2.0,
                    "z0": 1.2,
                },
            ]
        )
    )
    names = [n for n, _ in w.footprint_polygons()]
    assert names.count("t") == 5 and "shelf" not in names  # walker band 0–0.95 m
    assert [n for n, _ in w.footprint_polygons(0.05, 2.0)].count("shelf") == 1
    assert [n for n, _ in w.footprint_polygons(0.8, 2.0)] == ["shelf"]
    for _, p in w.footprint_polygons():
        x, y = p[:, 0], p[:, 1]
        assert 0.5 * (np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))) > 0  # CCW


@pytest.mark.parametrize("yaw", [0.0, 0.7, math.pi / 2, -2.5])
def test_world_T_tag_convention(yaw: float) -> None:
    w = World(
        "t", (0, 1, 0, 1), (), (TagPose(0, 1.0, 2.0, 0.35, yaw),), np.zeros((2, 2)), (0, 0, 0)
    )
    t = w.world_T_tag(w.tags[0])
    n = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    np.testing.assert_allclose(t[:3, 2], -n, atol=1e-12)  # z into the tag
    np.testing.assert_allclose(t[:3, 1], [0, 0, -1], atol=1e-12)  # y down
    # x is "right" for a viewer facing the tag (looking along -n, up = +z).
    np.testing.assert_allclose(t[:3, 0], np.cross(-n, [0, 0, 1]), atol=1e-12)
    np.testing.assert_allclose(t[:3, 3], [1.0, 2.0, 0.35])
    assert np.linalg.det(t[:3, :3]) == pytest.approx(1.0)


def test_world_validation() -> None:
    box = Box(0, 0, 0, 1, 1, 0, 1)
    with pytest.raises(ValueError, match="unique"):
        World(
            "w", (0, 1, 0, 1), (Obstacle("a", "box", (box,)),) * 2, (), np.zeros((2, 2)), (0, 0, 0)
        )
    with pytest.raises(ValueError, match="route"):
        World("w", (0, 1, 0, 1), (), (), np.zeros((1, 2)), (0, 0, 0))
    with pytest.raises(ValueError, match="kind"):
        Obstacle("a", "sofa", (box,))
    with pytest.raises(ValueError, match="z1 > z0"):
        Box(0, 0, 0, 1, 1, 1, 0.5)


# -- built-in courses -----------------------------------------------------------------
def sweep_poses(
    route: np.ndarray, step: float = 0.02, turn_step: float = math.radians(2)
) -> np.ndarray:
    """Poses along the route every `step` m, heading along each segment, plus in-place
    rotations from one segment's heading to the next at every waypoint."""
    poses = []
    for i in range(len(route) - 1):
        a, b = route[i], route[i + 1]
        h = math.atan2(b[1] - a[1], b[0] - a[0])
        n = max(1, math.ceil(np.hypot(*(b - a)) / step))
        poses += [(*(a + (b - a) * k / n), h) for k in range(n + 1)]
        if i + 2 < len(route):
            c = route[i + 2]
            dh = math.remainder(math.atan2(c[1] - b[1], c[0] - b[0]) - h, 2 * math.pi)
            m = max(1, math.ceil(abs(dh) / turn_step))
            poses += [(*b, h + dh * k / m) for k in range(m + 1)]
    return np.array(poses)


@pytest.mark.parametrize("name", ["thesis-course", "corner"])
def test_route_is_collision_free_with_clearance(name: str) -> None:
    # Clearance from everything reaching above the office chairs' star bases (0.1 m high,
    # under the way a user sees), and no contact with the bases themselves.
    w = load_world(name)
    poses = sweep_poses(w.route)
    rects = np.array([body_rectangle(p, *WALKER) for p in poses])
    dist, who = w.polygon_set(ABOVE_BASES_M, COLLISION_BAND_M[1]).clearances(rects, max_dist=0.5)
    worst = int(np.argmin(dist))
    assert dist[worst] >= CLEARANCE_M, f"{who[worst]} at {poses[worst]}: {dist[worst]:.3f} m"
    dist, who = w.polygon_set().clearances(rects, max_dist=0.5)
    assert dist.min() > 0.0, who[int(np.argmin(dist))]


@pytest.mark.parametrize("name", ["thesis-course", "corner"])
def test_route_spacing_and_start(name: str) -> None:
    w = load_world(name)
    assert np.hypot(*np.diff(w.route, axis=0).T).max() <= 0.5 + 1e-9
    x, y, th = w.start_pose
    np.testing.assert_allclose(w.route[0], [x, y])
    d = w.route[1] - w.route[0]
    assert abs(math.remainder(math.atan2(d[1], d[0]) - th, 2 * math.pi)) < 1e-9


def route_samples(route: np.ndarray, step: float = 0.02) -> np.ndarray:
    pts = [
        np.linspace(
            route[i],
            route[i + 1],
            max(2, math.ceil(np.hypot(*(route[i + 1] - route[i])) / step)),
            endpoint=False,
        )
        for i in range(len(route) - 1)
    ]
    return np.vstack([*pts, route[-1:]])


def nearest_obstacle(w: World, pts: np.ndarray, z_min: float = 0.0) -> np.ndarray:
    footprints = w.footprint_polygons(z_min, COLLISION_BAND_M[1])
    return np.min([point_polygon_distance(pts, p) for _, p in footprints], axis=0)


@pytest.mark.parametrize("name", ["thesis-course", "corner"])
def test_passages_are_at_least_90cm(name: str) -> None:
    # Every point of the route (every 2 cm) is >= 0.45 m from every obstacle footprint
    # above the office chairs' star bases (which reach under the way, as a chair's base
    # does under a desk): a 0.9 m wide band centred on the route is free, so no passage
    # on it is narrower, measured as a person measures a path between furniture.
    w = load_world(name)
    d = nearest_obstacle(w, route_samples(w.route), ABOVE_BASES_M)
    assert d.min() >= PASSAGE_M / 2 - 1e-9


def test_thesis_course_has_obstacles_next_to_the_route() -> None:
    # A user drifting 0.5 m sideways puts the walker's side 0.845 m from the route line.
    w = load_world("thesis-course")
    d = nearest_obstacle(w, route_samples(w.route))
    assert np.mean(d <= 0.5 + 0.345) >= 0.95
    assert np.mean(d <= 0.3 + 0.345) >= 0.3


def test_thesis_course_layout() -> None:
    w = load_world("thesis-course")
    walls = [o for o in w.obstacles if o.kind == "wall"]
    furniture = [o for o in w.obstacles if o.kind != "wall"]
    kinds = {o.kind for o in furniture}
    assert {"table", "desk", "office-chair"} <= kinds and len(furniture) >= 30
    inner = np.vstack([bx.corners() for o in furniture for bx in o.boxes])
    assert inner.min(axis=0) == pytest.approx([0.0, 0.0], abs=1e-9)
    assert inner.max(axis=0) == pytest.approx([10.5, 7.0], abs=1e-9)  # the 10.5 m × 7 m room
    assert len(walls) >= 4
    # Starts in the door (a gap in the south wall), facing into the room; ends near it.
    _, y, th = w.start_pose
    assert y == pytest.approx(0.0) and th == pytest.approx(math.pi / 2)
    assert np.hypot(*(w.route[-1] - w.route[0])) < 0.5
    length = np.hypot(*np.diff(w.route, axis=0).T).sum()
    assert 55 < length < 80
    # Spirals in: the route's farthest point from the start is near the room centre.
    mid = w.route[len(w.route) // 2]
    assert np.hypot(mid[0] - 5.25, mid[1] - 3.5) < 1.0


def test_corner_course_layout() -> None:
    w = load_world("corner")
    x, y, th = w.start_pose
    ahead = w.obstacle("wall-ahead").boxes[0].corners()
    right = w.obstacle("wall-right").boxes[0].corners()
    assert ahead[:, 0].min() - x == pytest.approx(4.0) and th == 0.0
    assert y - right[:, 1].max() == pytest.approx(0.6)
    assert w.route[:, 0].max() == pytest.approx(ahead[:, 0].min() - 1.0)  # turns 1 m before
    assert w.route[-1, 1] > y + 3.0  # then left, along the wall


def on_face(w: World, tag: TagPose, half: float) -> bool:
    """The whole tag square lies on an outward-facing box face (within 2 cm)."""
    for bx in (b for o in w.obstacles for b in o.boxes):
        c, s = math.cos(bx.yaw), math.sin(bx.yaw)
        lx = c * (tag.x - bx.cx) + s * (tag.y - bx.cy)
        ly = -s * (tag.x - bx.cx) + c * (tag.y - bx.cy)
        n_local = math.remainder(tag.yaw - bx.yaw, 2 * math.pi)
        for ang, off, along, extent in (
            (0.0, lx - bx.sx / 2, ly, bx.sy / 2),
            (math.pi, -lx - bx.sx / 2, ly, bx.sy / 2),
            (math.pi / 2, ly - bx.sy / 2, lx, bx.sx / 2),
            (-math.pi / 2, -ly - bx.sy / 2, lx, bx.sx / 2),
        ):
            if (
                abs(math.remainder(n_local - ang, 2 * math.pi)) < 1e-6
                and abs(off) <= 0.02
                and abs(along) + half <= extent + 1e-9
                and bx.z0 - 1e-9 <= tag.z - half
                and tag.z + half <= bx.z1 + 1e-9
            ):
                return True
    return False


@pytest.mark.parametrize("name", ["thesis-course", "corner"])
def test_tags_are_on_surfaces_facing_out(name: str) -> None:
    w = load_world(name)
    half = WalkerCalibration().tag_size_m / 2
    assert [t.tag_id for t in w.tags] == list(range(len(w.tags)))
    for t in w.tags:
        assert 0.30 <= t.z <= 0.40
        assert on_face(w, t, half), f"tag {t.tag_id} is not on a box face"
        # Facing away from the surface: a point 5 cm in front of the tag is in free space.
        p = np.array([t.x, t.y]) + 0.05 * np.array([math.cos(t.yaw), math.sin(t.yaw)])
        assert nearest_obstacle(w, p[None])[0] > 0.0
    assert (w.tag_host_boxes >= 0).all()


@pytest.mark.parametrize("name", ["thesis-course", "corner"])
def test_every_tag_is_seen_from_the_route(name: str) -> None:
    w = load_world(name)
    cam = SimTagCamera(
        w, WalkerCalibration(), TagCameraConfig(pixel_noise_px=0.0), np.random.default_rng(0)
    )
    poses = sweep_poses(w.route, step=0.1, turn_step=math.radians(10))
    seen = [[v.tag_id for v in cam.visible(p)] for p in poses]
    assert {i for s in seen for i in s} == {t.tag_id for t in w.tags}
    if name == "thesis-course":
        # Along the thesis course a tag is in view at least every ~2 m of route.
        along = np.concatenate([[0], np.cumsum(np.hypot(*np.diff(poses[:, :2], axis=0).T))])
        with_tag = along[[bool(s) for s in seen]]
        gaps = np.diff(np.concatenate([[0], with_tag, [along[-1]]]))
        assert gaps.max() < 2.5
        assert len(w.tags) >= 25


def test_a_course_can_say_how_its_route_is_walked(tmp_path: Path) -> None:
    """`user` sets UserParams fields for the course (the umbmark course's sighted helper);
    it round-trips, and a wrong name or type names the file and the field."""
    world = load_world("umbmark")
    assert world.user["sighted"] is True and world.user["speed_mps"] == 0.5
    assert World.from_dict(world.to_dict()).user == world.user
    assert "user" not in load_world("corner").to_dict()  # other courses are unchanged
    for user, needle in [
        ({"sightd": True}, "unknown setting 'sightd'"),
        ({"sighted": 1}, "'sighted' must be true or false"),
        ({"speed_mps": True}, "'speed_mps' must be a finite number"),
        ({"speed_mps": "fast"}, "'speed_mps' must be a finite number"),
        ([1], "'user' must be an object"),
    ]:
        d = minimal_world()
        d["user"] = user
        f = tmp_path / "walked.json"
        f.write_text(json.dumps(d))
        with pytest.raises(ValueError, match=r"walked\.json") as e:
            load_world(f)
        assert needle in str(e.value) and "\n" not in str(e.value)
