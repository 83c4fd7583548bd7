"""Depth cameras: the raw→mm table, decimation, intrinsics, time stamps, the one-line
errors, and Kinect frames replayed through the real libfreenect sync API with fakenect.

The replay tests need libfreenect-dev, libfreenect-bin, the freenect binding and a C
compiler (`make test` installs them); without them they fail, saying what is missing.
"""

from __future__ import annotations

import ctypes
import itertools
import json
import math
import os
import subprocess
import sys
import threading
import time
import types
from pathlib import Path

import numpy as np
import pytest

from hardware import depth as dp
from hardware import fakenect as fk
from hardware import kinect_worker as wire
from hardware.calibration import WalkerCalibration
from hardware.clock import HostClock
from hardware.depth import DeviceError, open_depth
from hardware.messages import CameraIntrinsics, DepthFrame
from hardware.source import Source

FPS = 30.0


def _record(folder: Path, depth: list[np.ndarray], rgb: list[np.ndarray], t0: float = 2.0):
    """Depth frame i at t0 + i/30 s, video frame i 10 ms after it."""
    with fk.FakenectWriter(folder) as w:
        for i in range(max(len(depth), len(rgb))):
            if i < len(depth):
                w.add_depth(depth[i], t0 + i / FPS)
            if i < len(rgb):
                w.add_video(rgb[i], t0 + i / FPS + 0.01)
    return folder


def _raw_frames(n: int, seed: int) -> list[np.ndarray]:
    """Raw frames covering the whole 11-bit range, with 2047 (no reading) patches."""
    rng = np.random.default_rng(seed)
    frames = []
    for _ in range(n):
        raw = rng.integers(0, 2048, size=(480, 640)).astype(np.uint16)
        raw[:40, :40] = 2047
        frames.append(raw)
    return frames


def _rgb_frames(n: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, size=(480, 640, 3), dtype=np.uint8) for _ in range(n)]


