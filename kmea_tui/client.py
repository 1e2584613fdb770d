"""Where the UI's data comes from: a running daemon (ZeroMQ) or a recorded telemetry stream.

Both clients share one small async interface, so :class:`kmea_tui.app.KmeaTui` runs
unchanged against either:

- ``await open()`` / ``close()``
- ``await recv(timeout)`` -> list of ``(topic, body)`` available now (waits at most
  ``timeout`` s for the first one). Bodies are checked with :func:`kmea.wire.protocol.decode`
  (JSON, version and the topic's declared type).
- ``await request(cmd, **args)`` -> the reply dict; never raises for a dead daemon: the
  reply is then ``{"ok": False, "error": ...}`` (lazy-pirate pattern: the REQ socket is
  closed and re-created after a timeout so it never stays stuck in its send/recv cycle).
- ``live`` (a daemon: stale/disconnected states apply), ``ended`` (a finished recording),
  ``bad_messages`` (telemetry that did not follow the protocol, skipped).

Recording format (``tests/data/telemetry_*.jsonl``, written by :func:`record_stream`): JSON
lines; an optional first line ``{"header": {"telemetry": ..., "get_config": {...},
"get_state": {...}}}`` with the control replies a replay can answer, then one line per
telemetry message ``{"topic": str, "body": {...}, "dt": seconds since the previous line}``.
"""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import zmq
import zmq.asyncio

from kmea.wire import protocol
from kmea.wire.curve_client import DEFAULT_CLIENT, apply_client_keys, read_client_keys

# Topics the UI shows. robot.<name> topics are for the robots themselves; "robots" has them all.
UI_TOPICS = (
    protocol.TOPIC_FRAME,
    protocol.TOPIC_MARKERS,
    protocol.TOPIC_ROBOTS,
    protocol.TOPIC_STATS,
    protocol.TOPIC_STATUS,
    protocol.TOPIC_EVENT,
    protocol.TOPIC_LOG,
    protocol.TOPIC_CAMERA,  # sent by the daemon only while the Camera tab holds a lease
)

Reply = dict[str, Any]
Message = tuple[str, dict[str, Any]]

# At most this many messages per recv() call, so one call never monopolises the event loop.
MAX_BATCH = 2000


def check_endpoint(endpoint: str) -> str | None:
    """None if ZeroMQ accepts ``endpoint`` for connecting, else the reason."""
    ctx = zmq.Context.instance()
    s = ctx.socket(zmq.REQ)
    s.setsockopt(zmq.LINGER, 0)
    try:
        s.connect(endpoint)
    except zmq.ZMQError as e:
        return f"{e} (expected e.g. tcp://127.0.0.1:5555)"
    finally:
        s.close(linger=0)
    return None


