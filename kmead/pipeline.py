"""One frame through the pipeline: detect, per-marker pose, estimator, LOO, filter, robots.

:class:`Pipeline` is pure computation (no sockets, no files): the daemon feeds it frames
(or, for replay, recorded detections and poses) and turns the :class:`FrameResult` into
CSV rows, telemetry and datagrams. Every stage is timed in milliseconds.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from kmea import estimators
from kmea.estimators.base import Estimate, MarkerObservation
from kmea.filters import PoseFilter
from kmea.maps import MarkerMap
from kmea.robots import RobotSpec, robot_pose
from kmea.transforms import wrap_angle
from kmea.vision.camera import CameraModel

STAGES = ("capture", "detect", "pose", "estimate", "loo", "filter", "robots", "output")


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
    detections: tuple[np.ndarray, np.ndarray] | None = None  # done by a worker thread
    detect_ms: float = 0.0


@dataclass
class RobotFix:
    """A robot pose in one frame: world x, y (m), theta (rad), 1-sigma (m) or None."""

    name: str
    x: float
    y: float
    theta: float
    sigma: float | None
    markers: list[int]


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

    @property
    def ok(self) -> bool:
        return self.estimate.ok


class Pipeline:
    """Holds the models and state of the per-frame computation.

    camera: the camera model at the frame size (``None`` until the first frame for live
    sources of unknown size: it is then scaled to the frame). world_map: the marker map.
    config: the daemon's configuration dict (``Config.data``).
    """

    def __init__(self, camera: CameraModel, world_map: MarkerMap, config: dict) -> None:
        self.base_camera = camera
        self.camera = camera
        self.world_map = world_map
        self.config = config
        self.detector = None
        self.estimator = None
        self.algorithm = ""
        self.filter = None
        self.configure(config)

    # ------------------------------------------------------------------ configuration
    def configure(self, config: dict) -> None:
        """(Re)build detector, estimator, filter and robot tables from the config dict."""
        self.config = config
        self.configure_detector()
        self.set_algorithm(config["estimator"]["algorithm"])
        self.configure_filter()
        self.configure_robots()

    def configure_detector(self) -> None:
        from kmea.vision.detection import DetectorConfig

        d = self.config["detector"]
        self.detector_config = DetectorConfig(
            dictionary=d["dictionary"] or self.world_map.dictionary,
            corner_refinement=d["corner_refinement"], parameters=dict(d["parameters"]))
        self.detector = self.new_detector()
        self.detector_generation = getattr(self, "detector_generation", 0) + 1

    def new_detector(self):
        """A detector as configured: :class:`MarkerDetector`, or the stateful
        :class:`kmead.fastdetect.FastDetector` when ``detector.fast`` is on."""
        from kmea.vision.detection import MarkerDetector
        from kmead.fastdetect import FastDetector

        d = self.config["detector"]
        if d["fast"]:
            return FastDetector(self.detector_config, d["fast_window"], d["full_every"])
        return MarkerDetector(self.detector_config)

    def set_algorithm(self, name: str) -> None:
        self.estimator = estimators.get(name)
        self.algorithm = name

    def configure_filter(self) -> None:
        f = self.config["filter"]
        self.filter = PoseFilter(alpha=f["alpha"], reset_after_s=f["reset_after_s"])

    def configure_robots(self) -> None:
        self.robots = list(self.config["robots"])
        self.robot_specs = [RobotSpec(name=r["name"], markers=tuple(r["markers"]),
                                      height=r["height"], length=r["length"],
                                      separation=r["separation"]) for r in self.robots]
        self.robot_lengths = {m: r["length"] for r in self.robots for m in r["markers"]}
        self.robot_heights = {r["name"]: r["height"] for r in self.robots}
        self.plane_heights = {m: r["height"] for r in self.robots for m in r["markers"]
                              if m not in self.world_map}

    def set_map(self, world_map: MarkerMap) -> None:
        self.world_map = world_map
        self.configure_detector()
        self.configure_robots()

    def camera_for(self, width: int, height: int) -> CameraModel:
        if (self.camera.width, self.camera.height) != (width, height):
            self.camera = self.base_camera.scaled_to(width, height)
        return self.camera

    # ------------------------------------------------------------------ per frame
    def detect(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        det = self.detector.detect(image)
        return det.ids, det.corners

    def poses(self, ids: np.ndarray, corners: np.ndarray
              ) -> tuple[list[MarkerObservation], dict]:
        from kmea.vision.marker_pose import estimate_marker_poses

        obs, diag = estimate_marker_poses(
            ids, corners, self.camera, self.robot_lengths, self.world_map,
            self.config["detector"]["marker_length"])
        # Shallow: nothing mutates it, and dataclasses.asdict (deep) cost ~30 us a frame.
        return list(obs), dict(vars(diag))

    def process(self, inp: FrameInput, loo: bool = True,
                on_robots: Callable[[float, dict[str, RobotFix]], None] | None = None
                ) -> FrameResult:
        """Run every stage on one frame; see :class:`FrameResult`.

        on_robots(t, fixes): called as soon as the robot poses are known, before the
        leave-one-out estimates (the relay's latency must not pay for the statistics).
        """
        tm: dict[str, float] = dict.fromkeys(STAGES, 0.0)
        tm["capture"] = inp.capture_ms
        t0 = time.perf_counter()
        if inp.observations is None:
            if inp.image is None:
                raise ValueError(f"frame {inp.index}: no image")
            h, w = inp.image.shape[:2]
            self.camera_for(w, h)
            if inp.detections is not None:
                ids, corners = inp.detections
                t1 = time.perf_counter()
                tm["detect"] = inp.detect_ms
            else:
                ids, corners = self.detect(inp.image)
                t1 = time.perf_counter()
                tm["detect"] = (t1 - t0) * 1e3
            obs, diag = self.poses(ids, corners)
            t2 = time.perf_counter()
            tm["pose"] = (t2 - t1) * 1e3
        else:
            ids = np.asarray(inp.ids if inp.ids is not None else [o.id for o in inp.observations],
                             dtype=np.int64)
            corners = np.asarray(inp.corners if inp.corners is not None
                                 else np.zeros((0, 4, 2)), dtype=float)
            obs, diag = list(inp.observations), dict(inp.diagnostics)
            t2 = time.perf_counter()
        intr = self.camera.intrinsics
        both = None
        try:
            if loo:  # one call: the estimate and its leave-one-out (kmea.estimators.base)
                both = self.estimator.estimate_with_loo(obs, self.world_map, camera=intr,
                                                        plane_heights=self.plane_heights)
                est = both.estimate
            else:
                est = self.estimator.estimate(obs, self.world_map, camera=intr,
                                              plane_heights=self.plane_heights)
        except ValueError as e:  # bad observations: report, never crash the loop
            est = Estimate.failed(self.algorithm, str(e))
        t3 = time.perf_counter()
        tm["estimate"] = (t3 - t2) * 1e3
        markers: dict[int, tuple[np.ndarray, float]] = {}
        if self.filter.alpha == 1.0:  # no filtering: skip the per-marker bookkeeping
            for mid, me in sorted(est.markers.items()):
                markers[mid] = (np.asarray(me.position, dtype=float), float(wrap_angle(me.yaw)))
        else:
            for mid, me in sorted(est.markers.items()):
                p, yaw = self.filter.update(("marker", mid), inp.timestamp, me.position, me.yaw)
                markers[mid] = (np.asarray(p, dtype=float), float(yaw))
        t4 = time.perf_counter()
        tm["filter"] = (t4 - t3) * 1e3
        robots = self.robot_fixes(est, inp.timestamp)
        if on_robots is not None:
            on_robots(inp.timestamp, robots)  # the relay: before the leave-one-out work
        t5 = time.perf_counter()
        tm["robots"] = (t5 - t4) * 1e3
        loo_err: dict[int, float] = {}
        if both is not None and est.ok:
            try:
                loo_err = both.loo_errors  # computed here, from the estimate's own state
            except ValueError:
                loo_err = {}
        tm["loo"] = (time.perf_counter() - t5) * 1e3
        return FrameResult(inp.index, inp.timestamp, self.algorithm, ids, corners, obs, diag,
                           est, markers, loo_err, robots, tm, inp.t_capture, inp.meta)

    def robot_fixes(self, est: Estimate, t: float) -> dict[str, RobotFix]:
        """Robot poses from the raw marker estimates (kmea.robots), then filtered per robot."""
        out: dict[str, RobotFix] = {}
        for spec in self.robot_specs:
            pose = robot_pose(spec, est.markers)
            if pose is None:
                continue
            p, th = self.filter.update(("robot", spec.name), t,
                                       np.array([pose.x, pose.y, pose.z]), pose.theta)
            out[spec.name] = RobotFix(spec.name, float(p[0]), float(p[1]), float(th),
                                      pose.sigma, list(pose.markers_seen))
        return out

