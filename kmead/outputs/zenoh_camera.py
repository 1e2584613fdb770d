"""A camera's measurements on Zenoh, for the fusion nodes (docs/fusion.md).

With ``[zenoh] enabled = true`` every ``kmead`` is a camera of its site. Keys (``<site>`` =
``zenoh.site``, ``<id>`` = :func:`camera_id`):

- ``<site>/cam/<id>``: a liveliness token, alive as long as the session (a killed kmead's
  goes at once, a frozen or cut-off one's after the lease);
- ``<site>/cam/<id>/meta``: a queryable answering :func:`meta_body` (map digest, camera
  model, resolution), JSON;
- ``<site>/cam/<id>/robots/<robot>``: one measurement per robot per frame, JSON
  ``{"name", "valid": true, "t", "x", "y", "theta", "sigma"}``: the capture instant and the
  robot's pose before the tracking filter (a fusion node filters);
- ``<site>/cam/<id>/frame``: ``{"t", "frames"}`` every :data:`HEARTBEAT_S` from the frame
  loop: a camera that sees no robot still shows it works (a fusion node drops a camera that
  sends nothing for the lease).

It also watches ``<site>/fusion/**`` (the fusion nodes' liveliness tokens): while a fusion
node is alive it speaks to the robots, so this kmead's relay is muted (no datagram, no
Zenoh robot pose) and one robot hears one voice.

Threads: :meth:`ZenohCamera.measurement`, :meth:`ZenohCamera.frame` and :meth:`close` are
the frame loop's (under the daemon's lock: the publisher table has one owner); the
queryable and the liveliness callback run on Zenoh's threads and touch only an immutable
payload and the fusion-node set under its own lock.
"""

from __future__ import annotations

import contextlib
import json
import logging
import re
import socket
import threading
import time
from collections.abc import Callable
from typing import Any

from kmea.maps.files import map_digest
from kmea.maps.model import MarkerMap
from kmead.net.site_tls import certificate_name
from kmead.outputs.zenoh_session import import_zenoh

log = logging.getLogger("kmead.zenoh")

HEARTBEAT_S = 0.2
STARTUP_S = 1.0  # s: the start waits at most this long for the fusion nodes' tokens
_ID_RE = re.compile(r"[^A-Za-z0-9_-]")


def camera_id(z: dict, source_spec: str) -> str:
    """With TLS, its certificate's common name (``kmea keys site``: ids cannot collide
    by accident); else ``zenoh.camera``, else ``camN`` for the simulator's
    ``sim:wide?camera=N``, else the host name (one camera per machine in the field)."""
    if z.get("tls_cert"):
        return certificate_name(z["tls_cert"])
    if z.get("camera"):
        return z["camera"]
    base, _, query = source_spec.partition("?")
    if base in ("sim:wide", "sim:wide-cam1"):
        opts = {k: v for k, _, v in (p.partition("=") for p in query.split("&") if p)}
        return f"cam{opts.get('camera', '1' if base.endswith('cam1') else '0')}"
    return _ID_RE.sub("-", socket.gethostname())[:32] or "cam"


def meta_body(cam_id: str, world_map: MarkerMap, camera: Any, source: str,
              camera_file: str) -> dict:
    """What the ``meta`` queryable answers: with the map's digest and name, its markers'
    extent (xmin, xmax, ymin, ymax: the floor a node without a map of its own checks
    positions against)."""
    return {"camera": cam_id, "map_digest": map_digest(world_map), "map_name": world_map.name,
            "model": camera_file or "built-in", "width": int(camera.width),
            "height": int(camera.height), "fx": float(camera.fx), "fy": float(camera.fy),
            "source": source, "extent": list(world_map.extent())}


