"""Robot relay over real UDP sockets on loopback: datagram format, sequence, stale messages."""

from __future__ import annotations

import math
import re
import socket

import pytest

from kmead.outputs.relay import Relay, datagram, parse_datagram

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
    assert relay.channels["amr1"].sent == 4 and relay.channels["amr1"].stale


def test_unreachable_destination_never_raises(udp: socket.socket) -> None:
    relay = Relay([{"name": "r", "markers": [1],
                    "destinations": ["udp:nonexistent.invalid:9",
                                     f"udp:127.0.0.1:{udp.getsockname()[1]}"]}], 0.5, 0.0)
    try:
        relay.update("r", 0.0, 1.0, 2.0, 0.0)
        assert parse_datagram(udp.recv(1024))["name"] == "r"
        assert relay.channels["r"].errors == 1 and relay.channels["r"].sent == 1
    finally:
        relay.close()


def _udp_listener() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(2.0)
    return s


def test_removed_robots_and_destinations_get_valid0_then_nothing() -> None:
    a, b, c = _udp_listener(), _udp_listener(), _udp_listener()
    dest = {s: f"udp:127.0.0.1:{s.getsockname()[1]}" for s in (a, b, c)}
    robots = [{"name": "amr1", "markers": [40, 41], "destinations": [dest[a], dest[b]]},
              {"name": "amr2", "markers": [42], "destinations": [dest[c]]}]
    relay = Relay(robots, 0.5, 0.0)
    try:
        relay.update("amr1", 5.0, 1.0, 2.0, 0.5)
        relay.update("amr2", 5.0, 3.0, 4.0, 0.0)
        assert parse_datagram(a.recv(1024))["valid"] and parse_datagram(b.recv(1024))["valid"]
        assert parse_datagram(c.recv(1024))["valid"]
        # Live change: amr2 removed, amr1 loses destination b.
        relay.configure([{**robots[0], "destinations": [dest[a]]}], t=5.1)
        gone_b, gone_c = parse_datagram(b.recv(1024)), parse_datagram(c.recv(1024))
        assert (gone_b["name"], gone_b["valid"], gone_b["x"]) == ("amr1", False, 1.0)
        assert (gone_c["name"], gone_c["valid"], gone_c["t"]) == ("amr2", False, 5.1)
        relay.update("amr1", 5.2, 1.1, 2.0, 0.5)
        assert parse_datagram(a.recv(1024))["x"] == 1.1
        for s in (b, c):  # nothing more to what was removed
            s.settimeout(0.2)
            with pytest.raises(TimeoutError):
                s.recv(1024)
        relay.shutdown(6.0)
        last = parse_datagram(a.recv(1024))
        assert (last["valid"], last["t"], last["x"]) == (False, 6.0, 1.1)
    finally:
        relay.close()
        for s in (a, b, c):
            s.close()


def test_refused_destination_is_counted_as_errors() -> None:
    closed = _udp_listener()
    port = closed.getsockname()[1]
    closed.close()  # nothing listens there now: the kernel answers port unreachable
    relay = Relay([{"name": "r", "markers": [1], "destinations": [f"udp:127.0.0.1:{port}"]}],
                  0.5, 0.0)
    try:
        for i in range(20):
            relay.update("r", float(i), 0.0, 0.0, 0.0)
        tr = relay.channels["r"]
        assert tr.sent + tr.errors == 20
        assert tr.errors >= 9, (tr.sent, tr.errors)  # at least every other send refused
        # Refusals, told apart from other errors: the UI says "no listener".
        assert tr.refused == tr.errors
        assert tr.refused_now() == [f"udp:127.0.0.1:{port}"]
        # Someone starts listening: the destination is no longer refused.
        listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        listener.bind(("127.0.0.1", port))
        try:
            for i in range(20, 30):
                relay.update("r", float(i), 0.0, 0.0, 0.0)
            assert tr.refused_now() == []
            assert listener.recv(1024)
        finally:
            listener.close()
    finally:
        relay.close()


