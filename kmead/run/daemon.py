"""The daemon: source -> pipeline -> outputs, plus the control/status service thread.

The daemon is the shell around :class:`kmea.pipeline.Pipeline`: start-up is
:mod:`kmead.config.startup`, where detection happens is a feed of :mod:`kmead.run.capture`, the CSV
rows and totals are :mod:`kmead.outputs.totals`, the datagrams :mod:`kmead.outputs.relay`.

Threads: the main loop (pipeline and outputs, one frame at a time, under ``self.lock``),
the capture thread of a live source (:mod:`kmead.run.capture`) and the service thread
(:mod:`kmead.net.control`: control requests, 1 Hz status, the stale-robot watchdog). A control
request takes the lock between two frames, so it waits at most one frame and never stalls
capture.
"""

from __future__ import annotations

import collections
import logging
import math
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from kmea.estimators import available as available_algorithms
from kmea.maps.files import MarkerMap
from kmea.pipeline import FrameInput, FrameResult, Pipeline, PipelineSettings
from kmea.recordings.format import Recorder
from kmea.sources.base import FrameSource
from kmea.sources.replay import ReplaySource
from kmea.stats.metrics import WindowStats
from kmea.stats.moved import MovedMonitor
from kmea.timing import blur_warning
from kmea.wire import protocol as P
from kmead.config.layers import Config
from kmead.config.plan import check_camera, plan_startup, robot_ids_problem
from kmead.config.startup import (
    EXIT_CONFIG,
    EXIT_OK,
    EXIT_RUNTIME,
    StartupError,
    configured_map,
    fit_camera,
    is_paced_sim,
    open_configured_source,
)
from kmead.net import bodies
from kmead.net.camera_feed import CameraFeed, camera_body, frame_outlines
from kmead.outputs.csvlog import CsvLog
from kmead.outputs.datadir import FileRefused
from kmead.outputs.files import LowSpace
from kmead.outputs.robots import RobotSender
from kmead.outputs.totals import RunTotals, csv_lines, truth_record
from kmead.run.capture import Capture, CaptureEnded, open_feed
from kmead.run.discovery import Discovery
from kmead.run.extras import ExtraOutputs
from kmead.run.gc_pacing import GcPacing
from kmead.run.live_settings import LiveSettings
from kmead.run.rollback import ChangeGuard

__all__ = ["Daemon", "StartupError"]

log = logging.getLogger("kmead")

DISPLACED_QUIET_S = 30.0
# Frames in a row that failed before any frame succeeded: a configuration under which no
# frame can succeed (the daemon exits 1 naming the first error instead of running forever).
STARTUP_FAILURES = 30


