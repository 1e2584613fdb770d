"""The fusion node end to end: two real daemons on the wide scene's two cameras, real
ZeroMQ sockets on loopback, a real UDP listener, a camera stopped and restarted, hostile
input; plus the pieces (input parsing, measurement checks, datagram extra fields)."""

from __future__ import annotations

import csv
import math
import socket
import threading
import time
from pathlib import Path

import pytest
import zmq
from deadlines import DEADLINE, JOIN

from kmea.sim.scenes import get_scene
from kmea.wire import protocol as P
from kmead.config.layers import ConfigError, load_config
from kmead.fusion.node import FusionNode, measurement_from, parse_inputs
from kmead.outputs.csvlog import HEADER
from kmead.outputs.relay import datagram, parse_datagram
from kmead.run.daemon import Daemon
from kmead.tools.kmea_cli import main as kmea_main

SPEED = 0.01  # m/s: the robots stay where the test expects them for its ~20 s
# A camera daemon in this busy process may stall for a second or two under load: stale only
# after longer than that, so that the camera left running keeps its robot valid.
STALE_S = 3.0


def _daemon(cam: int, epoch: float, telemetry: str = "tcp://127.0.0.1:*") -> Daemon:
    cfg = load_config(None, [
        f'source.spec="sim:wide?camera={cam}&clock=wall&epoch={epoch}&speed={SPEED}"',
        "source.width=640", "source.height=480", "source.fps=10",
        f'network.telemetry="{telemetry}"', 'network.control=""', "detector.workers=0",
        "stats.loo=false", 'log.level="warning"'])
    return Daemon(cfg)


def _start(d: Daemon) -> threading.Thread:
    t = threading.Thread(target=d.run, daemon=True)
    t.start()
    return t


def _stop(d: Daemon, t: threading.Thread) -> None:
    d.stop()
    t.join(timeout=JOIN)
    d.close()


class Udp:
    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.1)
        self.port = self.sock.getsockname()[1]

    def wait(self, pred, timeout: float) -> list[tuple[bytes, dict]]:
        """Datagrams until ``pred(seen)`` is true (or timeout); returns them all."""
        seen: list[tuple[bytes, dict]] = []
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            try:
                data = self.sock.recv(2048)
            except TimeoutError:
                continue
            seen.append((data, parse_datagram(data)))
            if pred(seen):
                break
        return seen


def _truth(name: str, t: float, epoch: float) -> tuple[float, float, float]:
    scene = get_scene("wide", speed=SPEED)
    robot = next(r for r in scene.robots if r.name == name)
    return robot.path.pose(t - epoch)


def test_two_cameras_fused_stop_and_return(tmp_path: Path,
                                           capsys: pytest.CaptureFixture) -> None:
    epoch = time.time()
    d0, d1 = _daemon(0, epoch), _daemon(1, epoch)
    t0, t1 = _start(d0), _start(d1)
    running = {"d0": (d0, t0), "d1": (d1, t1)}
    try:
        _fused_stop_and_return(d0, d1, epoch, running, tmp_path, capsys)
    finally:
        for d, t in running.values():
            _stop(d, t)


