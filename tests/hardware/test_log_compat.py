"""Logs written by earlier versions of the writer read back exactly.

`data/log_v1.mcap` was written by the walker-slam log v1 writer as it was before the log
module became a package (hardware/log.py at commit 6050796), from `v1_messages()`; a
reader must give back exactly those messages, metadata and attachments, forever.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from hardware.calibration import WalkerCalibration
from hardware.log import TOPICS, read_log
from hardware.messages import (
    BrakeCommand,
    CameraIntrinsics,
    Collision,
    DepthFrame,
    DeviceEvent,
    EncoderTicks,
    GroundTruthPose,
    LaserScan,
    RangeBearing,
    TagDetection,
    TagDetections,
    VelocityOdometry,
)
from tests.hardware.test_log import assert_same

V1_LOG = Path(__file__).parent / "data" / "log_v1.mcap"
V1_METADATA = {
    "config": {"command": "fixture", "seed": 11, "noise": [0.1, 1e-300]},
    "world": {"name": "course Ω", "tags": {"3": [1.5, 2.0]}},
}
V1_ATTACHMENTS = {"note.bin": b"\x00\x01walker\xff"}

Written = tuple[Any, str | None, float | None]  # (message, topic, log time)


def v1_messages() -> list[Written]:
    """1.2 s of every message type (custom topics and live log times included), written in
    this order; at the default flush interval they make three chunks."""
    rng = np.random.default_rng(11)
    k = CameraIntrinsics(8, 6, 5.0, 5.5, 3.5, 2.5)
    out: list[Written] = []
    for i in range(120):
        t = i / 100
        out.append((EncoderTicks(t, 3 * i, -2 * i), None, None))
        if i % 10 == 0:
            depth = rng.integers(0, 65536, (6, 8), dtype=np.uint16)
            out.append((DepthFrame(t, depth, k), None, None))
            pose = np.eye(4)
            pose[:3, 3] = rng.normal(size=3)
            dets = (TagDetection(i, pose, rng.uniform(0, 8, (4, 2)), 50.0 + i),) if i % 20 else ()
            out.append((TagDetections(t, dets), None, None))
            out.append((GroundTruthPose(t, t / 3, -t, math.pi * t / 7), None, None))
            ranges = rng.uniform(0.1, 4.0, 9).astype(np.float32)
            ranges[[1, 2]] = [np.inf, np.nan]
            out.append((LaserScan(t, -1.0, 0.25, ranges, 3.5), None, None))
        if i % 25 == 0:
            out.append((BrakeCommand(t, 0.1 * i, 1 / 3), None, None))
            out.append((BrakeCommand(t, 0.2, 0.3, "replay"), "/brakes/replayed", None))
            out.append((VelocityOdometry(t, 0.5, -0.25), None, None))
            out.append((RangeBearing(t, i, 2.0 + t, -math.pi / 3), None, None))
    out.append((Collision(0.77, "rear-wheel", "table 2", 0.125, -7.5), None, None))
    out.append((DeviceEvent(0.8, "board", "reset", "counts re-based"), None, 0.805))
    return out


def expected_order(written: list[Written]) -> list[Any]:
    """What a replay gives: log-time order, ties in write order."""
    keyed = [(m.t if log_time is None else log_time, m) for m, _, log_time in written]
    return [m for _, m in sorted(keyed, key=lambda e: e[0])]


def test_a_log_written_by_the_v1_writer_reads_back_exactly() -> None:
    written = v1_messages()
    log = read_log(V1_LOG)
    assert log.complete
    assert log.calibration == WalkerCalibration()
    assert log.metadata == V1_METADATA and log.attachments == V1_ATTACHMENTS
    assert log.topics == {
        **{TOPICS[type(m)]: type(m) for m, topic, _ in written if topic is None},
        "/brakes/replayed": BrakeCommand,
    }
    assert log.message_count == len(written)
    got = list(log.messages())
    expected = expected_order(written)
    assert len(got) == len(expected)
    for a, b in zip(expected, got, strict=True):
        assert_same(a, b)
    replayed = [m.left_nm for m in log.messages(["/brakes/replayed"])]
    assert replayed == [0.2] * 5
