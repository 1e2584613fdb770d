"""Per-marker pose in the camera frame, with the IPPE two-fold ambiguity resolved by the scene.

This module is the orchestration (:func:`estimate_marker_poses`); the parts are
:mod:`kmea.vision.ippe` (both poses of every marker), :mod:`kmea.vision.pose_consensus`
(steps 1-2 below) and :mod:`kmea.vision.pose_quality` (``suspect``).

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

import numpy as np

from kmea.estimators.base import MarkerObservation
from kmea.geometry import marker_corners_local
from kmea.geometry.camera import CameraIntrinsics
from kmea.maps.files import MarkerMap
from kmea.vision import pose_consensus
from kmea.vision.camera import CameraModel
from kmea.vision.ippe import (
    FALLBACK_PX,
    exact_corners,
    ippe_pair,
    ippe_square,
    solve_pnp_pair,
)
from kmea.vision.pose_consensus import DisambiguationSettings
from kmea.vision.pose_quality import QualitySettings, suspect_mask

__all__ = ["DisambiguationSettings", "PoseDiagnostics", "QualitySettings", "estimate_marker_poses"]


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


# Up to this many markers a frame, the poses come from OpenCV marker by marker.
SMALL_N = 8


def _per_marker(corners: np.ndarray, lengths: list[float], K: np.ndarray, D: np.ndarray,
                local: dict[float, np.ndarray]
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`~kmea.vision.ippe.ippe_square`'s result from ``cv2.solvePnPGeneric`` with
    ``SOLVEPNP_IPPE_SQUARE`` per marker (no SQPnP fallback here: the caller decides it);
    NaN rows where OpenCV gives nothing."""
    n = len(corners)
    R = np.full((n, 2, 3, 3), np.nan)
    t = np.full((n, 2, 3), np.nan)
    e = np.full((n, 2), np.nan)
    for i in range(n):
        L = lengths[i]
        obj = local.get(L)
        if obj is None:
            obj = local[L] = marker_corners_local(L)
        got = ippe_pair(obj, corners[i], K, D)
        if got is not None:
            R[i], t[i], e[i] = got
    return R, t, e


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
    world2cam_R: np.ndarray | None = None,
) -> tuple[list[MarkerObservation], PoseDiagnostics]:
    """Pose of every detected marker in the camera frame (OpenCV axes, metres).

    ids: (N,) ints; corners: (N, 4, 2) pixels (TL, TR, BR, BL; or OpenCV's list of (1, 4, 2)).
    camera: intrinsics at the frame's resolution. lengths: id -> side (m), mapping or
    callable returning None for "don't know"; then the map's length, then ``default_length``.
    world_map: surveyed markers, whose rotations give their expected normals.
    expected_normals: id -> (3,) world normal for markers not in the map (default world +z:
    robots' markers lie flat); a None value means "no assumption" for that id.
    quality: when a marker is flagged ``suspect`` (:class:`QualitySettings`).
    world2cam_R: (3, 3) the scene's consensus rotation when known already (a fixed camera:
    from an earlier frame, :mod:`kmea.fixed_camera`); the markers' expected normals then
    come from it instead of a vote among these markers.
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
    local: dict[float, np.ndarray] = {}
    # A few markers (a fixed camera's tracked robots): OpenCV per marker is cheaper than the
    # batched replica's fixed cost (0.04 ms a marker against 0.4 ms; same results).
    batched = (_per_marker(c_arr, keep_len_all, K, D, local) if 0 < n_in <= SMALL_N
               else ippe_square(c_arr, np.array(keep_len_all) / 2.0, K, D) if n_in else None)
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
    # Exactness decides only between 1e-3 and FALLBACK_PX px: tested for those alone.
    exact = np.zeros(n_in, bool)
    band = np.flatnonzero((best_all >= 1e-3) & (best_all < FALLBACK_PX))
    if band.size:
        exact[band] = exact_corners(c_arr[band], K, D)
    redo = ~(best_all < np.where(exact, 1e-3, FALLBACK_PX))
    redo |= ~(np.isfinite(R_all).all(axis=(2, 3)) & np.isfinite(t_all).all(axis=2)
              & np.isfinite(e_all)).all(axis=1)
    ok = np.ones(n_in, bool)
    for i in np.flatnonzero(redo).tolist():
        L = keep_len_all[i]
        obj = local.get(L)
        if obj is None:
            obj = local[L] = marker_corners_local(L)
        got = solve_pnp_pair(obj, c_arr[i], K, D, bool(exact[i]))
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
    expected, diag_consensus = pose_consensus.expected_normals(
        keep_ids, R, normals, facing, confident, world_map, expected_normals, s,
        world2cam_R)
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
    sus = suspect_mask(ec, kept_corners, camera, quality or QualitySettings()).tolist()
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
