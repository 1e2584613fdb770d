"""A camera's measurements on Zenoh, for the fusion nodes (docs/fusion.md).

With ``[zenoh] enabled = true`` every ``kmead`` is a camera of its site. Keys (``<site>`` =
``zenoh.site``, ``<id>`` = :func:`camera_id`):

- ``<site>/cam/<id>``: a liveliness token, alive as long as the session (a killed kmead's
  goes at once, a frozen or cut-off one's after the lease);
- ``<site>/cam/<id>/meta``: a queryable answering :func:`meta_body` (map digest, camera
  model, resolution), JSON;
- ``<site>/cam/<id>/robots/<robot>``: one measurement per robot per frame, JSON
  ``{"name", "valid": true, "t", "x", "y", "theta", "sigma"}``: the capture instant and the
  robot's pose before the tracking filter, whatever this camera's filter made of it (a
  fusion node filters, and gates, itself);
- ``<site>/cam/<id>/frame``: ``{"t", "frames"}`` every :data:`HEARTBEAT_S` from the frame
  loop: a camera that sees no robot still shows it works (a fusion node drops a camera that
  sends nothing for the lease);
- ``<site>/cam/<id>/zid/<session>``: a second liveliness token naming the session, so that
  two ``kmead`` claiming one camera id are told apart: the second refuses to start
  (:class:`DuplicateCamera`, exit 2), or, started at the same moment, each reports the other
  (an ``error`` event); a fusion node lists them in its status.

Who speaks to each robot is :mod:`kmead.outputs.voice` (:attr:`ZenohCamera.voice`): this
camera keeps its voice until a fusion node (or a camera that sees the robot better) is
heard speaking for it, and takes it back when handed over or when nobody speaks.

Threads: :meth:`ZenohCamera.measurement`, :meth:`ZenohCamera.frame` and :meth:`close` are
the frame loop's (under the daemon's lock: the publisher table has one owner); the
queryable and the liveliness callbacks run on Zenoh's threads and touch only an immutable
payload, or report.
"""

from __future__ import annotations

import contextlib
import json
import logging
import re
import socket
import time
from collections.abc import Callable
from typing import Any

from kmea.maps.files import map_digest
from kmea.maps.model import MarkerMap
from kmead.config.site_tls import certificate_name
from kmead.outputs.voice import CAMERA, NODE, QUIET_S, Voice
from kmead.outputs.zenoh_session import import_zenoh

log = logging.getLogger("kmead.zenoh")

HEARTBEAT_S = 0.2
STARTUP_S = 1.0  # s: the start waits at most this long for the site's tokens
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


class DuplicateCamera(ValueError):
    """Another ``kmead`` holds this camera id on the site (a configuration error)."""


