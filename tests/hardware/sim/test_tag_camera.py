"""Simulated AprilTag camera: visibility rules, pose noise, and the pupil-apriltags
convention (checked by running the real detector on a rendered tag36h11 marker)."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from hardware.calibration import WalkerCalibration
from hardware.frames import invert_transform, planar_pose_to_transform
from hardware.sim.tag_camera import SimTagCamera, TagCameraConfig, tag_object_points
from hardware.sim.world import Box, Obstacle, TagPose, World
from hardware.tags import release_pupil_detector

CAL = WalkerCalibration()
TAG_SIZE = CAL.tag_size_m
DATA = Path(__file__).resolve().parents[3] / ".." / "shared" / "data" / "apriltag_images"


def world_with_tag(*extra: Obstacle, tag_yaw: float = math.pi) -> World:
    """A wall whose face is the plane x = 3 and a tag on it at (3, 0.2, 0.35)."""
    wall = Obstacle("wall", "wall", (Box(3.05, 0.0, 0.0, 0.1, 10.0, 0.0, 2.4),))
    tag = TagPose(0, 3.0, 0.2, 0.35, tag_yaw)
    return World("tag-test", (-5, 5, -5, 5), (wall, *extra), (tag,), np.zeros((2, 2)), (0, 0, 0))


def pose_viewing(
    distance: float, incidence_deg: float, bearing_deg: float = 0.0
) -> tuple[float, float, float]:
    """Walker pose whose tag camera is `distance` (horizontally) from the tag, on a line at
    `incidence_deg` from the tag normal, with the tag `bearing_deg` left of the optical axis."""
    a = math.radians(incidence_deg)
    cam = np.array([3.0 - distance * math.cos(a), 0.2 + distance * math.sin(a)])
    th = math.atan2(0.2 - cam[1], 3.0 - cam[0]) - math.radians(bearing_deg)
    m = CAL.tag_mount
    c, s = math.cos(th), math.sin(th)
    return (cam[0] - c * m.x + s * m.y, cam[1] - s * m.x - c * m.y, th)


def sim_camera(w: World, seed: int = 0, **cfg) -> SimTagCamera:
    return SimTagCamera(w, CAL, TagCameraConfig(**cfg), np.random.default_rng(seed))


def true_camera_T_tag(w: World, pose: tuple[float, float, float]) -> np.ndarray:
    world_T_cam = planar_pose_to_transform(*pose) @ CAL.tag_mount.walker_T_optical()
    return invert_transform(world_T_cam) @ w.world_T_tag(w.tags[0])


def rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = (np.trace(a.T @ b) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


def test_noise_free_detection_is_exact() -> None:
    w = world_with_tag()
    pose = pose_viewing(1.5, 20.0, 5.0)
    (det,) = sim_camera(w, pixel_noise_px=0.0).detect(pose)
    truth = true_camera_T_tag(w, pose)
    assert det.tag_id == 0
    np.testing.assert_allclose(det.camera_T_tag, truth, atol=1e-6)
    # Corners are the projections of the tag's object points, in pupil-apriltags order.
    k = CAL.tag_intrinsics.matrix
    p = (tag_object_points(TAG_SIZE) @ truth[:3, :3].T + truth[:3, 3]) @ k.T
    np.testing.assert_allclose(det.corners_px, p[:, :2] / p[:, 2:], atol=1e-9)


def test_pose_error_at_1_5_m_with_default_noise() -> None:
    w = world_with_tag()
    pose = pose_viewing(1.5, 20.0)
    cam = sim_camera(w, seed=42)
    truth = true_camera_T_tag(w, pose)
    assert np.linalg.norm(truth[:3, 3]) == pytest.approx(1.5, abs=0.01)  # 0.145 m below the camera
    errors, corner_noise = [], []
    true_corners = sim_camera(w, pixel_noise_px=0.0).visible(pose)[0].corners_px
    for _ in range(200):
        (det,) = cam.detect(pose)
        errors.append(np.linalg.norm(det.camera_T_tag[:3, 3] - truth[:3, 3]))
        corner_noise.append(det.corners_px - true_corners)
    errors = np.array(errors)
    # σ = 0.5 px on the corners of a ~60 px tag: about 1 cm of error, mostly in range.
    assert np.sqrt(np.mean(errors**2)) < 0.02
    assert np.median(errors) < 0.012
    assert np.std(corner_noise) == pytest.approx(0.5, rel=0.1)


@pytest.mark.parametrize(
    ("pose", "cfg", "why"),
    [
        (pose_viewing(1.5, 0.0, 40.0), {}, "outside the 62° field of view"),
        (pose_viewing(4.3, 0.0), {}, "beyond 4 m"),
        (pose_viewing(2.0, 65.0), {}, "more oblique than 60°"),
        (pose_viewing(1.5, 0.0), {"min_side_px": 80.0}, "smaller than the minimum side"),
        (pose_viewing(0.25, 0.0), {}, "nearer than 0.3 m"),
    ],
)
def test_not_detected(pose: tuple[float, float, float], cfg: dict, why: str) -> None:
    assert sim_camera(world_with_tag(), **cfg).detect(pose) == (), why


@pytest.mark.parametrize(
    "pose", [pose_viewing(1.5, 0.0, 20.0), pose_viewing(3.9, 0.0), pose_viewing(2.0, 55.0)]
)
def test_detected_just_inside_the_limits(pose: tuple[float, float, float]) -> None:
    assert len(sim_camera(world_with_tag()).detect(pose)) == 1


def test_back_of_a_tag_and_occluded_tags_are_not_detected() -> None:
    pose = pose_viewing(2.0, 10.0)
    assert sim_camera(world_with_tag(tag_yaw=0.0)).detect(pose) == ()  # facing away
    crate = Obstacle("crate", "box", (Box(2.2, 0.2, 0.0, 0.3, 0.3, 0.0, 0.8),))
    w = world_with_tag(crate)
    assert sim_camera(w).detect(pose) == ()
    beside = Obstacle("crate", "box", (Box(2.2, 1.0, 0.0, 0.3, 0.3, 0.0, 0.8),))
    assert len(sim_camera(world_with_tag(beside)).detect(pose)) == 1


# -- the convention of a real detector -------------------------------------------------
def canonical_tag36h11(tag_id: int, cell_px: int) -> np.ndarray:
    """The tag36h11 marker as the AprilTag library draws it: 10×10 cells with the white
    ring. OpenCV's APRILTAG_36h11 dictionary draws the 8×8 black-bordered pattern rotated
    by 180° relative to the AprilTag images (verified by decoding: the detector reports an
    upright OpenCV marker as rotated by 180°), hence the rot90(…, 2)."""
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    inner = np.rot90(cv2.aruco.generateImageMarker(d, tag_id, 8 * cell_px), 2)
    return cv2.copyMakeBorder(
        np.ascontiguousarray(inner), *(4 * [cell_px]), cv2.BORDER_CONSTANT, value=255
    )


def render_tag(camera_T_tag: np.ndarray, tag_id: int) -> np.ndarray:
    """640×480 grey image of the tag at camera_T_tag (tag frame: x right, y down)."""
    k = CAL.tag_intrinsics
    cell = 40
    marker = canonical_tag36h11(tag_id, cell)
    m_per_px = TAG_SIZE / (8 * cell)  # tag size = edge of the black square (8 of 10 cells)
    # Marker pixel centres (col, row) → tag plane (x, y); image centre is the tag centre.
    tag_from_px = np.array(
        [
            [m_per_px, 0, (0.5 - 5 * cell) * m_per_px],
            [0, m_per_px, (0.5 - 5 * cell) * m_per_px],
            [0, 0, 1],
        ]
    )
    r, t = camera_T_tag[:3, :3], camera_T_tag[:3, 3]
    h = k.matrix @ np.column_stack([r[:, 0], r[:, 1], t]) @ tag_from_px
    return cv2.warpPerspective(
        marker,
        h,
        (k.width, k.height),
        flags=cv2.INTER_AREA,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=160,
    )


@pytest.mark.parametrize(
    "pose", [pose_viewing(1.0, 0.0), pose_viewing(1.2, 35.0, 10.0), pose_viewing(0.9, -25.0, -12.0)]
)
def test_matches_pupil_apriltags_convention(pose: tuple[float, float, float]) -> None:
    pupil_apriltags = pytest.importorskip("pupil_apriltags")
    w = world_with_tag()
    (sim,) = sim_camera(w, pixel_noise_px=0.0).detect(pose)
    img = render_tag(sim.camera_T_tag, tag_id=5)
    k = CAL.tag_intrinsics
    detector = pupil_apriltags.Detector(families="tag36h11", quad_decimate=1.0)
    try:
        dets = detector.detect(
            img, estimate_tag_pose=True, camera_params=(k.fx, k.fy, k.cx, k.cy), tag_size=TAG_SIZE
        )
    finally:
        release_pupil_detector(detector)  # pupil's own __del__ corrupts the heap
    assert [d.tag_id for d in dets] == [5]
    real = dets[0]
    # Same corner order (detector corners carry a ~0.5 px offset of its own).
    assert np.abs(real.corners - sim.corners_px).max() < 1.2
    np.testing.assert_allclose(real.pose_t.ravel(), sim.camera_T_tag[:3, 3], atol=0.008)
    assert rotation_deg(real.pose_R, sim.camera_T_tag[:3, :3]) < 3.0


@pytest.mark.data
def test_real_photo_of_an_upright_tag_has_identity_rotation() -> None:
    # Duckietown rotation set, 0°: a printed tag facing the camera squarely and upright.
    # The real detector reports R ≈ I and corner 0 at the bottom left, i.e. the tag frame
    # is x right, y down, z into the tag — the frame `World.world_T_tag` uses.
    pupil_apriltags = pytest.importorskip("pupil_apriltags")
    path = DATA / "duckietown" / "test_image_rotation_0.png"
    if not path.exists():
        pytest.skip(f"real AprilTag images not found at {path}")
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    detector = pupil_apriltags.Detector(families="tag36h11")
    try:
        (det,) = detector.detect(
            img,
            estimate_tag_pose=True,
            camera_params=(329.873, 332.946, 528.0, 396.0),
            tag_size=0.065,
        )
    finally:
        release_pupil_detector(detector)
    assert rotation_deg(det.pose_R, np.eye(3)) < 20.0
    c = det.corners
    assert c[0, 0] < c[1, 0] and c[0, 1] > c[3, 1]  # bottom-left, then bottom-right
    assert det.pose_t[2, 0] == pytest.approx(0.2, abs=0.05)
