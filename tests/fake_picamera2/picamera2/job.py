"""picamera2/job.py: a Job wraps a concurrent.futures.Future; get_result(timeout) is
``Future.result(timeout)``, so a timeout raises concurrent.futures.TimeoutError (the built-in
TimeoutError since Python 3.11)."""

from __future__ import annotations

from concurrent.futures import Future
from typing import Any


class Job:
    def __init__(self, functions: list | None = None, signal_function: Any = None) -> None:
        self._future: Future = Future()
        self._future.set_running_or_notify_cancel()
        self._signal_function = signal_function

    def done(self) -> bool:
        return self._future.done()

    def signal(self, result: Any) -> None:
        self._future.set_result(result)
        if self._signal_function:
            self._signal_function(self)

    def get_result(self, timeout: float | None = None) -> Any:
        return self._future.result(timeout=timeout)
