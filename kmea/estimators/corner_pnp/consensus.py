"""Which references agree with the camera fit of ``corner-pnp``, and which of their corners
to use (rejection scaled by the corner noise the frame shows, see the package docstring)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from kmea.estimators.corner_noise import corner_outliers, robust_sigma, square_pose
from kmea.estimators.corner_pnp.fit import CameraFit, residuals
from kmea.estimators.corner_pnp.planes import intersect
from kmea.estimators.corner_pnp.uncertainty import marker_sigmas
from kmea.maps.model import MarkerMap


@dataclass(frozen=True)
class ConsensusSettings:
    """What the consensus reads of the estimator's options (see :class:`CornerPnP`)."""

    threshold: float | None  # m: the fixed rule (RMS corner distance); None: the noise test
    corner_q: float  # chi-square (2 dof) quantile of the corner test
    ref_q: float  # chi-square (2 dof) quantile of the reference test


def consensus(s: ConsensusSettings, fit: CameraFit, refs: Sequence[int],
              inliers: Sequence[int], X_refs: np.ndarray, uv_refs: np.ndarray,
              xy: np.ndarray, dis: Mapping[int, float], world_map: MarkerMap
              ) -> tuple[list[int], dict[int, np.ndarray]]:
    """The references that agree with the fit, and each one's corners to use ((4,) bool).
    Sets ``fit.corner_sigma``, ``fit.ref_sigma`` and ``fit.thresholds``.

    X_refs (4n, 3) the references' map corners, uv_refs (4n, 2) px their image corners, xy
    (4n, 2) the same normalized, dis id -> RMS corner disagreement (m).

    Two noise levels, both measured: the corners' own (each reference's square fitted in
    its map plane, 3 parameters: what a corrupted corner stands out from) and the fit's
    (the map corners reprojected: corner noise plus what the camera model and the survey
    leave, what a displaced reference stands out from)."""
    n = len(refs)
    uv4 = uv_refs.reshape(n, 4, 2)
    frames = np.array([world_map[i].rotation for i in refs])
    origins = world_map.positions(list(refs))
    P = intersect(fit.R, fit.t, xy, np.repeat(frames, 4, axis=0),
                  np.repeat(origins, 4, axis=0)).reshape(n, 4, 3)
    lengths = np.array([world_map[i].length for i in refs])
    good = np.all(np.isfinite(P), axis=(1, 2))
    pos = {i: k for k, i in enumerate(refs)}
    inl = np.array([pos[i] for i in inliers])
    drop = np.full(n, -1, dtype=int)
    # The corner noise: the median level of the consensus's reprojection residuals (a fit
    # of many references: one bad corner does not spread to the others).
    r = residuals(X_refs, uv_refs, fit.R, fit.t, fit.K, fit.d)
    e2 = (np.full(8 * n, np.inf) if r is None else r ** 2).reshape(n, 4, 2).sum(axis=2)
    sigma_c = robust_sigma(e2[inl].reshape(-1), fit.H.shape[0])
    if np.any(good):
        g = np.flatnonzero(good)
        centres, Rw = square_pose(P[g], frames[g], lengths[g])
        drop[g], _, _ = corner_outliers(fit.R, fit.t, fit.K, fit.d, uv4[g], centres, Rw,
                                        lengths[g], sigma_c, s.corner_q)
        # The fit leaves a corner out only when the map says so too: a corrupted corner
        # disagrees with its own square and with its map corner; one that a slight model
        # error (a grazing view, the lens) moves stays consistent with one of them.
        k = np.flatnonzero(drop >= 0)
        far = e2[k, drop[k]] / sigma_c ** 2 > s.corner_q
        drop[k[~far]] = -1
    fit.corner_sigma = sigma_c
    keep = {i: np.arange(4) != drop[k] for k, i in enumerate(refs)}
    kept = np.array([keep[i] for i in refs])
    # Each reference's corners against its map corners, in units of its own predicted
    # (centre) uncertainty (the fit's pose covariance and its corner noise through its
    # ray-plane intersection: larger for far, small or grazing markers), times the factor by
    # which the references show more spread than predicted (the median; at least 1: the
    # prediction is the floor). RMS over its kept corners: a shift moves all of them, a turn
    # in place too.
    M = X_refs.reshape(n, 4, 3)
    with np.errstate(invalid="ignore"):
        d = np.sqrt(np.sum(kept * np.sum((P - M) ** 2, axis=2), axis=1) / kept.sum(axis=1))
    d = np.where(good, d, np.inf)
    pred = marker_sigmas(fit, xy, np.repeat(frames, 4, axis=0),
                         np.repeat(origins, 4, axis=0))[0]
    pred = np.where(np.isfinite(pred) & (pred > 0), pred, np.inf) / math.sqrt(2.0)
    u2 = (d / pred) ** 2  # chi-square (2 dof) for a reference in place
    factor = max(robust_sigma(u2[inl], 0, 0.0), 1.0)
    fit.ref_sigma = factor
    q = s.ref_q
    new, thr = [], {}
    for k, i in enumerate(refs):
        thr[i] = float(math.sqrt(q) * factor * pred[k])
        ok = (dis[i] <= s.threshold if s.threshold is not None
              else bool(good[k]) and u2[k] <= q * factor ** 2)
        if ok:
            new.append(i)
    fit.thresholds = thr
    return new, keep
