"""Helpers shared by the estimators (numpy only).

Conventions: camera-frame positions ``cam`` and map positions ``world`` are (N, 3) arrays in
metres, row i belonging to reference ``ids[i]``. A similarity maps the camera frame to the
world frame as ``p_world = scale * R @ p_cam + t``.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence

import numpy as np

from kmea.estimators.base import Estimate, MarkerEstimate, MarkerObservation
from kmea.geometry import intersect_ray_height, make_transform, yaw_of
from kmea.maps.model import MarkerMap

__all__ = [
    "COINCIDENT_TOL",
    "COLLINEAR_TOL",
    "References",
    "apply_plane_heights",
    "apply_similarity",
    "finish_estimate",
    "reference_problem",
    "select_references",
]

# Reference sets whose second principal spread is below COLLINEAR_TOL times the first (the
# RMS distance to the best-fit line is under 1 mm per metre of extent) are called collinear:
# the rotation about that line would be decided by noise, which is a wrong pose, not an estimate.
COLLINEAR_TOL = 1e-3
# Largest principal spread (m) below which all references are taken to coincide.
COINCIDENT_TOL = 1e-9


class References:
    """The reference markers of one frame: observed, in the map, not excluded, not suspect;
    sorted by id.

    Attributes: ids (tuple of int), cam (N, 3) camera-frame centres (m), world (N, 3) map
    centres (m).
    """

    __slots__ = ("cam", "ids", "world")

    def __init__(self, ids: tuple[int, ...], cam: np.ndarray, world: np.ndarray) -> None:
        self.ids = ids
        self.cam = cam
        self.world = world

    def __len__(self) -> int:
        return len(self.ids)

    def index(self, marker_id: int) -> int | None:
        """Row of ``marker_id`` or None when it is not a reference."""
        try:
            return self.ids.index(marker_id)
        except ValueError:
            return None


def select_references(observations: Sequence[MarkerObservation], world_map: MarkerMap,
                      exclude: Collection[int] = ()) -> References:
    """Observed map markers not in ``exclude`` and not ``suspect``, sorted by id (so results
    do not depend on the detection order)."""
    excl = set(exclude)
    obs = sorted((o for o in observations
                  if o.id in world_map and o.id not in excl and not o.suspect),
                 key=lambda o: o.id)
    ids = tuple(o.id for o in obs)
    cam = np.array([np.asarray(o.marker2cam_t, dtype=float) for o in obs]).reshape(-1, 3)
    return References(ids, cam, world_map.positions(list(ids)))


def _spread(P: np.ndarray) -> np.ndarray:
    """Singular values (3,) of the centred (N, 3) point set, largest first."""
    return np.linalg.svd(P - P.mean(axis=0), compute_uv=False)


def reference_problem(world: np.ndarray, cam: np.ndarray, min_refs: int = 3) -> str | None:
    """Why these references cannot fix a 3-D similarity, or None when they can.

    Fewer than ``min_refs`` references, coincident or collinear references (in the map or
    as observed) are refused. Coplanar references are fine: Kabsch with the determinant
    correction has a unique solution for them.
    """
    n = len(world)
    if n < min_refs:
        return f"{n} reference marker(s) visible, need at least {min_refs}"
    for label, P in (("map", world), ("camera", cam)):
        s = _spread(P)
        if s[0] <= COINCIDENT_TOL:
            return f"reference markers coincide ({label} positions)"
        if s[1] <= COLLINEAR_TOL * s[0]:
            return f"reference markers are collinear ({label} positions)"
    return None


def apply_similarity(observations: Sequence[MarkerObservation], scale: float, R: np.ndarray,
                     t: np.ndarray) -> dict[int, MarkerEstimate]:
    """World pose of every observed marker under ``p_world = scale * R @ p_cam + t``.

    The world rotation of a marker is R @ marker2cam_R (scale does not rotate).
    """
    if not observations:
        return {}
    P = np.array([o.marker2cam_t for o in observations], dtype=float).reshape(-1, 3)
    Rc = np.array([o.marker2cam_R for o in observations], dtype=float).reshape(-1, 3, 3)
    Pw = scale * P @ R.T + t
    Rw = R @ Rc  # (N, 3, 3): R broadcast over the stack
    yaw = np.asarray(yaw_of(Rw))  # (N,)
    return {o.id: MarkerEstimate(o.id, Pw[i], Rw[i], float(yaw[i]))
            for i, o in enumerate(observations)}


def apply_plane_heights(markers: dict[int, MarkerEstimate], camera_world: np.ndarray,
                        plane_heights: Mapping[int, float] | None,
                        references: Collection[int]) -> list[int]:
    """Move each marker of known height h (not a reference) along its camera ray to z = h.

    A single marker's PnP depth is its least certain coordinate; the ray from the camera
    centre ``camera_world`` (3,) through the estimated centre is not. Returns the ids moved;
    a ray parallel to the plane or pointing away from it leaves the marker as it was.
    """
    moved: list[int] = []
    if not plane_heights:
        return moved
    refs = set(references)
    cx, cy, cz = np.asarray(camera_world, dtype=float).tolist()
    for mid, h in plane_heights.items():
        me = markers.get(mid)
        if me is None or mid in refs:
            continue
        x, y, z = np.asarray(me.position, dtype=float).tolist()
        dx, dy, dz = x - cx, y - cy, z - cz
        if abs(dz) < 1e-12:
            continue
        p = intersect_ray_height((cx, cy, cz), (dx, dy, dz), h)
        if p is None:
            continue
        me.position = np.array(p)
        moved.append(mid)
    return moved


def finish_estimate(name: str, observations: Sequence[MarkerObservation], refs: References,
                    scale: float, R: np.ndarray, t: np.ndarray,
                    plane_heights: Mapping[int, float] | None = None,
                    info: dict | None = None, unknown: tuple | None = None) -> Estimate:
    """Build the Estimate of a camera-to-world similarity: every marker, residuals, cam2world.

    unknown: (world_map, camera intrinsics or None, mode, level) to place the markers with no
    known plane (:func:`kmea.estimators.unknown_plane.place_with_similarity`); their choice
    goes to ``info["unknown_planes"]`` (id -> plane label or "free"), the test statistic to
    ``info["plane_statistics"]`` and the plane to ``info["plane_geometry"]`` (id -> (unit
    normal (3,), offset m) or None when free).
    """
    if not (np.isfinite(scale) and scale > 0.0 and np.all(np.isfinite(R))
            and np.all(np.isfinite(t))):
        return Estimate.failed(name, "alignment is not finite")
    markers = apply_similarity(observations, scale, R, t)
    aligned = scale * refs.cam @ R.T + t
    res = np.linalg.norm(aligned - refs.world, axis=1)
    residuals = {mid: float(r) for mid, r in zip(refs.ids, res, strict=True)}
    info = dict(info or {})
    info["rms_residual"] = float(np.sqrt(np.mean(res**2))) if len(res) else float("nan")
    moved = apply_plane_heights(markers, np.asarray(t, dtype=float), plane_heights, refs.ids)
    if moved:
        info["plane_height_ids"] = moved
    if unknown is not None:
        from kmea.estimators.unknown_plane import place_with_similarity

        world_map, camera, mode, level = unknown
        placed = place_with_similarity(markers, observations, world_map, refs.ids, scale, R,
                                       np.asarray(t, dtype=float), camera, mode, level,
                                       known=list(plane_heights or ()))
        if placed:
            info["unknown_planes"] = {i: c.kind for i, c in placed.items()}
            info["plane_statistics"] = {i: c.statistic for i, c in placed.items()}
            info["plane_geometry"] = {i: c.plane for i, c in placed.items()}
    return Estimate(algorithm=name, ok=True, markers=markers, references=refs.ids,
                    cam2world=make_transform(R, t, scale), scale=float(scale),
                    residuals=residuals, info=info)
