"""The fusion node's view of its cameras: their state, counters and clock (what each sends
is checked by :mod:`kmead.fusion.inputs`)."""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, field

from kmea.wire import protocol as P
from kmead.fusion.inputs import CLOCK_WINDOW, MAX_META_BYTES, check_meta, measurement_from

__all__ = ["MAX_META_BYTES", "Camera", "check_meta", "make_room", "measurement_from"]


@dataclass
class Camera:
    """One camera of the site: its id, state and counters.

    state: ``waiting`` (for its metadata), ``used``, ``refused`` (``reason`` says why: its
    map, its metadata, or its clock),
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
    bad_fields: dict[str, int] = field(default_factory=dict)  # refused messages per field
    clock: deque = field(default_factory=lambda: deque(maxlen=CLOCK_WINDOW))  # wall - t, s
    clock_offset_s: float | None = None  # its clock minus the node's (inputs.clock_offset)
    clock_warned: bool = False
    clock_refused: bool = False  # refused for its clock (used again once it is back)
    asked: float = -math.inf  # monotonic time of the last metadata query
    since: float = field(default_factory=time.monotonic)  # when its token made it known
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
                "bad_fields": dict(self.bad_fields),
                "dropped_old": self.dropped_old,
                "silent_s": None if self.last_wall is None else now_wall - self.last_wall,
                # Unix-time cameras: arrival minus capture = network + processing + offset.
                "delay_s": d[len(d) // 2] if d else None,
                "clock_offset_s": self.clock_offset_s}


def make_room(cameras: dict[str, Camera], most: int, silent_since: float) -> bool:
    """Room for one more camera in ``cameras`` (at most ``most``): when full, the first of
    a gone camera, a stranger that never answered for its metadata (``waiting``, known
    since before ``silent_since``, monotonic s) or a refused one goes. A used or silent camera
    (it answered with the node's map) never goes. False when there is no room."""
    if len(cameras) < most:
        return True
    for state in ("gone", "waiting", "refused"):
        for cam_id, cam in cameras.items():
            if cam.state == state and (state != "waiting" or cam.since < silent_since):
                del cameras[cam_id]
                return True
    return False
