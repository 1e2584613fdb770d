"""The systemd notify protocol (``man sd_notify``), without a dependency.

Under ``Type=notify`` systemd names a Unix datagram socket in ``$NOTIFY_SOCKET``; the
service sends it newline-separated ``KEY=VALUE`` assignments, one datagram per call:
``READY=1`` once started, ``WATCHDOG=1`` at least every ``$WATCHDOG_USEC`` microseconds
when ``WatchdogSec=`` is set (we send at half the interval, as the man page advises),
``STATUS=...`` a one-line status shown by ``systemctl status``, ``STOPPING=1`` when
shutting down. A name starting with ``@`` is a Linux abstract socket (leading NUL byte).

Outside systemd (no ``$NOTIFY_SOCKET``) every call does nothing, so the daemon calls
these unconditionally. A failed send is logged once and never stops the daemon.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from collections.abc import Callable, Mapping

log = logging.getLogger("kmead")


def _address(name: str) -> str | bytes:
    # "@name" is an abstract socket: its address is a NUL byte then the name.
    if name.startswith("@"):
        return b"\0" + name[1:].encode()
    return name


def watchdog_interval(env: Mapping[str, str] | None = None) -> float | None:
    """Seconds between ``WATCHDOG=1`` pings (half of ``$WATCHDOG_USEC``), or None when the
    watchdog is off or meant for another process (``$WATCHDOG_PID`` not ours)."""
    env = os.environ if env is None else env
    usec = env.get("WATCHDOG_USEC", "")
    pid = env.get("WATCHDOG_PID", "")
    if pid and pid != str(os.getpid()):
        return None
    try:
        value = int(usec)
    except ValueError:
        return None
    return value / 2e6 if value > 0 else None


class Notifier:
    """Sends notify datagrams to ``$NOTIFY_SOCKET`` (read once, at construction).

    ``enabled`` is False outside systemd; then every method is a no-op.
    """

    def __init__(self, env: Mapping[str, str] | None = None) -> None:
        env = os.environ if env is None else env
        name = env.get("NOTIFY_SOCKET", "")
        self.address: str | bytes | None = _address(name) if name else None
        self.interval = watchdog_interval(env) if self.address is not None else None
        self._sock: socket.socket | None = None
        self._lock = threading.Lock()
        self._warned = False
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def send(self, **fields: str | int) -> bool:
        """One datagram with ``KEY=VALUE`` lines (``send(READY=1, STATUS="running")``).

        Returns True when sent. Newlines in a value would start a new assignment: they
        are replaced by spaces.
        """
        if self.address is None or not fields:
            return False
        text = "\n".join(f"{k}={str(v).replace(chr(10), ' ')}" for k, v in fields.items())
        with self._lock:
            try:
                if self._sock is None:
                    self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
                    self._sock.setblocking(False)
                self._sock.sendto(text.encode(), self.address)
                return True
            except OSError as e:
                if not self._warned:
                    self._warned = True
                    log.warning("systemd notify: cannot send to NOTIFY_SOCKET: %s",
                                e.strerror or e)
                return False

    def ready(self, status: str | None = None) -> bool:
        return self.send(READY=1, **({"STATUS": status} if status else {}))

    def status(self, text: str) -> bool:
        return self.send(STATUS=text)

    def watchdog(self) -> bool:
        return self.send(WATCHDOG=1)

    def stopping(self, status: str | None = None) -> bool:
        # Pings end here: while stopping, systemd applies TimeoutStopSec, not the watchdog.
        self._stop_watchdog()
        return self.send(STOPPING=1, **({"STATUS": status} if status else {}))

    def _stop_watchdog(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
            self._thread = None

    def start_watchdog(self, alive: Callable[[], bool] | None = None) -> bool:
        """Ping ``WATCHDOG=1`` every :attr:`interval` s from a thread while ``alive()`` is
        true (default: always). A hung main loop should make ``alive`` false so systemd
        restarts the service. Returns False when the watchdog is off."""
        if self.interval is None or self._thread is not None:
            return False

        def loop() -> None:
            while not self._stop.wait(self.interval):
                if alive is None or alive():
                    self.watchdog()

        self.watchdog()
        self._thread = threading.Thread(target=loop, name="kmead-watchdog", daemon=True)
        self._thread.start()
        return True

    def close(self) -> None:
        self._stop_watchdog()
        with self._lock:
            if self._sock is not None:
                self._sock.close()
                self._sock = None


def monotonic_alive(last_progress: Callable[[], float], limit_s: float) -> Callable[[], bool]:
    """An ``alive`` test for :meth:`Notifier.start_watchdog`: true while
    ``last_progress()`` (a ``time.monotonic()`` reading) is less than ``limit_s`` old."""
    return lambda: time.monotonic() - last_progress() < limit_s
