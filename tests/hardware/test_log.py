"""Trial logs: round trip of every message type, MCAP/Foxglove compatibility, crash safety."""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import struct
import subprocess
import sys
import threading
import time
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from foxglove_schemas_protobuf.LaserScan_pb2 import LaserScan as PbLaserScan
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from mcap.reader import make_reader
from mcap.writer import Writer
from mcap_protobuf.decoder import DecoderFactory

import hardware.log as log_module
import hardware.log.reader as log_reader
from hardware.calibration import Mount, WalkerCalibration
from hardware.log import (
    TOPICS,
    LogError,
    LogRecoveryWarning,
    LogWriter,
    UnsupportedChannelWarning,
    read_log,
    replay,
)
from hardware.messages import (
    BrakeCommand,
    CameraIntrinsics,
    Collision,
    DepthFrame,
    EncoderTicks,
    GroundTruthPose,
    GyroRate,
    LaserScan,
    RangeBearing,
    RangeBearings,
    TagDetection,
    TagDetections,
    VelocityOdometry,
)

REPO = Path(__file__).resolve().parents[2]
AWKWARD_T = 1234567890.123456789 / 3


def assert_same(a: Any, b: Any) -> None:
    """Field-by-field equality: floats bit-exact (NaN == NaN), arrays same dtype and values."""
    if is_dataclass(a):
        assert type(a) is type(b)
        for f in fields(a):
            assert_same(getattr(a, f.name), getattr(b, f.name))
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray)
        assert (a.dtype, a.shape) == (b.dtype, b.shape)
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f")
    elif isinstance(a, tuple):
        assert isinstance(b, tuple) and len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            assert_same(x, y)
    elif isinstance(a, float):
        assert isinstance(b, float)
        assert (math.isnan(a) and math.isnan(b)) or struct.pack("<d", a) == struct.pack("<d", b)
    else:
        assert type(a) is type(b) and a == b


def depth(rng: np.random.Generator, k: CameraIntrinsics) -> np.ndarray:
    d = rng.integers(0, 65536, size=(k.height, k.width), dtype=np.uint16)
    d[0, 0], d[-1, -1], d[1, 2] = 0, 65535, 65535
    return d


