"""Corner noise measured on the data, and the tests that scale with it (numpy only).

Every threshold of the corner estimators is a quantile of a chi-square statistic built on
``sigma_px``, the corner noise (pixels, per coordinate) the frame itself shows, so a far,
small marker and a near, big one are judged in proportion to what their corners can tell:

- :func:`robust_sigma`: the noise level from the corners' reprojection residuals, by their
  median (robust to up to half of them being outliers: a drawn outline across some
  corners, a displaced marker), floored at :data:`SIGMA_FLOOR_PX`.
- :func:`corner_outliers`: a leave-one-corner-out test of each marker's 4 corners against
  its own square fitted in its plane (3 parameters): the corner whose deleted residual is
  beyond the chi-square (2 dof) quantile is dropped (at most one of 4).
- :func:`square_pose`: a marker's centre and in-plane rotation from the ray-plane points of
  its kept corners (a 2-D Procrustes fit of the known square).

Floor: kmea's detector refines corners to ``cornerRefinementMinAccuracy`` = 0.01 px
(:mod:`kmea.vision.detection`); below that a residual level says nothing about the corners
(exact synthetic corners give ~1e-6 px), so the measured noise is never taken below it.
"""

from __future__ import annotations

import math

import numpy as np

from kmea.geometry import marker_corners_local, project_jac_pc

__all__ = ["SIGMA_FLOOR_PX", "corner_outliers", "robust_sigma", "square_pose"]

SIGMA_FLOOR_PX = 0.01
_UNIT_SQUARE = marker_corners_local(1.0)  # (4, 3), z = 0
_CORNERS = np.arange(4)
# (8, 2): a square's plane coordinates (4 corners x (u, v), flat) -> the sums over its corners
# of c x a and c . a with c the unit square's local corners (the angle's sine and cosine
# parts; the side length scales both and drops out of the angle).
_SQUARE_CROSS_DOT = np.stack([np.stack([-_UNIT_SQUARE[:, 1], _UNIT_SQUARE[:, 0]], axis=1).ravel(),
                              _UNIT_SQUARE[:, :2].ravel()], axis=1)
# Median of the chi-square with 2 degrees of freedom (2 ln 2): |e|^2 / sigma^2 of a 2-D
# Gaussian residual with sigma per coordinate.
_CHI2_2_MEDIAN = 2.0 * math.log(2.0)


def robust_sigma(e2: np.ndarray, n_params: int = 0, floor: float = SIGMA_FLOOR_PX) -> float:
    """Per-coordinate noise level (px) of 2-D residuals with squared norms ``e2`` (m,):
    ``sqrt(median(e2) / (2 ln 2))``, corrected for the ``n_params`` fitted parameters
    (``2m / (2m - n_params)``), at least ``floor``."""
    e2 = np.asarray(e2, dtype=float)
    e2 = e2[np.isfinite(e2)]
    if e2.size == 0:
        return floor
    dof = max(2 * e2.size - n_params, 1)
    var = float(np.median(e2)) / _CHI2_2_MEDIAN * (2 * e2.size) / dof
    return max(math.sqrt(max(var, 0.0)), floor)


