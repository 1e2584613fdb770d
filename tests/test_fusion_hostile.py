"""A hostile peer on the site: a real Zenoh session on loopback playing a used camera (and
strangers) against a fusion node, robots as a real UDP listener; and a fuzz of the camera
message schema through the node. The node stays up, the robot never gets a wrong valid
pose, and every refusal is counted."""

from __future__ import annotations

import json
import logging
import math
import random
import re
import threading
import time
from pathlib import Path

import pytest
from deadlines import JOIN

pytest.importorskip("zenoh", reason="the zenoh extra is not installed "
                                    "(pip install 'kmea[zenoh]')")

from test_fusion_node import Udp, _node_cfg, _wait, _wide_map
from zenoh_helpers import FakeCamera, free_port, meta

from kmea.wire import protocol as P
from kmead.fusion.node import FusionNode

AT = (1.0, 0.3)  # where amr1 stands: the floor of the wide scene's map
NEAR = 0.02  # m: a valid pose further than this from AT is a wrong one


def _robots(port: int) -> str:
    return (f'robots=[{{name="amr1", markers=[40, 41], height=0.2, '
            f'destinations=["udp:127.0.0.1:{port}"]}}]')


def _good(t: float) -> dict:
    return {"name": "amr1", "valid": True, "t": t, "x": AT[0], "y": AT[1], "theta": 0.0,
            "sigma": 0.002}


class Beat:
    """A well-behaved camera: amr1 at AT, 30 measurements/s, stamped with Unix time."""

    def __init__(self, cam: FakeCamera) -> None:
        self.cam, self.stop = cam, threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop.wait(1 / 30):
            self.cam.put("robots/amr1", _good(time.time()))

    def close(self) -> None:
        self.stop.set()
        self.thread.join(JOIN)


# (what the row sent, the body, how many times, the field refused)
ROWS = [
    ("x = 1e300", {"x": 1e300}, 6, "x"),
    ("x = 1e100", {"x": 1e100}, 6, "x"),
    ("x = 1e308", {"x": 1e308}, 1, "x"),
    ("a pose 100 m away", {"x": 100.0, "y": 100.0}, 10, "x"),
    ("stamped 3,600 s ahead", {"t": 3600.0}, 1, "t"),
    ("stamped 20 s ahead", {"t": 20.0}, 1, "t"),
    ("sigma beyond fusion.max_sigma_m", {"sigma": 0.678}, 3, "sigma"),
]


def test_a_hostile_camera_cannot_crash_blind_or_misplace(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="kmead")
    port = free_port()
    wide, digest = _wide_map(tmp_path)
    udp = Udp()
    node = FusionNode(_node_cfg(port, wide, _robots(udp.port), "relay.extra_fields=true"))
    tn = threading.Thread(target=node.run, daemon=True)
    tn.start()
    good = FakeCamera(port, "cam0", meta("cam0", digest))
    evil = FakeCamera(port, "evil", meta("evil", digest))
    late = None
    beat = Beat(good)
    try:
        _wait(lambda: {c.label: c.state for c in node.cameras.values()}
              == {"cam0": "used", "evil": "used"}, "both cameras used")
        _wait(lambda: node.election.role == "active", "the node active")
        udp.wait(lambda s: sum(m["valid"] for _, m in s) >= 10)
        # A stranger's token of an active node with the lowest id, and no voice: the node
        # keeps speaking (a token is no voice).
        fake_active = evil.session.liveliness().declare_token("kmea/fusion/0/active")
        _wait(lambda: "0" in node.speaker.election.others, "the stranger's token seen")
        for _, body, times, _ in ROWS:
            for _ in range(times):
                now = time.time()
                evil.put("robots/amr1", {**_good(now), **body,
                                         **({"t": now + body["t"]} if "t" in body else {})})
        # A 401-digit integer is valid JSON; no float holds it.
        evil.put("robots/amr1", json.dumps(_good(time.time())).replace(
            f'"x": {AT[0]}', '"x": 1' + "0" * 400).encode())
        # 64 data-only messages under invented camera ids: strangers, not cameras.
        for k in range(64):
            evil.session.put(f"kmea/cam/ghost{k}/robots/amr1",
                             json.dumps(_good(time.time())).encode())
        refused = sum(n for _, _, n, _ in ROWS) + 1
        _wait(lambda: node.cameras["evil"].bad == refused, f"{refused} refusals counted")
        _wait(lambda: node.foreign >= 64, "64 strangers counted")
        # A real camera started afterwards is admitted and used.
        late = FakeCamera(port, "late", meta("late", digest))
        _wait(lambda: "late" in node.cameras and node.cameras["late"].state == "used",
              "the camera started after the strangers used")
        seen = udp.wait(lambda s: sum(m["valid"] for _, m in s) >= 30)
        status = node.status()
        fake_active.undeclare()
    finally:
        beat.close()
        node.stop()
        tn.join(timeout=JOIN)
        alive = tn.is_alive()
        node.close()
        for c in (good, evil, late):
            if c is not None:
                c.close()
        udp.sock.close()
    assert not alive
    P.check_body(P.TOPIC_STATUS, status, exact=True)  # the declared status, new fields too
    evil_state = next(i for i in status["inputs"] if i["label"] == "evil")
    assert evil_state["bad"] == refused and evil_state["state"] == "used"
    assert evil_state["bad_fields"] == {"x": 24, "t": 2, "sigma": 3}
    assert status["fusion"]["strangers"] >= 64 and status["fusion"]["reacquired"] == 0
    assert status["fusion"]["role"] == "active"  # the stranger's active token silenced nobody
    assert status["fusion"]["dropped_old"] == 0  # the future-stamped ones blinded nobody
    valid = [m for _, m in seen if m["valid"]]
    assert len(valid) >= 30 and all(math.hypot(m["x"] - AT[0], m["y"] - AT[1]) < NEAR
                                    for m in valid), valid
    assert all(m["t"] < time.time() + 1.0 for _, m in seen)
    # One event per camera and field.
    events = [r.getMessage() for r in caplog.records if "evil: message refused" in r.getMessage()]
    assert sorted(re.search(r"field '(\w+)'", e)[1] for e in events) == ["sigma", "t", "x"]
    assert sum("from no camera known" in r.getMessage() for r in caplog.records) == 1


