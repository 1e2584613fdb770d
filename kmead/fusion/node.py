"""``kmea fuse``: the fusion node, one picture from several cameras (docs/fusion.md).

Each camera runs ``kmead`` with ``[zenoh] enabled = true`` and publishes its robots'
measurements under ``<site>/cam/<id>/...`` (:mod:`kmead.outputs.zenoh_camera`). The node
finds the cameras by subscription, not configuration: a camera's liveliness token makes it
known, its metadata (asked once) must carry the node's map digest or it is refused with a
reason (:mod:`kmead.fusion.cameras`), its measurements are fused through the tracking filter
(:class:`kmea.robots.fusion.Fusion`). A camera whose token goes (killed: at once; frozen or
cut off: after the lease) or that sends nothing for the lease (its frame loop stuck) is
dropped; it is used again when it comes back.

Two or more nodes may run hot; the active one speaks to the robots, each robot once the
camera speaking to it hands over (:mod:`kmead.fusion.speaker`). The node serves a daemon's
ZeroMQ outputs (telemetry, :mod:`kmead.fusion.bodies`; control; the CSV log: ``kind``
robot, ``algorithm`` fusion, ``refs`` the number of cameras).

Everything received over Zenoh is hostile: a key or payload that does not decode, a missing
or non-finite field is counted and reported once per camera, never raised. Zenoh's callbacks
only queue what arrives (bounded; the measurements wait in Zenoh's ring buffers); the node's
loop owns every piece of state.

Time: the fusion clock is the newest measurement time, advanced by the wall clock between
measurements (so it works on the Pis' Unix time and on simulated time); robots go stale on
it.
"""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import re
import time
from collections import deque
from typing import Any

import zmq

from kmea.maps.files import MapError, map_digest
from kmea.robots.fusion import Fusion, Measurement
from kmea.robots.tracking import TrackerConfig
from kmea.wire import protocol as P
from kmead.config.layers import Config, ConfigError
from kmead.config.plan import network_exposure
from kmead.config.site_tls import certificate_name
from kmead.config.startup import StartupError, configured_map
from kmead.fusion.bodies import robots_body, state_body, status_body
from kmead.fusion.cameras import Camera, check_meta, make_room
from kmead.fusion.inputs import Limits, admit
from kmead.fusion.speaker import Speaker
from kmead.net.keys import KeysError
from kmead.net.service import Service
from kmead.outputs.csvlog import CsvLog, row
from kmead.outputs.files import LowSpace

log = logging.getLogger("kmead.fusion")

__all__ = ["FusionNode", "tracker_config"]

MAX_CAMERAS = 64  # cameras known at once (gone ones make room first)
QUEUE_MAX = 20000  # samples waiting for the loop; beyond, the oldest are dropped
POLL_S = 0.001  # s: the loop's sleep when nothing came
_ID_RE = re.compile(r"^[A-Za-z0-9_-]{1,32}$")


def tracker_config(cfg: Config) -> TrackerConfig:
    """The tracking filter's configuration from the ``[filter]`` section."""
    return TrackerConfig.from_table(cfg["filter"])


