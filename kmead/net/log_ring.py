"""The daemon's recent log lines, kept for a UI that attaches later (control ``get_log``)."""

from __future__ import annotations

import logging
import threading
from collections import deque
from typing import Any

RING_LINES = 200


class LogRing(logging.Handler):
    """Keeps the last ``size`` records as ``log`` telemetry bodies (t, level, logger, text)."""

    def __init__(self, size: int = RING_LINES, level: int = logging.NOTSET) -> None:
        super().__init__(level)
        self._lines: deque[dict[str, Any]] = deque(maxlen=size)
        self._guard = threading.Lock()

    def emit(self, record: logging.LogRecord) -> None:
        try:
            line = {"t": record.created, "level": record.levelname.lower(),
                    "logger": record.name, "text": record.getMessage()}
            with self._guard:
                self._lines.append(line)
        except Exception:  # a log handler must never raise into the caller
            self.handleError(record)

    def lines(self, limit: int | None = None) -> list[dict[str, Any]]:
        """The kept lines, oldest first (the last ``limit`` when given)."""
        with self._guard:
            out = list(self._lines)
        return out[-limit:] if limit else out
