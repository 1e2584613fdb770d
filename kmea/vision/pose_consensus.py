"""The scene consensus that resolves the IPPE two-fold ambiguity: candidate world2cam
rotations (or floor normals) voted robustly, and each marker's expected normal from the
consensus of the OTHER markers (see :mod:`kmea.vision.marker_pose`, steps 1 and 2)."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from kmea.geometry import project_to_so3
from kmea.maps.files import MarkerMap

__all__ = ["DisambiguationSettings", "expected_normals", "rotation_angles", "vote"]

_Z = np.array([0.0, 0.0, 1.0])


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


def rotation_angles(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Angles (rad) between rotations A (P, 3, 3) and B (Q, 3, 3) -> (P, Q)."""
    tr = np.einsum("pij,qij->pq", A, B)
    return np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0))


def expected_normals(
    ids: list[int], R: np.ndarray, normals: np.ndarray, facing: np.ndarray,
    confident: np.ndarray, world_map: MarkerMap | None,
    expected_normals: Mapping[int, np.ndarray | None] | None, s: DisambiguationSettings,
    world2cam: np.ndarray | None = None,
) -> tuple[list[np.ndarray | None], tuple[str, int, np.ndarray | None, np.ndarray | None]]:
    """Per-marker expected normal in the camera frame (or None) and the consensus summary.

    world2cam: (3, 3) a consensus rotation known already (a fixed camera's, from an earlier
    frame): used as it is, no vote (consensus "given")."""
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

    if world2cam is not None:
        R0 = np.asarray(world2cam, dtype=float)
        given = [None if (nw := world_normal(mid)) is None else R0 @ nw for mid in ids]
        return given, ("given", 0, R0, R0[:, 2].copy())
    in_map = [i for i, mid in enumerate(ids) if world_map is not None and mid in world_map]
    if in_map:
        # Candidate world2cam rotations of the map markers: (M, 2, 3, 3).
        Rw = np.array([world_map[ids[i]].rotation for i in in_map])  # type: ignore[index]
        cand = np.einsum("mkij,mlj->mkil", R[in_map], Rw)
        votes = vote(cand.reshape(-1, 3, 3), facing[in_map], confident[in_map], kernel,
                      rotation_angles)
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

    votes = vote(cand_n.reshape(-1, 3), facing[horiz], confident[horiz], kernel, normal_angles)
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


def vote(cands: np.ndarray, facing: np.ndarray, confident: np.ndarray, kernel: float,
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
