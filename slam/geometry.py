"""SE(2) pose algebra on arrays of poses (x, y, θ); θ wrapped to (−π, π]."""

from __future__ import annotations

import numpy as np


def wrap_angle(a: np.ndarray | float) -> np.ndarray | float:
    """Wrap angles to (−π, π]."""
    w = np.pi - np.mod(np.pi - np.asarray(a, dtype=float), 2.0 * np.pi)
    return float(w) if np.ndim(w) == 0 else w


def _as_poses(p: np.ndarray) -> np.ndarray:
    p = np.asarray(p, dtype=float)
    if p.shape[-1] != 3:
        raise ValueError(f"poses must have shape (..., 3) as (x, y, theta), got {p.shape}")
    return p


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a ⊕ b: pose b expressed in frame a, mapped to a's parent frame (broadcasts)."""
    a, b = _as_poses(a), _as_poses(b)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, wrap_angle(a[..., 2] + b[..., 2])], axis=-1)


def inverse(a: np.ndarray) -> np.ndarray:
    a = _as_poses(a)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = -c * a[..., 0] - s * a[..., 1]
    y = s * a[..., 0] - c * a[..., 1]
    return np.stack([x, y, wrap_angle(-a[..., 2])], axis=-1)


def between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a⁻¹ ⊕ b: pose b expressed in frame a."""
    return compose(inverse(a), b)


def transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map N×2 points from the frame of `pose` to its parent frame (rotate, then translate)."""
    pose = _as_poses(pose)
    c, s = np.cos(pose[2]), np.sin(pose[2])
    pts = np.asarray(points, dtype=float)
    return np.column_stack(
        [pose[0] + c * pts[:, 0] - s * pts[:, 1], pose[1] + s * pts[:, 0] + c * pts[:, 1]]
    )


def to_matrix(pose: np.ndarray) -> np.ndarray:
    """3×3 homogeneous matrix of one pose."""
    x, y, th = _as_poses(pose)
    c, s = np.cos(th), np.sin(th)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def from_matrix(m: np.ndarray) -> np.ndarray:
    return np.array([m[0, 2], m[1, 2], np.arctan2(m[1, 0], m[0, 0])])
