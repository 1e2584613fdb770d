"""Rotations and rigid/similarity transforms (numpy only).

Rotation matrices are (3, 3) float arrays; ``R_a2b @ p_a = p_b``.
Homogeneous transforms are (4, 4).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "check_rotation",
    "euler_zyx_fixed_deg",
    "make_transform",
    "marker_corners_local",
    "matrix_to_rotvec",
    "rot_x",
    "rot_y",
    "rot_z",
    "rotvec_to_matrix",
    "wrap_angle",
    "yaw_of",
]


def rot_x(a: float) -> np.ndarray:
    """Rotation about x by ``a`` radians, shape (3, 3)."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    """Rotation about y by ``a`` radians, shape (3, 3)."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    """Rotation about z by ``a`` radians, shape (3, 3)."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def euler_zyx_fixed_deg(rx_deg: float, ry_deg: float, rz_deg: float) -> np.ndarray:
    """RobotAtFactory rule: fixed-frame rotations, first about Z, then Y, then X.

    Returns ``R = Rx(rx) @ Ry(ry) @ Rz(rz)`` (marker2world), angles given in degrees.
    """
    return rot_x(math.radians(rx_deg)) @ rot_y(math.radians(ry_deg)) @ rot_z(math.radians(rz_deg))


def check_rotation(R: np.ndarray, tol: float = 1e-6, name: str = "R") -> np.ndarray:
    """Validate a rotation matrix: shape (3, 3), finite, orthonormal, det +1.

    Returns it as a float array; raises ``ValueError`` naming ``name`` otherwise.
    """
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3):
        raise ValueError(f"{name}: expected shape (3, 3), got {R.shape}")
    if not np.all(np.isfinite(R)):
        raise ValueError(f"{name}: non-finite entries")
    if np.abs(R @ R.T - np.eye(3)).max() > tol or abs(np.linalg.det(R) - 1.0) > tol:
        raise ValueError(f"{name}: not a proper rotation (orthonormal, det +1)")
    return R


def rotvec_to_matrix(rvec: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vector (3,) in radians -> rotation matrix (3, 3)."""
    r = np.asarray(rvec, dtype=float).reshape(3)
    theta = float(np.linalg.norm(r))
    if theta < 1e-12:
        return np.eye(3)
    k = r / theta
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(theta) * K + (1.0 - math.cos(theta)) * (K @ K)


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rotvec_to_matrix`; returns (3,) radians."""
    R = np.asarray(R, dtype=float)
    c = max(-1.0, min(1.0, (np.trace(R) - 1.0) / 2.0))
    theta = math.acos(c)
    if theta < 1e-12:
        return np.zeros(3)
    if math.pi - theta < 1e-6:
        # Near pi the antisymmetric part vanishes: take the axis from R + I.
        M = (R + np.eye(3)) / 2.0
        i = int(np.argmax(np.diag(M)))
        axis = M[:, i] / math.sqrt(max(M[i, i], 1e-300))
        return axis / np.linalg.norm(axis) * theta
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return w / (2.0 * math.sin(theta)) * theta


def wrap_angle(a: float | np.ndarray) -> float | np.ndarray:
    """Wrap radians to [-pi, pi)."""
    return (np.asarray(a) + math.pi) % (2.0 * math.pi) - math.pi if isinstance(a, np.ndarray) else (
        (a + math.pi) % (2.0 * math.pi) - math.pi
    )


def yaw_of(R_marker2world: np.ndarray) -> float:
    """Yaw (radians, CCW about world z) of a marker: the heading of its x axis on the floor."""
    return math.atan2(R_marker2world[1, 0], R_marker2world[0, 0])


def make_transform(R: np.ndarray, t: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """(4, 4) homogeneous similarity ``p' = scale * R @ p + t``."""
    T = np.eye(4)
    T[:3, :3] = scale * np.asarray(R, dtype=float)
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def marker_corners_local(length: float) -> np.ndarray:
    """Corners of a square marker of side ``length`` (m) in its own frame, shape (4, 3).

    OpenCV ArUco order (the order ``detectMarkers`` returns and ``SOLVEPNP_IPPE_SQUARE``
    expects): top-left, top-right, bottom-right, bottom-left, i.e.
    (-l/2, l/2), (l/2, l/2), (l/2, -l/2), (-l/2, -l/2), z = 0.
    """
    h = length / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
