"""The Foxglove live view, seen by a real WebSocket client speaking the SDK's protocol.

The client (`websockets`, in a thread of its own, like the Foxglove app in a process of
its own) negotiates the subprotocol the SDK serves, reads `serverInfo` and every
`advertise`, subscribes to every channel it is told about, and decodes the binary
message frames (opcode 0x01, uint32 subscription id, uint64 log time, payload): protobuf
payloads with a message class built from the FileDescriptorSet in the advertisement
only, JSON payloads as JSON.
"""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
from foxglove_client import SUBPROTOCOL, Client

from experiments.drag import Observed
from experiments.live_view import (
    FoxgloveView,
    RealtimePacer,
    ViewConfig,
    ViewError,
    grid_cells,
)
from experiments.pipeline import Pipeline
from hardware.calibration import WalkerCalibration
from hardware.messages import (
    BrakeCommand,
    CameraIntrinsics,
    DepthFrame,
    EncoderTicks,
    GroundTruthPose,
    LaserScan,
    RangeBearing,
    TagDetection,
    TagDetections,
    VelocityOdometry,
)
from mapping.mapper import OccupancyMapper
from slam.base import PoseEstimate, create
from slam.trajectory import Trajectory

FAST = ViewConfig(pose_hz=1e6, trajectory_hz=1e6, grid_hz=1e6, depth_hz=1e6, busy_fraction=1.0)


@pytest.fixture
def view():
    v = FoxgloveView(WalkerCalibration(), port=0, config=FAST)
    yield v
    v.close()


@pytest.fixture
def client(view):
    c = Client(view.url)
    c.wait(lambda: all(view.is_subscribed(t) for t in view.topics()), "the view's topics")
    yield c
    c.close()


def ns(t: float) -> int:
    return round(t * 1e9)


def stamp_ns(msg) -> int:
    return msg.timestamp.seconds * 1_000_000_000 + msg.timestamp.nanos


def yaw(q) -> float:
    return 2.0 * math.atan2(q.z, q.w)


def rotation(q) -> np.ndarray:
    x, y, z, w = q.x, q.y, q.z, q.w
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


# --------------------------------------------------------------------------- protocol


def test_server_info_and_the_advertised_topics_and_schemas(view, client):
    assert view.port > 0 and view.url.endswith(f":{view.port}")
    assert client.subprotocol == SUBPROTOCOL
    assert client.server_info is not None and client.server_info["name"] == "walker-slam"
    expected = {
        "/slam/pose": ("protobuf", "foxglove.PoseInFrame"),
        "/slam/estimate": ("json", "walker.PoseEstimate"),
        "/slam/pose/uncertainty": ("protobuf", "foxglove.SceneUpdate"),
        "/slam/trajectory": ("protobuf", "foxglove.PosesInFrame"),
        "/map": ("protobuf", "foxglove.Grid"),
        "/map/reference": ("protobuf", "foxglove.Grid"),
        "/tags/scene": ("protobuf", "foxglove.SceneUpdate"),
        "/tf": ("protobuf", "foxglove.FrameTransforms"),
    }
    for topic, (encoding, schema) in expected.items():
        ch = client.channels[topic]
        assert (ch["encoding"], ch["schemaName"]) == (encoding, schema), topic
    assert json.loads(client.channels["/slam/estimate"]["schema"])["required"] == [
        "t",
        "x",
        "y",
        "theta",
        "covariance",
    ]
    # The message types' channels, as the trial log has them, are there from the start.
    logged = {
        "/depth/image": ("protobuf", "foxglove.RawImage", "protobuf"),
        "/depth/camera_info": ("protobuf", "foxglove.CameraCalibration", "protobuf"),
        "/depth/image/exact": ("json", "walker.DepthFrameExact", "jsonschema"),
        "/brakes/command": ("json", "walker.BrakeCommand", "jsonschema"),
        "/encoders": ("json", "walker.EncoderTicks", "jsonschema"),
        "/scan": ("protobuf", "foxglove.LaserScan", "protobuf"),
        "/groundtruth/pose": ("protobuf", "foxglove.PoseInFrame", "protobuf"),
    }
    for topic, want in logged.items():
        ch = client.channels[topic]
        assert (ch["encoding"], ch["schemaName"], ch["schemaEncoding"]) == want, topic
    brake_schema = json.loads(client.channels["/brakes/command"]["schema"])
    assert {"t", "left_nm", "right_nm", "source"} <= set(brake_schema["properties"])
    assert set(logged) | set(expected) <= set(view.topics()) == set(client.channels)
    assert client.channels["/depth/camera_info"]["metadata"] == {"main_topic": "/depth/image"}
    assert client.statuses == []


