"""A camera's intrinsics and distortion: the calibration YAML file and checkerboard calibration.

File format: the ROS / OpenCV ``camera_info`` YAML (what ROS ``camera_calibration``
writes), plus the tag settings of the tag camera::

    image_width: 640
    image_height: 480
    camera_name: tag_camera
    camera_matrix: {rows: 3, cols: 3, data: [fx, 0, cx, 0, fy, cy, 0, 0, 1]}
    distortion_model: plumb_bob            # or rational_polynomial
    distortion_coefficients: {rows: 1, cols: 5, data: [k1, k2, p1, p2, k3]}
    rectification_matrix: {rows: 3, cols: 3, data: [1, 0, 0, 0, 1, 0, 0, 0, 1]}
    projection_matrix: {rows: 3, cols: 4, data: [fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0]}
    tag_family: tag36h11                   # optional: the walker calibration's when absent
    tag_size_m: 0.165                      # optional: edge of the tag's black square [m]

Required: image_width, image_height, camera_matrix, distortion_model,
distortion_coefficients. camera_name, the rectification and projection matrices and the
tag keys are optional (the rectification and projection matrices are written for ROS
tools and ignored on reading: a monocular camera's are the identity and [K | 0]); other
keys are ignored. Pixel coordinates follow OpenCV: (0, 0) is the centre of the top-left
pixel. The distortion coefficients are OpenCV's (k1, k2, p1, p2, k3[, k4, k5, k6]): plumb_bob
has 5, rational_polynomial 8. The camera matrix must have no skew (`CameraIntrinsics`
has none). Every problem with a file raises `CameraCalibrationError` (a ValueError) with
one line naming the file and what is wrong.

`calibrate_camera` calibrates from checkerboard photos with OpenCV
(`findChessboardCorners`, `cornerSubPix`, `calibrateCamera`) and returns a
`CheckerboardCalibration` that holds everything worth reporting and writes the file.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from hardware.calibration import WalkerCalibration
from hardware.errors import ConfigError
from hardware.messages import CameraIntrinsics

#: Tag families pupil-apriltags can detect.
TAG_FAMILIES = (
    "tag16h5",
    "tag25h9",
    "tag36h11",
    "tagCircle21h7",
    "tagCircle49h12",
    "tagCustom48h12",
    "tagStandard41h12",
    "tagStandard52h13",
)

#: Number of distortion coefficients of each supported distortion model.
DISTORTION_MODELS = {"plumb_bob": 5, "rational_polynomial": 8}

_REQUIRED_KEYS = (
    "image_width",
    "image_height",
    "camera_matrix",
    "distortion_model",
    "distortion_coefficients",
)


class CameraCalibrationError(ConfigError):
    """A camera calibration file or a checkerboard calibration that cannot be used (one
    line: the file and what is wrong)."""


@dataclass(frozen=True, eq=False)
class CameraCalibration:
    """Intrinsics and distortion of one camera at one resolution (OpenCV conventions).

    camera_matrix: 3×3 K; distortion: OpenCV coefficients (k1, k2, p1, p2, k3[, ...]);
    tag_family / tag_size_m: the tag settings the file carries (None: not given).
    """

    width: int
    height: int
    camera_matrix: np.ndarray
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(5))
    distortion_model: str = "plumb_bob"
    camera_name: str = "camera"
    tag_family: str | None = None
    tag_size_m: float | None = None

    def __post_init__(self) -> None:
        k = np.array(self.camera_matrix, dtype=np.float64)
        d = np.array(self.distortion, dtype=np.float64).ravel()
        object.__setattr__(self, "camera_matrix", k)
        object.__setattr__(self, "distortion", d)
        problem = _camera_problem(
            self.width, self.height, k, self.distortion_model, d, self.tag_family, self.tag_size_m
        )
        if problem:
            raise ValueError(problem)
        k.setflags(write=False)
        d.setflags(write=False)

    @classmethod
    def from_intrinsics(
        cls,
        intrinsics: CameraIntrinsics,
        distortion: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0, 0.0, 0.0),
        *,
        camera_name: str = "camera",
        tag_family: str | None = None,
        tag_size_m: float | None = None,
    ) -> CameraCalibration:
        d = np.asarray(distortion, dtype=np.float64).ravel()
        model = next((m for m, n in DISTORTION_MODELS.items() if n == len(d)), "")
        return cls(
            intrinsics.width,
            intrinsics.height,
            intrinsics.matrix,
            d,
            model,
            camera_name,
            tag_family,
            tag_size_m,
        )

    @property
    def intrinsics(self) -> CameraIntrinsics:
        """The pinhole part (what `WalkerCalibration.tag_intrinsics` holds)."""
        k = self.camera_matrix
        return CameraIntrinsics(
            self.width, self.height, float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])
        )

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.distortion != 0.0))

    def to_dict(self) -> dict[str, Any]:
        """The file's content as plain Python values (strict JSON too: all finite)."""
        k = self.camera_matrix
        p = np.hstack([k, np.zeros((3, 1))])
        d: dict[str, Any] = {
            "image_width": int(self.width),
            "image_height": int(self.height),
            "camera_name": self.camera_name,
            "camera_matrix": _matrix_dict(k),
            "distortion_model": self.distortion_model,
            "distortion_coefficients": _matrix_dict(self.distortion.reshape(1, -1)),
            "rectification_matrix": _matrix_dict(np.eye(3)),
            "projection_matrix": _matrix_dict(p),
        }
        if self.tag_family is not None:
            d["tag_family"] = self.tag_family
        if self.tag_size_m is not None:
            d["tag_size_m"] = float(self.tag_size_m)
        return d

    def to_yaml(self, comment: str = "") -> str:
        """The YAML text (floats in Python's shortest round-trip form: reads back exactly)."""
        lines = [f"# {c}" for c in comment.splitlines()] if comment else []
        for key, value in self.to_dict().items():
            if isinstance(value, dict):
                data = ", ".join(_num(x) for x in value["data"])
                lines += [
                    f"{key}:",
                    f"  rows: {value['rows']}",
                    f"  cols: {value['cols']}",
                    f"  data: [{data}]",
                ]
            elif isinstance(value, str):
                lines.append(f"{key}: {_yaml_str(value)}")
            else:
                lines.append(f"{key}: {_num(value)}")
        return "\n".join(lines) + "\n"

    def save(self, path: str | os.PathLike[str], comment: str = "") -> Path:
        """Write the YAML file (`comment` becomes leading # lines); returns the path."""
        out = Path(path)
        try:
            out.write_text(self.to_yaml(comment), encoding="utf-8")
        except OSError as e:
            raise CameraCalibrationError(f"{out}: cannot write ({e.strerror})") from None
        return out


