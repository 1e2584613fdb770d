"""The service shell: what a camera's kmead (:class:`kmead.run.daemon.Daemon`) and a fusion
node (:class:`kmead.fusion.node.FusionNode`) are both built on.

It holds the configuration, the lock between the main loop and the control thread, the
stop flag, the log ring (the UI's Log tab on attach), the ZeroMQ context and CURVE keys,
the telemetry publisher and its log handler, the data directory and its files (the CSV log,
a camera's recording), the robots' relay and the control server; :meth:`Service.event` and
:meth:`Service.publish` for everything else.

Teardown is written once: every resource registers its close on :attr:`Service.closing`
(an :class:`contextlib.ExitStack`) as it opens, so :meth:`Service.close` closes in the
reverse order of opening, after a full start as after one that failed half way (only what
opened is closed), and a close that raises does not keep the others from running. The
service opens its control server last, so it stops answering first; the relay's last word
to the robots (valid=0: they must not keep following a pose of a stopped service) is
registered once every way to the robots is open (:meth:`Service.last_word`), so it goes
before any of them closes.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

import zmq

from kmead.net.log_ring import LogRing
from kmead.net.telemetry import Telemetry, TelemetryLogHandler
from kmead.outputs.datadir import DataDir
from kmead.outputs.files import FileOutputs
from kmead.outputs.relay import Relay
from kmead.outputs.totals import RunTotals

if TYPE_CHECKING:
    from kmead.config.layers import Config
    from kmead.net.control import CameraHost, ControlServer, Host
    from kmead.net.keys import CurveServer

__all__ = ["Service"]

log = logging.getLogger("kmead")


class Service:
    """The shell of a kmead service; subclasses open what they need in this order: keys,
    telemetry, files, relay, their own parts, :meth:`last_word`, control."""

    # Opened by the subclass's start-up (close() copes with any of them missing).
    data_dir: DataDir
    files: FileOutputs
    relay: Relay

    def __init__(self, cfg: Config) -> None:
        self.cfg = cfg
        self.lock = threading.RLock()
        self.stop_event = threading.Event()
        self.t0 = time.time()
        self.progress_t = time.monotonic()  # the main loop's last sign of life (watchdog)
        self.closing = contextlib.ExitStack()
        self.zmq_context: zmq.Context | None = None  # its own when keyed (one ZAP handler)
        self.curve: CurveServer | None = None  # kmead.net.keys.CurveServer with network.keys
        self.telemetry: Telemetry | None = None
        self.control: ControlServer | None = None
        self.closed = False  # set (under the lock) when close() begins
        self.log_ring = LogRing()
        logger = logging.getLogger("kmead")
        logger.addHandler(self.log_ring)
        self.closing.callback(logger.removeHandler, self.log_ring)

    # ------------------------------------------------------------------ opening
    def open_keys(self) -> None:
        """CURVE on both sockets (``network.keys``): a context of its own with the ZAP
        handler. Raises :class:`kmead.net.keys.KeysError`."""
        keys = self.cfg["network"]["keys"]
        if not keys:
            return
        from kmead.net.keys import keyed_context

        self.zmq_context, self.curve = keyed_context(keys)
        self.closing.callback(self._close_keys)

    def _close_keys(self) -> None:
        if self.curve is not None:
            self.curve.stop()
            self.curve = None
        if self.zmq_context is not None:
            self.zmq_context.term()
            self.zmq_context = None

    def open_telemetry(self, context: zmq.Context | None = None,
                       log_level: int = logging.INFO) -> Telemetry:
        """The PUB socket (``network.telemetry``) and the log handler that publishes the
        ``kmead`` log on it (removed before the socket closes). Raises OSError."""
        self.telemetry = Telemetry(self.cfg["network"]["telemetry"],
                                   context=self.zmq_context or context, curve=self.curve)
        self.closing.callback(self._close_telemetry)
        handler = TelemetryLogHandler(self.telemetry, log_level)
        logger = logging.getLogger("kmead")
        logger.addHandler(handler)
        self.closing.callback(logger.removeHandler, handler)
        return self.telemetry

    def _close_telemetry(self) -> None:
        if self.telemetry is not None:
            self.farewell()
            self.telemetry.close()
            self.telemetry = None

    def farewell(self) -> None:
        """The last telemetry before the socket closes (a daemon: "stopped")."""

    def open_files(self, totals: RunTotals | None = None,
                   new_recorder: Callable[..., Any] | None = None) -> FileOutputs:
        """The data directory (``log.dir``) and its files, flushed and closed at the end.
        Raises :class:`kmead.outputs.datadir.FileRefused`."""
        self.data_dir = DataDir(self.cfg["log"]["dir"])
        self.files = FileOutputs(self.cfg["log"], self.data_dir,
                                 RunTotals() if totals is None else totals, self.event,
                                 new_recorder)
        self.closing.callback(self.files.close)
        return self.files

    def open_relay(self) -> Relay:
        """The robots' relay (``[relay]``, ``[[robots]]``); its sockets close at the end."""
        cfg = self.cfg
        self.relay = Relay(cfg["robots"], cfg["relay"]["stale_after_s"],
                           cfg["relay"]["stale_repeat_s"], publish=self.publish,
                           extra_fields=cfg["relay"]["extra_fields"],
                           max_sigma_m=cfg["relay"]["max_sigma_m"])
        self.closing.callback(self.relay.close)
        return self.relay

    def last_word(self, now: Callable[[], float]) -> None:
        """Registered once every way to the robots is open: at the end, before any of them
        closes, every robot gets valid=0 (``now()``: the relay's clock then)."""
        relay = self.relay

        def shutdown() -> None:
            try:  # robots must not keep following the last pose of a stopped service
                relay.shutdown(now())
            except Exception:
                log.exception("relay shutdown")

        self.closing.callback(shutdown)

    def open_control(self, host: Host, camera: CameraHost | None = None,
                     context: zmq.Context | None = None) -> ControlServer | None:
        """The control server (``network.control``; None when off), opened last so it stops
        first. Raises OSError (the port taken)."""
        endpoint = self.cfg["network"]["control"]
        if not endpoint:
            return None
        from kmead.net.control import ControlServer

        self.control = ControlServer(endpoint, host, context=self.zmq_context or context,
                                     curve=self.curve, camera=camera)
        self.closing.callback(self._close_control)
        return self.control

    def _close_control(self) -> None:
        if self.control is not None:
            self.control.stop()
            self.control = None

    # ------------------------------------------------------------------ the service
    def publish(self, topic: str, body: Mapping[str, Any]) -> None:
        if self.telemetry is not None:
            self.telemetry.publish(topic, body)

    def event(self, level: str, text: str) -> None:
        """A log line and an ``event`` message (the UI's log)."""
        getattr(log, "warning" if level == "warning" else level, log.info)(text)
        if self.telemetry is not None:
            self.telemetry.event(level, text)

    def stop(self) -> None:
        # Only a flag: this runs in a signal handler (no locks, no sockets here).
        self.stop_event.set()

    def close(self) -> None:
        """Close everything that opened, in the reverse order (idempotent; also after a
        start-up that failed half way)."""
        with self.lock:
            if self.closed:
                return
            self.closed = True
            self.closing.close()
