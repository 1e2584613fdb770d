"""Wire format shared by the daemon and its clients (see ``docs/protocol.md``).

Telemetry: ZeroMQ PUB, multipart ``[topic, body]``; topic is ASCII, body is UTF-8 JSON
with ``"v": PROTOCOL_VERSION``. Control: ZeroMQ REQ/REP, one JSON object each way.
No pickle anywhere. This module imports only the standard library.
"""

from __future__ import annotations

import json
import math
from typing import Any

PROTOCOL_VERSION = 1

# Telemetry topics. Subscribers filter by prefix ("robot." gets every robot topic).
TOPIC_FRAME = "frame"
TOPIC_MARKERS = "markers"
TOPIC_ROBOTS = "robots"
TOPIC_ROBOT_PREFIX = "robot."
TOPIC_STATS = "stats"
TOPIC_STATUS = "status"
TOPIC_EVENT = "event"
TOPIC_LOG = "log"

DEFAULT_TELEMETRY = "tcp://127.0.0.1:5555"
DEFAULT_CONTROL = "tcp://127.0.0.1:5556"

MAX_MESSAGE_BYTES = 1 << 20


class ProtocolError(ValueError):
    """A message that does not follow the protocol; the text says which field."""


def _clean(obj: Any) -> Any:
    # JSON has no NaN/inf: send null instead, so any JSON parser can read the body.
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if hasattr(obj, "tolist"):  # numpy arrays and scalars
        return _clean(obj.tolist())
    return obj


def _numpy_default(obj: Any) -> Any:
    if hasattr(obj, "tolist"):  # numpy arrays and scalars (not float subclasses)
        return obj.tolist()
    raise TypeError(type(obj).__name__)


def encode_body(body: dict[str, Any]) -> bytes:
    """JSON bytes of ``body`` with the protocol version added."""
    try:
        # Fast path (the sender thread's main cost): bodies without NaN/inf and with str or
        # int keys encode to the same bytes as the cleaned copy, without the Python walk.
        return json.dumps({"v": PROTOCOL_VERSION, **body}, separators=(",", ":"),
                          allow_nan=False, default=_numpy_default).encode()
    except (TypeError, ValueError):
        pass
    return json.dumps({"v": PROTOCOL_VERSION, **_clean(body)}, separators=(",", ":"),
                      allow_nan=False).encode()


def encode(topic: str, body: dict[str, Any]) -> list[bytes]:
    """Multipart frames ``[topic, body]`` for a PUB socket."""
    return [topic.encode("ascii"), encode_body(body)]


def decode_body(data: bytes) -> dict[str, Any]:
    """Parse and check one JSON body; ``ProtocolError`` names the problem."""
    if len(data) > MAX_MESSAGE_BYTES:
        raise ProtocolError(f"message too large ({len(data)} bytes)")
    try:
        body = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ProtocolError(f"body is not UTF-8 JSON: {e}") from None
    if not isinstance(body, dict):
        raise ProtocolError("body must be a JSON object")
    v = body.get("v")
    if v != PROTOCOL_VERSION:
        raise ProtocolError(f"field 'v': protocol version {v!r} not supported "
                            f"(expected {PROTOCOL_VERSION})")
    return body


def decode(frames: list[bytes]) -> tuple[str, dict[str, Any]]:
    """Inverse of :func:`encode`."""
    if len(frames) != 2:
        raise ProtocolError(f"expected 2 frames [topic, body], got {len(frames)}")
    try:
        topic = frames[0].decode("ascii")
    except UnicodeDecodeError:
        raise ProtocolError("topic is not ASCII") from None
    return topic, decode_body(frames[1])
