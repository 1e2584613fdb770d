"""Per-marker pose in the camera frame, with the IPPE two-fold ambiguity resolved by the scene.

A square marker seen nearly face-on has two PnP solutions (``SOLVEPNP_IPPE_SQUARE`` returns
both): the true pose and its mirror about the line of sight. Their reprojection errors are
close, so the lowest-error one is wrong now and then (a few percent of 60 px markers with
0.2 px corner noise), and its normal is then off by 15-50 degrees. We keep both and pick the
one consistent with the scene:

1. Consensus: every candidate of a visible map marker implies a world2cam rotation
   (``marker2cam @ marker2world.T``). The candidates that agree (within ``kernel_deg``) with
   the most markers form the consensus, averaged (chordal mean) over one candidate per marker.
   With no map marker in view, the floor normal alone is voted from the markers assumed
   horizontal (robots).
2. Decision: each marker's expected normal in the camera frame is its map normal (map
   markers) or world +z (others, unless ``expected_normals`` says otherwise) rotated by the
   consensus of the OTHER markers (leave-one-out, so a marker never votes for itself). The
   candidate closer to it wins if it faces the camera.

``flipped`` = the scene overrode the lowest-error solution (counted in the diagnostics);
``ambiguous`` = the errors are close and the scene could not decide, or the marker's clear
photometric answer contradicts the scene (a tilted or moved marker: we keep the photometric
answer, flag it and count a conflict).

``suspect`` = the detected quadrilateral is not a square seen by this camera: the chosen
pose's RMS reprojection error is above ``max(floor_px, ratio x the frame's median)``, or a
corner lies within ``border_px`` of the image border. A marker partly hidden (a passing
robot's plate over one of its corners) is often still decoded, with that corner a few
pixels off; its pose is then off by centimetres. Suspect markers are still returned, but the
estimators never use them as references (:func:`kmea.estimators.common.select_references`).
See ``docs/vision.md``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import cv2
import numpy as np

from kmea.estimators.base import CameraIntrinsics, MarkerObservation
from kmea.geometry import (
    distort,
    marker_corners_local,
    matrices_to_rotvecs,
    project_to_so3,
    rotvecs_to_matrices,
)
from kmea.maps import MarkerMap
from kmea.vision.camera import CameraModel

__all__ = ["DisambiguationSettings", "PoseDiagnostics", "QualitySettings", "estimate_marker_poses"]

_Z = np.array([0.0, 0.0, 1.0])
# Above this RMS reprojection error (px) of the best IPPE solution, SQPnP is tried too.
_FALLBACK_PX = 1.0


@dataclass(frozen=True)
class DisambiguationSettings:
    """Thresholds of the IPPE choice (pixels and degrees, since people tune them).

    noise_px: corner noise floor added to both errors before their ratio, so two tiny errors
        (noise-free data) do not look decisive.
    ambiguity_ratio: (alt + noise) / (best + noise) below this = the errors cannot tell.
    decisive_ratio: above this the photometric answer wins over a disagreeing scene.
    kernel_deg: candidates within this angle of the consensus vote for it.
    margin_deg: the scene decides only if the two candidates' normals differ in angle to the
        expected normal by at least this much.
    max_deviation_deg: a marker whose both candidates are further than this from its
        expected normal contradicts the scene (conflict).
    agree_deg: when the scene cannot decide but both candidates are within this of the
        expected normal, the choice is harmless: lowest error, not ambiguous.
    """

    noise_px: float = 0.1
    ambiguity_ratio: float = 2.0
    decisive_ratio: float = 3.0
    kernel_deg: float = 15.0
    margin_deg: float = 2.0
    max_deviation_deg: float = 25.0
    agree_deg: float = 5.0


@dataclass(frozen=True)
class QualitySettings:
    """When a detected quadrilateral is ``suspect`` (pixels).

    floor_px: a chosen-pose RMS reprojection error above this may be suspect (an unoccluded
        marker's stays below ~0.3 px on rendered 1640x1232 frames; a corner hidden by a
        robot gives 0.6-2.3 px).
    ratio: ... and it must also exceed ``ratio`` times the frame's median error, so a
        noisier camera (a higher median) raises the bar with its noise.
    border_px: a corner closer than this to the image border (truncated marker).
    """

    floor_px: float = 0.3
    ratio: float = 5.0
    border_px: float = 2.0


@dataclass
class PoseDiagnostics:
    """What the IPPE choice did in one frame (or, after :meth:`merge`, over many).

    n_markers: poses estimated; n_ambiguous / n_flipped / n_conflicts / n_suspect: markers
    flagged ambiguous / scene-corrected / contradicting the scene / suspect (see the module
    docstring); *_by_id: the same per id (counts).
    failed_ids: ids whose corners gave no pose (degenerate quadrilateral).
    consensus: "map" (world2cam rotation from map markers), "horizontal" (floor normal from
    markers assumed horizontal) or "none"; n_support: markers agreeing with it.
    world2cam_R: (3, 3) consensus rotation or None; floor_normal: (3,) world +z in the
    camera frame, or None.
    """

    n_markers: int = 0
    n_ambiguous: int = 0
    n_flipped: int = 0
    n_conflicts: int = 0
    n_suspect: int = 0
    flips_by_id: dict[int, int] = field(default_factory=dict)
    ambiguous_by_id: dict[int, int] = field(default_factory=dict)
    conflicts_by_id: dict[int, int] = field(default_factory=dict)
    suspect_by_id: dict[int, int] = field(default_factory=dict)
    failed_ids: list[int] = field(default_factory=list)
    consensus: str = "none"
    n_support: int = 0
    world2cam_R: np.ndarray | None = None
    floor_normal: np.ndarray | None = None

    def merge(self, other: PoseDiagnostics) -> None:
        """Accumulate another frame's counts into this one (the consensus fields become other's)."""
        self.n_markers += other.n_markers
        self.n_ambiguous += other.n_ambiguous
        self.n_flipped += other.n_flipped
        self.n_conflicts += other.n_conflicts
        self.n_suspect += other.n_suspect
        for mine, theirs in ((self.flips_by_id, other.flips_by_id),
                             (self.ambiguous_by_id, other.ambiguous_by_id),
                             (self.conflicts_by_id, other.conflicts_by_id),
                             (self.suspect_by_id, other.suspect_by_id)):
            for k, v in theirs.items():
                mine[k] = mine.get(k, 0) + v
        self.failed_ids.extend(other.failed_ids)
        self.consensus, self.n_support = other.consensus, other.n_support
        self.world2cam_R, self.floor_normal = other.world2cam_R, other.floor_normal


Lengths = Mapping[int, float] | Callable[[int], float | None] | None


def _length_resolver(lengths: Lengths, world_map: MarkerMap | None,
                     default_length: float) -> Callable[[int], float]:
    """id -> side (m): ``lengths`` first (mapping or callable), then the map, then the default."""
    def resolve(mid: int) -> float:
        value = None
        if callable(lengths):
            value = lengths(mid)
        elif lengths is not None:
            value = lengths.get(mid)
        if value is None and world_map is not None and mid in world_map:
            value = world_map[mid].length
        if value is None:
            value = default_length
        value = float(value)
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"marker {mid}: side length must be a finite value > 0 m, got {value}")
        return value
    return resolve


def _as_inputs(ids: object, corners: object) -> tuple[np.ndarray, np.ndarray]:
    id_arr = np.asarray(ids if ids is not None else [], dtype=np.int64).reshape(-1)
    if isinstance(corners, (list, tuple)):
        corners = [np.asarray(c, dtype=np.float64).reshape(-1) for c in corners]
        c_arr = np.array(corners, dtype=np.float64).reshape(len(corners), -1) if corners \
            else np.zeros((0, 8))
    else:
        c_arr = np.asarray(corners, dtype=np.float64)
    if c_arr.size != id_arr.size * 8:
        raise ValueError(f"corners: expected {id_arr.size} markers x 4 corners x 2, got shape "
                         f"{np.shape(c_arr)}")
    c_arr = c_arr.reshape(-1, 4, 2)
    if not np.all(np.isfinite(c_arr)):
        raise ValueError("corners: non-finite values")
    if len(set(id_arr.tolist())) != id_arr.size:
        raise ValueError(f"ids: duplicate marker id in one frame ({id_arr.tolist()})")
    return id_arr, c_arr


def _exact_corners(corners: np.ndarray, K: np.ndarray, D: np.ndarray) -> np.ndarray:
    """(N,) bool: the corners are those of a square at some pose to 1e-3 px, i.e. noise-free.

    The exact homography of the four corners gives a pose (columns r1, r2, t up to scale);
    its reprojection error is ~0 only for exact (synthetic) corners and >> 1e-3 px for any
    real detection. Batched over all markers.
    """
    u = cv2.undistortPoints(
        np.ascontiguousarray(corners.reshape(-1, 1, 2)), K, D,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-12)).reshape(-1, 4, 2)
    obj = np.array([[-1.0, 1.0], [1.0, 1.0], [1.0, -1.0], [-1.0, -1.0]]) / 2.0  # unit square
    N = len(u)
    A = np.zeros((N, 8, 8))
    x, y = obj[:, 0], obj[:, 1]
    A[:, 0::2, 0], A[:, 0::2, 1], A[:, 0::2, 2] = x, y, 1.0
    A[:, 1::2, 3], A[:, 1::2, 4], A[:, 1::2, 5] = x, y, 1.0
    A[:, 0::2, 6], A[:, 0::2, 7] = -u[:, :, 0] * x, -u[:, :, 0] * y
    A[:, 1::2, 6], A[:, 1::2, 7] = -u[:, :, 1] * x, -u[:, :, 1] * y
    try:
        h = np.linalg.solve(A, u.reshape(N, 8)[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return np.zeros(N, bool)
    H = np.concatenate([h, np.ones((N, 1))], axis=1).reshape(N, 3, 3)
    lam = 2.0 / (np.linalg.norm(H[:, :, 0], axis=1) + np.linalg.norm(H[:, :, 1], axis=1))
    lam = lam * np.sign(H[:, 2, 2])[:, None].reshape(-1)  # t_z > 0
    r1, r2, t = (H[:, :, k] * lam[:, None] for k in range(3))
    R = project_to_so3(np.stack([r1, r2, np.cross(r1, r2)], axis=2))
    p = np.einsum("nij,kj->nki", R[:, :, :2], obj) + t[:, None, :]
    proj = p[..., :2] / p[..., 2:3]
    err_px = np.sqrt(((proj - u) ** 2).sum(axis=2).mean(axis=1)) * K[0, 0]
    return err_px < 1e-3


def _solve_one(obj: np.ndarray, c: np.ndarray, K: np.ndarray, D: np.ndarray, exact: bool
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Both poses of one marker with OpenCV (IPPE_SQUARE, then SQPnP if IPPE looks
    degenerate): R (2, 3, 3), t (2, 3), errors (2,) px lowest first; None if no pose."""
    try:
        n, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj, c, K, D, flags=cv2.SOLVEPNP_IPPE_SQUARE)
    except cv2.error:
        n = 0
    if n:
        best = float(np.min(errs))
        if not best < (1e-3 if exact else _FALLBACK_PX):  # also NaN
            m, rv2, tv2, er2 = cv2.solvePnPGeneric(obj, c, K, D, flags=cv2.SOLVEPNP_SQPNP)
            if (m and float(np.min(er2)) < best) or not math.isfinite(best):
                n, rvecs, tvecs, errs = m, rv2, tv2, er2
    if not n:
        return None
    rv = np.asarray(rvecs, dtype=np.float64).reshape(-1, 3)[:2]
    R2 = [cv2.Rodrigues(r)[0] for r in rv]
    t2 = list(np.asarray(tvecs, dtype=np.float64).reshape(-1, 3)[:2])
    e2 = np.asarray(errs, dtype=np.float64).reshape(-1)[:2].tolist()
    if len(R2) == 1:
        R2.append(R2[0])
        t2.append(t2[0])
        e2.append(e2[0])
    if e2[1] < e2[0]:  # OpenCV sorts them; do not rely on it
        R2, t2, e2 = R2[::-1], t2[::-1], e2[::-1]
    return np.array(R2), np.array(t2), np.array(e2)


