"""The warm start of ``corner-pnp`` for a fixed camera: the last fit, kept with what it was
solved for, and the checks that say when it still answers."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kmea.estimators.base import MarkerObservation
from kmea.estimators.corner_pnp.fit import CameraFit
from kmea.geometry import check_distortion
from kmea.geometry.camera import CameraIntrinsics

CameraKey = tuple[bytes, bytes]  # (camera matrix bytes, distortion bytes), float64


@dataclass(frozen=True)
class WarmFit:
    """The last fit kept for the warm start (a fixed camera, :mod:`kmea.fixed_camera`).

    map_id: id of the map it was solved for; camera: its intrinsics as checked
    (:data:`CameraKey`); refs, uv: its references and their stacked corners (4 rows each,
    px); inliers, dis: its consensus and each reference's disagreement (m); ref_obs,
    intrinsics: the observation objects and the intrinsics object of the last call that
    returned it (the very objects: nothing to check again).
    """

    map_id: int
    camera: CameraKey
    refs: list[int]
    uv: np.ndarray
    fit: CameraFit
    inliers: tuple[int, ...]
    dis: dict[int, float]
    ref_obs: tuple[MarkerObservation, ...] = ()
    intrinsics: CameraIntrinsics | None = None


class SameCamera:
    """Is a camera the one of the warm fit: the same object, or the same numbers (a camera
    model hands out a new intrinsics object per call)? The last camera's arrays as given
    (bytes, dtype, shape) are kept with their checked form, so the usual call only compares
    bytes."""

    def __init__(self) -> None:
        self._last: tuple[tuple, CameraKey] | None = None

    def __call__(self, w: WarmFit, camera: CameraIntrinsics) -> bool:
        if w.intrinsics is camera:
            return True
        K, d = np.asarray(camera.camera_matrix), np.asarray(camera.dist_coeffs)
        raw = (K.dtype.str, K.shape, K.tobytes(), d.dtype.str, d.shape, d.tobytes())
        last = self._last
        if last is None or last[0] != raw:
            try:
                key = (np.asarray(K, dtype=float).tobytes(), check_distortion(d).tobytes())
            except (ValueError, TypeError):
                return False
            self._last = last = (raw, key)
        return last[1] == w.camera


def warm_subset(warm: WarmFit, refs: list[int], uv_refs: np.ndarray, min_references: int
                ) -> list[int] | None:
    """The previous fit's inliers among ``refs`` when ``refs`` are some of the previous
    fit's references with bit-identical corners (markers hidden, e.g. by a passing robot,
    and nothing else changed: the fit of the larger set stands); None otherwise."""
    old = {i: k for k, i in enumerate(warm.refs)}
    if len(refs) >= len(old) or any(i not in old for i in refs):
        return None
    prev = warm.uv.reshape(-1, 4, 2)
    rows = [old[i] for i in refs]
    if not np.array_equal(prev[rows], uv_refs.reshape(-1, 4, 2)):
        return None
    inl = [i for i in refs if i in warm.inliers]
    return inl if len(inl) >= min_references else None
