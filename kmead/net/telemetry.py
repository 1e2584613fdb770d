"""Telemetry: a ZeroMQ PUB socket shared by the pipeline, the service thread and logging.

ZeroMQ sockets are not thread-safe; every send goes through one lock (sends never block:
PUB drops messages for slow subscribers at the high-water mark).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Mapping
from typing import Any

import zmq

from kmea.wire.protocol import TOPIC_EVENT, TOPIC_LOG, encode


class Telemetry:
    """PUB socket bound to ``endpoint`` ("" = publish nowhere).

    ``publish`` only queues the body: a sender thread encodes (JSON, the costly part for a
    50-marker body) and sends, so the frame loop does not pay for it. Order is kept; when
    the queue is full (a stalled sender) messages are dropped and counted, never blocking.
    """

    def __init__(self, endpoint: str, context: zmq.Context | None = None,
                 queue_size: int = 2000, curve: Any = None) -> None:
        self.endpoint = endpoint
        self.bound = ""
        self.sent = 0
        self.dropped = 0
        self.sock = None
        self._queue: queue.Queue = queue.Queue(maxsize=queue_size)
        self._thread: threading.Thread | None = None
        if endpoint:
            ctx = context or zmq.Context.instance()
            self.sock = ctx.socket(zmq.PUB)
            self.sock.setsockopt(zmq.LINGER, 0)
            self.sock.setsockopt(zmq.SNDHWM, 1000)
            if curve is not None:  # kmead.net.keys.CurveServer: encrypted, known keys only
                curve.secure(self.sock, "telemetry")
            try:
                self.sock.bind(endpoint)
            except zmq.ZMQError as e:
                self.sock.close()
                self.sock = None
                raise OSError(f"network.telemetry: cannot bind {endpoint}: {e}") from None
            self.bound = self.sock.getsockopt_string(zmq.LAST_ENDPOINT)
            self._thread = threading.Thread(target=self._run, args=(self.sock,),
                                            name="kmead-telemetry", daemon=True)
            self._thread.start()

    def publish(self, topic: str, body: Mapping[str, Any]) -> None:
        if self._thread is None:
            return
        try:
            self._queue.put_nowait((topic, body))
        except queue.Full:
            self.dropped += 1

    def _run(self, sock: zmq.Socket) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            try:
                frames = encode(*item)
            except Exception:  # a body that cannot be encoded is a bug: drop it, go on
                self.dropped += 1
                continue
            try:
                sock.send_multipart(frames, flags=zmq.NOBLOCK)
                self.sent += 1
            except zmq.ZMQError:
                self.dropped += 1  # HWM reached: telemetry is best effort

    def flush(self, timeout: float = 2.0) -> None:
        """Wait until the queued messages are sent (or ``timeout`` s)."""
        end = time.monotonic() + timeout
        while not self._queue.empty() and time.monotonic() < end:
            time.sleep(0.005)

    def event(self, level: str, text: str) -> None:
        self.publish(TOPIC_EVENT, {"t": time.time(), "level": level, "text": text})

    def close(self) -> None:
        if self._thread is not None:
            self.flush()
            self._queue.put(None)
            self._thread.join(timeout=2.0)
            self._thread = None
        if self.sock is not None:
            # A short linger: the last messages (the "stopped" status) still go out.
            self.sock.close(linger=500)
            self.sock = None


class TelemetryLogHandler(logging.Handler):
    """Publishes the daemon's log records on the ``log`` topic."""

    def __init__(self, telemetry: Telemetry, level: int = logging.INFO) -> None:
        super().__init__(level)
        self.telemetry = telemetry

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.telemetry.publish(TOPIC_LOG, {"t": record.created,
                                               "level": record.levelname.lower(),
                                               "logger": record.name,
                                               "text": record.getMessage()})
        except Exception:  # a log handler must never raise into the caller
            self.handleError(record)