def load_camera_yaml(path: str | os.PathLike[str]) -> CameraCalibration:
    """Read a camera calibration YAML (format in the module docstring)."""
    p = Path(path)

    def fail(what: str) -> CameraCalibrationError:
        return CameraCalibrationError(f"{p}: {what}")

    if not p.exists():
        raise fail("no such file")
    if not p.is_file():
        raise fail("not a file")
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as e:
        raise fail(f"cannot read ({e.strerror})") from None
    except UnicodeDecodeError:
        raise fail("not a text file") from None
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise fail(f"not valid YAML ({_yaml_problem(e)})") from None
    if not isinstance(doc, dict):
        raise fail("not a camera calibration (expected a YAML mapping of keys)")
    missing = [k for k in _REQUIRED_KEYS if k not in doc]
    if missing:
        raise fail(f"missing key{'s' if len(missing) > 1 else ''} {', '.join(missing)}")
    width = _positive_int(doc["image_width"], "image_width", fail)
    height = _positive_int(doc["image_height"], "image_height", fail)
    k = _read_matrix(doc["camera_matrix"], "camera_matrix", fail, shape=(3, 3))
    model = doc["distortion_model"]
    if model not in DISTORTION_MODELS:
        valid = ", ".join(DISTORTION_MODELS)
        raise fail(f"unsupported distortion_model {model!r} (supported: {valid})")
    d = _read_matrix(
        doc["distortion_coefficients"],
        "distortion_coefficients",
        fail,
        shape=(1, DISTORTION_MODELS[model]),
    )
    name = doc.get("camera_name", "camera")
    if not isinstance(name, str):
        name = str(name)
    family = doc.get("tag_family")
    size = doc.get("tag_size_m")
    if size is not None and (isinstance(size, bool) or not isinstance(size, int | float)):
        raise fail(f"tag_size_m must be a number, got {size!r}")
    problem = _camera_problem(width, height, k, model, d.ravel(), family, size)
    if problem:
        raise fail(problem)
    return CameraCalibration(
        width, height, k, d.ravel(), model, name, family, None if size is None else float(size)
    )


def tag_intrinsics(camera: CameraCalibration | str | os.PathLike[str]) -> CameraIntrinsics:
    """The `CameraIntrinsics` for `WalkerCalibration.tag_intrinsics` from a camera
    calibration (or the path of its YAML file). The distortion is not part of it: the tag
    camera source undistorts the corners it reports (see `hardware.tags`)."""
    if not isinstance(camera, CameraCalibration):
        camera = load_camera_yaml(camera)
    return camera.intrinsics


