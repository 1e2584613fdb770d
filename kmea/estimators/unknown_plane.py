"""Markers whose plane nobody gave: infer it, or estimate them free with corrected depth.

A marker that is neither in the map nor on a configured robot has no known plane. Its own
single-marker PnP depth is its noisiest coordinate, and moved by a camera pose it goes
straight into its floor position. Given a fitted camera (world2cam ``R``, ``t``, intrinsics
``K``, ``d``) and the marker's 4 detected corners:

1. **Candidate planes** are the distinct planes of the map's markers (:func:`map_planes`:
   the floor, and e.g. each wall).
2. **Plane fit**: the marker's pose constrained to a candidate plane (3 parameters: x, y and
   the in-plane angle) minimising its corners' squared reprojection error, ``ssr_plane``.
3. **Free fit**: its full 6-DoF pose minimising the same error, ``ssr_free``.
4. **Likelihood-ratio test**: with independent Gaussian corner noise of standard deviation
   ``sigma_px`` per pixel coordinate (the camera fit's residual level, so the test scales
   with the corner noise actually measured), ``(ssr_plane - ssr_free) / sigma_px^2`` follows
   a chi-square with 3 degrees of freedom when the marker does lie on the plane. Below the
   ``level`` quantile (default 0.999: 16.27) the marker is put on that plane (the best
   such plane); above it on every candidate, it is estimated free.
5. **Free estimate**: the marker's camera-frame PnP position scaled by ``depth_scale``, the
   ratio of the references' fitted camera distances to their own PnP distances (what the
   references show about the single-marker depth: a focal length or printed-size error), then
   moved by the camera pose. This is KMEA's scale step with the all-corner camera: its error
   is at most KMEA's on the same frame, typically less.

Modes: ``"auto"`` (the test), ``"floor"`` (always the floor plane z = 0 of the map's
floor markers, as if told), ``"free"`` (never a plane). Numpy only.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from kmea.geometry import (
    check_distortion,
    intersect_rays_planes,
    marker_corners_local,
    project,
    rot_z,
    rotation_increment_jacobian,
    rotvec_to_matrix,
    undistort,
    yaw_of,
)
from kmea.maps.model import MarkerMap
from kmea.stats.chi2 import chi2_quantile

__all__ = ["MODES", "Plane", "PlaneChoice", "check_mode", "infer", "map_planes",
           "place_with_similarity"]

MODES = ("auto", "floor", "free")


@dataclass(frozen=True)
class Plane:
    """A plane of the map: ``frame`` (3, 3) columns e1, e2, unit normal n (world); ``origin``
    (3,) a point on it (m); ``label`` for people and telemetry ("floor", "plane 2", ...)."""

    frame: np.ndarray
    origin: np.ndarray
    label: str


@dataclass
class PlaneChoice:
    """What :func:`infer` decided for one marker.

    kind: the plane's label, or "free". statistic: the test statistic of the chosen plane
    (the smallest over the candidates; NaN when not tested). position (3,) world m,
    rotation (3, 3) marker2world. plane: (unit normal (3,), offset m) of the chosen plane
    ``normal . p = offset`` (world), None when free.
    """

    kind: str
    statistic: float
    position: np.ndarray
    rotation: np.ndarray
    plane: tuple[np.ndarray, float] | None = None
    dropped: int = -1  # a corner the marker's own square contradicts (left out), or -1


def check_mode(estimator: str, mode: str) -> str:
    """``mode`` when it is one of :data:`MODES`; ``ValueError`` naming the choices otherwise."""
    if mode not in MODES:
        raise ValueError(f"{estimator}: unknown_plane must be one of {', '.join(MODES)}, "
                         f"got {mode!r}")
    return mode


# References used to calibrate a Kabsch alignment's test, and the chi-square (3 dof) median.
_CALIBRATION_REFS = 6
_CHI2_3_MEDIAN = 2.365974

_FLOOR = Plane(np.eye(3), np.zeros(3), "floor")


def map_planes(world_map: MarkerMap, angle_tol: float = 1e-3, offset_tol: float = 1e-3
               ) -> list[Plane]:
    """Distinct planes of the map's markers: normals within ``angle_tol`` rad and offsets
    within ``offset_tol`` m are one plane. The floor (z = 0, facing up) comes first when a
    floor marker exists; the others are labelled "plane 1", "plane 2", ... in id order."""
    out: list[Plane] = []
    floor = False
    for mid in world_map.ids:
        m = world_map[mid]
        if m.on_floor:
            floor = True
            continue
        n = m.normal
        off = float(n @ m.position)
        if any(float(p.frame[:, 2] @ n) > math.cos(angle_tol)
               and abs(float(p.frame[:, 2] @ p.origin) - off) < offset_tol for p in out):
            continue
        out.append(Plane(m.rotation.copy(), m.position.copy(), f"plane {len(out) + 1}"))
    return ([_FLOOR] if floor else []) + out


def _square(length: float) -> np.ndarray:
    return marker_corners_local(length)  # (4, 3) marker frame, z = 0


def _plane_start(R, t, K, d, uv, plane: Plane, sq: np.ndarray):
    """(x, y, angle) in the plane frame from the corners' rays met with the plane, or None.
    uv (m, 2) and sq (m, 3): the corners used (all 4, or 3 of them)."""
    xy = undistort(uv, K, d)
    rays = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) @ R  # world directions
    P = intersect_rays_planes(-R.T @ t, rays, plane.origin, plane.frame[:, 2])
    if not np.all(np.isfinite(P)):
        return None
    local = (P - plane.origin) @ plane.frame  # (m, 3) in the plane frame
    m = local[:, :2].mean(axis=0)
    a = local[:, :2] - m
    ms = sq[:, :2].mean(axis=0)
    s = sq[:, :2] - ms
    ang = math.atan2(float(np.sum(s[:, 0] * a[:, 1] - s[:, 1] * a[:, 0])),
                     float(np.sum(s[:, 0] * a[:, 0] + s[:, 1] * a[:, 1])))
    c = m - rot_z(ang)[:2, :2] @ ms
    return np.array([c[0], c[1], ang])


def _plane_world(q: np.ndarray, plane: Plane, sq: np.ndarray) -> np.ndarray:
    Rl = rot_z(q[2])
    return plane.origin + (sq @ Rl.T + np.array([q[0], q[1], 0.0])) @ plane.frame.T


def _fit_plane(R, t, K, d, uv, plane: Plane, sq: np.ndarray, iterations: int = 8):
    """(ssr px^2, q) of the best in-plane pose, Gauss-Newton with a numerical Jacobian."""
    q = _plane_start(R, t, K, d, uv, plane, sq)
    if q is None:
        return math.inf, None

    def res(q):
        Pc = _plane_world(q, plane, sq) @ R.T + t
        if np.any(Pc[:, 2] <= 1e-9):
            return None
        return (project(Pc, K, d) - uv).reshape(-1)

    r = res(q)
    if r is None:
        return math.inf, None
    ssr = float(r @ r)
    scale = np.array([1e-6, 1e-6, 1e-6])
    for _ in range(iterations):
        J = np.empty((r.size, 3))
        for k in range(3):
            dq = np.zeros(3)
            dq[k] = scale[k]
            rk = res(q + dq)
            if rk is None:
                return ssr, q
            J[:, k] = (rk - r) / scale[k]
        try:
            step = -np.linalg.lstsq(J, r, rcond=None)[0]
        except np.linalg.LinAlgError:
            break
        q2 = q + step
        r2 = res(q2)
        if r2 is None or float(r2 @ r2) > ssr:
            break
        q, r = q2, r2
        done = ssr - float(r @ r) <= 1e-12 * max(ssr, 1e-30)
        ssr = float(r @ r)
        if done:
            break
    return ssr, q


def _fit_free(K, d, uv, R0: np.ndarray, t0: np.ndarray, sq: np.ndarray,
              iterations: int = 10) -> float:
    """Smallest squared reprojection error (px^2) of the square's 6-DoF camera-frame pose,
    Gauss-Newton from (R0, t0)."""
    R, t = np.asarray(R0, float), np.asarray(t0, float)

    def res(R, t, jac):
        Pc = sq @ R.T + t
        if np.any(Pc[:, 2] <= 1e-9):
            return None
        if not jac:
            return (project(Pc, K, d) - uv).reshape(-1)
        uvp, J_pc, _, _ = project(Pc, K, d, jac=True)
        J_w = rotation_increment_jacobian(J_pc, Pc - t)  # left increment exp(w) R
        return (uvp - uv).reshape(-1), np.concatenate([J_w, J_pc], axis=2).reshape(-1, 6)

    out = res(R, t, True)
    if out is None:
        return math.inf
    r, J = out
    ssr = float(r @ r)
    for _ in range(iterations):
        H = J.T @ J
        step = -np.linalg.solve(H + 1e-9 * np.diag(np.diag(H) + 1e-12), J.T @ r)
        R2, t2 = rotvec_to_matrix(step[:3]) @ R, t + step[3:]
        out2 = res(R2, t2, True)
        if out2 is None or float(out2[0] @ out2[0]) > ssr:
            break
        R, t = R2, t2
        r, J = out2
        done = ssr - float(r @ r) <= 1e-12 * max(ssr, 1e-30)
        ssr = float(r @ r)
        if done:
            break
    return ssr


def plane_statistic(R: np.ndarray, t: np.ndarray, K: np.ndarray, d: np.ndarray,
                    uv: np.ndarray, length: float, plane: Plane, marker2cam_R: np.ndarray,
                    marker2cam_t: np.ndarray) -> float:
    """(ssr_plane - ssr_free) in px^2 of one marker on one plane (the test statistic times
    sigma_px^2); inf when the plane is behind the camera."""
    uv = np.asarray(uv, dtype=float).reshape(4, 2)
    sq = _square(length)
    ssr, q = _fit_plane(R, t, K, d, uv, plane, sq)
    if q is None:
        return math.inf
    free = _fit_free(K, d, uv, np.asarray(marker2cam_R, float),
                     np.asarray(marker2cam_t, float), sq)
    return ssr - min(free, ssr)


def _drop_corner(R, t, K, d, uv, plane: Plane, sq: np.ndarray, q: np.ndarray, length: float,
                 sigma_px: float, threshold: float) -> int:
    """The corner of a square fitted in ``plane`` (in-plane pose q) that the other three
    contradict (:func:`kmea.estimators.corner_noise.corner_outliers`), or -1."""
    from kmea.estimators.corner_noise import corner_outliers

    centre = plane.origin + plane.frame @ np.array([q[0], q[1], 0.0])
    rot = plane.frame @ rot_z(q[2])
    drop, _, _ = corner_outliers(R, t, K, d, uv[None], centre[None], rot[None],
                              np.array([length]), sigma_px, threshold)
    return int(drop[0])


def infer(R: np.ndarray, t: np.ndarray, K: np.ndarray, d: np.ndarray, uv: np.ndarray,
          length: float, planes: Sequence[Plane], sigma_px: float, marker2cam_R: np.ndarray,
          marker2cam_t: np.ndarray, depth_scale: float, mode: str = "auto",
          level: float = 0.999, corner_sigma: float | None = None,
          corner_threshold: float | None = None) -> PlaneChoice:
    """Plane or free pose of one marker without a known plane (see the module docstring).

    R, t: world2cam of the fitted camera; K (3, 3), d (14,): its intrinsics; uv (4, 2) the
    marker's corners, px; length m; sigma_px the corner noise (px, per coordinate);
    marker2cam_R/t its own PnP pose (camera frame, m); depth_scale the references' ratio of
    fitted to PnP camera distance. With ``corner_threshold`` (a chi-square 2 dof quantile)
    each candidate plane's fit first drops a corner its own square contradicts at the noise
    ``corner_sigma`` (default sigma_px); the plane and free fits then use the other 3 (the
    test keeps its 3 degrees of freedom).
    """
    if mode not in MODES:
        raise ValueError(f"unknown_plane: mode must be one of {', '.join(MODES)}, got {mode!r}")
    uv = np.asarray(uv, dtype=float).reshape(4, 2)
    sq = _square(length)
    Rc2w = R.T
    C = -Rc2w @ t
    Rm = np.asarray(marker2cam_R, float)
    free_pos = Rc2w @ (depth_scale * np.asarray(marker2cam_t, float)) + C
    free = PlaneChoice("free", math.nan, free_pos, Rc2w @ Rm)
    if mode == "free":
        return free
    cands = [p for p in planes if p.label == "floor"] if mode == "floor" else list(planes)
    if mode == "floor" and not cands:
        cands = [_FLOOR]
    # Every candidate with the 4 corners; the corner test on the best one only (a bad
    # corner moves a marker's fit by pixels, the planes of a map are metres apart).
    fits = []
    for plane in cands:
        ssr, q = _fit_plane(R, t, K, d, uv, plane, sq)
        if q is not None:
            fits.append((ssr, plane, q))
            if mode == "floor":
                break
    if not fits:
        return free
    ssr, plane, q = min(fits, key=lambda f: f[0])
    k = -1
    if corner_threshold is not None:
        k = _drop_corner(R, t, K, d, uv, plane, sq, q, length,
                         sigma_px if corner_sigma is None else corner_sigma, corner_threshold)
        if k >= 0:
            use = np.arange(4) != k
            ssr3, q3 = _fit_plane(R, t, K, d, uv[use], plane, sq[use])
            if q3 is None:
                k = -1
            else:
                ssr, q = ssr3, q3
    if mode == "floor":
        stat = math.nan
    else:
        use = np.arange(4) != k
        # Scale-free start: the PnP pose with its depth corrected as the references say.
        ssr_free = _fit_free(K, d, uv[use], Rm, np.asarray(marker2cam_t, float), sq[use])
        stat = (ssr - min(ssr_free, ssr)) / max(sigma_px, 1e-6) ** 2
    if mode == "auto" and not stat <= chi2_quantile(level, 3):
        free.statistic = stat
        return free
    pos = plane.origin + plane.frame @ np.array([q[0], q[1], 0.0])
    n = plane.frame[:, 2].copy()
    return PlaneChoice(plane.label, stat, pos, plane.frame @ rot_z(q[2]), (n, float(n @ pos)),
                       k)


def place_with_similarity(markers: dict, observations: Sequence, world_map: MarkerMap,
                          references: Sequence[int], scale: float, R: np.ndarray,
                          t: np.ndarray, camera, mode: str, level: float = 0.999,
                          known: Sequence[int] = ()) -> dict[int, PlaneChoice]:
    """:func:`infer` for the Kabsch-family estimators, in place on ``markers`` (id ->
    MarkerEstimate): the markers observed with corners, not in the map and not in ``known``
    (given a plane height) are placed; returns id -> :class:`PlaneChoice` (its position and
    plane in world units).

    The camera is the similarity ``world = scale R cam + t`` (its centre ``t``). The test
    runs in the camera's metric frame (the world divided by ``scale``). Its noise level is
    calibrated on the references themselves, which do lie on their planes: ``sigma_px^2`` is
    the median of their own statistics (``ssr_plane - ssr_free`` on their map plane, up to
    ``_CALIBRATION_REFS`` of them spread over the id range) divided by the chi-square (3 dof)
    median, so the camera pose error of a Kabsch alignment, much larger than corner-pnp's,
    widens the test as it should. Without intrinsics or corners, "auto" gives "free" and
    "floor" slides the marker along its camera ray onto z = 0.
    """
    out: dict[int, PlaneChoice] = {}
    excl = set(known)
    todo = [o for o in observations if o.id not in world_map and o.id not in excl
            and o.id in markers]

    def free(i: int) -> PlaneChoice:
        return PlaneChoice("free", math.nan, markers[i].position, markers[i].rotation)

    if not todo or mode == "free":
        return {o.id: free(o.id) for o in todo}
    if camera is None:
        for o in todo:
            me = markers[o.id]
            if mode == "floor":
                P = intersect_rays_planes(t, me.position - t, _FLOOR.origin,
                                          _FLOOR.frame[:, 2])
                if np.all(np.isfinite(P)):
                    me.position = P
                    out[o.id] = PlaneChoice("floor", math.nan, me.position, me.rotation,
                                            (np.array([0.0, 0.0, 1.0]), 0.0))
                    continue
            out[o.id] = free(o.id)
        return out
    K = np.asarray(camera.camera_matrix, float)
    d = check_distortion(camera.dist_coeffs)
    by_id = {o.id: o for o in observations}
    s = float(scale)
    Rwc, twc = R.T, -R.T @ t / s
    planes = [Plane(p.frame, p.origin / s, p.label) for p in map_planes(world_map)]
    sigma = math.nan
    if mode == "auto":
        refs = [i for i in references if i in by_id and by_id[i].corners is not None]
        step = max(1, len(refs) // _CALIBRATION_REFS)
        stats = []
        for i in refs[::step][:_CALIBRATION_REFS]:
            m, o = world_map[i], by_id[i]
            own = Plane(m.rotation, m.position / s, "own")
            stats.append(plane_statistic(Rwc, twc, K, d, o.corners, m.length / s, own,
                                         o.marker2cam_R, o.marker2cam_t))
        stats = [v for v in stats if math.isfinite(v)]
        if len(stats) >= 3:
            sigma = math.sqrt(max(float(np.median(stats)) / _CHI2_3_MEDIAN, 1e-12))
    for o in todo:
        if o.corners is None or (mode == "auto" and not math.isfinite(sigma)):
            out[o.id] = free(o.id)
            continue
        ch = infer(Rwc, twc, K, d, np.asarray(o.corners, float), o.length / s, planes,
                   sigma, o.marker2cam_R, o.marker2cam_t, 1.0, mode, level)
        me = markers[o.id]
        me.position = s * ch.position
        me.rotation = ch.rotation
        me.yaw = float(yaw_of(ch.rotation))
        ch.position = me.position
        if ch.plane is not None:
            ch.plane = (ch.plane[0], s * ch.plane[1])
        out[o.id] = ch
    return out
