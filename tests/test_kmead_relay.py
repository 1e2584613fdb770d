"""Robot relay over real UDP sockets on loopback: datagram format, sequence, stale messages."""

from __future__ import annotations

import math
import re
import socket

import pytest

from kmead.relay import Relay, datagram, parse_datagram

LINE = re.compile(r"^name=[A-Za-z0-9_-]+;seq=\d+;t=-?\d+\.\d{6};x=-?\d+\.\d{6};y=-?\d+\.\d{6};"
                  r"theta=-?\d+\.\d{6};valid=[01]$")


@pytest.fixture
def udp() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(2.0)
    yield s
    s.close()


def test_datagram_is_one_ascii_line() -> None:
    d = datagram("amr1", 17, 1700000000.1234567, 0.5123, 0.2001, 1.5708, True)
    assert d == b"name=amr1;seq=17;t=1700000000.123457;x=0.512300;y=0.200100;theta=1.570800;valid=1"
    assert parse_datagram(d)["valid"] is True


def test_fixes_then_stale_over_udp(udp: socket.socket) -> None:
    port = udp.getsockname()[1]
    published = []
    relay = Relay([{"name": "amr1", "markers": [40, 41],
                    "destinations": [f"udp:127.0.0.1:{port}"]}],
                  stale_after_s=0.5, stale_repeat_s=1.0,
                  publish=lambda topic, body: published.append((topic, body)))
    try:
        relay.update("amr1", 10.0, 0.25, -0.125, math.pi / 2, None)
        relay.update("amr1", 10.1, 0.26, -0.125, math.pi / 2, None)
        assert relay.tick(10.4) == []          # 0.3 s unseen: still fresh
        assert relay.tick(10.6) == ["amr1"]    # 0.5 s: stale, one valid=0 message
        assert relay.tick(10.7) == []          # no repeat before stale_repeat_s
        relay.tick(11.7)                        # repeated after 1 s
        got = [udp.recv(1024) for _ in range(4)]
    finally:
        relay.close()
    for g in got:
        assert LINE.match(g.decode("ascii")), g
    msgs = [parse_datagram(g) for g in got]
    assert [m["seq"] for m in msgs] == [1, 2, 3, 4]
    assert [m["valid"] for m in msgs] == [True, True, False, False]
    assert msgs[0]["x"] == 0.25 and msgs[0]["y"] == -0.125
    assert msgs[2]["x"] == 0.26 and msgs[2]["t"] == 10.6  # last known pose, stale time
    assert [t for t, _ in published] == ["robot.amr1"] * 4
    assert relay.tracks["amr1"].sent == 4 and relay.tracks["amr1"].stale


def test_unreachable_destination_never_raises(udp: socket.socket) -> None:
    relay = Relay([{"name": "r", "markers": [1],
                    "destinations": ["udp:nonexistent.invalid:9",
                                     f"udp:127.0.0.1:{udp.getsockname()[1]}"]}], 0.5, 0.0)
    try:
        relay.update("r", 0.0, 1.0, 2.0, 0.0)
        assert parse_datagram(udp.recv(1024))["name"] == "r"
        assert relay.tracks["r"].errors == 1 and relay.tracks["r"].sent == 1
    finally:
        relay.close()
