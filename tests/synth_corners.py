"""Synthetic frames for the corner-based estimator tests: cv2.projectPoints + IPPE_SQUARE PnP.

The scene is scenario-1-like: the nominal Pi Camera v2 about 1.35 m above the centre of the
RobotAtFactory floor, looking down (camera x = world x, camera y = world -y). Markers may be
displaced on the floor (``true`` poses) while the map keeps its surveyed ones.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from kmea.estimators.base import MarkerObservation
from kmea.geometry import marker_corners_local, rot_x, rot_z
from kmea.maps.files import Marker, MarkerMap, default_map
from kmea.vision.camera import CameraModel, pi_camera_v2

__all__ = ["Scene", "observe", "scenario1"]


class Scene:
    """A camera pose (world2cam R, t), the camera, the map, and the true marker poses."""

    def __init__(self, camera: CameraModel, R: np.ndarray, t: np.ndarray, world_map: MarkerMap,
                 true: dict[int, Marker]) -> None:
        self.camera, self.R, self.t, self.map, self.true = camera, R, t, world_map, true

    @property
    def cam2world(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.R.T
        T[:3, 3] = -self.R.T @ self.t
        return T


def scenario1(height: float = 1.35, tilt_deg: float = 0.0,
              extra: dict[int, Marker] | None = None,
              displaced: dict[int, tuple[float, float]] | None = None) -> Scene:
    """Camera ``height`` m above the floor centre, pitched by ``tilt_deg`` about world x.

    extra: non-map markers (robots) added to the true scene. displaced: id -> (dx, dy) metres
    of a map marker's true position (the map is unchanged).
    """
    m = default_map()
    x0, x1, y0, y1 = m.floor_extent()
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2, height])
    R = rot_x(math.radians(tilt_deg)) @ np.diag([1.0, -1.0, -1.0])
    true = dict(m.markers)
    for i, (dx, dy) in (displaced or {}).items():
        mk = m[i]
        true[i] = Marker(i, mk.position + np.array([dx, dy, 0.0]), mk.rotation, mk.length)
    true.update(extra or {})
    return Scene(pi_camera_v2(), R, -R @ centre, m, true)


def observe(scene: Scene, noise_px: float = 0.0, seed: int = 0,
            ids: list[int] | None = None) -> list[MarkerObservation]:
    """Observations of the true markers fully inside the image, corners with Gaussian noise."""
    rng = np.random.default_rng(seed)
    cam = scene.camera
    rvec, _ = cv2.Rodrigues(scene.R)
    out = []
    for i in sorted(ids if ids is not None else scene.true):
        mk = scene.true[i]
        Pc = mk.corners_world() @ scene.R.T + scene.t
        if np.any(Pc[:, 2] <= 0.05) or mk.normal @ (-scene.R.T @ scene.t - mk.position) <= 0:
            continue
        uv, _ = cv2.projectPoints(mk.corners_world(), rvec, scene.t, cam.camera_matrix,
                                  cam.dist_coeffs)
        uv = uv.reshape(4, 2)
        if np.any(uv < 1) or np.any(uv[:, 0] > cam.width - 2) or np.any(uv[:, 1] > cam.height - 2):
            continue
        uv = uv + rng.normal(0.0, noise_px, uv.shape) if noise_px > 0 else uv
        obj = marker_corners_local(mk.length)
        ok, rv, tv = cv2.solvePnP(obj, uv, cam.camera_matrix, cam.dist_coeffs,
                                  flags=cv2.SOLVEPNP_IPPE_SQUARE)
        if not (ok and np.all(np.isfinite(rv)) and np.all(np.isfinite(tv))):
            # IPPE degenerates on an exactly fronto-parallel square with exact corners.
            ok, rv, tv = cv2.solvePnP(obj, uv, cam.camera_matrix, cam.dist_coeffs,
                                      flags=cv2.SOLVEPNP_ITERATIVE)
        assert ok
        Rm, _ = cv2.Rodrigues(rv)
        out.append(MarkerObservation(i, Rm, tv.reshape(3), corners=uv, length=mk.length))
    return out


def robot_marker(mid: int, x: float, y: float, height: float, yaw: float,
                 length: float = 0.06) -> Marker:
    return Marker(mid, np.array([x, y, height]), rot_z(yaw), length)
