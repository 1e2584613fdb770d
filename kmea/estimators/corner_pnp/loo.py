"""Leave-one-out of ``corner-pnp``'s references from one camera fit: one Gauss-Newton step
per left-out reference from the full solution, all at once (see
:meth:`CornerPnP.estimate_with_loo`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from kmea.estimators.base import MarkerObservation
from kmea.estimators.corner_noise import square_pose
from kmea.estimators.corner_pnp.fit import CameraFit, FitSettings, prior_rows, residuals_jacobian
from kmea.estimators.corner_pnp.placement import square_poses
from kmea.estimators.corner_pnp.planes import batched_plane_points, intersect, stack_corners
from kmea.estimators.robust_lm import huber_weights
from kmea.geometry import rotvecs_to_matrices, undistort
from kmea.maps.model import MarkerMap


def loo_steps(fit: CameraFit, refs: Sequence[int], inliers: Sequence[int], J: np.ndarray,
              Jw: np.ndarray, r: np.ndarray, g: np.ndarray, uv_refs: np.ndarray,
              xy_full: np.ndarray, frames: np.ndarray, origins: np.ndarray,
              lengths: np.ndarray, drop: np.ndarray) -> dict[int, np.ndarray]:
    """One Gauss-Newton step per left-out consensus reference, all at once: id -> centre
    (3,) m. J, Jw (8n, p) the inliers' (weighted) Jacobian, r (8n,) px, g (p,) gradient;
    uv_refs, xy_full (4N, 2) every reference's corners (px, normalized); frames (4N, 3, 3),
    origins (4N, 3) their planes; lengths (N,) m; drop (N,) each one's dropped corner."""
    n, p = len(inliers), J.shape[1]
    Jk, Jwk, rk = J.reshape(n, 8, p), Jw.reshape(n, 8, p), r.reshape(n, 8)
    Hs = fit.H[None] - np.swapaxes(Jwk, 1, 2) @ Jk
    gs = g[None] - np.einsum("nkp,nk->np", Jwk, rk)
    try:
        deltas = -np.linalg.solve(Hs, gs[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:
        return {}
    R = rotvecs_to_matrices(deltas[:, :3]) @ fit.R
    t = fit.t[None] + deltas[:, 3:6]
    pos = {i: k for k, i in enumerate(refs)}
    rows = np.array([np.arange(4 * pos[i], 4 * pos[i] + 4) for i in inliers])  # (n, 4)
    xy0 = xy_full[rows]
    xy = xy0.copy()
    if fit.refine:
        # The intrinsics move by ~1e-4 relative: first order in (f, k1) is exact enough.
        h = 1e-6
        uv = uv_refs[rows].reshape(-1, 2)
        for col, (dK, dd) in ((6, (h, 0.0)), (7, (0.0, h))):
            K2, d2 = fit.K.copy(), fit.d.copy()
            K2[0, 0] *= 1.0 + dK * fit.K0[0, 0] / fit.K[0, 0]
            K2[1, 1] *= 1.0 + dK * fit.K0[0, 0] / fit.K[0, 0]
            d2[0] += dd
            dxy = (undistort(uv, K2, d2).reshape(n, 4, 2) - xy0) / h
            xy = xy + dxy * deltas[:, col, None, None]
    P = batched_plane_points(R, t, xy, frames[rows[:, 0]], origins[rows[:, 0]])
    ok = np.all(np.isfinite(P), axis=(1, 2))
    k_ref = np.array([pos[i] for i in inliers])
    keep = np.ones((n, 4), bool)
    d = drop[k_ref]
    keep[np.flatnonzero(d >= 0), d[d >= 0]] = False
    centres, _ = square_pose(np.where(ok[:, None, None], P, 0.0), frames[rows[:, 0]],
                             lengths[k_ref], keep)
    return {i: centres[k] for k, i in enumerate(inliers) if ok[k]}


def fast_loo(s: FitSettings, corner_q: float, min_references: int, fit: CameraFit,
             refs: Sequence[int], inliers: Sequence[int],
             obs: Mapping[int, MarkerObservation], world_map: MarkerMap
             ) -> dict[int, np.ndarray]:
    """id -> leave-one-out position (3,) m of the fit's references; references the one-step
    update cannot give are omitted (they go through ``estimate(exclude={j})``)."""
    X = np.concatenate([world_map[i].corners_world() for i in inliers])
    uv = stack_corners(inliers, obs)
    rj = residuals_jacobian(X, uv, fit.R, fit.t, fit.K, fit.d, fit.refine, fit.K0)
    if rj is None:
        return {}
    r, J = rj
    w = huber_weights(r, s.huber_px)
    if fit.keep is not None:  # the corners the fit left out weigh nothing
        w = w * np.repeat(np.concatenate([fit.keep[i] for i in inliers]), 2)
    Jw = J * w[:, None]
    g = Jw.T @ r
    if fit.refine:
        rp, Jp = prior_rows(s, fit.K, fit.d, fit.K0, fit.d0)
        g = g + Jp.T @ rp
    out: dict[int, np.ndarray] = {}
    frames = np.repeat(np.array([world_map[i].rotation for i in refs]), 4, axis=0)
    origins = np.repeat(world_map.positions(list(refs)), 4, axis=0)
    uv_refs = stack_corners(refs, obs)
    xy_full = undistort(uv_refs, fit.K, fit.d)
    full = intersect(fit.R, fit.t, xy_full, frames, origins).reshape(-1, 4, 3)
    lengths = np.array([world_map[i].length for i in refs])
    good = np.all(np.isfinite(full), axis=(1, 2))
    # Each reference's own corner test, decided once at the full fit (a left-out reference
    # is tested the same way by estimate(exclude={j})).
    centres, _, drop = square_poses(fit, full, frames[::4], lengths,
                                    uv_refs.reshape(-1, 4, 2), good, corner_q)
    for k, i in enumerate(refs):
        if i not in inliers and good[k]:
            out[i] = centres[k]
    if len(inliers) - 1 >= min_references:
        out.update(loo_steps(fit, refs, inliers, J, Jw, r, g, uv_refs, xy_full, frames,
                             origins, lengths, drop))
    return out
