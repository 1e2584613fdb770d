"""OpenCV's pinhole + distortion camera model in numpy: projection with Jacobians, undistortion.

Conventions are OpenCV's: camera frame x right, y down, z forward; pixel centres at integer
coordinates; distortion coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4
[, tauX, tauY]]]]). The tilted-sensor terms (tauX, tauY) must be zero. Like
``cv2.projectPoints`` and ``cv2.undistortPoints``, the skew K[0, 1] is ignored. Numpy only, so the
estimators stay free of cv2; the tests check it against ``cv2.projectPoints`` and
``cv2.undistortPoints``.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["dist14", "distort", "project", "skew", "so3_exp", "so3_exp_batch", "undistort"]


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
    x, y, z = (float(v) for v in w)
    th2 = x * x + y * y + z * z
    if th2 < 1e-16:
        a, b = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
    else:
        th = math.sqrt(th2)
        a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th2
    # I + a K + b K^2 with K = [w]x and K^2 = w w^T - th2 I.
    return np.array([
        [1.0 - b * (y * y + z * z), b * x * y - a * z, b * x * z + a * y],
        [b * x * y + a * z, 1.0 - b * (x * x + z * z), b * y * z - a * x],
        [b * x * z - a * y, b * y * z + a * x, 1.0 - b * (x * x + y * y)],
    ])


def so3_exp_batch(w: np.ndarray) -> np.ndarray:
    """Rotation matrices (M, 3, 3) of rotation vectors ``w`` (M, 3) (Rodrigues)."""
    w = np.asarray(w, dtype=float).reshape(-1, 3)
    th2 = np.sum(w * w, axis=1)
    small = th2 < 1e-16
    th = np.sqrt(np.where(small, 1.0, th2))
    a = np.where(small, 1.0 - th2 / 6.0, np.sin(th) / th)
    b = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(th)) / np.where(small, 1.0, th2))
    K = skew(w)
    return np.eye(3)[None] + a[:, None, None] * K + b[:, None, None] * (K @ K)


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
    f = np.array([K[0, 0], K[1, 1]])
    c = np.array([K[0, 2], K[1, 2]])
    fx, fy = f
    if not jac:
        return distort(xy, d) * f + c
    xd, Jd, dk1 = distort(xy, d, jac=True)
    uv = xd * f + c
    iz = 1.0 / Z
    M = Jd * np.array([fx, fy])[None, :, None]  # A @ Jd with A = diag(fx, fy)
    J_pc = np.empty((len(Z), 2, 3))
    J_pc[:, :, 0] = M[:, :, 0] * iz[:, None]
    J_pc[:, :, 1] = M[:, :, 1] * iz[:, None]
    J_pc[:, :, 2] = -(M[:, :, 0] * xy[:, 0:1] + M[:, :, 1] * xy[:, 1:2]) * iz[:, None]
    J_f = np.stack([fx * xd[:, 0], fy * xd[:, 1]], axis=1)
    J_k1 = dk1 * np.array([fx, fy])
    return uv, J_pc, J_f, J_k1


def undistort(uv: np.ndarray, K: np.ndarray, d: np.ndarray, iterations: int = 20) -> np.ndarray:
    """Normalized undistorted coordinates (N, 2) of pixels uv (N, 2).

    Inverts :func:`distort` by a few fixed-point steps (OpenCV's scheme, robust far from
    the solution) followed by Newton steps with the analytic Jacobian, to machine precision
    for any distortion the calibration can produce inside the image.
    """
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    target = (uv - np.array([K[0, 2], K[1, 2]])) / np.array([K[0, 0], K[1, 1]])
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
