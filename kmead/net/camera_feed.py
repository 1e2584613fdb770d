"""Camera thumbnails for the UI's Camera tab, sent only while someone watches.

A client asks with the control command ``camera_watch`` (size of its pane in pixels and a
lease); the daemon then publishes a ``camera`` telemetry message at most ``MAX_RATE_HZ``
times a second until the lease ends. Nobody watching costs nothing per frame. Leases are
clamped (``MAX_LEASE_S``), sizes too (``MAX_WIDTH`` x ``MAX_HEIGHT``), and renewals faster
than ``MIN_RENEW_S`` are refused: a hostile client cannot make the daemon send big images
fast.

The body (see docs/protocol.md, topic ``camera``): the greyscale thumbnail (``gray8``,
base64), the frame size, the marker outlines in frame pixels by kind (``detected``,
``suspect``, ``rejected``, ``expected`` = a map marker the estimate says is in view but
that was not detected) and the focus figure of the marker regions.
"""

from __future__ import annotations

import base64
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from kmea.maps.files import MarkerMap
from kmea.vision.camera import CameraModel
from kmea.vision.overlay import (
    OverlayMarker,
    expected_marker_corners,
    focus_measure,
    thumbnail,
)

MAX_RATE_HZ = 2.0
MAX_LEASE_S = 10.0
MIN_RENEW_S = 0.2
MAX_WIDTH, MAX_HEIGHT = 320, 240
DEFAULT_WIDTH, DEFAULT_HEIGHT = 160, 120


class WatchError(ValueError):
    """A camera_watch request that is refused; the text names the field."""


@dataclass
class Lease:
    until: float  # time.monotonic()
    width: int
    height: int


def outlines(observations: list, rejected: set[int], expected: dict[int, np.ndarray]
             ) -> list[OverlayMarker]:
    """Outlines by kind from the frame's observations (with corners) and expected markers."""
    out = []
    for o in observations:
        if o.corners is None:
            continue
        kind = "suspect" if o.suspect else "rejected" if o.id in rejected else "detected"
        out.append(OverlayMarker(int(o.id), np.asarray(o.corners, dtype=float), kind))
    out += [OverlayMarker(mid, c, "expected") for mid, c in sorted(expected.items())]
    return out


def frame_outlines(observations: list, rejected: set[int], cam2world: np.ndarray | None,
                   camera: CameraModel, world_map: MarkerMap) -> list[OverlayMarker]:
    """Every outline of one frame: detections, and map markers expected but not detected."""
    expected: dict[int, np.ndarray] = {}
    if cam2world is not None and np.all(np.isfinite(cam2world)):
        seen = {int(o.id) for o in observations}
        expected = expected_marker_corners(cam2world, camera, world_map, exclude=seen,
                                           margin=2.0)
    return outlines(observations, rejected, expected)


def camera_body(image: np.ndarray, marks: list[OverlayMarker], width: int, height: int,
                frame: int, t: float) -> dict[str, Any]:
    """The ``camera`` telemetry body for one frame (``image``: (H, W) uint8 or BGR)."""
    gray = image if image.ndim == 2 else image.mean(axis=2).astype(np.uint8)
    thumb, _ = thumbnail(gray, width, height)
    focus = focus_measure(gray, [m.corners for m in marks if m.kind != "expected"])
    h, w = gray.shape
    return {"t": t, "frame": frame, "width": int(thumb.shape[1]),
            "height": int(thumb.shape[0]), "full_width": int(w), "full_height": int(h),
            "encoding": "gray8", "data": base64.b64encode(thumb.tobytes()).decode("ascii"),
            "focus": focus,
            "markers": [{"id": m.id, "kind": m.kind,
                         "corners": [[round(float(x), 2), round(float(y), 2)]
                                     for x, y in m.corners]} for m in marks]}


class CameraFeed:
    """Leases and rate limit of the thumbnails (thread-safe: control thread and frame loop)."""

    def __init__(self, max_rate_hz: float = MAX_RATE_HZ) -> None:
        self.max_rate_hz = max_rate_hz
        self._lease: Lease | None = None
        self._last_watch = -1e9
        self._last_sent = -1e9
        self._lock = threading.Lock()
        self.sent = 0

    def watch(self, width: Any = None, height: Any = None, lease_s: Any = None,
              now: float | None = None) -> dict[str, Any]:
        """Start or renew the lease; the reply fields. ``WatchError`` for a bad request."""
        now = time.monotonic() if now is None else now

        def number(v: Any, name: str, default: float, lo: float, hi: float) -> float:
            if v is None:
                return default
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not lo <= v:
                raise WatchError(f"field {name!r}: expected a number >= {lo:g}")
            return float(min(v, hi))  # an integer of any size: compared before converted

        w = int(number(width, "width", DEFAULT_WIDTH, 8, MAX_WIDTH))
        h = int(number(height, "height", DEFAULT_HEIGHT, 8, MAX_HEIGHT))
        lease = number(lease_s, "lease_s", 5.0, 0.0, MAX_LEASE_S)
        with self._lock:
            if now - self._last_watch < MIN_RENEW_S:
                raise WatchError(f"camera_watch: at most one request every {MIN_RENEW_S:g} s")
            self._last_watch = now
            self._lease = Lease(now + lease, w, h) if lease > 0 else None
        return {"width": w, "height": h, "lease_s": lease, "rate_hz": self.max_rate_hz}

    def due(self, now: float | None = None) -> Lease | None:
        """The lease when a thumbnail should go out now (and counts it as sent), else None."""
        now = time.monotonic() if now is None else now
        with self._lock:
            lease = self._lease
            if lease is None or now >= lease.until:
                self._lease = None
                return None
            if now - self._last_sent < 1.0 / self.max_rate_hz:
                return None
            self._last_sent = now
            self.sent += 1
            return lease

    @property
    def watched(self) -> bool:
        with self._lock:
            return self._lease is not None and time.monotonic() < self._lease.until
