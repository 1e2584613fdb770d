"""``kmea fuse``: the fusion node, one picture from several cameras (docs/fusion.md).

Each camera runs ``kmead`` and publishes its robots' poses on its telemetry socket
(``robot.NAME`` topics: capture time, pose, sigma). The node subscribes to every input,
fuses each robot's measurements through the tracking filter (:class:`kmea.robots.fusion.Fusion`)
and serves the same outputs as a daemon: telemetry (``robot.NAME``, ``robots`` with the
cameras that saw each robot, ``status``, ``event``, ``log``), control (the daemon's
commands that make sense without a camera), UDP datagrams to the robots and the CSV log in
the daemon's format (``kind`` robot, ``algorithm`` fusion, ``refs`` the number of cameras).

Everything an input sends is hostile: a message that does not decode, lacks a field or has
a non-finite number is counted and reported once per input, never raised.

Time: the fusion clock is the newest measurement time, advanced by the wall clock between
measurements (so it works on the Pis' Unix time and on simulated time); robots go stale
on it. A camera that stops leaves its robots stale (valid=0) and is picked up again when
it returns: the SUB sockets reconnect by themselves.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import zmq

from kmea.maps.files import MapError
from kmea.robots.fusion import Fusion, Measurement
from kmea.robots.tracking import TrackerConfig
from kmea.wire import protocol as P
from kmead.config.layers import Config, ConfigError
from kmead.config.plan import network_exposure
from kmead.net.bodies import map_info
from kmead.net.keys import CurveServer, KeysError
from kmead.net.telemetry import Telemetry, TelemetryLogHandler
from kmead.outputs.csvlog import CsvLog, row
from kmead.outputs.datadir import DataDir
from kmead.outputs.relay import Relay
from kmead.run.log_ring import LogRing
from kmead.run.startup import StartupError, configured_map

log = logging.getLogger("kmead.fusion")

__all__ = ["FusionNode", "Input", "tracker_config"]


def tracker_config(cfg: Config) -> TrackerConfig:
    """The tracking filter's configuration from the ``[filter]`` section."""
    return TrackerConfig.from_table(cfg["filter"])


def secure_subscriber(sock: zmq.Socket, endpoint: str, cfg: Config) -> None:
    """With ``network.keys``: make ``sock`` a CURVE client of the cameras (before it
    connects to ``endpoint``) with the key pair ``clients/fusion.key_secret`` of that
    directory, else ``clients/operator.key_secret`` (``kmea keys add DIR fusion --viewer``:
    the node only watches the cameras). The cameras must share the key directory's server
    key. Without keys the inputs are plain TCP (keep them on loopback or a private network).
    """
    keys = cfg["network"]["keys"]
    if not keys:
        return
    from pathlib import Path

    from kmea.wire.curve_client import CurveKeyError, apply_client_keys

    name = "fusion" if (Path(keys).expanduser() / "clients" / "fusion.key_secret").exists() \
        else "operator"
    try:
        apply_client_keys(sock, keys, name)
    except CurveKeyError as e:
        raise ConfigError(f"network.keys: {e}") from None


