"""Every marker from its corners, given the camera fit of ``corner-pnp``.

The rays of a marker's 4 corners meet its plane (a given height, a robot's top plate, or
its map plane); centre = mean of the 4 points, in-plane rotation from a 2D Procrustes fit
of the square. A corner the marker's own square contradicts (leave-one-corner-out test) is
left out of that fit. A marker with no known plane is put on a plane of the map when its
corners are consistent with it, else estimated free with its depth corrected by the
references (:mod:`kmea.estimators.unknown_plane`); a marker without corners gets its own
PnP pose moved by the fitted camera pose.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from kmea.estimators import unknown_plane as unknown_plane_mod
from kmea.estimators.base import MarkerEstimate, MarkerObservation
from kmea.estimators.corner_noise import SIGMA_FLOOR_PX, corner_outliers, square_pose
from kmea.estimators.corner_pnp.fit import CameraFit
from kmea.estimators.corner_pnp.planes import CornerPlanes, plane_frames, stack_corners
from kmea.estimators.corner_pnp.uncertainty import marker_sigmas
from kmea.geometry import undistort, yaw_of
from kmea.maps.model import MarkerMap


@dataclass(frozen=True)
class PlacementSettings:
    """What placing markers reads of the estimator's options (see :class:`CornerPnP`)."""

    corner_q: float  # chi-square (2 dof) quantile of the corner test
    unknown_plane: str  # "auto", "floor" or "free"
    plane_level: float  # level of the unknown-plane test


def corner_sigma(fit: CameraFit) -> float:
    """The corner noise (px) the per-marker corner tests use: the consensus's robust level,
    or the fit's residual level for a fit that did not measure it."""
    s = fit.corner_sigma
    return s if math.isfinite(s) else max(fit.sigma_px, SIGMA_FLOOR_PX)


def square_poses(fit: CameraFit, P: np.ndarray, frames: np.ndarray, lengths: np.ndarray,
                 uv: np.ndarray, good: np.ndarray, corner_q: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centres (n, 3), rotations (n, 3, 3) and dropped corner (n,) (-1: none) of n squares
    from their corners' ray-plane points P (n, 4, 3): the 4-corner fit, then the
    leave-one-corner-out test (:func:`corner_outliers`) and the 3-corner fit where a corner
    is dropped. Rows not ``good`` (non-finite P) are left as they come."""
    centres, Rw = square_pose(P, frames, lengths)
    if good.all():
        drop, _, _ = corner_outliers(fit.R, fit.t, fit.K, fit.d, uv, centres, Rw, lengths,
                                     corner_sigma(fit), corner_q)
    else:
        drop = np.full(len(P), -1, dtype=int)
        if not np.any(good):
            return centres, Rw, drop
        g = np.flatnonzero(good)
        d_g, _, _ = corner_outliers(fit.R, fit.t, fit.K, fit.d, uv[g], centres[g], Rw[g],
                                    lengths[g], corner_sigma(fit), corner_q)
        drop[g] = d_g
    sel = np.flatnonzero(drop >= 0)
    if sel.size:
        keep = np.ones((sel.size, 4), bool)
        keep[np.arange(sel.size), drop[sel]] = False
        centres[sel], Rw[sel] = square_pose(P[sel], frames[sel], lengths[sel], keep)
    return centres, Rw, drop


def depth_scale(fit: CameraFit, obs: Mapping[int, MarkerObservation], world_map: MarkerMap,
                inliers: Sequence[int]) -> float:
    """Median ratio of the inliers' fitted camera distances to their own PnP distances (1
    when they agree): what the references show about single-marker depth."""
    X = world_map.positions(list(inliers))
    fitted = np.linalg.norm(X @ fit.R.T + fit.t, axis=1)
    own = np.linalg.norm(np.array([obs[i].marker2cam_t for i in inliers], float), axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = float(np.median(fitted / own))
    return s if math.isfinite(s) and s > 0 else 1.0


def place_markers(s: PlacementSettings, corner_planes: CornerPlanes, fit: CameraFit,
                  obs: Mapping[int, MarkerObservation], world_map: MarkerMap,
                  plane_heights: Mapping[int, float], inliers: Sequence[int] = (),
                  planes: dict[int, unknown_plane_mod.PlaneChoice] | None = None,
                  only: Collection[int] | None = None,
                  dropped: dict[int, int] | None = None,
                  scale_refs: Sequence[int] | None = None) -> dict[int, MarkerEstimate]:
    """World pose and sigma of every observed marker (of ``only`` if given; the others still
    inform the depth scale); ``planes`` receives id -> the choice made for each marker
    without a known plane, ``dropped`` id -> the index of a corner its own square contradicts
    (left out of its pose); ``scale_refs``: the references whose distance ratios give the
    free markers' depth scale (default ``inliers``)."""
    all_obs = obs
    if only is not None:
        obs = {i: o for i, o in obs.items() if i in only}
    Rc2w = fit.R.T
    C = -Rc2w @ fit.t

    def by_pnp(o: MarkerObservation) -> MarkerEstimate:
        Rw = Rc2w @ np.asarray(o.marker2cam_R, dtype=float)
        return MarkerEstimate(o.id, Rc2w @ np.asarray(o.marker2cam_t, float) + C, Rw,
                              float(yaw_of(Rw)))

    frames = plane_frames([i for i in obs if obs[i].corners is not None], world_map,
                          plane_heights)
    out = {i: by_pnp(o) for i, o in obs.items() if i not in frames}
    unknown = [i for i in out if obs[i].corners is not None and i not in world_map]
    if unknown and inliers:
        # Every reference in view: a displaced one barely changes its distance ratio
        # (centimetres over metres), and the median takes care of the rest.
        scale = depth_scale(fit, all_obs, world_map,
                            inliers if scale_refs is None else scale_refs)
        cands = unknown_plane_mod.map_planes(world_map)
        for i in unknown:
            o = obs[i]
            ch = unknown_plane_mod.infer(
                fit.R, fit.t, fit.K, fit.d, np.asarray(o.corners, float), o.length, cands,
                fit.sigma_px, o.marker2cam_R, o.marker2cam_t, scale, s.unknown_plane,
                s.plane_level, corner_sigma=corner_sigma(fit), corner_threshold=s.corner_q)
            if ch.dropped >= 0 and dropped is not None:
                dropped[i] = ch.dropped
            out[i] = MarkerEstimate(i, ch.position, ch.rotation, float(yaw_of(ch.rotation)))
            if planes is not None:
                planes[i] = ch
    if not frames:
        return out
    ids = list(frames)
    uv = stack_corners(ids, obs)
    xy = undistort(uv, fit.K, fit.d)
    F, O = corner_planes(ids, frames)
    sig, P = marker_sigmas(fit, xy, F, O)
    P = P.reshape(-1, 4, 3)
    Fm = F[::4]
    lengths = np.array([world_map[i].length if i in world_map else obs[i].length
                        for i in ids])
    good = np.asarray(np.isfinite(P).all(axis=(1, 2)))  # (n,) bool
    centres, Rw, drop = square_poses(fit, P, Fm, lengths, uv.reshape(-1, 4, 2), good,
                                     s.corner_q)
    if dropped is not None:
        dropped.update({i: int(drop[k]) for k, i in enumerate(ids) if drop[k] >= 0})
    for k, i in enumerate(ids):
        if not good[k]:  # plane behind the camera or parallel to the rays: PnP pose
            out[i] = by_pnp(obs[i])
        else:
            out[i] = MarkerEstimate(i, centres[k], Rw[k], float(yaw_of(Rw[k])), float(sig[k]))
    return out