class DaemonClient:
    """SUB (telemetry) + REQ (control) sockets to one kmead.

    Args:
        telemetry: ZeroMQ endpoint of the daemon's PUB socket.
        control: ZeroMQ endpoint of the daemon's REP socket.
        timeout: seconds to wait for a control reply before giving up on it.
        keys: a kmead key directory (``kmea keys init``): both sockets speak CURVE with
            the key pair of ``client`` (``keys/clients/CLIENT.key_secret``) and the daemon's
            public key ``keys/server.key``. None: plain sockets (a daemon without keys).
        client: the client name in ``keys`` (default ``operator``).
    """

    live = True
    ended = False

    def __init__(self, telemetry: str = protocol.DEFAULT_TELEMETRY,
                 control: str = protocol.DEFAULT_CONTROL, timeout: float = 1.0,
                 keys: str | Path | None = None, client: str = DEFAULT_CLIENT) -> None:
        self.telemetry = telemetry
        self.control = control
        self.timeout = timeout
        self.keys = keys
        self.client = client
        if keys is not None:
            read_client_keys(keys, client)  # CurveKeyError (one line) now, not at connect
        self.bad_messages = 0
        self.last_error = ""
        self._ctx: zmq.asyncio.Context | None = None
        # The SUB socket is a plain (blocking-API) socket: the UI drains it a few times a
        # second (drain_raw) instead of waking its event loop for every message; recv_raw
        # polls it through asyncio (recordings, tools).
        self._sub: zmq.Socket | None = None
        self._req: zmq.asyncio.Socket | None = None
        self._lock: asyncio.Lock | None = None

    @property
    def name(self) -> str:
        return self.telemetry

    async def open(self) -> None:
        """Create the sockets (inside the event loop that will use them)."""
        self._ctx = zmq.asyncio.Context()
        self._lock = asyncio.Lock()
        sub = zmq.Context.shadow(self._ctx.underlying).socket(zmq.SUB)
        sub.setsockopt(zmq.LINGER, 0)
        # A UI that falls behind loses old telemetry at the socket, never memory.
        sub.setsockopt(zmq.RCVHWM, 1000)
        for topic in UI_TOPICS:
            sub.setsockopt(zmq.SUBSCRIBE, topic.encode())
        if self.keys is not None:
            apply_client_keys(sub, self.keys, self.client)
        if self.telemetry:  # "" = the daemon's telemetry is off: nothing to read
            sub.connect(self.telemetry)
        self._sub = sub

    def close(self) -> None:
        for s in (self._sub, self._req):
            if s is not None:
                s.close(linger=0)
        self._sub = self._req = None
        if self._ctx is not None:
            self._ctx.term()
            self._ctx = None

    async def recv(self, timeout: float) -> list[Message]:
        """Every telemetry message waiting now, decoded and checked (bad ones counted);
        waits up to ``timeout`` s for the first."""
        msgs = (self.decode_raw(frames) for _, frames in await self.recv_raw(timeout))
        return [m for m in msgs if m is not None]

    async def recv_raw(self, timeout: float) -> list[tuple[str, list[bytes]]]:
        """Like :meth:`recv`, bodies not decoded yet: ``(topic, frames)``; the caller
        decodes (:meth:`decode_raw`) only the messages it keeps (the UI keeps the last of
        each topic per repaint: 4 of the daemon's 30 markers bodies a second)."""
        if self._sub is None:
            raise RuntimeError("DaemonClient.recv before open()")
        poller = zmq.asyncio.Poller()
        poller.register(self._sub, zmq.POLLIN)
        # pyzmq's stubs give Poller.poll an int timeout; the asyncio poller takes float ms.
        if not await poller.poll(timeout * 1000):  # pyright: ignore[reportArgumentType]
            return []
        return self.drain_raw()

    def drain_raw(self) -> list[tuple[str, list[bytes]]]:
        """Every telemetry message waiting now (at most ``MAX_BATCH``), without waiting
        and without the event loop: ``(topic, frames)``, bodies not decoded."""
        sub = self._sub
        if sub is None:
            raise RuntimeError("DaemonClient.drain_raw before open()")
        out: list[tuple[str, list[bytes]]] = []
        while len(out) < MAX_BATCH:
            try:
                frames = sub.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                break
            try:
                topic = frames[0].decode("ascii") if len(frames) == 2 else None
            except UnicodeDecodeError:
                topic = None
            if topic is None:
                self._bad(protocol.ProtocolError(
                    f"expected 2 frames [ASCII topic, body], got {len(frames)}"))
                continue
            out.append((topic, frames))
        return out

    def decode_raw(self, frames: list[bytes]) -> Message | None:
        """A message of :meth:`recv_raw` decoded and checked, None (counted) if bad."""
        try:
            return protocol.decode(frames)
        except protocol.ProtocolError as e:
            self._bad(e)
            return None

    def _bad(self, e: Exception) -> None:
        self.bad_messages += 1
        self.last_error = str(e)

    def _new_req(self) -> zmq.asyncio.Socket:
        assert self._ctx is not None
        req = self._ctx.socket(zmq.REQ)
        req.setsockopt(zmq.LINGER, 0)
        req.setsockopt(zmq.SNDTIMEO, int(self.timeout * 1000))
        req.setsockopt(zmq.RCVTIMEO, int(self.timeout * 1000))
        if self.keys is not None:
            apply_client_keys(req, self.keys, self.client)
        req.connect(self.control)
        return req

    async def request(self, cmd: str, timeout: float | None = None, **args: Any) -> Reply:
        """Send one control command; the reply, or ``{"ok": False, "error": ...}``."""
        if self._ctx is None or self._lock is None:
            return {"ok": False, "error": "not connected (client not open)"}
        if not self.control:
            return {"ok": False, "error": "the daemon's control socket is off"}
        wait = self.timeout if timeout is None else timeout
        async with self._lock:
            if self._req is None:
                self._req = self._new_req()
            req = self._req
            try:
                await req.send(protocol.encode_body({"cmd": cmd, **args}))
                # pyzmq's _future.pyi copies Poller.poll(timeout) for the asyncio
                # Socket.poll, which takes (timeout, flags) at run time.
                if not await req.poll(wait * 1000, zmq.POLLIN):  # pyright: ignore[reportCallIssue]
                    raise TimeoutError
                data = await req.recv()
            except (TimeoutError, zmq.ZMQError):
                # Lazy pirate: a REQ socket that missed its reply is unusable; start afresh.
                req.close(linger=0)
                self._req = None
                if self.keys is None:  # a keyed daemon ignores a plain client: say so first
                    return {"ok": False, "error": f"no reply within {wait:g} s: down, or it "
                                                  f"needs --keys DIR ({self.control})"}
                return {"ok": False, "error": f"no reply from {self.control} within {wait:g} s"}
        try:
            reply = protocol.decode_body(data)
        except protocol.ProtocolError as e:
            return {"ok": False, "error": f"bad reply to {cmd!r}: {e}"}
        reply.setdefault("ok", False)
        return reply


