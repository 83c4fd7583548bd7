"""`walkerslam live` with real device paths and no simulator: the board emulator on a
pty, the Kinect driver replaying a fakenect recording through the real libfreenect sync
API, the tag camera detecting AprilTags with pupil-apriltags on an image folder — fed,
recorded and replayed exactly as on the walker."""

from __future__ import annotations

import itertools
import threading

import cv2
import numpy as np
import pytest

from experiments.live import LiveOptions, LiveRun
from experiments.run import replay_log
from hardware.board_emulator import BoardEmulator
from hardware.calibration import WalkerCalibration
from hardware.depth import decimate_nearest, kinect_raw_to_mm_table
from hardware.fakenect import FakenectWriter
from hardware.log import read_log
from hardware.messages import DepthFrame, EncoderTicks, TagDetections

CAL = WalkerCalibration()
FRAMES = 45  # 1.5 s at 30 Hz


def raw_for_mm(mm: float) -> int:
    """The 11-bit raw value whose depth is nearest `mm` (inverting the driver's table)."""
    table = kinect_raw_to_mm_table().astype(float)
    table[table == 0] = np.inf
    return int(np.argmin(np.abs(table - mm)))


def record_fakenect(folder):
    """A wall 1.6 m ahead with a box at 1.0 m in the lower middle, a little noise."""
    rng = np.random.default_rng(4)
    w = FakenectWriter(folder)
    raws = []
    for i in range(FRAMES):
        raw = np.full((480, 640), raw_for_mm(1500.0 + 10 * i), np.uint16)  # tells frames apart
        raw[260:480, 240:400] = raw_for_mm(1000.0)
        raw += rng.integers(0, 3, raw.shape, dtype=np.uint16)
        raw[:20, :] = 2047  # no reading
        w.add_depth(raw, (i + 1) / 30.0)
        raws.append(raw)
    w.close()
    return raws


def tag_images(folder, n=40):
    folder.mkdir()
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    for i in range(n):
        img = np.full((480, 640), 200, np.uint8)
        marker = cv2.aruco.generateImageMarker(dictionary, 7 + i, 160)
        img[160:320, 240:400] = marker
        img[140:340, 220:420][(img[140:340, 220:420] == 200)] = 255  # a white border
        cv2.imwrite(str(folder / f"f{i:02d}.png"), img)


@pytest.mark.slow
def test_live_on_a_pty_board_fakenect_depth_and_a_tag_camera(tmp_path):
    raws = record_fakenect(tmp_path / "kinect")
    tag_images(tmp_path / "tags")
    log = tmp_path / "live.mcap"
    with BoardEmulator(tmp_path / "tty") as emu:
        stop = threading.Event()

        def walk():  # the walker rolls forward at ~1 m/s: 400 counts per metre
            n = 0
            while not stop.wait(0.01):
                n += 4
                emu.set_counts(n, n)

        threading.Thread(target=walk, daemon=True).start()
        opts = LiveOptions(
            localizer="dead-reckoning",
            controller="open-loop",
            serial=emu.port,
            depth=f"fakenect:{tmp_path / 'kinect'}",
            camera=str(tmp_path / "tags"),
            camera_fps=20.0,
            record=str(log),
            duration_s=30.0,
        )
        run = LiveRun(opts)
        try:
            res = run.run()
        finally:
            stop.set()
    # the recording's end ended the run (45 frames at 30 Hz; the folder lasts 2 s at 20 Hz)
    assert res.ended_by == "depth stream ended"
    msgs = list(read_log(log).messages())
    frames = [m for m in msgs if isinstance(m, DepthFrame)]
    tags = [m for m in msgs if isinstance(m, TagDetections)]
    # a loop that falls behind drops the oldest frames and images, counted (a loaded
    # machine drops one now and then): none is lost uncounted
    assert frames and tags
    received = {name: res.sources[name].by_type for name in ("depth", "tags")}
    assert len(frames) + res.dropped["depth"] == received["depth"]["DepthFrame"]
    assert len(tags) + res.dropped["tags"] == received["tags"]["TagDetections"]
    # every frame recorded value for value: the recording's raw through the 11-bit table,
    # limited to the calibration's range, decimated to its 160×120 as the driver says
    table = kinect_raw_to_mm_table(CAL.depth_range_m)
    wanted = [decimate_nearest(table[raw], 4) for raw in raws]
    assert len(frames) > FRAMES // 2
    index = []
    for got in frames:
        same = [i for i, want in enumerate(wanted) if np.array_equal(got.depth_mm, want)]
        assert len(same) == 1, "a recorded frame is not one of the recording's"
        index.append(same[0])
        assert got.intrinsics == CAL.depth_intrinsics
    # in order; libfreenect's replay may skip a frame of its buffer ring (counted)
    assert index == sorted(index) and len(set(index)) == len(index)
    assert all(b.t > a.t for a, b in itertools.pairwise(frames))
    # the tag camera's detections: the ids of the images, in order (gaps where dropped)
    seen = [[d.tag_id for d in m.detections] for m in tags]
    assert all(len(ids) == 1 for ids in seen)
    ids = [ids[0] for ids in seen]
    if res.dropped["tags"] == 0:
        assert ids == list(range(7, 7 + len(tags)))
    assert ids[0] >= 7 and all(b > a for a, b in itertools.pairwise(ids))
    # the encoder ticks all there, and the replay is the live run
    assert sum(isinstance(m, EncoderTicks) for m in msgs) == res.board["ticks"]
    rep = replay_log(log, tmp_path / "replay", localizer="dead-reckoning", figures=False)
    np.testing.assert_array_equal(
        rep.pipeline.localizer.trajectory().poses, res.pipeline.localizer.trajectory().poses
    )
    # the box 1 m ahead (1.41 m from the rear axle) is in the map, in front of the walker
    occ = res.pipeline.mapper.occupied_xy()
    assert len(occ) > 0
