"""One frame through the localizer: detect, per-marker pose, estimator, LOO, filter, robots.

The library's per-frame computation, used by the daemon (``kmead``), the experiments, the
benchmarks and the gridboard study. No sockets, no files, no threads: the caller feeds
frames (or, for replay, recorded detections and poses) and turns the :class:`FrameResult`
into CSV rows, telemetry and datagrams. Every stage is timed in milliseconds.

- :class:`MarkerObserver`: detect-then-pose, the one place where detections become
  camera-frame marker poses (:func:`kmea.vision.marker_pose.estimate_marker_poses`);
- :class:`PipelineSettings`: what the pipeline is told (detector, algorithm, filter, robots);
- :class:`Pipeline`: the whole frame, ``process(FrameInput) -> FrameResult``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from kmea import estimators
from kmea.estimators.base import Estimate, MarkerObservation, WarmStart
from kmea.fixed_camera import FixedCameraConfig, FixedCameraDetector, FixedCameraSession
from kmea.fixed_camera.discovery import Background
from kmea.fixed_camera.session import Models
from kmea.geometry import wrap_angle
from kmea.maps.files import MarkerMap
from kmea.robots.iir import PoseFilter
from kmea.robots.poses import RobotSpec, robot_pose, robot_time
from kmea.robots.tracking import Tracker, TrackerConfig
from kmea.vision.camera import CameraModel
from kmea.vision.detection import Detections, DetectorConfig, MarkerDetector

__all__ = ["STAGES", "FrameInput", "FrameResult", "MarkerObserver", "Pipeline",
           "PipelineSettings", "RobotFix"]

STAGES = ("capture", "detect", "pose", "estimate", "loo", "filter", "robots", "output")

# A fixed marker whose reference corners moved by at most this (px) keeps its pose, for
# estimators that fit corners (kmea.fixed_camera.reuse.IncrementalPoses.reuse_px): a tenth of a
# pixel, above the 0.005-0.05 px of one more averaged look, below the 0.1-0.3 px corner
# noise of a single detection.
REUSE_PX = 0.1


@dataclass
class FrameInput:
    """What the pipeline gets for one frame.

    image: (H, W) uint8 grey or BGR; None for replay. ids/corners/observations: recorded
    detections and poses (replay), else None. t_capture: ``time.perf_counter()`` when the
    frame was captured (latency). capture_ms: time spent getting it from the source.
    """

    index: int
    timestamp: float
    image: np.ndarray | None = None
    ids: np.ndarray | None = None
    corners: np.ndarray | None = None
    observations: list[MarkerObservation] | None = None
    diagnostics: dict = field(default_factory=dict)
    meta: dict = field(default_factory=dict)
    t_capture: float = 0.0
    capture_ms: float = 0.0
    # Done by a worker thread: (ids, corners) or the detector's Detections (mode, events).
    detections: tuple[np.ndarray, np.ndarray] | Detections | None = None
    detect_ms: float = 0.0


@dataclass
class RobotFix:
    """A robot pose in one frame: world x, y (m), theta (rad), 1-sigma (m) or None.

    With the tracking filter: vx, vy (world velocity, m/s), omega (turn rate, rad/s), and
    raw, the measurement before filtering (x, y, theta, sigma), which a fusion node fuses;
    cov, the filter's (3, 3) covariance of (x, y, theta) in m^2, m rad, rad^2 (the ROS 2
    output's covariance; None with the IIR filter, which has none).
    t: the instant the pose stands for (s, the frame timestamps' clock): its markers'
    mid-exposure when the source gives the frame's timing (``meta["timing"]``,
    :class:`kmea.timing.FrameTiming`), else the frame's timestamp.
    """

    name: str
    x: float
    y: float
    theta: float
    sigma: float | None
    markers: list[int]
    vx: float | None = None
    vy: float | None = None
    omega: float | None = None
    raw: tuple[float, float, float, float | None] | None = None
    t: float | None = None
    cov: np.ndarray | None = None


@dataclass
class FrameResult:
    """Everything computed for one frame (see the module docstring)."""

    index: int
    timestamp: float
    algorithm: str
    ids: np.ndarray
    corners: np.ndarray
    observations: list[MarkerObservation]
    diagnostics: dict
    estimate: Estimate
    markers: dict[int, tuple[np.ndarray, float]]  # id -> (filtered position (3,), yaw)
    loo: dict[int, float]
    robots: dict[str, RobotFix]
    timings: dict[str, float]
    t_capture: float = 0.0
    meta: dict = field(default_factory=dict)
    #: robot name -> why the tracking filter rejected its measurement in this frame
    robot_rejections: dict[str, str] = field(default_factory=dict)
    # What the detection noticed (a fixed-camera detector: "camera moved: ..."); restart: the
    # estimation restarted in this frame. detect_mode: "full" or "followed".
    events: tuple[str, ...] = ()
    restart: bool = False
    detect_mode: str = "full"
    loo_fresh: bool = True
    #: fixed markers placed with the last floor fit, not references yet (fixed camera: the
    #: floor's refits are paced, see Pipeline.process)
    deferred: tuple[int, ...] = ()

    @property
    def ok(self) -> bool:
        return self.estimate.ok


@dataclass
class _Work:
    """One frame's values on their way through :meth:`Pipeline.process`'s steps."""

    inp: FrameInput
    tm: dict[str, float]
    loo: bool
    on_robots: Callable[[float, dict[str, RobotFix]], None] | None
    t0: float
    t1: float = 0.0
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    corners: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 2)))
    obs: list[MarkerObservation] = field(default_factory=list)
    diag: dict = field(default_factory=dict)
    events: tuple[str, ...] = ()
    restart: bool = False
    mode: str = "full"
    incremental: bool = False
    deferred: tuple[int, ...] = ()
    est: Estimate = field(default_factory=lambda: Estimate.failed("", "not estimated"))
    both: Any = None  # the estimate with its leave-one-out (estimate_with_loo)
    robots: dict[str, RobotFix] | None = None  # sent already (before the poses)
    rejections: dict[str, str] = field(default_factory=dict)


@dataclass
class PipelineSettings:
    """What the pipeline is told (units: m, s).

    dictionary: ArUco dictionary ("" = the map's); corner_refinement, detector_parameters:
    see :class:`kmea.vision.detection.DetectorConfig`; marker_length: side of markers the map
    and the robots do not size; algorithm: an estimator name (:func:`kmea.estimators.get`);
    unknown_plane: what the estimator does with markers of unknown plane ("auto", "floor",
    "free"; :mod:`kmea.estimators.unknown_plane`);
    alpha, reset_after_s: the pose filter; filter_kind: the robots' filter, "iir" (the
    paper's, with alpha) or "kalman" (:mod:`kmea.robots.tracking`, configured by ``tracker``);
    loo: compute leave-one-out errors; robots: the robots carrying markers.
    fixed_camera: a fixed live camera (:mod:`kmea.fixed_camera`): the fixed-camera detector
    (:mod:`kmea.fixed_camera.detector`, a background full detection every
    ``fixed_full_every`` frames), marker poses and leave-one-out errors reused while the
    floor's detections do not change (recomputed at least every ``loo_every`` frames),
    the floor's camera fit updated at most every ``refit_every`` frames (see
    :meth:`Pipeline.process`); False: every frame from scratch (file sources: frame-exact).
    """

    dictionary: str = ""
    corner_refinement: str = "subpix"
    detector_parameters: dict[str, Any] = field(default_factory=dict)
    marker_length: float = 0.06
    algorithm: str = estimators.DEFAULT_ALGORITHM
    unknown_plane: str = "auto"
    alpha: float = 1.0
    reset_after_s: float = 1.0
    filter_kind: str = "iir"
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    loo: bool = True
    robots: tuple[RobotSpec, ...] = ()
    fixed_camera: bool = False
    fixed_full_every: int = 6
    loo_every: int = 30
    refit_every: int = 30

    @classmethod
    def from_config(cls, data: Mapping[str, Any], live: bool = False) -> PipelineSettings:
        """From a configuration dict shaped like kmead's (``Config.data``: sections
        ``detector``, ``estimator``, ``filter``, ``stats`` and the ``robots`` tables).
        live: the source is a live camera (``detector.fixed_camera`` applies to live sources
        only)."""
        d, f = data["detector"], data["filter"]
        return cls(dictionary=d["dictionary"], corner_refinement=d["corner_refinement"],
                   detector_parameters=dict(d["parameters"]),
                   marker_length=float(d["marker_length"]),
                   algorithm=data["estimator"]["algorithm"],
                   unknown_plane=data["estimator"].get("unknown_plane", "auto"),
                   alpha=f["alpha"],
                   reset_after_s=f["reset_after_s"], filter_kind=f.get("kind", "iir"),
                   tracker=tracker_config(f), loo=bool(data["stats"]["loo"]),
                   robots=tuple(RobotSpec(name=r["name"], markers=tuple(r["markers"]),
                                          height=r["height"], length=r["length"],
                                          separation=r["separation"])
                                for r in data["robots"]),
                   fixed_camera=bool(live and d.get("fixed_camera", False)),
                   fixed_full_every=int(d.get("fixed_full_every", 6)),
                   refit_every=int(d.get("fixed_refit_every", 30)))


def tracker_config(f: Mapping[str, Any]) -> TrackerConfig:
    """The tracking filter's configuration from a ``[filter]`` table (missing keys: the
    defaults of :class:`TrackerConfig`)."""
    return TrackerConfig.from_table(f)


class MarkerObserver:
    """Detect-then-pose: an image -> detections -> camera-frame marker poses.

    detector: anything with ``detect(image) -> Detections`` (None: poses only). camera: the
    intrinsics used for the poses (at the frame size). lengths: id -> side (m) for markers
    the map does not size (robots); world_map: surveyed markers (lengths and expected
    normals); default_length: side of any other marker (m), None for
    :func:`~kmea.vision.marker_pose.estimate_marker_poses`' default.
    """

    def __init__(self, detector, camera: CameraModel, world_map: MarkerMap | None = None,
                 lengths: Mapping[int, float] | None = None,
                 default_length: float | None = None) -> None:
        self.detector = detector
        self.camera = camera
        self.world_map = world_map
        self.lengths = lengths
        self.default_length = default_length

    def detect(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(ids (N,), corners (N, 4, 2) px) of the markers in ``image``."""
        det = self.detector.detect(image)
        return det.ids, det.corners

    def poses(self, ids: np.ndarray, corners: np.ndarray,
              world2cam_R: np.ndarray | None = None) -> tuple[list[MarkerObservation], dict]:
        """Camera-frame poses of detected markers and the pose diagnostics (as a dict);
        ``world2cam_R``: the consensus rotation when known (see estimate_marker_poses)."""
        from kmea.vision.marker_pose import estimate_marker_poses

        extra: dict[str, Any] = ({} if self.default_length is None
                                 else {"default_length": self.default_length})
        obs, diag = estimate_marker_poses(ids, corners, self.camera, self.lengths,
                                          self.world_map, world2cam_R=world2cam_R, **extra)
        # Shallow: nothing downstream mutates the diagnostics, so no deep copy is needed.
        return list(obs), dict(vars(diag))

    def observe(self, image: np.ndarray) -> list[MarkerObservation]:
        """Detect and pose: the observations of ``image``."""
        return self.poses(*self.detect(image))[0]


