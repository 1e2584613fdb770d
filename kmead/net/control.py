"""Control: a ZeroMQ REP socket served by its own thread (see docs/protocol.md).

The thread also publishes the 1 Hz ``status`` message and runs the daemon's watchdog. Every
request gets exactly one reply: bad JSON, too deep or too large, wrong types, unknown
commands, values out of range, a viewer's request get ``{"v": 2, "ok": false, "error":
"..."}``; nothing a client sends can raise out of this thread, leave the REP socket without
its reply, or hold the pipeline for longer than one frame.

With CURVE keys (``network.keys``) a request is served only if the key that sent it is an
operator's now (kmead.net.keys).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from contextlib import AbstractContextManager
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import zmq

from kmea.wire import protocol as P
from kmead.config.layers import LIVE_KEYS, ConfigError, validate_setting
from kmead.config.schema import ADVANCED
from kmead.net import bodies

if TYPE_CHECKING:
    from kmead.config.layers import Config
    from kmead.net.camera_feed import CameraFeed
    from kmead.net.keys import CurveServer
    from kmead.net.log_ring import LogRing
    from kmead.outputs.datadir import DataDir

log = logging.getLogger("kmead.control")

# Bigger messages are dropped by ZeroMQ itself (the peer is disconnected); between
# MAX_MESSAGE_BYTES and this, the client gets an error reply.
SOCKET_MAX_BYTES = 16 * P.MAX_MESSAGE_BYTES

# What every service answers (a camera's kmead and a fusion node alike), and what only a
# camera's kmead adds: its pipeline's statistics, its camera's image, its recording and map,
# its live settings' save. A service without the camera part answers each of these with
# one line saying so.
SERVICE_COMMANDS = ("ping", "get_state", "get_config", "set", "log_start", "log_stop",
                    "get_log")
CAMERA_COMMANDS = ("record_start", "record_stop", "reload_map", "save_config", "reset_stats",
                   "camera_watch", "snapshot")
COMMANDS = (*SERVICE_COMMANDS, *CAMERA_COMMANDS)
# What a viewer key may ask: everything that only reads (the watch-only role sees all the
# operator sees); the rest changes settings, files or statistics.
READ_ONLY = ("ping", "get_state", "get_config", "camera_watch", "snapshot", "get_log")
# The service without a camera part (kmead.fusion.node).
NO_CAMERA = "not supported by a fusion node (it has no camera)"


class Host(Protocol):
    """What the control thread uses of every service (:mod:`kmead.net.service`): a daemon
    (``kmead.run.daemon.Daemon``) and a fusion node (``kmead.fusion.FusionNode``). Declared
    here so this module imports neither (they create the server); pyright checks that both
    satisfy it where they hand themselves to the server."""

    # Read-only properties: a plain attribute or a property of the host satisfies each.
    @property
    def cfg(self) -> Config: ...
    @property
    def lock(self) -> AbstractContextManager[Any]: ...
    @property
    def data_dir(self) -> DataDir: ...
    @property
    def log_ring(self) -> LogRing: ...

    def status(self) -> P.StatusBody: ...
    def state(self) -> dict[str, Any]: ...  # get_state: status, frame, stats
    def publish(self, topic: str, body: Mapping[str, Any]) -> None: ...
    def event(self, level: str, text: str) -> None: ...
    def tick(self) -> None: ...
    def apply_setting(self, key: str, value: Any, remote: bool = False) -> Any: ...
    def start_csv(self, path: str, remote: bool = False, keep: bool = False) -> Any: ...
    def stop_csv(self) -> dict: ...


class CameraHost(Protocol):
    """What a camera's kmead adds (``kmead.run.daemon.Daemon``): :data:`CAMERA_COMMANDS`."""

    @property
    def stats(self) -> bodies.StatsWindow: ...
    @property
    def camera_feed(self) -> CameraFeed: ...
    @property
    def replay(self) -> bool: ...

    def start_recording(self, path: str, remote: bool = False, keep: bool = False
                        ) -> Any: ...
    def stop_recording(self) -> dict: ...
    def reload_map(self) -> Any: ...
    def save_config(self, path: str | None = None) -> dict: ...
    def snapshot(self, overlay: bool = False) -> dict: ...


class RequestError(ValueError):
    """A request that cannot be served; the text goes to the client."""


def _short(v: Any, n: int = 60) -> str:
    r = repr(v) if not isinstance(v, str) or len(v) < 4 * n else repr(v[: 2 * n])
    return r if len(r) <= n else r[: n - 3] + "..."


def _field(req: dict, name: str, types: type | tuple[type, ...], required: bool = True) -> Any:
    if name not in req or req[name] is None:
        if required:
            raise RequestError(f"field {name!r}: missing")
        return None
    v = req[name]
    if not isinstance(v, types) or (isinstance(v, bool) and bool not in (
            types if isinstance(types, tuple) else (types,))):
        tn = types.__name__ if isinstance(types, type) else "/".join(t.__name__ for t in types)
        raise RequestError(f"field {name!r}: expected {tn}, got {type(v).__name__}")
    return v


