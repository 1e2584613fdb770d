"""The UI's recorded stream and the daemon's messages agree, both with kmea.wire.protocol's types.

``tests/data/telemetry_sim.jsonl`` (the UI tests' and snapshots' input) is written by
``scripts/record_telemetry.py`` from a real daemon run. These tests fail when it drifts
from what the daemon sends now: every recorded message must decode with the typed decoder
(exactly the declared fields), and a short real daemon run (same scene, in process, real
sockets) must send, per topic, the same field paths as the recording. Regenerate the
stream with the script when a field changes (and bump ``PROTOCOL_VERSION``).
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path
from typing import Any

import zmq
from deadlines import DEADLINE

from kmea.wire import protocol as P
from kmead.config.layers import load_config
from kmead.run.daemon import Daemon

RECORDING = Path(__file__).parent / "data" / "telemetry_sim.jsonl"
SCENE = "sim:misplaced?robots=true"
UI_TOPICS = {P.TOPIC_FRAME, P.TOPIC_MARKERS, P.TOPIC_ROBOTS, P.TOPIC_STATS, P.TOPIC_STATUS}


def _recording() -> tuple[dict[str, Any], list[tuple[str, dict[str, Any]]]]:
    lines = [json.loads(line) for line in RECORDING.read_text().splitlines()]
    return lines[0]["header"], [(r["topic"], r["body"]) for r in lines[1:]]


# Dicts with free keys (per-stage timings, the configuration's tables): one path each.
OPAQUE = ("timings_ms", "config")


def paths(value: Any, prefix: str = "") -> set[str]:
    """Every field path of a JSON value (``markers[].id``)."""
    out: set[str] = set()
    if isinstance(value, dict):
        for k, v in value.items():
            p = f"{prefix}.{k}" if prefix else k
            out.add(p)
            if k not in OPAQUE:
                out |= paths(v, p)
    elif isinstance(value, list):
        for v in value:
            out |= paths(v, f"{prefix}[]")
    return out


def test_every_recorded_message_has_its_declared_type() -> None:
    header, messages = _recording()
    for cmd, td in P.REPLY_TYPES.items():
        assert header[cmd]["v"] == P.PROTOCOL_VERSION
        P.check_fields(header[cmd], td, cmd, exact=True)
    for topic, body in messages:
        assert body["v"] == P.PROTOCOL_VERSION, topic
        P.check_body(topic, body, exact=True)
    topics = {t for t, _ in messages}
    assert topics >= UI_TOPICS, UI_TOPICS - topics
    # The recording shows what the UI tests rely on: the daemon's moved marker 7 (moved by
    # 2 cm in this scene) with its evidence, and a suspect marker in the last frame.
    last = [b for t, b in messages if t == P.TOPIC_MARKERS][-1]
    by_id = {m["id"]: m for m in last["markers"]}
    assert by_id[7]["moved"] and by_id[7]["moved_offset"] > by_id[7]["moved_threshold"]
    assert [m["id"] for m in last["markers"] if m["moved"]] == [7]
    assert any(m["suspect"] for m in last["markers"])
    assert header["get_state"]["status"]["algorithms"]


def _collect(sock: zmq.Socket, into: dict[str, list[dict]], stop: threading.Event) -> None:
    while not stop.is_set():
        if sock.poll(50):
            frames = sock.recv_multipart()
            topic, body = P.decode(frames, typed=False)  # typed below, with a clear message
            into.setdefault(topic, []).append(body)


def _request(ctx: zmq.Context, endpoint: str, cmd: str) -> dict:
    req = ctx.socket(zmq.REQ)
    req.setsockopt(zmq.LINGER, 0)
    req.connect(endpoint)
    try:
        req.send(P.encode_body({"cmd": cmd}))
        assert req.poll(10000), f"no reply to {cmd}"
        return P.decode_body(req.recv())
    finally:
        req.close(0)


def test_a_real_daemon_sends_what_the_recording_holds(tmp_path: Path) -> None:
    header, recorded = _recording()
    cfg = load_config(None, [
        # The recording's scene at its size (at 640x480 every LOO error is ~5 mm and the
        # monitor's threshold rightly rises above marker 7's 2 cm).
        f'source.spec="{SCENE}"', "source.fps=0",
        'network.telemetry="tcp://127.0.0.1:*"', 'network.control="tcp://127.0.0.1:*"',
        "network.status_period_s=0.2", f'log.csv="{tmp_path / "run.csv"}"'])
    daemon = Daemon(cfg, max_frames=8)
    ctx = zmq.Context()
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.SUBSCRIBE, b"")
    sub.connect(daemon.telemetry.bound)
    got: dict[str, list[dict]] = {}
    stop = threading.Event()
    reader = threading.Thread(target=_collect, args=(sub, got, stop))
    try:
        reader.start()
        # Until the subscription is through (PUB drops messages for a joining SUB).
        for _ in range(200):
            daemon.telemetry.event("info", "subscription check")
            time.sleep(0.02)
            if got.get("event"):
                break
        assert got.get("event"), "the subscriber never joined"
        daemon.run()
        replies = {cmd: _request(ctx, daemon.control.bound, cmd) for cmd in P.REPLY_TYPES}
        # The last queued messages (all sent before this event) and one more status.
        daemon.telemetry.event("info", "end of the test's stream")
        end = time.monotonic() + DEADLINE

        def texts() -> list[str]:
            return [e["text"] for e in list(got.get("event", []))]
        while "end of the test's stream" not in texts() and time.monotonic() < end:
            time.sleep(0.02)
        n_status = len(got.get("status", []))
        while len(got.get("status", [])) <= n_status and time.monotonic() < end:
            time.sleep(0.02)
        assert len(got.get("status", [])) > n_status, "no status after the run"
    finally:
        stop.set()
        reader.join()
        daemon.close()
        sub.close(0)
        ctx.term()

    # Every live message has its declared type, exactly.
    for topic, bodies in got.items():
        for body in bodies:
            P.check_body(topic, body, exact=True)
    for cmd, reply in replies.items():
        P.check_fields(reply, P.REPLY_TYPES[cmd], cmd, exact=True)
    assert any(t.startswith(P.TOPIC_ROBOT_PREFIX) for t in got)

    # Per topic, the recorded field paths are the daemon's.
    by_topic: dict[str, set[str]] = {}
    for topic, body in recorded:
        by_topic.setdefault(topic, set()).update(paths(body))
    for topic, recorded_paths in by_topic.items():
        assert topic in got, f"the daemon sent no {topic!r} message"
        live = set().union(*(paths(b) for b in got[topic]))
        assert live == recorded_paths, (topic, sorted(live ^ recorded_paths))
    for cmd, reply in replies.items():
        assert paths(reply) == paths(header[cmd]), (cmd, sorted(paths(reply)
                                                                ^ paths(header[cmd])))

    # The moved decision comes from the daemon: marker 7 (2 cm off) within 8 frames.
    last = got[P.TOPIC_MARKERS][-1]["markers"]
    assert [m["id"] for m in last if m["moved"]] == [7]
    assert any("marker 7 looks displaced" in e["text"] for e in got["event"])
