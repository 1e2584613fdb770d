"""A fixed live camera across frames: recompute only what changed (:class:`FixedCameraSession`).

With :mod:`kmea.vision.fixed_camera_detector` a floor marker that did not move is reported
with the same corners, bit for bit, frame after frame. What depends only on those corners
is then the same too, and is reused instead of recomputed:

- its camera-frame pose (:class:`IncrementalPoses`): only markers with new corners (the
  robots, a marker that reappeared) are posed. When only moving markers are new, the IPPE
  choice of each leans on the scene's consensus rotation kept from the last frame whose
  fixed markers were posed (the camera is fixed: it is still the scene's); when fixed
  markers are new too, a few unchanged floor markers are posed with them as anchors;
- the leave-one-out errors of the floor (:class:`IncrementalLoo`): they depend only on the
  map markers' observations (robots are never references), so while those are the same
  (the same ``version``) the last errors are exactly what a recomputation would give. They are
  recomputed when any map marker's observation changes, and at least every ``every``
  frames.

The session also keeps the floor of the last camera fit: the robots are placed from their
corners with that fit and sent before any pose is computed, and the fit itself is updated at
most every ``refit_every`` frames.

What "the same" means is explicit: an observation's ``version`` (new at every
construction), never object identity. ``reset()`` after anything that invalidates the
session: a bumped camera, a new map, camera intrinsics or robot table. Not used for file
sources (their results must be frame-exact and independent of the frames before).
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, Protocol

import numpy as np

from kmea.estimators.base import Estimate, MarkerObservation, PlacesOnPlanes
from kmea.maps.model import MarkerMap

__all__ = ["FixedCameraSession", "IncrementalLoo", "IncrementalPoses", "SessionHost"]

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


class SessionHost(Protocol):
    """What the session asks of the pipeline it serves (:class:`kmea.pipeline.Pipeline`)."""

    estimator: Any
    algorithm: str
    world_map: MarkerMap
    robot_specs: list
    robot_lengths: dict[int, float]
    plane_heights: dict[int, float]

    @property
    def marker_length(self) -> float: ...
    @property
    def refit_every(self) -> int: ...
    @property
    def intrinsics(self) -> Any: ...
    def poses(self, ids: np.ndarray, corners: np.ndarray,
              world2cam_R: np.ndarray | None = None) -> tuple[list[MarkerObservation], dict]: ...
    def robot_fixes(self, est: Estimate, t: float, rejections: dict[str, str] | None = None,
                    times: Mapping[int, float] | None = None) -> dict: ...


# on_robots(t, fixes): the relay, called as soon as the robots are known
OnRobots = Callable[[float, dict], None]


@dataclass
class Observed:
    """One frame's observations from the session: ``obs`` and the pose ``diag``;
    ``corners`` the frame's (with deferred fixed markers' kept from the last fit);
    ``deferred`` the fixed markers placed but not references; ``early`` the robot fixes
    sent before the poses (None: the pipeline computes and sends them)."""

    obs: list[MarkerObservation]
    diag: dict
    corners: np.ndarray
    deferred: tuple[int, ...]
    early: dict | None


class FixedCameraSession:
    """A fixed live camera's state across frames: the reused poses (:attr:`poses`), the
    reused leave-one-out errors (:attr:`loo`), the floor of the last camera fit
    (:attr:`floor`) and the age of that fit (refitted at most every ``host.refit_every``
    frames). The pipeline keeps one beside its plain path and uses it only with
    ``settings.fixed_camera``."""

    def __init__(self, loo_every: int = 30) -> None:
        self.poses = IncrementalPoses()
        self.loo = IncrementalLoo(loo_every)
        self.floor: list[MarkerObservation] = []  # the last fit's fixed markers
        self._floor_cache: tuple | None = None  # see _floor_rows
        self._refit_age = 0  # frames since the floor's camera fit was last updated

    def reset(self, fixed: Collection[int], loo_every: int) -> None:
        """Forget everything (new map, robots, camera, view); ``fixed``: the markers that
        do not move (the map's, minus the robots')."""
        self.poses.reset(fixed)
        self.floor = []
        self._refit_age = 0
        self.loo.reset()
        self.loo.every = max(1, int(loo_every))

    def observe(self, host: SessionHost, t: float, ids: np.ndarray, corners: np.ndarray,
                on_robots: OnRobots | None, rejections: dict[str, str],
                times: Mapping[int, float]) -> Observed:
        """This frame's observations, reusing what did not change; the robots sent first
        when the floor of the last fit allows it (see :class:`Observed`)."""
        known = None
        early = None
        deferred: tuple[int, ...] = ()
        self._refit_age += 1
        changed = bool(self.floor) and (self.poses.fixed_changed(ids, corners)
                                        or self._floor_grew(ids))
        if changed and self._refit_age < host.refit_every:
            corners, deferred = self._last_floor(ids, corners)
            changed = False
        elif changed:
            self._refit_age = 0
        if host.robot_specs and self.floor and isinstance(host.estimator, PlacesOnPlanes):
            # The floor of the last camera fit: the robots are placed from their corners
            # with that fit and sent before any pose is computed; their observations come
            # from those placements (no IPPE pose for them). Also when the floor changed:
            # the refit is for the statistics and the next frame (the same fixes with and
            # without a relay).
            early, known = self._robots_from_corners(host, t, ids, corners, on_robots,
                                                     rejections, times)
        if changed and early is None and on_robots is not None and host.robot_specs:
            # The floor's corners changed (one more averaged look, a marker back in view):
            # re-posing it and refitting the camera can take 10 ms or more. The robots go
            # first, placed with the camera fit of the floor as it was; then the floor is
            # updated for the statistics and the next frame.
            early, known = self._robots_first(host, t, ids, corners, on_robots, rejections,
                                              times)
        obs, diag = self.poses.poses(host.poses, ids, corners, known)
        return Observed(obs, diag, corners, deferred, early)

    def remember(self, obs: Sequence[MarkerObservation], ok: bool) -> None:
        """After the frame's estimate: its fixed markers are the floor of the new fit."""
        self.floor = ([o for o in obs if o.id in self.poses.fixed and o.corners is not None]
                      if ok else [])

    def _robots_from_corners(self, host: SessionHost, t: float, ids: np.ndarray,
                             corners: np.ndarray, on_robots: OnRobots | None,
                             rejections: dict[str, str], times: Mapping[int, float]
                             ) -> tuple[dict | None, dict[int, MarkerObservation] | None]:
        """Robot fixes of this frame from the moving markers' corners and the estimator's
        last camera fit (``place_on_planes``), sent with ``on_robots``, and the moving
        markers' observations from those placements (``placed_observations``: the pose
        stage then has nothing to pose for them); (None, None) (the usual path then) when a
        moving marker has no known plane or there is no fit."""
        fixed = self.poses.fixed
        sel = [k for k, m in enumerate(ids.tolist()) if m not in fixed]
        if not sel:
            return None, None
        est = host.estimator
        if not isinstance(est, PlacesOnPlanes):
            return None, None
        mids = [int(ids[k]) for k in sel]
        lengths = [host.robot_lengths.get(m, host.marker_length) for m in mids]
        placed = est.place_on_planes(mids, corners[sel], lengths, host.world_map,
                                     host.plane_heights)
        if placed is None:
            return None, None
        fixes = host.robot_fixes(Estimate(host.algorithm, True, placed), t, rejections, times)
        if on_robots is not None:
            on_robots(t, fixes)
        return fixes, est.placed_observations(placed, mids, corners[sel], lengths)

    def _robots_first(self, host: SessionHost, t: float, ids: np.ndarray,
                      corners: np.ndarray, on_robots: OnRobots, rejections: dict[str, str],
                      times: Mapping[int, float]
                      ) -> tuple[dict | None, dict[int, MarkerObservation] | None]:
        """Robot fixes of this frame from its moving markers and the last fit's floor
        observations (their camera fit is the estimator's warm start: the same fit, not a
        new one), sent with ``on_robots``; (fixes, this frame's moving-marker
        observations) or (None, None) when no moving marker is in the frame."""
        fixed = self.poses.fixed
        sel = [k for k, m in enumerate(ids.tolist()) if m not in fixed]
        if not sel:
            return None, None
        floor = self.floor
        r_ids = np.concatenate([ids[sel], np.array([o.id for o in floor], np.int64)])
        r_c = np.concatenate([corners[sel], np.stack([np.asarray(o.corners, float)
                                                      for o in floor])])
        obs, _ = self.poses.poses(host.poses, r_ids, r_c)
        try:
            est = host.estimator.estimate(obs, host.world_map, camera=host.intrinsics,
                                          plane_heights=host.plane_heights)
        except ValueError:
            return None, None
        if not est.ok:
            return None, None
        fixes = host.robot_fixes(est, t, rejections, times)
        on_robots(t, fixes)
        return fixes, {o.id: o for o in obs if o.id not in fixed}

    def _last_floor(self, ids: np.ndarray, corners: np.ndarray
                    ) -> tuple[np.ndarray, tuple[int, ...]]:
        """This frame's corners with the floor of the last camera fit: a fixed marker of
        that fit keeps its corners there (its observation is reused); the fixed markers not
        in it keep their new corners and are returned second (placed, not references:
        ``exclude``)."""
        rows, stack = self._floor_rows()
        fixed = self.poses.fixed
        c = corners.copy()
        new = []
        ks, js = [], []
        for k, m in enumerate(ids.tolist()):
            j = rows.get(m)
            if j is not None:
                ks.append(k)
                js.append(j)
            elif m in fixed:
                new.append(m)
        if ks:
            c[ks] = stack[js]
        return c, tuple(new)

    def _floor_rows(self) -> tuple[dict[int, int], np.ndarray]:
        """The last fit's floor as id -> row and its corners stacked (m, 4, 2) px; kept
        while its observations are the same versions (frames with deferred markers keep
        it, and compare against it every frame)."""
        cache = self._floor_cache
        floor = self.floor
        key = tuple(o.version for o in floor)
        if cache is None or cache[0] != key:
            stack = np.array([np.asarray(o.corners, float).reshape(4, 2) for o in floor]
                             ).reshape(-1, 4, 2)
            cache = self._floor_cache = (key, {o.id: k for k, o in enumerate(floor)}, stack)
        return cache[1], cache[2]

    def _floor_grew(self, ids: np.ndarray) -> bool:
        """Is a fixed marker in ``ids`` that the last fit's floor did not have (back in
        view: the camera fit gains a reference and is solved again)?"""
        had = {o.id for o in self.floor}
        fixed = self.poses.fixed
        return any(m in fixed and m not in had for m in ids.tolist())
