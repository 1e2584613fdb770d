"""The fusion node's view of its cameras: their state and counters, and what each sends,
checked (everything received over Zenoh is hostile: a bad field raises ValueError naming it,
and the node counts and reports it once per camera)."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

from kmea.robots.fusion import Measurement
from kmea.wire import protocol as P
from kmea.wire.jsonlimits import safe_loads

__all__ = ["MAX_META_BYTES", "NUMBER", "Camera", "check_meta", "measurement_from"]

MAX_META_BYTES = 4096


@dataclass
class Camera:
    """One camera of the site: its id, state and counters.

    state: ``waiting`` (for its metadata), ``used``, ``refused`` (``reason`` says why),
    ``silent`` (alive but nothing for the lease), ``gone`` (its token went)."""

    label: str
    key: str
    state: str = "waiting"
    reason: str | None = None
    received: int = 0
    measurements: int = 0
    bad: int = 0
    dropped_old: int = 0
    ignored: int = 0  # measurements while not used, or of robots not this node's
    last_wall: float | None = None  # time.time() of its last sample
    last_mono: float | None = None  # time.monotonic() of its last sample
    last_t: float | None = None
    delays: deque = field(default_factory=lambda: deque(maxlen=300))  # wall - t, s
    bad_reported: bool = False
    asked: float = -math.inf  # monotonic time of the last metadata query
    meta: dict | None = None
    sessions: set[str] = field(default_factory=set)  # Zenoh sessions holding this id


    def body(self, now_wall: float) -> P.InputState:
        d = sorted(self.delays)
        return {"label": self.label, "key": self.key, "state": self.state,
                "reason": self.reason if len(self.sessions) < 2 else (
                    f"{len(self.sessions)} kmead claim this camera id (sessions "
                    f"{', '.join(sorted(z[:8] for z in self.sessions))})"),
                "received": self.received,
                "measurements": self.measurements, "bad": self.bad,
                "dropped_old": self.dropped_old,
                "silent_s": None if self.last_wall is None else now_wall - self.last_wall,
                # Unix-time cameras: arrival minus capture = network + processing + offset.
                "delay_s": d[len(d) // 2] if d else None}


def check_meta(payload: bytes) -> dict:
    """A camera's metadata (kmead.outputs.zenoh_camera.meta_body), checked; ValueError names what
    is wrong."""
    body = safe_loads(payload, MAX_META_BYTES, 4)
    if not isinstance(body, dict):
        raise ValueError("metadata: expected a JSON object")
    for k in ("camera", "map_digest", "map_name", "model", "source"):
        if not isinstance(body.get(k), str) or len(body[k]) > 256:
            raise ValueError(f"metadata field {k!r}: expected a string")
    for k in ("width", "height"):
        v = body.get(k)
        if isinstance(v, bool) or not isinstance(v, int) or not 0 < v < 100000:
            raise ValueError(f"metadata field {k!r}: expected a size in pixels")
    return body


NUMBER = (int, float)


def measurement_from(label: str, body: dict, names: set[str]) -> Measurement | None:
    """A measurement from a ``robot.NAME`` body (its ``raw`` measurement when the camera's
    daemon filters with the tracking filter), None for a valid=0 (stale) message;
    ``ValueError`` names the bad field."""
    name = body.get("name")
    if not isinstance(name, str) or name not in names:
        raise ValueError(f"field 'name': unknown robot {name!r}")
    valid = body.get("valid")
    if not isinstance(valid, bool):
        raise ValueError("field 'valid': expected true or false")
    if not valid:
        return None
    raw = body.get("raw")
    # A daemon with the tracking filter sends its filtered pose and the measurement ("raw"):
    # fuse the measurement (filtering filtered poses again would count the noise twice).
    src = {**body, **raw} if isinstance(raw, dict) else body
    vals = {}
    for k in ("t", "x", "y", "theta"):
        v = src.get(k)
        if isinstance(v, bool) or not isinstance(v, NUMBER) or not math.isfinite(v):
            raise ValueError(f"field {k!r}: expected a finite number, got {v!r}")
        vals[k] = float(v)
    sigma = src.get("sigma")
    if sigma is not None and (isinstance(sigma, bool) or not isinstance(sigma, NUMBER)
                              or not math.isfinite(sigma) or sigma < 0):
        raise ValueError(f"field 'sigma': expected a number >= 0 or null, got {sigma!r}")
    return Measurement(label, name, vals["t"], vals["x"], vals["y"], vals["theta"],
                       None if sigma is None else float(sigma))
