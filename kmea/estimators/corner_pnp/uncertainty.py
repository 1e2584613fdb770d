"""How well ``corner-pnp`` places a marker: first-order propagation of the camera fit's
covariance and of the marker's own corner noise through the ray-plane intersection.

``sigma`` (m) is the RMS position error, ``sqrt(trace(Cov))``: (a) the pose (and
intrinsics) covariance ``sigma_px^2 (J^T J)^-1`` of the fit and (b) the marker's corner noise
``sigma_px`` per pixel coordinate. Derivatives are numerical (the plane intersection is
cheap) with the step :data:`H_STEP`.
"""

from __future__ import annotations

import numpy as np

from kmea.estimators.corner_pnp.fit import CameraFit, FitConsts
from kmea.estimators.corner_pnp.planes import plane_hits
from kmea.geometry import distort, distort_jacobian, distort_jacobian_entries, rotvec_to_matrix

# The step of the numerical derivatives of the ray-plane points (normalized coordinates and
# pose parameters).
H_STEP = 1e-7


def fit_consts(fit: CameraFit) -> FitConsts:
    """The fit's per-fit constants (:class:`FitConsts`), computed on first use and kept
    with the fit (keyed on its version)."""
    c = fit.consts
    if c is not None and c.version == fit.version:
        return c
    try:
        cov = fit.sigma_px ** 2 * np.linalg.inv(fit.H)
    except np.linalg.LinAlgError:
        cov = None
    # The six perturbed poses of the fit's update: three rotation increments, three
    # translations.
    h = H_STEP
    Rs = np.repeat(fit.R[None], 6, axis=0)
    ts = np.repeat(fit.t[None], 6, axis=0)
    for k in range(3):
        Rs[k] = rotvec_to_matrix(h * np.eye(3)[k]) @ fit.R
        ts[3 + k, k] += h
    c = FitConsts(fit.version, -fit.R.T @ fit.t, cov, Rs, -np.einsum("kji,kj->ki", Rs, ts))
    fit.consts = c
    return c


def marker_sigmas(fit: CameraFit, xy: np.ndarray, F: np.ndarray, O: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """1-sigma (RMS) centre error (m) per marker (n,), and the ray-plane points (4n, 3);
    xy (4n, 2) holds 4 normalized corners per marker, F (4n, 3, 3) and O (4n, 3) their
    planes (frame with the normal as third column, origin).

    First order: Cov = Jp Cov_params Jp^T + sigma_px^2 sum_k Ju_k Ju_k^T / 16 with Jp the
    centre's derivative in the fitted parameters and Ju_k in corner k's pixel; only its
    trace is formed. The points and their xy steps are computed in one product.
    """
    N = len(xy)
    n = N // 4
    c = fit_consts(fit)
    h = H_STEP
    X = np.empty((3, N, 3))  # the rays (x, y, 1), then with x + h, then with y + h
    X[:, :, :2] = xy
    X[:, :, 2] = 1.0
    X[1, :, 0] += h
    X[2, :, 1] += h
    normals = F[:, :, 2]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        num = np.add.reduce(normals * (O - c.C), axis=-1)
        hits = plane_hits(c.C, (X.reshape(-1, 3) @ fit.R).reshape(3, N, 3), normals, num)
        P = hits[0]
        if c.cov is None:
            return np.full(n, np.nan), P
        cov = c.cov
        dP = (hits[1:] - P) / h  # (2, N, 3): d P / d x, d P / d y per corner
        # Pose: the rays stay, the camera moves; the six perturbed poses.
        rays = np.einsum("nj,kji->kni", X[0], c.Rs)                 # (6, N, 3) world
        Cs = c.Cs[:, None, :]
        Pk = plane_hits(Cs, rays, normals, np.add.reduce(normals * (O - Cs), axis=-1))
        Jc = (np.add.reduce(((Pk - P) / h).reshape(6, n, 4, 3), axis=2) / 4.0).reshape(6, -1)
    if fit.refine:
        # Intrinsics move the rays: distort(xy) = (uv - c) / (K0 m) at fixed pixels, so
        # d xy / d m = -Jd^-1 xd / m and d xy / d k1 = -Jd^-1 d distort / d k1.
        xd, Jd, dk1 = distort(xy, fit.d, jac=True)
        Jd_inv = np.linalg.inv(Jd)
        m = fit.K[0, 0] / fit.K0[0, 0]
        dP_dxy = dP.transpose(1, 2, 0)
        Jc = np.concatenate([Jc, np.empty((2, Jc.shape[1]))])
        for k, rhs in ((6, -xd / m), (7, -dk1)):
            dxy = np.einsum("nij,nj->ni", Jd_inv, rhs)
            Jc[k] = np.einsum("nij,nj->ni", dP_dxy, dxy).reshape(n, 4, 3).mean(axis=1
                                                                             ).reshape(-1)
        j00, j01, j10, j11 = Jd[:, 0, 0], Jd[:, 0, 1], Jd[:, 1, 0], Jd[:, 1, 1]
    else:
        j00, j01, j10, j11 = distort_jacobian_entries(xy[:, 0], xy[:, 1], fit.d)
    # Jc (p, 3n): column (marker, axis); the trace of Jc^T cov Jc per marker.
    var = np.add.reduce((np.add.reduce((cov @ Jc) * Jc, axis=0)).reshape(n, 3), axis=1)
    # Own corner noise: d P / d uv = d P / d xy (d uv / d xy)^-1, per corner, with
    # d uv / d xy = diag(fx, fy) Jd and Jd^-1 in closed form.
    det = j00 * j11 - j01 * j10
    if not (det != 0.0).all():
        np.linalg.inv(distort_jacobian(xy, fit.d))  # singular: the error inv() gives
    sx, sy = det * fit.K[0, 0], det * fit.K[1, 1]
    u0 = dP[0] * (j11 / sx)[:, None] - dP[1] * (j10 / sx)[:, None]
    u1 = dP[1] * (j00 / sy)[:, None] - dP[0] * (j01 / sy)[:, None]
    own = np.add.reduce((u0 * u0 + u1 * u1).reshape(n, 12), axis=1)
    return np.sqrt(var + fit.sigma_px ** 2 / 16.0 * own), P