def square_pose(P: np.ndarray, frames: np.ndarray, lengths: np.ndarray,
                keep: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Centres (n, 3) and marker2world rotations (n, 3, 3) of n squares from the world points
    P (n, 4, 3) of their corners on their planes (frames (n, 3, 3): columns e1, e2, normal),
    using the corners where ``keep`` (n, 4) is True (all by default; at least 2 each).

    2-D Procrustes of the local square onto the kept points in the plane; with all 4
    corners the centre is their mean (the square's local corners sum to zero)."""
    n = len(P)
    if keep is None:
        # All 4 corners (the per-frame case): the centre is their mean, the rotation from
        # one product of the plane coordinates with the local corners.
        mP = P.sum(axis=1) / 4.0
        a = ((P - mP[:, None, :]) @ frames[:, :, :2]).reshape(n, 8)  # plane coords, flat
        cs = a @ _SQUARE_CROSS_DOT  # (n, 2): sum of c x a, sum of c . a (per unit length)
        ang = np.arctan2(cs[:, 0], cs[:, 1])
        cos, sin = np.cos(ang), np.sin(ang)
        Rw = np.empty((n, 3, 3))
        Rw[:, :, 0] = frames[:, :, 0] * cos[:, None] + frames[:, :, 1] * sin[:, None]
        Rw[:, :, 1] = frames[:, :, 1] * cos[:, None] - frames[:, :, 0] * sin[:, None]
        Rw[:, :, 2] = frames[:, :, 2]
        return mP, Rw
    w = np.asarray(keep, dtype=float)
    c = marker_corners_local(1.0)[None, :, :2] * np.asarray(lengths, float)[:, None, None]
    sw = w.sum(axis=1)
    mP = np.einsum("nk,nki->ni", w, P) / sw[:, None]
    mc = np.einsum("nk,nki->ni", w, c) / sw[:, None]
    a = np.einsum("nki,nij->nkj", P - mP[:, None, :], frames[:, :, :2])  # plane coords
    cc = c - mc[:, None, :]
    ang = np.arctan2(np.sum(w * (cc[:, :, 0] * a[:, :, 1] - cc[:, :, 1] * a[:, :, 0]), axis=1),
                     np.sum(w * (cc[:, :, 0] * a[:, :, 0] + cc[:, :, 1] * a[:, :, 1]), axis=1))
    Rz = np.zeros((n, 3, 3))
    Rz[:, 0, 0] = Rz[:, 1, 1] = np.cos(ang)
    Rz[:, 1, 0] = np.sin(ang)
    Rz[:, 0, 1] = -Rz[:, 1, 0]
    Rz[:, 2, 2] = 1.0
    Rw = frames @ Rz
    # The square's centre: the kept points' mean minus the rotated mean of their local corners.
    off = np.einsum("nij,nj->ni", Rw[:, :, :2], mc)
    return mP - off, Rw


def corner_outliers(R: np.ndarray, t: np.ndarray, K: np.ndarray, d: np.ndarray,
                    uv: np.ndarray, centres: np.ndarray, rotations: np.ndarray,
                    lengths: np.ndarray, sigma_px: float | np.ndarray, threshold: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Leave-one-corner-out test of n squares in their planes.

    R, t: world2cam; K (3, 3), d (14,): intrinsics; uv (n, 4, 2) detected corners, px;
    centres (n, 3), rotations (n, 3, 3) marker2world of the squares fitted in their planes
    (their normal is rotations[:, :, 2]); lengths (n,) m; sigma_px the corner noise
    (px, one value or one per square);
    threshold the chi-square (2 dof) quantile.

    Linearised in the square's 3 in-plane parameters (x, y, angle): J (8, 3) the pixel
    Jacobian, H = J (J^T J)^-1 J^T the hat matrix, e = (I - H) e0 the least-squares
    residuals of the current residuals e0. Corner k's deleted residual (its error when the
    other 3 fix the square) has the statistic ``e_k^T (I - H_kk)^-1 e_k / sigma_px^2``,
    chi-square with 2 dof for a good corner. Returns (dropped corner index (n,), -1 for
    none; the largest statistic (n,); the squared residual norms |e_k|^2 (n, 4), px^2, of
    the 4-corner fit, from which :func:`robust_sigma` (3 parameters a square) measures the
    corners' own noise). The worst corner is dropped when beyond threshold.
    """
    n = len(uv)
    if n == 0:
        return np.full(0, -1, dtype=int), np.zeros(0), np.zeros((0, 4))
    # Batched matrix products and closed-form 2x2 solves: this runs for every robot marker
    # in every frame, where numpy's per-call overhead is the cost.
    sq = _UNIT_SQUARE[None] * np.asarray(lengths, float)[:, None, None]
    off = sq @ rotations.transpose(0, 2, 1)  # (n, 4, 3): the corners about the centre, world
    X = centres[:, None, :] + off
    Pc = X.reshape(-1, 3) @ R.T + t
    if (Pc[:, 2] <= 1e-9).any():
        return np.full(n, -1, dtype=int), np.full(n, np.nan), np.full((n, 4), np.nan)
    proj, J_pc = project_jac_pc(Pc, K, d)
    e0 = (proj - uv.reshape(-1, 2)).reshape(n, 8)
    # d X_k / d (x, y, angle) in world: e1, e2, normal x (X_k - centre); then camera.
    dX = np.empty((n, 4, 3, 3))
    dX[:, :, :, 0] = rotations[:, None, :, 0]
    dX[:, :, :, 1] = rotations[:, None, :, 1]
    nx, ny, nz = (rotations[:, None, i, 2] for i in range(3))
    vx, vy, vz = off[:, :, 0], off[:, :, 1], off[:, :, 2]
    dX[:, :, 0, 2] = ny * vz - nz * vy
    dX[:, :, 1, 2] = nz * vx - nx * vz
    dX[:, :, 2, 2] = nx * vy - ny * vx
    J = ((J_pc @ R).reshape(n, 4, 2, 3) @ dX).reshape(n, 8, 3)
    Jt = J.transpose(0, 2, 1)
    try:
        inv = np.linalg.inv(Jt @ J)
    except np.linalg.LinAlgError:
        return np.full(n, -1, dtype=int), np.full(n, np.nan), np.full((n, 4), np.nan)
    H = J @ inv @ Jt  # (n, 8, 8) hat matrices
    e = e0 - (H @ e0[:, :, None])[:, :, 0]
    # Corner k: e_k^T (I - H_kk)^-1 e_k, the 2x2 inverse in closed form.
    Hd = H.reshape(n, 4, 2, 4, 2)[:, _CORNERS, :, _CORNERS, :]  # (4, n, 2, 2)
    a00, a01 = 1.0 - Hd[:, :, 0, 0], -Hd[:, :, 0, 1]
    a10, a11 = -Hd[:, :, 1, 0], 1.0 - Hd[:, :, 1, 1]
    ex, ey = e[:, 0::2].T, e[:, 1::2].T  # (4, n)
    det = a00 * a11 - a01 * a10
    with np.errstate(invalid="ignore", divide="ignore"):
        stats = ((ex * (a11 * ex - a01 * ey) + ey * (a00 * ey - a10 * ex)) / det).T
    stats[(det == 0.0).T] = np.nan  # singular: no statistic (as a failed solve gave)
    if isinstance(sigma_px, float) or np.ndim(sigma_px) == 0:
        stats /= max(float(sigma_px), 1e-12) ** 2
    else:
        stats /= np.maximum(np.broadcast_to(np.asarray(sigma_px, float), (n,)), 1e-12)[:, None] ** 2
    worst = np.where(np.isfinite(stats), stats, -np.inf).argmax(axis=1)
    top = stats[np.arange(n), worst]
    drop = np.where(np.isfinite(top) & (top > threshold), worst, -1)
    return drop, top, ex.T ** 2 + ey.T ** 2