class ControlServer:
    """REP socket on ``endpoint`` serving ``daemon``; :meth:`start` runs the thread.

    camera: the host's camera part (:class:`CameraHost`), None for a service without one:
    then :data:`CAMERA_COMMANDS` are refused with one line (:data:`NO_CAMERA`)."""

    def __init__(self, endpoint: str, daemon: Host, context: zmq.Context | None = None,
                 poll_ms: int = 100, curve: CurveServer | None = None,
                 camera: CameraHost | None = None) -> None:
        self.daemon = daemon
        self.camera = camera
        self.poll_ms = poll_ms
        self.curve = curve
        ctx = context or zmq.Context.instance()
        self.sock = ctx.socket(zmq.REP)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.setsockopt(zmq.MAXMSGSIZE, SOCKET_MAX_BYTES)
        if curve is not None:
            curve.secure(self.sock, "control")
        try:
            self.sock.bind(endpoint)
        except zmq.ZMQError as e:
            self.sock.close()
            raise OSError(f"network.control: cannot bind {endpoint}: {e}") from None
        self.bound = self.sock.getsockopt_string(zmq.LAST_ENDPOINT)
        self.requests = 0
        self.errors = 0
        # The command table: every command of COMMANDS the host answers and its handler (a
        # test holds them equal), typed, instead of looking a method up by the request's
        # text; the camera's commands only with the camera part.
        self.handlers: dict[str, Callable[[dict], dict]] = {
            "ping": self._cmd_ping, "get_state": self._cmd_get_state,
            "get_config": self._cmd_get_config, "set": self._cmd_set,
            "log_start": self._cmd_log_start, "log_stop": self._cmd_log_stop,
            "get_log": self._cmd_get_log,
        }
        if camera is not None:
            self.handlers.update({
                "record_start": self._cmd_record_start, "record_stop": self._cmd_record_stop,
                "reload_map": self._cmd_reload_map, "save_config": self._cmd_save_config,
                "reset_stats": self._cmd_reset_stats, "camera_watch": self._cmd_camera_watch,
                "snapshot": self._cmd_snapshot})
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="kmead-control", daemon=True)

    def start(self) -> None:
        if not self._thread.is_alive():
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout=2.0)
        self.sock.close(linger=0)

    def _run(self) -> None:
        period = self.daemon.cfg["network"]["status_period_s"]
        next_status = time.monotonic() + period
        while not self._stop.is_set():
            try:
                if self.sock.poll(self.poll_ms, zmq.POLLIN):
                    frames = self.sock.recv_multipart(zmq.NOBLOCK, copy=False)
                    self.sock.send(self._answer(frames))
            except zmq.ZMQError as e:
                if self._stop.is_set() or e.errno == zmq.ETERM:
                    return
                log.warning("control socket: %s", e)
            except Exception:  # never let the service thread die
                log.exception("control thread error")
            now = time.monotonic()
            try:
                if now >= next_status:
                    next_status = now + period
                    self.daemon.publish(P.TOPIC_STATUS, self.daemon.status())
                self.daemon.tick()
            except Exception:
                log.exception("status/watchdog error")

    def _answer(self, frames: list) -> bytes:
        """The encoded reply to one request: always exactly one, whatever happened."""
        role = None
        if self.curve is not None and frames:
            who = self.curve.peer(frames[0])  # (role, client name) from the key folders now
            role = f"{who[0]} {who[1]!r}" if who else "revoked"
        try:
            reply = self.serve([f.bytes for f in frames], role=role)
            return P.encode_body(reply)
        except Exception as e:  # serve() replies to anything; this is the last line
            log.exception("control: reply failed")
            return P.encode_body({"ok": False, "error": f"internal error: {type(e).__name__}"})

    def serve(self, frames: list[bytes], role: str | None = None) -> dict:
        """The reply (without ``v``) to one request given as its ZeroMQ frames.

        role: with CURVE keys, who sent it ("operator 'NAME'", "viewer 'NAME'", "revoked");
        None without keys. Never raises: anything it cannot handle becomes an error reply.
        """
        self.requests += 1
        try:
            if role == "revoked":
                raise RequestError("control refused: this key is no longer allowed")
            if len(frames) != 1:
                raise RequestError(f"expected one JSON frame, got {len(frames)} frames")
            try:
                req = P.decode_body(frames[0], max_bytes=P.MAX_REQUEST_BYTES)
            except P.ProtocolError as e:
                raise RequestError(str(e)) from None
            cmd = _field(req, "cmd", str)
            if cmd not in COMMANDS:
                raise RequestError(f"unknown command {_short(cmd)} "
                                   f"(commands: {', '.join(COMMANDS)})")
            handler = self.handlers.get(cmd)
            if handler is None:
                raise RequestError(f"{cmd}: {NO_CAMERA}")
            kind = role.split(" ", 1)[0] if role is not None else None
            if kind not in (None, "operator") and cmd not in READ_ONLY:
                raise RequestError(f"control refused: {cmd} needs an operator key; this is "
                                   f"the key of {role} (read-only: {', '.join(READ_ONLY)})")
            reply = handler(req)
            if cmd == "ping":  # the UI says what its key may do
                reply["role"] = kind
            return {"ok": True, "cmd": cmd, **reply}
        except (RequestError, ConfigError, ValueError, OSError) as e:
            text = str(e) or type(e).__name__
        except Exception as e:  # a bug, never the client's problem to crash us
            log.exception("control request failed")
            text = f"internal error: {type(e).__name__}: {_short(str(e), 200)}"
        self.errors += 1
        text = text if len(text) <= 500 else text[:497] + "..."
        try:
            self.daemon.event("warning", f"control request refused: {text}")
        except Exception:
            log.exception("control: event")
        return {"ok": False, "error": text}

    # ------------------------------------------------------------------ commands
    def _cmd_ping(self, req: dict) -> dict:
        return {"t": time.time()}

    def _cmd_get_state(self, req: dict) -> dict:
        with self.daemon.lock:
            return self.daemon.state()

    def _cmd_get_config(self, req: dict) -> dict:
        d = self.daemon
        with d.lock:
            return {"config": d.cfg.to_dict(), "config_file": d.cfg.user_file,
                    "config_files": d.cfg.files, "overlay_file": str(d.cfg.overlay_path),
                    "live_keys": sorted(LIVE_KEYS), "advanced": sorted(ADVANCED)}

    def _cmd_set(self, req: dict) -> dict:
        key = _field(req, "key", str)
        if "value" not in req:
            raise RequestError("field 'value': missing")
        # Checked before waiting for the frame loop: a refused value never holds the pipeline.
        validate_setting(key, req["value"], "control", remote=True)
        with self.daemon.lock:
            v = self.daemon.apply_setting(key, req["value"], remote=True)
        return {"key": key, "value": v}

    def _path(self, req: dict) -> str | None:
        p = _field(req, "path", str, required=False)
        if p is not None and not p.strip():
            raise RequestError("field 'path': empty")
        return p

    def _cmd_log_start(self, req: dict) -> dict:
        # A name from the client: a new plain file in the data directory (kmead.outputs.datadir); no
        # name: the configured log.csv (the operator's own path) or a timestamped name.
        d = self.daemon
        name = self._path(req)
        if name is not None:  # refused before waiting for the frame loop
            d.data_dir.check_name(name, "log")
        with d.lock:
            if name is None and d.cfg["log"]["csv"]:
                # A restart over control never truncates what was logged (append or a new
                # name; the reply says which).
                c = d.start_csv(d.cfg["log"]["csv"], keep=True)
            else:
                c = d.start_csv(name or time.strftime("kmead-%Y%m%d-%H%M%S.csv"), remote=True)
        return {"path": str(c.path), "mode": c.mode}

    def _cmd_log_stop(self, req: dict) -> dict:
        with self.daemon.lock:
            return self.daemon.stop_csv()

    def _cam(self) -> CameraHost:
        assert self.camera is not None  # its commands are in the table only with it
        return self.camera

    def _cmd_record_start(self, req: dict) -> dict:
        d, cam = self.daemon, self._cam()
        name = self._path(req)
        if name is not None:
            d.data_dir.check_name(name, "record")
        with d.lock:
            if name is None and d.cfg["log"]["record"]:
                r = cam.start_recording(d.cfg["log"]["record"], keep=True)
            else:
                r = cam.start_recording(name or time.strftime("kmead-%Y%m%d-%H%M%S.jsonl.zst"),
                                        remote=True)
        return {"path": str(r.path), "mode": r.mode}

    def _cmd_record_stop(self, req: dict) -> dict:
        with self.daemon.lock:
            return self._cam().stop_recording()

    def _cmd_reload_map(self, req: dict) -> dict:
        with self.daemon.lock:
            m = self._cam().reload_map()
        return {"map": {"name": m.name, "n": len(m)}}

    def _cmd_save_config(self, req: dict) -> dict:
        path = self._path(req)
        overlay = self.daemon.cfg.overlay_path
        if path is not None and Path(path) != overlay:
            raise RequestError(f"save_config writes only the daemon's overlay {overlay} "
                               "(get_config: overlay_file); send it without a path")
        with self.daemon.lock:
            return self._cam().save_config()

    def _cmd_reset_stats(self, req: dict) -> dict:
        with self.daemon.lock:
            self._cam().stats.reset()
        return {}

    def _cmd_camera_watch(self, req: dict) -> dict:
        """Thumbnails on the ``camera`` topic until the lease ends (renew to keep them)."""
        cam = self._cam()
        reply = cam.camera_feed.watch(req.get("width"), req.get("height"), req.get("lease_s"))
        return {**reply, "images": not cam.replay}

    def _cmd_snapshot(self, req: dict) -> dict:
        overlay = bool(_field(req, "overlay", bool, required=False))
        return self._cam().snapshot(overlay)

    def _cmd_get_log(self, req: dict) -> dict:
        limit = _field(req, "limit", int, required=False)
        if limit is not None and not 1 <= limit <= 1000:
            raise RequestError("field 'limit': expected 1 to 1000")
        return {"lines": self.daemon.log_ring.lines(limit)}
