"""KMEA, the Kabsch Marker Estimation Algorithm (the paper's Algorithm 2), numpy only.

Steps, on the references (observed markers that are in the map and not excluded):

1. scale = mean distance of the references to the origin marker in the map / the same mean
   in the camera frame. When the origin marker is not a reference (not visible, or
   excluded), the reference centroid stands in for it: map centroid in the map, camera
   centroid in the camera frame (for an exact similarity both give the true scale).
2. Scale the camera positions.
3. Kabsch rotation between the scaled camera positions and the map positions, both about
   their centroids; if det(R) < 0, flip the last axis.
4. t = map centroid - R @ scaled camera centroid; every detected marker is transformed.

Option ``unknown_plane`` ("free" by default, the paper's: a marker not in the map and not
given a height keeps its own PnP pose moved by the alignment; "floor" or "auto": see
:mod:`kmea.estimators.unknown_plane`).

Option ``z_noise``: the paper adds uniform noise in [-z_noise, +z_noise] m (1e-4 in the
paper) to the map z of the references against coplanar degeneracy. Off by default: the
determinant correction of step 3 already handles coplanar references.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence

import numpy as np

from kmea.estimators.base import (
    CheckedObservations,
    Estimate,
    EstimatorBase,
    MarkerObservation,
    check_observations,
    loo_by_exclusion,
)
from kmea.estimators.common import (
    COINCIDENT_TOL,
    COLLINEAR_TOL,
    References,
    finish_estimate,
    reference_problem,
    select_references,
)
from kmea.estimators.unknown_plane import check_mode
from kmea.geometry import kabsch
from kmea.geometry.camera import CameraIntrinsics
from kmea.maps.model import MarkerMap

__all__ = ["KMEA", "kmea_align"]

# Leave-one-out works on (chunk, N, 3) arrays; this bounds their size for big maps.
_LOO_CHUNK = 128


def kmea_align(cam: np.ndarray, world: np.ndarray, ids: Sequence[int], origin_id: int
               ) -> tuple[float, np.ndarray, np.ndarray]:
    """Steps 1-4 of the module docstring: camera positions cam (N, 3) onto map positions
    world (N, 3), row i being marker ``ids[i]``. Returns (scale, R (3, 3), t (3,)) with
    ``world = scale R cam + t``; the references' centroid stands in for ``origin_id`` when it
    is not among ``ids``.
    """
    ids = list(ids)
    if origin_id in ids:
        o = ids.index(origin_id)
        c0, w0 = cam[o], world[o]
    else:
        c0, w0 = cam.mean(axis=0), world.mean(axis=0)
    scale = float(np.linalg.norm(world - w0, axis=1).mean()
                  / np.linalg.norm(cam - c0, axis=1).mean())
    cam_s = scale * cam
    cs, ws = cam_s.mean(axis=0), world.mean(axis=0)
    R = kabsch((cam_s - cs).T @ (world - ws))
    return scale, R, ws - R @ cs


class KMEA(EstimatorBase):
    """The paper's Algorithm 2. See the module docstring for the steps."""

    name = "kmea"

    def __init__(self, z_noise: float = 0.0, seed: int | None = None,
                 unknown_plane: str = "free", plane_level: float = 0.999) -> None:
        self.unknown_plane = check_mode(self.name, unknown_plane)
        self.plane_level = float(plane_level)
        if not (np.isfinite(z_noise) and z_noise >= 0.0):
            raise ValueError(f"z_noise must be a finite number >= 0 m, got {z_noise!r}")
        self.z_noise = float(z_noise)
        self.seed = seed
        self._rng = np.random.default_rng(seed)
        # Warm start (a fixed live camera, set by kmea.pipeline): while the references'
        # observations are the very objects of the last call (kmea.fixed_camera reuses a
        # floor marker's), their alignment is the last one; only the markers are mapped.
        self.warm_start = False
        self._check = CheckedObservations()
        self._warm: tuple | None = None  # (map, exclude, reference observations, alignment)

    def reset_warm(self) -> None:
        """Forget the last alignment (the view changed)."""
        self._warm = None
        self._check.reset()

    def _world(self, refs: References) -> np.ndarray:
        if self.z_noise == 0.0 or len(refs) == 0:
            return refs.world
        w = refs.world.copy()
        w[:, 2] += self._rng.uniform(-self.z_noise, self.z_noise, size=len(w))
        return w

    def estimate(
        self,
        observations: Sequence[MarkerObservation],
        world_map: MarkerMap,
        exclude: Collection[int] = (),
        camera: CameraIntrinsics | None = None,
        plane_heights: Mapping[int, float] | None = None,
    ) -> Estimate:
        """World pose of every observed marker; see :class:`kmea.estimators.base.Estimator`."""
        warm = self.warm_start and self.z_noise == 0.0
        observations = self._check(observations) if warm else check_observations(observations)
        excl = frozenset(exclude)
        key = None
        if warm:
            key = tuple(sorted((o for o in observations if o.id in world_map
                                and o.id not in excl and not o.suspect), key=lambda o: o.id))
            w = self._warm
            if (w is not None and w[0] is world_map and w[1] == excl and len(w[2]) == len(key)
                    and all(a is b for a, b in zip(w[2], key, strict=True))):
                refs, scale, R, t = w[3]
                return self._finish(observations, world_map, refs, scale, R, t, camera,
                                    plane_heights)
        refs = select_references(observations, world_map, exclude)
        world = self._world(refs)
        problem = reference_problem(world, refs.cam)
        if problem:
            return Estimate.failed(self.name, problem)
        scale, R, t = kmea_align(refs.cam, world, refs.ids, world_map.origin_id)
        if key is not None:
            self._warm = (world_map, excl, key, (refs, scale, R, t))
        return self._finish(observations, world_map, refs, scale, R, t, camera, plane_heights)

    def _finish(self, observations, world_map: MarkerMap, refs, scale: float, R: np.ndarray,
                t: np.ndarray, camera: CameraIntrinsics | None,
                plane_heights: Mapping[int, float] | None) -> Estimate:
        scale_from = "origin" if world_map.origin_id in refs.ids else "centroid"
        return finish_estimate(self.name, observations, refs, scale, R, t, plane_heights,
                               info={"scale_from": scale_from},
                               unknown=(world_map, camera, self.unknown_plane,
                                        self.plane_level))

    def _loo_positions(self, observations: Sequence[MarkerObservation], world_map: MarkerMap,
                       ids: list[int], exclude: Collection[int],
                       camera: CameraIntrinsics | None,
                       plane_heights: Mapping[int, float] | None
                       ) -> tuple[dict[int, np.ndarray], dict[int, str]]:
        """Leave-one-out by the definition (:func:`kmea.estimators.base.loo_by_exclusion`),
        the references' all at once: equal (to rounding) to ``estimate(..., exclude={id})``
        for every id, but the N alignments are computed together (masked sums and one batched
        SVD). Markers the batch does not cover (not references, degenerate without
        themselves, moved to a known plane height, or ``z_noise`` drawing per estimate) go
        through ``estimate`` one by one."""
        observations = check_observations(observations)
        refs = select_references(observations, world_map, exclude)
        heights = plane_heights or {}
        fast: dict[int, np.ndarray] = {}
        n = len(refs)
        if n >= 4 and self.z_noise == 0.0:
            want = set(ids)
            o = refs.index(world_map.origin_id)
            for k0 in range(0, n, _LOO_CHUNK):
                ks = np.arange(k0, min(n, k0 + _LOO_CHUNK))
                pos, ok = _loo_chunk(ks, refs.cam, refs.world, o)
                for k, p, good in zip(ks, pos, ok, strict=True):
                    mid = refs.ids[k]
                    if good and mid in want and mid not in heights:
                        fast[mid] = p
        rest = [i for i in ids if i not in fast]
        pos, fail = loo_by_exclusion(self, observations, world_map, rest, exclude, camera,
                                     plane_heights)
        pos.update(fast)
        return pos, fail


