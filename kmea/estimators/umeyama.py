"""Umeyama (1991): the closed-form least-squares similarity over all references, numpy only.

Minimises sum_i || world_i - (s R cam_i + t) ||^2 over scale s > 0, proper rotation R and
translation t: with centred sets and Sigma = (1/N) sum world_c cam_c^T = U D V^T,
S = diag(1, 1, det(U) det(V)), R = U S V^T, s = trace(D S) / var(cam), t = mean(world) -
s R mean(cam).
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence

import numpy as np

from kmea.estimators.base import (
    CameraIntrinsics,
    Estimate,
    MarkerObservation,
    check_observations,
)
from kmea.estimators.common import finish_estimate, reference_problem, select_references
from kmea.maps import MarkerMap

__all__ = ["Umeyama", "umeyama"]


def umeyama(cam: np.ndarray, world: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(scale, R (3, 3), t (3,)) of the least-squares similarity cam -> world, (N, 3) each."""
    mc, mw = cam.mean(axis=0), world.mean(axis=0)
    C, Wd = cam - mc, world - mw
    sigma = Wd.T @ C / len(cam)
    U, D, Vt = np.linalg.svd(sigma)
    S = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        S[2] = -1.0
    R = (U * S) @ Vt
    var_c = (C**2).sum() / len(cam)
    scale = float((D * S).sum() / var_c)
    return scale, R, mw - scale * (R @ mc)


class Umeyama:
    """Least-squares similarity over all references (no anchors needed)."""

    name = "umeyama"

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
        return finish_estimate(self.name, observations, refs, scale, R, t, plane_heights)
