"""The tag camera: AprilTag detection on real images and the live tag-camera source.

    camera = load_camera_yaml("camera.yaml")           # hardware.camera_calibration
    detector = TagDetector(camera, tag_size_m=0.165)   # family tag36h11
    detector.detect(image)                             # -> tuple[TagDetection, ...]

    src = open_tag_camera(0, calibration, clock, camera_yaml="camera.yaml")
    for msg in src.messages():                         # TagDetections, one per image
        ...
    src.close()                                        # from any thread

Detections are the same `hardware.messages.TagDetection` the simulated tag camera
(`hardware.sim.tag_camera`) produces, computed the same way:

- pupil-apriltags finds the tags and their corners. Its pixel coordinates put the centre
  of the top-left pixel at (0.5, 0.5) (AprilRobotics/apriltag issue #121; measured here on
  rendered tags: +0.50 px in u and v at every quad_decimate); OpenCV's, the camera
  calibration's and the simulator's put it at (0, 0). The corners are shifted by −0.5 px
  into OpenCV's convention.
- The corners are undistorted with the calibration's K and distortion coefficients into
  the ideal pinhole image of the same K (`cv2.undistortPoints`, iterated to 1e-10), and
  the pose is solved from them with `cv2.solvePnP(..., SOLVEPNP_IPPE_SQUARE)` on the tag
  object points of `hardware.sim.tag_camera.tag_object_points` — exactly the call the
  simulated camera makes. With distortion this is the pose solvePnP would give on the
  distorted corners with K and the coefficients (it undistorts them the same way, with
  fewer iterations); pupil-apriltags' own pose (homography + orthogonal iteration) cannot
  take distortion at all.
- `corners_px` are those undistorted corners (`undistort_corners=True`, the default), so
  a detection means the same as a simulated one: the tag's corners in the pinhole image
  of `WalkerCalibration.tag_intrinsics` (which has no distortion), in the order of
  hardware/messages.py (corner 0 at the tag's (−s/2, +s/2), counter-clockwise in the
  image), and `camera_T_tag` re-projects onto them. `undistort_corners=False` reports
  the corners where they are in the captured image instead (the pose is the same).
- `decision_margin` is pupil-apriltags' (how far the sampled bits are from the
  black/white threshold; 45-193 on the NASA photos, 60-93 on the Duckietown set).

Measured on this machine (tests/hardware/test_tags.py): on rendered tags at 0.8-3 m
(640×480, f ≈ 530 px) the corners are within 0.27 px of the truth (RMS 0.07 px, no
bias left), the translation within 0.3 % and the rotation within 0.8° (RMS 0.27°) —
except close to frontal, where a square tag's tilt is ill-conditioned (2.0° at 1 m
exactly frontal; 0.2° with refine_pose); through a strongly distorting lens (k1 = −0.28)
the same within 0.3 % and 0.3°. The simulated camera and this detector agree on the same
view within 0.25 px, 0.2 % and 0.8°. On the Duckietown rotation set the yaw (turn of the
tag normal about the camera's y axis) is −rotz with 3.2° RMS (bias +2.0°, max 7.2° near
frontal); the NASA reference corners are all matched within 0.14 px with the
reference's settings (refine_edges=False).

Three pupil-apriltags 1.0.4 (AprilTag 3.1) facts shape the detector. (1) Its
`Detector.__del__` frees the tag families before the C detector, which then writes into
the freed families: heap corruption that aborted 6 of 6 runs of a script creating a few
dozen detectors (pupil-labs/apriltags PR #65, unmerged). `TagDetector` frees its pupil
detector itself, in the right order, and disarms pupil's __del__. (2) It passes
`decode_sharpening` to the C library truncated to an int (0.25 → 0); `TagDetector` sets
the value in the detector struct, so AprilTag's default 0.25 applies: on the NASA photos
it decodes 47 of 47 reference tags instead of 46 and raises the decision margins from
26-96 to 45-193. (3) `refine_edges` (on by default) snaps the quad edges to the gradient:
on rendered tags it halves the corner error (RMS 0.10 → 0.04 px) but moves the corners of
the smallest (~12 px) real tags by up to 0.8 px and loses one or two of them (NASA: 45 of
47 references within 2 px; with refine_edges=False all 47 within 0.14 px).

**Sources.** `open_tag_camera(spec, ...)` opens a device index (OpenCV `VideoCapture`),
a video file, an image folder (files sorted by name), a single image, or `kinect` /
`kinect:N` / `fakenect:DIR` (the Kinect's RGB stream through
`hardware.depth.kinect_rgb_frames`, which stamps it from the device's clock). A
capture thread reads frames and stamps them on the run's `HostClock` when they arrive
(`VideoCapture.grab()` returning; the file read for folders); the consumer's thread
detects. The buffer between them holds one frame:

- `drop_frames=True` (default for devices and the Kinect): the capture thread always
  replaces the waiting frame by the newest one, so detection runs on the newest frame
  when it is slower than the camera and the stream lags by at most one frame; each
  replaced frame is counted (`frames_skipped` in `diagnostics` and the metadata).
- `drop_frames=False` (default for files and folders): every frame is detected, the
  capture thread waits for the detector (reproducible on recorded input). `fps` paces a
  file or folder like a camera (default: as fast as the detector takes them).

Each frame gives one `TagDetections` (possibly empty), with strictly increasing t (a frame
whose stamp is not later than the previous one is dropped and counted). `close()` from
any thread ends a blocked `messages()` iterator at once; ending or abandoning the
iterator closes the source. Errors (unknown spec, missing file, unopenable device, a
device that stops delivering, a frame of another size than the calibration) raise
`TagCameraError`, a ValueError with one line.
"""