HOSTILE = {
    "t": [None, "1", True, [], {}, 10 ** 401, 1e308, "inf", 3600.0],
    "x": [None, "1", False, 1e300, -1e300, 10 ** 401, 100.0, -50.0, [1], 1e100],
    "y": [None, "0", 1e300, 10 ** 401, 100.0, -5.0],
    "theta": [None, "0", 1e300, 10 ** 401, 100.0, -100.0],
    "sigma": [-1.0, 1e300, 0.5, "0.1", True, 10 ** 401, [0.1]],
    "valid": [1, "true", None, 0],
}


def _fuzzed(rng: random.Random, t: float) -> bytes:
    """One message that the schema must refuse: a field given a hostile value, or a
    payload that is no measurement."""
    kind = rng.randrange(10)
    body = _good(t)
    if kind < 7:
        for f in rng.sample(sorted(HOSTILE), rng.randint(1, 2)):
            v = rng.choice(HOSTILE[f])
            body[f] = t + v if f == "t" and isinstance(v, float) and v < 1e6 else v
        return json.dumps(body).encode()
    if kind == 7:
        return bytes(rng.randrange(256) for _ in range(rng.randint(0, 40)))
    if kind == 8:
        text = json.dumps(body)
        return text[: rng.randint(0, len(text) - 1)].encode()
    return rng.choice([b"[" * 40 + b"]" * 40, b'{"x": NaN}', b"x" * 2000, b"1e400",
                       json.dumps({**body, "name": "amr2"}).encode(),
                       json.dumps({**body, "pad": "p" * 1100}).encode()])


def test_fuzzed_camera_messages_are_refused_and_counted(tmp_path: Path) -> None:
    """2,400 fuzzed messages between the good ones, through the node's own entry
    (:meth:`FusionNode.handle`, as its loop calls it): never raised, each counted once as
    bad, the robot's valid poses stay at AT."""
    port = free_port()
    wide, digest = _wide_map(tmp_path)
    udp = Udp()
    node = FusionNode(_node_cfg(port, wide, _robots(udp.port), 'network.control=""'))
    rng = random.Random(38)
    try:
        for cam in ("good", "fuzz"):
            node.handle("camera", f"kmea/cam/{cam}", True, 0.0)
            node.handle("meta", cam, json.dumps(meta(cam, digest)).encode(), 0.0)
        node.election.role = "active"
        assert node.relay is not None
        node.relay.muted = False
        n = 2400
        sent = 0
        for k in range(n):
            t = time.time()
            if k % 4 == 0:
                node.handle("data", "kmea/cam/good/robots/amr1", json.dumps(_good(t)).encode(),
                            time.perf_counter())
            payload = _fuzzed(rng, t)
            before = node.cameras["fuzz"].bad
            fused = node.handle("data", "kmea/cam/fuzz/robots/amr1", payload,
                                time.perf_counter())
            assert not fused and node.cameras["fuzz"].bad == before + 1, payload
            sent += 1
        seen = udp.wait(lambda s: False, 0.5)
        fuzz = node.cameras["fuzz"]
    finally:
        node.close()
        udp.sock.close()
    assert sent == n and fuzz.measurements == 0 and fuzz.bad == n
    valid = [m for _, m in seen if m["valid"]]
    assert len(valid) >= 100 and all(math.hypot(m["x"] - AT[0], m["y"] - AT[1]) < NEAR
                                     for m in valid)
    assert node.fusion.tracker.counts["failed"] == 0 and node.fusion.accepted == n // 4


