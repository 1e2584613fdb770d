"""The one interface of every estimator.

An estimator takes the camera-frame poses of the markers detected in one frame and the
map, and returns the world pose of every detected marker (in the map or not) plus
diagnostics. Numpy only.

The calls (see :class:`Estimator`)::

    est = estimator.estimate(observations, world_map, exclude=(), camera=None,
                             plane_heights=None)                        # -> Estimate
    res = estimator.estimate_with_loo(observations, world_map, exclude=(), camera=None,
                                      plane_heights=None, loo_ids=None)  # -> EstimateWithLoo
    res.estimate      # the Estimate of ``estimate(...)`` with the same arguments
    res.loo_positions # id -> (3,) world position (m) of that marker estimated without it
    res.loo_errors    # id -> floor-plane error (m) of that position against the map
    res.loo_failures  # id -> why it could not be estimated without itself

**Leave-one-out has one definition**: the leave-one-out position of marker j is
``estimate(observations, world_map, exclude={j, *exclude}, camera, plane_heights)
.markers[j].position`` (:func:`loo_by_exclusion` computes exactly that). By default j runs
over the observed map markers that can be references (not suspect, not in ``exclude``);
``loo_ids`` chooses them (the experiments evaluate chosen markers). An estimator may compute
the same thing faster (KMEA: all alignments in one batched SVD) but never something else.
The daemon's statistics and the experiment tables both come from this call.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from kmea.geometry.camera import CameraIntrinsics
from kmea.maps.model import MarkerMap

__all__ = [
    "CheckedObservations",
    "Estimate",
    "EstimateWithLoo",
    "Estimator",
    "EstimatorBase",
    "MarkerEstimate",
    "MarkerObservation",
    "check_observations",
    "floor_errors",
    "loo_by_exclusion",
    "loo_candidates",
]


# Observation versions: itertools.count's next() is atomic under the GIL.
_VERSIONS = itertools.count(1)


@dataclass(frozen=True)
class MarkerObservation:
    """One marker detected in one frame, in the camera frame (OpenCV axes, metres).

    Attributes:
        id: ArUco id.
        marker2cam_R: (3, 3) rotation of the chosen PnP solution.
        marker2cam_t: (3,) marker centre in the camera frame, metres.
        corners: (4, 2) detected pixel corners (TL, TR, BR, BL, OpenCV convention: pixel
            centres at integer coordinates), or None when unknown.
        length: side used for the PnP, metres.
        reproj_error: RMS reprojection error of the chosen solution, pixels.
        alt_R, alt_t: the other IPPE solution, if any.
        alt_reproj_error: its RMS reprojection error, pixels.
        ambiguous: the choice between the two solutions is uncertain.
        flipped: the scene-consistent choice differs from the lowest-error one.
        suspect: the detected quadrilateral is not trustworthy (a corner hidden, e.g. by a
            passing robot, or at the image border: see ``docs/vision.md``). The marker is
            still estimated and published, but never used as an alignment reference.
        version: unique to this measurement in this process, given at construction (also
            by ``dataclasses.replace``: new corners are a new measurement). What a fixed
            camera's caches key on: the same version is the same measurement
            (:mod:`kmea.fixed_camera`, the estimators' warm starts).
    """

    id: int
    marker2cam_R: np.ndarray
    marker2cam_t: np.ndarray
    corners: np.ndarray | None = None
    length: float = 0.06
    reproj_error: float = math.nan
    alt_R: np.ndarray | None = None
    alt_t: np.ndarray | None = None
    alt_reproj_error: float = math.nan
    ambiguous: bool = False
    flipped: bool = False
    suspect: bool = False
    version: int = field(init=False, compare=False, default_factory=lambda: next(_VERSIONS))


@dataclass
class MarkerEstimate:
    """World pose of one marker.

    position: (3,) world, metres; rotation: (3, 3) marker2world; yaw: radians (heading of
    the marker's x axis, CCW from world x); sigma: 1-sigma position uncertainty (m) or None.
    """

    id: int
    position: np.ndarray
    rotation: np.ndarray
    yaw: float
    sigma: float | None = None


@dataclass
class Estimate:
    """Result of one estimator on one frame.

    ok: False means "not estimated" (``reason`` says why; ``markers`` is then empty).
    references: ids of the map markers the alignment used.
    cam2world: (4, 4) similarity world = scale * R @ cam + t, or None.
    scale: the similarity's scale (1 for rigid estimators).
    residuals: reference id -> distance (m) between its aligned and its map position.
    rejected: reference id -> disagreement with the map (m), for robust estimators.
    info: anything else worth publishing (refined focal length, iterations, ...).
    """

    algorithm: str
    ok: bool
    markers: dict[int, MarkerEstimate] = field(default_factory=dict)
    reason: str = ""
    references: tuple[int, ...] = ()
    cam2world: np.ndarray | None = None
    scale: float = math.nan
    residuals: dict[int, float] = field(default_factory=dict)
    rejected: dict[int, float] = field(default_factory=dict)
    info: dict = field(default_factory=dict)

    @classmethod
    def failed(cls, algorithm: str, reason: str) -> Estimate:
        return cls(algorithm=algorithm, ok=False, reason=reason)


class EstimateWithLoo:
    """An estimate of one frame together with its leave-one-out results.

    estimate: the :class:`Estimate` with all references (but ``exclude``).
    loo_positions: id -> (3,) world position (m) of that marker estimated with itself left
        out of the references (see the module docstring for the definition).
    loo_errors: id -> floor-plane distance (m) between that position and the map's; only
        for markers in the map.
    loo_failures: id -> reason, for the markers that could not be estimated without
        themselves (too few references, an LMEA anchor, ...).
    loo_seconds: time the leave-one-out part took (s), for the daemon's timings.

    The leave-one-out part runs on first access to one of the ``loo_*`` attributes, from
    the state of this frame's estimate that this object holds (for example corner-pnp's
    camera fit): a caller can act on ``estimate`` first (the daemon relays robot poses)
    and nothing is cached in the estimator.
    """

    def __init__(self, estimate: Estimate, world_map: MarkerMap,
                 loo: Callable[[], tuple[dict[int, np.ndarray], dict[int, str]]]) -> None:
        self.estimate = estimate
        self._map = world_map
        self._loo: Callable[[], tuple[dict[int, np.ndarray], dict[int, str]]] | None = loo
        self._pos: dict[int, np.ndarray] = {}
        self._err: dict[int, float] = {}
        self._fail: dict[int, str] = {}
        self._seconds = 0.0

    def _run(self) -> None:
        if self._loo is None:
            return
        t0 = time.perf_counter()
        pos, fail = self._loo()
        self._loo = None
        self._pos = dict(sorted(pos.items()))
        self._err = floor_errors(self._pos, self._map)
        self._fail = dict(sorted(fail.items()))
        self._seconds = time.perf_counter() - t0

    @property
    def loo_positions(self) -> dict[int, np.ndarray]:
        self._run()
        return self._pos

    @property
    def loo_errors(self) -> dict[int, float]:
        self._run()
        return self._err

    @property
    def loo_failures(self) -> dict[int, str]:
        self._run()
        return self._fail

    @property
    def loo_seconds(self) -> float:
        self._run()
        return self._seconds


@runtime_checkable
class Estimator(Protocol):
    """What every estimator provides (optional abilities: :class:`WarmStart`,
    :class:`PlacesOnPlanes`)."""

    name: str
    fits_corners: bool  # see EstimatorBase

    def estimate(
        self,
        observations: Sequence[MarkerObservation],
        world_map: MarkerMap,
        exclude: Collection[int] = (),
        camera: CameraIntrinsics | None = None,
        plane_heights: Mapping[int, float] | None = None,
    ) -> Estimate:
        """Estimate the world pose of every observed marker.

        exclude: map ids not to use as references; they are still estimated.
        camera: intrinsics, for estimators that work on corners.
        plane_heights: id -> known height (m) of a horizontal marker not in the map (robots).
        """
        ...

    def estimate_with_loo(
        self,
        observations: Sequence[MarkerObservation],
        world_map: MarkerMap,
        exclude: Collection[int] = (),
        camera: CameraIntrinsics | None = None,
        plane_heights: Mapping[int, float] | None = None,
        loo_ids: Collection[int] | None = None,
    ) -> EstimateWithLoo:
        """``estimate`` and the leave-one-out positions/errors of ``loo_ids`` (default
        :func:`loo_candidates`), as defined in the module docstring."""
        ...


@runtime_checkable
class WarmStart(Protocol):
    """An estimator that can start from its previous call's fit (a fixed live camera)."""

    warm_start: bool

    def reset_warm(self) -> None:
        """Forget the previous fit (the view changed: the next call solves afresh)."""
        ...


@runtime_checkable
class PlacesOnPlanes(Protocol):
    """An estimator that places markers of known plane height with its last camera fit,
    before (and without) the frame's estimate: a fixed camera's robots, sent first."""

    def place_on_planes(self, ids: Sequence[int], corners: np.ndarray,
                        lengths: Sequence[float], world_map: MarkerMap,
                        plane_heights: Mapping[int, float]
                        ) -> dict[int, MarkerEstimate] | None:
        """World poses of ``ids`` from their corners (n, 4, 2) px; None without a fit."""
        ...

    def placed_observations(self, placed: Mapping[int, MarkerEstimate], ids: Sequence[int],
                            corners: np.ndarray, lengths: Sequence[float]
                            ) -> dict[int, MarkerObservation]:
        """Camera-frame observations of the markers :meth:`place_on_planes` placed."""
        ...


def loo_candidates(observations: Sequence[MarkerObservation], world_map: MarkerMap,
                   exclude: Collection[int] = ()) -> list[int]:
    """The markers leave-one-out evaluates by default: observed, in the map, not suspect, not
    in ``exclude`` (the markers that can be references), sorted by id."""
    excl = set(exclude)
    return sorted(o.id for o in observations
                  if o.id in world_map and not o.suspect and o.id not in excl)


def loo_by_exclusion(estimator: Estimator, observations: Sequence[MarkerObservation],
                     world_map: MarkerMap, ids: Collection[int], exclude: Collection[int] = (),
                     camera: CameraIntrinsics | None = None,
                     plane_heights: Mapping[int, float] | None = None
                     ) -> tuple[dict[int, np.ndarray], dict[int, str]]:
    """The definition of leave-one-out: for each id in ``ids``, ``estimator.estimate`` with
    ``exclude={id, *exclude}``. Returns (id -> (3,) world position, m; id -> failure reason)."""
    pos: dict[int, np.ndarray] = {}
    fail: dict[int, str] = {}
    for j in ids:
        e = estimator.estimate(observations, world_map, exclude={j, *exclude}, camera=camera,
                               plane_heights=plane_heights)
        if not e.ok:
            fail[j] = e.reason or "not estimated"
        elif j not in e.markers:
            fail[j] = "marker missing from the estimate"
        else:
            pos[j] = np.asarray(e.markers[j].position, dtype=float)
    return pos, fail


def floor_errors(positions: Mapping[int, np.ndarray], world_map: MarkerMap) -> dict[int, float]:
    """id -> |(x, y) - map (x, y)| (m) for the positions of map markers, sorted by id."""
    return {mid: float(np.hypot(*(np.asarray(p)[:2] - world_map[mid].position[:2])))
            for mid, p in sorted(positions.items()) if mid in world_map}


class EstimatorBase:
    """Shared implementation of :meth:`Estimator.estimate_with_loo` by the definition
    (:func:`loo_by_exclusion`); an estimator with a faster exact way overrides
    :meth:`_loo_positions`."""

    name: str
    # The fit reads the references' corners (their poses only seed it): a reference's pose
    # may be reused while its corners move a little (kmea.fixed_camera).
    fits_corners: bool = False

    def estimate(self, observations, world_map, exclude=(), camera=None,
                 plane_heights=None) -> Estimate:  # pragma: no cover - every subclass has one
        raise NotImplementedError

    def _loo_positions(self, observations: Sequence[MarkerObservation], world_map: MarkerMap,
                       ids: list[int], exclude: Collection[int],
                       camera: CameraIntrinsics | None,
                       plane_heights: Mapping[int, float] | None
                       ) -> tuple[dict[int, np.ndarray], dict[int, str]]:
        return loo_by_exclusion(self, observations, world_map, ids, exclude, camera,
                                plane_heights)

    def estimate_with_loo(
        self,
        observations: Sequence[MarkerObservation],
        world_map: MarkerMap,
        exclude: Collection[int] = (),
        camera: CameraIntrinsics | None = None,
        plane_heights: Mapping[int, float] | None = None,
        loo_ids: Collection[int] | None = None,
    ) -> EstimateWithLoo:
        """See :meth:`Estimator.estimate_with_loo`."""
        est = self.estimate(observations, world_map, exclude=exclude, camera=camera,
                            plane_heights=plane_heights)
        ids = (loo_candidates(observations, world_map, exclude) if loo_ids is None
               else sorted(set(loo_ids)))
        return EstimateWithLoo(est, world_map, lambda: self._loo_positions(
            observations, world_map, ids, exclude, camera, plane_heights))


class CheckedObservations:
    """:func:`check_observations` for a fixed camera's consecutive frames (an estimator's
    warm start): an observation whose version the last call checked (a fixed marker's,
    reused by :mod:`kmea.fixed_camera`) is not checked again; the duplicate-id test covers
    them all, and any failure is raised by the full check (the same error). ``reset()``
    forgets."""

    def __init__(self) -> None:
        self._checked: set[int] = set()

    def reset(self) -> None:
        self._checked = set()

    def __call__(self, observations: Sequence[MarkerObservation]) -> list[MarkerObservation]:
        obs = list(observations)
        seen = self._checked
        new = [o for o in obs if o.version not in seen]
        if len({o.id for o in obs}) != len(obs):
            check_observations(obs)  # raises on the duplicate
        if new:
            try:
                check_observations(new)
            except ValueError:
                check_observations(obs)  # the error the full check gives
                raise
        self._checked = {o.version for o in obs}
        return obs


def check_observations(observations: Sequence[MarkerObservation]) -> list[MarkerObservation]:
    """Drop nothing silently: raise ``ValueError`` on duplicate ids, non-finite poses or bad
    shapes."""
    seen: set[int] = set()
    out = []
    Rs: list[np.ndarray] = []
    ts: list[np.ndarray] = []
    for o in observations:
        if o.id in seen:
            raise ValueError(f"observation id {o.id}: duplicate id in one frame")
        seen.add(o.id)
        R = np.asarray(o.marker2cam_R, dtype=float)
        t = np.asarray(o.marker2cam_t, dtype=float)
        if R.shape != (3, 3) or t.shape != (3,):
            raise ValueError(f"observation id {o.id}: marker2cam_R must be (3, 3) and "
                             f"marker2cam_t (3,), got {R.shape} and {t.shape}")
        Rs.append(R)
        ts.append(t)
        out.append(o)
    if len(out) > 8:
        # One vectorised finiteness test for a whole frame.
        ok = np.isfinite(np.stack(Rs)).all(axis=(1, 2)) & np.isfinite(np.stack(ts)).all(axis=1)
        if not ok.all():
            raise ValueError(f"observation id {out[int(np.argmin(ok))].id}: non-finite pose")
    else:
        # A few (a tracked frame's new ones, every frame): floats beat numpy's per-call cost.
        for o, R, t in zip(out, Rs, ts, strict=True):
            if not all(map(math.isfinite, R.ravel().tolist() + t.tolist())):
                raise ValueError(f"observation id {o.id}: non-finite pose")
    return out