class Pipeline:
    """Holds the models and state of the per-frame computation.

    camera: the camera model at the frame size (scaled to each frame's size when it
    differs). world_map: the marker map. settings: see :class:`PipelineSettings`.
    """

    def __init__(self, camera: CameraModel, world_map: MarkerMap,
                 settings: PipelineSettings | None = None,
                 background: Background | None = None) -> None:
        """background: where a fixed-camera detector's discoveries run (the caller's, e.g.
        the daemon's one low-priority thread, :mod:`kmead.run.discovery`); None: in the
        frame path itself (:class:`kmea.fixed_camera.Inline`)."""
        self.background = background
        self.base_camera = camera
        self.camera = camera
        self.world_map = world_map
        self.settings = settings or PipelineSettings()
        self.detector_generation = 0
        self.observer = MarkerObserver(None, camera, world_map)
        # A fixed live camera (settings.fixed_camera): what carries over from frame to frame.
        self.session = FixedCameraSession(self.settings.loo_every)
        self._times: dict[int, float] = {}  # this frame's robot markers' times (process)
        self._rates: dict[int, tuple[float, float]] = {}  # and their row time gradients
        self.configure(self.settings)

    # ------------------------------------------------------------------ configuration
    def configure(self, settings: PipelineSettings) -> None:
        """(Re)build detector, estimator, filter and robot tables from ``settings``."""
        self.settings = settings
        self.configure_detector()
        self.set_algorithm(settings.algorithm)
        self.configure_filter()
        self.configure_robots()

    def configure_detector(self) -> None:
        """Rebuild the detector from ``self.settings`` (``ValueError`` for bad parameters)."""
        s = self.settings
        self.detector_config = DetectorConfig(
            dictionary=s.dictionary or self.world_map.dictionary,
            corner_refinement=s.corner_refinement, parameters=dict(s.detector_parameters))
        old = self.observer.detector
        self.observer.detector = self.new_detector()
        self.detector_generation += 1
        if hasattr(old, "close"):
            old.close()
        self.reset_incremental()

    def reset_incremental(self) -> None:
        """Forget the fixed camera's session (new map, robots, camera, view)."""
        robot_ids = {m for r in self.settings.robots for m in r.markers}
        self.session.reset(set(self.world_map.markers) - robot_ids, self.settings.loo_every)
        est = getattr(self, "estimator", None)  # (None while __init__ builds the pipeline)
        if isinstance(est, WarmStart):
            est.warm_start = self.settings.fixed_camera
            est.reset_warm()

    def new_detector(self):
        """A fresh detector as configured (one per detection thread): a
        :class:`kmea.vision.detection.MarkerDetector`, or with ``settings.fixed_camera`` a
        :class:`kmea.fixed_camera.FixedCameraDetector` told which markers are fixed (the
        map's, minus the robots'), its discoveries run by ``background``."""
        s = self.settings
        if s.fixed_camera:
            robot_ids = {m for r in s.robots for m in r.markers}
            static = frozenset(set(self.world_map.markers) - robot_ids)
            return FixedCameraDetector(self.detector_config, FixedCameraConfig(
                full_every=s.fixed_full_every, static_ids=static),
                jobs=None if self.background is None else self.background.jobs())
        return MarkerDetector(self.detector_config)

    @property
    def detector(self):
        return self.observer.detector

    @property
    def marker_length(self) -> float:
        """Side (m) of markers neither in the map nor on a robot."""
        return self.settings.marker_length

    @property
    def refit_every(self) -> int:
        """With tracking: the floor's camera fit is updated at most every N frames."""
        return max(1, int(self.settings.refit_every))

    @property
    def intrinsics(self):
        return self.camera.intrinsics

    def set_algorithm(self, name: str) -> None:
        """Build estimator ``name`` with the configured ``unknown_plane``."""
        self.estimator = estimators.get(name, unknown_plane=self.settings.unknown_plane)
        self.algorithm = name
        if isinstance(self.estimator, WarmStart):
            # Tracking (a fixed live camera): the camera fit starts from the previous one.
            self.estimator.warm_start = self.settings.fixed_camera
        self.session.loo.reset()
        # A floor reference averaged once more keeps its pose when the estimator fits the
        # corners (see IncrementalPoses).
        self.session.poses.reuse_px = REUSE_PX if self.estimator.fits_corners else 0.0

    def close(self) -> None:
        """No more background detections (one waiting for the frame's robots goes at
        once)."""
        close = getattr(self.observer.detector, "close", None)
        if close is not None:
            close()
        if self.background is not None:
            self.background.robots_sent()

    def configure_filter(self) -> None:
        s = self.settings
        self.filter = PoseFilter(alpha=s.alpha, reset_after_s=s.reset_after_s)
        if s.filter_kind not in ("iir", "kalman"):
            raise ValueError(f"filter kind must be iir or kalman, got {s.filter_kind!r}")
        self.tracker = Tracker(s.tracker) if s.filter_kind == "kalman" else None
        # The last robot_fixes call's measurements, before any filter and whatever the
        # filter made of them: name -> (t, x, y, theta, sigma). A fusion node fuses these,
        # not only the ones this camera's filter accepted (it would miss what this filter
        # rejected before a re-acquisition, and be left behind: kmead.outputs.robots).
        self.measured: dict[str, tuple[float, float, float, float, float | None]] = {}

    def configure_robots(self) -> None:
        self.robot_specs = list(self.settings.robots)
        self.robot_lengths = {m: r.length for r in self.robot_specs for m in r.markers}
        self.robot_heights = {r.name: r.height for r in self.robot_specs}
        self.plane_heights = {m: r.height for r in self.robot_specs for m in r.markers
                              if m not in self.world_map}
        self.observer.lengths = self.robot_lengths
        self.observer.default_length = self.settings.marker_length
        self.reset_incremental()

    def set_map(self, world_map: MarkerMap) -> None:
        self.world_map = world_map
        self.observer.world_map = world_map
        self.configure_detector()
        self.configure_robots()

    def camera_for(self, width: int, height: int) -> CameraModel:
        if (self.camera.width, self.camera.height) != (width, height):
            self.camera = self.base_camera.scaled_to(width, height)
            self.observer.camera = self.camera
            self.reset_incremental()
        return self.camera

    # ------------------------------------------------------------------ per frame
    def detect(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.observer.detect(image)

    def poses(self, ids: np.ndarray, corners: np.ndarray,
              world2cam_R: np.ndarray | None = None) -> tuple[list[MarkerObservation], dict]:
        return self.observer.poses(ids, corners, world2cam_R)

    def process(self, inp: FrameInput, loo: bool | None = None,
                on_robots: Callable[[float, dict[str, RobotFix]], None] | None = None
                ) -> FrameResult:
        """Run every stage on one frame; see :class:`FrameResult`.

        loo: compute the leave-one-out errors (None: ``settings.loo``).

        on_robots(t, fixes): called once, as soon as the robot poses are known, before the
        leave-one-out estimates (the relay's latency must not pay for the statistics).

        With ``settings.fixed_camera`` the frame goes through the fixed camera's session
        (:class:`kmea.fixed_camera.FixedCameraSession`): the robots may be placed before
        the frame's poses, and the floor's camera fit is updated at most every
        ``settings.refit_every`` frames: in between, a fixed marker whose corners changed
        (one more averaged look) keeps the observation of the last fit, and a fixed marker
        new to the floor (found, or uncovered for the first time) is placed with the last
        fit but is not a reference yet (``FrameResult.deferred``); the next update takes
        them all at once (a refit costs 10-40 ms of CPU; the fit moves by micrometres).
        """
        w = _Work(inp, dict.fromkeys(STAGES, 0.0), loo=self.settings.loo if loo is None
                  else loo, on_robots=on_robots, t0=time.perf_counter())
        w.tm["capture"] = inp.capture_ms
        self._times, self._rates = {}, {}
        if inp.observations is None:
            self._detect_step(w)
            self._pose_step(w)
        else:
            self._replay_step(w)
        t2 = time.perf_counter()
        w.tm["pose"] = (t2 - w.t1) * 1e3 if w.t1 else 0.0
        self._estimate_step(w)
        t3 = time.perf_counter()
        w.tm["estimate"] = (t3 - t2) * 1e3
        # The robots first: their datagrams must not wait for the markers' bookkeeping.
        robots = w.robots if w.robots is not None else self._send_robots(w, w.est)
        if w.incremental and not w.deferred:
            self.session.remember(w.obs, w.est.ok)
        t4 = time.perf_counter()
        w.tm["robots"] = (t4 - t3) * 1e3
        markers = self._filter_step(w.est, inp.timestamp)
        t5 = time.perf_counter()
        w.tm["filter"] = (t5 - t4) * 1e3
        loo_err, fresh = self._loo_step(w)
        w.tm["loo"] = (time.perf_counter() - t5) * 1e3
        return FrameResult(inp.index, inp.timestamp, self.algorithm, w.ids, w.corners, w.obs,
                           w.diag, w.est, markers, loo_err, robots, w.tm, inp.t_capture,
                           inp.meta, w.rejections, w.events, w.restart, w.mode, fresh,
                           w.deferred)

    def _detect_step(self, w: _Work) -> None:
        """The frame's detections (done already by a detection thread, or here), with what
        the detector noticed; a restart when the view changed."""
        inp = w.inp
        if inp.image is None:
            raise ValueError(f"frame {inp.index}: no image")
        h, wd = inp.image.shape[:2]
        self.camera_for(wd, h)
        det = inp.detections
        if det is not None:
            w.t1 = time.perf_counter()
            w.tm["detect"] = inp.detect_ms
        else:
            det = self.detector.detect(inp.image)
            w.t1 = time.perf_counter()
            w.tm["detect"] = (w.t1 - w.t0) * 1e3
        if isinstance(det, Detections):
            w.ids, w.corners = det.ids, det.corners
            w.events, w.restart, w.mode = det.events, det.restart, det.mode
        else:
            w.ids, w.corners = det
        self._times = self.observation_times(inp, w.ids, w.corners)
        if w.restart:  # the view changed: estimation starts again
            self.reset_incremental()
            self.configure_filter()
        w.incremental = self.settings.fixed_camera

    def _pose_step(self, w: _Work) -> None:
        """The frame's observations: every marker posed, or with a fixed camera what did
        not change reused and the robots placed (and sent) before the poses when the
        session can."""
        if not w.incremental:
            w.obs, w.diag = self.poses(w.ids, w.corners)
            return
        s = self.session
        models = self._models()
        plan = s.plan(w.ids, w.corners, self.refit_every)
        early = (s.early_robots(plan, w.ids, models, relay=w.on_robots is not None)
                 if self.robot_specs else None)
        if early is not None:
            w.robots = self._send_robots(w, early.estimate)
        w.obs, w.diag = s.observations(w.ids, plan, models, early)
        w.corners, w.deferred = plan.corners, plan.deferred

    def _replay_step(self, w: _Work) -> None:
        """Recorded detections and poses (replay: frame-exact, no session)."""
        inp = w.inp
        assert inp.observations is not None  # (the caller's branch)
        w.ids = np.asarray(inp.ids if inp.ids is not None
                           else [o.id for o in inp.observations], dtype=np.int64)
        w.corners = np.asarray(inp.corners if inp.corners is not None
                               else np.zeros((0, 4, 2)), dtype=float)
        w.obs, w.diag = list(inp.observations), dict(inp.diagnostics)
        self._times = self.observation_times(inp, w.ids, w.corners)

    def _models(self) -> Models:
        """What the fixed camera's session places robots with, as the pipeline is now."""
        return Models(self.estimator, self.algorithm, self.world_map, self.robot_lengths,
                      self.marker_length, self.plane_heights, self.camera.intrinsics,
                      self.poses)

    def _estimate_step(self, w: _Work) -> None:
        """The estimate, with its leave-one-out when asked (one call:
        kmea.estimators.base); a failed estimate for bad observations (never a crash)."""
        intr = self.camera.intrinsics
        try:
            if w.loo:
                w.both = self.estimator.estimate_with_loo(
                    w.obs, self.world_map, exclude=w.deferred, camera=intr,
                    plane_heights=self.plane_heights)
                w.est = w.both.estimate
            else:
                w.est = self.estimator.estimate(w.obs, self.world_map, exclude=w.deferred,
                                                camera=intr, plane_heights=self.plane_heights)
        except ValueError as e:
            w.est = Estimate.failed(self.algorithm, str(e))

    def _send_robots(self, w: _Work, est: Estimate) -> dict[str, RobotFix]:
        """The one place robot fixes are made (:meth:`robot_fixes`, once a frame) and sent
        (``on_robots``); then the caller's background work may run."""
        fixes = self.robot_fixes(est, w.inp.timestamp, w.rejections, self._times)
        if w.on_robots is not None:
            w.on_robots(w.inp.timestamp, fixes)  # the relay: before the leave-one-out work
        if self.background is not None:
            self.background.robots_sent()
        return fixes

    def _filter_step(self, est: Estimate, t: float) -> dict[int, tuple[np.ndarray, float]]:
        """The markers' positions and yaws through the pose filter."""
        markers: dict[int, tuple[np.ndarray, float]] = {}
        if self.filter.alpha == 1.0:  # no filtering: skip the per-marker bookkeeping
            for mid, me in sorted(est.markers.items()):
                markers[mid] = (np.asarray(me.position, dtype=float), float(wrap_angle(me.yaw)))
        else:
            for mid, me in sorted(est.markers.items()):
                p, yaw = self.filter.update(("marker", mid), t, me.position, me.yaw)
                markers[mid] = (np.asarray(p, dtype=float), float(yaw))
        return markers

    def _loo_step(self, w: _Work) -> tuple[dict[int, float], bool]:
        """(leave-one-out errors, computed in this frame): with a fixed camera the last
        errors while the floor's observations are unchanged."""
        both, est = w.both, w.est
        if both is None or not est.ok:
            return {}, True

        def compute() -> dict[int, float]:
            try:
                return both.loo_errors  # computed here, from the estimate's own state
            except ValueError:
                return {}

        if not w.incremental:
            return compute(), True
        refs = [o for o in w.obs if o.id not in w.deferred] if w.deferred else w.obs
        return self.session.loo.get(refs, self.world_map.markers, compute)

    def observation_times(self, inp: FrameInput, ids: np.ndarray, corners: np.ndarray
                          ) -> dict[int, float]:
        """Robot marker id -> the instant it was seen (s): the mid-exposure of its rows (the
        mean row of its corners), from the frame's timing (``inp.meta["timing"]``) as an
        offset from the frame's timestamp (a live source may restamp frames with the unix
        time; the offset stays). Empty without a timing: every marker at the timestamp."""
        timing = inp.meta.get("timing") if inp.meta else None
        self._rates = {}
        if timing is None or not self.robot_lengths or len(ids) == 0:
            return {}
        out = {}
        for k, m in enumerate(np.asarray(ids).tolist()):
            if m in self.robot_lengths:
                rows = np.asarray(corners[k], dtype=float)[:, 1]
                out[int(m)] = inp.timestamp + timing.row_offset(float(rows.mean()))
                if timing.line_s > 0:
                    # The time gradient over the marker (s/m along its own x, y): the least
                    # squares fit of its corner rows against its corners (TL, TR, BR, BL at
                    # (-h, h), (h, h), (h, -h), (-h, -h)), in closed form.
                    k = timing.line_s / (2.0 * self.robot_lengths[m])
                    v0, v1, v2, v3 = rows.tolist()
                    self._rates[int(m)] = ((v1 + v2 - v0 - v3) * k, (v0 + v1 - v2 - v3) * k)
        return out

    def robot_fixes(self, est: Estimate, t: float,
                    rejections: dict[str, str] | None = None,
                    times: Mapping[int, float] | None = None) -> dict[str, RobotFix]:
        """Robot poses from the raw marker estimates (kmea.robots.poses), then filtered per robot
        (the IIR filter, or the tracking filter: a measurement it rejects gives no fix this
        frame, and its reason goes to ``rejections``).

        Each robot's measurement is at its own markers' time (``times``, id -> s: in
        :meth:`process`, :meth:`observation_times` of the frame; else ``t``); the tracking
        filter runs on those times, and its velocity and turn rate bring a pair seen in two
        rows to one instant (kmea.robots.poses)."""
        out: dict[str, RobotFix] = {}
        self.measured = {}
        times = times or {}
        rates = self._rates if times is self._times else {}
        for spec in self.robot_specs:
            motion = None
            if self.tracker is not None and times:
                seen = tuple(m for m in spec.markers if m in est.markers)
                tm = robot_time(spec, seen, times) if seen else None
                # the motion matters for a pair seen at two instants and a skewed square
                need = tm is not None and (any(m in rates for m in seen) or (
                    len(seen) == 2 and times[seen[0]] != times[seen[1]]))
                st = self.tracker.predict(spec.name, tm) if need and tm is not None else None
                if st is not None:
                    motion = (st.vx, st.vy, st.omega)
            pose = robot_pose(spec, est.markers, times, motion, rates)
            if pose is None:
                continue
            tp = t if pose.t is None else pose.t
            self.measured[spec.name] = (tp, pose.x, pose.y, pose.theta, pose.sigma)
            if self.tracker is not None:
                o = self.tracker.update(spec.name, tp, pose.x, pose.y, pose.theta, pose.sigma)
                if not o.accepted or o.state is None:
                    if rejections is not None:
                        rejections[spec.name] = o.reason
                    continue
                st = o.state
                out[spec.name] = RobotFix(spec.name, st.x, st.y, st.theta, st.sigma,
                                          list(pose.markers_seen), st.vx, st.vy, st.omega,
                                          raw=(pose.x, pose.y, pose.theta, pose.sigma),
                                          t=tp, cov=st.cov)
                continue
            p, th = self.filter.update(("robot", spec.name), tp,
                                       np.array([pose.x, pose.y, pose.z]), pose.theta)
            out[spec.name] = RobotFix(spec.name, float(p[0]), float(p[1]), float(th),
                                      pose.sigma, list(pose.markers_seen), t=tp)
        return out
