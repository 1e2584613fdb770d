"""Both poses of square markers: OpenCV's ``SOLVEPNP_IPPE_SQUARE`` replicated in numpy for
all markers at once, the per-marker OpenCV fallback, and the reprojection error.

The replica follows OpenCV's ippe.cpp step for step (undistorted corners, closed-form square
homography, the two rotations from its Jacobian at the centre, least-squares translations,
rotation vectors and back, projection with distortion) so its results equal
``cv2.solvePnPGeneric(..., SOLVEPNP_IPPE_SQUARE)`` to rounding; the tests check it.
Rotations and the camera model come from :mod:`kmea.geometry`.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from kmea.geometry import distort, matrices_to_rotvecs, project_to_so3, rotvecs_to_matrices
from kmea.vision.cvcompat import undistort_points

__all__ = ["FALLBACK_PX", "exact_corners", "ippe_pair", "ippe_square", "reprojection_rms",
           "solve_pnp_pair"]

# Above this RMS reprojection error (px) of the best IPPE solution, SQPnP is tried too.
FALLBACK_PX = 1.0


def exact_corners(corners: np.ndarray, K: np.ndarray, D: np.ndarray) -> np.ndarray:
    """(N,) bool: the corners are those of a square at some pose to 1e-3 px, i.e. noise-free.

    The exact homography of the four corners gives a pose (columns r1, r2, t up to scale);
    its reprojection error is ~0 only for exact (synthetic) corners and >> 1e-3 px for any
    real detection. Batched over all markers.
    """
    u = undistort_points(
        np.ascontiguousarray(corners.reshape(-1, 1, 2)), K, D,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-12)).reshape(-1, 4, 2)
    obj = np.array([[-1.0, 1.0], [1.0, 1.0], [1.0, -1.0], [-1.0, -1.0]]) / 2.0  # unit square
    N = len(u)
    A = np.zeros((N, 8, 8))
    x, y = obj[:, 0], obj[:, 1]
    A[:, 0::2, 0], A[:, 0::2, 1], A[:, 0::2, 2] = x, y, 1.0
    A[:, 1::2, 3], A[:, 1::2, 4], A[:, 1::2, 5] = x, y, 1.0
    A[:, 0::2, 6], A[:, 0::2, 7] = -u[:, :, 0] * x, -u[:, :, 0] * y
    A[:, 1::2, 6], A[:, 1::2, 7] = -u[:, :, 1] * x, -u[:, :, 1] * y
    try:
        h = np.linalg.solve(A, u.reshape(N, 8)[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return np.zeros(N, bool)
    H = np.concatenate([h, np.ones((N, 1))], axis=1).reshape(N, 3, 3)
    n1 = np.linalg.norm(H[:, :, 0], axis=1)
    n2 = np.linalg.norm(H[:, :, 1], axis=1)
    # A square's first two columns are orthogonal and of one length. Corners within 1e-3 px
    # of a square's projection miss that by ~1e-3 px over the marker's size in pixels, far
    # below the screen's 1e-3 (a test: exact corners of oblique, small and distorted markers
    # pass, the decisions are those of the full test); real detections (0.05 px and more of
    # noise) mostly fail it, and the SVD below runs only for those that pass.
    with np.errstate(invalid="ignore"):
        screen = ((np.abs(np.einsum("ni,ni->n", H[:, :, 0], H[:, :, 1])) <= 1e-3 * n1 * n2)
                  & (np.abs(n1 - n2) <= 1e-3 * (n1 + n2)))
    out = np.zeros(N, bool)
    if not screen.any():
        return out
    H, n1, n2, u = H[screen], n1[screen], n2[screen], u[screen]
    lam = 2.0 / (n1 + n2)
    lam = lam * np.sign(H[:, 2, 2])[:, None].reshape(-1)  # t_z > 0
    r1, r2, t = (H[:, :, k] * lam[:, None] for k in range(3))
    R = project_to_so3(np.stack([r1, r2, np.cross(r1, r2)], axis=2))
    p = np.einsum("nij,kj->nki", R[:, :, :2], obj) + t[:, None, :]
    proj = p[..., :2] / p[..., 2:3]
    err_px = np.sqrt(((proj - u) ** 2).sum(axis=2).mean(axis=1)) * K[0, 0]
    out[screen] = err_px < 1e-3
    return out


def _packed(n: int, rvecs, tvecs, errs) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``cv2.solvePnPGeneric``'s output as R (2, 3, 3), t (2, 3), errors (2,) px, lowest
    error first (one solution is given twice); None without a solution."""
    if not n:
        return None
    rv = np.asarray(rvecs, dtype=np.float64).reshape(-1, 3)[:2]
    R2 = [cv2.Rodrigues(r)[0] for r in rv]
    t2 = list(np.asarray(tvecs, dtype=np.float64).reshape(-1, 3)[:2])
    e2 = np.asarray(errs, dtype=np.float64).reshape(-1)[:2].tolist()
    if len(R2) == 1:
        R2.append(R2[0])
        t2.append(t2[0])
        e2.append(e2[0])
    if e2[1] < e2[0]:  # OpenCV sorts them; do not rely on it
        R2, t2, e2 = R2[::-1], t2[::-1], e2[::-1]
    return np.array(R2), np.array(t2), np.array(e2)