def _ippe_square(corners: np.ndarray, half: np.ndarray, K: np.ndarray, D: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Both ``SOLVEPNP_IPPE_SQUARE`` solutions of every marker at once.

    corners: (N, 4, 2) px; half: (N,) half side (m). Returns R (N, 2, 3, 3) marker2cam,
    t (N, 2, 3) m and RMS reprojection errors (N, 2) px, lowest error first, equal to
    ``cv2.solvePnPGeneric(..., SOLVEPNP_IPPE_SQUARE)`` to rounding (same steps as OpenCV's
    ippe.cpp: undistorted corners, closed-form square homography, the two rotations from its
    Jacobian at the centre, least-squares translations, rotation vectors and back, projection
    with distortion). None when the distortion model has a tilted sensor (not replicated).
    Degenerate markers come out non-finite; the caller re-solves those with OpenCV.
    """
    D = D.reshape(-1)
    if D.size > 12 and np.any(D[12:] != 0.0):
        return None
    N = len(corners)
    u = cv2.undistortPoints(np.ascontiguousarray(corners.reshape(-1, 1, 2)), K, D
                            ).reshape(N, 4, 2)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        p1x, p1y = -u[:, 0, 0], -u[:, 0, 1]
        p2x, p2y = -u[:, 1, 0], -u[:, 1, 1]
        p3x, p3y = -u[:, 2, 0], -u[:, 2, 1]
        p4x, p4y = -u[:, 3, 0], -u[:, 3, 1]
        hl = half
        dets_inv = -1 / (hl * (p1x * p2y - p2x * p1y - p1x * p4y + p2x * p3y - p3x * p2y
                               + p4x * p1y + p3x * p4y - p4x * p3y))
        h00 = dets_inv * (p1x * p3x * p2y - p2x * p3x * p1y - p1x * p4x * p2y + p2x * p4x * p1y
                          - p1x * p3x * p4y + p1x * p4x * p3y + p2x * p3x * p4y
                          - p2x * p4x * p3y)
        h01 = dets_inv * (p1x * p2x * p3y - p1x * p3x * p2y - p1x * p2x * p4y + p2x * p4x * p1y
                          + p1x * p3x * p4y - p3x * p4x * p1y - p2x * p4x * p3y
                          + p3x * p4x * p2y)
        h02 = dets_inv * hl * (p1x * p2x * p3y - p2x * p3x * p1y - p1x * p2x * p4y
                               + p1x * p4x * p2y - p1x * p4x * p3y + p3x * p4x * p1y
                               + p2x * p3x * p4y - p3x * p4x * p2y)
        h10 = dets_inv * (p1x * p2y * p3y - p2x * p1y * p3y - p1x * p2y * p4y + p2x * p1y * p4y
                          - p3x * p1y * p4y + p4x * p1y * p3y + p3x * p2y * p4y
                          - p4x * p2y * p3y)
        h11 = dets_inv * (p2x * p1y * p3y - p3x * p1y * p2y - p1x * p2y * p4y + p4x * p1y * p2y
                          + p1x * p3y * p4y - p4x * p1y * p3y - p2x * p3y * p4y
                          + p3x * p2y * p4y)
        h12 = dets_inv * hl * (p1x * p2y * p3y - p3x * p1y * p2y - p2x * p1y * p4y
                               + p4x * p1y * p2y - p1x * p3y * p4y + p3x * p1y * p4y
                               + p2x * p3y * p4y - p4x * p2y * p3y)
        h20 = -dets_inv * (p1x * p3y - p3x * p1y - p1x * p4y - p2x * p3y + p3x * p2y
                           + p4x * p1y + p2x * p4y - p4x * p2y)
        h21 = dets_inv * (p1x * p2y - p2x * p1y - p1x * p3y + p3x * p1y + p2x * p4y
                          - p4x * p2y - p3x * p4y + p4x * p3y)
        # Jacobian of the homography at the centre, and the centre's image.
        j00, j01 = h00 - h20 * h02, h01 - h21 * h02
        j10, j11 = h10 - h20 * h12, h11 - h21 * h12
        p, q = h02, h12
        # rotateVec2ZAxis((p, q, 1)), transposed.
        nrm = np.sqrt(p * p + q * q + 1.0)
        ax, ay, az = p / nrm, q / nrm, 1.0 / nrm
        d = 1.0 / (1.0 + az)
        ax2, ay2, axay = ax * ax, ay * ay, ax * ay
        rv00, rv01, rv02 = -ax2 * d + 1.0, -axay * d, ax
        rv10, rv11, rv12 = -axay * d, -ay2 * d + 1.0, ay
        rv20, rv21, rv22 = -ax, -ay, 1.0 - (ax2 + ay2) * d
        b00, b01 = rv00 - p * rv20, rv01 - p * rv21
        b10, b11 = rv10 - q * rv20, rv11 - q * rv21
        dtinv = 1.0 / (b00 * b11 - b01 * b10)
        bi00, bi01, bi10, bi11 = dtinv * b11, -dtinv * b01, -dtinv * b10, dtinv * b00
        a00 = bi00 * j00 + bi01 * j10
        a01 = bi00 * j01 + bi01 * j11
        a10 = bi10 * j00 + bi11 * j10
        a11 = bi10 * j01 + bi11 * j11
        ata00 = a00 * a00 + a01 * a01
        ata01 = a00 * a10 + a01 * a11
        ata11 = a10 * a10 + a11 * a11
        gamma = np.sqrt(0.5 * (ata00 + ata11 + np.sqrt((ata00 - ata11) * (ata00 - ata11)
                                                      + 4.0 * ata01 * ata01)))
        r00, r01, r10, r11 = a00 / gamma, a01 / gamma, a10 / gamma, a11 / gamma
        b0 = np.sqrt(-r00 * r00 - r10 * r10 + 1)
        b1 = np.sqrt(-r01 * r01 - r11 * r11 + 1)
        b1 = np.where((-r00 * r01 - r10 * r11) < 0, -b1, b1)
        # R_k = Rv @ M_k with M_k's columns (r00, r10, +-b0), (r01, r11, +-b1), (c0, c1, c2);
        # summed in ippe.cpp's order: near a half turn the rotation vector OpenCV returns is
        # ill-conditioned, so the last bits matter.
        c2 = r00 * r11 - r01 * r10
        col_x0 = np.stack([np.stack([r00, r01, b1 * r10 - b0 * r11], -1),
                           np.stack([r00, r01, b0 * r11 - b1 * r10], -1)], 1)   # (N, 2, 3)
        col_x1 = np.stack([np.stack([r10, r11, b0 * r01 - b1 * r00], -1),
                           np.stack([r10, r11, b1 * r00 - b0 * r01], -1)], 1)
        col_x2 = np.stack([np.stack([b0, b1, c2], -1), np.stack([-b0, -b1, c2], -1)], 1)
        x0 = np.stack([rv00, rv10, rv20], -1)[:, None, :, None]                # (N, 1, 3, 1)
        x1 = np.stack([rv01, rv11, rv21], -1)[:, None, :, None]
        x2 = np.stack([rv02, rv12, rv22], -1)[:, None, :, None]
        R = (col_x0[:, :, None, :] * x0 + col_x1[:, :, None, :] * x1
             + col_x2[:, :, None, :] * x2)                                     # (N, 2, 3, 3)
        # Least-squares translations (computeTranslation), canonical corners = object x, y.
        obj = np.stack([-half, half, half, -half, half, half, -half, -half], 1).reshape(N, 2, 4)
        obj = obj.transpose(0, 2, 1)                                   # (N, 4, 2) x, y
        a2, b2 = -u[:, :, 0], -u[:, :, 1]                              # (N, 4)
        A02 = a2.sum(1)
        A12 = b2.sum(1)
        A22 = (a2 * a2 + b2 * b2).sum(1)
        n = 4.0
        det_inv = 1.0 / (n * n * A22 - n * A12 * A12 - A02 * n * A02)
        S00, S01, S02 = n * A22 - A12 * A12, A02 * A12, -A02 * n
        S10, S11, S12 = A12 * A02, n * A22 - A02 * A02, -n * A12
        S20, S21, S22 = -n * A02, -n * A12, np.full_like(A02, n * n)
        P = np.einsum("nkij,npj->nkpi", R[..., :2], obj)               # (N, 2, 4, 3)
        bx = -a2[:, None] * P[..., 2] - P[..., 0]
        by = -b2[:, None] * P[..., 2] - P[..., 1]
        T0, T1 = bx.sum(2), by.sum(2)
        T2 = (a2[:, None] * bx + b2[:, None] * by).sum(2)
        di = det_inv[:, None]
        t = np.stack([di * (S00[:, None] * T0 + S01[:, None] * T1 + S02[:, None] * T2),
                      di * (S10[:, None] * T0 + S11[:, None] * T1 + S12[:, None] * T2),
                      di * (S20[:, None] * T0 + S21[:, None] * T1 + S22[:, None] * T2)], -1)
        # OpenCV hands out rotation vectors: go through them as it does.
        R = rotvecs_to_matrices(matrices_to_rotvecs(R.reshape(-1, 3, 3))).reshape(N, 2, 3, 3)
        err = _reproj_rms(R, t, obj, corners, K, D)
    swap = err[:, 1] < err[:, 0]
    R[swap] = R[swap][:, ::-1]
    t[swap] = t[swap][:, ::-1]
    err[swap] = err[swap][:, ::-1]
    return R, t, err


def _reproj_rms(R: np.ndarray, t: np.ndarray, obj: np.ndarray, corners: np.ndarray,
                K: np.ndarray, D: np.ndarray) -> np.ndarray:
    """(N, 2) RMS px error of poses R (N, 2, 3, 3), t (N, 2, 3) of the (N, 4, 2) square
    corners, projected as ``cv2.projectPoints`` does (up to 12 distortion coefficients)."""
    k = np.zeros(12)
    k[:D.size] = D[:12]
    X = np.einsum("nkij,npj->nkpi", R[..., :2], obj) + t[:, :, None, :]
    z = np.where(X[..., 2] != 0, 1.0 / X[..., 2], 1.0)
    xy = X[..., :2] * z[..., None]
    xyd = distort(xy.reshape(-1, 2), k).reshape(xy.shape)
    xd, yd = xyd[..., 0], xyd[..., 1]
    u = xd * K[0, 0] + yd * K[0, 1] + K[0, 2]
    v = yd * K[1, 1] + K[1, 2]
    du, dv = u - corners[:, None, :, 0], v - corners[:, None, :, 1]
    return np.sqrt((du * du + dv * dv).sum(axis=2) / 8.0)

def _rot_angles(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Angles (rad) between rotations A (P, 3, 3) and B (Q, 3, 3) -> (P, Q)."""
    tr = np.einsum("pij,qij->pq", A, B)
    return np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0))