def every_message(rng: np.random.Generator) -> list[Any]:
    """One or more messages of every type, with awkward values, in time order."""
    small = WalkerCalibration().depth_intrinsics
    vga = CameraIntrinsics.from_fov(640, 480, 1.0821, 0.8482)
    pose = np.eye(4)
    pose[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    pose[:3, 3] = rng.normal(size=3)
    scan = rng.uniform(0.1, 5.0, 360).astype(np.float32)
    scan[[3, 4, 5]] = [np.inf, np.nan, -np.inf]
    return [
        EncoderTicks(0.0, -12345, 2**40),
        EncoderTicks(1e-9 / 3, 0, -1),
        BrakeCommand(0.1 + 0.2, 0.068, 3.95),
        BrakeCommand(0.3, 1 / 3, -0.0, source="replay"),
        TagDetections(0.35),
        TagDetections(
            0.4,
            (
                TagDetection(7, pose, rng.uniform(0, 640, (4, 2))),
                TagDetection(8, np.eye(4), rng.uniform(0, 640, (4, 2)), decision_margin=42.5),
            ),
        ),
        RangeBearing(0.5, 3, 2.0000000000000004, -math.pi),
        RangeBearings.of(0.55, [], [], []),
        RangeBearings.of(
            0.56, [4, -1, 2**40], [1 / 3, math.inf, 0.0], [-math.pi, math.nan, 1e-300]
        ),
        VelocityOdometry(0.6, -0.25, math.inf),
        LaserScan(0.7, -math.pi, 2 * math.pi / 360, scan, 3.5),
        LaserScan(0.71, 0.1, 0.7 / 3, rng.uniform(0, 2, 5), math.inf),
        GroundTruthPose(0.8, 1e6 / 7, -2.5, 3.0000001),
        GroundTruthPose(0.9, 0.0, 0.0, -math.pi),
        Collision(1.0, "rear-wheel", "table 2", 0.125, -7.5),
        DepthFrame(AWKWARD_T, depth(rng, small), small),
        DepthFrame(AWKWARD_T + 0.1, depth(rng, vga), vga),
        LaserScan(AWKWARD_T + 0.2, 0.0, 1e-3 / 3, np.array([], np.float32), 1 / 3),
        GroundTruthPose(AWKWARD_T + 0.3, -0.0, 5e-324, 2 * math.pi / 3),
        EncoderTicks(AWKWARD_T + 1, 1, 2),
    ]


def write_log(path: Path, msgs: list[Any], **kw: Any) -> None:
    with LogWriter(path, WalkerCalibration(), **kw) as w:
        for m in msgs:
            w.write(m)


def read_all(path: Path, **kw: Any) -> list[Any]:
    return list(read_log(path).messages(**kw))


# ---------------------------------------------------------------- round trip


def test_every_message_type_round_trips_exactly(tmp_path: Path) -> None:
    msgs = every_message(np.random.default_rng(0))
    path = tmp_path / "trial.mcap"
    write_log(path, msgs)
    log = read_log(path)
    assert log.complete and log.message_count == len(msgs)
    assert set(log.topics) == {TOPICS[type(m)] for m in msgs}
    got = list(log.messages())
    assert len(got) == len(msgs)
    for a, b in zip(msgs, got, strict=True):
        assert_same(a, b)
    scan = got[10]
    assert abs(scan.angle_increment - 2 * math.pi / 360) < 1e-12
    assert np.isnan(scan.ranges[4]) and np.isposinf(scan.ranges[3])
    assert not got[15].depth_mm.flags.writeable  # messages are immutable


def test_custom_topic_keeps_streams_apart(tmp_path: Path) -> None:
    path = tmp_path / "brakes.mcap"
    with LogWriter(path, WalkerCalibration()) as w:
        w.write(BrakeCommand(0.0, 1.0, 2.0))
        w.write(BrakeCommand(0.0, 3.0, 4.0, "replay"), topic="/brakes/replayed")
        w.write(
            DepthFrame(0.1, np.zeros((2, 3), np.uint16), CameraIntrinsics(3, 2, 1, 1, 1, 1)), "/d2"
        )
        with pytest.raises(ValueError, match=r"holds walker\.BrakeCommand"):
            w.write(EncoderTicks(0.2, 1, 1), topic="/brakes/replayed")
    log = read_log(path)
    assert log.topics == {
        "/brakes/command": BrakeCommand,
        "/brakes/replayed": BrakeCommand,
        "/d2": DepthFrame,
    }
    assert [m.left_nm for m in log.messages(["/brakes/replayed"])] == [3.0]
    assert [type(m) for m in replay(path, topics=["/d2"])] == [DepthFrame]


def test_gyro_rates_round_trip_exactly_on_their_json_channel(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    rates = [0.0, -0.0, 1 / 3, -2.5e-7, math.pi, math.inf, -math.inf, math.nan]
    rates += list(rng.normal(0.0, 0.5, 50))
    msgs = [GyroRate(0.01 * i + 1e-9 / 3, r) for i, r in enumerate(rates)]
    msgs.insert(3, EncoderTicks(0.025, 4, -5))  # interleaved with another stream
    path = tmp_path / "gyro.mcap"
    write_log(path, msgs)
    log = read_log(path)
    assert log.topics == {"/imu/gyro": GyroRate, "/encoders": EncoderTicks}
    got = list(log.messages())
    assert len(got) == len(msgs) == 59
    for a, b in zip(msgs, got, strict=True):
        assert_same(a, b)
    with open(path, "rb") as f:  # a plain MCAP reader sees the JSON channel and schema
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        (channel,) = [c for c in summary.channels.values() if c.topic == "/imu/gyro"]
        schema = summary.schemas[channel.schema_id]
        assert (schema.name, schema.encoding, channel.message_encoding) == (
            "walker.GyroRate",
            "jsonschema",
            "json",
        )
        assert json.loads(schema.data)["required"] == ["t", "rate_rad_s"]
        first = next(m for _, c, m in reader.iter_messages(topics=["/imu/gyro"]))
        assert json.loads(first.data) == {"t": 1e-9 / 3, "rate_rad_s": 0.0}


def test_metadata_calibration_and_attachments_round_trip(tmp_path: Path) -> None:
    cal = WalkerCalibration(
        wheel_diameter_m=0.204, track_m=0.68, depth_mount=Mount(0.4, 0.01, 0.5, pitch=0.1)
    )
    meta = {
        "config": {"localizer": "fastslam", "particles": 100, "noise": [0.1, 1e-300]},
        "world": {"walls": [[0, 0, 5, 0]], "tags": {"3": [1.5, 2.0]}, "name": "course Ω"},
    }
    path = tmp_path / "meta.mcap"
    with LogWriter(path, cal, meta, {"map.png": b"\x89PNG\x00\xff"}) as w:
        w.write(EncoderTicks(0.0, 1, 1))
    log = read_log(path)
    assert log.calibration == cal
    assert log.metadata == meta
    assert log.attachments == {"map.png": b"\x89PNG\x00\xff"}
    assert log.message_count == 1 and log.time_range == (0.0, 0.0)
    with open(path, "rb") as f:  # plain MCAP: one record per dict, a single key "json"
        records = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert set(records) == {"calibration", "config", "world"}
    assert json.loads(records["calibration"]["json"]) == json.loads(json.dumps(cal.to_dict()))


def test_metadata_written_at_the_end_round_trips(tmp_path: Path) -> None:
    """A record added after the messages (what a run knows only when it ends) reads back
    with the rest; bad input is refused as at the start; a closed writer takes none."""
    path = tmp_path / "late.mcap"
    with LogWriter(path, WalkerCalibration(), {"config": {"a": 1}}) as w:
        for k in range(60):  # past a chunk boundary (0.5 s)
            w.write(EncoderTicks(0.02 * k, k, k))
        w.add_metadata("slip", {"k_effective": [0.1, None]})
        with pytest.raises(ValueError, match="reserved"):
            w.add_metadata("calibration", {})
        with pytest.raises(ValueError, match="strict JSON"):
            w.add_metadata("x", {"v": math.inf})
    with pytest.raises(ValueError, match="closed"):
        w.add_metadata("late", {})
    log = read_log(path)
    assert log.metadata == {"config": {"a": 1}, "slip": {"k_effective": [0.1, None]}}
    assert log.message_count == 60


def test_writer_rejects_bad_input(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="reserved"):
        LogWriter(tmp_path / "a.mcap", WalkerCalibration(), {"calibration": {}})
    with pytest.raises(ValueError, match="strict JSON"):
        LogWriter(tmp_path / "b.mcap", WalkerCalibration(), {"config": {"x": math.nan}})
    with LogWriter(tmp_path / "c.mcap", WalkerCalibration()) as w:
        for t in (-0.1, math.nan, math.inf):
            with pytest.raises(ValueError, match="finite and >= 0"):
                w.write(EncoderTicks(t, 0, 0))
        with pytest.raises(TypeError, match="cannot log"):
            w.write("hello")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="closed"):
        w.write(EncoderTicks(0.0, 0, 0))


# ---------------------------------------------------------------- MCAP / Foxglove compatibility


def test_plain_mcap_reader_sees_standard_schemas(tmp_path: Path) -> None:
    msgs = every_message(np.random.default_rng(0))
    path = tmp_path / "trial.mcap"
    write_log(path, msgs)
    expected = {
        "/encoders": ("walker.EncoderTicks", "json", "jsonschema"),
        "/brakes/command": ("walker.BrakeCommand", "json", "jsonschema"),
        "/tags/detections": ("walker.TagDetections", "json", "jsonschema"),
        "/range_bearing": ("walker.RangeBearing", "json", "jsonschema"),
        "/range_bearings": ("walker.RangeBearings", "json", "jsonschema"),
        "/odometry/velocity": ("walker.VelocityOdometry", "json", "jsonschema"),
        "/collisions": ("walker.Collision", "json", "jsonschema"),
        "/depth/image": ("foxglove.RawImage", "protobuf", "protobuf"),
        "/depth/camera_info": ("foxglove.CameraCalibration", "protobuf", "protobuf"),
        "/depth/image/exact": ("walker.DepthFrameExact", "json", "jsonschema"),
        "/scan": ("foxglove.LaserScan", "protobuf", "protobuf"),
        "/scan/exact": ("walker.LaserScanExact", "json", "jsonschema"),
        "/groundtruth/pose": ("foxglove.PoseInFrame", "protobuf", "protobuf"),
        "/groundtruth/pose/exact": ("walker.GroundTruthPoseExact", "json", "jsonschema"),
    }
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None
        seen = {
            c.topic: (
                summary.schemas[c.schema_id].name,
                c.message_encoding,
                summary.schemas[c.schema_id].encoding,
            )
            for c in summary.channels.values()
        }
        assert seen == expected
        for schema in summary.schemas.values():
            if schema.encoding == "jsonschema":
                assert_foxglove_json_schema(json.loads(schema.data))
        companions = {DepthFrame: 2, LaserScan: 1, GroundTruthPose: 1}
        n_records = sum(1 + companions.get(type(m), 0) for m in msgs)
        assert summary.statistics.message_count == n_records
        assert len(list(reader.iter_messages())) == n_records
        decoded = list(reader.iter_decoded_messages(topics=["/depth/image", "/scan"]))
        raw = list(reader.iter_messages(topics=["/encoders", "/tags/detections"]))
    images = [d.decoded_message for d in decoded if d.channel.topic == "/depth/image"]
    assert [(i.encoding, i.frame_id, i.width, i.height) for i in images] == [
        ("16UC1", "depth_optical", 160, 120),
        ("16UC1", "depth_optical", 640, 480),
    ]
    first_depth = msgs[15].depth_mm
    assert np.array_equal(np.frombuffer(images[0].data, "<u2").reshape(120, 160), first_depth)
    scan = next(d for d in decoded if d.channel.topic == "/scan")
    assert scan.decoded_message.start_angle == -math.pi
    assert scan.message.log_time == scan.message.publish_time == round(0.7 * 1e9)
    assert json.loads(raw[0][2].data) == {"t": 0.0, "left": -12345, "right": 2**40}
    tags = [json.loads(m.data) for _, c, m in raw if c.topic == "/tags/detections"]
    margin = tags[1]["detections"][0]["decision_margin"]
    assert margin == "NaN"


def assert_foxglove_json_schema(schema: dict[str, Any]) -> None:
    """What Foxglove's JSON Schema parser accepts: objects, one type per field, no nested arrays."""
    assert schema["type"] == "object"
    for prop in schema["properties"].values():
        assert prop["type"] in {"boolean", "string", "number", "integer", "object", "array"}
        if prop["type"] == "object":
            assert_foxglove_json_schema(prop)
        if prop["type"] == "array":
            assert prop["items"]["type"] != "array"
            if prop["items"]["type"] == "object":
                assert_foxglove_json_schema(prop["items"])


def test_foxglove_messages_carry_the_standard_fields(tmp_path: Path) -> None:
    k = CameraIntrinsics(4, 3, 10.5, 11.25, 1.5, 1.0)
    path = tmp_path / "fox.mcap"
    write_log(
        path,
        [
            DepthFrame(2.5, np.arange(12, dtype=np.uint16).reshape(3, 4), k),
            GroundTruthPose(3.0, 1.0, 2.0, math.pi / 2),
            LaserScan(3.5, -1.0, 0.5, np.array([1.0, 2.0, 3.0], np.float32), 4.0),
        ],
    )
    with open(path, "rb") as f:
        out = {
            d.channel.topic: d.decoded_message
            for d in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
                topics=["/depth/camera_info", "/groundtruth/pose", "/scan"]
            )
        }
    cal = out["/depth/camera_info"]
    assert (cal.width, cal.height, cal.frame_id) == (4, 3, "depth_optical")
    assert list(cal.K) == [10.5, 0, 1.5, 0, 11.25, 1.0, 0, 0, 1]
    assert list(cal.P) == [10.5, 0, 1.5, 0, 0, 11.25, 1.0, 0, 0, 0, 1, 0]
    assert (cal.timestamp.seconds, cal.timestamp.nanos) == (2, 500_000_000)
    pose = out["/groundtruth/pose"]
    assert pose.frame_id == "world" and pose.pose.position.x == 1.0
    q = pose.pose.orientation
    assert np.allclose([q.x, q.y, q.z, q.w], [0, 0, math.sqrt(0.5), math.sqrt(0.5)])
    scan = out["/scan"]
    assert (scan.start_angle, scan.end_angle, list(scan.ranges)) == (-1.0, 0.0, [1, 2, 3])