def test_camera_clocks_estimated_reported_refused_and_back(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A camera 80 ms ahead: an event, still used; one an hour ahead: every measurement
    refused, the camera refused for its clock, the other camera's robot unaffected; its clock
    set right: used again. One 10 s behind: refused too."""
    caplog.set_level(logging.INFO, logger="kmead")
    wide, digest = _wide_map(tmp_path)
    udp = Udp()
    node = FusionNode(_node_cfg(free_port(), wide, _robots(udp.port), 'network.control=""'))
    try:
        for cam in ("good", "fast", "far", "slow"):
            node.handle("camera", f"kmea/cam/{cam}", True, 0.0)
            node.handle("meta", cam, json.dumps(meta(cam, digest)).encode(), 0.0)
        node.election.role = "active"
        assert node.relay is not None
        node.relay.muted = False

        def send(cam: str, offset: float, n: int) -> None:
            for _ in range(n):
                t = time.time()
                node.handle("data", "kmea/cam/good/robots/amr1",
                            json.dumps(_good(t - 0.01)).encode(), time.perf_counter())
                node.handle("data", f"kmea/cam/{cam}/robots/amr1",
                            json.dumps(_good(t + offset)).encode(), time.perf_counter())

        send("fast", 0.08, 20)
        fast = node.cameras["fast"]
        assert fast.state == "used" and fast.bad == 0 and fast.clock_offset_s is not None
        assert 0.07 < fast.clock_offset_s < 0.09
        send("far", 3600.0, 20)
        far = node.cameras["far"]
        assert far.state == "refused" and "s ahead of the node's" in (far.reason or "")
        assert far.clock_offset_s is not None and 3599.0 < far.clock_offset_s < 3600.1
        assert far.bad == 20 and far.bad_fields == {"t": 20} and far.measurements == 0
        send("far", 0.0, 60)  # its clock set right: the window forgets the hour
        assert far.state == "used" and far.reason is None and far.measurements > 0
        send("slow", -10.0, 20)
        assert node.cameras["slow"].state == "refused" and node.cameras["slow"].measurements \
            < 5 and "behind" in (node.cameras["slow"].reason or "")
        status = node.status()
        seen = udp.wait(lambda s: False, 0.5)
    finally:
        node.close()
        udp.sock.close()
    offsets = {i["label"]: i["clock_offset_s"] for i in status["inputs"]}
    assert abs(offsets["good"]) < 0.05 and offsets["slow"] < -9.0
    good = node.cameras["good"]
    assert good.dropped_old == 0 and good.bad == 0 and good.measurements == 120
    texts = [r.getMessage() for r in caplog.records]
    assert any("camera fast: its clock is 0.0" in t and "ahead" in t for t in texts)
    assert any("camera far: refused: its clock is 3" in t for t in texts)
    assert any("camera far: its clock is back within" in t for t in texts)
    valid = [m for _, m in seen if m["valid"]]
    assert valid and all(math.hypot(m["x"] - AT[0], m["y"] - AT[1]) < NEAR for m in valid)
    assert all(m["t"] < time.time() + 1.0 for _, m in seen)


def test_the_camera_table_evicts_silent_strangers_never_a_used_camera() -> None:
    from kmead.fusion.cameras import Camera, make_room

    now = time.monotonic()
    table = {f"s{k}": Camera(f"s{k}", f"kmea/cam/s{k}", since=now) for k in range(63)}
    table["cam0"] = Camera("cam0", "kmea/cam/cam0", state="used", since=now - 100)
    # Full, every stranger known for less than the lease: no room, nothing evicted.
    assert not make_room(table, 64, now - 2.0) and len(table) == 64
    # Later, the strangers that never answered for their metadata make room, one at a time.
    assert make_room(table, 64, now + 1.0) and len(table) == 63 and "cam0" in table
    table["new"] = Camera("new", "kmea/cam/new", state="used")
    table["s1"].state = "gone"
    assert make_room(table, 64, now - 2.0) and "s1" not in table  # a gone one first
    table["new2"] = Camera("new2", "kmea/cam/new2")
    for c in table.values():
        c.state = "used"
    assert len(table) == 64 and not make_room(table, 64, now + 1.0) and len(table) == 64
