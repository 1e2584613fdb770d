"""OpenCV's pinhole + distortion camera model in numpy: projection, its Jacobians, undistortion.

Conventions are OpenCV's: camera frame x right, y down, z forward (metres); pixel centres at
integer coordinates, the top-left pixel's centre at (0, 0); normalised coordinates (x, y) are
the undistorted ray (x, y, 1). Distortion coefficients in OpenCV's order (k1, k2, p1, p2[, k3
[, k4, k5, k6[, s1, s2, s3, s4[, tauX, tauY]]]]); the tilted-sensor terms (tauX, tauY) must be
zero. Like ``cv2.projectPoints`` and ``cv2.undistortPoints``, the skew K[0, 1] is ignored.

The one implementation of the model: the estimators (corner-pnp, the IPPE replica) and the
simulator's lens (``kmea.sim.lens``) call it. Numpy only; the tests compare it with
``cv2.projectPoints`` and ``cv2.undistortPoints``.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "check_camera_matrix",
    "check_distortion",
    "distort",
    "distort_xy",
    "project",
    "project_world",
    "rotation_increment_jacobian",
    "undistort",
]


def check_distortion(dist: np.ndarray) -> np.ndarray:
    """Distortion coefficients (n <= 14,) in OpenCV's order, padded to OpenCV's 14.

    ``ValueError`` for more than 14, non-finite values or a tilted sensor (tauX, tauY != 0).
    """
    d = np.asarray(dist, dtype=float).reshape(-1)
    if d.size > 14:
        raise ValueError(f"distortion: at most 14 coefficients, got {d.size}")
    if not np.all(np.isfinite(d)):
        raise ValueError("distortion: non-finite coefficients")
    out = np.zeros(14)
    out[: d.size] = d
    if out[12] != 0.0 or out[13] != 0.0:
        raise ValueError("distortion: the tilted-sensor terms (tauX, tauY) are not supported")
    return out


def check_camera_matrix(K: np.ndarray) -> np.ndarray:
    """A (3, 3) camera matrix with finite, positive fx, fy; ``ValueError`` otherwise."""
    K = np.asarray(K, dtype=float)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise ValueError(f"camera matrix: expected finite (3, 3), got shape {K.shape}")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError("camera matrix: fx and fy must be > 0")
    return K


def distort_xy(x: np.ndarray, y: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distort normalised coordinates x, y (any equal shapes) with coefficients ``d`` (14,)
    (see :func:`check_distortion`) -> distorted normalised (xd, yd), same shapes.

    Terms whose coefficients are all zero are skipped: the simulator calls this on whole
    images.
    """
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = (float(v) for v in d[:12])
    r2 = x * x
    r2 += y * y
    # Horner: 1 + r2 (k1 + r2 (k2 + r2 k3)), in place.
    radial = k3 * r2 if k3 else np.zeros_like(r2)
    radial += k2
    radial *= r2
    radial += k1
    radial *= r2
    radial += 1.0
    if k4 or k5 or k6:
        den = k6 * r2
        den += k5
        den *= r2
        den += k4
        den *= r2
        den += 1.0
        radial /= den
    xd = x * radial
    yd = y * radial
    if p1 or p2:
        xy2 = 2.0 * x * y
        xd += p1 * xy2 + p2 * (r2 + 2.0 * x * x)
        yd += p1 * (r2 + 2.0 * y * y) + p2 * xy2
    if s1 or s2 or s3 or s4:
        r4 = r2 * r2
        xd += s1 * r2 + s2 * r4
        yd += s3 * r2 + s4 * r4
    return xd, yd


def distort(xy: np.ndarray, d: np.ndarray, jac: bool = False):
    """Distort normalised points xy (N, 2) with coefficients ``d`` (14,).

    Returns xd (N, 2); with ``jac`` also d xd / d xy (N, 2, 2) and d xd / d k1 (N, 2).
    """
    xy = np.asarray(xy, dtype=float)
    x, y = xy[:, 0], xy[:, 1]
    xd, yd = distort_xy(x, y, d)
    out = np.stack([xd, yd], axis=1)
    if not jac:
        return out
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = d[:12]
    r2 = x * x + y * y
    a = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    b = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
    rad = a / b
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
    """Pixels (N, 2) of camera-frame points Pc (N, 3) (metres, z > 0), camera matrix K (3, 3)
    and distortion d (14,).

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


def project_world(points_world: np.ndarray, world2cam: np.ndarray, K: np.ndarray,
                  d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points (N, 3), m, through the (4, 4) world2cam pose -> pixels (N, 2) and
    camera-frame depths z (N,). Points behind the camera give non-finite or mirrored pixels:
    check z."""
    P = np.asarray(points_world, dtype=float).reshape(-1, 3)
    P = P @ world2cam[:3, :3].T + world2cam[:3, 3]
    z = P[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xd, yd = distort_xy(P[:, 0] / z, P[:, 1] / z, d)
    # K[0, 1] (skew) is ignored, as cv2.projectPoints and solvePnP do.
    return np.column_stack([K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]]), z


def rotation_increment_jacobian(J_pc: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(N, 2, 3) derivative of pixels in the left rotation increment w of ``R <- exp(w) R``.

    J_pc: (N, 2, 3) pixels' derivative in their camera-frame points Pc (:func:`project`
    with ``jac``); v: (N, 3) the rotated points R X (Pc minus the translation). Column k is
    J_pc (e_k x v): d Pc / d w = -[v]x.
    """
    J_w = np.empty_like(J_pc)
    J_w[:, :, 0] = J_pc[:, :, 2] * v[:, None, 1] - J_pc[:, :, 1] * v[:, None, 2]
    J_w[:, :, 1] = J_pc[:, :, 0] * v[:, None, 2] - J_pc[:, :, 2] * v[:, None, 0]
    J_w[:, :, 2] = J_pc[:, :, 1] * v[:, None, 0] - J_pc[:, :, 0] * v[:, None, 1]
    return J_w


def undistort(uv: np.ndarray, K: np.ndarray, d: np.ndarray, iterations: int = 20) -> np.ndarray:
    """Normalised undistorted coordinates (N, 2) of pixels uv (N, 2).

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