def _fused_stop_and_return(d0: Daemon, d1: Daemon, epoch: float, running: dict,
                           tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    ctx = zmq.Context.instance()
    junk = ctx.socket(zmq.PUB)  # a hostile "camera"
    junk_ep = f"tcp://127.0.0.1:{junk.bind_to_random_port('tcp://127.0.0.1')}"
    udp = Udp()
    log = tmp_path / "fused.csv"
    dest = f'destinations=["udp:127.0.0.1:{udp.port}"]'
    cfg = load_config(None, [
        'network.telemetry="tcp://127.0.0.1:*"', 'network.control="tcp://127.0.0.1:*"',
        f'robots=[{{name="amr1", markers=[40, 41], height=0.2, {dest}}}, '
        f'{{name="amr2", markers=[42], height=0.2, {dest}}}]',
        "relay.extra_fields=true", f"relay.stale_after_s={STALE_S}", f'log.csv="{log}"',
        'log.level="warning"'])
    node = FusionNode(cfg, parse_inputs([d0.telemetry.bound, d1.telemetry.bound,
                                         f"junk={junk_ep}"]))
    sub = ctx.socket(zmq.SUB)
    sub.connect(node.telemetry.bound)
    sub.setsockopt(zmq.SUBSCRIBE, P.TOPIC_ROBOTS.encode())
    tn = threading.Thread(target=node.run, daemon=True)
    tn.start()
    try:
        # 1. Both robots fused: amr1 in the overlap (both cameras), amr2 on floor B.
        def both_valid(seen):
            return {m["name"] for _, m in seen if m["valid"]} == {"amr1", "amr2"} and \
                sum(m["name"] == "amr1" for _, m in seen) > 10
        seen = udp.wait(both_valid, 60.0)
        assert both_valid(seen), [m for _, m in seen][-3:]
        data, m = seen[-1]
        keys = [p.split("=")[0] for p in data.decode().split(";")]
        assert keys == ["name", "seq", "t", "x", "y", "theta", "valid", "vx", "vy", "omega",
                        "sigma", "age"]
        for _, m in seen[-10:]:
            x, y, _ = _truth(m["name"], m["t"], epoch)
            assert math.hypot(m["x"] - x, m["y"] - y) < 0.02, m
            assert abs(m["vx"]) < 0.5 and m["age"] == 0.0  # 0.01 m/s, 10 noisy fixes/s
        sources = {}
        expected = {"amr1": "cam0+cam1", "amr2": "cam1"}
        end = time.monotonic() + DEADLINE
        while time.monotonic() < end and sources != expected:
            if sub.poll(200):
                body = P.decode(sub.recv_multipart())[1]
                sources = {r["name"]: r["source"] for r in body["robots"]}
        assert sources == expected, (node.status(),
                                                                  list(node.fusion.tracker.rejections))

        # 2. Hostile input: junk frames, wrong fields, a non-finite pose; nothing breaks.
        for frames in ([b"robot.amr1", b"\xff\x00"], [b"robot.amr1"],
                       P.encode("robot.amr1", {"name": "amr1", "valid": True, "t": 1.0,
                                               "x": "NaN", "y": 0.0, "theta": 0.0}),
                       P.encode("robot.ghost", {"name": "ghost", "valid": True})):
            junk.send_multipart(frames)
        end = time.monotonic() + DEADLINE
        while time.monotonic() < end and node.inputs[2].bad < 3:
            time.sleep(0.05)
        assert node.inputs[2].bad >= 3 and tn.is_alive()

        # 3. Camera 1 stops: amr2 (only it saw) goes stale, amr1 stays valid on camera 0.
        _stop(*running.pop("d1"))
        t_stop = time.time()
        # (STALE_S without a measurement: a daemon stalled by a busy machine is not "stopped")
        seen = udp.wait(lambda s: any(m["name"] == "amr2" and not m["valid"] for _, m in s),
                        60.0)
        assert any(m["name"] == "amr2" and not m["valid"] for _, m in seen)
        seen = udp.wait(lambda s: sum(m["name"] == "amr1" for _, m in s) > 5, 60.0)
        amr1 = [m for _, m in seen if m["name"] == "amr1"]
        assert len(amr1) > 5 and all(m["valid"] for m in amr1), (amr1, node.status())
        assert all(m["t"] > t_stop - STALE_S for m in amr1)

        # 4. It comes back on the same endpoint: amr2 is picked up again.
        d1 = _daemon(1, epoch, telemetry=node.inputs[1].endpoint)
        running["d1"] = (d1, _start(d1))
        seen = udp.wait(lambda s: any(m["name"] == "amr2" and m["valid"] for _, m in s), 60.0)
        assert any(m["name"] == "amr2" and m["valid"] for _, m in seen)
    finally:
        node.stop()
        tn.join(timeout=JOIN)
        status = node.status()
        robots_body = node.robots_body()
        node.close()
        sub.close(linger=0)
        junk.close(linger=0)
        udp.sock.close()
    assert status["fusion"]["latency_ms_p99"] is not None
    # The same declared message types as a daemon's (with the fusion node's own fields).
    P.check_body(P.TOPIC_STATUS, status, exact=True)
    P.check_body(P.TOPIC_ROBOTS, robots_body, exact=True)
    assert [i["label"] for i in status["inputs"]] == ["cam0", "cam1", "junk"]

    # 5. The CSV log is the daemon's format.
    with open(log, newline="") as f:
        assert f.readline().rstrip("\n") == HEADER
        f.seek(0)
        rows = list(csv.DictReader(f))
    assert rows and {r["kind"] for r in rows} == {"robot"}
    assert {r["algorithm"] for r in rows} == {"fusion"} and {r["id"] for r in rows} == {
        "amr1", "amr2"}
    assert {r["refs"] for r in rows if r["id"] == "amr1"} >= {"2"}

    # 6. The command line, until --frames fused outputs, on camera 0 alone.
    code = kmea_main(["fuse", "--input", d0.telemetry.bound, "--headless", "--frames", "5",
                      "--set", 'network.telemetry="tcp://127.0.0.1:*"',
                      "--set", 'network.control=""'])
    assert code == 0
    assert "kmea fuse: 5 fused outputs" in capsys.readouterr().out


def test_fuse_command_line_errors(capsys: pytest.CaptureFixture) -> None:
    assert kmea_main(["fuse", "--headless"]) == 2
    assert "no input" in capsys.readouterr().err
    off = ["--set", 'network.telemetry=""', "--set", 'network.control=""']
    assert kmea_main(["fuse", "--input", "tcp://nowhere", "--headless", *off]) == 2
    assert "--input" in capsys.readouterr().err
    assert kmea_main(["fuse", "--input", "tcp://127.0.0.1:1", "--set", "fusion.max_age_s=0",
                      "--headless"]) == 2
    assert "fusion.max_age_s" in capsys.readouterr().err
    for bad, key in (("filter.kind=\"ukf\"", "filter.kind"),
                     ("filter.gate_probability=1.0", "filter.gate_probability"),
                     ("fusion.inputs=[\"http://x\"]", "fusion.inputs")):
        assert kmea_main(["fuse", "--input", "tcp://127.0.0.1:1", "--set", bad,
                          "--headless", *off]) == 2
        assert key in capsys.readouterr().err


def test_inputs_and_measurements_are_checked() -> None:
    assert parse_inputs(["tcp://a:1", "top=tcp://b:2"]) == [("cam0", "tcp://a:1"),
                                                            ("top", "tcp://b:2")]
    with pytest.raises(ConfigError, match="duplicate"):
        parse_inputs(["x=tcp://a:1", "x=tcp://b:2"])
    names = {"amr1"}
    ok = {"name": "amr1", "valid": True, "t": 2.0, "x": 0.1, "y": 0.2, "theta": 0.3,
          "sigma": 0.002}
    m = measurement_from("cam1", ok, names)
    assert (m.source, m.name, m.t, m.x, m.sigma) == ("cam1", "amr1", 2.0, 0.1, 0.002)
    assert measurement_from("cam1", {**ok, "valid": False}, names) is None
    for bad, field in (({**ok, "name": "ghost"}, "name"), ({**ok, "t": float("inf")}, "t"),
                       ({**ok, "x": "1"}, "x"), ({**ok, "sigma": -1.0}, "sigma"),
                       ({**ok, "valid": 1}, "valid"), ({**ok, "theta": True}, "theta")):
        with pytest.raises(ValueError, match=f"'{field}'"):
            measurement_from("cam1", bad, names)


def test_datagram_extra_fields_follow_the_existing_ones() -> None:
    plain = datagram("amr1", 3, 12.5, 0.1, 0.2, 0.3, True)
    extra = datagram("amr1", 3, 12.5, 0.1, 0.2, 0.3, True,
                     {"vx": 0.5, "omega": -1.0, "sigma": float("nan")})
    assert extra.startswith(plain + b";vx=0.500000;vy=0.000000;omega=-1.000000;sigma=0.0")
    m = parse_datagram(extra)
    assert (m["vx"], m["omega"], m["age"], m["valid"]) == (0.5, -1.0, 0.0, True)
    assert "vx" not in parse_datagram(plain)


async def test_tui_connects_to_the_fusion_node_and_shows_the_cameras() -> None:
    from kmea_tui.app import KmeaTui
    from kmea_tui.client import DaemonClient
    from kmea_tui.widgets.robots import RobotsTable

    d1 = _daemon(1, time.time())
    t1 = _start(d1)
    cfg = load_config(None, ['network.telemetry="tcp://127.0.0.1:*"',
                             'network.control="tcp://127.0.0.1:*"', 'log.level="warning"',
                             "network.status_period_s=0.5"])
    node = FusionNode(cfg, parse_inputs([f"cam1={d1.telemetry.bound}"]))
    tn = threading.Thread(target=node.run, daemon=True)
    tn.start()
    app = KmeaTui(DaemonClient(node.telemetry.bound, node.control.bound, timeout=1.0),
                  theme="textual-dark", ping_period=0.5)
    try:
        async with app.run_test(size=(100, 30)) as pilot:
            robots = app.query_one(RobotsTable)
            await pilot.press("2")  # the UI repaints the visible tab only
            end = time.monotonic() + DEADLINE
            state = ""
            while time.monotonic() < end:
                if "amr2" in robots.raw:
                    state = str(robots.get_cell("amr2", "state"))
                    if state == "ok cam1" and app.connection_state == "connected":
                        break
                await pilot.pause(0.1)
            assert state == "ok cam1"
            assert app.connection_state == "connected"
    finally:
        node.stop()
        tn.join(timeout=JOIN)
        node.close()
        _stop(d1, t1)


def test_frames_n_stops_at_exactly_n_outputs_with_messages_queued() -> None:
    """``--frames N`` with more measurements already waiting on both inputs (as when the
    node is busy or two cameras send at once): the Nth fused output is the last one."""
    ctx = zmq.Context()
    pubs = []
    try:
        for i in range(2):
            pub = ctx.socket(zmq.XPUB)  # XPUB: the node's subscription can be waited for
            pub.setsockopt(zmq.LINGER, 0)
            pub.bind(f"inproc://frames-{i}")
            pubs.append(pub)
        cfg = load_config(None, [
            'network.telemetry=""', 'network.control=""', 'log.level="warning"',
            'robots=[{name="amr1", markers=[40], height=0.2, destinations=[]}, '
            '{name="amr2", markers=[42], height=0.2, destinations=[]}]'])
        node = FusionNode(cfg, parse_inputs(["inproc://frames-0", "inproc://frames-1"]),
                          max_outputs=5, context=ctx)
        try:
            for pub in pubs:
                assert pub.poll(30_000), "the node never subscribed"
                assert pub.recv() == b"\x01" + P.TOPIC_ROBOT_PREFIX.encode()
            # inproc delivers on send: all 20 are queued before run() reads the first.
            for k in range(10):
                for pub, name in zip(pubs, ("amr1", "amr2"), strict=True):
                    pub.send_multipart(P.encode(f"robot.{name}", {
                        "name": name, "seq": k, "valid": True, "t": 100.0 + 0.1 * k,
                        "x": 0.5 + 0.001 * k, "y": 0.3, "theta": 0.0, "sigma": 0.002}))
            tn = threading.Thread(target=node.run, daemon=True)
            tn.start()
            tn.join(timeout=60)
            stuck = tn.is_alive()
            node.stop()
            tn.join(timeout=JOIN)
            assert not stuck, [(i.received, i.bad, i.measurements) for i in node.inputs]
            assert node.outputs == 5
            assert sum(i.received for i in node.inputs) == 5  # the rest are left unread
            assert node.summary().startswith("kmea fuse: 5 fused outputs;")
        finally:
            node.close()
    finally:
        for pub in pubs:
            pub.close(linger=0)
        ctx.term()
