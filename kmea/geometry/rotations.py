"""Rotations: elementary rotations, Rodrigues both ways, projection onto SO(3), angles.

Rotation matrices are (3, 3) float arrays acting on column vectors, ``R_a2b @ p_a = p_b``;
batched functions take and return stacks (..., 3, 3). Rotation vectors are (3,) or (N, 3),
radians (axis times angle). Angles are radians unless a name ends in ``_deg``. Numpy only.
"""

from __future__ import annotations

import math
from typing import overload

import numpy as np

__all__ = [
    "check_rotation",
    "check_rotvecs",
    "euler_zyx_fixed_deg",
    "kabsch",
    "matrices_to_rotvecs",
    "project_to_so3",
    "rot_x",
    "rot_y",
    "rot_z",
    "rotvec_to_matrix",
    "rotvecs_to_matrices",
    "skew",
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


def check_rotvecs(rv: np.ndarray, name: str = "rotation vectors") -> np.ndarray:
    """Validate rotation vectors: (3,) or (N, 3), finite. Returns them as (N, 3) floats."""
    a = np.asarray(rv, dtype=float)
    if a.shape != (3,) and (a.ndim != 2 or a.shape[1] != 3):
        raise ValueError(f"{name}: expected shape (3,) or (N, 3), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: non-finite entries")
    return a.reshape(-1, 3)


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices ``[v]x`` of vectors (..., 3) -> (..., 3, 3): ``[v]x @ w = v x w``."""
    v = np.asarray(v, dtype=float)
    z = np.zeros(v.shape[:-1])
    return np.stack([np.stack([z, -v[..., 2], v[..., 1]], -1),
                     np.stack([v[..., 2], z, -v[..., 0]], -1),
                     np.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def rotvecs_to_matrices(rv: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vectors (N, 3), radians -> rotation matrices (N, 3, 3).

    OpenCV's ``cv2.Rodrigues`` formula step for step, with libm's cos/sin (numpy's SIMD ones
    differ in the last bit), so the IPPE replica in :mod:`kmea.vision.ippe` matches OpenCV to
    rounding. A vector shorter than machine epsilon gives the identity.
    """
    rv = np.asarray(rv, dtype=float).reshape(-1, 3)
    theta = np.sqrt((rv * rv).sum(axis=1))
    tl = theta.tolist()
    c = np.array([math.cos(a) for a in tl])
    s = np.array([math.sin(a) for a in tl])
    small = theta < np.finfo(float).eps
    itheta = np.where(small, 0.0, 1.0 / np.where(small, 1.0, theta))
    r = rv * itheta[:, None]
    c1 = 1.0 - c
    rx, ry, rz = r[:, 0], r[:, 1], r[:, 2]
    R = c1[:, None, None] * (r[:, :, None] * r[:, None, :])
    R[:, 0, 0] += c
    R[:, 1, 1] += c
    R[:, 2, 2] += c
    R[:, 0, 1] -= s * rz
    R[:, 0, 2] += s * ry
    R[:, 1, 0] += s * rz
    R[:, 1, 2] -= s * rx
    R[:, 2, 0] -= s * ry
    R[:, 2, 1] += s * rx
    R[small] = np.eye(3)
    return R


def rotvec_to_matrix(rvec: np.ndarray) -> np.ndarray:
    """Rodrigues: one rotation vector (3,), radians -> rotation matrix (3, 3)."""
    return rotvecs_to_matrices(np.asarray(rvec, dtype=float).reshape(1, 3))[0]


def matrices_to_rotvecs(R: np.ndarray) -> np.ndarray:
    """Inverse Rodrigues: rotation matrices (N, 3, 3) -> rotation vectors (N, 3), radians.

    The formula of OpenCV's IPPE (``rot2vec``: angle from the trace, axis from the
    antisymmetric part), with libm's acos/sin, so the IPPE replica matches OpenCV; like it,
    it is ill-conditioned within ~1e-4 rad of a half turn (exact at a half turn only for
    the round trip through :func:`rotvecs_to_matrices`). Angles below float32 epsilon give
    the zero vector.
    """
    R = np.asarray(R, dtype=float).reshape(-1, 3, 3)
    tr = R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2]
    w = np.array([math.acos(a) if -1.0 <= a <= 1.0 else math.nan
                  for a in ((tr - 1.0) / 2.0).tolist()])
    with np.errstate(divide="ignore", invalid="ignore"):
        d = 1.0 / (2.0 * np.array([math.sin(a) for a in w.tolist()])) * w
    c = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]],
                 axis=1)
    rv = d[:, None] * c
    rv[w < np.finfo(np.float32).eps] = 0.0
    return rv


def project_to_so3(M: np.ndarray) -> np.ndarray:
    """Nearest rotations (Frobenius norm) of matrices (..., 3, 3): ``U diag(1, 1, d) V^T``
    from the SVD ``M = U S V^T`` with ``d = sign(det(U V^T))`` (no reflections).

    Used for the chordal mean of rotations (project their sum) and to orthonormalise.
    """
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0.0, 1.0, d)
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    return U @ Vt


def kabsch(H: np.ndarray) -> np.ndarray:
    """Kabsch rotations from cross-covariances H (..., 3, 3) = sum_i src_i dst_i^T (centred
    point sets) -> R (..., 3, 3) minimising sum ||R src_i - dst_i||^2.

    The textbook steps: H = U S V^T, R = V U^T; a reflection (det < 0) flips the last column
    of V, the axis of least spread. Equal to ``project_to_so3(H^T)``.
    """
    U, _, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, -1, -2)
    Ut = np.swapaxes(U, -1, -2)
    d = np.sign(np.linalg.det(V @ Ut))
    d = np.where(d == 0.0, 1.0, d)
    V = V.copy()
    V[..., :, -1] *= d[..., None]
    return V @ Ut


@overload
def wrap_angle(a: float) -> float: ...
@overload
def wrap_angle(a: np.ndarray) -> np.ndarray: ...
def wrap_angle(a: float | np.ndarray) -> float | np.ndarray:
    """The one angle wrap: radians to [-pi, pi); a float for a float, an array for an
    array."""
    if isinstance(a, np.ndarray):
        return (np.asarray(a) + math.pi) % (2.0 * math.pi) - math.pi
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def yaw_of(R_marker2world: np.ndarray) -> np.ndarray | float:
    """Yaw (radians, CCW about world z) of marker2world rotations (3, 3) or (N, 3, 3): the
    heading of the marker's x axis on the floor. A float for one matrix, (N,) for a stack."""
    R = np.asarray(R_marker2world)
    if R.ndim == 2:
        return math.atan2(R[1, 0], R[0, 0])
    return np.arctan2(R[..., 1, 0], R[..., 0, 0])
