"""Homogeneous transforms and the square marker's corner model (numpy only).

A (4, 4) transform ``T_a2b`` maps homogeneous points of frame a to frame b; a similarity
has ``T[:3, :3] = scale * R``. Metres.
"""

from __future__ import annotations

import numpy as np

__all__ = ["check_transform", "invert_transform", "make_transform", "marker_corners_local"]


def make_transform(R: np.ndarray, t: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """(4, 4) homogeneous similarity ``p' = scale * R @ p + t``; R (3, 3), t (3,) m."""
    T = np.eye(4)
    T[:3, :3] = scale * np.asarray(R, dtype=float)
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def check_transform(T: np.ndarray, name: str = "transform", tol: float = 1e-6) -> np.ndarray:
    """A finite (4, 4) rigid transform (rotation block orthonormal with det +1, last row
    0 0 0 1) as floats; ``ValueError`` naming ``name`` otherwise."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"{name}: expected a finite (4, 4) matrix, got shape {T.shape}")
    R = T[:3, :3]
    if (np.abs(R @ R.T - np.eye(3)).max() > tol or abs(np.linalg.det(R) - 1.0) > tol
            or np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > tol):
        raise ValueError(f"{name}: not a rigid transform")
    return T


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse (4, 4) of a rigid transform (R, t) -> (R^T, -R^T t)."""
    T = np.asarray(T, dtype=float)
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def marker_corners_local(length: float) -> np.ndarray:
    """Corners of a square marker of side ``length`` (m) in its own frame, shape (4, 3).

    OpenCV ArUco order (the order ``detectMarkers`` returns and ``SOLVEPNP_IPPE_SQUARE``
    expects): top-left, top-right, bottom-right, bottom-left, i.e.
    (-l/2, l/2), (l/2, l/2), (l/2, -l/2), (-l/2, -l/2), z = 0.
    """
    h = length / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
