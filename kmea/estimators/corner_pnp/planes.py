"""Rays meet planes: where ``corner-pnp`` puts a marker's corners given the camera fit.

A plane is a frame (3, 3) whose third column is its normal and an origin (3,), world; a
normalized image point (x, y) is the ray (x, y, 1) in the camera frame.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from kmea.estimators.base import MarkerObservation
from kmea.geometry import intersect_rays_planes
from kmea.maps.model import MarkerMap

EYE3 = np.eye(3)
EYE3.flags.writeable = False  # shared: a horizontal plane's frame

Plane = tuple[np.ndarray, np.ndarray]  # (frame (3, 3), origin (3,))


def plane_frames(ids: Sequence[int], world_map: MarkerMap, plane_heights: Mapping[int, float]
                 ) -> dict[int, Plane]:
    """id -> (frame (3, 3) with columns e1, e2, normal; origin (3,)) for markers with a plane.

    An explicit height wins over the map (the caller knows the marker was lifted, e.g. a
    map marker put on a robot); otherwise a map marker lies in its surveyed plane.
    """
    out = {}
    for i in ids:
        if i in plane_heights:
            out[i] = (EYE3, np.array([0.0, 0.0, float(plane_heights[i])]))
        elif i in world_map:
            m = world_map[i]
            out[i] = (m.rotation, m.position)
    return out


def plane_hits(C: np.ndarray, rays: np.ndarray, normals: np.ndarray, num: np.ndarray
               ) -> np.ndarray:
    """:func:`kmea.geometry.intersect_rays_planes` from camera centres C (..., 3) along rays
    (..., N, 3) with the planes' part ``num = sum(normals * (points - C))`` (..., N) given:
    the same operations, so the same numbers (the numerical derivatives difference them)."""
    den = np.add.reduce(normals * rays, axis=-1)
    lam = num / den  # the caller ignores division and overflow warnings (NaN marks misses)
    P = C + lam[..., None] * rays
    bad = ~((lam > 0) & (lam < np.inf))
    if bad.any():
        P[bad] = np.nan
    return P


def intersect(R: np.ndarray, t: np.ndarray, xy: np.ndarray, frames: np.ndarray,
              origins: np.ndarray) -> np.ndarray:
    """World points (N, 3) where the rays of normalized image points xy (N, 2) of the
    world2cam pose (R, t) meet the planes with normals frames[:, :, 2] through origins
    (N, 3); NaN where the plane is behind the camera or parallel to the ray."""
    ray = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) @ R  # R^T ray, world
    return intersect_rays_planes(-R.T @ t, ray, origins, frames[:, :, 2])


def batched_plane_points(R: np.ndarray, t: np.ndarray, xy: np.ndarray, frames: np.ndarray,
                         origins: np.ndarray) -> np.ndarray:
    """Ray-plane points (M, 4, 3) of M poses (R (M, 3, 3) world2cam, t (M, 3)) for each one's
    4 normalized corners xy (M, 4, 2) and plane (frames (M, 3, 3), origins (M, 3))."""
    rays = np.concatenate([xy, np.ones((*xy.shape[:2], 1))], axis=2) @ R  # R^T ray, world
    C = -np.einsum("mji,mj->mi", R, t)
    return intersect_rays_planes(C[:, None, :], rays, origins[:, None, :],
                                 frames[:, None, :, 2])


def stack_corners(ids: Sequence[int], obs: Mapping[int, MarkerObservation]) -> np.ndarray:
    """The corners (4n, 2) px of the markers ``ids``, 4 rows each."""
    return np.concatenate([np.asarray(obs[i].corners, float).reshape(4, 2) for i in ids])


def disagreement(R: np.ndarray, t: np.ndarray, ref_ids: Sequence[int], xy: np.ndarray,
                 world_map: MarkerMap) -> dict[int, float]:
    """id -> RMS distance (m) between a reference's corners intersected with its map plane
    (normalized corners xy, 4 rows per id; world2cam pose R, t) and its map corners."""
    frames = np.repeat(np.array([world_map[i].rotation for i in ref_ids]), 4, axis=0)
    origins = np.repeat(world_map.positions(list(ref_ids)), 4, axis=0)
    P = intersect(R, t, xy, frames, origins).reshape(-1, 4, 3)
    M = np.array([world_map[i].corners_world() for i in ref_ids])
    e = np.sqrt(np.mean(np.sum((P - M) ** 2, axis=2), axis=1))
    return {i: (float(v) if np.isfinite(v) else math.inf)
            for i, v in zip(ref_ids, e, strict=True)}


class CornerPlanes:
    """Each corner's plane frame (4n, 3, 3) and origin (4n, 3) of n markers (4 rows each);
    the last set is kept (read-only), as the robots' planes are the same frame after frame."""

    def __init__(self) -> None:
        self._last: tuple[tuple, np.ndarray, np.ndarray] | None = None

    def __call__(self, ids: Sequence[int], frames: Mapping[int, Plane]
                 ) -> tuple[np.ndarray, np.ndarray]:
        key = tuple((i, frames[i][0].tobytes(), frames[i][1].tobytes()) for i in ids)
        last = self._last
        if last is not None and last[0] == key:
            return last[1], last[2]
        F = np.repeat(np.array([frames[i][0] for i in ids]), 4, axis=0)
        O = np.repeat(np.array([frames[i][1] for i in ids]), 4, axis=0)
        F.flags.writeable = False
        O.flags.writeable = False
        self._last = (key, F, O)
        return F, O