def _masked_centroid(W: np.ndarray, P: np.ndarray, m: float) -> np.ndarray:
    # W holds exact zeros for left-out rows, so a left-out value never leaks into a sum.
    return (W @ P) / m


def _loo_chunk(ks: np.ndarray, cam: np.ndarray, world: np.ndarray,
               o: int | None) -> tuple[np.ndarray, np.ndarray]:
    """Positions (K, 3) of markers ``ks`` each estimated without itself, and an ok mask (K,)."""
    n = len(cam)
    K = len(ks)
    m = n - 1
    W = np.ones((K, n))
    W[np.arange(K), ks] = 0.0
    ca = _masked_centroid(W, cam, m)  # (K, 3) camera centroids without k
    wa = _masked_centroid(W, world, m)
    Cc = cam[None, :, :] - ca[:, None, :]  # (K, N, 3)
    Wc = world[None, :, :] - wa[:, None, :]
    Cc *= W[:, :, None]
    Wc *= W[:, :, None]

    # Degeneracy of each reduced set, the same test as reference_problem.
    ok = np.ones(K, dtype=bool)
    for P in (Wc, Cc):
        s = np.sqrt(np.clip(np.linalg.eigvalsh(np.swapaxes(P, 1, 2) @ P), 0.0, None))[:, ::-1]
        ok &= (s[:, 0] > COINCIDENT_TOL) & (s[:, 1] > COLLINEAR_TOL * s[:, 0])

    # Scale: distances to the origin marker, or to the centroid when the origin is left out.
    dm_c = (np.linalg.norm(Wc, axis=2)).sum(axis=1)
    dc_c = (np.linalg.norm(Cc, axis=2)).sum(axis=1)
    scale = dm_c / np.where(dc_c > 0, dc_c, np.nan)
    if o is not None:
        dm_o = np.linalg.norm(world - world[o], axis=1)
        dc_o = np.linalg.norm(cam - cam[o], axis=1)
        use = ks != o
        so = (W @ dm_o) / np.where((W @ dc_o) > 0, W @ dc_o, np.nan)
        scale = np.where(use, so, scale)

    H = np.swapaxes(Cc, 1, 2) @ Wc  # (K, 3, 3); a positive scale does not change Kabsch's R
    R = kabsch(H)
    t = wa - scale[:, None] * np.einsum("kij,kj->ki", R, ca)
    pos = scale[:, None] * np.einsum("kij,kj->ki", R, cam[ks]) + t
    ok &= np.isfinite(pos).all(axis=1) & np.isfinite(scale) & (scale > 0)
    return pos, ok