def test_a_topic_of_its_own_is_advertised_with_its_first_message(view, client):
    assert "/brakes/replayed" not in client.channels
    first = BrakeCommand(1.0, 0.5, 0.5, "replay")
    view.publish(first, topic="/brakes/replayed")
    client.wait(lambda: view.is_subscribed("/brakes/replayed"), "the new topic's subscription")
    ch = client.channels["/brakes/replayed"]
    assert (ch["encoding"], ch["schemaName"]) == ("json", "walker.BrakeCommand")
    assert view.publish(BrakeCommand(1.5, 0.25, 0.75, "replay"), topic="/brakes/replayed")
    # (the first message reaches the client too when its subscription was quicker than
    # that first publish: a race the client cannot see; the second always does)
    client.wait(
        lambda: any(m["right_nm"] == 0.75 for _, m in client.messages("/brakes/replayed")),
        "the message published after the subscription",
    )
    msgs = client.messages("/brakes/replayed")
    assert [m["right_nm"] for _, m in msgs][-1] == 0.75 and len(msgs) <= 2


def test_depth_frame_pixels_and_its_camera_info(view, client):
    k = CameraIntrinsics.from_fov(160, 120, math.radians(57.0), math.radians(43.0))
    depth = np.random.default_rng(7).integers(0, 65536, (120, 160)).astype(np.uint16)
    frame = DepthFrame(1.25, depth, k)
    assert view.publish(frame)
    (log_ns, img), *_ = client.wait_count("/depth/image", 1)
    assert log_ns == ns(1.25) and stamp_ns(img) == ns(1.25)
    assert (img.width, img.height, img.encoding, img.step) == (160, 120, "16UC1", 320)
    assert img.frame_id == "depth_optical"
    np.testing.assert_array_equal(np.frombuffer(img.data, "<u2").reshape(120, 160), depth)
    (_, cal), *_ = client.wait_count("/depth/camera_info", 1)
    assert cal.frame_id == "depth_optical" and (cal.width, cal.height) == (160, 120)
    np.testing.assert_allclose(np.reshape(cal.K, (3, 3)), k.matrix)


def test_brake_command_and_encoder_ticks_as_json(view, client):
    view.publish(BrakeCommand(2.5, 1.75, 0.068, "safety"))
    view.publish(EncoderTicks(2.52, -41, 1234))
    (log_ns, cmd), *_ = client.wait_count("/brakes/command", 1)
    assert log_ns == ns(2.5)
    assert cmd == {"t": 2.5, "left_nm": 1.75, "right_nm": 0.068, "source": "safety"}
    (log_ns, ticks), *_ = client.wait_count("/encoders", 1)
    assert log_ns == ns(2.52) and (ticks["left"], ticks["right"]) == (-41, 1234)