class Daemon(ExtraOutputs):
    """A configured daemon; :meth:`run` processes frames until the end, --frames or stop().

    A service (:class:`kmead.net.service.Service`) with a camera part: its control server
    answers every command (:class:`kmead.net.control.Host` and
    :class:`kmead.net.control.CameraHost`)."""

    # Made by _build, before anything can use them (close() copes with a partial build).
    robots: RobotSender
    source: FrameSource

    def __init__(self, cfg: Config, max_frames: int | None = None) -> None:
        super().__init__(cfg)
        self.max_frames = max_frames
        self.totals = RunTotals()
        self.capture: Capture | None = None
        self.feed = None
        self.gc_pacing: GcPacing | None = None
        self.last_frame_body: Mapping[str, Any] = {}
        self.last_result: FrameResult | None = None
        self.frame_times: collections.deque[float] = collections.deque(maxlen=31)
        self.displaced: dict[int, float] = {}
        self._last_stats_pub = 0.0
        self._last_status_pub = 0.0
        self._blur_warned = False
        self._t_capture = 0.0
        self._last_frame_wall = time.time()
        self.exit_code = EXIT_OK
        # Field kit: liveness, the UI's camera view and log on attach, snapshots, Foxglove.
        self.run_state = "starting"  # running, then stopped: in the status telemetry
        self.camera_feed = CameraFeed()
        self.last_image = None  # the last processed frame's image (snapshots)
        self.foxglove = None
        self.zenoh = None  # kmead.outputs.zenoh.ZenohOutput when [zenoh] enabled = true
        self.zenoh_camera = None  # kmead.outputs.zenoh_camera.ZenohCamera, with it
        self.live_settings = LiveSettings(cfg, self._reconfigure, self.event,
                                          self._setting_problem)
        self.frames_read = 0  # what --frames counts: frames that came in, failed or not
        self._fail_streak = 0
        self._first_failure: str | None = None
        self._succeeded = False
        try:
            self._build()
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ construction
    def _build(self) -> None:
        cfg = self.cfg
        # Every configuration problem is found here, as `kmead --check` finds it (exit 2);
        # what follows can fail only at opening (exit 1).
        plan = plan_startup(cfg)
        for w in plan.warnings:
            log.warning("%s", w)
        self.world_map = plan.world_map
        # The order of opening is the reverse of closing (kmead.net.service): the network
        # first (it closes last, after the "stopped" status), the control server last.
        self._secure_network()
        try:
            self.open_telemetry(log_level=logging.NOTSET)
        except OSError as e:
            raise StartupError(str(e), EXIT_RUNTIME) from None
        logging.getLogger("kmead").setLevel(cfg["log"]["level"].upper())
        self.source = open_configured_source(cfg)
        self.closing.callback(self._close_source)
        self.source_spec = cfg["source"]["spec"]
        self.replay = isinstance(self.source, ReplaySource)
        self.live = bool(getattr(self.source, "live", False)) or is_paced_sim(cfg)
        camera = fit_camera(cfg, plan.camera, self.source)
        check_camera(cfg, camera)
        if isinstance(self.source, ReplaySource) and self.source.header.get("fast_path"):
            log.warning("replay: %s was recorded with the fixed-camera fast path "
                        "(detector.fixed_camera on a live source), which refits the floor every "
                        "detector.fixed_refit_every frames; the replay refits every frame, so "
                        "its rows differ slightly (record with --set detector.fixed_camera=false "
                        "for rows identical to the recorded run's)", self.source_spec)
        try:
            self.open_files(self.totals, self._new_recorder)
        except FileRefused as e:
            raise StartupError(f"key 'log.dir': {e}") from None
        # The tracking detector's background detection: one thread of the daemon's (the
        # library starts none), started on first use.
        self.discovery = Discovery()
        self.closing.callback(self.discovery.shutdown, wait=False, cancel_futures=True)
        try:
            self.pipeline = Pipeline(camera, self.world_map, self._settings(),
                                     background=self.discovery)
        except ValueError as e:  # detector parameters, dictionary, algorithm options
            raise StartupError(f"{cfg.files[-1]}: detector: {e}") from None
        self.closing.callback(self.pipeline.close)
        self.stats = WindowStats(cfg["stats"]["window"], self.world_map.ref_length())
        self.monitor = MovedMonitor(cfg["stats"]["displaced_threshold"],
                                    cfg["stats"]["displaced_frames"])
        self.robots = RobotSender(self.open_relay(), self.totals, self.event)
        for key, start in (("csv", self.start_csv), ("record", self.start_recording)):
            if not cfg["log"][key]:
                continue
            try:  # an existing file is never written over (continued or a new name)
                start(cfg["log"][key], keep=True)
            except LowSpace as e:
                # A full disk is the moment's state, not a configuration error: the robots
                # get their poses without this output (event, status "error").
                self.files.refused("log" if key == "csv" else "record", str(e))
            except ValueError as e:  # an unwritable path: name the key, do not start
                raise StartupError(f"key 'log.{key}': {e}") from None
        if cfg.data.get("foxglove", {}).get("enabled"):
            self._start_foxglove()
        if cfg.data.get("zenoh", {}).get("enabled"):
            self._start_zenoh()
        self.last_word(self._now)
        self.closing.callback(self.live_settings.settle)  # a trial comes over control only
        try:
            self.open_control(self, camera=self)
        except OSError as e:
            raise StartupError(str(e), EXIT_RUNTIME) from None

    def _secure_network(self) -> None:
        """CURVE on both sockets when keys are configured (the plan judged the exposure)."""
        net = self.cfg["network"]
        if net["keys"]:
            from kmead.net.keys import KeysError

            try:
                self.open_keys()
            except KeysError as e:
                raise StartupError(str(e), EXIT_CONFIG) from None
            log.info("CURVE on: keys %s (%d operator(s), %d viewer(s))", net["keys"],
                     *self._key_counts())

    def _key_counts(self) -> tuple[int, int]:
        roles = [r for r, _ in self.curve.ring._roles.values()] if self.curve else []
        return roles.count("operator"), roles.count("viewer")

    def _settings(self) -> PipelineSettings:
        """The pipeline's settings from the configuration (tracking only for live sources)."""
        return PipelineSettings.from_config(self.cfg.data, live=self.live)

    # ------------------------------------------------------------------ files
    # The CSV log and the recording are kmead.outputs.files.FileOutputs; control and the
    # summary reach them through these.
    @property
    def csv(self) -> CsvLog | None:
        return self.files.csv

    @property
    def recorder(self) -> Recorder | None:
        return self.files.recorder

    def start_csv(self, path: str, remote: bool = False, keep: bool = False) -> CsvLog:
        return self.files.start_csv(path, remote, keep)

    def stop_csv(self) -> dict:
        return self.files.stop_csv()

    def start_recording(self, path: str, remote: bool = False, keep: bool = False
                        ) -> Recorder:
        return self.files.start_recording(path, remote, keep)

    def stop_recording(self) -> dict:
        return self.files.stop_recording()

    def _new_recorder(self, path: str | Path, part: int = 1,
                      previous: str | None = None) -> Recorder:
        return Recorder(path, self.pipeline.camera, self.world_map, self.source_spec,
                        self.cfg.to_dict(), fast_path=self.pipeline.settings.fixed_camera,
                        part=part, previous=previous)

    # ------------------------------------------------------------------ live settings
    # kmead.run.live_settings: check, apply, trial, rollback, save; the daemon's part is
    # what follows a change.
    def apply_setting(self, key: str, value: Any, remote: bool = False) -> Any:
        return self.live_settings.set(key, value, remote)

    def save_config(self, path: str | None = None) -> dict:
        return self.live_settings.save(path)

    @property
    def guard(self) -> ChangeGuard:
        return self.live_settings.guard

    def _setting_problem(self, key: str, value: Any) -> str | None:
        return robot_ids_problem(self.cfg, self.world_map, value) if key == "robots" else None

    def _reconfigure(self, key: str, v: Any) -> None:
        """Make the running parts follow the configuration after ``key`` became ``v``."""
        section = key.partition(".")[0]
        self.pipeline.settings = self._settings()
        if key == "estimator.algorithm":
            self.pipeline.set_algorithm(v)
            self.stats.reset()
        elif key == "estimator.unknown_plane":
            self.pipeline.set_algorithm(self.pipeline.algorithm)
        elif key.startswith("filter."):
            self.pipeline.configure_filter()
        elif section == "detector":
            self.pipeline.configure_detector()
        elif key == "robots":
            self.pipeline.configure_robots()
            self.relay.configure(v, t=self._now())
            if self.zenoh is not None:
                self.zenoh.retain({r["name"] for r in v})
        elif key.startswith("relay."):
            self.relay.apply(self.cfg["relay"])
        elif key == "stats.window":
            self.stats = WindowStats(v, self.world_map.ref_length())
        elif key in ("stats.displaced_threshold", "stats.displaced_frames"):
            self.monitor = MovedMonitor(self.cfg["stats"]["displaced_threshold"],
                                        self.cfg["stats"]["displaced_frames"])
        elif key == "log.level":
            logging.getLogger("kmead").setLevel(v.upper())

    def _now(self) -> float:
        """The time of the last frame (the relay's clock), else the wall clock."""
        return self.last_result.timestamp if self.last_result is not None else time.time()

    def reload_map(self) -> MarkerMap:
        new = configured_map(self.cfg, self.source)
        self.world_map = new
        self.pipeline.set_map(new)
        self.stats = WindowStats(self.cfg["stats"]["window"], new.ref_length())
        self.displaced.clear()
        self.monitor.clear()
        log.info("map reloaded: %s (%d markers)", new.name, len(new))
        if self.zenoh_camera is not None:
            self.zenoh_camera.set_meta(self._camera_meta())
        return new

    # ------------------------------------------------------------------ telemetry bodies
    def status(self) -> P.StatusBody:
        """The ``status`` body now (kmead.net.bodies.status_body from this daemon's state)."""
        return bodies.status_body(
            t0=self.t0, source=self.source_spec,
            config_file=self.cfg.user_file or "<default config>",
            config_files=self.cfg.files, algorithm=self.pipeline.algorithm,
            algorithms=available_algorithms(live=True), csv=self.csv, recorder=self.recorder,
            output_errors=self.files.errors,
            camera=self.pipeline.camera, world_map=self.world_map,
            frames=self.totals.frames, dropped=self.dropped,
            bad_frames=self.totals.bad_frames,
            telemetry=self.telemetry.bound if self.telemetry else "",
            control=self.control.bound if self.control else "",
            stopped=self.run_state == "stopped")

    def state(self) -> dict[str, Any]:
        """``get_state``: the status, the last frame and the statistics."""
        return {"status": self.status(), "frame": self.last_frame_body,
                "stats": bodies.stats_body(self.stats, self.pipeline.algorithm,
                                           self.last_result)}

    def progress(self) -> dict:
        """A snapshot for the headless status line and systemd STATUS (any thread)."""
        with self.lock:  # between two frames: the robot tracks are not changing
            return self._progress()

    def _progress(self) -> dict:
        tracks = self.relay.channels.values()
        loo = self.stats.mean_error
        return {"frames": self.totals.frames, "fps": self.fps(),
                "robots_tracked": sum(1 for tr in tracks
                                      if tr.last_seen is not None and not tr.stale),
                "robots": len(self.cfg["robots"]),
                "loo_mean_m": loo if loo is not None and math.isfinite(loo) else None,
                "dropped": self.dropped, "bad_frames": self.totals.bad_frames}

    @property
    def dropped(self) -> int:
        if self.feed is not None:
            return self.feed.dropped
        return self.capture.dropped if self.capture else 0

    def fps(self) -> float:
        ts = self.frame_times
        if len(ts) < 2 or ts[-1] <= ts[0]:
            return 0.0
        return (len(ts) - 1) / (ts[-1] - ts[0])

    def _check_blur(self, meta: dict) -> None:
        """Warn once when the camera's exposure smears a robot at ``filter.max_speed`` by
        more than :data:`kmea.timing.BLUR_WARN_M` (docs/motion.md)."""
        timing = meta.get("timing")
        if timing is None or timing.exact or timing.exposure_s <= 0:
            return  # files, the simulator: nothing a setting can change
        self._blur_warned = True
        speed = float(self.cfg["filter"]["max_speed"])
        msg = blur_warning(timing.exposure_s, speed)
        if msg:
            self.event("warning", msg)

    # ------------------------------------------------------------------ per frame
    def _frame_input(self, frame, capture_ms: float, t_cap: float) -> FrameInput:
        ts = frame.timestamp
        stamped = "sensor_timestamp_ns" in frame.meta or frame.meta.get("unix_time")
        age = time.time() - ts if stamped else -1.0
        if self.live and 0.0 <= age < 60.0:
            # picamera: the frame's time is the sensor's (the start of readout as unix time,
            # kmea.sources.picamera); a wall-clock simulator's, the instant it drew the
            # robots. The datagram's t and the latency count from it, not from when Python
            # received the frame (docs/speed.md: the latency budget).
            # A stamp in the future or a minute old is not trusted.
            t_cap = time.perf_counter() - age
        elif self.live:
            # Live: unix time of the capture, so robots can age a fix with their own clock.
            ts = time.time() - (time.perf_counter() - t_cap)
        rep = frame.meta.get("replay")
        if rep is not None:
            ids, corners, obs, diag = rep
            return FrameInput(frame.index, ts, None, ids, corners, obs, diag, frame.meta, t_cap,
                              capture_ms)
        return FrameInput(frame.index, ts, frame.image, meta=frame.meta, t_capture=t_cap,
                          capture_ms=capture_ms)

    def process_frame(self, frame, capture_ms: float, t_cap: float,
                      detections=None, detect_ms: float = 0.0) -> FrameResult | None:
        """One frame through the pipeline and every output (caller holds ``self.lock``)."""
        self.progress_t = time.monotonic()
        if frame.image is None and "replay" not in frame.meta:
            self.totals.bad_frames += 1
            self.event("warning", f"frame {frame.index}: {frame.meta.get('error', 'no image')}"
                                  "; skipped")
            return None
        inp = self._frame_input(frame, capture_ms, t_cap)
        self.robots.time_step(inp.timestamp, self.cfg["relay"]["max_time_step_s"], self.pipeline)
        if not self._blur_warned:
            self._check_blur(frame.meta)
        self._t_capture = inp.t_capture
        if detections is not None:
            inp.detections, inp.detect_ms = detections, detect_ms
        try:
            res = self.pipeline.process(inp, on_robots=self._relay_robots)
        except Exception as e:  # a frame the detector or pose cannot digest: report, go on
            self.totals.bad_frames += 1
            text = f"frame {frame.index}: {type(e).__name__}: {e}"
            self.event("error", f"{text}; skipped")
            log.debug("frame failure", exc_info=True)
            self._fail_streak += 1
            if self._first_failure is None:
                self._first_failure = " ".join(text.split())  # one line
            self.live_settings.judge(False)
            return None
        self._fail_streak = 0
        self._succeeded = True
        self._outputs(res)
        self._camera_outputs(frame.image, res)
        self.live_settings.judge(bool(res.estimate.ok))
        return res

    def _camera_outputs(self, image, res: FrameResult) -> None:
        """The Camera tab's thumbnail (while watched) and Foxglove (when enabled)."""
        self.last_image = image
        lease = self.camera_feed.due() if image is not None else None
        if lease is None and self.foxglove is None:
            return
        cache: list = []

        def marks() -> list:  # the outlines, computed once and only when something uses them
            if not cache:
                cache.append(frame_outlines(res.observations, set(res.estimate.rejected),
                                            res.estimate.cam2world, self.pipeline.camera,
                                            self.world_map))
            return cache[0]

        if lease is not None and image is not None:
            self.publish(P.TOPIC_CAMERA, camera_body(image, marks(), lease.width, lease.height,
                                                     res.index, res.timestamp))
        if self.foxglove is not None:
            from kmead.viewers.foxglove import FrameView, MarkerView, RobotView

            rejected = set(res.estimate.rejected)
            suspect = {o.id for o in res.observations if o.suspect}
            markers = [MarkerView(mid, p, yaw, "rejected" if mid in rejected else
                                  "suspect" if mid in suspect else "detected")
                       for mid, (p, yaw) in res.markers.items()]
            robots = [RobotView(tr.name, tr.x, tr.y, tr.theta, tr.name in res.robots)
                      for tr in self.relay.channels.values() if tr.last_seen is not None]
            self.foxglove.publish(FrameView(res.timestamp, res.index, image, marks, markers,
                                            robots, res.estimate.cam2world))

    def snapshot(self, overlay: bool = False) -> dict:
        """Save the last frame as PNG in the data directory (kmead's working directory)."""
        from kmea.vision.overlay import focus_measure
        from kmead.outputs.snapshot import Limits, save_snapshot

        with self.lock:  # between two frames: take the image and what to draw on it
            res, image = self.last_result, self.last_image
            image = None if image is None else image.copy()
            marks = [] if res is None or not overlay else frame_outlines(
                res.observations, set(res.estimate.rejected), res.estimate.cam2world,
                self.pipeline.camera, self.world_map)
        focus = None
        if overlay and image is not None and image.ndim == 2:
            focus = focus_measure(image, [m.corners for m in marks if m.kind != "expected"])
        # PNG encoding (tens of ms at full size) happens outside the lock.
        lg = self.cfg["log"]
        limits = Limits(lg["snapshots_max"], lg["snapshots_max_mb"], lg["min_free_mb"])
        path = save_snapshot(image, res.index if res else -1, self.data_dir.root, marks, focus,
                             overlay, limits)
        log.info("snapshot saved: %s", path)
        return {"path": str(path), "frame": res.index if res else None, "overlay": overlay}

    def _outputs(self, res: FrameResult) -> None:
        t_out = time.perf_counter()
        tot = self.totals
        for text in res.events:  # e.g. the tracking detector noticed a bumped camera
            self.event("warning", f"frame {res.index}: {text}")
        # 2. statistics
        tot.add_frame(res)
        for mid, e in res.loo.items():
            self.stats.add(mid, e)
        self._displacement_events(res)
        for name, reason in res.robot_rejections.items():
            self.event("warning", f"robot {name}: measurement rejected by the tracking "
                                  f"filter: {reason}")
        # 3. files: a failing disk stops that file only, never the frame or the robots
        files = self.files
        files.watch_space()
        if files.csv is not None:
            files.write_csv(csv_lines(res, self.world_map, self.pipeline.robot_heights))
        if files.recorder is not None:
            truth = res.meta.get("truth")
            files.write_frame(lambda r: r.write_frame(
                res.index, res.timestamp, res.ids, res.corners, res.observations,
                res.diagnostics, truth_record(truth) if truth is not None else None))
        # 4. telemetry
        self.publish(P.TOPIC_MARKERS, bodies.markers_body(res, self.world_map,
                                                          self.monitor.get))
        self.publish(P.TOPIC_ROBOTS, bodies.robots_body(res, self.relay.channels.values()))
        now = time.perf_counter()
        if self.control is None and now - self._last_status_pub >= \
                self.cfg["network"]["status_period_s"]:
            self._last_status_pub = now  # no service thread: status from the frame loop
            self.publish(P.TOPIC_STATUS, self.status())
        if now - self._last_stats_pub >= 0.2:
            self._last_stats_pub = now
            self.publish(P.TOPIC_STATS, bodies.stats_body(self.stats, self.pipeline.algorithm,
                                                          res))
        self.frame_times.append(now)
        self._last_frame_wall = time.time()
        res.timings["output"] = (time.perf_counter() - t_out) * 1e3
        res.timings["total"] = sum(v for k, v in res.timings.items() if k != "total")
        for k, v in res.timings.items():
            tot.timing_sums[k] = tot.timing_sums.get(k, 0.0) + v
        self.last_frame_body = bodies.frame_body(res, source=self.source_spec, fps=self.fps(),
                                                 dropped=self.dropped,
                                                 bad_frames=self.totals.bad_frames)
        self.publish(P.TOPIC_FRAME, self.last_frame_body)
        self.last_result = res

    def _relay_robots(self, t: float, fixes: dict) -> None:
        """The pipeline's ``on_robots``: what the robots get, as soon as the poses are known
        (kmead.outputs.robots); latency compensation on live sources only (a file's
        timestamps are not the wall clock)."""
        self.robots.send(t, fixes, self.pipeline.tracker,
                         predict=bool(self.cfg["filter"]["predict"]) and self.live,
                         t_capture=self._t_capture, measured=self.pipeline.measured)

    def _displacement_events(self, res: FrameResult) -> None:
        # The moved-marker decision (kmea.stats.moved: persistence over the frames the marker was
        # measured in, a threshold scaled to the error level) from its LOO error or a robust
        # estimator's rejection distance; the markers body publishes it with its evidence.
        # The event is quiet for that marker for DISPLACED_QUIET_S (noise near the
        # threshold must not flood the technician's log). Suspect markers give no figure.
        figures = dict(res.loo)
        for mid, d in res.estimate.rejected.items():
            figures[mid] = max(figures.get(mid, 0.0), d)
        fx = float(self.pipeline.camera.fx)
        gsd = {o.id: float(o.marker2cam_t[2]) / fx for o in res.observations if fx > 0}
        bad = self.monitor.update(figures, gsd)
        now = time.monotonic()
        for mid, ev in sorted(bad.items()):
            if ev.offset is None or ev.threshold is None:
                continue  # (a moved marker has both)
            if now - self.displaced.get(mid, -math.inf) >= DISPLACED_QUIET_S:
                self.displaced[mid] = now
                self.event("warning", f"marker {mid} looks displaced by "
                                      f"{ev.offset * 1e3:.0f} mm (threshold "
                                      f"{ev.threshold * 1e3:.0f} mm over {ev.frames} frames)")


    # ------------------------------------------------------------------ service thread hooks
    def tick(self) -> None:
        """Called by the service thread about every 100 ms."""
        if self.live:
            # No frame for a while (camera stalled): robots still go stale on the wall clock.
            now = time.time()
            if now - self._last_frame_wall >= self.cfg["relay"]["stale_after_s"]:
                with self.lock:
                    # close() runs under the lock (SIGTERM): nothing to tick after it
                    for name in self.relay.tick(now) if not self.closed else ():
                        # The frames stopped, not the robot: say which.
                        self.event("warning", f"no frame for {now - self._last_frame_wall:.1f}"
                                              f" s (the camera or this machine stalled): robot "
                                              f"{name} stale (valid=0 sent)")

    # ------------------------------------------------------------------ public bodies
    # ------------------------------------------------------------------ main loop
    def run(self) -> int:
        """Process frames until the source ends, ``max_frames`` or :meth:`stop`.

        The one run loop: the feed decides where detection happens (main thread, a thread
        of its own for a live source, a pool for files; :func:`kmead.run.capture.open_feed`).
        """
        paced = is_paced_sim(self.cfg)
        self.capture = Capture(self.source, threaded=self.live,
                               pace_fps=self.cfg["source"]["fps"] if paced else 0.0)
        if self.control is not None:
            self.control.start()
        self.totals.t_start = time.perf_counter()
        self.run_state = "running"
        self.publish(P.TOPIC_STATUS, self.status())
        log.info("running: source %s, algorithm %s, map %s (%d markers)", self.source_spec,
                 self.pipeline.algorithm, self.world_map.name, len(self.world_map))
        self.feed = open_feed(self.capture, self.pipeline, self.cfg["detector"]["workers"],
                              self.live, self.replay)
        # Live: the garbage collector runs between frames, not inside one (kmead.run.gc_pacing).
        self.gc_pacing = GcPacing() if self.live else None
        try:
            while not self.stop_event.is_set():
                if self.max_frames is not None and self.frames_read >= self.max_frames:
                    break
                try:
                    got = self.feed.get(timeout=0.1)
                except CaptureEnded as e:
                    self._source_ended(e)
                    self._check_complete()
                    break
                self.progress_t = time.monotonic()
                if got is not None:
                    (frame, cap_ms, t_cap), det, det_ms = got
                    self.frames_read += 1
                    with self.lock:
                        self.process_frame(frame, cap_ms, t_cap, det, det_ms)
                    if not self._succeeded and self._fail_streak >= STARTUP_FAILURES:
                        break
                if self.gc_pacing is not None:
                    self.gc_pacing.idle()
        finally:
            if self.gc_pacing is not None:
                self.gc_pacing.close()
            self.feed.close()
            self.totals.t_end = time.perf_counter()
        self._check_never_succeeded()
        return self.exit_code

    def _check_never_succeeded(self) -> None:
        """Frames came in, every one failed, none succeeded: the configuration cannot work
        (exit 1 with the first error), whether STARTUP_FAILURES or --frames ended the run."""
        if self._succeeded or self._first_failure is None:
            return
        if self.stop_event.is_set() and self._fail_streak < STARTUP_FAILURES:
            return  # stopped before the frames could tell
        self.event("error", f"no frame succeeded: {self._fail_streak} failed in a row from "
                            f"the start; stopping. The first: {self._first_failure}")
        self.exit_code = EXIT_RUNTIME

    def _check_complete(self) -> None:
        """A file source that announced more frames than it gave was cut short."""
        src = self.source
        want, got = getattr(src, "expected_frames", 0), getattr(src, "frames_read", None)
        if want and got is not None and got < want and not self.stop_event.is_set() and (
                self.max_frames is None or self.totals.frames < self.max_frames):
            self.event("error", f"source {self.source_spec} ended after {got} of the {want} "
                                "frames it announces (file truncated or damaged)")
            self.exit_code = EXIT_RUNTIME

    def _source_ended(self, e: CaptureEnded) -> None:
        if e.args and e.args[0]:
            self.event("error", f"source stopped: {e.args[0]}")
            self.exit_code = EXIT_RUNTIME

    # ------------------------------------------------------------------ closing
    # Each registered on self.closing as its part opens (kmead.net.service.Service.close).
    def _close_source(self) -> None:
        if self.capture is not None:  # it closes the source
            self.capture.close()
        else:
            self.source.close()

    def farewell(self) -> None:
        """Announce the end, so a UI shows "daemon stopped" instead of frozen data."""
        if self.telemetry is not None and self.run_state != "starting":
            self.run_state = "stopped"
            self.telemetry.event("info", "kmead stopped")
            self.publish(P.TOPIC_STATUS, self.status())

    # ------------------------------------------------------------------ summary
    def summary(self) -> str:
        from kmead.run.summary import format_summary  # summary.py reads the daemon it is given

        return format_summary(self)

