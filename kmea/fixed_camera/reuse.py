"""What a fixed camera's floor markers let the pipeline reuse from frame to frame.

With :mod:`kmea.fixed_camera.detector` a floor marker that did not move is reported with
the same corners, bit for bit, frame after frame. What depends only on those corners is
then the same too, and is reused instead of recomputed:

- its camera-frame pose (:class:`IncrementalPoses`): only markers with new corners (the
  robots, a marker that reappeared) are posed. When only moving markers are new, the IPPE
  choice of each leans on the scene's consensus rotation kept from the last frame whose
  fixed markers were posed (the camera is fixed: it is still the scene's); when fixed
  markers are new too, a few unchanged floor markers are posed with them as anchors;
- the leave-one-out errors of the floor (:class:`IncrementalLoo`): they depend only on the
  map markers' observations (robots are never references), so while those are the same
  (the same ``version``) the last errors are exactly what a recomputation would give. They
  are recomputed when any map marker's observation changes, and at least every ``every``
  frames.

What "the same" means is explicit: an observation's ``version`` (new at every
construction), never object identity.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import replace

import numpy as np

from kmea.estimators.base import MarkerObservation

__all__ = ["IncrementalLoo", "IncrementalPoses", "PoseFn"]

# pose(ids, corners, world2cam_R or None) -> (observations, diagnostics)
PoseFn = Callable[..., tuple[list[MarkerObservation], dict]]


class IncrementalPoses:
    """Camera-frame poses, reusing those of fixed markers whose corners did not change.

    fixed: ids of markers that do not move (the map's floor and wall markers, not the
    robots'); anchors: how many unchanged fixed markers are posed with the changed ones.
    reuse_px: a fixed marker whose corners moved by at most this (px, each coordinate) from
    those of its last pose keeps that pose with its new corners (0: off). For estimators
    that fit the corners themselves (corner-pnp): one more averaged look moves a floor
    reference by 0.005-0.05 px, far below the corner noise that sets a pose's error, and
    re-posing the whole floor costs 2-4 ms; the pose's ``reproj_error`` is then the one
    of the posed corners.
    ``posed`` / ``reused`` / ``refreshed`` (poses kept with new corners) count markers
    over the run.
    """

    def __init__(self, fixed: Collection[int] = (), anchors: int = 4,
                 reuse_px: float = 0.0) -> None:
        self.fixed = frozenset(fixed)
        self.anchors = anchors
        self.reuse_px = float(reuse_px)
        # id -> (the corners' bytes, the observation, the corners it was posed from)
        self._cache: dict[int, tuple[bytes, MarkerObservation, np.ndarray]] = {}
        self._diag: dict = {}
        self.posed = 0
        self.reused = 0
        self.refreshed = 0

    def reset(self, fixed: Collection[int] | None = None) -> None:
        self._cache.clear()
        self._diag = {}
        if fixed is not None:
            self.fixed = frozenset(fixed)

    def fixed_changed(self, ids: np.ndarray, corners: np.ndarray) -> bool:
        """Does a fixed marker of ``ids`` come with corners other than its cached pose's
        (a new reference, one more averaged look, a marker back in view)?"""
        for mid, c in zip(ids.tolist(), corners, strict=True):
            if mid in self.fixed:
                hit = self._cache.get(mid)
                if hit is None or hit[0] != c.tobytes():
                    return True
        return False

    def poses(self, pose: PoseFn, ids: np.ndarray, corners: np.ndarray,
              known: Mapping[int, MarkerObservation] | None = None
              ) -> tuple[list[MarkerObservation], dict]:
        """Observations of ``ids`` (N,) with ``corners`` (N, 4, 2) px, in input order (minus
        markers without a pose), and the pose diagnostics; ``pose(ids, corners)`` is the
        full computation (:meth:`kmea.pipeline.MarkerObserver.poses`). ``known``: id ->
        observation of this frame posed already (reused when its corners are these)."""
        id_list = [int(i) for i in ids]
        reuse: dict[int, MarkerObservation] = {}
        todo: list[int] = []
        for k, mid in enumerate(id_list):
            hit = self._cache.get(mid)
            if hit is not None and hit[0] == corners[k].tobytes():
                reuse[mid] = hit[1]
            elif (known is not None and (seen := known.get(mid)) is not None
                  and seen.corners is not None and np.array_equal(seen.corners, corners[k])):
                reuse[mid] = seen
            elif (hit is not None and self.reuse_px > 0.0
                  and float(np.abs(corners[k] - hit[2]).max()) <= self.reuse_px):
                o = replace(hit[1], corners=np.array(corners[k], dtype=float))
                self._cache[mid] = (corners[k].tobytes(), o, hit[2])
                reuse[mid] = o
                self.refreshed += 1
            else:
                todo.append(k)
        new: dict[int, MarkerObservation] = {}
        w2c = self._diag.get("world2cam_R") if self._diag.get("consensus") == "map" else None
        if todo and reuse and w2c is not None and all(id_list[k] not in self.fixed
                                                      for k in todo):
            # Only moving markers are new: the fixed camera's consensus rotation (from the
            # last frame whose fixed markers were posed) gives their expected normals; no
            # anchors, no vote.
            got, _ = pose(ids[todo], corners[todo], w2c)
            for o in got:
                new[o.id] = o
        elif todo:
            sel = list(todo)
            if reuse:
                # Anchors: the best-fitting unchanged fixed markers carry the consensus.
                best = sorted((o.reproj_error, mid) for mid, o in reuse.items()
                              if not o.suspect and mid in self.fixed)[:self.anchors]
                index = {mid: k for k, mid in enumerate(id_list)}
                sel += [index[mid] for _, mid in best]
            got, diag = pose(ids[sel], corners[sel])
            by_id = {o.id: o for o in got}
            for k in todo:
                o = by_id.get(id_list[k])
                if o is None:
                    continue
                new[o.id] = o
                if o.id in self.fixed:
                    self._cache[o.id] = (corners[k].tobytes(), o,
                                         np.array(corners[k], dtype=float))
            self._diag = diag
        obs = [reuse.get(mid) or new[mid] for mid in id_list if mid in reuse or mid in new]
        self.posed += len(new)
        self.reused += len(reuse)
        return obs, self._counted(obs)

    def _counted(self, obs: Sequence[MarkerObservation]) -> dict:
        """The last full diagnostics with the per-frame counts taken from ``obs``."""
        d = dict(self._diag)
        d["n_markers"] = len(obs)
        for flag, key in (("ambiguous", "ambiguous"), ("flipped", "flips"),
                          ("suspect", "suspect")):
            by = {o.id: 1 for o in obs if getattr(o, flag)}
            d[f"n_{flag}"] = len(by)
            d[f"{key}_by_id"] = by
        return d


class IncrementalLoo:
    """Leave-one-out errors recomputed only when the map markers' observations change (or
    every ``every`` frames). ``computed`` / ``reused`` count frames."""

    def __init__(self, every: int = 30) -> None:
        self.every = max(1, int(every))
        self._key: dict[int, int] | None = None  # id -> observation version
        self._value: dict[int, float] = {}
        self._age = 0
        self.computed = 0
        self.reused = 0

    def reset(self) -> None:
        self._key = None
        self._value = {}

    def get(self, obs: Sequence[MarkerObservation], in_map: Collection[int],
            compute: Callable[[], dict[int, float]]) -> tuple[dict[int, float], bool]:
        """(errors, computed now): ``compute()`` unless the map markers' observations are
        the same versions as last time and it ran fewer than ``every`` frames ago."""
        # By id, not by order: a full detection lists the markers in its own order, a
        # tracked frame by id, and the errors do not depend on the order.
        key = {o.id: o.version for o in obs if o.id in in_map}
        self._age += 1
        same = key == self._key
        if same and self._age < self.every:
            self.reused += 1
            return self._value, False
        self._value = compute()
        self._key, self._age = key, 0
        self.computed += 1
        return self._value, True

