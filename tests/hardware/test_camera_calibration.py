"""Checkerboard camera calibration (hardware/camera_calibration.py): checkerboard images
rendered with a known camera (pinhole + mild lens distortion) at known poses give the
camera back; bad input gives one-line errors."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from hardware.camera_calibration import (
    CameraCalibration,
    CameraCalibrationError,
    calibrate_camera,
    load_camera_yaml,
)
from hardware.frames import make_transform, rot_rpy

TRUE = CameraCalibration(
    640,
    480,
    np.array([[525.3, 0.0, 318.6], [0.0, 523.9, 243.2], [0.0, 0.0, 1.0]]),
    np.array([-0.21, 0.07, 0.0008, -0.0006, 0.0]),
    camera_name="truth",
)
BOARD = (9, 6)  # inner corners: 10 × 7 squares
SQUARE = 0.025


def normalized_subpixels(cam: CameraCalibration, ss: int) -> np.ndarray:
    """(H·ss, W·ss, 2) undistorted normalized image coordinates of each sub-pixel sample
    (OpenCV pixel convention: integer coordinates are pixel centres)."""
    off = (np.arange(ss) + 0.5) / ss - 0.5
    u = (np.arange(cam.width)[:, None] + off).ravel()
    v = (np.arange(cam.height)[:, None] + off).ravel()
    uu, vv = np.meshgrid(u, v)
    pts = np.stack([uu, vv], axis=-1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    xy = cv2.undistortPoints(pts, cam.camera_matrix, cam.distortion, criteria=crit)
    return xy.reshape((*uu.shape, 2))


def render_board(
    camera_T_board: np.ndarray, xy: np.ndarray, rng: np.random.Generator, ss: int = 3
) -> np.ndarray:
    """Grey image of the checkerboard (origin at its first inner corner, x along the
    columns, y along the rows) in a one-square white margin on a grey wall."""
    r, t = camera_T_board[:3, :3], camera_T_board[:3, 3]
    d = np.concatenate([xy, np.ones((*xy.shape[:2], 1))], axis=-1)
    n = r[:, 2]
    s = (n @ t) / (d @ n)
    q = (s[..., None] * d - t) @ r  # board coordinates of each ray's hit
    x, y = q[..., 0] / SQUARE, q[..., 1] / SQUARE
    cols, rows = BOARD
    img = np.full(s.shape, 110.0)
    margin = (x >= -2) & (x <= cols + 1) & (y >= -2) & (y <= rows + 1) & (s > 0)
    img[margin] = 235.0
    board = (x >= -1) & (x <= cols) & (y >= -1) & (y <= rows) & (s > 0)
    black = board & ((np.floor(x) + np.floor(y)) % 2 == 0)
    img[black] = 25.0
    h, w = img.shape[0] // ss, img.shape[1] // ss
    img = img.reshape(h, ss, w, ss).mean(axis=(1, 3))
    img = cv2.GaussianBlur(img, (0, 0), 0.6) + rng.normal(0.0, 1.5, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def board_poses(n: int, rng: np.random.Generator) -> list[np.ndarray]:
    """Views spread over the image, tilted up to ~35°, at 0.3-0.5 m."""
    cols, rows = BOARD
    centre = np.array([(cols - 1) / 2 * SQUARE, (rows - 1) / 2 * SQUARE, 0.0])
    out = []
    for i in range(n):
        roll, pitch = rng.uniform(-0.6, 0.6, 2)
        yaw = rng.uniform(-0.4, 0.4) + (math.pi if i % 4 == 3 else 0.0)
        r = rot_rpy(roll, pitch, yaw)
        z = rng.uniform(0.3, 0.5)
        c = np.array([rng.uniform(-0.25, 0.25) * z, rng.uniform(-0.18, 0.18) * z, z])
        out.append(make_transform(r, c - r @ centre))
    return out


@pytest.fixture(scope="module")
def views() -> tuple[list[np.ndarray], list[np.ndarray]]:
    rng = np.random.default_rng(7)
    xy = normalized_subpixels(TRUE, 3)
    poses = board_poses(14, rng)
    return [render_board(p, xy, rng) for p in poses], poses


def test_recovers_a_known_camera(views, tmp_path: Path) -> None:
    images, _ = views
    blank = np.full((480, 640), 120, np.uint8)
    result = calibrate_camera([*images, blank], BOARD, SQUARE, names=[*map(str, range(14)), "wall"])
    k, k_true = result.camera.camera_matrix, TRUE.camera_matrix
    # measured: fx, fy within 0.05 %, cx, cy within 0.13 px, RMS 0.06 px
    assert abs(k[0, 0] / k_true[0, 0] - 1) < 0.002
    assert abs(k[1, 1] / k_true[1, 1] - 1) < 0.002
    assert abs(k[0, 2] - k_true[0, 2]) < 0.5 and abs(k[1, 2] - k_true[1, 2]) < 0.5
    np.testing.assert_allclose(result.camera.distortion[:2], TRUE.distortion[:2], atol=0.01)
    np.testing.assert_allclose(result.camera.distortion[2:4], TRUE.distortion[2:4], atol=0.001)
    assert result.camera.distortion[4] == 0.0  # k3 fixed by default
    assert result.rms_px < 0.5
    assert len(result.per_image_rms_px) == 14 and max(result.per_image_rms_px) < 0.5
    assert result.used == tuple(map(str, range(14))) and result.rejected == ("wall",)
    assert result.image_size == (640, 480)
    lines = result.summary_lines()
    assert "images used: 14 of 15" in lines[1]
    assert any(line == "rejected (board not found): wall" for line in lines)
    assert any(line.startswith("RMS reprojection error: ") for line in lines)
    assert all("\n" not in line for line in lines)
    # the YAML the CLI writes reads back as the same camera
    path = result.save(tmp_path / "camera.yaml", camera_name="tag_camera", tag_size_m=0.165)
    back = load_camera_yaml(path)
    np.testing.assert_array_equal(back.camera_matrix, result.camera.camera_matrix)
    np.testing.assert_array_equal(back.distortion, result.camera.distortion)
    assert (back.camera_name, back.tag_size_m, back.tag_family) == ("tag_camera", 0.165, None)
    assert path.read_text().startswith("# checkerboard calibration: 9x6 inner corners")


def test_the_recovered_lens_model_matches_the_true_one_over_the_image(views) -> None:
    """What the calibration is for: every pixel of the image, undistorted with the
    recovered camera, lands where the true camera puts it (in the true pinhole image)."""
    images, _ = views
    cam = calibrate_camera(images, BOARD, SQUARE).camera
    u, v = np.meshgrid(np.linspace(0, 639, 33), np.linspace(0, 479, 25))
    pts = np.stack([u.ravel(), v.ravel()], axis=-1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    k = TRUE.camera_matrix
    got = cv2.undistortPoints(pts, cam.camera_matrix, cam.distortion, P=k, criteria=crit)
    want = cv2.undistortPoints(pts, k, TRUE.distortion, P=k, criteria=crit)
    err = np.linalg.norm((got - want).reshape(-1, 2), axis=1)
    # measured: max 0.32 px (the image corners, beyond the boards), median 0.15 px
    assert err.max() < 0.5 and np.median(err) < 0.25
    # the distortion matters: ignoring it is off by pixels near the image edges
    plain = cv2.undistortPoints(pts, k, np.zeros(5), P=k).reshape(-1, 2)
    assert np.linalg.norm(plain - want.reshape(-1, 2), axis=1).max() > 10.0


def test_reads_image_files(views, tmp_path: Path) -> None:
    images, _ = views
    paths = []
    for i, img in enumerate(images[:6]):
        paths.append(tmp_path / f"view_{i}.png")
        cv2.imwrite(str(paths[-1]), cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    result = calibrate_camera(paths, BOARD, SQUARE)
    assert result.used == tuple(str(p) for p in paths)
    assert abs(result.camera.camera_matrix[0, 0] / TRUE.camera_matrix[0, 0] - 1) < 0.01


def one_line(fn, match: str) -> None:
    with pytest.raises(CameraCalibrationError) as e:
        fn()
    msg = str(e.value)
    assert isinstance(e.value, ValueError) and "\n" not in msg and match in msg, msg


def test_errors_are_one_line(views, tmp_path: Path) -> None:
    images, _ = views
    blank = np.full((480, 640), 120, np.uint8)
    one_line(
        lambda: calibrate_camera([*images[:3], blank, blank], BOARD, SQUARE),
        "found in 3 of 5 images; at least 5 are needed",
    )
    small = cv2.resize(images[4], (320, 240))
    one_line(
        lambda: calibrate_camera([*images[:4], small], BOARD, SQUARE),
        "image 4: image is 320x240 but image 0 is 640x480",
    )
    one_line(lambda: calibrate_camera([tmp_path / "none.png"], BOARD, SQUARE), "no such file")
    (tmp_path / "x.png").write_text("not an image")
    one_line(lambda: calibrate_camera([tmp_path / "x.png"], BOARD, SQUARE), "not an image")
    one_line(lambda: calibrate_camera(images[:5], (1, 6), SQUARE), "at least 2x2")
    one_line(lambda: calibrate_camera(images[:5], BOARD, 0.0), "square size")
    one_line(lambda: calibrate_camera([], BOARD, SQUARE), "no images")
    one_line(lambda: calibrate_camera([images[0].astype(float)], BOARD, SQUARE), "uint8")


def test_the_cli_command_calibrates_from_a_folder_and_writes_the_yaml(views, tmp_path: Path):
    import subprocess
    import sys

    from tests.experiments.test_cli import walkerslam

    images, _ = views
    folder = tmp_path / "photos"
    folder.mkdir()
    for i, img in enumerate(images):
        cv2.imwrite(str(folder / f"view_{i:02d}.png"), img)
    cv2.imwrite(str(folder / "wall.png"), np.full((480, 640), 120, np.uint8))
    out = tmp_path / "camera.yaml"
    cmd = [str(Path(sys.executable).parent / "walkerslam"), "calibrate-camera", str(folder)]
    args = ["--board", "9x6", "--square", "0.025", "-o", str(out), "--tag-size", "0.165"]
    r = subprocess.run([*cmd, *args], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "images used: 14 of 15" in r.stdout and "wall.png" in r.stdout
    rms = float(r.stdout.split("RMS reprojection error: ")[1].split()[0])
    assert rms < 0.5 and f"wrote {out}" in r.stdout
    cam = load_camera_yaml(out)
    assert abs(cam.camera_matrix[0, 0] / TRUE.camera_matrix[0, 0] - 1) < 0.002
    assert cam.tag_size_m == 0.165
    # bad input: one line naming what is wrong, exit code 2 (run in this process: the
    # installed script was run above)
    for bad, what in [
        (["--board", "9by6"], "COLSxROWS"),
        (["--board", "7x5"], "images"),
        (["--square", "-1"], "square"),
    ]:
        r = walkerslam(*cmd[1:], *bad, "-o", tmp_path / "x.yaml")
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and what in lines[0], r.stderr
    r = walkerslam("calibrate-camera", tmp_path / "none")
    assert r.returncode == 2 and "no such image" in r.stderr