class RecordingClient:
    """Replays a recorded telemetry stream (see the module docstring for the format).

    Args:
        path: the JSON-lines recording.
        realtime: replay at the recorded pace (``dt``) times ``speed``; otherwise every
            message is delivered at once, which makes the UI deterministic for snapshots.
        loop: start again at the end (demos).
    """

    live = False

    def __init__(self, path: str | Path, realtime: bool = False, speed: float = 1.0,
                 loop: bool = False) -> None:
        self.path = Path(path)
        self.realtime = realtime
        self.speed = speed
        self.loop = loop
        self.header: dict[str, Any] = {}
        self.messages: list[tuple[str, dict[str, Any], float]] = []
        self.bad_messages = 0
        self.telemetry = f"replay:{self.path.name}"
        self.control = "(none: replay)"
        self._load()
        self._pos = 0
        self._t0 = 0.0
        self._next_due = 0.0

    @property
    def name(self) -> str:
        return self.telemetry

    def _load(self) -> None:
        try:
            lines = self.path.read_text(encoding="utf-8").splitlines()
        except OSError as e:
            raise ValueError(f"{self.path}: cannot read recording: {e.strerror}") from None
        for n, line in enumerate(lines, 1):
            if not line.strip():
                continue
            try:
                rec = json.loads(line)
            except json.JSONDecodeError as e:
                raise ValueError(f"{self.path}:{n}: not JSON: {e.msg}") from None
            if not isinstance(rec, dict):
                raise ValueError(f"{self.path}:{n}: expected a JSON object")
            if "header" in rec:
                self.header = dict(rec["header"])
                for cmd, td in protocol.REPLY_TYPES.items():
                    if cmd in self.header:
                        try:
                            protocol.check_fields(self.header[cmd], td, cmd)
                        except protocol.ProtocolError as e:
                            raise ValueError(f"{self.path}:{n}: header: {e}") from None
                continue
            topic, body = rec.get("topic"), rec.get("body")
            if not isinstance(topic, str) or not isinstance(body, dict):
                raise ValueError(f"{self.path}:{n}: expected fields 'topic' (str) and "
                                 f"'body' (object)")
            try:
                protocol.decode([topic.encode("ascii"), json.dumps(body).encode()])
            except (protocol.ProtocolError, UnicodeEncodeError) as e:
                raise ValueError(f"{self.path}:{n}: {e}") from None
            self.messages.append((topic, body, float(rec.get("dt", 0.0))))

    @property
    def ended(self) -> bool:
        return self._pos >= len(self.messages) and not self.loop

    async def open(self) -> None:
        self._pos = 0
        self._t0 = time.monotonic()
        self._next_due = self._t0

    def close(self) -> None:
        pass

    async def recv(self, timeout: float) -> list[Message]:
        if self._pos >= len(self.messages):
            if not self.loop:
                await asyncio.sleep(timeout)
                return []
            self._pos = 0
        if not self.realtime:
            chunk = self.messages[self._pos:self._pos + MAX_BATCH]
            self._pos += len(chunk)
            await asyncio.sleep(0)
            return [(t, b) for t, b, _ in chunk]
        out: list[Message] = []
        deadline = time.monotonic() + timeout
        while self._pos < len(self.messages) and len(out) < MAX_BATCH:
            topic, body, dt = self.messages[self._pos]
            due = self._next_due + dt / self.speed
            now = time.monotonic()
            if due > now:
                if out or due > deadline:
                    break
                await asyncio.sleep(due - now)
            self._next_due = due
            out.append((topic, body))
            self._pos += 1
        if not out:
            await asyncio.sleep(max(0.0, deadline - time.monotonic()))
        return out

    async def request(self, cmd: str, timeout: float | None = None, **args: Any) -> Reply:
        if cmd == "ping":
            return {"ok": True, "pong": True}
        if cmd in ("get_config", "get_state") and isinstance(self.header.get(cmd), dict):
            return dict(self.header[cmd])
        return {"ok": False, "error": f"replaying {self.path.name}: no daemon to {cmd}"}