class FusionNode(Service):
    """The fusion node; :meth:`run` until ``max_outputs`` fused outputs or :meth:`stop`.

    A service (:class:`kmead.net.service.Service`) without a camera part: its control
    server answers the commands of every service (:class:`kmead.net.control.Host`) and
    refuses a camera's with one line.
    """

    def __init__(self, cfg: Config, max_outputs: int | None = None,
                 context: zmq.Context | None = None, session: Any = None) -> None:
        super().__init__(cfg)
        self.max_outputs = max_outputs
        self.session: Any = None
        self.zenoh_out: Any = None  # kmead.outputs.zenoh.ZenohOutput while active
        self._subs: list[Any] = []
        self._data: list[Any] = []  # the data subscribers (ring channels)
        self.guard = None  # no change on trial: nothing of a camera to roll back
        self.z = {**cfg["zenoh"], "enabled": True}  # the node lives on Zenoh
        self.lease_s = float(self.z["lease_s"])
        self.site = self.z["site"]
        try:
            try:
                warnings = network_exposure(cfg)
                from kmead.config.plan import zenoh_plan

                warnings += zenoh_plan(cfg, self.z)
            except StartupError as e:
                raise ConfigError(str(e)) from None
            for w in warnings:
                log.warning("%s", w)
            try:  # the daemon's one set-up: a context of its own with the ZAP handler
                self.open_keys()
            except KeysError as e:
                raise ConfigError(str(e)) from None
            context = self.zmq_context or context or zmq.Context.instance()
            self.open_telemetry(context)
            self.open_files()  # the CSV log (no recording: no frames)
            try:  # the floor the robots are on: map.file, else the first camera's
                self.world_map = configured_map(cfg, None)
            except MapError as e:
                raise ConfigError(f"map: {e}") from None
            # Without map.file the node takes the map of the first camera it uses; the
            # others must have the same.
            self.map_digest: str | None = map_digest(self.world_map) \
                if cfg["map"]["file"] else None
            self.map_name = self.world_map.name if cfg["map"]["file"] else None
            self.fusion = Fusion(tracker_config(cfg), cfg["fusion"]["max_age_s"])
            self.names = {r["name"] for r in cfg["robots"]}
            self.open_relay().muted = True  # until this node is the active one
            self.cameras: dict[str, Camera] = {}
            self.queue: queue.Queue = queue.Queue(QUEUE_MAX)
            self.overflow = 0  # events dropped: the loop fell behind by QUEUE_MAX
            self.foreign = 0  # samples of strangers: no camera of that id (no token)
            self.table_full_reported = False
            self.limits = Limits.of(cfg["fusion"], self.world_map.extent())
            self.camera_extent: tuple[float, ...] | None = None  # the first camera's map
            # The daemon's rules for its files (never truncating, the data directory over
            # control, the free-space floor, a failing disk stops the log only).
            if cfg["log"]["csv"]:
                try:
                    self.files.start_csv(cfg["log"]["csv"], keep=True)
                except LowSpace as e:
                    self.files.refused("log", str(e))
                except ValueError as e:
                    raise ConfigError(f"key 'log.csv': {e}") from None
            self.outputs = 0
            self.rejected_events = 0
            self.latency_ms: deque = deque(maxlen=100000)
            self._clock_t = -math.inf  # fusion clock at _clock_wall
            self._clock_wall = time.monotonic()
            self._last_robots_pub = 0.0
            self._open_zenoh(session)
            self.speaker = Speaker(self)  # the election, its token, the voice per robot
            self.closing.callback(self.speaker.close)
            self.closing.callback(self._close_zenoh_out)
            self.election = self.speaker.election
            self.last_word(time.time)
            self.open_control(self, context=context)
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ Zenoh
    def _open_zenoh(self, session: Any) -> None:
        from kmead.outputs.zenoh_session import open_session

        self._owns_session = session is None
        self.session = session if session is not None else open_session(self.z)
        self.closing.callback(self._close_zenoh)
        # With TLS a node's id is its certificate's name: the site's ACL lets it hold
        # tokens under <site>/fusion/<that name>/ only.
        self.node_id = (certificate_name(self.z["tls_cert"]) if self.z.get("tls_cert")
                        else str(self.session.info.zid()))
        q, site = self.queue, self.site
        from kmead.outputs.zenoh_session import import_zenoh

        ring = import_zenoh().handlers.RingChannel

        def on_liveliness(kind: str) -> Any:
            def cb(sample: Any) -> None:
                alive = str(sample.kind).rsplit(".", 1)[-1] == "PUT"
                try:
                    q.put_nowait((kind, str(sample.key_expr), alive, 0.0))
                except queue.Full:
                    self.overflow += 1
            return cb

        live = self.session.liveliness()
        # The measurements wait in Zenoh's own ring buffers (no Python on Zenoh's threads
        # per sample: that cost a third of the node's capacity); when the loop falls behind
        # by QUEUE_MAX the oldest go.
        self._data = [
            self.session.declare_subscriber(f"{site}/cam/*/robots/*", ring(QUEUE_MAX)),
            self.session.declare_subscriber(f"{site}/cam/*/frame", ring(QUEUE_MAX))]
        self._subs = [
            *self._data,
            live.declare_subscriber(f"{site}/cam/*", on_liveliness("camera"), history=True),
            live.declare_subscriber(f"{site}/fusion/*/*", on_liveliness("node"),
                                    history=True),
            # Each camera's session token: two kmead claiming one camera id (status).
            live.declare_subscriber(f"{site}/cam/*/zid/*", on_liveliness("twin"),
                                    history=True)]

    # ------------------------------------------------------------------ clock
    def clock(self) -> float:
        """The fusion clock: newest measurement time + wall time since it arrived."""
        if not math.isfinite(self._clock_t):
            return -math.inf
        return self._clock_t + (time.monotonic() - self._clock_wall)

    # ------------------------------------------------------------------ what arrives
    def handle(self, kind: str, key: str, value: Any, t_recv: float) -> bool:
        """One queued item; True when it produced a fused output. Never raises on input."""
        if kind == "data":
            return self._sample(key, value, t_recv)
        parts = key.split("/")
        if kind == "camera" and len(parts) == 3 and _ID_RE.match(parts[2]):
            self._camera_token(parts[2], value)
        elif kind == "node" and len(parts) == 4:
            self.election.token(parts[2], parts[3], value)
        elif kind == "twin" and len(parts) == 5 and _ID_RE.match(parts[2]):
            self._twin(parts[2], parts[4][:32], value)
        elif kind == "meta":
            self._meta(key, value)
        return False

    def _camera(self, cam_id: str) -> Camera | None:
        cam = self.cameras.get(cam_id)
        if cam is None:
            if not make_room(self.cameras, MAX_CAMERAS, time.monotonic() - self.lease_s):
                if not self.table_full_reported:
                    self.table_full_reported = True
                    self.event("warning", f"camera {cam_id}: not admitted: {MAX_CAMERAS} "
                                          "cameras known, none gone or silent")
                return None
            cam = self.cameras[cam_id] = Camera(cam_id, f"{self.site}/cam/{cam_id}")
        return cam

    def _camera_token(self, cam_id: str, alive: bool) -> None:
        cam = self._camera(cam_id)
        if cam is None:
            self.foreign += 1
            return
        if alive:
            if cam.state in ("gone", "silent") or cam.meta is None:
                cam.state, cam.reason = "waiting", None
                cam.meta = None
                self._ask(cam)
        elif cam.state != "gone":
            was = cam.state
            cam.state, cam.reason = "gone", "its liveliness token went (stopped, or cut off)"
            if was == "used":
                self._drop_sources(cam)
            self.event("warning", f"camera {cam.label}: gone (its session closed or its "
                                  "lease ran out): dropped")

    def _twin(self, cam_id: str, zid: str, alive: bool) -> None:
        """A session's token of camera ``cam_id``: more than one is two kmead, one id."""
        cam = self._camera(cam_id)
        if cam is not None:
            (cam.sessions.add if alive else cam.sessions.discard)(zid)
            if alive and len(cam.sessions) > 1:
                self.event("error", f"camera {cam.label}: {len(cam.sessions)} kmead claim "
                                    "this camera id: give each its own zenoh.camera")

    def _ask(self, cam: Camera) -> None:
        """Ask the camera's metadata; the answer comes back through the queue."""
        cam.asked = time.monotonic()
        q = self.queue

        def on_reply(reply: Any) -> None:
            ok = reply.ok
            try:
                q.put_nowait(("meta", cam.label, ok.payload.to_bytes() if ok is not None
                              else None, 0.0))
            except queue.Full:
                self.overflow += 1

        try:
            self.session.get(f"{cam.key}/meta", on_reply, timeout=self.lease_s)
        except Exception as e:  # a session closing
            log.debug("zenoh: metadata query of %s failed: %s", cam.label, e)

    def _meta(self, cam_id: str, payload: bytes | None) -> None:
        cam = self.cameras.get(cam_id)
        if cam is None or cam.state != "waiting" or payload is None:
            return
        try:
            meta = check_meta(payload)
        except ValueError as e:
            self._refuse(cam, f"metadata: {e}")
            return
        cam.meta = meta
        if self.map_digest is None:
            self.map_digest, self.map_name = meta["map_digest"], meta["map_name"]
            if meta.get("extent") is not None:  # the floor the measurements must be on
                self.limits = Limits.of(self.cfg["fusion"], meta["extent"])
                self.camera_extent = tuple(meta["extent"])
            log.info("map: %s (%s), the first camera's (%s); the other cameras must have the "
                     "same (or set map.file)", self.map_name, self.map_digest, cam.label)
        if meta["map_digest"] != self.map_digest:
            self._refuse(cam, f"its map {meta['map_name']!r} ({meta['map_digest']}) is not "
                              f"the node's {self.map_name!r} ({self.map_digest})")
            return
        cam.state, cam.reason = "used", None
        cam.last_mono = time.monotonic()  # the data timeout starts now
        self.event("info", f"camera {cam.label}: used ({meta['width']}x{meta['height']}, "
                           f"{meta['source']})")

    def _refuse(self, cam: Camera, reason: str) -> None:
        cam.state, cam.reason = "refused", reason
        self.event("warning", f"camera {cam.label}: refused: {reason}")

    def _drop_sources(self, cam: Camera) -> None:
        """A dropped camera no longer counts among the robots' sources."""
        for seen in self.fusion.seen.values():
            seen.last.pop(cam.label, None)

    def _sample(self, key: str, payload: bytes, t_recv: float) -> bool:
        parts = key.split("/")
        # Only a camera with a token has an entry: data under invented ids cannot fill the
        # table (they are counted as strangers).
        cam = self.cameras.get(parts[2]) if len(parts) >= 4 else None
        if cam is None:
            self.foreign += 1
            if self.foreign == 1:
                self.event("info", f"data on {key[:80]!r} from no camera known (no token): "
                                      "ignored (further ones counted: status strangers)")
            return False
        cam.received += 1
        now_wall, now_mono = time.time(), time.monotonic()
        cam.last_wall, cam.last_mono = now_wall, now_mono
        if cam.state == "silent":
            cam.state, cam.reason = "used", None
            self.event("info", f"camera {cam.label}: sends again: used")
        m = admit(cam, parts, payload, now_wall, self.names, self.limits, self.cfg["fusion"],
                  self.event)
        if m is None:
            return False
        if cam.state != "used":
            cam.ignored += 1
            if cam.state == "waiting" and now_mono - cam.asked >= self.lease_s:
                self._ask(cam)  # the first answer was lost, or the token came late
            return False
        cam.measurements += 1
        cam.last_t = m.t
        out = self.fusion.add(m)
        if out is None:
            cam.dropped_old += 1
            return False
        if m.t >= self._clock_t or not math.isfinite(self._clock_t):
            self._clock_t, self._clock_wall = m.t, time.monotonic()
        if not out.accepted:  # gated out, or refused (a non-finite or singular step)
            self.rejected_events += 1
            self.event("warning", f"robot {m.name}: measurement of {cam.label} rejected: "
                                  f"{out.reason}")
            return False
        if out.kind == "reacquired":
            self.event("warning", f"robot {m.name}: re-acquired from {cam.label}: "
                                  f"{out.reason}")
        self._output(m, t_recv)
        return True

    def _watch_cameras(self, now_mono: float) -> None:
        """Drop a used camera silent for the lease (alive, but its frame loop is stuck);
        ask again the metadata of a waiting one."""
        for cam in self.cameras.values():
            if cam.state == "used" and cam.last_mono is not None \
                    and now_mono - cam.last_mono >= self.lease_s:
                cam.state = "silent"
                cam.reason = f"nothing for {self.lease_s:g} s (the lease)"
                self._drop_sources(cam)
                self.event("warning", f"camera {cam.label}: silent for {self.lease_s:g} s: "
                                      "dropped")
            elif cam.state == "waiting" and now_mono - cam.asked >= self.lease_s:
                self._ask(cam)

    def _output(self, m: Measurement, t_recv: float) -> None:
        tr = self.fusion.tracker.tracks[m.name]
        t_meas = tr.t if tr.t is not None else m.t  # the newest measurement time
        t_out = t_meas
        if self.cfg["filter"]["predict"]:
            t_out = max(t_out, self.clock())
        st = tr.predict(t_out)
        if st is None:
            return
        srcs = self.fusion.sources(m.name, self.cfg["relay"]["stale_after_s"])
        extra = {"vx": st.vx, "vy": st.vy, "omega": st.omega, "age": st.t - t_meas,
                 "source": "+".join(srcs), "t_capture": t_meas}
        self.relay.update(m.name, st.t, st.x, st.y, st.theta, st.sigma, extra, cov=st.cov)
        self.outputs += 1
        files = self.files
        if files.csv is not None:
            files.watch_space()
            files.write_csv([row(self.outputs, st.t, "fusion", "robot", m.name, st.x, st.y,
                                 None, st.theta, st.sigma, len(srcs))])
        self.latency_ms.append((time.perf_counter() - t_recv) * 1e3)
        now = time.perf_counter()
        if now - self._last_robots_pub >= 1.0 / 30.0:
            self._last_robots_pub = now
            self.publish(P.TOPIC_ROBOTS, self.robots_body())

    # ------------------------------------------------------------------ bodies
    def robots_body(self) -> dict:
        return robots_body(self)

    def status(self) -> P.StatusBody:
        """The ``status`` body (kmead.fusion.bodies)."""
        return status_body(self)

    def state(self) -> dict[str, Any]:
        """``get_state``: the status; no frame and no marker statistics (kmead.fusion.bodies)."""
        return state_body(self)

    # ------------------------------------------------------------------ the service's part
    def event(self, level: str, text: str) -> None:
        """A log line (the ``log`` telemetry topic carries it)."""
        getattr(log, "warning" if level == "warning" else level, log.info)(text)

    def tick(self) -> None:
        """Stale robots on the fusion clock (called by the control thread and the loop)."""
        now = self.clock()
        if not math.isfinite(now):
            return
        with self.lock:
            if self.closed:  # close() runs under the lock
                return
            relay = self.relay
            for name in relay.tick(now):
                self.event("warning", f"robot {name} not seen for "
                                      f"{relay.stale_after_s:g} s: stale (valid=0 sent)")
                self.publish(P.TOPIC_ROBOTS, self.robots_body())

    @property
    def csv(self) -> CsvLog | None:
        return self.files.csv

    def start_csv(self, path: str, remote: bool = False, keep: bool = False) -> CsvLog:
        return self.files.start_csv(path, remote, keep)

    def stop_csv(self) -> dict:
        return self.files.stop_csv()

    def apply_setting(self, key: str, value: Any, remote: bool = False) -> Any:
        if key not in ("relay.stale_after_s", "relay.stale_repeat_s", "relay.max_sigma_m",
                       "log.level"):
            raise ValueError(f"{key}: not settable on a fusion node (restart it with --set)")
        v = self.cfg.set(key, value, remote=remote)
        self.relay.stale_after_s = self.cfg["relay"]["stale_after_s"]
        self.relay.stale_repeat_s = self.cfg["relay"]["stale_repeat_s"]
        self.relay.max_sigma_m = self.cfg["relay"]["max_sigma_m"]
        return v

    # ------------------------------------------------------------------ run
    def run(self) -> int:
        if self.control is not None:
            self.control.start()
        self.publish(P.TOPIC_STATUS, self.status())
        log.info("fusion node %s on zenoh site %r (lease %g s), telemetry %s",
                 self.node_id[:8], self.site, self.lease_s,
                 self.telemetry.bound if self.telemetry else "off")
        next_tick = last_status = last_loop = time.monotonic()
        while not self.stop_event.is_set() and not self.done():
            now = self.progress_t = time.monotonic()
            # The election before anything is sent: a node that did not run for the lease
            # (frozen) steps down first.
            stalled = now - last_loop > self.lease_s
            last_loop = now
            with self.lock:
                self.speaker.elect(now, stalled)
                n = self._pump()
            if not n:
                time.sleep(POLL_S)
            if now >= next_tick:
                next_tick = now + 0.05
                with self.lock:
                    self.speaker.elect(now)
                    self._watch_cameras(now)
                self.tick()
            if self.control is None and now - last_status >= \
                    self.cfg["network"]["status_period_s"]:
                last_status = now
                self.publish(P.TOPIC_STATUS, self.status())
        # Stopped on purpose: the robots are handed over before this node goes.
        self.speaker.hand_over(self._pump)
        return 0

    def _pump(self, limit: int = 1000) -> int:
        """Handle what is there, oldest first: the queued events (cameras, nodes,
        metadata), then up to ``limit`` samples; ``--frames N`` is checked before each
        (the Nth output must be the last one). Returns how many were handled."""
        n = 0
        while n < limit and not self.done():
            try:
                item = self.queue.get_nowait()
            except queue.Empty:
                break
            self.handle(*item)
            n += 1
        for sub in self._data:
            while n < limit and not self.done():
                sample = sub.try_recv()
                if sample is None:
                    break
                self.handle("data", str(sample.key_expr), sample.payload.to_bytes(),
                            time.perf_counter())
                n += 1
        return n

    def done(self) -> bool:
        """True once ``max_outputs`` fused outputs have been made."""
        return self.max_outputs is not None and self.outputs >= self.max_outputs

    def _close_zenoh_out(self) -> None:
        if self.zenoh_out is not None:
            self.zenoh_out.close()
            self.zenoh_out = None

    def _close_zenoh(self) -> None:
        for entity in self._subs:
            with contextlib.suppress(Exception):  # a session already closed
                entity.undeclare()
        self._subs = []
        if self.session is not None and self._owns_session:
            try:
                self.session.close()
            except Exception as e:  # zenoh.ZError: "close operation timed out"
                log.warning("zenoh: closing the session: %s", str(e).splitlines()[0])
        self.session = None

    def summary(self) -> str:
        lat = sorted(self.latency_ms)
        p99 = f"{lat[min(len(lat) - 1, int(0.99 * len(lat)))]:.2f} ms" if lat else "-"
        per = ", ".join(f"{i.label} ({i.state}): {i.measurements} measurements, {i.bad} bad, "
                        f"{i.dropped_old} too old" for i in self.cameras.values())
        return (f"kmea fuse: {self.outputs} fused outputs; {per or 'no camera'}; rejected "
                f"{self.fusion.tracker.counts['rejected']}, re-acquired "
                f"{self.fusion.tracker.counts['reacquired']}; added latency p99 {p99}")
