"""Ray-plane intersection (numpy only).

A ray is ``origin + lam * direction`` (metres, any frame; lam > 0 ahead of the origin); a
plane is the set of points p with ``normal . (p - point) = 0``. All functions broadcast over
leading dimensions: origins, directions, points and normals are (..., 3).
"""

from __future__ import annotations

import contextlib
import math

import numpy as np

__all__ = ["intersect_ray_height", "intersect_rays_planes", "ray_plane_parameter",
           "unit_rays_plane_depth"]


def ray_plane_parameter(origins: np.ndarray, directions: np.ndarray, points: np.ndarray,
                        normals: np.ndarray) -> np.ndarray:
    """lam (...) with ``origin + lam * direction`` on the plane; +-inf or NaN where the
    direction is parallel to the plane (no warning)."""
    den = np.sum(normals * directions, axis=-1)
    num = np.sum(normals * (points - origins), axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return num / den


def intersect_rays_planes(origins: np.ndarray, directions: np.ndarray, points: np.ndarray,
                          normals: np.ndarray) -> np.ndarray:
    """Points (..., 3) where the rays meet the planes; NaN rows where the plane is behind
    the origin (lam <= 0) or parallel to the ray."""
    lam = ray_plane_parameter(origins, directions, points, normals)
    with np.errstate(invalid="ignore", over="ignore"):
        P = origins + lam[..., None] * directions
    bad = ~(lam > 0) | ~np.isfinite(lam)
    P = np.where(bad[..., None], np.nan, P)
    return P


def intersect_ray_height(origin: tuple[float, float, float],
                         direction: tuple[float, float, float], height: float
                         ) -> tuple[float, float, float] | None:
    """:func:`intersect_rays_planes` for one ray (x, y, z floats, metres) and the horizontal
    plane z = ``height`` (normal +z), in floats: the same operations (the sums over the
    normal's zero components add exact zeros), without numpy's per-call cost (the pipeline
    places each robot marker on its plane every frame). None where that gives NaN: the plane
    behind the origin or parallel to the ray."""
    ox, oy, oz = origin
    dx, dy, dz = direction
    with contextlib.suppress(ZeroDivisionError):
        lam = (float(height) - oz) / dz
        p = (ox + lam * dx, oy + lam * dy, oz + lam * dz)
        if lam > 0.0 and math.isfinite(lam) and all(map(math.isfinite, p)):
            return p
    return None


def unit_rays_plane_depth(x: np.ndarray, y: np.ndarray, normal: np.ndarray, offset: float,
                          min_depth: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """Depth t along the normalised camera rays (x, y, 1) (arrays of any equal shape, the
    camera at the origin) to the plane ``normal . p = offset`` (camera frame, normal (3,),
    offset in metres), and a mask where the plane is hit from the side its normal points to
    (``normal . ray < 0``, e.g. the floor's up normal seen from above) at least
    ``min_depth`` ahead.

    Scalar arithmetic on whole images (the renderer casts one ray per pixel); t is
    ``offset / (normal . ray)`` where the mask holds, +inf elsewhere.
    """
    n0, n1, n2 = (float(v) for v in normal)
    nd = n0 * x + n1 * y + n2
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t = offset / nd
    ok = (t > min_depth) & (nd < 0)
    t[~ok] = np.inf
    return t, ok
