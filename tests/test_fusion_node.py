"""The fusion node end to end: two real daemons on the wide scene's two cameras, found on
Zenoh (real sessions on loopback, explicit endpoints), a real UDP listener; cameras played by
the test for what a daemon would not do (a map of its own, a frozen frame loop, hostile
messages); a camera killed and restarted; plus the pieces (measurement checks, datagram
extra fields)."""

from __future__ import annotations

import csv
import json
import math
import socket
import threading
import time
from pathlib import Path

import pytest
from deadlines import DEADLINE, JOIN, wait_until

pytest.importorskip("zenoh", reason="the zenoh extra is not installed "
                                    "(pip install 'kmea[zenoh]')")

from zenoh_helpers import FakeCamera, free_port, meta, open_peer, zenoh_sets

from kmea.maps.files import map_digest, save_map_toml
from kmea.sim.scenes import get_scene
from kmea.wire import protocol as P
from kmead.config.layers import load_config
from kmead.fusion.cameras import measurement_from
from kmead.fusion.election import Election
from kmead.fusion.node import FusionNode
from kmead.outputs.csvlog import HEADER
from kmead.outputs.relay import datagram, parse_datagram
from kmead.outputs.robot_pose_wire import TRACKED, unpack_pose
from kmead.run.daemon import Daemon
from kmead.tools.kmea_cli import main as kmea_main

SPEED = 0.01  # m/s: the robots stay where the test expects them for its ~20 s
# A camera daemon in this busy process may stall for a second or two under load: stale only
# after longer than that, so that the camera left running keeps its robot valid.
STALE_S = 3.0


def _daemon(cam: int, epoch: float, port: int, robots: str | None = None) -> Daemon:
    """Camera ``cam`` of the wide scene, a Zenoh peer connecting to the node's ``port``."""
    cfg = load_config(None, [
        f'source.spec="sim:wide?camera={cam}&clock=wall&epoch={epoch}&speed={SPEED}"',
        "source.width=640", "source.height=480", "source.fps=10",
        'network.telemetry="tcp://127.0.0.1:*"', 'network.control=""', "detector.workers=0",
        "stats.loo=false", 'log.level="warning"', *zenoh_sets(connect=port),
        *([robots] if robots else [])])
    return Daemon(cfg)


_wait = wait_until


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

    def wait(self, pred, timeout: float = DEADLINE) -> list[tuple[bytes, dict]]:
        """Datagrams until ``pred(seen)`` is true (or timeout); returns them all. The
        sender's port of each is in ``self.senders``."""
        seen: list[tuple[bytes, dict]] = []
        self.senders: list[int] = []
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            try:
                data, addr = self.sock.recvfrom(2048)
            except TimeoutError:
                continue
            seen.append((data, parse_datagram(data)))
            self.senders.append(addr[1])
            if pred(seen):
                break
        return seen


def _truth(name: str, t: float, epoch: float) -> tuple[float, float, float]:
    scene = get_scene("wide", speed=SPEED)
    robot = next(r for r in scene.robots if r.name == name)
    return robot.path.pose(t - epoch)


def _node_cfg(port: int, wide: Path, *extra: str):
    return load_config(None, [
        'network.telemetry="tcp://127.0.0.1:*"', 'network.control="tcp://127.0.0.1:*"',
        'log.level="warning"', f'map.file="{wide}"', *zenoh_sets(listen=port), *extra])


def _wide_map(tmp_path: Path) -> tuple[Path, str]:
    wide = tmp_path / "wide.toml"
    m = get_scene("wide").effective_map()
    save_map_toml(m, wide)
    return wide, map_digest(m)


