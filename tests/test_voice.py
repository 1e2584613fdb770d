"""One voice per robot (kmead.outputs.voice): the rules between cameras and fusion nodes, on
an in-memory bus that delivers when the test says (the network's delay made explicit), with
the relay's own robot channels. The same rules over real Zenoh sessions and processes:
tests/test_fusion_voice.py."""

from __future__ import annotations

import contextlib
import json
from dataclasses import dataclass
from typing import Any

import pytest

import kmead.outputs.voice as voice_mod
from kmead.outputs.relay import Relay, RobotChannel
from kmead.outputs.voice import BETTER_S, CAMERA, CLAIM_EVERY_S, NODE, TAKEOVER_SKIP, Voice

FRAME_S = 0.05  # s: the time between two messages of a speaker, on the test's clock


class Clock:
    """The voices' monotonic clock, advanced by the test (no scheduling involved)."""

    def __init__(self) -> None:
        self.t = 1000.0

    def monotonic(self) -> float:
        return self.t


@pytest.fixture(autouse=True)
def clock(monkeypatch: pytest.MonkeyPatch) -> Clock:
    c = Clock()
    monkeypatch.setattr(voice_mod, "time", c)
    return c


@dataclass
class _Sample:
    key_expr: str
    data: bytes

    @property
    def payload(self) -> Any:
        return self

    def to_bytes(self) -> bytes:
        return self.data


class Bus:
    """Zenoh's put and subscribe, held until :meth:`flush` (every session hears every put)."""

    def __init__(self) -> None:
        self.subs: list[Any] = []
        self.pending: list[_Sample] = []
        self.log: list[dict] = []

    def session(self) -> Any:
        bus = self

        class Session:
            def declare_subscriber(self, key: str, cb: Any) -> Any:
                bus.subs.append(cb)

                class Sub:
                    def undeclare(self) -> None:
                        bus.subs.remove(cb)
                return Sub()

            def put(self, key: str, payload: bytes) -> None:
                bus.pending.append(_Sample(key, payload))
                with contextlib.suppress(ValueError):
                    bus.log.append(json.loads(payload))
        return Session()

    def flush(self) -> None:
        while self.pending:
            s = self.pending.pop(0)
            for cb in list(self.subs):
                cb(s)


def _channel(name: str = "amr1") -> RobotChannel:
    return RobotChannel(name, [40], [], [])


class Speaker:
    """A speaker's relay channel for one robot and its voice: ``send`` is what the relay
    does with each message (ask, count, say)."""

    def __init__(self, bus: Bus, me: str, kind: str, **kw: Any) -> None:
        self.quiet: list[str] = []
        self.voice = Voice(bus.session(), "kmea", me, kind, known=lambda n: n == "amr1",
                           on_quiet=self.quiet.append, listen_s=0.0, **kw)
        self.tr = _channel()
        self.sent: list[int] = []

    def send(self, q: float | None = 0.002, valid: bool = True) -> bool:
        voice_mod.time.t += FRAME_S / 10  # type: ignore[attr-defined]
        if self.voice.kind == CAMERA and valid:
            self.voice.want("amr1", q)
        ok = self.voice.speak(self.tr, valid)
        self.tr.seq += 1
        if ok:
            self.sent.append(self.tr.seq)
            self.voice.said(self.tr, valid)
        return ok


def start(bus: Bus, sp: Speaker, q: float = 0.002) -> None:
    """A camera on a silent robot: it claims for a claim period, then speaks."""
    for _ in range(10):
        if sp.send(q=q):
            bus.flush()
            return
        bus.flush()
        voice_mod.time.t += CLAIM_EVERY_S / 2  # type: ignore[attr-defined]
    raise AssertionError("the camera never spoke")


