"""kmea.wire.protocol: encoding (fast path = cleaned path), versions, and the typed decoder."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from kmea.wire import protocol as P
from kmea.wire.jsonsafe import to_jsonable


def slow(body: dict) -> bytes:
    return json.dumps({"v": P.PROTOCOL_VERSION, **to_jsonable(body)}, separators=(",", ":"),
                      allow_nan=False).encode()


def test_fast_path_bytes_equal_the_cleaned_encoding() -> None:
    rng = np.random.default_rng(3)
    p = rng.normal(size=3)
    bodies = [
        {"t": 1.5, "frame": 7, "markers": [{"id": 4, "x": p[0], "y": float(p[1]),
                                            "in_map": np.bool_(True), "n": np.int64(3),
                                            "pos": p, "none": None}]},
        {"ids": (1, 2), "by_id": {5: 2, 7: np.int32(1)}, "R": np.eye(3), "s": "é"},
        {"x": math.nan, "arr": np.array([1.0, np.inf]), "ok": np.bool_(False)},  # cleaned
        {"nested": {"deeper": [np.float32(0.25), -0.0, 1e-300]}},
    ]
    for body in bodies:
        assert P.encode_body(body) == slow(body)
    assert P.decode_body(P.encode_body(bodies[2]))["x"] is None


def test_other_versions_and_garbage_are_refused_by_field() -> None:
    with pytest.raises(P.ProtocolError, match="field 'v': protocol version 1 not supported"):
        P.decode_body(b'{"v": 1, "t": 0}')
    with pytest.raises(P.ProtocolError, match="not UTF-8 JSON"):
        P.decode_body(b"\xff")
    with pytest.raises(P.ProtocolError, match="JSON object"):
        P.decode_body(b"[1]")
    with pytest.raises(P.ProtocolError, match="too large"):
        P.decode_body(b" " * (P.MAX_MESSAGE_BYTES + 1))
    with pytest.raises(P.ProtocolError, match="expected 2 frames"):
        P.decode([b"event"])


EVENT = {"t": 1.0, "level": "warning", "text": "marker 7 looks displaced"}


def test_typed_decoder_names_the_field() -> None:
    assert P.decode(P.encode(P.TOPIC_EVENT, EVENT)) == ("event", {"v": 2, **EVENT})
    with pytest.raises(P.ProtocolError, match=r"event: field 'text': missing"):
        P.decode(P.encode(P.TOPIC_EVENT, {"t": 1.0, "level": "info"}))
    with pytest.raises(P.ProtocolError, match=r"event: field 't': expected float, got str"):
        P.decode(P.encode(P.TOPIC_EVENT, {**EVENT, "t": "noon"}))
    with pytest.raises(P.ProtocolError, match="topic 'gossip': unknown"):
        P.decode(P.encode("gossip", EVENT))
    # Without typing: any object of the right version.
    assert P.decode(P.encode("gossip", EVENT), typed=False)[0] == "gossip"
    # Added fields: accepted by clients, refused by the exact check the tests use.
    P.check_body("event", {**EVENT, "extra": 1})
    with pytest.raises(P.ProtocolError, match="field 'extra': not in EventBody"):
        P.check_body("event", {**EVENT, "extra": 1}, exact=True)


def test_typed_decoder_walks_nested_bodies() -> None:
    row = {"name": "amr1", "markers": [40, 41], "x": 0.5, "y": None, "theta": 0, "sigma": None,
           "valid": True, "age_s": 0.1, "stale": False, "destinations": ["udp:h:1"],
           "sent": 3, "seq": 3, "send_errors": 0}
    body = {"t": 2.0, "frame": 9, "robots": [row]}
    P.check_body("robots", body, exact=True)
    # bool is not an int, an int is a float, null only where declared.
    for field, value, want in (("sent", True, "int"), ("valid", 1, "bool"),
                               ("markers", [40, "41"], "int"), ("name", None, "str")):
        bad = {**body, "robots": [{**row, field: value}]}
        with pytest.raises(P.ProtocolError, match=rf"robots\[0\]\.{field}.*expected {want}"):
            P.check_body("robots", bad)


def test_robot_topics() -> None:
    assert P.robot_topic("amr1") == "robot.amr1"
    assert P.body_type(P.robot_topic("amr1")) is P.RobotMessage
    msg = {"name": "amr1", "seq": 1, "t": 0.0, "x": 0.1, "y": 0.2, "theta": 0.0,
           "valid": True, "sigma": None}
    P.check_body("robot.amr1", msg, exact=True)


def test_every_topic_has_one_declared_type() -> None:
    topics = [v for k, v in vars(P).items()
              if k.startswith("TOPIC_") and isinstance(v, str) and k != "TOPIC_ROBOT_PREFIX"]
    assert sorted(topics) == sorted(P.TOPIC_TYPES)
    assert len(set(P.TOPIC_TYPES.values())) == len(P.TOPIC_TYPES)
