"""systemd notify datagrams, received on a real Unix datagram socket."""

from __future__ import annotations

import logging
import os
import socket
import time

import pytest

from kmead.run.notify import Notifier, monotonic_alive, watchdog_interval


def _recv_all(sock: socket.socket, n: int, timeout: float = 30.0) -> list[str]:
    sock.settimeout(timeout)
    return [sock.recv(4096).decode() for _ in range(n)]


@pytest.fixture
def listener(tmp_path):
    path = str(tmp_path / "notify.sock")
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(path)
    yield path, s
    s.close()


def test_ready_status_stopping_datagrams(listener):
    path, sock = listener
    n = Notifier({"NOTIFY_SOCKET": path})
    assert n.enabled
    assert n.ready("running: sim")
    assert n.status("frames 10\nfps 30")
    assert n.stopping()
    n.close()
    got = _recv_all(sock, 3)
    assert got[0].split("\n") == ["READY=1", "STATUS=running: sim"]
    assert got[1] == "STATUS=frames 10 fps 30"  # a newline would start a new assignment
    assert got[2] == "STOPPING=1"


def test_abstract_socket_name():
    name = f"kmea-test-{os.getpid()}-{time.monotonic_ns()}"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(b"\0" + name.encode())
    try:
        n = Notifier({"NOTIFY_SOCKET": "@" + name})
        assert n.ready()
        n.close()
        assert _recv_all(s, 1) == ["READY=1"]
    finally:
        s.close()


def test_watchdog_pings_at_half_the_interval(listener):
    path, sock = listener
    n = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "200000"})
    assert n.interval == pytest.approx(0.1)
    assert n.start_watchdog()
    try:
        got = _recv_all(sock, 4)
    finally:
        n.close()
    assert got == ["WATCHDOG=1"] * 4


def test_watchdog_stops_when_not_alive(listener):
    path, sock = listener
    n = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "100000"})
    stamp = [time.monotonic()]
    n.start_watchdog(monotonic_alive(lambda: stamp[0], 0.12))
    try:
        first = _recv_all(sock, 1)  # the immediate ping
        time.sleep(0.4)  # progress is now 0.4 s old: no more pings
        sock.setblocking(False)
        late = []
        while True:
            try:
                late.append(sock.recv(4096))
            except BlockingIOError:
                break
    finally:
        n.close()
    assert first == ["WATCHDOG=1"]
    assert len(late) <= 2  # at most the pings sent before 0.12 s passed


def test_outside_systemd_nothing_is_sent():
    n = Notifier({})
    assert not n.enabled
    assert not n.ready()
    assert not n.start_watchdog()
    n.close()


def test_watchdog_interval_rules():
    assert watchdog_interval({"WATCHDOG_USEC": "30000000"}) == 15.0
    assert watchdog_interval({"WATCHDOG_USEC": "0"}) is None
    assert watchdog_interval({"WATCHDOG_USEC": "x"}) is None
    assert watchdog_interval({"WATCHDOG_USEC": "1000000", "WATCHDOG_PID": "1"}) is None
    assert watchdog_interval({"WATCHDOG_USEC": "1000000",
                              "WATCHDOG_PID": str(os.getpid())}) == 0.5


def test_missing_socket_warns_once_and_does_not_raise(tmp_path):
    records: list[logging.LogRecord] = []
    handler = logging.Handler()
    handler.emit = records.append  # type: ignore[method-assign]
    logger = logging.getLogger("kmead")
    logger.addHandler(handler)
    try:
        n = Notifier({"NOTIFY_SOCKET": str(tmp_path / "absent.sock")})
        assert not n.ready()
        assert not n.watchdog()
        n.close()
    finally:
        logger.removeHandler(handler)
    assert sum("NOTIFY_SOCKET" in r.getMessage() for r in records) == 1