def test_a_camera_hands_a_robot_to_the_node_before_the_node_speaks() -> None:
    bus = Bus()
    cam = Speaker(bus, "cam0", CAMERA)
    node = Speaker(bus, "n1", NODE)
    start(bus, cam)
    for _ in range(5):
        assert cam.send()
        bus.flush()
    node.tr.seq = 2  # the node counted its own (muted) outputs
    assert not node.send()  # the camera speaks: the node claims first
    assert cam.send()  # the claim is still on its way: the camera goes on
    bus.flush()  # the claim arrives: the camera yields, naming the node
    assert not cam.send() and cam.quiet == ["amr1"]  # its Zenoh outputs go
    bus.flush()
    assert node.send() and node.send()
    bus.flush()
    assert not cam.send(q=0.0001)  # a node speaks: a camera never claims
    # One sequence: the node continues above the camera's last (a yield reserves one).
    assert node.sent[0] > cam.sent[-1] and node.sent == sorted(set(node.sent))
    assert [m["op"] for m in bus.log if m["by"] == "cam0"][-1] == "yield"


def test_a_node_that_stops_hands_back_to_the_camera_that_measured_last() -> None:
    bus = Bus()
    cam = Speaker(bus, "cam0", CAMERA)
    node = Speaker(bus, "n1", NODE, successor=lambda name: ("cam0", CAMERA))
    assert node.send()  # nobody spoke: the node takes the robot at once
    bus.flush()
    assert not cam.send()
    for _ in range(3):
        assert node.send()
    bus.flush()
    node.voice.stopping = True
    node.voice.release()
    bus.flush()
    assert not node.send(valid=False)  # its valid=0 at the close does not go out
    assert cam.send()  # named: the camera's next fix goes out at once
    assert cam.sent[0] > node.sent[-1]


def test_a_node_that_stops_yields_to_the_new_active_node_and_an_active_one_to_nobody() -> None:
    bus = Bus()
    a = Speaker(bus, "n2", NODE)
    b = Speaker(bus, "n1", NODE, alive=lambda s, k: True)
    assert a.send()
    bus.flush()
    assert not b.send()  # a claim: an active node does not yield to it
    bus.flush()
    assert a.send()
    a.voice.stopping = True
    bus.flush()
    b.voice._robot("amr1").claimed = -1e9  # its next claim goes at once
    assert not b.send()
    bus.flush()  # the stopping node yields
    assert not a.send()
    bus.flush()
    assert b.send() and b.sent[0] > a.sent[-1]


def test_a_killed_node_is_replaced_at_once_when_its_token_went() -> None:
    bus = Bus()
    alive = {"n1"}
    a = Speaker(bus, "n1", NODE)
    b = Speaker(bus, "n2", NODE, alive=lambda s, k: s in alive)
    assert a.send() and a.send()
    bus.flush()
    assert not b.send()  # a claim: n1 speaks
    alive.clear()  # its token went (killed)
    # Its last messages may have reached the robot without their say: numbers skipped.
    assert b.send() and b.sent[0] > a.sent[-1] + TAKEOVER_SKIP


def test_cameras_one_at_a_time_the_better_one_with_hysteresis() -> None:
    bus = Bus()
    c0 = Speaker(bus, "cam0", CAMERA)
    c1 = Speaker(bus, "cam1", CAMERA)
    start(bus, c0)
    assert not c1.send(q=0.0015)  # it sees the robot a little better: a claim only
    bus.flush()
    c0.voice.frame({"amr1"})
    assert c0.send(q=0.002)  # within the hysteresis: camera 0 keeps it
    bus.flush()
    c0.voice.frame(set())  # camera 0 lost the robot; camera 1 claims it: hand-over
    bus.flush()
    assert c1.send(q=0.0015) and c1.sent[0] > c0.sent[-1]
    bus.flush()
    # Camera 0 sees it again, not twice as well: camera 1 keeps it; no valid=0 from 0.
    assert not c0.send(q=0.001)
    assert not c0.send(valid=False)
    bus.flush()
    c1.voice.frame({"amr1"})
    assert c1.send(q=0.0015)
    c0.voice._robot("amr1").claimed = -1e9
    assert not c0.send(q=0.0005)  # twice as well: a claim ...
    bus.flush()
    c1.voice.frame({"amr1"})  # ... not granted at once (a sigma is noisy) ...
    bus.flush()
    assert not c0.send(q=0.0005)
    t_better = voice_mod.time.t  # type: ignore[attr-defined]
    while not c0.send(q=0.0005):  # ... but once it has lasted BETTER_S
        assert voice_mod.time.t - t_better < BETTER_S + 2 * FRAME_S  # type: ignore[attr-defined]
        voice_mod.time.t += FRAME_S  # type: ignore[attr-defined]
        assert c1.send(q=0.0015)
        c0.voice._robot("amr1").claimed = -1e9
        bus.flush()
        c1.voice.frame({"amr1"})
        bus.flush()
    assert voice_mod.time.t - t_better >= BETTER_S  # type: ignore[attr-defined]
    seqs = sorted(c0.sent + c1.sent)
    assert len(set(seqs)) == len(seqs)


