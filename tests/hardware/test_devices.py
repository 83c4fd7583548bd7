"""Live devices are found through entry points (hardware.devices): the built-in depth
and tag cameras are declared in pyproject.toml, another package's member opens through
the same functions, and specs name them as NAME[:ARG]."""

from __future__ import annotations

import threading
from importlib.metadata import entry_points

import cv2
import numpy as np
import pytest

from hardware.calibration import WalkerCalibration
from hardware.clock import HostClock
from hardware.depth import open_depth
from hardware.devices import DEPTH_CAMERAS, TAG_CAMERAS, DeviceSpec, forms, split_spec
from hardware.errors import DeviceError
from hardware.tags import TagCameraError, open_frames, parse_spec


def test_the_built_in_devices_come_from_the_entry_points():
    for registry, names in (
        (DEPTH_CAMERAS, {"kinect", "fakenect", "realsense"}),
        (TAG_CAMERAS, {"device", "kinect", "fakenect", "video", "images"}),
    ):
        declared = {ep.name: ep.load() for ep in entry_points(group=registry.group)}
        assert set(declared) == names == set(registry.names())
        assert all(isinstance(s, DeviceSpec) and s.forms for s in declared.values())


def test_another_packages_depth_camera_opens_through_open_depth(monkeypatch):
    opened = []

    class Camera:  # a Source would stream DepthFrames; only the call is checked here
        def __init__(self, arg, calibration, clock, **options):
            opened.append((arg, calibration, clock, options))

    spec = DeviceSpec("oak-d", None, Camera, "test camera", forms=("oak-d", "oak-d:SERIAL"))
    DEPTH_CAMERAS.names()  # the entry points loaded first
    monkeypatch.setitem(DEPTH_CAMERAS._specs, "oak-d", spec)
    cal, clock = WalkerCalibration(), HostClock()
    assert isinstance(open_depth("oak-d:1844", cal, clock, decimation=2), Camera)
    assert isinstance(open_depth("oak-d", cal, clock), Camera)
    assert opened == [("1844", cal, clock, {"decimation": 2}), (None, cal, clock, {})]
    assert "oak-d:SERIAL" in forms(DEPTH_CAMERAS)
    with pytest.raises(DeviceError, match=r"valid: .*oak-d:SERIAL"):
        open_depth("oak", cal, clock)


def test_specs_are_name_and_argument():
    assert split_spec("kinect") == ("kinect", None)
    assert split_spec("kinect:2") == ("kinect", "2")
    assert split_spec("fakenect:/a/b:c") == ("fakenect", "/a/b:c")
    assert parse_spec(3) == parse_spec("3") == parse_spec("device:3") == ("device", "3")
    assert parse_spec("kinect:1") == ("kinect", "1")
    with pytest.raises(TagCameraError) as e:
        parse_spec("webcam-front")
    assert "\n" not in str(e.value)
    assert str(e.value).endswith(", ".join(forms(TAG_CAMERAS)))
    with pytest.raises(DeviceError, match="realsense takes no argument"):
        open_depth("realsense:0", WalkerCalibration(), HostClock())
    with pytest.raises(TagCameraError, match="device:INDEX needs an index"):
        open_frames("device:front", HostClock())


def test_an_image_folder_opens_by_path_or_by_name(tmp_path):
    rng = np.random.default_rng(4)
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), rng.integers(0, 255, (24, 32), dtype=np.uint8))
    assert parse_spec(tmp_path) == ("images", str(tmp_path))
    assert parse_spec(tmp_path / "f0.png") == ("images", str(tmp_path / "f0.png"))
    counts = []
    for spec in (tmp_path, f"images:{tmp_path}"):
        frames = open_frames(spec, HostClock())
        try:
            got = list(frames.frames(threading.Event()))
        finally:
            frames.release()
        assert frames.kind == "folder"
        counts.append(len(got))
        assert all(img.shape[:2] == (24, 32) for _, img in got)
    assert counts == [3, 3]
