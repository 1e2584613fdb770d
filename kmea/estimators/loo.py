"""Leave-one-out errors: each observed map marker estimated with itself left out.

The paper evaluates every marker this way, "since it would be disingenuous to estimate its
pose if it used its ground truth pose". Numpy only.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from kmea.estimators.base import CameraIntrinsics, Estimator, MarkerObservation
from kmea.maps import MarkerMap

__all__ = ["loo_errors", "loo_positions"]


def loo_positions(estimator: Estimator, observations: Sequence[MarkerObservation],
                  world_map: MarkerMap, camera: CameraIntrinsics | None = None,
                  plane_heights: Mapping[int, float] | None = None) -> dict[int, np.ndarray]:
    """id -> (3,) world position (m) of each observed map marker, estimated with that marker
    excluded from the references; markers whose estimate fails are omitted.

    Uses ``estimator.estimate_loo`` when the estimator has one (KMEA: all at once).
    """
    fast = getattr(estimator, "estimate_loo", None)
    if fast is not None:
        return fast(observations, world_map, camera=camera, plane_heights=plane_heights)
    out: dict[int, np.ndarray] = {}
    for o in observations:
        if o.id not in world_map or o.suspect:  # never a reference: no statistics either
            continue
        est = estimator.estimate(observations, world_map, exclude=(o.id,), camera=camera,
                                 plane_heights=plane_heights)
        if est.ok and o.id in est.markers:
            out[o.id] = est.markers[o.id].position
    return out


def loo_errors(estimator: Estimator, observations: Sequence[MarkerObservation],
               world_map: MarkerMap, camera: CameraIntrinsics | None = None,
               plane_heights: Mapping[int, float] | None = None) -> dict[int, float]:
    """id -> floor-plane error (m): |(x, y) estimated with the marker left out - (x, y) in
    the map|, for each observed map marker; markers not estimable without themselves
    (too few references, or an LMEA anchor) are omitted."""
    pos = loo_positions(estimator, observations, world_map, camera, plane_heights)
    return {mid: float(np.hypot(*(p[:2] - world_map[mid].position[:2])))
            for mid, p in sorted(pos.items())}