def test_pose_covariance_and_transforms(view, client):
    cov = np.array([[0.04, 0.01, 0.0], [0.01, 0.09, 0.002], [0.0, 0.002, 0.0025]])
    assert view.publish_pose(PoseEstimate(3.0, np.array([1.5, -0.75, 2.9]), cov))
    (log_ns, pose), *_ = client.wait_count("/slam/pose", 1)
    assert log_ns == ns(3.0) and stamp_ns(pose) == ns(3.0) and pose.frame_id == "world"
    p = pose.pose.position
    assert (p.x, p.y, p.z) == (1.5, -0.75, 0.0)
    assert yaw(pose.pose.orientation) == pytest.approx(2.9, abs=1e-12)
    (_, est), *_ = client.wait_count("/slam/estimate", 1)
    assert (est["t"], est["x"], est["y"], est["theta"]) == (3.0, 1.5, -0.75, 2.9)
    assert est["covariance"] == cov.ravel().tolist()
    (_, tf), *_ = client.wait_count("/tf", 1)
    by_child = {f.child_frame_id: f for f in tf.transforms}
    walker = by_child["walker"]
    assert walker.parent_frame_id == "world" and stamp_ns(walker) == ns(3.0)
    assert (walker.translation.x, walker.translation.y) == (1.5, -0.75)
    assert yaw(walker.rotation) == pytest.approx(2.9, abs=1e-12)
    cal = WalkerCalibration()
    for child, mount in (("depth_optical", cal.depth_mount), ("tag_optical", cal.tag_mount)):
        f = by_child[child]
        want = mount.walker_T_optical()
        assert f.parent_frame_id == "walker"
        t = f.translation
        np.testing.assert_allclose([t.x, t.y, t.z], want[:3, 3], atol=1e-12)
        np.testing.assert_allclose(rotation(f.rotation), want[:3, :3], atol=1e-12)
    # The uncertainty ellipse: every point is on the 95 % contour of the position.
    (_, scene), *_ = client.wait_count("/slam/pose/uncertainty", 1)
    ring = scene.entities[0].lines[0]
    d = np.array([[q.x - 1.5, q.y + 0.75] for q in ring.points])
    m = np.einsum("ni,ij,nj->n", d, np.linalg.inv(cov[:2, :2]), d)
    np.testing.assert_allclose(m, 5.991, rtol=1e-9)


def test_a_long_trajectory_is_sent_evenly_thinned_with_its_ends(view, client):
    t = np.arange(5000) * 0.01
    poses = np.column_stack([t, np.sin(t), np.cos(t)])
    assert view.publish_trajectory(Trajectory(t, poses), 50.0)
    (_, msg), *_ = client.wait_count("/slam/trajectory", 1)
    got = np.array([[q.position.x, q.position.y, yaw(q.orientation)] for q in msg.poses])
    assert len(got) == 2000 and msg.frame_id == "world"
    np.testing.assert_allclose(got[[0, -1]], poses[[0, -1]], atol=1e-12)
    steps = np.rint(np.diff(got[:, 0]) / 0.01)  # evenly spread: every 2nd or 3rd pose
    assert set(steps.tolist()) == {2.0, 3.0}


def test_a_pose_without_a_time_is_not_published(view, client):
    assert not view.publish_pose(PoseEstimate(math.nan, np.zeros(3), np.eye(3)))


def test_occupancy_grid_size_origin_resolution_and_cells(view, client):
    mapper = OccupancyMapper(WalkerCalibration())
    scan = LaserScan(0.0, -0.4, 0.02, np.full(41, 1.5), 4.0)
    mapper.integrate_scan(scan, np.array([0.3, -0.2, 0.4]))
    grid = mapper.grid
    assert view.publish_grid(grid, 4.0)
    (log_ns, msg), *_ = client.wait_count("/map", 1)
    ny, nx = grid.shape
    assert log_ns == ns(4.0) and msg.frame_id == "world"
    assert msg.column_count == nx and len(msg.data) == ny * msg.row_stride
    assert msg.cell_stride == 5 and msg.row_stride == 5 * nx
    assert (msg.cell_size.x, msg.cell_size.y) == (grid.resolution, grid.resolution)
    assert (msg.pose.position.x, msg.pose.position.y) == grid.origin
    assert msg.pose.orientation.w == 1.0
    fields = {f.name: (f.offset, f.type) for f in msg.fields}
    assert fields["occupancy"][0] == 0 and fields["alpha"][0] == 4
    cells = np.frombuffer(msg.data, np.uint8).reshape(ny, nx, 5)
    occ = cells[..., 0].view(np.int8)
    known, p = grid.known(), grid.probability()
    assert np.all(occ[~known] == -1) and np.all(cells[..., 4][~known] == 0)
    assert np.all(np.abs(occ[known] - 100.0 * p[known]) <= 0.5)
    assert np.all(cells[..., 4][known] == 255)
    # A cell the beams hit is occupied, one they crossed is free: world point -> [iy, ix].
    hit = 0.3 + 1.5 * math.cos(0.4), -0.2 + 1.5 * math.sin(0.4)
    crossed = 0.3 + 0.7 * math.cos(0.4), -0.2 + 0.7 * math.sin(0.4)
    (hx, hy), (fx, fy) = grid.world_to_cell(np.array([hit, crossed]))
    assert occ[hy, hx] > 50 and cells[hy, hx, 1] < 128
    assert 0 <= occ[fy, fx] < 50 and cells[fy, fx, 1] > 128


