"""OpenCV's pinhole + distortion camera model in numpy: projection with Jacobians, undistortion.

Conventions are OpenCV's: camera frame x right, y down, z forward; pixel centres at integer
coordinates; distortion coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4
[, tauX, tauY]]]]). The tilted-sensor terms (tauX, tauY) must be zero. Like
``cv2.projectPoints`` and ``cv2.undistortPoints``, the skew K[0, 1] is ignored. Numpy only, so the
estimators stay free of cv2; the tests check it against ``cv2.projectPoints`` and
``cv2.undistortPoints``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["dist14", "distort", "project", "skew", "so3_exp", "undistort"]


def dist14(dist: np.ndarray) -> np.ndarray:
    """Distortion coefficients padded to OpenCV's 14; ``ValueError`` for a tilted sensor."""
    d = np.asarray(dist, dtype=float).reshape(-1)
    if d.size > 14:
        raise ValueError(f"distortion: at most 14 coefficients, got {d.size}")
    out = np.zeros(14)
    out[: d.size] = d
    if out[12] != 0.0 or out[13] != 0.0:
        raise ValueError("distortion: the tilted-sensor terms (tauX, tauY) are not supported")
    return out


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices of vectors (..., 3) -> (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    z = np.zeros(v.shape[:-1])
    return np.stack([np.stack([z, -v[..., 2], v[..., 1]], -1),
                     np.stack([v[..., 2], z, -v[..., 0]], -1),
                     np.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of the rotation vector ``w`` (3,) (Rodrigues)."""
    w = np.asarray(w, dtype=float)
    th = float(np.linalg.norm(w))
    K = skew(w)
    if th < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + np.sin(th) / th * K + (1.0 - np.cos(th)) / th ** 2 * K @ K


def distort(xy: np.ndarray, d: np.ndarray, jac: bool = False):
    """Distort normalized points (N, 2) with coefficients ``d`` (14,).

    Returns xd (N, 2); with ``jac`` also d xd / d xy (N, 2, 2) and d xd / d k1 (N, 2).
    """
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = d[:12]
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    r4 = r2 * r2
    a = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    b = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
    rad = a / b
    xd = x * rad + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) + s1 * r2 + s2 * r4
    yd = y * rad + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y + s3 * r2 + s4 * r4
    out = np.stack([xd, yd], axis=1)
    if not jac:
        return out
    da = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    db = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2)
    drad = (da * b - a * db) / (b * b)  # d rad / d r2
    tx = s1 + 2.0 * s2 * r2
    ty = s3 + 2.0 * s4 * r2
    J = np.empty((len(x), 2, 2))
    J[:, 0, 0] = rad + 2.0 * x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x + 2.0 * tx * x
    J[:, 0, 1] = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y + 2.0 * tx * y
    J[:, 1, 0] = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y + 2.0 * ty * x
    J[:, 1, 1] = rad + 2.0 * y * y * drad + 6.0 * p1 * y + 2.0 * p2 * x + 2.0 * ty * y
    dk1 = np.stack([x * r2 / b, y * r2 / b], axis=1)
    return out, J, dk1


def project(Pc: np.ndarray, K: np.ndarray, d: np.ndarray, jac: bool = False):
    """Pixels (N, 2) of camera-frame points Pc (N, 3) (metres, z > 0).

    With ``jac`` also returns d uv / d Pc (N, 2, 3), d uv / d f (N, 2) for a common
    multiplier of fx and fy at 1, and d uv / d k1 (N, 2).
    """
    Z = Pc[:, 2]
    xy = Pc[:, :2] / Z[:, None]
    fx, s, cx, fy, cy = K[0, 0], 0.0, K[0, 2], K[1, 1], K[1, 2]
    if not jac:
        xd = distort(xy, d)
        return np.stack([fx * xd[:, 0] + s * xd[:, 1] + cx, fy * xd[:, 1] + cy], axis=1)
    xd, Jd, dk1 = distort(xy, d, jac=True)
    uv = np.stack([fx * xd[:, 0] + s * xd[:, 1] + cx, fy * xd[:, 1] + cy], axis=1)
    A = np.array([[fx, s], [0.0, fy]])
    iz = 1.0 / Z
    Jxy = np.zeros((len(Z), 2, 3))
    Jxy[:, 0, 0] = iz
    Jxy[:, 1, 1] = iz
    Jxy[:, 0, 2] = -xy[:, 0] * iz
    Jxy[:, 1, 2] = -xy[:, 1] * iz
    J_pc = np.einsum("ij,njk,nkl->nil", A, Jd, Jxy)
    J_f = np.stack([fx * xd[:, 0] + s * xd[:, 1], fy * xd[:, 1]], axis=1)
    J_k1 = dk1 @ A.T
    return uv, J_pc, J_f, J_k1


def undistort(uv: np.ndarray, K: np.ndarray, d: np.ndarray, iterations: int = 20) -> np.ndarray:
    """Normalized undistorted coordinates (N, 2) of pixels uv (N, 2).

    Inverts :func:`distort` by a few fixed-point steps (OpenCV's scheme, robust far from
    the solution) followed by Newton steps with the analytic Jacobian, to machine precision
    for any distortion the calibration can produce inside the image.
    """
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    fx, s, cx, fy, cy = K[0, 0], 0.0, K[0, 2], K[1, 1], K[1, 2]
    yd = (uv[:, 1] - cy) / fy
    xd = (uv[:, 0] - cx - s * yd) / fx
    target = np.stack([xd, yd], axis=1)
    if not np.any(d[:12]):
        return target
    xy = target.copy()
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = d[:12]
    for _ in range(3):
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        r4 = r2 * r2
        icd = (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))) / (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)))
        dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) + s1 * r2 + s2 * r4
        dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y + s3 * r2 + s4 * r4
        xy = np.stack([(target[:, 0] - dx) * icd, (target[:, 1] - dy) * icd], axis=1)
    for _ in range(iterations):
        f, J = distort(xy, d, jac=True)[:2]
        F = f - target
        if np.max(np.abs(F)) < 1e-15:
            break
        det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
        step_x = (J[:, 1, 1] * F[:, 0] - J[:, 0, 1] * F[:, 1]) / det
        step_y = (-J[:, 1, 0] * F[:, 0] + J[:, 0, 0] * F[:, 1]) / det
        xy = xy - np.stack([step_x, step_y], axis=1)
    return xy
