"""One host for a daemon or a fusion node: systemd (ready once its sockets are bound, a
watchdog fed while its loop shows signs of life, stopping), its run in the foreground
(headless, with SIGINT and SIGTERM stopping it) or in a thread under the terminal UI, which
talks to it over its own sockets, then closing it. ``kmead`` and ``kmea fuse`` both serve
through :func:`serve`."""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Callable
from typing import Any, Protocol

from kmea.wire.runtime import announce, withdraw
from kmead.run.notify import Notifier, monotonic_alive
from kmead.run.status_line import StatusReporter

__all__ = ["Servable", "run_host", "serve"]


class Servable(Protocol):
    """What a host runs: the daemon (kmead.run.daemon.Daemon) or a fusion node."""

    cfg: Any
    telemetry: Any
    control: Any

    @property
    def progress_t(self) -> float: ...  # time.monotonic() of the loop's last sign of life

    def run(self) -> int: ...
    def stop(self) -> None: ...
    def close(self) -> None: ...


def serve(host: Servable, ui: bool, ready: str,
          reporter: Callable[[Notifier], StatusReporter | None] | None = None,
          kind: str = "kmead") -> int:
    """Tell systemd ``ready`` (a no-op outside systemd), feed its watchdog from
    ``host.progress_t``, run the host (:func:`run_host`), then say stopping and close it.
    ``reporter(notifier)``: a started status-line reporter (stopped here), or None.
    ``kind``: what the runtime file (:mod:`kmea.wire.runtime`) calls it."""
    notifier = Notifier()
    notifier.ready(ready)
    # kmea-tui without endpoints finds this process (kmea.wire.runtime): make run binds
    # free ports.
    announced = None
    if host.telemetry is not None and host.telemetry.bound:
        announced = announce(kind, _connectable(host.telemetry.bound),
                             _connectable(host.control.bound) if host.control else "",
                             host.cfg["network"]["keys"] or "")
    if notifier.interval is not None:
        notifier.start_watchdog(monotonic_alive(lambda: host.progress_t,
                                                max(10.0, 4 * notifier.interval)))
    status = reporter(notifier) if reporter is not None else None
    try:
        return run_host(host, ui)
    finally:
        withdraw(announced)
        if status is not None:
            status.stop()
        notifier.stopping("stopping")
        host.close()
        notifier.close()


def run_host(host: Servable, ui: bool) -> int:
    """``host.run()`` to its end: under the UI (``ui``), else headless with SIGINT and
    SIGTERM stopping it; Ctrl-C stops it too. Returns its exit code (0 after Ctrl-C)."""
    try:
        if ui:
            return _run_with_ui(host)
        previous = {s: signal.signal(s, lambda *_: host.stop())
                    for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            return host.run()
        finally:
            for s, h in previous.items():
                signal.signal(s, h)
    except KeyboardInterrupt:
        host.stop()
        return 0


def _run_with_ui(daemon: Servable) -> int:
    """Daemon in a background thread, the Textual UI in the foreground on its sockets."""
    try:
        from kmea_tui.app import KmeaTui
        from kmea_tui.client import DaemonClient
    except ImportError as e:
        logging.getLogger("kmead").warning("terminal UI unavailable (%s); running headless", e)
        signal.signal(signal.SIGTERM, lambda *_: daemon.stop())
        return daemon.run()
    # A keyed daemon's own UI connects as the operator of its key directory.
    from kmea.wire.curve_client import CurveKeyError

    try:
        client = DaemonClient(_connectable(daemon.telemetry.bound),
                              _connectable(daemon.control.bound if daemon.control else ""),
                              keys=daemon.cfg["network"]["keys"] or None)
    except CurveKeyError as e:
        logging.getLogger("kmead").warning("terminal UI unavailable (%s); running headless", e)
        signal.signal(signal.SIGTERM, lambda *_: daemon.stop())
        return daemon.run()
    result: dict[str, int] = {}
    # The UI owns the terminal: log lines go to its Log tab (telemetry "log"), not stderr.
    root = logging.getLogger("kmead")
    quiet = [h for h in root.handlers if getattr(h, "_kmead", False)]
    for h in quiet:
        root.removeHandler(h)
    app = KmeaTui(client)
    t = threading.Thread(target=lambda: result.setdefault("code", daemon.run()),
                         name="kmead-main", daemon=True)
    t.start()

    def terminate(*_: object) -> None:
        daemon.stop()
        app.exit()

    previous = signal.signal(signal.SIGTERM, terminate)
    try:
        app.run()  # until the user quits (q) or SIGTERM
    finally:
        signal.signal(signal.SIGTERM, previous)
        daemon.stop()
        t.join(timeout=5.0)
        for h in quiet:
            root.addHandler(h)
    return result.get("code", 0)


def _connectable(endpoint: str) -> str:
    # A daemon bound to every interface is reached on loopback.
    return endpoint.replace("tcp://0.0.0.0:", "tcp://127.0.0.1:").replace(
        "tcp://*:", "tcp://127.0.0.1:")