class _FakeGrid:
    """What grid_cells reads of a grid: shape, known(), probability()."""

    def __init__(self, p: np.ndarray) -> None:
        self.p = p
        self.shape = p.shape

    def known(self) -> np.ndarray:
        return ~np.isnan(self.p)

    def probability(self) -> np.ndarray:
        return np.where(np.isnan(self.p), 0.5, self.p)


def test_a_large_grid_is_pooled_keeping_its_obstacles():
    p = np.full((5, 7), np.nan)
    p[0, 0], p[1, 1] = 0.2, 0.9  # a free and an occupied cell in the first block
    p[4, 6] = 0.3  # a free cell alone in the last block
    cells, k = grid_cells(_FakeGrid(p), max_cells=4)
    assert k == 4 and cells.shape == (2, 2, 5)
    occ = cells[..., 0].view(np.int8)
    assert occ.tolist() == [[90, -1], [-1, 30]]
    assert cells[..., 4].tolist() == [[255, 0], [0, 255]]
    full, k1 = grid_cells(_FakeGrid(p), max_cells=35)
    assert k1 == 1 and full[1, 1, 0].view(np.int8) == 90


def test_grid_cells_round_the_probability_to_percent_and_shade_it():
    p = np.array([[0.0, 0.004, 0.006, 0.494, 0.5, 0.555, 0.996, 1.0, np.nan]])
    cells, _ = grid_cells(_FakeGrid(p), max_cells=100)
    assert cells[0, :, 0].view(np.int8).tolist() == [0, 0, 1, 49, 50, 56, 100, 100, -1]
    grey = cells[0, :, 1].tolist()
    assert grey[0] == 255 and grey[7] == 0 and grey[:8] == sorted(grey[:8], reverse=True)
    assert grey[8] == 0 and cells[0, 8, 4] == 0 and (cells[0, :8, 4] == 255).all()
    assert (cells[0, :, 1] == cells[0, :, 2]).all() and (cells[0, :, 2] == cells[0, :, 3]).all()


def test_depth_images_are_rate_limited_in_run_and_wall_time():
    now = [0.0]
    cfg = ViewConfig(depth_hz=8.0)  # a period of 0.125 s: exact in binary
    with FoxgloveView(WalkerCalibration(), port=0, config=cfg, clock=lambda: now[0]) as v:
        c = Client(v.url)
        try:
            c.wait(lambda: all(v.is_subscribed(t) for t in v.topics()), "the view's topics")
            k = CameraIntrinsics.from_fov(16, 12, 1.0, 0.8)
            frame = DepthFrame(0.0, np.zeros((12, 16), np.uint16), k)
            assert v.publish(frame)
            sent = []
            for i in range(1, 33):  # 16 Hz for 2 s, the wall clock keeping pace
                now[0] = t = i * 0.0625
                sent.append(v.publish(DepthFrame(t, frame.depth_mm, k)))
            assert sent == [False, True] * 16
            now[0] = 2.0 + 1e-3  # run time goes on, wall time stands still: held back
            assert not v.publish(DepthFrame(2.5, frame.depth_mm, k))
            msgs = c.wait_count("/depth/image", 17)
            assert [ns_ for ns_, _ in msgs] == [ns(i * 0.0625) for i in range(0, 33, 2)]
            assert v.counts["depth_rate_limited"] == 17
            # Other messages are not limited: two at the same time both go out.
            assert v.publish(EncoderTicks(2.5, 1, 1)) and v.publish(EncoderTicks(2.5, 2, 2))
        finally:
            c.close()


