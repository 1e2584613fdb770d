"""Telemetry: a ZeroMQ PUB socket shared by the pipeline, the service thread and logging.

ZeroMQ sockets are not thread-safe; every send goes through one lock (sends never block:
PUB drops messages for slow subscribers at the high-water mark).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import zmq

from kmead.protocol import TOPIC_EVENT, TOPIC_LOG, encode


class Telemetry:
    """PUB socket bound to ``endpoint`` ("" = publish nowhere, still counted)."""

    def __init__(self, endpoint: str, context: zmq.Context | None = None) -> None:
        self.endpoint = endpoint
        self.bound = ""
        self._lock = threading.Lock()
        self.sent = 0
        self.sock = None
        if endpoint:
            ctx = context or zmq.Context.instance()
            self.sock = ctx.socket(zmq.PUB)
            self.sock.setsockopt(zmq.LINGER, 0)
            self.sock.setsockopt(zmq.SNDHWM, 1000)
            try:
                self.sock.bind(endpoint)
            except zmq.ZMQError as e:
                self.sock.close()
                raise OSError(f"network.telemetry: cannot bind {endpoint}: {e}") from None
            self.bound = self.sock.getsockopt_string(zmq.LAST_ENDPOINT)

    def publish(self, topic: str, body: dict[str, Any]) -> None:
        if self.sock is None:
            return
        frames = encode(topic, body)
        with self._lock:
            if self.sock is None:
                return
            try:
                self.sock.send_multipart(frames, flags=zmq.NOBLOCK)
                self.sent += 1
            except zmq.ZMQError:
                pass  # HWM reached or shutting down: telemetry is best effort

    def event(self, level: str, text: str) -> None:
        self.publish(TOPIC_EVENT, {"t": time.time(), "level": level, "text": text})

    def close(self) -> None:
        with self._lock:
            if self.sock is not None:
                self.sock.close(linger=0)
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