def test_a_frames_datagrams_all_go_out_before_its_robot_telemetry(udp: socket.socket) -> None:
    """The daemon sends every robot's datagram of a frame first and publishes their telemetry
    after (a published body wakes the telemetry thread, which would compete with the next
    robot's datagram for the GIL)."""
    from kmea.pipeline import RobotFix
    from kmead.config.layers import load_config
    from kmead.run.daemon import Daemon

    port = udp.getsockname()[1]
    robots = (f'robots=[{{name="amr1", markers=[40, 41], destinations=["udp:127.0.0.1:{port}"]}},'
              f' {{name="amr2", markers=[42], destinations=["udp:127.0.0.1:{port}"]}}]')
    d = Daemon(load_config(None, ["source.spec=sim:default", robots, 'network.telemetry=""',
                                  'network.control=""']))
    arrived: list[int] = []
    udp.setblocking(False)

    def publish(topic: str, body: dict) -> None:
        if topic.startswith("robot."):
            n = 0
            while True:  # loopback delivers at send: count what is already there
                try:
                    udp.recv(1024)
                except BlockingIOError:
                    break
                n += 1
            arrived.append(n)

    try:
        d.relay.publish = publish
        fixes = {n: RobotFix(n, 0.1, 0.2, 0.3, 0.001, [40]) for n in ("amr1", "amr2")}
        d._relay_robots(100.0, fixes)
        got = list(arrived)
    finally:
        d.close()
    assert got == [2, 0], got  # both datagrams were out at the first publish


def test_the_sink_gets_every_message_after_the_frames_datagrams(udp: socket.socket) -> None:
    """The Zenoh output's hook: each fix (with its covariance), stale and stopping message,
    handed over where the telemetry body is, so after all of a frame's datagrams."""
    port = udp.getsockname()[1]
    seen: list[tuple[str, int, bool, bool, object]] = []
    relay = Relay([{"name": n, "markers": [m], "destinations": [f"udp:127.0.0.1:{port}"]}
                   for n, m in (("amr1", 40), ("amr2", 42))],
                  stale_after_s=0.5, stale_repeat_s=0.0,
                  sink=lambda tr, t, valid, stopping: seen.append(
                      (tr.name, tr.seq, valid, stopping, tr.cov)))
    try:
        cov = [[4e-6, 0, 0], [0, 4e-6, 0], [0, 0, 1e-4]]
        relay.update("amr1", 10.0, 0.1, 0.2, 0.3, 0.002, publish=False, cov=cov)
        relay.update("amr2", 10.0, 0.4, 0.5, 0.6, 0.002, publish=False)
        assert seen == []  # the datagrams first
        assert [parse_datagram(udp.recv(256))["name"] for _ in range(2)] == ["amr1", "amr2"]
        relay.publish_fixes(["amr1", "amr2"])
        assert seen == [("amr1", 1, True, False, cov), ("amr2", 1, True, False, None)]
        relay.tick(10.6)  # both stale
        assert [(s[0], s[2], s[3]) for s in seen[2:]] == [("amr1", False, False),
                                                          ("amr2", False, False)]
        relay.shutdown(11.0)
        assert [(s[0], s[1], s[2], s[3]) for s in seen[4:]] == [("amr1", 3, False, True),
                                                                ("amr2", 3, False, True)]
    finally:
        relay.close()


def test_a_pose_no_robot_can_use_is_never_sent_as_valid(udp: socket.socket) -> None:
    """Not finite, absurdly far, or with a sigma beyond relay.max_sigma_m: valid=0 on the
    wire and in the telemetry (the UI shows no fix, never "ok"), a short line; the next
    usable pose is valid again."""
    from kmea_tui.widgets.robots import robot_state

    port = udp.getsockname()[1]
    published = []
    relay = Relay([{"name": "amr1", "markers": [40, 41],
                    "destinations": [f"udp:127.0.0.1:{port}"]}],
                  stale_after_s=0.5, stale_repeat_s=1.0, extra_fields=True, max_sigma_m=0.1,
                  publish=lambda topic, body: published.append(body))
    poses = [(1.0, 1.0, 0.678), (math.nan, 1.0, 0.002), (1e308, 1.0, 0.002),
             (math.inf, 1.0, None), (1.0, 1.0, math.nan), (1.0, 1.0, 0.002)]
    try:
        for k, (x, y, sigma) in enumerate(poses):
            relay.update("amr1", 10.0 + 0.1 * k, x, y, 0.0, sigma)
        got = [udp.recv(1024) for _ in poses]
        # A live set of relay.max_sigma_m (the daemon's and the node's set requests).
        relay.apply({"stale_after_s": 0.5, "stale_repeat_s": 1.0, "extra_fields": True,
                     "max_sigma_m": 1.0})
        relay.update("amr1", 11.0, 1.0, 1.0, 0.0, 0.678)
        later = parse_datagram(udp.recv(1024))
    finally:
        relay.close()
    assert later["valid"] and later["sigma"] == 0.678
    published.pop()
    assert [parse_datagram(g)["valid"] for g in got] == [False] * 5 + [True]
    assert all(len(g) < 200 for g in got)
    assert [b["valid"] for b in published] == [False] * 5 + [True]
    assert [robot_state(b) for b in published] == ["no fix"] * 5 + ["ok"]
    assert relay.channels["amr1"].unfit is None