@dataclass
class Input:
    """One camera's telemetry: label (cam0, cam1, ...), endpoint and counters."""

    label: str
    endpoint: str
    sock: zmq.Socket | None = None
    received: int = 0
    measurements: int = 0
    bad: int = 0
    dropped_old: int = 0
    last_wall: float | None = None
    last_t: float | None = None
    delays: deque = field(default_factory=lambda: deque(maxlen=300))  # wall - t, s
    bad_reported: bool = False

    def body(self, now_wall: float) -> dict:
        d = sorted(self.delays)
        return {"label": self.label, "endpoint": self.endpoint, "received": self.received,
                "measurements": self.measurements, "bad": self.bad,
                "dropped_old": self.dropped_old,
                "silent_s": None if self.last_wall is None else now_wall - self.last_wall,
                # Unix-time cameras: arrival minus capture = network + processing + offset.
                "delay_s": d[len(d) // 2] if d else None}


def parse_inputs(items: list[str]) -> list[tuple[str, str]]:
    """``[LABEL=]ENDPOINT`` items -> (label, endpoint); labels default to cam0, cam1, ..."""
    out = []
    for i, item in enumerate(items):
        label, eq, ep = item.partition("=")
        if not eq or "://" in label:
            label, ep = f"cam{i}", item
        if not label.replace("_", "").replace("-", "").isalnum():
            raise ConfigError(f"--input {item!r}: label must be letters, digits, '_' or '-'")
        out.append((label, ep))
    labels = [lb for lb, _ in out]
    if len(set(labels)) != len(labels):
        raise ConfigError(f"--input: duplicate labels {labels}")
    return out


_NUM = (int, float)


def measurement_from(label: str, body: dict, names: set[str]) -> Measurement | None:
    """A measurement from a ``robot.NAME`` body (its ``raw`` measurement when the camera's
    daemon filters with the tracking filter), None for a valid=0 (stale) message;
    ``ValueError`` names the bad field."""
    name = body.get("name")
    if not isinstance(name, str) or name not in names:
        raise ValueError(f"field 'name': unknown robot {name!r}")
    valid = body.get("valid")
    if not isinstance(valid, bool):
        raise ValueError("field 'valid': expected true or false")
    if not valid:
        return None
    raw = body.get("raw")
    # A daemon with the tracking filter sends its filtered pose and the measurement ("raw"):
    # fuse the measurement (filtering filtered poses again would count the noise twice).
    src = {**body, **raw} if isinstance(raw, dict) else body
    vals = {}
    for k in ("t", "x", "y", "theta"):
        v = src.get(k)
        if isinstance(v, bool) or not isinstance(v, _NUM) or not math.isfinite(v):
            raise ValueError(f"field {k!r}: expected a finite number, got {v!r}")
        vals[k] = float(v)
    sigma = src.get("sigma")
    if sigma is not None and (isinstance(sigma, bool) or not isinstance(sigma, _NUM)
                              or not math.isfinite(sigma) or sigma < 0):
        raise ValueError(f"field 'sigma': expected a number >= 0 or null, got {sigma!r}")
    return Measurement(label, name, vals["t"], vals["x"], vals["y"], vals["theta"],
                       None if sigma is None else float(sigma))


class _NoStats:
    """The statistics a fusion node does not have (no markers): an empty window."""

    window = 0
    mean_error = None
    max_error = None

    def per_marker(self) -> dict:
        return {}

    def reset(self) -> None:
        pass


class _NoPipeline:
    algorithm = "fusion"


class FusionNode:
    """The fusion node; :meth:`run` until ``max_outputs`` fused outputs or :meth:`stop`.

    Duck-typed for :class:`kmead.net.control.ControlServer` (``cfg``, ``lock``, ``publish``,
    ``status_body``, ``tick``, ``event`` and the command methods).
    """

    def __init__(self, cfg: Config, inputs: list[tuple[str, str]],
                 max_outputs: int | None = None, context: zmq.Context | None = None) -> None:
        if not inputs:
            raise ConfigError("fusion: no input; give --input ENDPOINT (a camera daemon's "
                              "telemetry) at least once, or fusion.inputs")
        self.cfg = cfg
        self.max_outputs = max_outputs
        self.lock = threading.RLock()
        self.stop_event = threading.Event()
        self.t0 = time.time()
        self.curve = None
        self.log_ring = LogRing()  # the UI's Log tab on attach (get_log), as a daemon's
        net = cfg["network"]
        try:
            warnings = network_exposure(cfg)
        except StartupError as e:
            raise ConfigError(str(e)) from None
        for w in warnings:
            log.warning("%s", w)
        # A keyed node has its own context: one ZAP handler per context (kmead.net.keys).
        self._own_ctx = zmq.Context() if net["keys"] else None
        self.ctx = self._own_ctx or context or zmq.Context.instance()
        if net["keys"]:
            try:
                self.curve = CurveServer(self.ctx, net["keys"])
            except KeysError as e:
                self.close()
                raise ConfigError(str(e)) from None
        self.data_dir = DataDir(cfg["log"]["dir"])
        try:  # the floor the robots are on: the UI's map outline (map.file, else built-in)
            self.world_map = configured_map(cfg, None)
        except MapError as e:
            self.close()
            raise ConfigError(f"map: {e}") from None
        self.fusion = Fusion(tracker_config(cfg), cfg["fusion"]["max_age_s"])
        self.names = {r["name"] for r in cfg["robots"]}
        self.telemetry = Telemetry(cfg["network"]["telemetry"], self.ctx, curve=self.curve)
        self._log_handler = TelemetryLogHandler(self.telemetry)
        logging.getLogger("kmead").addHandler(self._log_handler)
        logging.getLogger("kmead").addHandler(self.log_ring)
        self.relay = Relay(cfg["robots"], cfg["relay"]["stale_after_s"],
                           cfg["relay"]["stale_repeat_s"], publish=self.publish,
                           extra_fields=cfg["relay"]["extra_fields"])
        self.inputs = [Input(label, ep) for label, ep in inputs]
        for inp in self.inputs:
            s = self.ctx.socket(zmq.SUB)
            s.setsockopt(zmq.LINGER, 0)
            s.setsockopt(zmq.RCVHWM, 10000)
            s.setsockopt(zmq.MAXMSGSIZE, P.MAX_MESSAGE_BYTES + 4096)
            s.setsockopt(zmq.RECONNECT_IVL, 100)
            s.setsockopt(zmq.RECONNECT_IVL_MAX, 1000)
            secure_subscriber(s, inp.endpoint, cfg)
            try:
                s.connect(inp.endpoint)
            except zmq.ZMQError as e:
                s.close()
                self.close()
                raise ConfigError(f"--input {inp.endpoint!r}: {e}") from None
            s.setsockopt(zmq.SUBSCRIBE, P.TOPIC_ROBOT_PREFIX.encode())
            inp.sock = s
        self.csv: CsvLog | None = None
        if cfg["log"]["csv"]:
            self.start_csv(cfg["log"]["csv"])
        self.outputs = 0
        self.rejected_events = 0
        self.latency_ms: deque = deque(maxlen=100000)
        self._clock_t = -math.inf  # fusion clock at _clock_wall
        self._clock_wall = time.monotonic()
        self._last_robots_pub = 0.0
        self.control = None
        if cfg["network"]["control"]:
            from kmead.net.control import ControlServer

            try:
                self.control = ControlServer(cfg["network"]["control"], self, self.ctx,
                                             curve=self.curve)
            except OSError:
                self.close()
                raise

    # ------------------------------------------------------------------ clock
    def clock(self) -> float:
        """The fusion clock: newest measurement time + wall time since it arrived."""
        if not math.isfinite(self._clock_t):
            return -math.inf
        return self._clock_t + (time.monotonic() - self._clock_wall)

    # ------------------------------------------------------------------ messages
    def handle(self, inp: Input, frames: list[bytes], t_recv: float) -> bool:
        """One message of one input; True when it produced a fused output."""
        inp.received += 1
        now_wall = time.time()
        inp.last_wall = now_wall
        try:
            topic, body = P.decode(frames)
            if not topic.startswith(P.TOPIC_ROBOT_PREFIX):
                return False
            m = measurement_from(inp.label, body, self.names)
        except ValueError as e:  # ProtocolError is a ValueError
            inp.bad += 1
            if not inp.bad_reported:
                inp.bad_reported = True
                self.event("warning", f"input {inp.label} ({inp.endpoint}): bad message "
                                      f"ignored: {e} (further ones are only counted)")
            return False
        if m is None:
            return False
        inp.measurements += 1
        inp.last_t = m.t
        inp.delays.append(now_wall - m.t)
        out = self.fusion.add(m)
        if out is None:
            inp.dropped_old += 1
            return False
        if m.t >= self._clock_t or not math.isfinite(self._clock_t):
            self._clock_t, self._clock_wall = m.t, time.monotonic()
        if out.kind == "rejected":
            self.rejected_events += 1
            self.event("warning", f"robot {m.name}: measurement of {inp.label} rejected: "
                                  f"{out.reason}")
            return False
        if out.kind == "reacquired":
            self.event("warning", f"robot {m.name}: re-acquired from {inp.label}: {out.reason}")
        self._output(m, t_recv)
        return True

    def _output(self, m: Measurement, t_recv: float) -> None:
        tr = self.fusion.tracker.tracks[m.name]
        t_out = tr.t  # the newest measurement time of this robot
        if self.cfg["filter"]["predict"]:
            t_out = max(t_out, self.clock())
        st = tr.predict(t_out)
        srcs = self.fusion.sources(m.name, self.cfg["relay"]["stale_after_s"])
        extra = {"vx": st.vx, "vy": st.vy, "omega": st.omega, "age": st.t - tr.t,
                 "source": "+".join(srcs), "t_capture": tr.t}
        self.relay.update(m.name, st.t, st.x, st.y, st.theta, st.sigma, extra)
        self.outputs += 1
        if self.csv is not None:
            self.csv.write_rows([row(self.outputs, st.t, "fusion", "robot", m.name, st.x, st.y,
                                     None, st.theta, st.sigma, len(srcs))])
        self.latency_ms.append((time.perf_counter() - t_recv) * 1e3)
        now = time.perf_counter()
        if now - self._last_robots_pub >= 1.0 / 30.0:
            self._last_robots_pub = now
            self.publish(P.TOPIC_ROBOTS, self.robots_body())

    # ------------------------------------------------------------------ bodies
    def robots_body(self) -> dict:
        now = self.clock()
        out = []
        for tr in self.relay.tracks.values():
            seen = tr.last_seen is not None
            srcs = self.fusion.sources(tr.name, self.cfg["relay"]["stale_after_s"])
            last = self.fusion.seen.get(tr.name)
            track = self.fusion.tracker.tracks.get(tr.name)
            st = track.state() if track is not None and track.started else None
            out.append({"name": tr.name, "markers": tr.markers,
                        "x": tr.x if seen else None, "y": tr.y if seen else None,
                        "theta": tr.theta if seen else None, "sigma": tr.sigma,
                        "valid": seen and not tr.stale,
                        "age_s": (now - tr.last_seen) if seen else None,
                        "stale": tr.stale, "destinations": tr.destinations, "sent": tr.sent,
                        "seq": tr.seq, "send_errors": tr.errors,
                        "send_refused": tr.refused, "refused": tr.refused_now(),
                        "source": "+".join(srcs),
                        "sources": {s: now - t for s, t in last.last.items()} if last else {},
                        "vx": st.vx if st else None, "vy": st.vy if st else None,
                        "omega": st.omega if st else None})
        return {"t": now if math.isfinite(now) else time.time(), "frame": self.outputs,
                "robots": out}

    def status(self) -> P.StatusBody:
        """The ``status`` body: a daemon's, without camera (zeros) and map (its robots),
        plus ``inputs`` and ``fusion``."""
        c = self.csv
        now_wall = time.time()
        lat = sorted(self.latency_ms)
        return {
            "t": now_wall, "uptime": now_wall - self.t0,
            "source": "fusion: " + ", ".join(f"{i.label}={i.endpoint}" for i in self.inputs),
            "config_file": self.cfg.user_file or "<default config>",
            "config_files": self.cfg.files, "algorithm": "fusion", "algorithms": ["fusion"],
            "logging": {"active": c is not None, "path": str(c.path) if c else None,
                        "rows": c.rows if c else 0, "bytes": c.bytes if c else 0},
            "recording": {"active": False, "path": None, "frames": 0, "bytes": 0},
            "camera": {"width": 0, "height": 0, "fx": 0.0, "fy": 0.0},
            "map": map_info(self.world_map),
            "frames": self.outputs, "dropped": sum(i.dropped_old for i in self.inputs),
            "bad_frames": sum(i.bad for i in self.inputs),
            "inputs": [i.body(now_wall) for i in self.inputs],
            "fusion": {"accepted": self.fusion.accepted,
                       "rejected": self.fusion.tracker.counts["rejected"],
                       "reacquired": self.fusion.tracker.counts["reacquired"],
                       "dropped_old": self.fusion.dropped_old,
                       "latency_ms_p50": lat[len(lat) // 2] if lat else None,
                       "latency_ms_p99": lat[min(len(lat) - 1, int(0.99 * len(lat)))]
                       if lat else None},
            "telemetry": self.telemetry.bound, "control": self.control.bound
            if self.control else "",
        }

    # ------------------------------------------------------------------ daemon interface
    def publish(self, topic: str, body: Mapping[str, Any]) -> None:
        self.telemetry.publish(topic, body)

    def event(self, level: str, text: str) -> None:
        getattr(log, "warning" if level == "warning" else level, log.info)(text)

    # No frames, no marker statistics, no camera: what the control thread reads.
    last_frame_body: dict = {}  # never mutated
    last_result = None
    pipeline = _NoPipeline()
    stats = _NoStats()
    camera_feed = None
    replay = False

    def tick(self) -> None:
        """Stale robots on the fusion clock (called by the control thread and the loop)."""
        now = self.clock()
        if not math.isfinite(now):
            return
        with self.lock:
            for name in self.relay.tick(now):
                self.event("warning", f"robot {name} not seen for "
                                      f"{self.relay.stale_after_s:g} s: stale (valid=0 sent)")
                self.publish(P.TOPIC_ROBOTS, self.robots_body())

    def start_csv(self, path: str, remote: bool = False) -> CsvLog:
        if self.csv is not None:
            self.csv.close()
        if remote:  # over control: a new plain name in the data directory (kmead.outputs.datadir)
            path = str(self.data_dir.create(path, "log"))
        try:
            self.csv = CsvLog(path)
        except OSError as e:
            raise OSError(f"log.csv: cannot open {path}: {e.strerror or e}") from None
        return self.csv

    def stop_csv(self) -> dict:
        c = self.csv
        if c is None:
            return {"path": None, "rows": 0}
        c.close()
        self.csv = None
        return {"path": str(c.path), "rows": c.rows}

    def apply_setting(self, key: str, value: Any, remote: bool = False) -> Any:
        if key not in ("relay.stale_after_s", "relay.stale_repeat_s", "log.level"):
            raise ValueError(f"{key}: not settable on a fusion node (restart it with --set)")
        v = self.cfg.set(key, value, remote=remote)
        self.relay.stale_after_s = self.cfg["relay"]["stale_after_s"]
        self.relay.stale_repeat_s = self.cfg["relay"]["stale_repeat_s"]
        return v

    def _unsupported(self, *_: Any) -> dict:
        raise ValueError("not available on a fusion node (no camera)")

    start_recording = stop_recording = reload_map = save_config = snapshot = _unsupported

    # ------------------------------------------------------------------ run
    def run(self) -> int:
        if self.control is not None:
            self.control.start()
        self.publish(P.TOPIC_STATUS, self.status())
        log.info("fusion: %d inputs (%s), telemetry %s", len(self.inputs),
                 ", ".join(i.endpoint for i in self.inputs), self.telemetry.bound or "off")
        poller = zmq.Poller()
        by_sock = {}
        for inp in self.inputs:
            poller.register(inp.sock, zmq.POLLIN)
            by_sock[inp.sock] = inp
        next_tick = time.monotonic()
        last_status = time.monotonic()
        try:
            while not self.stop_event.is_set() and not self.done():
                for sock, _ in poller.poll(50):
                    inp = by_sock[sock]
                    # Drain what is there, oldest first, then look at the other inputs.
                    # --frames N is checked before every message: when several are queued
                    # the Nth output must still be the last one.
                    for _ in range(1000):
                        if self.done():
                            break
                        try:
                            frames = sock.recv_multipart(zmq.NOBLOCK)
                        except zmq.Again:
                            break
                        t_recv = time.perf_counter()
                        with self.lock:
                            self.handle(inp, frames, t_recv)
                now = time.monotonic()
                if now >= next_tick:
                    next_tick = now + 0.05
                    self.tick()
                if self.control is None and now - last_status >= \
                        self.cfg["network"]["status_period_s"]:
                    last_status = now
                    self.publish(P.TOPIC_STATUS, self.status())
        except zmq.ZMQError as e:
            if e.errno != zmq.ETERM:
                raise
        return 0

    def done(self) -> bool:
        """True once ``max_outputs`` fused outputs have been made."""
        return self.max_outputs is not None and self.outputs >= self.max_outputs

    def stop(self) -> None:
        self.stop_event.set()

    def close(self) -> None:
        if getattr(self, "control", None) is not None:
            self.control.stop()
            self.control = None
        for inp in getattr(self, "inputs", []):
            if inp.sock is not None:
                inp.sock.close(linger=0)
                inp.sock = None
        if getattr(self, "csv", None) is not None:
            self.csv.close()
        if getattr(self, "_log_handler", None) is not None:
            logging.getLogger("kmead").removeHandler(self._log_handler)
            self._log_handler = None
        if getattr(self, "log_ring", None) is not None:
            logging.getLogger("kmead").removeHandler(self.log_ring)
        if getattr(self, "relay", None) is not None:
            try:  # robots must not keep following the last fused pose
                self.relay.shutdown(time.time())
            except Exception:
                log.exception("relay shutdown")
            self.relay.close()
            self.relay = None
        if getattr(self, "telemetry", None) is not None:
            self.telemetry.close()
            self.telemetry = None
        if getattr(self, "curve", None) is not None:
            self.curve.stop()
            self.curve = None
        if getattr(self, "_own_ctx", None) is not None:
            self._own_ctx.term()
            self._own_ctx = None

    def summary(self) -> str:
        lat = sorted(self.latency_ms)
        p99 = f"{lat[min(len(lat) - 1, int(0.99 * len(lat)))]:.2f} ms" if lat else "-"
        per = ", ".join(f"{i.label}: {i.measurements} measurements, {i.bad} bad, "
                        f"{i.dropped_old} too old" for i in self.inputs)
        return (f"kmea fuse: {self.outputs} fused outputs; {per}; rejected "
                f"{self.fusion.tracker.counts['rejected']}, re-acquired "
                f"{self.fusion.tracker.counts['reacquired']}; added latency p99 {p99}")



# ---------------------------------------------------------------------------- command line
def add_arguments(p: Any) -> None:
    """``kmea fuse`` options (as for kmead, plus --input)."""
    p.add_argument("--input", metavar="[LABEL=]ENDPOINT", action="append", default=[],
                   help="a camera daemon's telemetry endpoint (repeat for each camera; "
                        "labels default to cam0, cam1, ...); adds to fusion.inputs")
    p.add_argument("--config", metavar="FILE", help="configuration file overlaid on the default")
    p.add_argument("--set", metavar="SECTION.KEY=VALUE", action="append", default=[],
                   help="override any configuration key; VALUE is TOML (repeatable)")
    p.add_argument("--log", metavar="FILE.csv", help="CSV log of every fused pose (log.csv)")
    p.add_argument("--map", metavar="FILE", help="the floor's map, drawn by the terminal UI "
                                                 "(map.file; default: the built-in one)")
    p.add_argument("--headless", action="store_true", help="no terminal UI")
    p.add_argument("--frames", metavar="N", type=int, help="stop after N fused outputs")


def run(args: Any) -> int:
    """Run the fusion node; exit codes as kmead's (0 done, 1 runtime failure, 2 config)."""
    import sys

    from kmead.cli import stderr_logging
    from kmead.config.layers import load_config

    if args.frames is not None and args.frames < 1:
        print("kmea fuse: --frames: must be >= 1", file=sys.stderr)
        return 2
    try:
        overrides = {k: v for k, v in (("log.csv", args.log), ("map.file", args.map)) if v}
        cfg = load_config(args.config, args.set, overrides or None)
        inputs = parse_inputs([*cfg["fusion"]["inputs"], *args.input])
        node = FusionNode(cfg, inputs, max_outputs=args.frames)
    except ConfigError as e:
        print(f"kmea fuse: configuration error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"kmea fuse: {e}", file=sys.stderr)
        return 1
    with stderr_logging(cfg["log"]["level"]):
        if cfg["zenoh"]["enabled"]:
            # Said, not silently ignored: the fused poses go by UDP and ZeroMQ only so far.
            log.warning("zenoh: [zenoh] is not used by kmea fuse yet; its robots get UDP "
                        "datagrams (docs/ros2.md)")
        return _serve(node, args)


def _serve(node: FusionNode, args: Any) -> int:
    """The node's run (with the UI or headless), then its summary; closes the node."""
    import signal
    import sys

    from kmead.cli import _run_with_ui

    print(f"kmea fuse: telemetry {node.telemetry.bound or 'off'}, control "
          f"{node.control.bound if node.control else 'off'}", file=sys.stderr, flush=True)
    ui = not args.headless and sys.stdout.isatty() and sys.stdin.isatty()
    code = 0
    try:
        if ui:
            code = _run_with_ui(node)
        else:
            previous = {s: signal.signal(s, lambda *_: node.stop())
                        for s in (signal.SIGINT, signal.SIGTERM)}
            try:
                code = node.run()
            finally:
                for s, h in previous.items():
                    signal.signal(s, h)
    except KeyboardInterrupt:
        node.stop()
    finally:
        summary = node.summary()
        node.close()
    print(summary, flush=True)
    return code


def main(argv: list[str] | None = None) -> int:
    """``python -m kmead.fusion.node [options]``: ``kmea fuse`` in a process of its own (the
    fusion-node benchmark starts it so)."""
    import argparse
    import sys

    p = argparse.ArgumentParser(prog="kmea fuse", description=add_arguments.__doc__)
    add_arguments(p)
    return run(p.parse_args(sys.argv[1:] if argv is None else argv))


if __name__ == "__main__":
    raise SystemExit(main())
