"""A fixed live camera across frames: recompute only what changed (:class:`FixedCameraSession`).

The session owns what carries over from frame to frame and returns what the pipeline
needs; it calls nothing back:

- the reused poses and leave-one-out errors (:mod:`kmea.fixed_camera.reuse`);
- the floor of the last camera fit: the fit is updated at most every ``refit_every``
  frames (:meth:`FixedCameraSession.plan`); in between, a fixed marker whose corners
  changed keeps the observation of the last fit, and a fixed marker new to the floor is
  placed with the last fit but is not a reference yet (``deferred``);
- the robots placed before any pose (:meth:`FixedCameraSession.early_robots`): from their
  corners with the last fit (estimators that place on planes), or, when the floor changed
  and a relay waits, from the last fit's floor observations. The pipeline turns the
  returned estimate into robot fixes and sends them, then asks for the frame's
  observations (:meth:`FixedCameraSession.observations`).

``reset()`` after anything that invalidates the session: a bumped camera, a new map, camera
intrinsics or robot table. Not used for file sources (their results must be frame-exact and
independent of the frames before).
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from kmea.estimators.base import Estimate, MarkerObservation, PlacesOnPlanes
from kmea.fixed_camera.reuse import IncrementalLoo, IncrementalPoses, PoseFn
from kmea.maps.model import MarkerMap

__all__ = ["EarlyRobots", "FixedCameraSession", "FramePlan", "Models"]


@dataclass
class Models:
    """What the session places robots with (the pipeline's, this frame): the estimator
    and its ``algorithm`` name, the map, robot marker id -> side (m) ``lengths`` and the
    side of any other marker, robot marker id -> height (m) ``plane_heights``, the camera
    ``intrinsics`` and ``pose(ids, corners, world2cam_R=None) -> (observations,
    diagnostics)`` (:meth:`kmea.pipeline.MarkerObserver.poses`)."""

    estimator: Any
    algorithm: str
    world_map: MarkerMap
    lengths: Mapping[int, float]
    marker_length: float
    plane_heights: dict[int, float]
    intrinsics: Any
    pose: PoseFn


@dataclass
class FramePlan:
    """This frame against the last camera fit: ``corners`` the frame's (deferred fixed
    markers' kept from the last fit), ``deferred`` the fixed markers placed but not
    references, ``changed`` the floor changed and the fit is updated in this frame."""

    corners: np.ndarray
    deferred: tuple[int, ...]
    changed: bool


@dataclass
class EarlyRobots:
    """The robots' markers placed before the frame's poses: ``estimate`` their world
    estimates (robot fixes come from it), ``known`` id -> their observations of this frame
    (the pose stage has nothing to pose for them)."""

    estimate: Estimate
    known: dict[int, MarkerObservation]


class FixedCameraSession:
    """A fixed live camera's state across frames: the reused poses (:attr:`poses`), the
    reused leave-one-out errors (:attr:`loo`), the floor of the last camera fit
    (:attr:`floor`) and the age of that fit. The pipeline keeps one beside its plain path
    and uses it only with ``settings.fixed_camera``."""

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

    def plan(self, ids: np.ndarray, corners: np.ndarray, refit_every: int) -> FramePlan:
        """Is the camera fit updated in this frame (at most every ``refit_every``
        frames, when the floor changed)? If not, the frame's corners with the last fit's
        floor (see :class:`FramePlan`)."""
        deferred: tuple[int, ...] = ()
        self._refit_age += 1
        changed = bool(self.floor) and (self.poses.fixed_changed(ids, corners)
                                        or self._floor_grew(ids))
        if changed and self._refit_age < refit_every:
            corners, deferred = self._last_floor(ids, corners)
            changed = False
        elif changed:
            self._refit_age = 0
        return FramePlan(corners, deferred, changed)

    def early_robots(self, plan: FramePlan, ids: np.ndarray, models: Models,
                     relay: bool) -> EarlyRobots | None:
        """The robots placed before any pose, or None (the pipeline places them with the
        frame's estimate). With the floor of the last camera fit, an estimator that places
        on planes places them from their corners (also when the floor changed: the refit is
        for the statistics and the next frame; the same fixes with and without a relay).
        Else, when the floor changed and a relay waits (``relay``), they are placed with
        the last fit's floor observations: re-posing the floor and refitting the camera can
        take 10 ms or more, and the robots go first."""
        early = None
        if self.floor and isinstance(models.estimator, PlacesOnPlanes):
            early = self._from_corners(ids, plan.corners, models)
        if plan.changed and early is None and relay:
            early = self._with_last_floor(ids, plan.corners, models)
        return early

    def observations(self, ids: np.ndarray, plan: FramePlan, models: Models,
                     early: EarlyRobots | None) -> tuple[list[MarkerObservation], dict]:
        """This frame's observations and pose diagnostics, reusing what did not change."""
        return self.poses.poses(models.pose, ids, plan.corners,
                                None if early is None else early.known)

    def remember(self, obs: Sequence[MarkerObservation], ok: bool) -> None:
        """After the frame's estimate: its fixed markers are the floor of the new fit."""
        self.floor = ([o for o in obs if o.id in self.poses.fixed and o.corners is not None]
                      if ok else [])

    def _from_corners(self, ids: np.ndarray, corners: np.ndarray, models: Models
                      ) -> EarlyRobots | None:
        """The moving markers placed from their corners with the estimator's last camera
        fit (``place_on_planes``), their observations from those placements
        (``placed_observations``); None when a moving marker has no known plane or there is
        no fit."""
        fixed = self.poses.fixed
        sel = [k for k, m in enumerate(ids.tolist()) if m not in fixed]
        if not sel:
            return None
        est = models.estimator
        mids = [int(ids[k]) for k in sel]
        lengths = [models.lengths.get(m, models.marker_length) for m in mids]
        placed = est.place_on_planes(mids, corners[sel], lengths, models.world_map,
                                     models.plane_heights)
        if placed is None:
            return None
        return EarlyRobots(Estimate(models.algorithm, True, placed),
                           est.placed_observations(placed, mids, corners[sel], lengths))

    def _with_last_floor(self, ids: np.ndarray, corners: np.ndarray, models: Models
                         ) -> EarlyRobots | None:
        """The frame's moving markers estimated with the last fit's floor observations
        (their camera fit is the estimator's warm start: the same fit, not a new one);
        None when no moving marker is in the frame or the estimate fails."""
        fixed = self.poses.fixed
        sel = [k for k, m in enumerate(ids.tolist()) if m not in fixed]
        if not sel:
            return None
        floor = self.floor
        r_ids = np.concatenate([ids[sel], np.array([o.id for o in floor], np.int64)])
        r_c = np.concatenate([corners[sel], np.stack([np.asarray(o.corners, float)
                                                      for o in floor])])
        obs, _ = self.poses.poses(models.pose, r_ids, r_c)
        try:
            est = models.estimator.estimate(obs, models.world_map, camera=models.intrinsics,
                                            plane_heights=models.plane_heights)
        except ValueError:
            return None
        if not est.ok:
            return None
        return EarlyRobots(est, {o.id: o for o in obs if o.id not in fixed})

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