def estimate_marker_poses(
    ids: object,
    corners: object,
    camera: CameraModel | CameraIntrinsics,
    lengths: Lengths = None,
    world_map: MarkerMap | None = None,
    default_length: float = 0.06,
    *,
    expected_normals: Mapping[int, np.ndarray | None] | None = None,
    settings: DisambiguationSettings | None = None,
    quality: QualitySettings | None = None,
) -> tuple[list[MarkerObservation], PoseDiagnostics]:
    """Pose of every detected marker in the camera frame (OpenCV axes, metres).

    ids: (N,) ints; corners: (N, 4, 2) pixels (TL, TR, BR, BL; or OpenCV's list of (1, 4, 2)).
    camera: intrinsics at the frame's resolution. lengths: id -> side (m), mapping or
    callable returning None for "don't know"; then the map's length, then ``default_length``.
    world_map: surveyed markers, whose rotations give their expected normals.
    expected_normals: id -> (3,) world normal for markers not in the map (default world +z:
    robots' markers lie flat); a None value means "no assumption" for that id.
    quality: when a marker is flagged ``suspect`` (:class:`QualitySettings`).
    Returns the observations (in input order, minus ``failed_ids``) and the diagnostics.
    """
    s = settings or DisambiguationSettings()
    id_arr, c_arr = _as_inputs(ids, corners)
    length_of = _length_resolver(lengths, world_map, default_length)
    K = np.asarray(camera.camera_matrix, dtype=np.float64)
    D = np.asarray(camera.dist_coeffs, dtype=np.float64)
    diag = PoseDiagnostics()

    # ---- both IPPE solutions of every marker: batched, OpenCV per marker only when needed
    n_in = len(id_arr)
    mids = id_arr.tolist()
    lens: dict[int, float] = {}
    keep_len_all = [lens.setdefault(mid, length_of(mid)) for mid in mids]
    exact = _exact_corners(c_arr, K, D) if n_in else np.zeros(0, bool)
    batched = _ippe_square(c_arr, np.array(keep_len_all) / 2.0, K, D) if n_in else None
    if batched is None:
        R_all = np.full((n_in, 2, 3, 3), np.nan)
        t_all = np.full((n_in, 2, 3), np.nan)
        e_all = np.full((n_in, 2), np.nan)
    else:
        R_all, t_all, e_all = batched
    best_all = e_all[:, 0]
    # IPPE degenerates on some exact (noise-free, synthetic) configurations, e.g. a marker
    # parallel to the image plane: NaN, or both poses wrong by tens of degrees with a
    # sub-pixel error. Real corners (noise >= 1e-3 px) never do. Those markers (and any
    # non-finite batched result) go through OpenCV, with SQPnP (7x slower) as a second try.
    redo = ~(best_all < np.where(exact, 1e-3, _FALLBACK_PX))
    redo |= ~(np.isfinite(R_all).all(axis=(2, 3)) & np.isfinite(t_all).all(axis=2)
              & np.isfinite(e_all)).all(axis=1)
    ok = np.ones(n_in, bool)
    local: dict[float, np.ndarray] = {}
    for i in np.flatnonzero(redo).tolist():
        L = keep_len_all[i]
        obj = local.get(L)
        if obj is None:
            obj = local[L] = marker_corners_local(L)
        got = _solve_one(obj, c_arr[i], K, D, bool(exact[i]))
        if got is None:
            ok[i] = False
            diag.failed_ids.append(mids[i])
        else:
            R_all[i], t_all[i], e_all[i] = got
    keep = np.flatnonzero(ok)
    keep_ids = [mids[i] for i in keep.tolist()]
    kept_corners = c_arr[keep]                                      # (N, 4, 2)
    keep_corners = list(kept_corners)
    keep_len = [keep_len_all[i] for i in keep.tolist()]
    R, t, e = R_all[keep], t_all[keep], e_all[keep]
    # IPPE_SQUARE returns NaN for an exactly fronto-parallel square: keep the finite
    # solution if one is, else the marker has no pose (failed, not a crash).
    finite = (np.isfinite(R).all(axis=(2, 3)) & np.isfinite(t).all(axis=2)
              & np.isfinite(e))
    if not finite.all():
        keep = []
        for i in range(len(keep_ids)):
            if finite[i].all():
                keep.append(i)
            elif finite[i].any():
                k = int(np.argmax(finite[i]))
                R[i], t[i], e[i] = R[i, k], t[i, k], e[i, k]
                keep.append(i)
            else:
                diag.failed_ids.append(keep_ids[i])
        R, t, e = R[keep], t[keep], e[keep]
        keep_ids = [keep_ids[i] for i in keep]
        kept_corners = kept_corners[keep]
        keep_corners = list(kept_corners)
        keep_len = [keep_len[i] for i in keep]
    N = len(keep_ids)
    diag.n_markers = N
    if N == 0:
        return [], diag
    normals = R[:, :, :, 2]     # (N, 2, 3)
    # Facing the camera: the printed face's normal points back along the line of sight.
    facing = np.einsum("nkj,nkj->nk", normals, t) < 0.0
    # IPPE returns the same pose twice for an exactly fronto-parallel marker.
    same = np.einsum("nij,nij->n", R[:, 0], R[:, 1]) > 1.0 + 2.0 * math.cos(math.radians(0.1))
    ratio = (e[:, 1] + s.noise_px) / (e[:, 0] + s.noise_px)
    confident = (ratio >= s.ambiguity_ratio) & facing[:, 0]

    # ---- scene consensus, leave-one-out expected normals (N, 3) in the camera frame
    expected, diag_consensus = _expected_normals(
        keep_ids, R, normals, facing, confident, world_map, expected_normals, s)
    diag.consensus, diag.n_support, diag.world2cam_R, diag.floor_normal = diag_consensus

    # ---- per-marker decision
    obs: list[MarkerObservation] = []
    margin = math.radians(s.margin_deg)
    max_dev = math.radians(s.max_deviation_deg)
    agree = math.radians(s.agree_deg)
    E = np.array([np.full(3, np.nan) if v is None else v for v in expected])
    theta = np.arccos(np.clip(np.einsum("nkj,nj->nk", normals, E), -1.0, 1.0)).tolist()
    n_facing = facing.sum(axis=1).tolist()
    ratios = ratio.tolist()
    same_l = same.tolist()
    flags: list[tuple[int, bool, bool, bool]] = []
    for i in range(N):
        chosen, ambiguous, flipped, conflict = 0, False, False, False
        if same_l[i]:
            pass
        elif n_facing[i] == 1:
            chosen = int(np.argmax(facing[i]))
            flipped = chosen == 1  # the lowest-error one faces away from the camera
        elif n_facing[i] == 0:
            ambiguous = True
        else:
            th0, th1 = theta[i]
            decided = False
            if expected[i] is not None:
                if min(th0, th1) > max_dev:
                    conflict = True
                elif abs(th0 - th1) >= margin:
                    decided = True
                    if th1 < th0:
                        if ratios[i] >= s.decisive_ratio:
                            conflict = True
                        else:
                            chosen, flipped = 1, True
                elif max(th0, th1) <= agree:
                    # Both agree with the scene (nearly face-on): either pose is fine.
                    decided = True
            if conflict:
                ambiguous = True
            elif not decided:
                ambiguous = ratios[i] < s.ambiguity_ratio
        flags.append((chosen, ambiguous, flipped, conflict))
    # One gather for the chosen and alternative solutions of all markers (each observation
    # gets its own rows of these fresh arrays: no per-marker copies).
    rows = np.arange(N)
    ch = np.array([f[0] for f in flags], dtype=np.intp)
    Rc, tc, ec = R[rows, ch], t[rows, ch], e[rows, ch]
    Ra, ta, ea = R[rows, 1 - ch], t[rows, 1 - ch], e[rows, 1 - ch]
    sus = _suspect_mask(ec, kept_corners, camera, quality or QualitySettings()).tolist()
    ec_l, ea_l = ec.tolist(), ea.tolist()
    for i, mid in enumerate(keep_ids):
        chosen, ambiguous, flipped, conflict = flags[i]
        has_alt = not same_l[i]
        obs.append(MarkerObservation(
            id=mid,
            marker2cam_R=Rc[i],
            marker2cam_t=tc[i],
            corners=keep_corners[i],
            length=keep_len[i],
            reproj_error=ec_l[i],
            alt_R=Ra[i] if has_alt else None,
            alt_t=ta[i] if has_alt else None,
            alt_reproj_error=ea_l[i] if has_alt else math.nan,
            ambiguous=ambiguous,
            flipped=flipped,
            suspect=sus[i],
        ))
        if ambiguous:
            diag.n_ambiguous += 1
            diag.ambiguous_by_id[mid] = diag.ambiguous_by_id.get(mid, 0) + 1
        if flipped:
            diag.n_flipped += 1
            diag.flips_by_id[mid] = diag.flips_by_id.get(mid, 0) + 1
        if conflict:
            diag.n_conflicts += 1
            diag.conflicts_by_id[mid] = diag.conflicts_by_id.get(mid, 0) + 1
        if sus[i]:
            diag.n_suspect += 1
            diag.suspect_by_id[mid] = diag.suspect_by_id.get(mid, 0) + 1
    return obs, diag