class ZenohCamera:
    """This kmead as a camera of its site, on an open session (module docstring).

    ``known(name)``: a robot of this kmead's; ``on_quiet(name)``: it stopped speaking for a
    robot (its Zenoh robot outputs go); ``event(level, text)``: a report for its log."""

    def __init__(self, session: Any, site: str, cam_id: str, meta: dict,
                 known: Callable[[str], bool] = lambda _name: True,
                 on_quiet: Callable[[str], None] | None = None,
                 event: Callable[[str, str], None] | None = None) -> None:
        zenoh = import_zenoh()
        self.session = session
        self.site = site
        self.id = cam_id
        self.prefix = f"{site}/cam/{cam_id}"
        self.zid = str(session.info.zid())
        self.event = event
        self._meta = json.dumps(meta).encode()
        self._pubs: dict[str, Any] = {}
        self.sent = 0
        self.errors = 0
        self._warned = False
        self._frames = 0
        self._last_beat = 0.0
        self._twins: set[str] = set()  # other sessions holding this camera id
        self._declare = lambda key: session.declare_publisher(
            key, reliability=zenoh.Reliability.RELIABLE,
            congestion_control=zenoh.CongestionControl.DROP)
        twins = self._tokens(f"{self.prefix}/zid/*")
        twins.discard(f"{self.prefix}/zid/{self.zid}")
        if twins:
            raise DuplicateCamera(
                f"zenoh: camera id {cam_id!r} is already alive on site {site!r} (session "
                f"{sorted(twins)[0].rsplit('/', 1)[-1][:8]}): give this kmead another "
                "zenoh.camera")
        # Speakers already on the site (cameras, fusion nodes): listen to their voices
        # before speaking to a robot, so as not to start a second one.
        busy = bool(self._tokens(f"{site}/cam/*") | self._tokens(f"{site}/fusion/**"))
        # Speakers whose token went (killed, or their lease ran out): gone at once, their
        # robots taken without waiting for their silence. (A token never silences anyone.)
        self._gone: set[tuple[str, str]] = set()
        self._roles: dict[str, set[str]] = {}  # node id -> its role tokens alive
        self.voice = Voice(session, site, cam_id, CAMERA, known, alive=self._alive,
                           on_quiet=on_quiet, listen_s=QUIET_S if busy else 0.0)
        self.speakers = [
            session.liveliness().declare_subscriber(f"{site}/cam/*", self._speaker),
            session.liveliness().declare_subscriber(f"{site}/fusion/*/*", self._speaker)]
        self.queryable = session.declare_queryable(f"{self.prefix}/meta", self._answer)
        self.beat = self._declare(f"{self.prefix}/frame")
        self.twin_watch = session.liveliness().declare_subscriber(
            f"{self.prefix}/zid/*", self._twin, history=True)
        self.id_token = session.liveliness().declare_token(f"{self.prefix}/zid/{self.zid}")
        self.token = session.liveliness().declare_token(self.prefix)
        log.info("zenoh: camera %s on site %r (%s/...)", cam_id, site, self.prefix)

    def _tokens(self, key: str) -> set[str]:
        """The liveliness tokens alive on ``key`` now."""
        out: set[str] = set()
        try:
            for reply in self.session.liveliness().get(key, timeout=STARTUP_S):
                if reply.ok is not None:
                    out.add(str(reply.ok.key_expr))
        except Exception as e:  # a session closing
            log.debug("zenoh: liveliness query %s failed: %s", key, e)
        return out

    # ------------------------------------------------------------------ Zenoh's threads
    def _answer(self, query: Any) -> None:
        try:
            query.reply(f"{self.prefix}/meta", self._meta)
        except Exception as e:  # the querier went away
            log.debug("zenoh: meta reply failed: %s", e)

    def _speaker(self, sample: Any) -> None:
        """A camera's or node's token came or went (Zenoh's thread)."""
        parts = str(sample.key_expr).split("/")
        alive = str(sample.kind).rsplit(".", 1)[-1] == "PUT"
        if len(parts) == 3:  # <site>/cam/<id>
            key = (parts[2], CAMERA)
        elif len(parts) == 4:  # <site>/fusion/<id>/<role>: gone with its last role
            if len(self._roles) > 4096:  # bounded (hostile tokens): forget, nothing worse
                self._roles.clear()
            roles = self._roles.setdefault(parts[2], set())
            (roles.add if alive else roles.discard)(parts[3])
            alive = bool(roles)
            key = (parts[2], NODE)
        else:
            return
        (self._gone.discard if alive else self._gone.add)(key)
        if len(self._gone) > 4096:  # bounded: the oldest knowledge matters least
            self._gone.clear()

    def _alive(self, speaker: str, kind: str) -> bool:
        return (speaker, kind) not in self._gone

    def _twin(self, sample: Any) -> None:
        """Another session's token of this camera id (two kmead started at once)."""
        zid = str(sample.key_expr).rsplit("/", 1)[-1]
        if zid == self.zid:
            return
        alive = str(sample.kind).rsplit(".", 1)[-1] == "PUT"
        (self._twins.add if alive else self._twins.discard)(zid)
        if alive:
            text = (f"zenoh: camera id {self.id!r} is claimed by another kmead on site "
                    f"{self.site!r} (session {zid[:8]}): two cameras with one id; give one "
                    "of them another zenoh.camera")
            if self.event is not None:
                self.event("error", text)
            else:
                log.error("%s", text)

    @property
    def twins(self) -> int:
        """Other kmead holding this camera id now."""
        return len(self._twins)

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

    def frame(self, t: float, seen: set[str] | None = None) -> None:
        """A frame was processed at capture time ``t`` with fixes of ``seen``: the voice's
        hand-overs, and the heartbeat, at most every :data:`HEARTBEAT_S`."""
        self.voice.frame(seen or set())
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
        self.voice.close()
        for entity in (self.token, self.id_token, self.twin_watch, *self.speakers,
                       self.queryable, self.beat, *self._pubs.values()):
            with contextlib.suppress(Exception):  # a session already closed
                entity.undeclare()
        self._pubs.clear()
