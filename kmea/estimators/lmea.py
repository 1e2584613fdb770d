"""LMEA, the paper's Algorithm 1 (KMEA's predecessor and the baseline of every comparison).

It uses only the three anchor markers of the map (``origin_id``, ``x_id``, ``y_id``):

1. scale = |x anchor - origin| in the map / the same distance in the camera frame;
2. translate the camera positions to the origin marker and scale them;
3. rotate them into the orthonormal basis built from the anchors: e_x along origin -> x
   anchor, e_z = e_x x (y anchor - origin) normalised, e_y = e_z x e_x (Gram-Schmidt);
4. place that basis on the same basis built from the anchors' map positions.

On the RobotAtFactory map (origin at 0, x anchor on +X, y anchor on +Y) step 4 is the
identity; on other maps it keeps its meaning. Without its three anchors (not visible, or
excluded) it reports "not estimated".

``lmea-printed`` (:class:`LMEAPrinted`) is Algorithm 1 exactly as printed: e_x and e_y are
the two anchor directions, each normalised, and e_z = e_x x e_y is **not** normalised (so e_y
is not made orthogonal to e_x either: otherwise e_z would be a unit vector already). The
basis is then not orthonormal: noise or a displaced anchor that skews the two camera-frame
axes skews every estimate (a point at x along e_x moves by about x times the skew angle
along y). ``lmea`` is the orthonormalised reading; ``kmea experiment`` shows both.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence

import numpy as np

from kmea.estimators.base import Estimate, EstimatorBase, MarkerObservation, check_observations
from kmea.estimators.common import COLLINEAR_TOL, References, finish_estimate
from kmea.estimators.unknown_plane import check_mode
from kmea.geometry.camera import CameraIntrinsics
from kmea.maps.model import MarkerMap

__all__ = ["LMEA", "LMEAPrinted", "anchor_basis", "printed_basis"]


def anchor_basis(origin: np.ndarray, x_anchor: np.ndarray,
                 y_anchor: np.ndarray) -> np.ndarray | None:
    """Orthonormal right-handed basis (3, 3), columns e_x, e_y, e_z, from three anchor
    positions (3,); None when they are coincident or collinear."""
    vx = x_anchor - origin
    vy = y_anchor - origin
    lx, ly = np.linalg.norm(vx), np.linalg.norm(vy)
    if lx == 0.0 or ly == 0.0:
        return None
    ex = vx / lx
    z = np.cross(ex, vy)
    lz = np.linalg.norm(z)
    if lz <= COLLINEAR_TOL * ly:
        return None
    ez = z / lz
    return np.column_stack([ex, np.cross(ez, ex), ez])


def printed_basis(origin: np.ndarray, x_anchor: np.ndarray,
                  y_anchor: np.ndarray) -> np.ndarray | None:
    """The basis of Algorithm 1 as printed (3, 3), columns e_x, e_y, e_z: e_x and e_y the
    normalised anchor directions, e_z = e_x x e_y not normalised; None when degenerate."""
    vx = x_anchor - origin
    vy = y_anchor - origin
    lx, ly = np.linalg.norm(vx), np.linalg.norm(vy)
    if lx == 0.0 or ly == 0.0:
        return None
    ex, ey = vx / lx, vy / ly
    ez = np.cross(ex, ey)
    if np.linalg.norm(ez) <= COLLINEAR_TOL:
        return None
    return np.column_stack([ex, ey, ez])


class LMEA(EstimatorBase):
    """The paper's Algorithm 1. See the module docstring for the steps."""

    name = "lmea"
    _basis = staticmethod(anchor_basis)

    def __init__(self, unknown_plane: str = "free", plane_level: float = 0.999) -> None:
        self.unknown_plane = check_mode(self.name, unknown_plane)
        self.plane_level = float(plane_level)

    def estimate(
        self,
        observations: Sequence[MarkerObservation],
        world_map: MarkerMap,
        exclude: Collection[int] = (),
        camera: CameraIntrinsics | None = None,
        plane_heights: Mapping[int, float] | None = None,
    ) -> Estimate:
        """World pose of every observed marker; see :class:`kmea.estimators.base.Estimator`."""
        observations = check_observations(observations)
        anchors = (world_map.origin_id, world_map.x_id, world_map.y_id)
        excl = set(exclude)
        seen = {o.id: o for o in observations}
        for label, mid in zip(("origin", "x-axis", "y-axis"), anchors, strict=True):
            if mid not in world_map:
                return Estimate.failed(self.name, f"{label} anchor {mid} is not in the map")
            if mid in excl:
                return Estimate.failed(self.name, f"{label} anchor {mid} is excluded")
            if mid not in seen:
                return Estimate.failed(self.name, f"{label} anchor {mid} not visible")
        cam = np.array([np.asarray(seen[m].marker2cam_t, dtype=float) for m in anchors])
        world = world_map.positions(list(anchors))
        B_cam = self._basis(*cam)
        B_map = self._basis(*world)
        if B_cam is None or B_map is None:
            return Estimate.failed(self.name, "anchors are coincident or collinear")
        dc = np.linalg.norm(cam[1] - cam[0])
        scale = float(np.linalg.norm(world[1] - world[0]) / dc)
        # p_world = world_o + B_map @ B_cam^T @ (scale * (p_cam - cam_o))
        R = B_map @ B_cam.T
        t = world[0] - scale * (R @ cam[0])
        refs = References(anchors, cam, world)
        return finish_estimate(self.name, observations, refs, scale, R, t, plane_heights,
                               unknown=(world_map, camera, self.unknown_plane,
                                        self.plane_level))


class LMEAPrinted(LMEA):
    """Algorithm 1 exactly as printed (e_z not normalised); see the module docstring."""

    name = "lmea-printed"
    _basis = staticmethod(printed_basis)
