"""Two fusion nodes run hot (kmead.fusion.Election): one speaks to the robots, the other
waits; the active one killed (SIGKILL), the standby takes over and the robot hears one voice
at a time; the killed one restarted does not take the voice back. Real ``kmea fuse``
processes, a camera played by the test on Zenoh (loopback, explicit endpoints), the robot a
UDP listener. No timing is asserted: only the order of the voices (``kmea bench
fusion-zenoh`` measures the times)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from deadlines import DEADLINE, JOIN

pytest.importorskip("zenoh", reason="the zenoh extra is not installed "
                                    "(pip install 'kmea[zenoh]')")

from zenoh_helpers import FakeCamera, free_port, meta

ROOT = Path(__file__).resolve().parent.parent


class Node:
    """``kmea fuse --headless`` in its own process; the first listens on ``zport``, the
    others on a port of their own, connecting to it."""

    def __init__(self, tmp: Path, name: str, zport: int, first: bool, udp_port: int) -> None:
        self.err_path = tmp / f"{name}.err"
        self.err = open(self.err_path, "w")  # noqa: SIM115 (closed in stop())
        listen = zport if first else free_port()
        extra = [] if first else ["--set", f'zenoh.connect=["tcp/127.0.0.1:{zport}"]']
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "kmead.tools.fuse", "--headless",
             "--set", 'network.telemetry=""', "--set", 'network.control=""',
             "--set", 'log.level="info"', "--set", "zenoh.lease_s=2.0",
             "--set", "zenoh.ros2=false", "--set", "relay.stale_after_s=30.0",
             "--set", f'zenoh.listen=["tcp/127.0.0.1:{listen}"]', *extra,
             "--set", f'robots=[{{name="amr1", markers=[40, 41], height=0.2, '
                      f'destinations=["udp:127.0.0.1:{udp_port}"]}}]'],
            stdout=subprocess.DEVNULL, stderr=self.err, cwd=tmp,
            env=dict(os.environ, PYTHONPATH=str(ROOT)))

    def said(self, text: str) -> bool:
        return text in self.err_path.read_text()

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
        self.proc.wait(timeout=JOIN)
        self.err.close()


class Robot:
    """The UDP listener: (sender port, valid) of every datagram, in order."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.1)
        self.port = self.sock.getsockname()[1]
        self.got: list[tuple[int, bool]] = []
        self.lock = threading.Lock()
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.done.is_set():
            try:
                data, addr = self.sock.recvfrom(2048)
            except TimeoutError:
                continue
            with self.lock:
                self.got.append((addr[1], b"valid=1" in data))

    def senders(self) -> list[int]:
        """The valid datagrams' senders, each run of one sender once."""
        with self.lock:
            out: list[int] = []
            for port, valid in self.got:
                if valid and (not out or out[-1] != port):
                    out.append(port)
            return out

    def count(self) -> int:
        with self.lock:
            return len(self.got)


def _wait(cond, what: str, nodes: list[Node]) -> None:
    end = time.monotonic() + DEADLINE
    while time.monotonic() < end:
        if cond():
            return
        for n in nodes:
            if n.proc.poll() is not None and n.proc.returncode not in (0, -9):
                raise AssertionError(f"a node exited: {n.err_path.read_text()[-500:]}")
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}: "
                         + " | ".join(n.err_path.read_text()[-300:] for n in nodes))


def test_the_standby_takes_over_with_one_voice_and_no_preemption(tmp_path: Path) -> None:
    zport = free_port()
    robot = Robot()
    nodes: list[Node] = []
    cam: FakeCamera | None = None
    stop = threading.Event()
    sender: threading.Thread | None = None
    try:
        a = Node(tmp_path, "a", zport, True, robot.port)
        nodes.append(a)
        cam = FakeCamera(zport, "cam0", meta("cam0", "d" * 16), mesh=True)

        def measurements() -> None:
            assert cam is not None
            k = 0
            while not stop.wait(0.05):
                t = time.time()
                cam.measurement("amr1", t, 0.5 + 1e-4 * k, 0.3)
                cam.put("frame", {"t": t, "frames": k})
                k += 1

        sender = threading.Thread(target=measurements, daemon=True)
        sender.start()
        _wait(lambda: robot.senders() != [], "node A speaking", nodes)
        b = Node(tmp_path, "b", zport, False, robot.port)
        nodes.append(b)
        _wait(lambda: b.said("standby:"), "node B standby", nodes)
        n = robot.count()
        _wait(lambda: robot.count() > n + 20, "more poses", nodes)
        assert len(robot.senders()) == 1, "the standby spoke while the active one did"

        a.proc.send_signal(signal.SIGKILL)
        _wait(lambda: len(robot.senders()) >= 2, "node B speaking", nodes)
        n = robot.count()
        _wait(lambda: robot.count() > n + 20, "more poses", nodes)
        port_a, port_b = robot.senders()[:2]
        assert robot.senders() == [port_a, port_b], "voices interleaved"
        assert b.said("active: this node speaks")

        # A restarted: a standby; B keeps the voice.
        a2 = Node(tmp_path, "a2", zport, True, robot.port)
        nodes.append(a2)
        _wait(lambda: a2.said("standby:"), "the restarted node standby", nodes)
        n = robot.count()
        _wait(lambda: robot.count() > n + 40, "more poses", nodes)
        assert robot.senders() == [port_a, port_b], "the restarted node took the voice"
        assert not a2.said("active: this node speaks")
    finally:
        stop.set()
        if sender is not None:
            sender.join(timeout=JOIN)
        for node in nodes:
            node.stop()
        if cam is not None:
            cam.close()
        robot.done.set()
        robot.thread.join(timeout=JOIN)
        robot.sock.close()