def test_cameras_found_on_zenoh_fused_dropped_refused_and_back(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    epoch = time.time()
    port = free_port()
    wide, digest = _wide_map(tmp_path)
    udp = Udp()
    log = tmp_path / "fused.csv"
    dest = f'destinations=["udp:127.0.0.1:{udp.port}"]'
    robots = (f'robots=[{{name="amr1", markers=[40, 41], height=0.2, {dest}}}, '
              f'{{name="amr2", markers=[42], height=0.2, {dest}}}]')
    cfg = _node_cfg(port, wide, robots, "relay.extra_fields=true",
                    f"relay.stale_after_s={STALE_S}", f'log.csv="{log}"')
    node = FusionNode(cfg)
    tn = threading.Thread(target=node.run, daemon=True)
    tn.start()
    # The cameras have the robots' UDP destinations too: they hand them to the node.
    running = {f"d{c}": (d := _daemon(c, epoch, port, robots), _start(d)) for c in (0, 1)}
    fakes: list[FakeCamera] = []
    try:
        _fused_dropped_refused_and_back(node, running, fakes, port, digest, epoch, udp)
    finally:
        node.stop()
        tn.join(timeout=JOIN)
        status = node.status()
        robots_body = node.robots_body()
        node.close()
        for d, t in running.values():
            _stop(d, t)
        for f in fakes:
            f.close()
        udp.sock.close()
    assert status["fusion"]["latency_ms_p99"] is not None
    # The same declared message types as a daemon's (with the fusion node's own fields).
    P.check_body(P.TOPIC_STATUS, status, exact=True)
    P.check_body(P.TOPIC_ROBOTS, robots_body, exact=True)
    states = {i["label"]: i["state"] for i in status["inputs"]}
    assert states["cam0"] == "used" and states["odd"] == "refused"

    # The CSV log is the daemon's format.
    with open(log, newline="") as f:
        assert f.readline().rstrip("\n") == HEADER
        f.seek(0)
        rows = list(csv.DictReader(f))
    assert rows and {r["kind"] for r in rows} == {"robot"}
    assert {r["algorithm"] for r in rows} == {"fusion"} and {r["id"] for r in rows} == {
        "amr1", "amr2"}
    assert {r["refs"] for r in rows if r["id"] == "amr1"} >= {"2"}

    # The command line, until --frames fused outputs, on camera 0 alone (it reconnects to
    # the port the command's node listens on now).
    d0 = _daemon(0, epoch, port)
    t0 = _start(d0)
    try:
        code = kmea_main(["fuse", "--headless", "--frames", "5",
                          "--set", 'network.telemetry="tcp://127.0.0.1:*"',
                          "--set", 'network.control=""', "--set", "zenoh.lease_s=2.0",
                          "--set", f'zenoh.listen=["tcp/127.0.0.1:{port}"]'])
    finally:
        _stop(d0, t0)
    assert code == 0
    assert "kmea fuse: 5 fused outputs" in capsys.readouterr().out


def _fused_dropped_refused_and_back(node: FusionNode, running: dict, fakes: list,
                                    port: int, digest: str, epoch: float, udp: Udp) -> None:
    # 1. Both cameras found and used; both robots fused: amr1 in the overlap (both
    #    cameras), amr2 on floor B. One voice: the node's, the cameras handed over.
    _wait(lambda: {c.label: c.state for c in node.cameras.values()}
          == {"cam0": "used", "cam1": "used"}, "both cameras used")
    _wait(lambda: node.election.role == "active", "the node active")
    _wait(lambda: all(not d.zenoh_camera.voice.speaking() for d, _ in running.values())
          and node.speaker.voice.speaking() == {"amr1", "amr2"},
          "the cameras handed both robots to the node")
    udp.wait(lambda s: False, 0.5)  # what a camera sent before it handed over
    seen = udp.wait(lambda s: {m["name"] for _, m in s if m["valid"]} == {"amr1", "amr2"}
                    and sum(m["name"] == "amr1" for _, m in s) > 10)
    assert {m["name"] for _, m in seen if m["valid"]} == {"amr1", "amr2"}
    assert len(set(udp.senders)) == 1, "a second voice: datagrams from two senders"
    data, m = seen[-1]
    keys = [p.split("=")[0] for p in data.decode().split(";")]
    assert keys == ["name", "seq", "t", "x", "y", "theta", "valid", "vx", "vy", "omega",
                    "sigma", "age"]
    for _, m in seen[-10:]:
        x, y, _ = _truth(m["name"], m["t"], epoch)
        assert math.hypot(m["x"] - x, m["y"] - y) < 0.02, m
    expected = {"amr1": "cam0+cam1", "amr2": "cam1"}
    _wait(lambda: {r["name"]: r["source"] for r in node.robots_body()["robots"]} == expected,
          "amr1 from both cameras, amr2 from camera 1")
    # The fused poses on Zenoh too: the binary pose on <site>/robots/<robot>/pose.
    poses: list = []
    listener = open_peer(connect=port)
    sub = listener.declare_subscriber(
        "kmea/robots/*/pose", lambda smp: poses.append(unpack_pose(smp.payload.to_bytes())))
    try:
        _wait(lambda: sum(p.valid for p in list(poses)) >= 5, "fused binary poses on Zenoh")
    finally:
        sub.undeclare()
        listener.close()
    for p in [p for p in poses if p.valid][-5:]:
        assert p.flags & TRACKED and p.sigma_x > 0

    # 2. A camera whose map differs is refused, with the reason.
    odd = FakeCamera(port, "odd", meta("odd", "0" * 16))
    fakes.append(odd)
    _wait(lambda: "odd" in node.cameras and node.cameras["odd"].state == "refused",
          "the odd camera refused")
    assert "map" in (node.cameras["odd"].reason or "")
    odd.measurement("amr1", time.time(), 5.0, 5.0)  # never fused: amr1 is not at (5, 5)

    # 3. Hostile messages: counted once reported, never raised; the node goes on.
    junk = FakeCamera(port, "junk", b"\xff\x00 not json")
    fakes.append(junk)
    _wait(lambda: "junk" in node.cameras and node.cameras["junk"].state == "refused",
          "the junk camera refused (bad metadata)")
    for suffix, body in (("robots/amr1", b"\xff\x00"), ("robots/amr1", b"x" * 5000),
                         ("robots/amr1", b'{"name": "amr1", "valid": true, "t": 1.0, '
                                         b'"x": NaN, "y": 0, "theta": 0}'),
                         ("robots/ghost", {"name": "ghost", "valid": True}),
                         ("robots/amr2", {"name": "amr1", "valid": True}),
                         ("frame", b"[1, 2]")):
        junk.put(suffix, body)
    _wait(lambda: node.cameras["junk"].bad >= 5, "five bad messages counted")
    _wait(lambda: node.cameras["junk"].ignored >= 1, "another node's robot ignored")
    assert all(m["name"] in ("amr1", "amr2") for _, m in udp.wait(lambda s: len(s) > 3))

    # Two kmead holding one camera id (two sessions' tokens): the status says so.
    with node.lock:
        for zid in ("aaaa1111", "bbbb2222"):
            node.handle("twin", f"kmea/cam/twin/zid/{zid}", True, 0.0)
    (twin,) = [i for i in node.status()["inputs"] if i["label"] == "twin"]
    assert "2 kmead claim this camera id" in (twin["reason"] or "")

    # 4. A frozen camera (alive, its frame loop stuck): dropped within the lease.
    frozen = FakeCamera(port, "frozen", meta("frozen", digest))
    fakes.append(frozen)
    stop_beats = threading.Event()

    def beats() -> None:
        while not stop_beats.wait(0.1):
            frozen.put("frame", {"t": time.time(), "frames": 1})

    tb = threading.Thread(target=beats, daemon=True)
    tb.start()
    _wait(lambda: "frozen" in node.cameras and node.cameras["frozen"].state == "used",
          "the frozen camera used while it sends")
    stop_beats.set()
    tb.join(timeout=JOIN)
    t_freeze = time.monotonic()
    _wait(lambda: node.cameras["frozen"].state == "silent", "the frozen camera dropped")
    # (its token is still alive: the data timeout dropped it, not Zenoh)
    assert "lease" in (node.cameras["frozen"].reason or "")
    assert time.monotonic() - t_freeze >= node.lease_s * 0.9

    # 5. Camera 1 killed: dropped at once (its token goes); amr2, which only it saw, goes
    #    stale; amr1 stays valid on camera 0.
    _stop(*running.pop("d1"))
    _wait(lambda: node.cameras["cam1"].state == "gone", "camera 1 gone")
    seen = udp.wait(lambda s: any(m["name"] == "amr2" and not m["valid"] for _, m in s))
    assert any(m["name"] == "amr2" and not m["valid"] for _, m in seen)
    seen = udp.wait(lambda s: sum(m["name"] == "amr1" for _, m in s) > 5)
    amr1 = [m for _, m in seen if m["name"] == "amr1"]
    assert len(amr1) > 5 and all(m["valid"] for m in amr1), (amr1, node.status())

    # 6. It comes back: used again, amr2 valid again.
    d1 = _daemon(1, epoch, port)
    running["d1"] = (d1, _start(d1))
    _wait(lambda: node.cameras["cam1"].state == "used", "camera 1 used again")
    seen = udp.wait(lambda s: any(m["name"] == "amr2" and m["valid"] for _, m in s))
    assert any(m["name"] == "amr2" and m["valid"] for _, m in seen)


def test_fuse_command_line_errors(capsys: pytest.CaptureFixture) -> None:
    off = ["--set", 'network.telemetry=""', "--set", 'network.control=""']
    assert kmea_main(["fuse", "--set", "fusion.max_age_s=0", "--headless", *off]) == 2
    assert "fusion.max_age_s" in capsys.readouterr().err
    for bad, key in (("filter.kind=\"ukf\"", "filter.kind"),
                     ("filter.gate_probability=1.0", "filter.gate_probability"),
                     ('zenoh.listen=["tcp/10.1.2.3:7447"]', "zenoh.listen"),
                     ("fusion.inputs=[]", "fusion.inputs")):
        assert kmea_main(["fuse", "--set", bad, "--headless", *off]) == 2
        assert key in capsys.readouterr().err
    # --input is gone: the cameras are found on Zenoh.
    with pytest.raises(SystemExit):
        kmea_main(["fuse", "--input", "tcp://127.0.0.1:5555", "--headless", *off])


def test_election_one_voice_no_preemption_and_step_down() -> None:
    """The rule (kmead.fusion.Election), as each node applies it to the tokens it sees."""
    a = Election("b", grace_s=1.0, now=0.0)
    assert a.decide(0.5) is None and a.role == "starting"  # watches the site first
    assert a.decide(1.0) == "standby" and a.decide(1.0) == "active"
    # A node with a lower id starts: it is "starting", then a standby; no preemption.
    a.token("a", "starting", True)
    assert a.decide(2.0) is None
    a.token("a", "starting", False)
    a.token("a", "standby", True)
    assert a.decide(3.0) is None and a.role == "active"
    # Seen from the newcomer: an active node is there, it waits.
    n = Election("a", grace_s=1.0, now=2.0)
    n.token("b", "active", True)
    assert n.decide(3.0) == "standby" and n.decide(3.0) is None
    # The active one dies: the lowest standby claims.
    n.token("b", "active", False)
    assert n.decide(3.1) == "active"
    # Two actives (a partition healed): the higher id steps down once it hears the other
    # speak; a lower active token that says nothing (a stranger's) silences nobody.
    a.token("a", "standby", False)
    a.token("a", "active", True)
    assert a.decide(4.0) is None and a.role == "active"
    assert a.decide(4.0, speaking={"c"}) is None and a.role == "active"
    assert a.decide(4.0, speaking={"a"}) == "standby" and a.decide(4.0) is None
    # A standby with a higher id does not claim while a lower standby lives.
    c = Election("c", grace_s=1.0, now=0.0)
    c.decide(1.0)
    c.token("a", "standby", True)
    assert c.decide(2.0) is None
    # Frozen beyond the lease: step down and start over.
    assert n.decide(10.0, stalled=True) == "starting"
    assert n.decide(10.5) is None and n.decide(11.0) == "standby"


def test_measurements_are_checked() -> None:
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


async def test_tui_connects_to_the_fusion_node_and_shows_the_cameras(tmp_path: Path) -> None:
    from kmea_tui.app import KmeaTui
    from kmea_tui.client import DaemonClient
    from kmea_tui.widgets.robots import RobotsTable

    port = free_port()
    wide, _ = _wide_map(tmp_path)
    node = FusionNode(_node_cfg(port, wide, "network.status_period_s=0.5"))
    tn = threading.Thread(target=node.run, daemon=True)
    tn.start()
    d1 = _daemon(1, time.time(), port)
    t1 = _start(d1)
    assert node.telemetry is not None and node.control is not None
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
    """``--frames N`` with more measurements already waiting (as when the node is busy or
    two cameras send at once): the Nth fused output is the last one. The items go into the
    node's queue as Zenoh's callbacks put them."""
    port = free_port()
    cfg = load_config(None, [
        'network.telemetry=""', 'network.control=""', 'log.level="warning"',
        'robots=[{name="amr1", markers=[40], height=0.2, destinations=[]}, '
        '{name="amr2", markers=[42], height=0.2, destinations=[]}]',
        *zenoh_sets(listen=port)])
    node = FusionNode(cfg, max_outputs=5)
    try:
        for cam in ("c0", "c1"):
            node.handle("camera", f"kmea/cam/{cam}", True, 0.0)
            node.handle("meta", cam, json.dumps(meta(cam, "d" * 16)).encode(), 0.0)
        assert {c.state for c in node.cameras.values()} == {"used"}
        t0 = time.time() - 1.0  # Unix time, as the cameras stamp it
        for k in range(10):
            for cam, name in (("c0", "amr1"), ("c1", "amr2")):
                node.queue.put(("data", f"kmea/cam/{cam}/robots/{name}", json.dumps({
                    "name": name, "valid": True, "t": t0 + 0.01 * k, "x": 0.5 + 0.001 * k,
                    "y": 0.3, "theta": 0.0, "sigma": 0.002}).encode(), time.perf_counter()))
        tn = threading.Thread(target=node.run, daemon=True)
        tn.start()
        tn.join(timeout=DEADLINE)
        stuck = tn.is_alive()
        node.stop()
        tn.join(timeout=JOIN)
        assert not stuck, node.summary()
        assert node.outputs == 5
        assert sum(c.received for c in node.cameras.values()) == 5  # the rest left unread
        assert node.summary().startswith("kmea fuse: 5 fused outputs;")
    finally:
        node.close()


def test_a_node_served_by_the_host_tells_systemd_ready_and_stopping(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """kmea fuse is served by the daemon's host (kmead.tools.host.serve): READY=1 once its
    sockets are bound, STOPPING=1 at the end, over a real notify socket."""
    import socket as sk

    from kmead.tools.host import serve

    path = str(tmp_path / "notify.sock")
    listener = sk.socket(sk.AF_UNIX, sk.SOCK_DGRAM)
    listener.bind(path)
    listener.settimeout(DEADLINE)
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    wide, _ = _wide_map(tmp_path)
    node = FusionNode(_node_cfg(free_port(), wide))
    got: list[str] = []

    def watch() -> None:  # READY, then stop the node as SIGTERM would
        try:
            got.append(listener.recv(4096).decode())
        finally:
            node.stop()

    t = threading.Thread(target=watch)
    t.start()
    code = serve(node, False, "fusing")  # the main thread: it installs the signal handlers
    t.join(JOIN)
    assert code == 0 and not t.is_alive()
    assert got and got[0].split("\n")[0] == "READY=1" and "STATUS=fusing" in got[0]
    while "STOPPING=1" not in got[-1]:
        got.append(listener.recv(4096).decode())
    listener.close()
    assert node.closed  # closed by the host