def test_after_a_silence_the_best_camera_starts_and_only_it() -> None:
    bus = Bus()
    c0 = Speaker(bus, "cam0", CAMERA)
    c1 = Speaker(bus, "cam1", CAMERA)
    for _ in range(4):  # both claim for a claim period; the better (camera 1) starts
        c0.send(q=0.003)
        c1.send(q=0.001)
        bus.flush()
        voice_mod.time.t += CLAIM_EVERY_S / 2  # type: ignore[attr-defined]
    assert c1.sent and not c0.sent
    assert not c0.send(q=0.003)


@pytest.mark.parametrize("frame_s", [0.8, 2.5])
def test_a_lone_camera_at_a_slow_frame_rate_speaks_by_its_second_frame(frame_s: float) -> None:
    """Seconds between frames (a Pi in a full detection, an emulated one): the claims of
    successive frames are one run, so the camera starts at its second frame."""
    bus = Bus()
    cam = Speaker(bus, "cam0", CAMERA)
    spoke = []
    for _ in range(4):
        spoke.append(cam.send())
        bus.flush()
        voice_mod.time.t += frame_s  # type: ignore[attr-defined]
    assert spoke == [False, True, True, True]


def test_two_voices_heard_at_once_the_lower_rank_stops() -> None:
    bus = Bus()
    n1, n2 = Speaker(bus, "n1", NODE), Speaker(bus, "n2", NODE)
    assert n1.send() and n2.send()  # cut off from each other: both speak
    bus.flush()
    assert n1.send() and not n2.send()  # they meet: the lower id stays
    bus.flush()
    cam = Speaker(bus, "cam0", CAMERA)
    voice_mod.time.t += 1.0  # type: ignore[attr-defined]  # the nodes went quiet
    start(bus, cam)
    n1.voice.alive = lambda s, k: False  # n1 believes the camera gone: it speaks at once
    assert cam.send() and n1.send()
    bus.flush()
    assert not cam.send() and n1.send()


def test_hostile_voice_messages_are_counted_and_change_nothing() -> None:
    bus = Bus()
    cam = Speaker(bus, "cam0", CAMERA)
    s = bus.session()
    for body in (b"\xff", b"[1]", b'{"op": "say"}', json.dumps({
            "op": "say", "by": "x" * 100, "kind": "node", "seq": 5}).encode(),
            json.dumps({"op": "say", "by": "n", "kind": "node", "seq": -1}).encode(),
            json.dumps({"op": "say", "by": "n", "kind": "node", "seq": 2**40}).encode(),
            json.dumps({"op": "yield", "by": "n", "kind": "node", "seq": 1,
                        "to": "../x", "tk": "node"}).encode(), b"{" * 600):
        s.put("kmea/voice/amr1", body)
    s.put("kmea/voice/ghost", json.dumps({"op": "say", "by": "n", "kind": "node",
                                          "seq": 9}).encode())  # not a robot of ours
    bus.flush()
    assert cam.voice.bad == 8
    start(bus, cam)