def ippe_pair(obj: np.ndarray, c: np.ndarray, K: np.ndarray, D: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Both ``SOLVEPNP_IPPE_SQUARE`` poses of one marker (object corners obj (4, 3) m,
    pixels c (4, 2)): R (2, 3, 3), t (2, 3), errors (2,) px lowest first; None if none."""
    try:
        return _packed(*cv2.solvePnPGeneric(obj, c, K, D, flags=cv2.SOLVEPNP_IPPE_SQUARE))
    except cv2.error:
        return None


def solve_pnp_pair(obj: np.ndarray, c: np.ndarray, K: np.ndarray, D: np.ndarray, exact: bool
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Both poses of one marker with OpenCV (IPPE_SQUARE, then SQPnP if IPPE looks
    degenerate): R (2, 3, 3), t (2, 3), errors (2,) px lowest first; None if no pose."""
    got = ippe_pair(obj, c, K, D)
    if got is None:
        return None
    best = float(np.min(got[2]))
    if not best < (1e-3 if exact else FALLBACK_PX):  # also NaN
        m, rv2, tv2, er2 = cv2.solvePnPGeneric(obj, c, K, D, flags=cv2.SOLVEPNP_SQPNP)
        if (m and float(np.min(er2)) < best) or not math.isfinite(best):
            return _packed(m, rv2, tv2, er2)
    return got


def ippe_square(corners: np.ndarray, half: np.ndarray, K: np.ndarray, D: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Both ``SOLVEPNP_IPPE_SQUARE`` solutions of every marker at once.

    corners: (N, 4, 2) px; half: (N,) half side (m). Returns R (N, 2, 3, 3) marker2cam,
    t (N, 2, 3) m and RMS reprojection errors (N, 2) px, lowest error first, equal to
    ``cv2.solvePnPGeneric(..., SOLVEPNP_IPPE_SQUARE)`` to rounding (same steps as OpenCV's
    ippe.cpp: undistorted corners, closed-form square homography, the two rotations from its
    Jacobian at the centre, least-squares translations, rotation vectors and back, projection
    with distortion). None when the distortion model has a tilted sensor (not replicated).
    Degenerate markers come out non-finite; the caller re-solves those with OpenCV.
    """
    D = D.reshape(-1)
    if D.size > 12 and np.any(D[12:] != 0.0):
        return None
    N = len(corners)
    u = cv2.undistortPoints(np.ascontiguousarray(corners.reshape(-1, 1, 2)), K, D
                            ).reshape(N, 4, 2)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        p1x, p1y = -u[:, 0, 0], -u[:, 0, 1]
        p2x, p2y = -u[:, 1, 0], -u[:, 1, 1]
        p3x, p3y = -u[:, 2, 0], -u[:, 2, 1]
        p4x, p4y = -u[:, 3, 0], -u[:, 3, 1]
        hl = half
        dets_inv = -1 / (hl * (p1x * p2y - p2x * p1y - p1x * p4y + p2x * p3y - p3x * p2y
                               + p4x * p1y + p3x * p4y - p4x * p3y))
        h00 = dets_inv * (p1x * p3x * p2y - p2x * p3x * p1y - p1x * p4x * p2y + p2x * p4x * p1y
                          - p1x * p3x * p4y + p1x * p4x * p3y + p2x * p3x * p4y
                          - p2x * p4x * p3y)
        h01 = dets_inv * (p1x * p2x * p3y - p1x * p3x * p2y - p1x * p2x * p4y + p2x * p4x * p1y
                          + p1x * p3x * p4y - p3x * p4x * p1y - p2x * p4x * p3y
                          + p3x * p4x * p2y)
        h02 = dets_inv * hl * (p1x * p2x * p3y - p2x * p3x * p1y - p1x * p2x * p4y
                               + p1x * p4x * p2y - p1x * p4x * p3y + p3x * p4x * p1y
                               + p2x * p3x * p4y - p3x * p4x * p2y)
        h10 = dets_inv * (p1x * p2y * p3y - p2x * p1y * p3y - p1x * p2y * p4y + p2x * p1y * p4y
                          - p3x * p1y * p4y + p4x * p1y * p3y + p3x * p2y * p4y
                          - p4x * p2y * p3y)
        h11 = dets_inv * (p2x * p1y * p3y - p3x * p1y * p2y - p1x * p2y * p4y + p4x * p1y * p2y
                          + p1x * p3y * p4y - p4x * p1y * p3y - p2x * p3y * p4y
                          + p3x * p2y * p4y)
        h12 = dets_inv * hl * (p1x * p2y * p3y - p3x * p1y * p2y - p2x * p1y * p4y
                               + p4x * p1y * p2y - p1x * p3y * p4y + p3x * p1y * p4y
                               + p2x * p3y * p4y - p4x * p2y * p3y)
        h20 = -dets_inv * (p1x * p3y - p3x * p1y - p1x * p4y - p2x * p3y + p3x * p2y
                           + p4x * p1y + p2x * p4y - p4x * p2y)
        h21 = dets_inv * (p1x * p2y - p2x * p1y - p1x * p3y + p3x * p1y + p2x * p4y
                          - p4x * p2y - p3x * p4y + p4x * p3y)
        # Jacobian of the homography at the centre, and the centre's image.
        j00, j01 = h00 - h20 * h02, h01 - h21 * h02
        j10, j11 = h10 - h20 * h12, h11 - h21 * h12
        p, q = h02, h12
        # rotateVec2ZAxis((p, q, 1)), transposed.
        nrm = np.sqrt(p * p + q * q + 1.0)
        ax, ay, az = p / nrm, q / nrm, 1.0 / nrm
        d = 1.0 / (1.0 + az)
        ax2, ay2, axay = ax * ax, ay * ay, ax * ay
        rv00, rv01, rv02 = -ax2 * d + 1.0, -axay * d, ax
        rv10, rv11, rv12 = -axay * d, -ay2 * d + 1.0, ay
        rv20, rv21, rv22 = -ax, -ay, 1.0 - (ax2 + ay2) * d
        b00, b01 = rv00 - p * rv20, rv01 - p * rv21
        b10, b11 = rv10 - q * rv20, rv11 - q * rv21
        dtinv = 1.0 / (b00 * b11 - b01 * b10)
        bi00, bi01, bi10, bi11 = dtinv * b11, -dtinv * b01, -dtinv * b10, dtinv * b00
        a00 = bi00 * j00 + bi01 * j10
        a01 = bi00 * j01 + bi01 * j11
        a10 = bi10 * j00 + bi11 * j10
        a11 = bi10 * j01 + bi11 * j11
        ata00 = a00 * a00 + a01 * a01
        ata01 = a00 * a10 + a01 * a11
        ata11 = a10 * a10 + a11 * a11
        gamma = np.sqrt(0.5 * (ata00 + ata11 + np.sqrt((ata00 - ata11) * (ata00 - ata11)
                                                      + 4.0 * ata01 * ata01)))
        r00, r01, r10, r11 = a00 / gamma, a01 / gamma, a10 / gamma, a11 / gamma
        b0 = np.sqrt(-r00 * r00 - r10 * r10 + 1)
        b1 = np.sqrt(-r01 * r01 - r11 * r11 + 1)
        b1 = np.where((-r00 * r01 - r10 * r11) < 0, -b1, b1)
        # R_k = Rv @ M_k with M_k's columns (r00, r10, +-b0), (r01, r11, +-b1), (c0, c1, c2);
        # summed in ippe.cpp's order: near a half turn the rotation vector OpenCV returns is
        # ill-conditioned, so the last bits matter.
        c2 = r00 * r11 - r01 * r10
        col_x0 = np.stack([np.stack([r00, r01, b1 * r10 - b0 * r11], -1),
                           np.stack([r00, r01, b0 * r11 - b1 * r10], -1)], 1)   # (N, 2, 3)
        col_x1 = np.stack([np.stack([r10, r11, b0 * r01 - b1 * r00], -1),
                           np.stack([r10, r11, b1 * r00 - b0 * r01], -1)], 1)
        col_x2 = np.stack([np.stack([b0, b1, c2], -1), np.stack([-b0, -b1, c2], -1)], 1)
        x0 = np.stack([rv00, rv10, rv20], -1)[:, None, :, None]                # (N, 1, 3, 1)
        x1 = np.stack([rv01, rv11, rv21], -1)[:, None, :, None]
        x2 = np.stack([rv02, rv12, rv22], -1)[:, None, :, None]
        R = (col_x0[:, :, None, :] * x0 + col_x1[:, :, None, :] * x1
             + col_x2[:, :, None, :] * x2)                                     # (N, 2, 3, 3)
        # Least-squares translations (computeTranslation), canonical corners = object x, y.
        obj = np.stack([-half, half, half, -half, half, half, -half, -half], 1).reshape(N, 2, 4)
        obj = obj.transpose(0, 2, 1)                                   # (N, 4, 2) x, y
        a2, b2 = -u[:, :, 0], -u[:, :, 1]                              # (N, 4)
        A02 = a2.sum(1)
        A12 = b2.sum(1)
        A22 = (a2 * a2 + b2 * b2).sum(1)
        n = 4.0
        det_inv = 1.0 / (n * n * A22 - n * A12 * A12 - A02 * n * A02)
        S00, S01, S02 = n * A22 - A12 * A12, A02 * A12, -A02 * n
        S10, S11, S12 = A12 * A02, n * A22 - A02 * A02, -n * A12
        S20, S21, S22 = -n * A02, -n * A12, np.full_like(A02, n * n)
        P = np.einsum("nkij,npj->nkpi", R[..., :2], obj)               # (N, 2, 4, 3)
        bx = -a2[:, None] * P[..., 2] - P[..., 0]
        by = -b2[:, None] * P[..., 2] - P[..., 1]
        T0, T1 = bx.sum(2), by.sum(2)
        T2 = (a2[:, None] * bx + b2[:, None] * by).sum(2)
        di = det_inv[:, None]
        t = np.stack([di * (S00[:, None] * T0 + S01[:, None] * T1 + S02[:, None] * T2),
                      di * (S10[:, None] * T0 + S11[:, None] * T1 + S12[:, None] * T2),
                      di * (S20[:, None] * T0 + S21[:, None] * T1 + S22[:, None] * T2)], -1)
        # OpenCV hands out rotation vectors: go through them as it does.
        R = rotvecs_to_matrices(matrices_to_rotvecs(R.reshape(-1, 3, 3))).reshape(N, 2, 3, 3)
        err = reprojection_rms(R, t, obj, corners, K, D)
    swap = err[:, 1] < err[:, 0]
    R[swap] = R[swap][:, ::-1]
    t[swap] = t[swap][:, ::-1]
    err[swap] = err[swap][:, ::-1]
    return R, t, err


def reprojection_rms(R: np.ndarray, t: np.ndarray, obj: np.ndarray, corners: np.ndarray,
                K: np.ndarray, D: np.ndarray) -> np.ndarray:
    """(N, 2) RMS px error of poses R (N, 2, 3, 3), t (N, 2, 3) of the (N, 4, 2) square
    corners, projected as ``cv2.projectPoints`` does (up to 12 distortion coefficients)."""
    k = np.zeros(12)
    k[:D.size] = D[:12]
    X = np.einsum("nkij,npj->nkpi", R[..., :2], obj) + t[:, :, None, :]
    z = np.where(X[..., 2] != 0, 1.0 / X[..., 2], 1.0)
    xy = X[..., :2] * z[..., None]
    xyd = distort(xy.reshape(-1, 2), k).reshape(xy.shape)
    xd, yd = xyd[..., 0], xyd[..., 1]
    u = xd * K[0, 0] + yd * K[0, 1] + K[0, 2]
    v = yd * K[1, 1] + K[1, 2]
    du, dv = u - corners[:, None, :, 0], v - corners[:, None, :, 1]
    return np.sqrt((du * du + dv * dv).sum(axis=2) / 8.0)
