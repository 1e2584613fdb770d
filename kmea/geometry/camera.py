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

from dataclasses import dataclass
from typing import Literal, overload

import numpy as np

__all__ = [
    "MAX_DISTORTION_STRETCH",
    "CameraIntrinsics",
    "check_camera_matrix",
    "check_distortion",
    "distort",
    "distort_jacobian",
    "distort_jacobian_entries",
    "distort_xy",
    "distortion_problem",
    "project",
    "project_jac_pc",
    "project_world",
    "rotation_increment_jacobian",
    "undistort",
]


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics with OpenCV distortion, as plain arrays (numpy only).

    camera_matrix: (3, 3) K in pixels; dist_coeffs: (n,) OpenCV order (k1, k2, p1, p2, k3, ...).
    width, height: image size in pixels the intrinsics belong to.
    """

    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray
    width: int
    height: int


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
    """The one camera-matrix check: ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` in pixels,
    finite, fx and fy > 0; (9,) row by row is accepted. Returns it (3, 3) float;
    ``ValueError`` saying what is wrong otherwise."""
    K = np.asarray(K, dtype=float)
    if K.shape == (9,):  # written row by row as one list
        K = K.reshape(3, 3)
    if K.shape != (3, 3):
        raise ValueError(f"expected a 3x3 matrix, got shape {K.shape}")
    if not np.all(np.isfinite(K)):
        raise ValueError(f"non-finite entries in {K.tolist()}")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError(f"focal lengths fx, fy must be > 0, got {K[0, 0]}, {K[1, 1]}")
    if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0.0:
        raise ValueError("not a camera matrix (expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]]), "
                         f"got {K.tolist()}")
    return K


# Focal lengths, in units of the image's larger side. Below 1/10 the field of view across
# that side would exceed 2 atan(5) = 157 degrees, more than a pinhole model with OpenCV
# distortion can describe (a 180-degree fisheye images at f = side / pi, three times
# more); above 100 it would be under 0.6 degrees, a telescope, not a localization camera.
MIN_FOCAL_SIDES = 0.1
MAX_FOCAL_SIDES = 100.0
# How many distortion coefficients OpenCV's models have (none: no distortion).
DISTORTION_COUNTS = (0, 4, 5, 8, 12, 14)


def check_image_size(width: int, height: int) -> None:
    """``ValueError`` unless both sides are positive."""
    if int(width) <= 0 or int(height) <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")


def check_focal(fx: float, fy: float, width: int, height: int) -> None:
    """The one rule on focal lengths: each within [MIN_FOCAL_SIDES, MAX_FOCAL_SIDES] times the
    ``width`` x ``height`` image's larger side; ``ValueError`` naming the one outside."""
    side = max(width, height)
    lo, hi = MIN_FOCAL_SIDES * side, MAX_FOCAL_SIDES * side
    for name, f in (("fx", fx), ("fy", fy)):
        if not lo <= f <= hi:
            raise ValueError(f"{name} = {f:g} px is outside [{lo:g}, {hi:g}] px, "
                             f"{MIN_FOCAL_SIDES:g} to {MAX_FOCAL_SIDES:g} times the "
                             f"{width}x{height} image's larger side")


def check_intrinsics(fx: float, fy: float, cx: float, cy: float, width: int,
                     height: int) -> None:
    """A pinhole model that can belong to a ``width`` x ``height`` image (pixels): finite,
    focal lengths within :func:`check_focal`'s bounds, the principal point inside the image.
    ``ValueError`` saying what is wrong."""
    vals = (fx, fy, cx, cy)
    if not np.all(np.isfinite(np.asarray(vals, dtype=float))):
        raise ValueError(f"non-finite camera intrinsics {vals}")
    check_image_size(width, height)
    check_focal(fx, fy, width, height)
    if not (0 <= cx <= width and 0 <= cy <= height):
        raise ValueError(f"principal point ({cx:g}, {cy:g}) px is outside the "
                         f"{width}x{height} image")


def check_camera(K: np.ndarray, dist: np.ndarray, width: int,
                 height: int) -> tuple[np.ndarray, np.ndarray]:
    """The one check of a whole camera: the matrix (:func:`check_camera_matrix`), a
    distortion count OpenCV knows (:data:`DISTORTION_COUNTS`) of finite values, a positive
    image size. Returns (K (3, 3), distortion as given, flat); ``ValueError`` naming the
    field otherwise."""
    try:
        K = check_camera_matrix(K)
    except ValueError as e:
        raise ValueError(f"camera_matrix: {e}") from None
    d = np.asarray(dist, dtype=float).reshape(-1)
    if d.size not in DISTORTION_COUNTS:
        raise ValueError(f"distortion_coefficients: expected 4, 5, 8, 12 or 14 values, "
                         f"got {d.size}")
    if not np.all(np.isfinite(d)):
        raise ValueError(f"distortion_coefficients: non-finite value in {d.tolist()}")
    check_image_size(width, height)
    return K, d


# How far a lens's distortion may push the image's border out from where the pinhole would
# put it (distorted radius / undistorted radius at the border). Real lenses stay near 1:
# pincushion a few per cent above it, wide and fisheye lenses below (a 157-degree view at
# the border is 0.3). k1 = 9000 at f = 1357 px puts the Pi camera's border 15 times out: the
# whole image would be 4.6 degrees wide, and every marker collapses to a point (OpenCV's
# SQPnP then refuses every frame).
MAX_DISTORTION_STRETCH = 3.0
# Directions from the principal point and undistorted angles (to 89.5 degrees) sampled.
_RAYS = 32
_ANGLES = np.tan(np.radians(np.linspace(0.0, 89.5, 1500)))[1:]


def distortion_problem(K: np.ndarray, d: np.ndarray, width: int, height: int) -> str | None:
    """Why the distortion ``d`` (14,) cannot describe a lens on this image, in one phrase,
    or None. Along rays from the principal point the distorted radius must grow with the
    undistorted one until it reaches the image's border (else two directions meet in one
    pixel, or the border has no direction at all: undistortion has no answer there), and
    there it may exceed the undistorted radius by at most ``MAX_DISTORTION_STRETCH``."""
    K = np.asarray(K, dtype=float)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if not (-0.5 < cx < width - 0.5 and -0.5 < cy < height - 0.5):
        return None  # no rays to follow: the principal point's own check names that
    phi = np.linspace(0.0, 2 * np.pi, _RAYS, endpoint=False)
    ux, uy = np.cos(phi), np.sin(phi)
    # The border along each ray, in distorted normalised coordinates.
    with np.errstate(divide="ignore"):
        tx = np.where(ux > 0, (width - 0.5 - cx) / fx, (-0.5 - cx) / fx) / ux
        ty = np.where(uy > 0, (height - 0.5 - cy) / fy, (-0.5 - cy) / fy) / uy
    border = np.minimum(np.where(np.abs(ux) > 1e-12, tx, np.inf),
                        np.where(np.abs(uy) > 1e-12, ty, np.inf))[:, None]  # (rays, 1)
    r = _ANGLES[None, :]
    with np.errstate(over="ignore", invalid="ignore"):
        xd, yd = distort_xy(ux[:, None] * r, uy[:, None] * r, check_distortion(d))
        s = xd * ux[:, None] + yd * uy[:, None]  # the distorted radius along each ray
    s = np.where(np.isfinite(s), s, -np.inf)
    inside = s < border
    # The first sample at or past the border (past the last if the ray never reaches it).
    reach = np.where(inside.all(axis=1), r.shape[1], np.argmin(inside, axis=1))
    for i in range(_RAYS):
        n = int(reach[i])
        path = s[i, :n + 1] if n < r.shape[1] else s[i]
        if np.any(np.diff(np.concatenate(([0.0], path))) <= 0):
            return (f"the distortion folds over inside the image ({np.degrees(phi[i]):.0f} "
                    "degrees from the principal point: two directions would meet in one "
                    "pixel, and undistortion has no answer there)")
        if n >= r.shape[1]:
            return (f"the distortion never reaches the image's border {np.degrees(phi[i]):.0f} "
                    "degrees from the principal point (no direction images there)")
        # The undistorted radius of the border, between the samples either side of it.
        r0, s0 = (r[0, n - 1], s[i, n - 1]) if n else (0.0, 0.0)
        rb = r0 + (border[i, 0] - s0) * (r[0, n] - r0) / (s[i, n] - s0)
        stretch = float(border[i, 0] / rb)
        if stretch > MAX_DISTORTION_STRETCH:
            view = 2 * np.degrees(np.arctan(rb))
            return (f"the distortion pushes the image's border {stretch:.2g} times out from "
                    f"where the pinhole puts it (at most {MAX_DISTORTION_STRETCH:g}): the "
                    f"image would see only {view:.2g} degrees across that way, and every "
                    "marker would shrink to a point")
    return None


def distort_xy(x: np.ndarray, y: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distort normalised coordinates x, y (any equal shapes) with coefficients ``d`` (14,)
    (see :func:`check_distortion`) -> distorted normalised (xd, yd), same shapes.

    Terms whose coefficients are all zero are skipped: the simulator calls this on whole
    images.
    """
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = np.asarray(d[:12], dtype=float).tolist()
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


@overload
def distort(xy: np.ndarray, d: np.ndarray, jac: Literal[False] = False) -> np.ndarray: ...
@overload
def distort(xy: np.ndarray, d: np.ndarray, jac: Literal[True]
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...
def distort(xy: np.ndarray, d: np.ndarray, jac: bool = False
            ) -> np.ndarray | tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distort normalised points xy (N, 2) with coefficients ``d`` (14,).

    Returns xd (N, 2); with ``jac`` also d xd / d xy (N, 2, 2) and d xd / d k1 (N, 2).
    """
    xy = np.asarray(xy, dtype=float)
    x, y = xy[:, 0], xy[:, 1]
    xd, yd = distort_xy(x, y, d)
    out = np.stack([xd, yd], axis=1)
    if not jac:
        return out
    J = distort_jacobian(xy, d)
    k4, k5, k6 = np.asarray(d[5:8], dtype=float).tolist()
    r2 = x * x + y * y
    b = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
    dk1 = np.stack([x * r2 / b, y * r2 / b], axis=1)
    return out, J, dk1


@overload
def project(Pc: np.ndarray, K: np.ndarray, d: np.ndarray, jac: Literal[False] = False
            ) -> np.ndarray: ...
@overload
def project(Pc: np.ndarray, K: np.ndarray, d: np.ndarray, jac: Literal[True]
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]: ...
def project(Pc: np.ndarray, K: np.ndarray, d: np.ndarray, jac: bool = False
            ) -> np.ndarray | tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
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


def distort_jacobian_entries(x: np.ndarray, y: np.ndarray, d: np.ndarray
                             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The entries (J00, J01, J10, J11) of d xd / d xy at x, y (any equal shapes): the
    formulas of :func:`distort` with ``jac``, the terms of all-zero coefficient groups left
    out (adding their exact zeros changes no bit), for the per-frame paths."""
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = np.asarray(d[:12], dtype=float).tolist()
    r2 = x * x + y * y
    a = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    da = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    if k4 or k5 or k6:
        b = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
        db = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2)
        rad = a / b
        drad = (da * b - a * db) / (b * b)
    else:  # b = 1, db = 0 exactly
        rad, drad = a, da
    j00 = rad + 2.0 * x * x * drad
    j01 = 2.0 * x * y * drad
    j10 = j01
    j11 = rad + 2.0 * y * y * drad
    if p1 or p2:
        j00 = j00 + 2.0 * p1 * y + 6.0 * p2 * x
        j01 = j01 + 2.0 * p1 * x + 2.0 * p2 * y
        j10 = j01
        j11 = j11 + 6.0 * p1 * y + 2.0 * p2 * x
    if s1 or s2 or s3 or s4:
        tx = s1 + 2.0 * s2 * r2
        ty = s3 + 2.0 * s4 * r2
        j10 = j01 + 2.0 * ty * x
        j00 = j00 + 2.0 * tx * x
        j01 = j01 + 2.0 * tx * y
        j11 = j11 + 2.0 * ty * y
    return j00, j01, j10, j11


def distort_jacobian(xy: np.ndarray, d: np.ndarray) -> np.ndarray:
    """d xd / d xy (N, 2, 2) of :func:`distort` at normalised points xy (N, 2) (what
    ``distort(xy, d, jac=True)[1]`` gives, without the rest)."""
    xy = np.asarray(xy, dtype=float)
    j00, j01, j10, j11 = distort_jacobian_entries(xy[:, 0], xy[:, 1], d)
    J = np.empty((len(xy), 2, 2))
    J[:, 0, 0] = j00
    J[:, 0, 1] = j01
    J[:, 1, 0] = j10
    J[:, 1, 1] = j11
    return J


def project_jac_pc(Pc: np.ndarray, K: np.ndarray, d: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) of camera-frame points Pc (N, 3) and their derivative d uv / d Pc
    (N, 2, 3): ``project(Pc, K, d, jac=True)[:2]`` without the intrinsics' derivatives."""
    Z = Pc[:, 2]
    x = Pc[:, 0] / Z
    y = Pc[:, 1] / Z
    xd, yd = distort_xy(x, y, d)
    fx, fy = K[0, 0], K[1, 1]
    uv = np.empty((len(Z), 2))
    uv[:, 0] = xd * fx + K[0, 2]
    uv[:, 1] = yd * fy + K[1, 2]
    j00, j01, j10, j11 = distort_jacobian_entries(x, y, d)
    iz = 1.0 / Z
    m00, m01, m10, m11 = j00 * fx, j01 * fx, j10 * fy, j11 * fy
    J = np.empty((len(Z), 2, 3))
    J[:, 0, 0] = m00 * iz
    J[:, 0, 1] = m01 * iz
    J[:, 0, 2] = -(m00 * x + m01 * y) * iz
    J[:, 1, 0] = m10 * iz
    J[:, 1, 1] = m11 * iz
    J[:, 1, 2] = -(m10 * x + m11 * y) * iz
    return uv, J


def undistort(uv: np.ndarray, K: np.ndarray, d: np.ndarray, iterations: int = 20) -> np.ndarray:
    """Normalised undistorted coordinates (N, 2) of pixels uv (N, 2).

    Inverts :func:`distort` by a few fixed-point steps (OpenCV's scheme, robust far from
    the solution) followed by Newton steps with the analytic Jacobian, to machine precision
    for any distortion the calibration can produce inside the image.
    """
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    # Coordinates apart, and the terms of all-zero coefficient groups left out (adding
    # their exact zeros changes no bit): this runs on every frame's robot corners.
    tx = (uv[:, 0] - K[0, 2]) / K[0, 0]
    ty = (uv[:, 1] - K[1, 2]) / K[1, 1]
    coef = np.asarray(d[:12], dtype=float).tolist()
    if not any(coef):
        return np.stack([tx, ty], axis=1)
    x, y = tx, ty
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = coef
    tangential, prism, rational = bool(p1 or p2), bool(s1 or s2 or s3 or s4), bool(k4 or k5 or k6)
    for _ in range(3):
        r2 = x * x + y * y
        den = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        icd = ((1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))) / den) if rational else 1.0 / den
        if tangential or prism:
            r4 = r2 * r2
            dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) + s1 * r2 + s2 * r4
            dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y + s3 * r2 + s4 * r4
            x, y = (tx - dx) * icd, (ty - dy) * icd
        else:
            x, y = tx * icd, ty * icd
    for _ in range(iterations):
        xd, yd = distort_xy(x, y, d)
        fx_ = xd - tx
        fy_ = yd - ty
        if max(np.maximum.reduce(np.abs(fx_)), np.maximum.reduce(np.abs(fy_))) < 1e-15:
            break
        j00, j01, j10, j11 = distort_jacobian_entries(x, y, d)
        det = j00 * j11 - j01 * j10
        step_x = (j11 * fx_ - j01 * fy_) / det
        step_y = (-j10 * fx_ + j00 * fy_) / det
        x = x - step_x
        y = y - step_y
    out = np.empty((len(x), 2))
    out[:, 0] = x
    out[:, 1] = y
    return out