from __future__ import annotations

import math
import os
import threading
import time
import weakref
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

from hardware.calibration import WalkerCalibration
from hardware.camera_calibration import (
    TAG_FAMILIES,
    CameraCalibration,
    load_camera_yaml,
    to_grey,
    with_tag_camera,
)
from hardware.clock import HostClock
from hardware.devices import TAG_CAMERAS, DeviceSpec, forms, split_spec
from hardware.errors import DeviceError
from hardware.frames import make_transform
from hardware.messages import CameraIntrinsics, TagDetection, TagDetections
from hardware.sim.tag_camera import tag_object_points

#: pupil-apriltags' pixel coordinate of the centre of the top-left pixel (OpenCV: 0).
PUPIL_PIXEL_CENTRE = 0.5

#: File name endings of the images an image folder source reads.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm", ".pnm", ".tif", ".tiff")

_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)


class TagCameraError(DeviceError):
    """A tag camera that cannot be opened or stopped working (one line)."""


class TagDetector:
    """AprilTag detector producing `TagDetection`s in the simulated tag camera's conventions.

    camera: the calibration (intrinsics and distortion) or pinhole intrinsics (no
    distortion); tag_size_m: edge of the tag's black square; family: a pupil-apriltags
    family. min_decision_margin: detections below it are dropped; max_hamming: most bit
    errors accepted (pupil-apriltags corrects up to 2); quad_decimate: detect quads on an
    image decimated by this factor (faster, misses small tags; the corners are refined
    on the full image); threads: detector threads; quad_sigma: Gaussian blur of the quad
    image; refine_edges: snap the quad edges to strong gradients; undistort_corners: see
    the module docstring; refine_pose: polish the IPPE pose by Levenberg-Marquardt on the
    reprojection error (`cv2.solvePnPRefineLM`). refine_pose is off by default because the
    simulated camera does not refine; measured: on the Duckietown rotation set it lowers
    the yaw error from 3.2° to 2.4° RMS (max 7.2° → 4.7°), on rendered tags it raises the
    rotation error from 0.25° to 0.32° RMS; decode_sharpening: sharpening of the sampled
    bits (AprilTag's default 0.25). Images must have the calibration's size. Thread-safe
    (one detection at a time).
    """

    def __init__(
        self,
        camera: CameraCalibration | CameraIntrinsics,
        tag_size_m: float,
        family: str = "tag36h11",
        *,
        min_decision_margin: float = 0.0,
        max_hamming: int = 2,
        quad_decimate: float = 1.0,
        threads: int = 1,
        quad_sigma: float = 0.0,
        refine_edges: bool = True,
        undistort_corners: bool = True,
        refine_pose: bool = False,
        decode_sharpening: float = 0.25,
    ) -> None:
        import pupil_apriltags

        if isinstance(camera, CameraIntrinsics):
            camera = CameraCalibration.from_intrinsics(camera)
        if family not in TAG_FAMILIES:
            raise ValueError(f"unknown tag family {family!r}; valid: {', '.join(TAG_FAMILIES)}")
        if not (math.isfinite(tag_size_m) and tag_size_m > 0):
            raise ValueError(f"tag_size_m must be > 0, got {tag_size_m}")
        if not quad_decimate >= 1.0:
            raise ValueError(f"quad_decimate must be >= 1, got {quad_decimate}")
        if threads < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        if not 0 <= max_hamming <= 2:
            raise ValueError(f"max_hamming must be 0, 1 or 2, got {max_hamming}")
        self.camera = camera
        self.tag_size_m = float(tag_size_m)
        self.family = family
        self.min_decision_margin = float(min_decision_margin)
        self.max_hamming = int(max_hamming)
        self.quad_decimate = float(quad_decimate)
        self.threads = int(threads)
        self.quad_sigma = float(quad_sigma)
        self.refine_edges = bool(refine_edges)
        self.undistort_corners = bool(undistort_corners)
        self.refine_pose = bool(refine_pose)
        self.decode_sharpening = float(decode_sharpening)
        self.object_points = tag_object_points(self.tag_size_m)
        self._k = camera.camera_matrix
        self._dist = camera.distortion if camera.has_distortion else None
        self._lock = threading.Lock()
        self._detector = pupil_apriltags.Detector(
            families=family,
            nthreads=self.threads,
            quad_decimate=self.quad_decimate,
            quad_sigma=self.quad_sigma,
            refine_edges=int(self.refine_edges),
        )
        weakref.finalize(self, release_pupil_detector, self._detector)
        # pupil-apriltags passes int(decode_sharpening): set the real value in the struct
        self._detector.tag_detector_ptr.contents.decode_sharpening = self.decode_sharpening

    @classmethod
    def from_calibration(
        cls,
        calibration: WalkerCalibration,
        camera: CameraCalibration | None = None,
        **options: Any,
    ) -> TagDetector:
        """The detector of a walker's tag camera: the camera file's intrinsics, distortion
        and tag settings where given, else the calibration's (no distortion)."""
        if camera is None:
            camera = CameraCalibration.from_intrinsics(calibration.tag_intrinsics)
        family = camera.tag_family or calibration.tag_family
        size = camera.tag_size_m or calibration.tag_size_m
        return cls(camera, size, family, **options)

    def settings(self) -> dict[str, Any]:
        """The detector's settings (strict JSON)."""
        return {
            "family": self.family,
            "tag_size_m": self.tag_size_m,
            "min_decision_margin": self.min_decision_margin,
            "max_hamming": self.max_hamming,
            "quad_decimate": self.quad_decimate,
            "threads": self.threads,
            "quad_sigma": self.quad_sigma,
            "refine_edges": self.refine_edges,
            "decode_sharpening": self.decode_sharpening,
            "corners": "undistorted" if self.undistort_corners else "image",
            "pose": "cv2.solvePnP SOLVEPNP_IPPE_SQUARE on the undistorted corners"
            + (", refined by cv2.solvePnPRefineLM" if self.refine_pose else ""),
        }

    def detect(self, image: np.ndarray) -> tuple[TagDetection, ...]:
        """The tags in one image (grey or BGR uint8), sorted by tag id."""
        grey = to_grey(np.asarray(image))
        h, w = grey.shape
        if (w, h) != (self.camera.width, self.camera.height):
            raise ValueError(
                f"image is {w}x{h} but the camera calibration is for "
                f"{self.camera.width}x{self.camera.height}"
            )
        with self._lock:
            found = self._detector.detect(grey)
        out = []
        for d in found:
            if d.hamming > self.max_hamming or d.decision_margin < self.min_decision_margin:
                continue
            image_px = np.asarray(d.corners, dtype=np.float64) - PUPIL_PIXEL_CENTRE
            ideal_px = self.undistort(image_px)
            ok, rvec, tvec = cv2.solvePnP(
                self.object_points, ideal_px, self._k, None, flags=cv2.SOLVEPNP_IPPE_SQUARE
            )
            if not ok:
                continue
            if self.refine_pose:
                rvec, tvec = cv2.solvePnPRefineLM(
                    self.object_points, ideal_px, self._k, None, rvec, tvec
                )
            rot, _ = cv2.Rodrigues(rvec)
            corners = ideal_px if self.undistort_corners else image_px
            out.append(
                TagDetection(
                    int(d.tag_id),
                    make_transform(rot, tvec.ravel()),
                    corners,
                    float(d.decision_margin),
                )
            )
        out.sort(key=lambda det: det.tag_id)
        return tuple(out)

    def undistort(self, image_px: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N×2, OpenCV convention) of the captured image → the same
        points in the ideal pinhole image of K."""
        pts = np.asarray(image_px, dtype=np.float64).reshape(-1, 2)
        if self._dist is None:
            return pts.copy()
        und = cv2.undistortPoints(
            pts.reshape(-1, 1, 2),
            self._k,
            self._dist,
            R=None,
            P=self._k,
            criteria=_UNDISTORT_CRITERIA,
        )
        return und.reshape(-1, 2)


def release_pupil_detector(detector: Any) -> None:
    """Free a pupil-apriltags detector in the right order: the C detector first (it clears
    its families' decode tables), then the families. pupil-apriltags 1.0.4's own __del__
    frees the families first, so the C detector then writes into freed memory: heap
    corruption that aborted or crashed a process that made a few detectors (measured:
    6 of 6 runs creating 48; pupil-labs/apriltags PR #65, unmerged)."""
    ptr = getattr(detector, "tag_detector_ptr", None)
    if ptr is None:
        return
    detector.tag_detector_ptr = None  # its own __del__ then does nothing
    lib = detector.libc
    lib.apriltag_detector_destroy.restype = None
    lib.apriltag_detector_destroy(ptr)
    for name, family in detector.tag_families.items():
        destroy = getattr(lib, f"{name}_destroy")
        destroy.restype = None
        destroy(family)


# -- frame sources ----------------------------------------------------------------------


class FrameSource(Protocol):
    """Images stamped on the run's clock. `frames(stop)` runs in the capture thread."""

    kind: str  # "device", "video", "folder", "kinect"
    name: str
    live: bool  # a real-time device (drop frames by default)

    def frames(self, stop: threading.Event) -> Iterator[tuple[float, np.ndarray]]: ...

    def describe(self) -> dict[str, Any]: ...

    def release(self) -> None: ...


@contextmanager
def _quiet_opencv() -> Iterator[None]:
    """OpenCV's warnings on stderr off while opening (an absent device is an error here)."""
    logging = cv2.utils.logging
    level = logging.getLogLevel()
    logging.setLogLevel(logging.LOG_LEVEL_ERROR)
    try:
        yield
    finally:
        logging.setLogLevel(level)


class VideoCaptureFrames:
    """Frames of an OpenCV `VideoCapture`: a device index or path (/dev/videoN) or a video
    file.

    width, height: resolution to request from a device (it may not honour it; the tag
    camera source then reports the mismatch). fps: for a file, deliver at most this many
    frames per second (default: as fast as they are taken); for a device, the rate to
    request.
    """

    def __init__(
        self,
        target: int | str | os.PathLike[str],
        clock: HostClock,
        *,
        width: int | None = None,
        height: int | None = None,
        fps: float | None = None,
    ) -> None:
        self.clock = clock
        self.fps = fps
        if isinstance(target, int) or Path(target).is_char_device():  # index or /dev/videoN
            self.kind, self.live, self.name = "device", True, str(target)
            with _quiet_opencv():
                cap = cv2.VideoCapture(target if isinstance(target, int) else str(target))
            if not cap.isOpened():
                raise TagCameraError(f"tag camera {target}: cannot open video device {target}")
            for prop, value in (
                (cv2.CAP_PROP_FRAME_WIDTH, width),
                (cv2.CAP_PROP_FRAME_HEIGHT, height),
                (cv2.CAP_PROP_FPS, fps),
            ):
                if value:
                    cap.set(prop, value)
        else:
            path = Path(target)
            self.kind, self.live, self.name = "video", False, str(path)
            if not path.is_file():
                raise TagCameraError(f"tag camera {path}: no such file")
            with _quiet_opencv():
                cap = cv2.VideoCapture(str(path))
            if not cap.isOpened():
                raise TagCameraError(f"tag camera {path}: not a video file OpenCV can read")
        self._cap = cap
        self._lock = threading.Lock()

    def describe(self) -> dict[str, Any]:
        d: dict[str, Any] = {"kind": self.kind, "source": self.name}
        with self._lock:
            if self._cap is not None:
                d["width"] = int(self._cap.get(cv2.CAP_PROP_FRAME_WIDTH))
                d["height"] = int(self._cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
                fps = float(self._cap.get(cv2.CAP_PROP_FPS))
                d["reported_fps"] = fps if math.isfinite(fps) else 0.0
                d["backend"] = self._cap.getBackendName()
        if self.fps:
            d["fps"] = float(self.fps)
        return d

    def frames(self, stop: threading.Event) -> Iterator[tuple[float, np.ndarray]]:
        pace = _Pacer(self.fps if not self.live else None)
        while not stop.is_set():
            if not pace.wait(stop):
                return
            cap = self._cap
            if cap is None or not cap.grab():
                if self.live and not stop.is_set():
                    raise TagCameraError(
                        f"tag camera {self.name}: the device stopped delivering frames"
                    )
                return
            t = self.clock.now()
            ok, img = cap.retrieve()
            if not ok or img is None:
                if self.live:
                    raise TagCameraError(f"tag camera {self.name}: could not decode a frame")
                return
            yield t, img

    def release(self) -> None:
        with self._lock:
            if self._cap is not None:
                self._cap.release()
                self._cap = None


class ImageFolderFrames:
    """The images of a folder in file-name order (or one image file), read at capture.

    fps: deliver at most this many frames per second (default: as fast as taken)."""

    kind = "folder"
    live = False

    def __init__(
        self, path: str | os.PathLike[str], clock: HostClock, *, fps: float | None = None
    ) -> None:
        p = Path(path)
        self.name = str(p)
        self.clock = clock
        self.fps = fps
        if p.is_dir():
            self.paths = sorted(
                (f for f in p.iterdir() if f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES),
                key=lambda f: f.name,
            )
            if not self.paths:
                raise TagCameraError(
                    f"tag camera {p}: no images in the folder ({', '.join(IMAGE_SUFFIXES)})"
                )
        elif p.is_file():
            self.paths = [p]
        else:
            raise TagCameraError(f"tag camera {p}: no such file or folder")

    def describe(self) -> dict[str, Any]:
        d: dict[str, Any] = {"kind": self.kind, "source": self.name, "images": len(self.paths)}
        if self.fps:
            d["fps"] = float(self.fps)
        return d

    def frames(self, stop: threading.Event) -> Iterator[tuple[float, np.ndarray]]:
        pace = _Pacer(self.fps)
        for f in self.paths:
            if stop.is_set() or not pace.wait(stop):
                return
            img = cv2.imread(str(f), cv2.IMREAD_COLOR)
            t = self.clock.now()
            if img is None:
                raise TagCameraError(f"tag camera {self.name}: {f.name} is not a readable image")
            yield t, img

    def release(self) -> None:
        pass


class KinectFrames:
    """The Kinect's RGB stream through `hardware.depth.kinect_rgb_frames` (BGR, stamped
    there on the clock at capture). spec: "kinect", "kinect:INDEX" or "fakenect:DIR" (a
    recording replayed through libfreenect). Opening waits for the first frame."""

    kind = "kinect"
    live = True

    def __init__(self, spec: str, clock: HostClock) -> None:
        self.name = spec
        self.clock = clock
        try:
            from hardware.depth import kinect_rgb_frames
        except ImportError as e:
            raise TagCameraError(
                f"tag camera {spec}: hardware.depth.kinect_rgb_frames is not available ({e})"
            ) from None
        index: int | str = int(spec.split(":", 1)[1]) if spec.startswith("kinect:") else spec
        if spec == "kinect":
            index = 0
        self._stop = _StopFlag()
        try:
            self._stream: Any = kinect_rgb_frames(clock, index=index, stop=self._stop)
        except ValueError as e:  # hardware.depth.DeviceError: one line already
            raise TagCameraError(f"tag camera {spec}: {e}") from None
        self._lock = threading.Lock()

    def describe(self) -> dict[str, Any]:
        return {"kind": self.kind, "source": self.name}

    def diagnostics(self) -> dict[str, Any]:
        """The driver's own counts (frames it dropped or the device skipped)."""
        out = {}
        for key in ("frames_dropped", "frames_skipped"):
            value = getattr(self._stream, key, None)
            if isinstance(value, int):
                out[f"driver_{key}"] = value
        return out

    def frames(self, stop: threading.Event) -> Iterator[tuple[float, np.ndarray]]:
        self._stop.also(stop)  # the stream then ends <= 0.1 s after the source's stop
        for t, img in self._stream:
            if stop.is_set():
                return
            yield t, img

    def release(self) -> None:
        self._stop.set()
        with self._lock:
            close = getattr(self._stream, "close", None)
            if close is not None:
                close()


class _StopFlag:
    """Set by release(), or when an attached event is set (what `stop` arguments take)."""

    def __init__(self) -> None:
        self._own = threading.Event()
        self._other: threading.Event | None = None

    def also(self, event: threading.Event) -> None:
        self._other = event

    def set(self) -> None:
        self._own.set()

    def is_set(self) -> bool:
        return self._own.is_set() or (self._other is not None and self._other.is_set())


class _Pacer:
    """Waits until frame i is due at i / fps after the first (no wait without fps)."""

    def __init__(self, fps: float | None) -> None:
        self.period = 1.0 / fps if fps else 0.0
        self.start: float | None = None
        self.i = 0

    def wait(self, stop: threading.Event) -> bool:
        """False when stopped while waiting."""
        if self.period > 0:
            now = time.monotonic()
            if self.start is None:
                self.start = now
            delay = self.start + self.i * self.period - now
            if delay > 0 and stop.wait(delay):
                return False
        self.i += 1
        return not stop.is_set()


def _open_device(arg, clock, *, width=None, height=None, fps=None) -> VideoCaptureFrames:
    if arg is None or not arg.isdigit():
        raise TagCameraError(f"tag camera device:INDEX needs an index >= 0, got {arg!r}")
    return VideoCaptureFrames(int(arg), clock, width=width, height=height, fps=fps)


def _open_kinect(arg, clock, **_: Any) -> KinectFrames:
    return KinectFrames("kinect" if arg is None else f"kinect:{arg}", clock)


def _open_fakenect(arg, clock, **_: Any) -> KinectFrames:
    return KinectFrames(f"fakenect:{arg or ''}", clock)


def _open_video(arg, clock, *, fps=None, **_: Any) -> VideoCaptureFrames:
    return VideoCaptureFrames(Path(arg or ""), clock, fps=fps)


def _open_images(arg, clock, *, fps=None, **_: Any) -> ImageFolderFrames:
    return ImageFolderFrames(Path(arg or ""), clock, fps=fps)


DEVICE = DeviceSpec(
    "device", None, _open_device, "a camera through OpenCV", forms=("INDEX", "device:INDEX")
)
KINECT = DeviceSpec(
    "kinect", None, _open_kinect, "the Kinect's RGB stream", forms=("kinect", "kinect:INDEX")
)
FAKENECT = DeviceSpec(
    "fakenect", None, _open_fakenect, "a fakenect recording's RGB", forms=("fakenect:DIR",)
)
VIDEO = DeviceSpec(
    "video",
    None,
    _open_video,
    "a video file or V4L2 device path through OpenCV",
    forms=("video:PATH", "a video file", "/dev/videoN"),
)
IMAGES = DeviceSpec(
    "images",
    None,
    _open_images,
    "an image, or a folder of images in name order",
    forms=("images:PATH", "an image or image folder"),
)


def parse_spec(spec: int | str | os.PathLike[str]) -> tuple[str, str | None]:
    """A tag camera spec → (member name, ARG) of hardware.devices.TAG_CAMERAS: a device
    index (int or digits) stands for device:INDEX, an existing path for video:PATH or
    images:PATH (by its suffix; a folder is images), anything else is NAME[:ARG]."""
    if isinstance(spec, bool):
        raise TagCameraError(f"unknown tag camera {spec!r}")
    if isinstance(spec, int):
        if spec < 0:
            raise TagCameraError(f"tag camera {spec}: a device index must be >= 0")
        return "device", str(spec)
    if not isinstance(spec, str | os.PathLike):
        raise TagCameraError(f"unknown tag camera {spec!r}")
    text = str(spec).strip()
    if text.isdigit():
        return "device", text
    path = Path(spec)
    if path.exists():
        images = path.is_dir() or path.suffix.lower() in IMAGE_SUFFIXES
        return ("images" if images else "video"), str(path)
    if isinstance(spec, str) and split_spec(text)[0] in TAG_CAMERAS.names():
        return split_spec(text)
    raise TagCameraError(
        f"unknown tag camera {str(spec)!r}: not an existing file or folder; valid: "
        f"{', '.join(forms(TAG_CAMERAS))}"
    )


def open_frames(
    spec: int | str | os.PathLike[str],
    clock: HostClock,
    *,
    width: int | None = None,
    height: int | None = None,
    fps: float | None = None,
) -> FrameSource:
    """The frame source of a tag camera spec (see `open_tag_camera`)."""
    name, arg = parse_spec(spec)
    return TAG_CAMERAS.spec(name).factory(arg, clock, width=width, height=height, fps=fps)


# -- the tag camera source --------------------------------------------------------------


class TagCameraSource:
    """A Source of `TagDetections`: one per captured frame, detected in the consumer's
    thread (see the module docstring for the frame policy)."""

    def __init__(
        self,
        frames: FrameSource,
        detector: TagDetector,
        calibration: WalkerCalibration,
        *,
        drop_frames: bool | None = None,
        camera_yaml: str | None = None,
    ) -> None:
        self.frames = frames
        self.detector = detector
        self._calibration = calibration
        self.drop_frames = frames.live if drop_frames is None else bool(drop_frames)
        self.camera_yaml = camera_yaml
        self._cv = threading.Condition()
        self._stop = threading.Event()
        self._pending: tuple[float, np.ndarray] | None = None
        self._finished = False
        self._closed = False
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None
        self._counts = {
            "frames_captured": 0,
            "frames_skipped": 0,
            "frames_out_of_order": 0,
            "frames_detected": 0,
            "detections": 0,
        }
        self._detect_s = 0.0
        self._described = frames.describe()

    @property
    def calibration(self) -> WalkerCalibration:
        return self._calibration

    @property
    def diagnostics(self) -> dict[str, Any]:
        """Frame counts so far: captured (accepted from the camera), skipped (replaced by a
        newer frame before detection), out of order (dropped: stamp not increasing),
        detected (TagDetections yielded), detections (tags), mean detection time; and the
        driver's own counts where it has them (`driver_*`)."""
        with self._cv:
            d: dict[str, Any] = dict(self._counts)
        n = d["frames_detected"]
        d["detect_ms_mean"] = 1000.0 * self._detect_s / n if n else 0.0
        driver = getattr(self.frames, "diagnostics", None)
        if driver is not None:
            d.update(driver())
        return d

    @property
    def metadata(self) -> dict[str, Any]:
        return {
            "tag_camera": {
                **self._described,
                "frame_policy": "newest" if self.drop_frames else "every",
                "camera_yaml": self.camera_yaml,
                "camera": self.detector.camera.to_dict(),
                "detector": self.detector.settings(),
                **self.diagnostics,
            }
        }

    def messages(self) -> Iterator[TagDetections]:
        """TagDetections in time order; live: can be iterated once."""
        with self._cv:
            if self._thread is not None:
                raise RuntimeError(f"tag camera {self.frames.name}: messages() already iterated")
            self._thread = threading.Thread(
                target=self._capture, name=f"tag-camera-{self.frames.name}", daemon=True
            )
            closed = self._closed
        if not closed:
            self._thread.start()
        return self._iterate()

    def _capture(self) -> None:
        last_t = -math.inf
        try:
            for t, img in self.frames.frames(self._stop):
                with self._cv:
                    if self._closed:
                        return
                    if not t > last_t:
                        self._counts["frames_out_of_order"] += 1
                        continue
                    last_t = t
                    if not self.drop_frames:
                        while self._pending is not None and not self._closed:
                            self._cv.wait()
                        if self._closed:
                            return
                    if self._pending is not None:
                        self._counts["frames_skipped"] += 1
                    self._pending = (t, img)
                    self._counts["frames_captured"] += 1
                    self._cv.notify_all()
        except TagCameraError as e:
            self._error = e
        except Exception as e:  # a driver's failure ends the stream with one line
            first = str(e).strip().splitlines()[0] if str(e).strip() else ""
            self._error = TagCameraError(
                f"tag camera {self.frames.name}: {type(e).__name__}: {first}"
            )
        finally:
            self.frames.release()
            with self._cv:
                self._finished = True
                self._cv.notify_all()

    def _iterate(self) -> Iterator[TagDetections]:
        cal = self.detector.camera
        try:
            while True:
                with self._cv:
                    while self._pending is None and not self._finished and not self._closed:
                        self._cv.wait()
                    if self._closed:
                        return
                    if self._pending is None:
                        if self._error is not None:
                            raise self._error
                        return
                    t, img = self._pending
                    self._pending = None
                    self._cv.notify_all()
                h, w = img.shape[:2]
                if (w, h) != (cal.width, cal.height):
                    where = f" ({self.camera_yaml})" if self.camera_yaml else ""
                    raise TagCameraError(
                        f"tag camera {self.frames.name}: frame is {w}x{h} but the camera "
                        f"calibration{where} is for {cal.width}x{cal.height}"
                    )
                t0 = time.perf_counter()
                dets = self.detector.detect(img)
                dt = time.perf_counter() - t0
                with self._cv:
                    if self._closed:
                        return
                    self._detect_s += dt
                    self._counts["frames_detected"] += 1
                    self._counts["detections"] += len(dets)
                yield TagDetections(t, dets)
        finally:
            self.close(timeout_s=0.0)  # the consumer does not wait for a stuck driver

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop: a blocked `messages()` iterator ends at once; the device is released by
        the capture thread when its current read returns (waited for up to timeout_s)."""
        with self._cv:
            self._closed = True
            self._pending = None
            self._cv.notify_all()
            thread = self._thread
        self._stop.set()
        if thread is None or not thread.is_alive():
            if thread is None or thread.ident is None:
                self.frames.release()
            return
        if timeout_s > 0 and thread is not threading.current_thread():
            thread.join(timeout_s)


def open_tag_camera(
    spec: int | str | os.PathLike[str],
    calibration: WalkerCalibration,
    clock: HostClock,
    camera_yaml: str | os.PathLike[str] | None = None,
    *,
    fps: float | None = None,
    drop_frames: bool | None = None,
    **detector_options: Any,
) -> TagCameraSource:
    """Open a tag camera as a Source of TagDetections stamped on `clock`.

    spec: a device index (int or digits), "kinect" / "kinect:N" / "fakenect:DIR", a video
    file, an image file or a folder of images. camera_yaml: the camera calibration file (intrinsics,
    distortion, optionally tag family and size); without it the calibration's
    tag_intrinsics with no distortion. The source's calibration is `calibration` with the
    file's intrinsics and tag settings. A device is asked for the calibration's
    resolution. fps, drop_frames: see the module docstring; detector_options:
    `TagDetector` keywords (min_decision_margin, quad_decimate, threads, ...).
    """
    camera = load_camera_yaml(camera_yaml) if camera_yaml is not None else None
    cal = with_tag_camera(calibration, camera) if camera is not None else calibration
    detector = TagDetector.from_calibration(cal, camera, **detector_options)
    size = cal.tag_intrinsics
    frames = open_frames(spec, clock, width=size.width, height=size.height, fps=fps)
    try:
        return TagCameraSource(
            frames,
            detector,
            cal,
            drop_frames=drop_frames,
            camera_yaml=None if camera_yaml is None else str(camera_yaml),
        )
    except BaseException:
        frames.release()
        raise