def _formula_mm(raw: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Depth [mm] straight from the formula, independent of the table."""
    r = raw.astype(np.float64)
    inv = -0.0030711016 * r + 3.3309495161
    with np.errstate(divide="ignore"):
        z = np.where((inv > 0) & (r < 2047), 1.0 / inv, np.inf)
    return np.where((z >= lo) & (z <= hi), np.rint(z * 1000.0), 0).astype(np.uint16)


def _collect(iterable, timeout: float = 20.0) -> list:
    """Everything the iterable yields, in a thread: a hang fails instead of blocking."""
    out: list = []
    errors: list[BaseException] = []

    def run():
        try:
            out.extend(iterable)
        except BaseException as exc:
            errors.append(exc)

    th = threading.Thread(target=run, daemon=True)
    th.start()
    th.join(timeout)
    assert not th.is_alive(), f"iteration did not end within {timeout} s ({len(out)} items)"
    if errors:
        raise errors[0]
    return out


def _gone(pid: int, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.02)
    return False


# --------------------------------------------------------------------------- prerequisites


def test_fakenect_replay_prerequisites_are_installed():
    from importlib.util import find_spec

    assert find_spec("freenect") is not None, (
        "the freenect binding is missing: make test installs it (apt-get install "
        "libfreenect-dev, then pip install 'walker-slam[kinect]')"
    )
    lib = fk.fake_libfreenect()  # raises, naming the Debian packages, when missing
    assert lib.is_file()
    assert fk.fakenect_shim().is_file()


# --------------------------------------------------------------------------- raw → mm


def test_raw_to_mm_table_matches_hand_computed_values():
    table = dp.kinect_raw_to_mm_table()
    assert table.shape == (2048,) and table.dtype == np.uint16
    # 1000 / (3.3309495161 - 0.0030711016 raw), by hand:
    #   raw    0: 1000 / 3.3309495161 = 300.21 -> 300
    #   raw  500: 1000 / 1.7953987161 = 556.98 -> 557
    #   raw  700: 1000 / 1.1811783961 = 846.61 -> 847
    #   raw  900: 1000 / 0.5669580761 = 1763.80 -> 1764
    #   raw 1000: 1000 / 0.2598479161 = 3848.40 -> 3848
    #   raw 1050: 1000 / 0.1062928361 = 9407.97 -> 9408
    #   raw 1084: 1000 / 0.0018753817 = 533 m: beyond uint16 mm -> 0
    #   raw 1085: denominator -0.0011957199 < 0 -> 0; raw 2047: no reading -> 0
    expected = {0: 300, 500: 557, 700: 847, 900: 1764, 1000: 3848, 1050: 9408}
    expected |= {1084: 0, 1085: 0, 1500: 0, 2046: 0, 2047: 0}
    for raw, mm in expected.items():
        assert table[raw] == mm, raw
    # Valid exactly for raw 0..1079 (65.535 m at ~1079.6); non-decreasing there (the
    # steps are under 1 mm at the near end).
    valid = np.nonzero(table)[0]
    assert valid.min() == 0 and valid.max() == 1079 and len(valid) == 1080
    assert np.all(np.diff(table[valid].astype(int)) >= 0)


def test_raw_to_mm_table_zeroes_depths_outside_the_usable_range():
    table = dp.kinect_raw_to_mm_table((0.8, 3.5))
    # raw 677: 1000 / 1.2518137329 = 798.84 mm < 800 -> 0
    # raw 678: 1000 / 1.2487426313 = 800.81 -> 801
    # raw 991: 1000 / 0.2874878305 = 3478.41 -> 3478
    # raw 992: 1000 / 0.2844167289 = 3515.97 mm > 3500 -> 0
    assert (table[677], table[678], table[991], table[992]) == (0, 801, 3478, 0)
    assert np.count_nonzero(table) == 991 - 678 + 1
    with pytest.raises(ValueError):
        dp.kinect_raw_to_mm_table((3.5, 0.8))


def test_raw_to_mm_reads_impossible_raw_values_as_invalid():
    raw = np.array([[0, 700], [2047, 4095]], dtype=np.uint16)
    assert dp.kinect_raw_to_mm(raw).tolist() == [[300, 847], [0, 0]]


# --------------------------------------------------------------------------- decimation


def test_decimation_keeps_the_nearest_valid_depth_per_block():
    d = np.array(
        [
            [0, 5, 0, 0, 9, 9],
            [3, 0, 0, 0, 9, 2],
            [65535, 0, 7, 7, 1000, 999],
            [0, 0, 7, 7, 1001, 65535],
        ],
        dtype=np.uint16,
    )
    assert dp.decimate_nearest(d, 2).tolist() == [[3, 0, 2], [65535, 7, 999]]
    assert dp.decimate_nearest(d, 1) is d
    with pytest.raises(ValueError, match="does not divide"):
        dp.decimate_nearest(d, 4)
    with pytest.raises(ValueError):
        dp.decimate_nearest(d.astype(np.int32), 2)


def test_decimation_default_matches_the_calibration_size():
    def k(w, h):
        return CameraIntrinsics.from_fov(w, h, math.radians(57), math.radians(43))

    assert dp.default_decimation(640, 480, k(160, 120)) == 4
    assert dp.default_decimation(640, 480, k(320, 240)) == 2
    assert dp.default_decimation(640, 480, k(640, 480)) == 1
    assert dp.default_decimation(640, 480, k(200, 150)) == 1  # not an integer divisor
    assert dp.default_decimation(640, 480, k(160, 160)) == 1  # not the same factor


# --------------------------------------------------------------------------- intrinsics


def test_intrinsics_scale_with_pixel_centres_at_integers():
    small = CameraIntrinsics.from_fov(160, 120, math.radians(57.0), math.radians(43.0))
    big = dp.scale_intrinsics(small, 640, 480)
    want = CameraIntrinsics.from_fov(640, 480, math.radians(57.0), math.radians(43.0))
    assert (big.width, big.height) == (640, 480)
    assert big.fx == pytest.approx(small.fx * 4) and big.fy == pytest.approx(small.fy * 4)
    # (79.5 + 0.5)·4 − 0.5 = 319.5, the centre of a 640-pixel row
    assert (big.cx, big.cy) == (319.5, 239.5)
    for a, b in zip(
        (big.fx, big.fy, big.cx, big.cy), (want.fx, want.fy, want.cx, want.cy), strict=True
    ):
        assert a == pytest.approx(b, rel=1e-12)
    off = CameraIntrinsics(160, 120, 150.0, 151.0, 80.0, 60.0)
    s = dp.scale_intrinsics(off, 320, 120)
    assert (s.fx, s.fy, s.cx, s.cy) == (300.0, 151.0, 160.5, 60.0)
    assert dp.scale_intrinsics(dp.scale_intrinsics(off, 640, 480), 160, 120) == off
    assert dp.scale_intrinsics(off, 160, 120) is off


def test_kinect_frame_intrinsics_follow_the_calibration():
    cal = WalkerCalibration()  # depth intrinsics 160×120
    k, dec, origin = dp._frame_intrinsics(cal, 640, 480, None)
    assert dec == 4 and k == cal.depth_intrinsics and origin == "calibration"
    k, dec, origin = dp._frame_intrinsics(cal, 640, 480, 2)
    assert dec == 2 and k == dp.scale_intrinsics(cal.depth_intrinsics, 320, 240)
    assert "scaled" in origin
    with pytest.raises(DeviceError, match="does not divide"):
        dp._frame_intrinsics(cal, 640, 480, 7)


# --------------------------------------------------------------------------- time stamps


def test_device_stamps_unwrap_the_60mhz_counter_and_map_onto_the_host_clock():
    clock = HostClock(start=100.0)
    st = dp._Stamper(clock, "device", 60e6, 2**32)
    start_ticks = 2**32 - 3 * 2_000_000  # wraps after the third frame
    ts = []
    for i in range(10):
        ticks = (start_ticks + i * 2_000_000) % 2**32  # 1/30 s per frame
        arrival = 100.0 + 5.0 + i / 30 + (0.004 if i % 3 else 0.001)  # jittered latency
        ts.append(st.stamp(ticks, arrival))
    assert all(b > a for a, b in itertools.pairwise(ts))
    # t = device time + the smallest latency seen so far: 5.001 s after the first frame
    # at 5.001 + i/30, never later than the arrival.
    for i, t in enumerate(ts):
        assert t == pytest.approx(5.001 + i / 30, abs=1e-9)
    # A gap of 3 wraps (≈ 214.7 s) plus one frame is counted from the arrival gap.
    later = st.stamp(
        (start_ticks + 10 * 2_000_000) % 2**32, 100.0 + 5.0 + 3 * 2**32 / 60e6 + 10 / 30 + 0.001
    )
    assert later == pytest.approx(5.001 + 3 * 2**32 / 60e6 + 10 / 30, abs=1e-6)
    # The same device time again, 10 ms later: dropped.
    again = 100.0 + 5.0 + 3 * 2**32 / 60e6 + 10 / 30 + 0.011
    assert st.stamp((start_ticks + 10 * 2_000_000) % 2**32, again) is None


def test_device_stamps_resync_when_the_device_clock_jumps():
    clock = HostClock(start=0.0)
    st = dp._Stamper(clock, "device", 1000.0, None)  # milliseconds, no wrap
    a = st.stamp(50_000.0, 10.0)
    b = st.stamp(50_033.0, 10.034)
    c = st.stamp(10.0, 10.067)  # the device restarted its clock
    d = st.stamp(43.0, 10.101)
    assert a == pytest.approx(10.0) and b == pytest.approx(10.033)
    assert st.resyncs == 1 and c > b and d > c


def test_arrival_stamps_are_the_arrival_on_the_run_clock():
    st = dp._Stamper(HostClock(start=50.0), "arrival", 60e6, 2**32)
    assert st.stamp(0, 51.25) == 1.25
    assert st.stamp(0, 51.25) is None  # not after the previous frame
    with pytest.raises(DeviceError, match="unknown stamp mode"):
        dp._Stamper(HostClock(), "wall", 60e6, 2**32)


# --------------------------------------------------------------------------- fakenect folders


def test_writer_writes_the_fakenect_format(tmp_path):
    raw = np.arange(480 * 640, dtype=np.uint16).reshape(480, 640) % 2048
    rgb = _rgb_frames(1, seed=3)[0]
    with fk.FakenectWriter(tmp_path / "rec") as w:
        d = w.add_depth(raw, 1.5)
        r = w.add_video(rgb, 1.52, timestamp=7)
    assert d.name == "d-1.500000-90000000.pgm" and r.name == "r-1.520000-7.ppm"
    assert (tmp_path / "rec" / "INDEX.txt").read_text() == f"{d.name}\n{r.name}\n"
    data = (tmp_path / "rec" / d.name).read_bytes()
    assert data[:17] == b"P5 640 480 65535\n" and len(data) == 17 + 480 * 640 * 2
    assert data[17:21] == bytes([0, 0, 1, 0])  # little-endian: 0, then 1 as 01 00
    vid = (tmp_path / "rec" / r.name).read_bytes()
    assert vid[:15] == b"P6 640 480 255\n" and vid[15:] == rgb.tobytes()
    assert np.array_equal(fk.read_depth_file(tmp_path / "rec" / d.name), raw)
    assert np.array_equal(fk.read_video_file(tmp_path / "rec" / r.name), rgb)
    entries = fk.read_index(tmp_path / "rec")
    assert [(e.type, e.time, e.timestamp) for e in entries] == [
        ("d", 1.5, 90_000_000),
        ("r", 1.52, 7),
    ]


def test_writer_rejects_what_fakenect_cannot_replay(tmp_path):
    with fk.FakenectWriter(tmp_path / "rec") as w:
        with pytest.raises(ValueError, match="11-bit"):
            w.add_depth(np.full((480, 640), 2048, np.uint16), 1.0)
        with pytest.raises(ValueError, match="480x640"):
            w.add_depth(np.zeros((120, 160), np.uint16), 1.0)
        with pytest.raises(ValueError, match="RGB"):
            w.add_video(np.zeros((480, 640), np.uint8), 1.0)
        with pytest.raises(ValueError, match="> 0"):
            w.add_depth(np.zeros((480, 640), np.uint16), 0.0)
        w.add_depth(np.zeros((480, 640), np.uint16), 2.0)
        with pytest.raises(ValueError, match="decrease"):
            w.add_depth(np.zeros((480, 640), np.uint16), 1.0)
    with pytest.raises(FileExistsError):
        fk.FakenectWriter(tmp_path / "rec")


def test_shim_provides_libfreenects_camera_to_world(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    lib_path = fk.fakenect_shim()
    assert lib_path.parent == tmp_path / "cache" / "walker-slam"
    assert fk.fakenect_shim() == lib_path  # built once
    lib = ctypes.CDLL(str(lib_path))
    f = lib.freenect_camera_to_world
    f.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_int, ctypes.c_int]
    f.argtypes += [ctypes.POINTER(ctypes.c_double)] * 2
    wx, wy = ctypes.c_double(), ctypes.c_double()
    f(None, 420, 140, 2000, ctypes.byref(wx), ctypes.byref(wy))
    focal = 320 / math.tan(math.radians(28.5))
    assert wx.value == pytest.approx(100 * 2000 / focal, rel=1e-5)
    assert wy.value == pytest.approx(-100 * 2000 / focal, rel=1e-5)


# --------------------------------------------------------------------------- replay


def test_fakenect_replays_depth_value_for_value(tmp_path):
    raws = _raw_frames(12, seed=11)
    folder = _record(tmp_path / "rec", raws, [])
    cal = WalkerCalibration()
    clock = HostClock()
    src = open_depth(f"fakenect:{folder}", cal, clock, decimation=1)
    try:
        assert isinstance(src, Source)
        json.dumps(src.metadata, allow_nan=False)
        info = src.metadata["depth_camera"]
        assert info["device"] == "fakenect" and info["recorded_frames"] == 12
        frames, seen_at = [], []
        for f in src.messages():
            seen_at.append(clock.now())
            frames.append(f)
    finally:
        src.close()
    assert len(frames) == 12
    assert src.frames_skipped == 0 and src.frames_dropped == 0
    lo, hi = cal.depth_range_m
    for f, raw in zip(frames, raws, strict=True):
        assert isinstance(f, DepthFrame)
        assert f.intrinsics == dp.scale_intrinsics(cal.depth_intrinsics, 640, 480)
        assert np.array_equal(f.depth_mm, _formula_mm(raw, lo, hi))
    ts = np.array([f.t for f in frames])
    assert np.all(np.diff(ts) > 0)
    assert np.all(ts <= np.array(seen_at))  # stamped no later than it arrived
    # Device time stamps: the recorded 1/30 s spacing, whatever the arrival jitter.
    assert np.median(np.diff(ts)) == pytest.approx(1 / FPS, abs=1e-3)


def test_fakenect_depth_is_decimated_to_the_calibration_size_by_default(tmp_path):
    raws = _raw_frames(3, seed=12)
    folder = _record(tmp_path / "rec", raws, [])
    cal = WalkerCalibration()
    with open_depth(f"fakenect:{folder}", cal, HostClock()) as src:
        frames = _collect(src.messages())
    assert src.decimation == 4 and len(frames) == 3
    table = dp.kinect_raw_to_mm_table(cal.depth_range_m)
    for f, raw in zip(frames, raws, strict=True):
        assert f.depth_mm.shape == (120, 160) and f.intrinsics == cal.depth_intrinsics
        assert np.array_equal(f.depth_mm, dp.decimate_nearest(table[raw], 4))


def test_fakenect_rgb_frames_are_byte_for_byte_bgr(tmp_path):
    rgbs = _rgb_frames(8, seed=13)
    folder = _record(tmp_path / "rec", _raw_frames(8, seed=14), rgbs)
    clock = HostClock()
    frames = _collect(dp.kinect_rgb_frames(clock, index=f"fakenect:{folder}"))
    assert len(frames) == 8
    for (_t, img), rgb in zip(frames, rgbs, strict=True):
        assert img.dtype == np.uint8 and img.shape == (480, 640, 3) and img.flags.c_contiguous
        assert img.tobytes() == np.ascontiguousarray(rgb[..., ::-1]).tobytes()
    ts = [t for t, _ in frames]
    assert all(b > a for a, b in itertools.pairwise(ts))


def test_depth_and_rgb_of_one_recording_share_one_capture_process(tmp_path):
    raws, rgbs = _raw_frames(10, seed=15), _rgb_frames(10, seed=16)
    folder = _record(tmp_path / "rec", raws, rgbs)
    clock = HostClock()
    cal = WalkerCalibration()
    src = open_depth(f"fakenect:{folder}", cal, clock, decimation=1)
    video = dp.kinect_rgb_frames(clock, f"fakenect:{folder}")
    try:
        assert video.worker_pid == src.worker_pid is not None
        with pytest.raises(DeviceError, match="already open"):
            open_depth(f"fakenect:{folder}", cal, clock)
        got_video: list = []
        th = threading.Thread(target=lambda: got_video.extend(video), daemon=True)
        th.start()
        frames = _collect(src.messages())
        th.join(10)
        assert not th.is_alive()
    finally:
        src.close()
        video.close()
    assert len(frames) == 10
    for f, raw in zip(frames, raws, strict=True):
        assert np.array_equal(f.depth_mm, _formula_mm(raw, *cal.depth_range_m))
    # Video opened after depth: it may start a few frames late, but what it gets is the
    # recording's frames in order, up to and including the last one.
    assert 1 <= len(got_video) <= 10
    bgrs = [np.ascontiguousarray(rgb[..., ::-1]) for rgb in rgbs]
    idx = [next(i for i, b in enumerate(bgrs) if np.array_equal(b, img)) for _, img in got_video]
    assert idx == list(range(10 - len(got_video), 10))
    assert _gone(src.worker_pid)


def test_close_from_another_thread_ends_a_blocked_iterator_and_the_process(tmp_path):
    raw = np.full((480, 640), 800, np.uint16)
    folder = _record(tmp_path / "rec", [raw] * 150, [])  # 5 s of frames
    src = open_depth(f"fakenect:{folder}", WalkerCalibration(), HostClock())
    pid, staged = src.worker_pid, src._hub.replay.path
    assert (staged / "INDEX.txt").is_file()
    got: list[DepthFrame] = []
    th = threading.Thread(target=lambda: got.extend(src.messages()), daemon=True)
    th.start()
    time.sleep(0.3)
    t0 = time.monotonic()
    src.close()
    th.join(2.0)
    assert not th.is_alive() and time.monotonic() - t0 < 1.0
    assert 1 <= len(got) < 150
    assert _gone(pid)
    assert not staged.exists()  # the staged copy of the recording is removed


def test_stop_event_ends_the_rgb_iterator(tmp_path):
    folder = _record(tmp_path / "rec", [], _rgb_frames(1, seed=17) * 90)
    stop = threading.Event()
    video = dp.kinect_rgb_frames(HostClock(), f"fakenect:{folder}", stop)
    pid = video.worker_pid
    first = next(video)
    assert first[1].shape == (480, 640, 3)
    stop.set()
    rest = _collect(video, timeout=2.0)
    assert len(rest) <= 5
    assert _gone(pid)


def test_worker_starts_a_second_stream_on_command(tmp_path):
    # The live Kinect starts video this way when the tag camera opens after depth.
    folder = _record(tmp_path / "rec", _raw_frames(30, seed=18), _rgb_frames(30, seed=19))
    replay = fk.ReplayFolder(folder)
    try:
        env = fk.replay_environment(replay.path)
        env["PYTHONPATH"] = str(dp._PACKAGE_ROOT)
        r, w = os.pipe()
        proc = subprocess.Popen(
            [sys.executable, "-m", "hardware.kinect_worker", "--fd", str(w), "--stream", "depth"],
            stdin=subprocess.PIPE,
            stdout=subprocess.DEVNULL,
            pass_fds=(w,),
            env=env,
        )
        os.close(w)
        seen = []
        with os.fdopen(r, "rb") as f:
            while len(seen) < 20:
                head = f.read(wire.HEADER.size)
                assert len(head) == wire.HEADER.size, "worker ended early"
                magic, stream, status, width, height, ch, ts, _, n = wire.HEADER.unpack(head)
                payload = f.read(n)
                assert magic == wire.MAGIC and status == wire.STATUS_FRAME
                seen.append((stream, ts, width, height, ch, len(payload)))
                if len(seen) == 3:
                    proc.stdin.write(b"video\n")
                    proc.stdin.flush()
        proc.stdin.close()
        assert proc.wait(timeout=5) == 0
    finally:
        replay.close()
    assert [s[0] for s in seen[:3]] == [wire.STREAM_DEPTH] * 3
    video = [s for s in seen if s[0] == wire.STREAM_VIDEO]
    assert video and all(s[2:] == (640, 480, 3, 640 * 480 * 3) for s in video)
    depth = [s for s in seen if s[0] == wire.STREAM_DEPTH]
    assert all(s[2:] == (640, 480, 1, 640 * 480 * 2) for s in depth)
    # Timestamps are the staged line numbers: depth on even lines, video on odd ones.
    assert all(s[1] % 2 == 0 for s in depth) and all(s[1] % 2 == 1 for s in video)


# --------------------------------------------------------------------------- errors


def _one_line(exc: pytest.ExceptionInfo) -> str:
    text = str(exc.value)
    assert "\n" not in text and text
    return text


def test_unknown_spec_lists_the_valid_forms():
    with pytest.raises(DeviceError) as e:
        open_depth("webcam", WalkerCalibration(), HostClock())
    assert _one_line(e) == (
        "unknown depth camera 'webcam'; valid: fakenect:DIR, kinect, kinect:INDEX, realsense"
    )
    with pytest.raises(DeviceError, match="device index"):
        open_depth("kinect:first", WalkerCalibration(), HostClock())
    assert issubclass(DeviceError, ValueError)


def test_fakenect_folder_errors_are_one_line(tmp_path):
    cal, clock = WalkerCalibration(), HostClock()
    with pytest.raises(DeviceError) as e:
        open_depth(f"fakenect:{tmp_path / 'absent'}", cal, clock)
    assert _one_line(e).startswith("fakenect folder not found")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DeviceError) as e:
        open_depth(f"fakenect:{tmp_path / 'empty'}", cal, clock)
    assert "no INDEX.txt" in _one_line(e)
    folder = _record(tmp_path / "video-only", [], _rgb_frames(2, seed=20))
    with pytest.raises(DeviceError) as e:
        open_depth(f"fakenect:{folder}", cal, clock)
    assert "has no depth frames" in _one_line(e)
    folder = _record(tmp_path / "broken", _raw_frames(2, seed=21), [])
    next(folder.glob("d-*.pgm")).unlink()
    with pytest.raises(DeviceError) as e:
        open_depth(f"fakenect:{folder}", cal, clock)
    assert "missing" in _one_line(e)
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "INDEX.txt").write_text("depth.pgm\n")
    with pytest.raises(DeviceError) as e:
        open_depth(f"fakenect:{tmp_path / 'bad'}", cal, clock)
    assert "line 1" in _one_line(e)


def test_missing_freenect_binding_is_a_one_line_error(monkeypatch):
    monkeypatch.setattr(dp, "find_spec", lambda name: None)
    with pytest.raises(DeviceError) as e:
        open_depth("kinect", WalkerCalibration(), HostClock())
    assert "pip install 'walker-slam[kinect]'" in _one_line(e)


def test_kinect_that_is_not_connected_is_a_one_line_error():
    with pytest.raises(DeviceError) as e:
        open_depth("kinect:63", WalkerCalibration(), HostClock())
    assert _one_line(e).startswith("libfreenect could not open Kinect 63")


def test_missing_pyrealsense2_is_a_one_line_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # import raises ImportError
    with pytest.raises(DeviceError) as e:
        open_depth("realsense", WalkerCalibration(), HostClock())
    assert _one_line(e) == "the RealSense needs pyrealsense2: pip install 'walker-slam[realsense]'"


class _NoDevices:
    """pyrealsense2's context when nothing is connected (for machines without the
    realsense extra; with it installed, the test uses the real binding)."""

    def query_devices(self):
        return []


def test_realsense_without_a_device_is_a_one_line_error(monkeypatch):
    try:
        import pyrealsense2 as rs
    except ImportError:
        rs = types.SimpleNamespace(context=_NoDevices)
        monkeypatch.setitem(sys.modules, "pyrealsense2", rs)
    if len(rs.context().query_devices()) > 0:
        pytest.skip("a RealSense is connected: the no-device error cannot occur")
    with pytest.raises(DeviceError) as e:
        open_depth("realsense", WalkerCalibration(), HostClock())
    assert _one_line(e) == "no RealSense device found (pyrealsense2 sees none connected)"


class _FakeRealSense:
    """A stand-in for pyrealsense2 with one device connected (the calls
    `RealSenseDepthSource` makes): a depth stream whose profile has `native` intrinsics,
    a depth scale, and `frames` (z16 arrays) delivered one per wait, 33 ms apart."""

    class stream:  # pyrealsense2's names
        depth = "depth"

    class format:
        z16 = "z16"

    class camera_info:
        name, serial_number, firmware_version = "name", "serial", "firmware"

    def __init__(self, native, scale_m=0.001, frames=(), start_error=None):
        self.native, self.scale_m, self.frames = native, scale_m, list(frames)
        self.start_error = start_error
        self.enabled: list[tuple] = []
        self.stops = 0
        self.delivered = 0
        rs = self

        class Config:
            def enable_stream(self, *args):
                rs.enabled.append(args)

        class Pipeline:
            def __init__(self, context):
                pass

            def start(self, config):
                if rs.start_error:
                    raise RuntimeError(rs.start_error)
                return rs._profile()

            def stop(self):
                rs.stops += 1

            def try_wait_for_frames(self, timeout_ms):
                if not rs.frames:
                    return False, None
                t_ms = 1000.0 + 33.0 * rs.delivered
                rs.delivered += 1
                data = rs.frames.pop(0)
                depth = types.SimpleNamespace(get_timestamp=lambda: t_ms, get_data=lambda: data)
                return True, types.SimpleNamespace(get_depth_frame=lambda: depth)

        self.config, self.pipeline = Config, Pipeline
        self.context = lambda: types.SimpleNamespace(query_devices=lambda: ["D435"])

    def _profile(self):
        n = self.native
        intr = types.SimpleNamespace(
            width=n.width, height=n.height, fx=n.fx, fy=n.fy, ppx=n.cx, ppy=n.cy
        )
        video = types.SimpleNamespace(get_intrinsics=lambda: intr)
        stream = types.SimpleNamespace(as_video_stream_profile=lambda: video)

        def info(key):
            if key == "firmware":
                raise RuntimeError("not supported")
            return {"name": "Intel RealSense D435", "serial": "0123"}[key]

        sensor = types.SimpleNamespace(get_depth_scale=lambda: self.scale_m)
        device = types.SimpleNamespace(first_depth_sensor=lambda: sensor, get_info=info)
        return types.SimpleNamespace(get_device=lambda: device, get_stream=lambda s: stream)


def _realsense(monkeypatch, **fake) -> _FakeRealSense:
    rs = _FakeRealSense(**fake)
    monkeypatch.setitem(sys.modules, "pyrealsense2", rs)
    return rs


def test_a_realsense_opens_with_its_stream_profile_decimated_to_the_calibration(monkeypatch):
    native = CameraIntrinsics(640, 480, 384.0, 383.5, 320.25, 238.75)
    z = np.full((480, 640), 2000, np.uint16)
    z[0, :4] = (0, 700, 3600, 1500)  # no reading, nearer and farther than the range, valid
    rs = _realsense(monkeypatch, native=native, frames=[z, z])
    src = open_depth("realsense", WalkerCalibration(), HostClock(), stamp="arrival")
    assert rs.enabled == [("depth", 640, 480, "z16", 30)]
    assert src.decimation == 4
    assert src.intrinsics == CameraIntrinsics(160, 120, 96.0, 95.875, 79.6875, 59.3125)
    assert src.metadata == {
        "depth_camera": {
            "device": "realsense",
            "name": "Intel RealSense D435",
            "serial": "0123",
            "firmware": "",
            "depth_scale_m": 0.001,
            "native_size": [640, 480],
            "fps": 30,
            "decimation": 4,
            "decimation_rule": "nearest valid depth per block",
            "range_m": [0.8, 3.5],
            "stamp": "arrival",
            "intrinsics": {
                "width": 160,
                "height": 120,
                "fx": 96.0,
                "fy": 95.875,
                "cx": 79.6875,
                "cy": 59.3125,
            },
            "intrinsics_from": "device stream profile",
        }
    }
    frames = list(itertools.islice(src.messages(), 2))
    assert rs.stops == 1  # the generator's end stopped the pipeline
    assert frames[0].t < frames[1].t
    assert frames[0].depth_mm.shape == (120, 160)
    assert frames[0].depth_mm[0, 0] == 1500  # the block's nearest valid reading
    assert np.all(frames[0].depth_mm[1:] == 2000) and np.all(frames[0].depth_mm[0, 1:] == 2000)
    src.close()
    assert rs.stops == 1


def test_realsense_errors_opening_are_one_line_and_stop_the_pipeline(monkeypatch):
    native = CameraIntrinsics(640, 480, 384.0, 383.5, 320.0, 240.0)
    rs = _realsense(monkeypatch, native=native)
    with pytest.raises(DeviceError) as e:
        open_depth("realsense", WalkerCalibration(), HostClock(), decimation=3)
    assert _one_line(e) == "decimation 3 does not divide the depth frame 640x480"
    assert rs.stops == 1
    _realsense(monkeypatch, native=native, start_error="Couldn't resolve requests")
    with pytest.raises(DeviceError) as e:
        open_depth("realsense", WalkerCalibration(), HostClock(), width=1280, height=720, fps=6)
    assert _one_line(e) == (
        "cannot start the RealSense depth stream 1280x720@6: Couldn't resolve requests"
    )