def test_the_relay_asks_the_voice_and_sends_nothing_when_it_is_not_its_turn() -> None:
    bus = Bus()
    node = Speaker(bus, "n1", NODE)
    relay = Relay([{"name": "amr1", "markers": [40], "destinations": []}], 0.5, 1.0)
    sunk: list[int] = []
    relay.sink = lambda tr, t, valid, stopping: sunk.append(tr.seq)
    relay.voice = Voice(bus.session(), "kmea", "cam0", CAMERA, known=lambda n: True,
                        listen_s=0.0)
    relay.update("amr1", 1.0, 0.1, 0.2, 0.0, 0.002)  # no fix seen: not the camera's
    relay.voice.want("amr1", 0.002)
    relay.update("amr1", 1.1, 0.1, 0.2, 0.0, 0.002)  # a claim
    bus.flush()
    voice_mod.time.t += CLAIM_EVERY_S  # type: ignore[attr-defined]
    relay.voice.want("amr1", 0.002)
    relay.update("amr1", 1.15, 0.1, 0.2, 0.0, 0.002)  # nobody else: it speaks
    bus.flush()
    assert node.send() is False  # a claim
    bus.flush()
    relay.update("amr1", 1.2, 0.1, 0.2, 0.0, 0.002)
    relay.shutdown(1.3)  # its valid=0 does not go either: the node speaks
    bus.flush()
    assert node.send()
    assert sunk == [3] and node.sent[0] > 3


def test_a_new_speaker_never_sends_the_robot_back_in_time() -> None:
    bus = Bus()
    cam = Speaker(bus, "cam0", CAMERA)
    node = Voice(bus.session(), "kmea", "n1", NODE, known=lambda n: True, listen_s=0.0)
    start(bus, cam)
    cam.voice.want("amr1", 0.002)
    assert cam.voice.speak(cam.tr, True, 10.0)
    cam.tr.seq += 1
    cam.voice.said(cam.tr, True, 10.0)
    bus.flush()
    tr = _channel()
    assert not node.speak(tr, True, 9.8)  # a claim
    bus.flush()  # the camera yields
    assert not node.speak(tr, True, 9.9)  # lagging behind the camera's last: not yet
    assert node.speak(tr, True, 10.05) and tr.seq >= cam.tr.seq


def test_a_camera_sends_the_fusion_nodes_every_measurement_also_those_it_rejected() -> None:
    from kmead.outputs.robots import RobotSender
    from kmead.outputs.totals import RunTotals

    class Cam:
        def __init__(self) -> None:
            self.got: list[tuple] = []
            self.voice = self

        def want(self, name: str, q: float | None) -> None:
            pass

        def measurement(self, name: str, t: float, x: float, y: float, theta: float,
                        sigma: float | None) -> None:
            self.got.append((name, t, x, y))

        def frame(self, t: float, seen: set[str]) -> None:
            pass

    relay = Relay([{"name": "amr1", "markers": [40], "destinations": []}], 0.5, 1.0)
    sender = RobotSender(relay, RunTotals(), lambda level, text: None)
    sender.camera = cam = Cam()
    # The camera's own filter rejected amr1's measurement: no fix, the measurement goes.
    sender.send(5.0, {}, None, False, 0.0, measured={"amr1": (4.99, 0.3, 0.4, 0.0, 0.002)})
    assert cam.got == [("amr1", 4.99, 0.3, 0.4)]


def test_a_speaker_that_hands_a_robot_over_undeclares_its_ros_publishers() -> None:
    pytest.importorskip("zenoh", reason="the zenoh extra is not installed")
    from zenoh_helpers import open_peer

    from kmead.config.layers import load_config
    from kmead.outputs.zenoh import ZenohOutput

    z = {**load_config(None, ["zenoh.ros2=true"])["zenoh"]}
    session = open_peer()
    try:
        out = ZenohOutput.open(z, session)
        tr = _channel()
        tr.seq, tr.x, tr.y, tr.theta, tr.sigma = 7, 0.1, 0.2, 0.0, 0.002
        out.send(tr, 1.0, True)
        assert out.errors == 0 and out.robots["amr1"].pose is not None and out.tf is not None
        assert out.robots["amr1"].pose.seq == 7  # the robot's own seq in the attachment
        out.quiet("amr1")  # another speaker took the robot: no publisher left listed
        assert "amr1" not in out.robots and out.tf is None
        out.close()
    finally:
        session.close()
