"""The simulator's lens: per-pixel rays of a camera (the distortion model is
:mod:`kmea.geometry.camera`'s), inverted on whole images.

Pixel convention is OpenCV's: the centre of the top-left pixel is (0, 0) and pixel (u, v)
covers [u - 0.5, u + 0.5] x [v - 0.5, v + 0.5]. Normalised coordinates (x, y) are the
undistorted camera-frame ray (x, y, 1).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np

from kmea.geometry import check_distortion, distort_xy, project_world
from kmea.vision.camera import CameraModel

__all__ = ["RayMap", "distort", "project", "ray_map", "undistort_pixels"]


def distort(x: np.ndarray, y: np.ndarray, camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """Normalised undistorted (x, y) -> pixel (u, v): :func:`kmea.geometry.distort_xy` and the
    camera matrix (the skew K[0, 1] ignored, as ``cv2.projectPoints`` does)."""
    try:
        d = check_distortion(camera.dist_coeffs)
    except ValueError as e:
        raise ValueError(f"camera: {e} by the simulator") from None
    xd, yd = distort_xy(x, y, d)
    K = camera.camera_matrix
    return K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]


def project(points_world: np.ndarray, world2cam: np.ndarray,
            camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """World points (N, 3) -> pixels (N, 2) and camera-frame depths z (N,)
    (:func:`kmea.geometry.project_world`)."""
    return project_world(points_world, world2cam, camera.camera_matrix,
                         check_distortion(camera.dist_coeffs))


def undistort_pixels(u: np.ndarray, v: np.ndarray, camera: CameraModel,
                     newton_steps: int = 3, jacobian: bool = False) -> tuple[np.ndarray, ...]:
    """Pixel (u, v) -> normalised (x, y), inverting :func:`distort` to ~1e-10 px.

    OpenCV's iterative undistortion gives the start; Newton steps on the forward model (with a
    finite-difference Jacobian) make it exact. ``jacobian``: also return dx/du, dx/dv, dy/du,
    dy/dv (per pixel), from the last Newton step (so ``newton_steps`` >= 1).
    """
    if jacobian and newton_steps < 1:
        raise ValueError(f"undistort_pixels: the jacobian needs newton_steps >= 1, got "
                         f"{newton_steps}")
    shape = np.shape(u)
    pts = np.column_stack([np.ravel(u), np.ravel(v)]).astype(np.float64)
    und = cv2.undistortPoints(pts.reshape(-1, 1, 2), camera.camera_matrix,
                              np.asarray(camera.dist_coeffs, dtype=float)).reshape(-1, 2)
    x, y = und[:, 0].copy(), und[:, 1].copy()
    h = 1e-6
    a = b = c = d = det = np.ones_like(x)  # the Jacobian: set again by every Newton step
    for _ in range(newton_steps):
        fu, fv = distort(x, y, camera)
        eu, ev = fu - pts[:, 0], fv - pts[:, 1]
        ux, vx = distort(x + h, y, camera)
        uy, vy = distort(x, y + h, camera)
        a, c = (ux - fu) / h, (vx - fv) / h
        b, d = (uy - fu) / h, (vy - fv) / h
        det = a * d - b * c
        x -= (d * eu - b * ev) / det
        y -= (-c * eu + a * ev) / det
    if not jacobian:
        return x.reshape(shape), y.reshape(shape)
    return (x.reshape(shape), y.reshape(shape), (d / det).reshape(shape),
            (-b / det).reshape(shape), (-c / det).reshape(shape), (a / det).reshape(shape))


@dataclass(frozen=True)
class RayMap:
    """Per-pixel rays of a camera and their derivatives, for casting rays into a scene.

    x, y: (H, W) float64 normalised ray of each pixel centre. dxdu, dxdv, dydu, dydv: (H, W)
    float32 derivatives per pixel (a sub-pixel sample at (u + du, v + dv) has the ray
    x + dxdu du + dxdv dv, exact to ~1e-5 px for sub-pixel offsets). tile: tile side in
    pixels; tx0, tx1, ty0, ty1: (rows, cols) bounds of the rays of each tile (pixel squares
    included), for culling.
    """

    x: np.ndarray
    y: np.ndarray
    dxdu: np.ndarray
    dxdv: np.ndarray
    dydu: np.ndarray
    dydv: np.ndarray
    tile: int
    tx0: np.ndarray
    tx1: np.ndarray
    ty0: np.ndarray
    ty1: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.x.shape

    def pixel_rect(self, x0: float, x1: float, y0: float, y1: float,
                   margin: int = 0) -> tuple[int, int, int, int] | None:
        """Pixel rectangle (r0, r1, c0, c1), half-open, of the tiles whose rays may fall in
        the normalised box [x0, x1] x [y0, y1]; None when no tile does."""
        hit = (self.tx1 >= x0) & (self.tx0 <= x1) & (self.ty1 >= y0) & (self.ty0 <= y1)
        rows = np.flatnonzero(hit.any(axis=1))
        if rows.size == 0:
            return None
        cols = np.flatnonzero(hit.any(axis=0))
        H, W = self.shape
        t = self.tile
        return (max(int(rows[0]) * t - margin, 0), min((int(rows[-1]) + 1) * t + margin, H),
                max(int(cols[0]) * t - margin, 0), min((int(cols[-1]) + 1) * t + margin, W))


_CACHE: OrderedDict[tuple, RayMap] = OrderedDict()


def ray_map(camera: CameraModel, tile: int = 16) -> RayMap:
    """The :class:`RayMap` of ``camera`` (cached for the last few cameras)."""
    key = (camera.camera_matrix.tobytes(), np.asarray(camera.dist_coeffs).tobytes(),
           camera.width, camera.height, tile)
    if key in _CACHE:
        _CACHE.move_to_end(key)
        return _CACHE[key]
    W, H = camera.width, camera.height
    u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    x, y, *jac = undistort_pixels(u, v, camera, newton_steps=1, jacobian=True)
    dxdu, dxdv, dydu, dydv = (j.astype(np.float32) for j in jac)
    # Tile bounds include each pixel's square: extend by half a pixel's ray step both ways.
    ex = 0.5 * (np.abs(dxdu) + np.abs(dxdv)) * 1.01
    ey = 0.5 * (np.abs(dydu) + np.abs(dydv)) * 1.01
    nty, ntx = -(-H // tile), -(-W // tile)

    def reduce(a: np.ndarray, fn: np.ufunc, fill: float) -> np.ndarray:
        pad = np.full((nty * tile, ntx * tile), fill)
        pad[:H, :W] = a
        return fn.reduce(fn.reduce(pad.reshape(nty, tile, ntx, tile), axis=3), axis=1)

    rm = RayMap(x, y, dxdu, dxdv, dydu, dydv, tile,
                reduce(x - ex, np.minimum, np.inf), reduce(x + ex, np.maximum, -np.inf),
                reduce(y - ey, np.minimum, np.inf), reduce(y + ey, np.maximum, -np.inf))
    _CACHE[key] = rm
    while len(_CACHE) > 4:
        _CACHE.popitem(last=False)
    return rm
