"""A kmead in a thread with real sockets on loopback, and a client for it (security tests)."""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path

import zmq
from deadlines import JOIN

from kmea.wire import protocol as P
from kmead.config.layers import load_config
from kmead.net.keys import connect_client
from kmead.run.daemon import Daemon

# 640x480 paced simulator, detection in the main loop: light on a 2-core machine.
BASE = ["source.width=640", "source.height=480", "source.fps=20", "detector.workers=0",
        'network.telemetry="tcp://127.0.0.1:*"', 'network.control="tcp://127.0.0.1:*"']


def udp_listener() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(3.0)
    return s


def robots_toml(ports: dict[str, int]) -> str:
    markers = {"amr1": "[40, 41]", "amr2": "[42]"}
    return "".join(f'\n[[robots]]\nname = "{n}"\nmarkers = {markers[n]}\nheight = 0.2\n'
                   f'destinations = ["udp:127.0.0.1:{p}"]\n' for n, p in ports.items())


class LiveDaemon:
    """``Daemon`` running in a thread; ``site.toml`` in ``root``, data directory
    ``root/data``. ``keys``/``client``: talk CURVE with that client's key pair."""

    def __init__(self, root: Path, sets: list[str] = (), site: str = "",
                 keys: Path | None = None, client: str = "operator") -> None:
        self.root = root
        self.data = root / "data"
        self.site = root / "site.toml"
        self.site.write_text("# the operator's own file\n" + site)
        self.cfg = load_config(str(self.site), [*BASE, f'log.dir="{self.data}"', *sets])
        self.daemon = Daemon(self.cfg)
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, name="test-kmead", daemon=True)
        self.thread.start()
        self.ctx = zmq.Context()
        self.keys, self.client = keys, client
        self.control = self.daemon.control.bound
        self.telemetry = self.daemon.telemetry.bound
        self._req: zmq.Socket | None = None

    def _run(self) -> None:
        try:
            self.daemon.run()
        except BaseException as e:  # the test asserts there was none
            self.error = e

    def _socket(self) -> zmq.Socket:
        if self._req is None:
            if self.keys is not None:
                self._req = connect_client(self.ctx, self.control, self.keys, self.client)
            else:
                self._req = self.ctx.socket(zmq.REQ)
                self._req.setsockopt(zmq.LINGER, 0)
                self._req.connect(self.control)
        return self._req

    def request(self, payload: bytes | list[bytes], timeout: float = 15.0) -> dict | None:
        """The decoded reply, or None if none came within ``timeout`` (the REQ socket is
        then replaced, lazy-pirate style)."""
        req = self._socket()
        if isinstance(payload, list):
            req.send_multipart(payload)
        else:
            req.send(payload)
        if not req.poll(int(timeout * 1000)):
            req.close(0)
            self._req = None
            return None
        return P.decode_body(req.recv())

    def cmd(self, cmd: str, **args: object) -> dict:
        reply = self.request(P.encode_body({"cmd": cmd, **args}), timeout=15.0)
        assert reply is not None, f"no reply to {cmd}"
        return reply

    def frames_flow(self, timeout: float = 30.0) -> bool:
        n = self.daemon.totals.frames
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.daemon.totals.frames > n + 1:
                return True
            time.sleep(0.02)
        return False

    def wait(self, cond, timeout: float = 30.0) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if cond():
                return True
            time.sleep(0.02)
        return False

    def alive(self) -> bool:
        return self.thread.is_alive() and self.error is None

    def close(self) -> None:
        if self._req is not None:
            self._req.close(0)
        self.daemon.stop()
        self.thread.join(timeout=JOIN)
        self.daemon.close()
        self.ctx.term()