def with_tag_camera(calibration: WalkerCalibration, camera: CameraCalibration) -> WalkerCalibration:
    """The walker calibration with the tag camera's intrinsics, and its tag family and
    size where the camera file gives them."""
    kw: dict[str, Any] = {"tag_intrinsics": camera.intrinsics}
    if camera.tag_family is not None:
        kw["tag_family"] = camera.tag_family
    if camera.tag_size_m is not None:
        kw["tag_size_m"] = camera.tag_size_m
    return replace(calibration, **kw)


# -- checkerboard calibration -----------------------------------------------------------


@dataclass(frozen=True, eq=False)
class CheckerboardCalibration:
    """Result of `calibrate_camera`.

    camera: the calibrated intrinsics and distortion; rms_px: RMS reprojection error over
    all corners of the used images; per_image_rms_px: the same per used image; used /
    rejected: the names of the images the board was found in / not found in.
    """

    camera: CameraCalibration
    rms_px: float
    board: tuple[int, int]
    square_m: float
    used: tuple[str, ...]
    rejected: tuple[str, ...]
    per_image_rms_px: tuple[float, ...]

    @property
    def image_size(self) -> tuple[int, int]:
        return (self.camera.width, self.camera.height)

    def summary_lines(self) -> list[str]:
        """What `walkerslam calibrate-camera` prints: the numbers a user checks."""
        k, d = self.camera.camera_matrix, self.camera.distortion
        total = len(self.used) + len(self.rejected)
        worst = int(np.argmax(self.per_image_rms_px))
        lines = [
            f"board {self.board[0]}x{self.board[1]} inner corners, square {self.square_m:g} m, "
            f"images {self.camera.width}x{self.camera.height}",
            f"images used: {len(self.used)} of {total}",
        ]
        if self.rejected:
            lines.append(f"rejected (board not found): {', '.join(self.rejected)}")
        lines += [
            f"RMS reprojection error: {self.rms_px:.3f} px "
            f"(worst {self.per_image_rms_px[worst]:.3f} px: {self.used[worst]})",
            f"fx {k[0, 0]:.2f}  fy {k[1, 1]:.2f}  cx {k[0, 2]:.2f}  cy {k[1, 2]:.2f} px",
            f"distortion ({self.camera.distortion_model}): " + " ".join(f"{x:.5g}" for x in d),
        ]
        return lines

    def save(
        self,
        path: str | os.PathLike[str],
        *,
        camera_name: str | None = None,
        tag_family: str | None = None,
        tag_size_m: float | None = None,
    ) -> Path:
        """Write the camera calibration YAML, with the calibration's numbers as a comment."""
        cam = replace(
            self.camera,
            camera_name=camera_name or self.camera.camera_name,
            tag_family=tag_family,
            tag_size_m=tag_size_m,
        )
        comment = (
            f"checkerboard calibration: {self.board[0]}x{self.board[1]} inner corners, "
            f"square {self.square_m:g} m, {len(self.used)} images, "
            f"RMS reprojection error {self.rms_px:.4f} px"
        )
        return cam.save(path, comment)