def _suspect_mask(err: np.ndarray, corners: np.ndarray,
                  camera: CameraModel | CameraIntrinsics, q: QualitySettings) -> np.ndarray:
    """(N,) bool: the quadrilateral is not trustworthy (module docstring). err: (N,) RMS px
    of the chosen poses; corners: (N, 4, 2) px."""
    if not len(err):
        return np.zeros(0, bool)
    bar = max(q.floor_px, q.ratio * float(np.median(err)))
    bad = ~(err <= bar)  # NaN is suspect too
    w, h = getattr(camera, "width", 0), getattr(camera, "height", 0)
    if w and h and q.border_px > 0:
        c = corners.reshape(-1, 4, 2)
        b = q.border_px
        # Pixel centres at integer coordinates: the image spans -0.5 .. w - 0.5.
        near = ((c[..., 0] < b - 0.5) | (c[..., 0] > w - 0.5 - b)
                | (c[..., 1] < b - 0.5) | (c[..., 1] > h - 0.5 - b)).any(axis=1)
        bad |= near
    return bad


def _expected_normals(
    ids: list[int], R: np.ndarray, normals: np.ndarray, facing: np.ndarray,
    confident: np.ndarray, world_map: MarkerMap | None,
    expected_normals: Mapping[int, np.ndarray | None] | None, s: DisambiguationSettings,
) -> tuple[list[np.ndarray | None], tuple[str, int, np.ndarray | None, np.ndarray | None]]:
    """Per-marker expected normal in the camera frame (or None) and the consensus summary."""
    N = len(ids)
    kernel = math.radians(s.kernel_deg)
    extra = expected_normals or {}

    def world_normal(mid: int) -> np.ndarray | None:
        if world_map is not None and mid in world_map:
            return world_map[mid].rotation[:, 2]
        if mid in extra:
            v = extra[mid]
            if v is None:
                return None
            v = np.asarray(v, dtype=float).reshape(3)
            return v / np.linalg.norm(v)
        return _Z

    in_map = [i for i, mid in enumerate(ids) if world_map is not None and mid in world_map]
    if in_map:
        # Candidate world2cam rotations of the map markers: (M, 2, 3, 3).
        Rw = np.array([world_map[ids[i]].rotation for i in in_map])  # type: ignore[index]
        cand = np.einsum("mkij,mlj->mkil", R[in_map], Rw)
        votes = _vote(cand.reshape(-1, 3, 3), facing[in_map], confident[in_map], kernel,
                      _rot_angles)
        if votes is not None:
            pick, inlier = votes
            chosen = cand[np.arange(len(in_map)), pick]            # (M, 3, 3)
            total = chosen[inlier].sum(axis=0)
            n_in = int(inlier.sum())
            mean = project_to_so3(total)
            # A single voter is trusted only if its own errors were decisive.
            decisive = confident[in_map] & (pick == 0) & inlier
            # Leave-one-out consensus for each inlier map marker.
            loo_all = project_to_so3(total[None] - chosen)    # one batched SVD
            loo = {}
            for j, i in enumerate(in_map):
                if inlier[j]:
                    others = n_in - 1
                    sole_ok = others == 1 and bool(np.delete(decisive, j).any())
                    loo[i] = loo_all[j] if others >= 2 or sole_ok else None
            trusted_all = n_in >= 2 or bool(decisive.any())
            out: list[np.ndarray | None] = []
            for i, mid in enumerate(ids):
                nw = world_normal(mid)
                rot = loo.get(i, mean if trusted_all else None)
                out.append(None if nw is None or rot is None else rot @ nw)
            return out, ("map", n_in, mean, mean[:, 2].copy())
    # No map marker: vote for the floor normal among markers assumed horizontal.
    horiz = [i for i, mid in enumerate(ids)
             if (w := world_normal(mid)) is not None and w[2] > 1.0 - 1e-9]
    if len(horiz) < 2:
        return [None] * N, ("none", 0, None, None)
    cand_n = normals[horiz]                                         # (H, 2, 3)

    def normal_angles(A: np.ndarray, B: np.ndarray) -> np.ndarray:
        return np.arccos(np.clip(A @ B.T, -1.0, 1.0))

    votes = _vote(cand_n.reshape(-1, 3), facing[horiz], confident[horiz], kernel, normal_angles)
    if votes is None:
        return [None] * N, ("none", 0, None, None)
    pick, inlier = votes
    chosen_n = cand_n[np.arange(len(horiz)), pick]
    total = chosen_n[inlier].sum(axis=0)
    n_in = int(inlier.sum())
    decisive = confident[horiz] & (pick == 0) & inlier
    out: list[np.ndarray | None] = [None] * N
    for j, i in enumerate(horiz):
        others = n_in - int(inlier[j])
        # A single other voter is trusted only if its own errors were decisive.
        if others >= 2 or (others == 1 and bool(np.delete(decisive, j).any())):
            v = total - chosen_n[j] if inlier[j] else total
            out[i] = v / np.linalg.norm(v)
    g = total / np.linalg.norm(total)
    return out, ("horizontal", n_in, None, g)