PER_FRAME_TOPICS = (protocol.TOPIC_FRAME, protocol.TOPIC_MARKERS, protocol.TOPIC_ROBOTS)


def _round_floats(obj: Any, digits: int = 6) -> Any:
    if isinstance(obj, float):
        return round(obj, digits)
    if isinstance(obj, dict):
        return {k: _round_floats(v, digits) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_round_floats(v, digits) for v in obj]
    return obj


def trim_messages(messages: list[dict[str, Any]], keep_frames: int) -> list[dict[str, Any]]:
    """Keep the last ``keep_frames`` messages of each per-frame topic and of ``stats``,
    every ``status``, ``event`` and ``log``; floats rounded to 6 digits (a small file)."""
    counts: dict[str, int] = {}
    keep: list[dict[str, Any]] = []
    for rec in reversed(messages):
        topic = rec["topic"]
        if topic in (*PER_FRAME_TOPICS, protocol.TOPIC_STATS):
            counts[topic] = counts.get(topic, 0) + 1
            if counts[topic] > keep_frames:
                continue
        keep.append(_round_floats(rec))
    keep.reverse()
    return keep


async def record_stream(telemetry: str, control: str, path: str | Path, seconds: float,
                        topics: Iterable[str] = UI_TOPICS, keep_frames: int = 0,
                        keys: str | Path | None = None, client: str = DEFAULT_CLIENT) -> int:
    """Record ``seconds`` of a daemon's telemetry into ``path`` (the replay format).

    The header holds the daemon's ``get_config`` and ``get_state`` replies when it answers.
    ``keep_frames`` > 0 trims the file with :func:`trim_messages`.
    Returns the number of messages written.
    """
    daemon = DaemonClient(telemetry, control, keys=keys, client=client)
    await daemon.open()
    wanted = tuple(topics)
    try:
        header: dict[str, Any] = {"telemetry": telemetry}
        for cmd in ("get_config", "get_state"):
            reply = await daemon.request(cmd)
            if reply.get("ok"):
                header[cmd] = reply
        records: list[dict[str, Any]] = []
        end = time.monotonic() + seconds
        last: float | None = None
        while (now := time.monotonic()) < end:
            for topic, body in await daemon.recv(min(0.1, end - now)):
                if not topic.startswith(wanted):
                    continue
                t = time.monotonic()
                dt = 0.0 if last is None else t - last
                last = t
                records.append({"topic": topic, "body": body, "dt": round(dt, 4)})
    finally:
        daemon.close()
    if keep_frames > 0:
        records = trim_messages(records, keep_frames)
    lines = [json.dumps({"header": header}, separators=(",", ":"))]
    lines += [json.dumps(r, separators=(",", ":")) for r in records]
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")
    return len(records)
