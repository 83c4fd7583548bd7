"""Rigid 3-D transforms for sensor mounts (4×4 homogeneous matrices).

Frames: the walker body frame has x forward, y left, z up, origin on the floor below the
rear-axle centre. Camera optical frames have x right, y down, z forward.
"""

from __future__ import annotations

import numpy as np

# Rotation taking optical-frame vectors (x right, y down, z forward) into a body-style
# frame (x forward, y left, z up) that looks the same way.
BODY_R_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def rot_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rotation matrix R = Rz(yaw) Ry(pitch) Rx(roll); positive pitch tilts +x downwards."""
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return rz @ ry @ rx


def make_transform(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = rotation
    t[:3, 3] = translation
    return t


def invert_transform(a_T_b: np.ndarray) -> np.ndarray:
    r = a_T_b[:3, :3]
    b_T_a = np.eye(4)
    b_T_a[:3, :3] = r.T
    b_T_a[:3, 3] = -r.T @ a_T_b[:3, 3]
    return b_T_a


def transform_points(a_T_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Map N×3 points from frame b to frame a."""
    return points_b @ a_T_b[:3, :3].T + a_T_b[:3, 3]


def planar_pose_to_transform(x: float, y: float, theta: float) -> np.ndarray:
    """world_T_walker as a 4×4 matrix from a planar pose."""
    return make_transform(rot_rpy(0.0, 0.0, theta), np.array([x, y, 0.0]))