def _vote(cands: np.ndarray, facing: np.ndarray, confident: np.ndarray, kernel: float,
          angles: Callable[[np.ndarray, np.ndarray], np.ndarray],
          ) -> tuple[np.ndarray, np.ndarray] | None:
    """Robust mode of per-marker candidate pairs.

    cands: (2M, ...) candidates, marker m's at 2m and 2m+1 (lowest error first).
    Returns (pick (M,) index 0/1 of each marker's candidate nearest the winner, inlier (M,)
    bool), or None when no candidate faces the camera.
    """
    M = facing.shape[0]
    valid = facing.reshape(-1)
    if not valid.any():
        return None
    A = angles(cands, cands).reshape(2 * M, M, 2)                 # seed x marker x candidate
    A = np.where(facing[None, :, :], A, np.inf)
    # Two candidates: elementwise min/compare beat a reduction over an axis of length 2.
    nearest = np.minimum(A[..., 0], A[..., 1])                     # (2M, M)
    # One vote per marker; a decisive lowest-error candidate counts a little more, so ties
    # between the two mirror families go to the photometrically better one.
    weight = np.where(confident, 1.05, 1.0)
    score = ((nearest < kernel) * weight[None, :]).sum(axis=1) - 1e-3 * np.where(
        np.isfinite(nearest), np.minimum(nearest, kernel), kernel).sum(axis=1)
    score = np.where(valid, score, -np.inf)
    seed = int(np.argmax(score))
    pick = (A[seed, :, 1] < A[seed, :, 0]).astype(np.intp)  # = argmin, first on ties
    inlier = nearest[seed] < kernel
    # Two refinement passes around the mean of the inliers.
    for _ in range(2):
        sel = cands.reshape(M, 2, *cands.shape[1:])[np.arange(M), pick][inlier]
        if sel.ndim == 3:
            centre = project_to_so3(sel.sum(axis=0))[None]
        else:
            v = sel.sum(axis=0)
            centre = (v / np.linalg.norm(v))[None]
        A2 = angles(centre, cands).reshape(M, 2)
        A2 = np.where(facing, A2, np.inf)
        pick = (A2[:, 1] < A2[:, 0]).astype(np.intp)
        inlier = np.minimum(A2[:, 0], A2[:, 1]) < kernel
        if not inlier.any():
            return None
    return pick, inlier