def test_unencodable_messages_are_counted_not_raised(view, client):
    assert not view.publish(EncoderTicks(-1.0, 0, 0))
    assert not view.publish(EncoderTicks(math.nan, 0, 0))
    assert not view.publish(object())  # type: ignore[arg-type]
    assert view.counts == {"not_encodable:EncoderTicks": 2, "not_encodable:object": 1}


def test_tag_detections_go_out_as_logged_and_as_a_scene(view, client):
    tag_pose = np.eye(4)
    tag_pose[:3, 3] = (0.2, -0.1, 2.0)
    tags = TagDetections(
        5.0, (TagDetection(7, tag_pose, np.arange(8.0).reshape(4, 2), decision_margin=40.0),)
    )
    view.publish(TagDetections(4.9))
    view.publish(tags)
    (_, logged) = client.wait_count("/tags/detections", 2)[-1]
    assert logged["t"] == 5.0 and logged["detections"][0]["tag_id"] == 7
    scenes = client.wait_count("/tags/scene", 2)
    entity = scenes[-1][1].entities[0]
    assert entity.frame_id == "tag_optical" and entity.id == "tag7"
    position = entity.cubes[0].pose.position
    assert (position.x, position.y, position.z) == (0.2, -0.1, 2.0)
    assert entity.texts[0].text == "7"
    assert [d.type for d in scenes[0][1].deletions] == [1]  # each update replaces the last


# --------------------------------------------------------------------------- the pipeline


LANDMARKS = {1: (3.0, 0.0), 2: (0.0, 3.0), 3: (-3.0, 0.0), 4: (0.0, -3.0)}


def circle_stream(n: int = 160):
    """Velocity odometry at 20 Hz round a circle; every 0.2 s one RangeBearing per
    landmark, all of one time, with the ground truth between the first and the second
    (where FastSLAM still holds the first: asking it then would split the batch); a laser
    scan every 0.5 s."""
    rng = np.random.default_rng(5)
    x = y = th = 0.0
    v, w, dt = 0.5, 0.25, 0.05
    for k in range(n):
        t = dt * k
        yield VelocityOdometry(t, v, w)
        if k % 4 == 0 and k:
            for i, (lid, (lx, ly)) in enumerate(LANDMARKS.items()):
                r = math.hypot(lx - x, ly - y) + rng.normal(0, 0.05)
                b = math.atan2(ly - y, lx - x) - th + rng.normal(0, 0.01)
                yield RangeBearing(t, lid, r, b)
                if i == 0:
                    yield GroundTruthPose(t, x, y, th)
        if k % 10 == 5:
            yield LaserScan(t, -0.5, 0.05, np.full(21, 2.0), 4.0)
        x += v * dt * math.cos(th)
        y += v * dt * math.sin(th)
        th += w * dt


def run_fastslam(observers=()) -> Pipeline:
    cal = WalkerCalibration()
    pipeline = Pipeline(create("fastslam", cal, initial_pose=(0.0, 0.0, 0.0)), cal)
    pipeline.run(Observed(circle_stream(), [o(pipeline) for o in observers]))
    return pipeline