class ZenohCamera:
    """This kmead as a camera of its site, on an open session (module docstring)."""

    def __init__(self, session: Any, site: str, cam_id: str, meta: dict,
                 on_fusion: Callable[[int], None] | None = None) -> None:
        zenoh = import_zenoh()
        self.session = session
        self.site = site
        self.id = cam_id
        self.prefix = f"{site}/cam/{cam_id}"
        self.on_fusion = on_fusion
        self._meta = json.dumps(meta).encode()
        self._pubs: dict[str, Any] = {}
        self._fusion: set[str] = set()  # the fusion nodes' token keys
        self._lock = threading.Lock()  # _fusion (Zenoh's callback thread vs readers)
        self.sent = 0
        self.errors = 0
        self._warned = False
        self._frames = 0
        self._last_beat = 0.0
        self._declare = lambda key: session.declare_publisher(
            key, reliability=zenoh.Reliability.RELIABLE,
            congestion_control=zenoh.CongestionControl.DROP)
        self.queryable = session.declare_queryable(f"{self.prefix}/meta", self._answer)
        self.beat = self._declare(f"{self.prefix}/frame")
        self.watch = session.liveliness().declare_subscriber(
            f"{site}/fusion/**", self._fusion_change, history=True)
        # Before the first frame: a fusion node already there mutes this kmead's relay
        # before it sends anything (the subscriber's history may come a moment later).
        try:
            for reply in session.liveliness().get(f"{site}/fusion/**", timeout=STARTUP_S):
                if reply.ok is not None:
                    self._fusion_change(reply.ok)
        except Exception as e:  # a session closing
            log.debug("zenoh: fusion nodes query failed: %s", e)
        self.token = session.liveliness().declare_token(self.prefix)
        log.info("zenoh: camera %s on site %r (%s/...)", cam_id, site, self.prefix)

    # ------------------------------------------------------------------ Zenoh's threads
    def _answer(self, query: Any) -> None:
        try:
            query.reply(f"{self.prefix}/meta", self._meta)
        except Exception as e:  # the querier went away
            log.debug("zenoh: meta reply failed: %s", e)

    def _fusion_change(self, sample: Any) -> None:
        key = str(sample.key_expr)  # <site>/fusion/<node>/<role>: one per node and role
        put = str(sample.kind).rsplit(".", 1)[-1] == "PUT"
        with self._lock:
            before = len(self._fusion)
            (self._fusion.add if put else self._fusion.discard)(key)
            n = len(self._fusion)
        if (before == 0) != (n == 0):
            log.warning("zenoh: %s", "a fusion node is alive on the site: it speaks to the "
                        "robots, this kmead's relay is muted" if n else
                        "no fusion node left on the site: this kmead speaks to the robots")
            if self.on_fusion is not None:
                self.on_fusion(n)

    @property
    def fusion_nodes(self) -> int:
        with self._lock:
            return len(self._fusion)

    def set_meta(self, meta: dict) -> None:
        """New metadata (a reloaded map): the next queries get it."""
        self._meta = json.dumps(meta).encode()

    # ------------------------------------------------------------------ the frame loop
    def measurement(self, name: str, t: float, x: float, y: float, theta: float,
                    sigma: float | None) -> None:
        """One robot's measurement; never raises (failures are counted, logged once)."""
        try:
            pub = self._pubs.get(name)
            if pub is None:
                pub = self._pubs[name] = self._declare(f"{self.prefix}/robots/{name}")
            pub.put(json.dumps({"name": name, "valid": True, "t": t, "x": x, "y": y,
                                "theta": theta, "sigma": sigma}).encode())
            self.sent += 1
        except Exception as e:
            self._failed(e)

    def frame(self, t: float) -> None:
        """A frame was processed at capture time ``t``: the heartbeat, at most every
        :data:`HEARTBEAT_S`."""
        self._frames += 1
        now = time.monotonic()
        if now - self._last_beat < HEARTBEAT_S:
            return
        self._last_beat = now
        try:
            self.beat.put(json.dumps({"t": t, "frames": self._frames}).encode())
        except Exception as e:
            self._failed(e)

    def _failed(self, e: Exception) -> None:
        self.errors += 1
        if not self._warned:
            self._warned = True
            log.warning("zenoh: camera %s: publishing failed: %s (counted; further failures "
                        "are not logged)", self.id, e)

    def close(self) -> None:
        """Undeclare everything (the session stays open: its owner closes it)."""
        for entity in (self.token, self.watch, self.queryable, self.beat,
                       *self._pubs.values()):
            with contextlib.suppress(Exception):  # a session already closed
                entity.undeclare()
        self._pubs.clear()
