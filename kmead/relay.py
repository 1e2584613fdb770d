"""Robot relay: each robot's pose to its destinations, and stale messages.

Datagram (one line of ASCII, no newline, ``;``-separated ``key=value``)::

    name=amr1;seq=17;t=1700000000.123456;x=0.512300;y=0.200100;theta=1.570800;valid=1

``seq`` counts this robot's messages (all destinations share it), ``t`` is the time the
pose refers to (s): the frame's capture time, or the send time when ``filter.predict`` is on
(the pose is then predicted to it). x/y metres in the world frame, theta radians in
[-pi, pi). ``valid=0``: the robot has not been seen for ``relay.stale_after_s``; x/y/theta
then repeat the last known pose (or 0 if never seen).

With ``relay.extra_fields`` on, fields follow ``valid`` (after the existing ones, whose
order never changes, so a parser reading the first seven keeps working)::

    ...;valid=1;vx=0.120000;vy=-0.010000;omega=0.300000;sigma=0.002000;age=0.000000

vx, vy: world velocity m/s; omega: turn rate rad/s (tracking filter; 0 with the IIR
filter); sigma: 1-sigma position m (0 when unknown); age: s from the newest measurement to
``t`` (0 unless predicted).
"""

from __future__ import annotations

import logging
import math
import socket
from dataclasses import dataclass, field
from typing import Any

from kmea.protocol import robot_topic
from kmead.config import parse_destination

log = logging.getLogger("kmead.relay")


@dataclass
class RobotTrack:
    """Relay state of one robot."""

    name: str
    markers: list[int]
    destinations: list[str]
    addrs: list[tuple[str, int] | None]
    x: float = math.nan
    y: float = math.nan
    theta: float = math.nan
    sigma: float | None = None
    last_seen: float | None = None  # source clock, s
    last_stale_sent: float | None = None
    stale: bool = True
    seq: int = 0
    sent: int = 0
    errors: int = 0
    extra: dict = field(default_factory=dict)


EXTRA_FIELDS = ("vx", "vy", "omega", "sigma", "age")


def datagram(name: str, seq: int, t: float, x: float, y: float, theta: float,
             valid: bool, extra: dict[str, float] | None = None) -> bytes:
    """The ASCII datagram of one message (see the module docstring); ``extra``: the
    :data:`EXTRA_FIELDS` to append (missing or non-finite ones are sent as 0)."""
    def f(v: float | None) -> str:
        return f"{(v if v is not None and math.isfinite(v) else 0.0):.6f}"
    text = (f"name={name};seq={seq};t={t:.6f};x={f(x)};y={f(y)};theta={f(theta)};"
            f"valid={int(valid)}")
    if extra is not None:
        text += "".join(f";{k}={f(extra.get(k))}" for k in EXTRA_FIELDS)
    return text.encode("ascii")


def parse_datagram(data: bytes) -> dict[str, Any]:
    """Inverse of :func:`datagram` (for tests and for clients written in Python); extra
    fields, when present, are floats under their names."""
    out: dict[str, Any] = {}
    for part in data.decode("ascii").split(";"):
        k, _, v = part.partition("=")
        out[k] = v
    res = {"name": out["name"], "seq": int(out["seq"]), "t": float(out["t"]),
           "x": float(out["x"]), "y": float(out["y"]), "theta": float(out["theta"]),
           "valid": out["valid"] == "1"}
    res.update({k: float(out[k]) for k in EXTRA_FIELDS if k in out})
    return res


def _resolve(host: str, port: int) -> tuple[str, int] | None:
    """Numeric address, resolved once: a DNS lookup must never happen in the frame loop."""
    try:
        info = socket.getaddrinfo(host, port, socket.AF_INET, socket.SOCK_DGRAM)
    except (OSError, UnicodeError):
        log.warning("relay destination udp:%s:%d does not resolve; datagrams to it are "
                    "counted as errors", host, port)
        return None
    return info[0][4][0], port


class Relay:
    """Sends robot poses; ``publish`` is called with (topic, body) for the telemetry topic."""

    def __init__(self, robots: list[dict], stale_after_s: float, stale_repeat_s: float,
                 publish=None, extra_fields: bool = False) -> None:
        self.stale_after_s = stale_after_s
        self.stale_repeat_s = stale_repeat_s
        self.extra_fields = extra_fields
        self.publish = publish
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        self.tracks: dict[str, RobotTrack] = {}
        self.configure(robots)

    def configure(self, robots: list[dict]) -> None:
        """Replace the robot list, keeping the state of robots that stay."""
        old = self.tracks
        self.tracks = {}
        for r in robots:
            addrs = [_resolve(*parse_destination(d, f"robot {r['name']}"))
                     for d in r["destinations"]]
            tr = old.get(r["name"])
            if tr is None or tr.markers != r["markers"]:
                tr = RobotTrack(r["name"], list(r["markers"]), list(r["destinations"]), addrs)
            else:
                tr.destinations, tr.addrs = list(r["destinations"]), addrs
            self.tracks[r["name"]] = tr

    def _send(self, tr: RobotTrack, t: float, valid: bool) -> None:
        tr.seq += 1
        extra = None
        if self.extra_fields:
            extra = {"sigma": tr.sigma, **tr.extra} if valid else {}
        data = datagram(tr.name, tr.seq, t, tr.x, tr.y, tr.theta, valid, extra)
        for addr in tr.addrs:
            if addr is None:  # a host name that did not resolve at configuration time
                tr.errors += 1
                continue
            try:
                self.sock.sendto(data, addr)
                tr.sent += 1
            except OSError:
                # Unresolvable host, no route, full buffer: count it, never stall the loop.
                tr.errors += 1
        if self.publish is not None:
            body = {"name": tr.name, "seq": tr.seq, "t": t, "x": tr.x, "y": tr.y,
                    "theta": tr.theta, "valid": valid, "sigma": tr.sigma}
            if valid and tr.extra:
                body.update(tr.extra)
            self.publish(robot_topic(tr.name), body)

    def update(self, name: str, t: float, x: float, y: float, theta: float,
               sigma: float | None = None, extra: dict[str, Any] | None = None) -> None:
        """A fix of robot ``name`` at time ``t`` (the time the pose refers to): send it
        everywhere. ``extra``: vx, vy, omega, age (datagram extra fields, telemetry) and
        anything else for the telemetry body (e.g. the fusion's ``source``)."""
        tr = self.tracks[name]
        tr.x, tr.y, tr.theta, tr.sigma = x, y, theta, sigma
        tr.extra = dict(extra) if extra else {}
        tr.last_seen = t
        tr.stale = False
        tr.last_stale_sent = None
        self._send(tr, t, True)

    def tick(self, now: float) -> list[str]:
        """Stale messages for robots unseen for ``stale_after_s`` at time ``now``.

        Returns the names that just became stale (for an event).
        """
        newly = []
        for tr in self.tracks.values():
            if tr.last_seen is None:
                continue  # never seen: nothing to withdraw
            if now - tr.last_seen < self.stale_after_s:
                continue
            if not tr.stale:
                tr.stale = True
                newly.append(tr.name)
                tr.last_stale_sent = now
                self._send(tr, now, False)
            elif (self.stale_repeat_s > 0 and tr.last_stale_sent is not None
                  and now - tr.last_stale_sent >= self.stale_repeat_s):
                tr.last_stale_sent = now
                self._send(tr, now, False)
        return newly

    def close(self) -> None:
        self.sock.close()