def test_replay_observer_publishes_the_state_and_leaves_the_results_alone(view, client):
    plain = run_fastslam()
    observer = None

    def attach(pipeline):
        nonlocal observer
        observer = view.observer(pipeline)
        return observer

    watched = run_fastslam([attach])
    observer.finish()
    # Asked for its state after every message, FastSLAM would give another path (the
    # batch split); the view asks only where that cannot happen.
    np.testing.assert_array_equal(
        watched.localizer.trajectory().poses, plain.localizer.trajectory().poses
    )
    assert watched.localizer.landmarks().keys() == plain.localizer.landmarks().keys()
    for lid, (mean, cov) in plain.localizer.landmarks().items():
        np.testing.assert_array_equal(watched.localizer.landmarks()[lid][0], mean)
        np.testing.assert_array_equal(watched.localizer.landmarks()[lid][1], cov)
    # The last pose, trajectory and map out are the final ones.
    final = watched.localizer.estimate()
    t_last = watched.recorded.t_last

    def last(topic):
        msgs = client.messages(topic) if topic in client.received else []
        return msgs[-1] if msgs else (None, None)

    client.wait(lambda: last("/slam/pose")[0] == ns(t_last), "the final pose")
    _, pose = last("/slam/pose")
    assert pose.pose.position.x == final.pose[0] and pose.pose.position.y == final.pose[1]
    assert yaw(pose.pose.orientation) == pytest.approx(final.pose[2], abs=1e-12)
    client.wait(lambda: last("/slam/trajectory")[0] == ns(t_last), "the final trajectory")
    traj = watched.localizer.trajectory()
    _, path = last("/slam/trajectory")
    assert len(path.poses) == len(traj)
    got = np.array([[q.position.x, q.position.y] for q in path.poses])
    np.testing.assert_array_equal(got, traj.poses[:, :2])
    client.wait(lambda: last("/map")[0] == ns(t_last), "the final map")
    _, grid = last("/map")
    assert grid.column_count == watched.mapper.grid.shape[1]
    assert len(client.messages("/slam/pose")) > 1  # published during the run too


def test_observe_is_the_call_for_a_live_loop(view, client):
    cal = WalkerCalibration()
    pipeline = Pipeline(create("dead-reckoning", cal, initial_pose=(1.0, 2.0, 0.5)), cal)
    for msg in (VelocityOdometry(0.0, 0.4, 0.0), VelocityOdometry(1.0, 0.4, 0.0)):
        pipeline.feed(msg)
        view.observe(pipeline, msg)
    msgs = client.wait_count("/slam/pose", 2)
    log_ns, pose = msgs[-1]
    est = pipeline.localizer.estimate()
    assert log_ns == ns(est.t)
    assert (pose.pose.position.x, pose.pose.position.y) == (est.pose[0], est.pose[1])
    assert pose.pose.position.x == pytest.approx(1.0 + 0.4 * math.cos(0.5))
    assert [m["t"] for _, m in client.wait_count("/odometry/velocity", 2)] == [0.0, 1.0]


def closed_loop(view: FoxgloveView | None):
    """Four seconds of the simulated thesis course in the live loop's shape (a command
    after every depth frame), the view attached as the live command would attach it."""
    from control.base import CONTROLLERS
    from experiments.pipeline import LoopConfig, run_closed_loop
    from hardware.sim.simulator import SimConfig, Simulator
    from hardware.sim.world import load_world

    world = load_world("thesis-course")
    sim = Simulator(world, SimConfig(seed=3, duration_s=4.0))
    cal = sim.calibration
    pipeline = Pipeline(create("dead-reckoning", cal, initial_pose=world.start_pose), cal)
    ctl = CONTROLLERS.create("open-loop", cal)
    loop = LoopConfig(trigger="frame", latency_s=0.0)
    if view is None:
        run_closed_loop(sim, sim, pipeline, ctl, loop)
        return pipeline, None
    obs = view.observer(pipeline)
    run_closed_loop(sim, sim, pipeline, ctl, loop, record=obs.record, on_command=obs.on_command)
    obs.finish()
    return pipeline, obs


