"""Leave-one-out errors: each observed map marker estimated with itself left out.

The paper evaluates every marker this way, "since it would be disingenuous to estimate its
pose if it used its ground truth pose". The one definition and the estimator call that
computes it (``Estimator.estimate_with_loo``) are in :mod:`kmea.estimators.base`; these
are shorthands for callers that want only the leave-one-out part. Numpy only.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from kmea.estimators.base import Estimator, MarkerObservation
from kmea.geometry.camera import CameraIntrinsics
from kmea.maps.model import MarkerMap

__all__ = ["loo_errors", "loo_positions"]


def loo_positions(estimator: Estimator, observations: Sequence[MarkerObservation],
                  world_map: MarkerMap, camera: CameraIntrinsics | None = None,
                  plane_heights: Mapping[int, float] | None = None) -> dict[int, np.ndarray]:
    """id -> (3,) world position (m) of each observed, non-suspect map marker estimated with
    that marker excluded from the references; markers whose estimate fails are omitted."""
    return estimator.estimate_with_loo(observations, world_map, camera=camera,
                                       plane_heights=plane_heights).loo_positions


def loo_errors(estimator: Estimator, observations: Sequence[MarkerObservation],
               world_map: MarkerMap, camera: CameraIntrinsics | None = None,
               plane_heights: Mapping[int, float] | None = None) -> dict[int, float]:
    """id -> floor-plane error (m): |(x, y) estimated with the marker left out - (x, y) in
    the map|, for each observed map marker; markers not estimable without themselves
    (too few references, or an LMEA anchor) are omitted."""
    return estimator.estimate_with_loo(observations, world_map, camera=camera,
                                       plane_heights=plane_heights).loo_errors