def calibrate_camera(
    images: Sequence[str | os.PathLike[str] | np.ndarray],
    board: tuple[int, int],
    square_m: float,
    *,
    names: Sequence[str] | None = None,
    min_images: int = 5,
    fix_k3: bool = True,
    camera_name: str = "camera",
) -> CheckerboardCalibration:
    """Calibrate a camera from photos of a checkerboard.

    images: file paths or images (grey or BGR uint8), all the same size; board: inner
    corners (cols, rows), e.g. (9, 6) for a board of 10×7 squares; square_m: side of a
    square. names: how to call the images in the result (default: the paths, or
    "image N"). Images where the board is not found are rejected and listed; fewer than
    `min_images` usable images, images of different sizes or an unreadable file raise
    `CameraCalibrationError`. fix_k3 keeps k3 = 0 (ROS camera_calibration's default: k3
    over-fits unless the board reaches the image corners).
    """
    cols, rows = _check_board(board, square_m, min_images)
    images = list(images)
    names = _image_names(images, names)
    size, used, rejected, img_points = _board_corners(images, names, (cols, rows))
    if len(used) < min_images:
        raise CameraCalibrationError(
            f"the board ({cols}x{rows} inner corners) was found in {len(used)} of "
            f"{len(images)} images; at least {min_images} are needed"
        )
    obj = np.zeros((rows * cols, 3), np.float32)
    obj[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_m
    cal_flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    rms, k, d, _, _, _, _, per_view = cv2.calibrateCameraExtended(
        [obj] * len(used), img_points, size, None, None, flags=cal_flags
    )
    camera = CameraCalibration(
        size[0], size[1], k, np.asarray(d).ravel()[:5], "plumb_bob", camera_name
    )
    return CheckerboardCalibration(
        camera,
        float(rms),
        (cols, rows),
        float(square_m),
        tuple(used),
        tuple(rejected),
        tuple(float(e) for e in np.asarray(per_view).ravel()),
    )


def _check_board(board: tuple[int, int], square_m: float, min_images: int) -> tuple[int, int]:
    """The board's inner corners (cols, rows) as integers, after checking the board, the
    square size and min_images."""
    cols, rows = (int(board[0]), int(board[1]))
    if cols < 2 or rows < 2:
        raise CameraCalibrationError(f"board must be at least 2x2 inner corners, got {board}")
    if not (math.isfinite(square_m) and square_m > 0):
        raise CameraCalibrationError(f"square size must be > 0 m, got {square_m}")
    if min_images < 1:
        raise CameraCalibrationError(f"min_images must be >= 1, got {min_images}")
    return cols, rows


def _image_names(
    images: list[str | os.PathLike[str] | np.ndarray], names: Sequence[str] | None
) -> Sequence[str]:
    """The images' names: `names` (one per image) or the paths, "image N" for arrays;
    raises when the counts differ or there are no images."""
    if names is None:
        names = [
            str(im) if not isinstance(im, np.ndarray) else f"image {i}"
            for i, im in enumerate(images)
        ]
    elif len(names) != len(images):
        raise CameraCalibrationError(f"{len(names)} names for {len(images)} images")
    if not images:
        raise CameraCalibrationError("no images given")
    return names


def _board_corners(
    images: list[str | os.PathLike[str] | np.ndarray],
    names: Sequence[str],
    board: tuple[int, int],
) -> tuple[tuple[int, int], list[str], list[str], list[np.ndarray]]:
    """(image size, names of the images the board was found in, of those it was not
    found in, the found images' refined corners); raises when the sizes differ."""
    size: tuple[int, int] | None = None
    first = ""
    used, rejected, img_points = [], [], []
    for name, im in zip(names, images, strict=True):
        grey = _grey(im, name)
        hw = (grey.shape[1], grey.shape[0])
        if size is None:
            size, first = hw, name
        elif hw != size:
            raise CameraCalibrationError(
                f"{name}: image is {hw[0]}x{hw[1]} but {first} is {size[0]}x{size[1]} "
                "(all images must have the same size)"
            )
        corners = _find_corners(grey, board)
        if corners is None:
            rejected.append(name)
            continue
        used.append(name)
        img_points.append(corners)
    assert size is not None
    return size, used, rejected, img_points


def _find_corners(grey: np.ndarray, board: tuple[int, int]) -> np.ndarray | None:
    """The board's inner corners in a grey image, refined to sub-pixel accuracy with a
    window of about a quarter of their spacing (float32); None if it is not found."""
    cols, rows = board
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(grey, (cols, rows), flags=flags)
    if not found:
        return None
    spacing = _corner_spacing(corners.reshape(rows, cols, 2))
    win = int(np.clip(spacing / 4.0, 2, 11))
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    corners = cv2.cornerSubPix(grey, corners, (win, win), (-1, -1), criteria)
    return corners.astype(np.float32)


# -- helpers ----------------------------------------------------------------------------


def _camera_problem(
    width: Any,
    height: Any,
    k: np.ndarray,
    model: str,
    d: np.ndarray,
    family: Any,
    size: Any,
) -> str:
    """What is wrong with a camera calibration ('' when nothing)."""
    if not (isinstance(width, int | np.integer) and width > 0):
        return f"image_width must be a positive integer, got {width!r}"
    if not (isinstance(height, int | np.integer) and height > 0):
        return f"image_height must be a positive integer, got {height!r}"
    if k.shape != (3, 3):
        return f"camera_matrix must be 3x3, got {'x'.join(map(str, k.shape))}"
    if not np.all(np.isfinite(k)):
        return "camera_matrix has non-finite entries"
    if not (k[0, 0] > 0 and k[1, 1] > 0):
        return f"camera_matrix must have fx, fy > 0, got {k[0, 0]:g}, {k[1, 1]:g}"
    if k[0, 1] != 0.0:
        return f"camera_matrix has skew {k[0, 1]:g} (only zero skew is supported)"
    if k[1, 0] != 0.0 or tuple(k[2]) != (0.0, 0.0, 1.0):
        return "camera_matrix must have the form [fx 0 cx; 0 fy cy; 0 0 1]"
    if model not in DISTORTION_MODELS:
        valid = ", ".join(DISTORTION_MODELS)
        return f"unsupported distortion_model {model!r} (supported: {valid})"
    if len(d) != DISTORTION_MODELS[model]:
        return f"distortion_model {model} has {DISTORTION_MODELS[model]} coefficients, got {len(d)}"
    if not np.all(np.isfinite(d)):
        return "distortion_coefficients has non-finite entries"
    if family is not None and family not in TAG_FAMILIES:
        return f"unknown tag_family {family!r} (valid: {', '.join(TAG_FAMILIES)})"
    if size is not None and not (math.isfinite(size) and size > 0):
        return f"tag_size_m must be > 0, got {size!r}"
    return ""


def _read_matrix(value: Any, key: str, fail, shape: tuple[int, int]) -> np.ndarray:
    if not isinstance(value, dict) or not {"rows", "cols", "data"} <= set(value):
        raise fail(f"{key} must be a mapping with rows, cols and data")
    r, c, data = value["rows"], value["cols"], value["data"]
    if not isinstance(data, list):
        raise fail(f"{key}.data must be a list of numbers")
    if (r, c) != shape:
        raise fail(f"{key} must be {shape[0]}x{shape[1]}, got {r}x{c}")
    if len(data) != r * c:
        raise fail(f"{key} is {r}x{c} but data has {len(data)} numbers")
    numbers = [_number(x) for x in data]
    if any(x is None for x in numbers):
        raise fail(f"{key}.data must contain only numbers")
    return np.array(numbers, dtype=np.float64).reshape(shape)


_FLOAT = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?")


def _number(x: Any) -> float | None:
    """A YAML number, or a plain string that is one (PyYAML reads "1e-05", which YAML
    1.1 has no float for and other writers produce, as a string)."""
    if isinstance(x, bool):
        return None
    if isinstance(x, int | float):
        return float(x)
    if isinstance(x, str) and _FLOAT.fullmatch(x.strip()):
        return float(x)
    return None


def _positive_int(value: Any, key: str, fail) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise fail(f"{key} must be a positive integer, got {value!r}")
    return value


def _yaml_problem(e: yaml.YAMLError) -> str:
    problem = getattr(e, "problem", None) or str(e).splitlines()[0]
    mark = getattr(e, "problem_mark", None)
    return f"{problem} at line {mark.line + 1}" if mark is not None else problem


def _matrix_dict(m: np.ndarray) -> dict[str, Any]:
    return {"rows": int(m.shape[0]), "cols": int(m.shape[1]), "data": [float(x) for x in m.ravel()]}


def _num(x: float | int) -> str:
    """A number as YAML 1.1 (PyYAML) reads back exactly: its floats need a dot in the
    mantissa ("1e-05" would be a string), so that is written "1.0e-05"."""
    if isinstance(x, int):
        return str(x)
    r = repr(float(x))
    if "e" in r and "." not in r:
        mantissa, exponent = r.split("e")
        r = f"{mantissa}.0e{exponent}"
    return r


def _yaml_str(s: str) -> str:
    """A YAML scalar that reads back as the string s."""
    plain = "\n" not in s and "#" not in s and ": " not in s
    return s if plain and yaml.safe_load(s) == s else json.dumps(s)


def _grey(im: str | os.PathLike[str] | np.ndarray, name: str) -> np.ndarray:
    if isinstance(im, np.ndarray):
        try:
            return to_grey(im, name)
        except ValueError as e:
            raise CameraCalibrationError(str(e)) from None
    p = Path(im)
    if not p.is_file():
        raise CameraCalibrationError(f"{name}: no such file")
    grey = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
    if grey is None:
        raise CameraCalibrationError(f"{name}: not an image OpenCV can read")
    return grey


def to_grey(image: np.ndarray, name: str = "image") -> np.ndarray:
    """A grey uint8 image from a grey (H×W or H×W×1), BGR or BGRA uint8 image."""
    if image.dtype != np.uint8:
        raise ValueError(f"{name}: expected a uint8 image, got {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 2:
        return np.ascontiguousarray(image)
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    raise ValueError(f"{name}: expected a grey, BGR or BGRA image, got shape {image.shape}")


def _corner_spacing(grid: np.ndarray) -> float:
    """Smallest distance between neighbouring corners of a rows×cols×2 grid [px]."""
    dx = np.linalg.norm(np.diff(grid, axis=1), axis=2)
    dy = np.linalg.norm(np.diff(grid, axis=0), axis=2)
    return float(min(dx.min(), dy.min()))