def test_the_closed_loop_with_a_background_view_sends_everything_and_changes_nothing():
    cfg = ViewConfig(depth_hz=1e6)  # the camera's 10 Hz; the SLAM state at its defaults
    # the loop is not paced: it hands the view the whole run's ~600 messages in a fraction
    # of a second, which the default queue of 64 drops (counted) in a busy hour (1 run in
    # 20 beside four busy loops); a live loop's messages come at the sensors' rates
    with FoxgloveView(
        port=0, config=cfg, background=True, queue_size=10_000, message_backlog=100_000
    ) as view:
        client = Client(view.url)
        try:
            client.wait(lambda: all(view.is_subscribed(t) for t in view.topics()), "topics")
            pipeline, _ = closed_loop(view)
            assert view.flush()
            commands = pipeline.recorded.commands
            got = client.wait_count("/brakes/command", len(commands))
            assert [(m["t"], m["left_nm"], m["right_nm"]) for _, m in got] == [
                (c.t, c.left_nm, c.right_nm) for c in commands
            ]
            frames = pipeline.recorded.counts["DepthFrame"]
            images = client.wait_count("/depth/image", frames)
            assert len(images) == frames and images[0][1].width == 160
            for topic, items in client.received.items():  # log time never goes back
                assert all(a[0] <= b[0] for a, b in itertools.pairwise(items)), topic
            final = pipeline.localizer.estimate()
            client.wait(
                lambda: client.messages("/slam/pose")[-1][0] == ns(final.t), "the final pose"
            )
            assert client.messages("/slam/pose")[-1][1].pose.position.x == final.pose[0]
            assert view.counts.get("queue_full", 0) == 0 and view.last_error is None
        finally:
            client.close()
    # The same run without a view gives the same commands.
    plain, _ = closed_loop(None)
    assert [(c.t, c.left_nm, c.right_nm) for c in plain.recorded.commands] == [
        (c.t, c.left_nm, c.right_nm) for c in commands
    ]


# --------------------------------------------------------------------------- pacing


def test_a_realtime_observer_paces_the_replay(view):
    cal = WalkerCalibration()
    pipeline = Pipeline(create("dead-reckoning", cal), cal)
    obs = view.observer(pipeline, realtime=True, speed=50.0)
    assert obs.pacer is not None and obs.pacer.speed == 50.0
    pipeline.run(Observed([VelocityOdometry(t, 0.1, 0.0) for t in (0.0, 0.5, 1.0)], [obs]))
    assert obs.pacer.slept_s > 0.0
    assert view.observer(pipeline).pacer is None


class FakeTime:
    def __init__(self) -> None:
        self.now = 100.0
        self.sleeps: list[float] = []

    def clock(self) -> float:
        return self.now

    def sleep(self, s: float) -> None:
        self.sleeps.append(s)
        self.now += s


def test_realtime_pacer_sleeps_to_the_messages_times():
    ft = FakeTime()
    pacer = RealtimePacer(2.0, clock=ft.clock, sleep=ft.sleep)
    for t in (10.0, 10.5, 11.0, 11.0, 13.0):
        pacer.before(EncoderTicks(t, 0, 0))
        ft.now += 0.05  # the consumer's work
    assert ft.sleeps == pytest.approx([0.2, 0.2, 0.9])
    assert pacer.slept_s == pytest.approx(1.3)


def test_realtime_pacer_does_not_rush_after_falling_behind_or_for_stale_messages():
    ft = FakeTime()
    pacer = RealtimePacer(1.0, max_lag_s=1.0, clock=ft.clock, sleep=ft.sleep)
    pacer.before(EncoderTicks(0.0, 0, 0))
    ft.now += 5.0  # a slow localizer: 5 s for the first message
    pacer.before(EncoderTicks(0.1, 0, 0))  # 4.9 s late: the pace restarts here
    pacer.before(EncoderTicks(0.6, 0, 0))
    assert ft.sleeps == pytest.approx([0.5])
    pacer.before(EncoderTicks(0.2, 0, 0))  # older than the latest: no wait, no restart
    pacer.before(EncoderTicks(1.1, 0, 0))
    assert ft.sleeps == pytest.approx([0.5, 0.5])


def test_a_taken_port_is_a_one_line_error(view):
    with pytest.raises(ViewError, match=f"127.0.0.1:{view.port}") as err:
        FoxgloveView(port=view.port)
    assert "\n" not in str(err.value)


def test_view_config_rejects_nonsense():
    with pytest.raises(ValueError, match="grid_hz"):
        ViewConfig(grid_hz=0.0)
    with pytest.raises(ValueError, match="busy_fraction"):
        ViewConfig(busy_fraction=0.0)
    with pytest.raises(ValueError, match="speed"):
        RealtimePacer(0.0)
