"""Umeyama (1991): the closed-form least-squares similarity over all references, numpy only.

Minimises sum_i || world_i - (s R cam_i + t) ||^2 over scale s > 0, proper rotation R and
translation t: with centred sets and Sigma = (1/N) sum world_c cam_c^T = U D V^T,
S = diag(1, 1, det(U) det(V)), R = U S V^T, s = trace(D S) / var(cam), t = mean(world) -
s R mean(cam).
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence

import numpy as np

from kmea.estimators.base import Estimate, EstimatorBase, MarkerObservation, check_observations
from kmea.estimators.common import finish_estimate, reference_problem, select_references
from kmea.estimators.unknown_plane import check_mode
from kmea.geometry.camera import CameraIntrinsics
from kmea.maps.model import MarkerMap

__all__ = ["Umeyama", "umeyama", "umeyama_batch"]


def umeyama(cam: np.ndarray, world: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(scale, R (3, 3), t (3,)) of the least-squares similarity cam -> world, (N, 3) each."""
    s, R, t = umeyama_batch(cam[None], world[None])
    return float(s[0]), R[0], t[0]


def umeyama_batch(P: np.ndarray, Q: np.ndarray, w: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted least-squares similarities ``Q ~ s R P + t`` for a batch of point sets.

    P, Q: (M, K, 3); w: (M, K) non-negative weights or None. Returns s (M,), R (M, 3, 3),
    t (M, 3). Degenerate sets give whatever the SVD gives; callers check collinearity.
    """
    P = np.asarray(P, dtype=float)
    Q = np.asarray(Q, dtype=float)
    weights = np.ones(P.shape[:2]) if w is None else np.asarray(w, dtype=float)
    wc = (weights / np.maximum(weights.sum(axis=1, keepdims=True), 1e-300))[:, :, None]
    mp = (wc * P).sum(axis=1)
    mq = (wc * Q).sum(axis=1)
    Pc = P - mp[:, None, :]
    Qc = Q - mq[:, None, :]
    C = np.swapaxes(wc * Qc, 1, 2) @ Pc  # (M, 3, 3) cross-covariance, map x camera
    U, S, Vt = np.linalg.svd(C)
    d = np.sign(np.linalg.det(U @ Vt))
    d[d == 0] = 1.0
    U[:, :, 2] *= d[:, None]
    R = U @ Vt
    var_p = (wc * Pc * Pc).sum(axis=(1, 2))
    s = (S[:, 0] + S[:, 1] + d * S[:, 2]) / np.maximum(var_p, 1e-300)
    t = mq - s[:, None] * (R @ mp[:, :, None])[:, :, 0]
    return s, R, t


class Umeyama(EstimatorBase):
    """Least-squares similarity over all references (no anchors needed)."""

    name = "umeyama"

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
        refs = select_references(observations, world_map, exclude)
        problem = reference_problem(refs.world, refs.cam)
        if problem:
            return Estimate.failed(self.name, problem)
        scale, R, t = umeyama(refs.cam, refs.world)
        return finish_estimate(self.name, observations, refs, scale, R, t, plane_heights,
                               unknown=(world_map, camera, self.unknown_plane,
                                        self.plane_level))