# ---------------------------------------------------------------- ordering


def test_messages_come_out_in_log_time_order(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    times = rng.uniform(0, 3, 300).round(2)  # many ties
    path = tmp_path / "shuffled.mcap"
    written = []
    with LogWriter(path, WalkerCalibration(), background_flush=False) as w:
        for i, t in enumerate(times):
            msg = (
                EncoderTicks(float(t), i, -i)
                if i % 3
                else VelocityOdometry(float(t), float(i), 0.0)
            )
            w.write(msg)
            written.append(msg)
            if i % 37 == 0:
                w.flush()  # chunks that overlap in time
    order = sorted(range(len(written)), key=lambda i: written[i].t)  # stable: ties in write order
    got = read_all(path)
    for i, msg in zip(order, got, strict=True):
        assert_same(written[i], msg)
    enc = read_all(path, topics=["/encoders"])
    assert [m.left for m in enc] == [i for i in order if i % 3]


def test_order_within_chunks_that_follow_each_other_in_time(tmp_path: Path) -> None:
    """Chunks disjoint in time, messages shuffled (with ties) inside each chunk."""
    rng = np.random.default_rng(1)
    path = tmp_path / "blocks.mcap"
    written = []
    with LogWriter(path, WalkerCalibration(), background_flush=False) as w:
        for block in range(8):
            times = block + rng.integers(0, 10, 40) / 10.0  # [block, block + 0.9], ties
            for i, t in enumerate(times):
                msg = EncoderTicks(float(t), block * 100 + i, 0)
                w.write(msg)
                written.append(msg)
            w.flush()
    expected = sorted(written, key=lambda m: m.t)  # stable: ties in write order
    assert [m.left for m in read_all(path)] == [m.left for m in expected]


def test_writers_on_several_threads(tmp_path: Path) -> None:
    path = tmp_path / "threads.mcap"
    with LogWriter(path, WalkerCalibration()) as w:

        def produce(k: int) -> None:
            for i in range(200):
                w.write(EncoderTicks(i / 100, k, i), topic=f"/encoders/{k}")

        threads = [threading.Thread(target=produce, args=(k,)) for k in range(4)]
        for th in threads:
            th.start()
        for th in threads:
            th.join()
    log = read_log(path)
    assert log.message_count == 800
    for k in range(4):
        assert [m.right for m in log.messages([f"/encoders/{k}"])] == list(range(200))


# ---------------------------------------------------------------- crash safety


def test_flushes_every_half_second_of_log_time_and_wall_time(tmp_path: Path) -> None:
    path = tmp_path / "live.mcap"
    w = LogWriter(path, WalkerCalibration(), background_flush=False)
    for i in range(50):  # 0.00 .. 0.49 s of log time, written at once
        w.write(EncoderTicks(i / 100, i, i))
    assert (w.message_count, w.flushed_count) == (50, 0)
    w.write(EncoderTicks(0.5, 50, 50))
    assert w.flushed_count == 51
    w.write(EncoderTicks(0.51, 51, 51))
    time.sleep(0.55)
    w.write(EncoderTicks(0.52, 52, 52))  # log time barely moved, wall time did
    assert w.flushed_count == 53
    with pytest.warns(LogRecoveryWarning, match="53 messages"):
        assert len(read_all(path)) == 53  # readable while the writer is still open
    w.close()

    with LogWriter(tmp_path / "idle.mcap", WalkerCalibration()) as w:
        w.write(EncoderTicks(0.0, 0, 0))
        deadline = time.monotonic() + 2.0
        while w.flushed_count == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert w.flushed_count == 1  # the background flush caught the idle writer


STREAM_SRC = '''
import numpy as np
from hardware.calibration import WalkerCalibration
from hardware.messages import DepthFrame, EncoderTicks

def stream(n):
    """Encoder ticks at 100 Hz of log time and a depth frame with every 10th tick."""
    k = WalkerCalibration().depth_intrinsics
    base = np.arange(k.height * k.width, dtype=np.uint32).reshape(k.height, k.width)
    for i in range(n):
        t = i / 100
        yield EncoderTicks(t, i, -2 * i)
        if i % 10 == 0:
            yield DepthFrame(t, ((base * (i + 1)) % 65536).astype(np.uint16), k)
'''

CHILD_SRC = """
import sys, time
sys.path.insert(0, {repo!r})
{stream}
from hardware.calibration import WalkerCalibration
from hardware.log import LogWriter

writer = LogWriter({path!r}, WalkerCalibration())
start = time.monotonic()
for msg in stream({n}):
    time.sleep(max(0.0, start + msg.t - time.monotonic()))  # real-time pacing
    writer.write(msg)
    print(writer.message_count, writer.flushed_count, flush=True)
time.sleep(60)  # killed before it gets here
"""


@pytest.mark.slow
def test_sigkill_loses_nothing_that_was_flushed(tmp_path: Path) -> None:
    n_ticks = 250  # 2.5 s of wall time; 275 messages
    namespace: dict[str, Any] = {}
    exec(STREAM_SRC, namespace)
    expected = list(namespace["stream"](n_ticks))
    kill_at = int(np.random.default_rng(0).integers(120, len(expected) - 5))
    path = tmp_path / "killed.mcap"
    script = CHILD_SRC.format(repo=str(REPO), stream=STREAM_SRC, path=str(path), n=n_ticks)
    proc = subprocess.Popen(
        [sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    lines = []
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line)
            if int(line.split()[0]) >= kill_at:
                os.kill(proc.pid, signal.SIGKILL)
                break
        lines += proc.stdout.readlines()
    finally:
        proc.kill()
        proc.wait(10)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.read() if proc.stderr else ""
    written, flushed = map(int, [ln for ln in lines if ln.endswith("\n")][-1].split())
    assert written >= kill_at and flushed > 0

    with pytest.warns(LogRecoveryWarning) as caught:
        log = read_log(path)
    got = list(log.messages())
    assert flushed <= len(got) <= written + 1  # all flushed ones; +1: killed before its print
    for a, b in zip(expected, got, strict=False):
        assert_same(a, b)
    assert any(isinstance(m, DepthFrame) for m in got)
    span = (round(got[-1].t * 1e9) - round(got[0].t * 1e9)) / 1e9
    text = str(caught[0].message)
    assert path.name in text and f"{len(got)} messages" in text and f"{span:.3f} s" in text


def chunked_log(path: Path) -> list[Any]:
    """A log of several chunks (one per 0.5 s of log time) with a depth frame in each."""
    k = CameraIntrinsics(8, 6, 5.0, 5.0, 3.5, 2.5)
    rng = np.random.default_rng(0)
    msgs: list[Any] = []
    for i in range(250):
        msgs.append(EncoderTicks(i / 100, i, -i))
        if i % 20 == 0:
            msgs.append(DepthFrame(i / 100, depth(rng, k), k))
    write_log(path, msgs, background_flush=False)
    return msgs


def test_truncated_files_replay_a_prefix(tmp_path: Path) -> None:
    full = tmp_path / "full.mcap"
    msgs = chunked_log(full)
    with open(full, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes  # type: ignore[union-attr]
    assert len(chunks) >= 4
    first_end = chunks[0].chunk_start_offset + chunks[0].chunk_length
    last_end = chunks[-1].chunk_start_offset + chunks[-1].chunk_length
    data = full.read_bytes()
    rng = np.random.default_rng(0)
    counts = []
    for cut in [*sorted(rng.integers(first_end, last_end + 1, 6)), last_end]:
        part = tmp_path / f"cut{cut}.mcap"
        part.write_bytes(data[:cut])
        with pytest.warns(LogRecoveryWarning, match=f"{part.name}: truncated"):
            got = read_all(part)
        assert len(got) >= 1
        for a, b in zip(msgs, got, strict=False):
            assert_same(a, b)
        counts.append(len(got))
    assert counts == sorted(counts) and counts[-1] == len(msgs)
    for cut in rng.integers(1, chunks[0].chunk_start_offset + 1, 4):
        part = tmp_path / f"early{cut}.mcap"
        part.write_bytes(data[:cut])
        with pytest.raises(LogError, match=f"{part.name}: .*truncated"):
            read_log(part)


def test_corrupt_chunk_loses_only_its_own_messages(tmp_path: Path) -> None:
    """More kinds of damage, on a simulated trial: tests/hardware/test_log_damage.py."""
    full = tmp_path / "full.mcap"
    msgs = chunked_log(full)
    with open(full, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes  # type: ignore[union-attr]
    data = bytearray(full.read_bytes())
    third = chunks[2]
    data[third.chunk_start_offset + third.chunk_length - 20] ^= 0xFF
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    with pytest.warns(LogRecoveryWarning, match="corrupt chunk record") as caught:
        log = read_log(bad)
    got = list(log.messages())
    in_third = range(third.message_start_time, third.message_end_time + 1)
    kept = [m for m in msgs if round(m.t * 1e9) not in in_third]
    assert 0 < len(kept) < len(msgs) and len(got) == len(kept)
    for a, b in zip(kept, got, strict=True):
        assert_same(a, b)
    assert not log.complete
    text = str(caught[0].message)
    start, end = third.chunk_start_offset, chunks[3].chunk_start_offset
    assert f"corrupt chunk record at byte {start}: skipped bytes {start}-{end}" in text
    assert f"lost log time {third.message_start_time / 1e9:.3f}-" in text
    assert f"recovered {len(kept)} messages (of {len(msgs)} in the summary)" in text


# ---------------------------------------------------------------- bad input


def raw_mcap(path: Path, calibration: bool, schemas: list[tuple[str, str, str, str]]) -> None:
    """An MCAP written without LogWriter; schemas: (topic, schema name, encoding, payload)."""
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        if calibration:
            w.add_metadata("calibration", {"json": json.dumps(WalkerCalibration().to_dict())})
        for i, (topic, name, encoding, payload) in enumerate(schemas):
            sid = w.register_schema(name, "jsonschema" if encoding == "json" else encoding, b"{}")
            cid = w.register_channel(topic, encoding, sid)
            w.add_message(cid, i, payload.encode(), i)
        w.finish()


@pytest.mark.parametrize(
    ("case", "expect"),
    [
        ("missing", "no such file"),
        ("directory", "is a directory"),
        ("unreadable", "permission denied"),
        ("text", "not an MCAP file"),
        ("empty", "empty file"),
        ("magic only", "truncated in the header"),
        ("half header", "truncated in the header"),
        ("no calibration", "no calibration record"),
        ("no messages", "before any message"),
    ],
)
def test_bad_files_raise_one_line_log_errors(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, case: str, expect: str
) -> None:
    path = tmp_path / f"{case.replace(' ', '_')}.mcap"
    good = tmp_path / "good.mcap"
    msgs = chunked_log(good)
    if case == "directory":
        path.mkdir()
    elif case == "unreadable":
        shutil.copy(good, path)
        path.chmod(0)
        if os.access(path, os.R_OK):  # root reads anything: make open() fail instead

            def deny(*args: Any, **kw: Any) -> Any:
                raise PermissionError(13, "Permission denied", str(path))

            monkeypatch.setattr(log_reader, "open", deny, raising=False)
    elif case == "text":
        path.write_text("t,left,right\n0.0,1,2\n")
    elif case == "empty":
        path.write_bytes(b"")
    elif case == "magic only":
        path.write_bytes(good.read_bytes()[:5])
    elif case == "half header":
        path.write_bytes(good.read_bytes()[:20])
    elif case == "no calibration":
        raw_mcap(
            path,
            False,
            [("/encoders", "walker.EncoderTicks", "json", '{"t":0,"left":1,"right":2}')],
        )
    elif case == "no messages":  # header and metadata flushed, then killed
        writer = LogWriter(path, WalkerCalibration(), background_flush=False)
        writer.write(msgs[0])
    with pytest.raises(LogError) as err:
        read_log(path)
    if case == "no messages":
        writer.close()
    text = str(err.value)
    assert expect in text and path.name in text and "\n" not in text


def test_unknown_schemas_are_skipped_with_a_warning(tmp_path: Path) -> None:
    path = tmp_path / "extra.mcap"
    rgb = RawImage(width=1, height=1, encoding="rgb8", step=3, data=b"abc")
    raw_mcap(
        path,
        True,
        [
            ("/encoders", "walker.EncoderTicks", "json", '{"t":0.5,"left":1,"right":2}'),
            ("/notes", "lab.Note", "json", '{"text":"hello"}'),
            ("/plain", "", "json", "{}"),
        ],
    )
    with pytest.warns(UnsupportedChannelWarning) as caught:
        log = read_log(path)
    text = " ".join(str(w.message) for w in caught)
    assert "'/notes'" in text and "'lab.Note'" in text and "'/plain'" in text
    assert log.topics == {"/encoders": EncoderTicks}
    assert_same(tuple(log.messages()), (EncoderTicks(0.5, 1, 2),))

    # a known schema with content the replayer cannot represent: skipped while replaying
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        w.add_metadata("calibration", {"json": json.dumps(WalkerCalibration().to_dict())})
        schema = log_module.RAW_IMAGE
        sid = w.register_schema(schema.name, schema.encoding, schema.data)
        w.add_message(
            w.register_channel("/camera/color", "protobuf", sid), 1, rgb.SerializeToString(), 1
        )
        w.finish()
    log = read_log(path)
    assert log.topics == {"/camera/color": DepthFrame}
    with pytest.warns(UnsupportedChannelWarning, match="'/camera/color'.*rgb8"):
        assert read_all(path) == []


def test_foxglove_channels_without_companions_are_read_approximately(tmp_path: Path) -> None:
    """Channels added by other tools: t from the timestamp, theta from the quaternion."""
    scan = PbLaserScan(start_angle=-1.0, end_angle=1.0, ranges=[1.0, 2.0, 3.0, 4.0, 5.0])
    scan.timestamp.seconds, scan.timestamp.nanos = 3, 250_000_000
    pose = PoseInFrame(frame_id="world")
    pose.timestamp.seconds = 4
    pose.pose.position.x = 1.5
    pose.pose.orientation.z, pose.pose.orientation.w = math.sin(0.35), math.cos(0.35)
    path = tmp_path / "foxglove.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        w.add_metadata("calibration", {"json": json.dumps(WalkerCalibration().to_dict())})
        for topic, schema, msg in (
            ("/lidar", log_module.LASER_SCAN, scan),
            ("/mocap", log_module.POSE_IN_FRAME, pose),
        ):
            sid = w.register_schema(schema.name, schema.encoding, schema.data)
            cid = w.register_channel(topic, "protobuf", sid)
            ns = msg.timestamp.seconds * 10**9 + msg.timestamp.nanos
            w.add_message(cid, ns, msg.SerializeToString(), ns)
        w.finish()
    got_scan, got_pose = read_all(path)
    assert got_scan.t == 3.25 and got_scan.angle_increment == 0.5
    assert got_scan.range_max == math.inf and got_scan.ranges.dtype == np.float64
    assert got_pose.t == 4.0 and got_pose.x == 1.5 and math.isclose(got_pose.theta, 0.7)
