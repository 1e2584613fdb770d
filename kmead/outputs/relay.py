"""Robot relay: each robot's pose to its destinations, and stale messages.

Datagram (one line of ASCII, no newline, ``;``-separated ``key=value``)::

    name=amr1;seq=17;t=1700000000.123456;x=0.512300;y=0.200100;theta=1.570800;valid=1

``seq`` counts this robot's messages (all destinations share it; with a voice,
:mod:`kmead.outputs.voice`, it continues above every seq heard from the robot's other
speakers), ``t`` is the time the
pose refers to (s): the frame's capture time, or the send time when ``filter.predict`` is on
(the pose is then predicted to it). x/y metres in the world frame, theta radians in
[-pi, pi). ``valid=0``: the pose is not finite or its sigma is beyond ``relay.max_sigma_m``
(never a valid pose a robot cannot use), the robot has not been seen for
``relay.stale_after_s``, or the daemon
stops (SIGTERM, SIGINT, end of frames: one message to every robot), or the robot or one of
its destinations was removed live (one message to what was removed); x/y/theta then repeat
the last known pose (or 0 if never seen).

With ``relay.extra_fields`` on, fields follow ``valid`` (after the existing ones, whose
order never changes, so a parser reading the first seven keeps working)::

    ...;valid=1;vx=0.120000;vy=-0.010000;omega=0.300000;sigma=0.002000;age=0.000000

vx, vy: world velocity m/s; omega: turn rate rad/s (tracking filter; 0 with the IIR
filter); sigma: 1-sigma position m (0 when unknown); age: s from the newest measurement to
``t`` (0 unless predicted).

Each destination has its own connected UDP socket, so a destination that refuses (ICMP port
unreachable, e.g. nothing listening) is reported by the kernel at the next send and counted
in ``errors`` rather than ``sent``; such refusals are also counted in ``refused``, and
:meth:`RobotChannel.refused_now` names the destinations refused among the last messages (the
UI's "no listener": with nothing listening about every other send fails, the others go
out and draw the next refusal).
"""

from __future__ import annotations

import errno
import logging
import math
import socket
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from kmea.wire.protocol import robot_topic
from kmead.config.checks import parse_destination

log = logging.getLogger("kmead.relay")


@dataclass
class RobotChannel:
    """Relay state of one robot."""

    name: str
    markers: list[int]
    destinations: list[str]
    addrs: list[tuple[str, int] | None]
    x: float = math.nan
    y: float = math.nan
    theta: float = math.nan
    sigma: float | None = None
    cov: Any = None  # the tracking filter's (3, 3) covariance of (x, y, theta), or None
    last_seen: float | None = None  # source clock, s
    last_stale_sent: float | None = None
    stale: bool = True
    seq: int = 0
    sent: int = 0
    errors: int = 0
    refused: int = 0  # of errors: refused by the destination (nothing listening)
    refused_seq: dict[str, int] = field(default_factory=dict)  # destination -> seq
    extra: dict = field(default_factory=dict)
    unfit: str | None = None  # why the last pose went out as valid=0 (not finite, sigma)
    voiced: bool = True  # the last message went to the robot (not muted, this voice's turn)

    def refused_now(self) -> list[str]:
        """Destinations refused among the last :data:`REFUSED_WINDOW` messages.

        The kernel reports a refusal at the send after the datagram that drew it, so a
        destination nobody listens on fails every other send; one that starts listening
        leaves this list within a few messages."""
        return [d for d in self.destinations
                if d in self.refused_seq and self.seq - self.refused_seq[d] < REFUSED_WINDOW]


REFUSED_WINDOW = 4
MAX_COORD_M = 1e4  # m: a pose beyond is no floor's (and its datagram would not be a line)


EXTRA_FIELDS = ("vx", "vy", "omega", "sigma", "age")


def datagram(name: str, seq: int, t: float, x: float, y: float, theta: float,
             valid: bool, extra: dict[str, float] | None = None) -> bytes:
    """The ASCII datagram of one message (see the module docstring); ``extra``: the
    :data:`EXTRA_FIELDS` to append (missing, non-finite or absurd ones, beyond
    :data:`MAX_COORD_M`, are sent as 0: the line stays short)."""
    def f(v: float | None) -> str:
        return f"{(v if v is not None and abs(v) <= MAX_COORD_M else 0.0):.6f}"
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
    return str(info[0][4][0]), port  # AF_INET: the address is (host, port)


class Relay:
    """Sends robot poses; ``publish`` is called with (topic, body) for the telemetry topic."""

    def __init__(self, robots: list[dict], stale_after_s: float, stale_repeat_s: float,
                 publish=None, extra_fields: bool = False, sink=None,
                 max_sigma_m: float = math.inf) -> None:
        self.stale_after_s = stale_after_s
        self.max_sigma_m = max_sigma_m
        # sink(track, t, valid, stopping): every message again for another output (Zenoh),
        # called where the telemetry body is, so after all of a frame's datagrams.
        self.sink = sink
        self._stopping = False
        # muted: nothing goes to the robots (no datagram, no sink message), the telemetry
        # still does: a fusion node's standby, or a camera while a fusion node speaks.
        self.muted = False
        # voice: kmead.outputs.voice.Voice, whose turn it is per robot (several speakers
        # on a Zenoh site: one voice per robot, one seq).
        self.voice: Any = None
        self.stale_repeat_s = stale_repeat_s
        self.extra_fields = extra_fields
        self.publish = publish
        self._socks: dict[tuple[str, int], socket.socket] = {}
        self.channels: dict[str, RobotChannel] = {}
        self.withdrawn = 0  # valid=0 messages for removed robots and destinations
        self.configure(robots)

    def apply(self, section: dict) -> None:
        """The live ``[relay]`` keys (a ``set`` request)."""
        self.stale_after_s = section["stale_after_s"]
        self.stale_repeat_s = section["stale_repeat_s"]
        self.extra_fields = section["extra_fields"]
        self.max_sigma_m = section["max_sigma_m"]

    def _sock(self, addr: tuple[str, int]) -> socket.socket | None:
        s = self._socks.get(addr)
        if s is None:
            try:
                s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                s.setblocking(False)
                s.connect(addr)  # UDP connect: no packet; lets the kernel report refusals
            except OSError as e:
                log.warning("relay destination udp:%s:%d: %s", addr[0], addr[1], e)
                return None
            self._socks[addr] = s
        return s

    def configure(self, robots: list[dict], t: float | None = None) -> None:
        """Replace the robot list, keeping the state of robots that stay.

        A robot that goes, and each destination a robot loses, gets one ``valid=0`` message
        (at time ``t``, default its last-seen time): it must not keep following a stale pose.
        """
        old = self.channels
        self.channels = {}
        for r in robots:
            addrs = [_resolve(*parse_destination(d, f"robot {r['name']}"))
                     for d in r["destinations"]]
            tr = old.pop(r["name"], None)
            if tr is not None:
                gone = [a for a in tr.addrs if a is not None and a not in addrs]
                if gone:
                    self._send(tr, self._t(tr, t), False, gone)
                    self.withdrawn += 1
            if tr is None or tr.markers != r["markers"]:
                tr = RobotChannel(r["name"], list(r["markers"]), list(r["destinations"]), addrs,
                                seq=tr.seq if tr else 0)
            else:
                tr.destinations, tr.addrs = list(r["destinations"]), addrs
            self.channels[r["name"]] = tr
        for tr in old.values():  # removed robots
            self._send(tr, self._t(tr, t), False)
            self.withdrawn += 1
        live = {a for tr in self.channels.values() for a in tr.addrs if a is not None}
        for addr in [a for a in self._socks if a not in live]:
            self._socks.pop(addr).close()

    @staticmethod
    def _fix_time(tr: RobotChannel) -> float:
        """The time of robot ``tr``'s last fix (:meth:`publish_fix` follows :meth:`update`)."""
        if tr.last_seen is None:
            raise ValueError(f"relay: robot {tr.name!r} has no fix to publish")
        return tr.last_seen

    @staticmethod
    def _t(tr: RobotChannel, t: float | None) -> float:
        return t if t is not None else (tr.last_seen if tr.last_seen is not None else 0.0)

    def _send(self, tr: RobotChannel, t: float, valid: bool,
              addrs: Sequence[tuple[str, int] | None] | None = None,
              publish: bool = True) -> None:
        voice = self.voice
        tr.voiced = not self.muted and (voice is None or voice.speak(tr, valid, t))
        tr.seq += 1
        extra = None
        if self.extra_fields:
            extra = {"sigma": tr.sigma, **tr.extra} if valid else {}
        data = datagram(tr.name, tr.seq, t, tr.x, tr.y, tr.theta, valid, extra)
        dests = dict(zip(tr.addrs, tr.destinations, strict=False))
        for addr in () if not tr.voiced else tr.addrs if addrs is None else addrs:
            s = self._sock(addr) if addr is not None else None
            if s is None:  # a host name that did not resolve at configuration time
                tr.errors += 1
                continue
            try:
                s.send(data)
                tr.sent += 1
            except OSError as e:
                # Refused (an earlier datagram drew ICMP port unreachable), no route, full
                # buffer: count it, never stall the loop.
                tr.errors += 1
                if e.errno == errno.ECONNREFUSED:
                    tr.refused += 1
                    if (dest := dests.get(addr)) is not None:
                        tr.refused_seq[dest] = tr.seq
        if tr.voiced and voice is not None:
            voice.said(tr, valid, t)
        if publish:
            self._publish(tr, t, valid)

    def _publish(self, tr: RobotChannel, t: float, valid: bool, sink: bool = True) -> None:
        if sink and self.sink is not None and tr.voiced:
            self.sink(tr, t, valid, self._stopping)
        if self.publish is not None:
            body = {"name": tr.name, "seq": tr.seq, "t": t, "x": tr.x, "y": tr.y,
                    "theta": tr.theta, "valid": valid, "sigma": tr.sigma}
            if valid and tr.extra:
                body.update(tr.extra)
            self.publish(robot_topic(tr.name), body)

    def update(self, name: str, t: float, x: float, y: float, theta: float,
               sigma: float | None = None, extra: dict[str, Any] | None = None,
               publish: bool = True, cov: Any = None) -> None:
        """A fix of robot ``name`` at time ``t`` (the time the pose refers to): send it
        everywhere. ``extra``: vx, vy, omega, age (datagram extra fields, telemetry) and
        anything else for the telemetry body (e.g. the fusion's ``source``); ``cov``: the
        tracking filter's (3, 3) covariance of (x, y, theta) (the ROS 2 output's).
        ``publish=False``: the telemetry body waits for :meth:`publish_fix` (a frame's
        datagrams all go out before its telemetry wakes the telemetry thread)."""
        tr = self.channels[name]
        tr.x, tr.y, tr.theta, tr.sigma, tr.cov = x, y, theta, sigma, cov
        tr.extra = dict(extra) if extra else {}
        tr.last_seen = t
        tr.stale = False
        tr.last_stale_sent = None
        unfit = self._unfit(x, y, theta, sigma)
        if unfit != tr.unfit and unfit is not None:
            log.warning("robot %s: %s: sent as valid=0", name, unfit)
        tr.unfit = unfit
        self._send(tr, t, unfit is None, publish=publish)

    def _unfit(self, x: float, y: float, theta: float, sigma: float | None) -> str | None:
        """Why a pose must not reach a robot as valid, or None."""
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(theta)):
            return "pose not finite"
        if abs(x) > MAX_COORD_M or abs(y) > MAX_COORD_M:
            return f"pose beyond {MAX_COORD_M:g} m"
        if sigma is not None and not sigma <= self.max_sigma_m:  # NaN too
            return f"sigma {sigma:.3g} m beyond relay.max_sigma_m {self.max_sigma_m:g} m"
        return None

    def publish_fix(self, name: str) -> None:
        """The telemetry body of robot ``name``'s last fix."""
        tr = self.channels[name]
        self._publish(tr, self._fix_time(tr), tr.unfit is None)

    def publish_fixes(self, names: list[str]) -> None:
        """:meth:`publish_fix` for a frame's robots: every sink message first, then the
        telemetry bodies (the first body wakes the telemetry thread, which would take the
        GIL from the next robot's Zenoh message)."""
        tracks = [self.channels[n] for n in names]
        if self.sink is not None:
            for tr in tracks:
                if tr.voiced:
                    self.sink(tr, self._fix_time(tr), tr.unfit is None, self._stopping)
        for tr in tracks:
            self._publish(tr, self._fix_time(tr), tr.unfit is None, sink=False)

    def tick(self, now: float) -> list[str]:
        """Stale messages for robots unseen for ``stale_after_s`` at time ``now``.

        Returns the names that just became stale (for an event).
        """
        newly = []
        for tr in self.channels.values():
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

    def invalidate(self, t: float) -> list[str]:
        """One ``valid=0`` message at ``t`` to every robot with a pose that is not stale
        yet (its source's time broke); they are stale until their next fix. Their names."""
        names = []
        for tr in self.channels.values():
            if tr.last_seen is not None and not tr.stale:
                tr.stale, tr.last_stale_sent = True, t
                self._send(tr, t, False)
                names.append(tr.name)
        return names

    def shutdown(self, t: float) -> None:
        """One ``valid=0`` message to every robot: the daemon stops (SIGTERM, SIGINT, end of
        frames); robots must not keep following their last pose. With a voice, the robots
        another speaker takes over get nothing from this one (it hands them over first)."""
        if self.voice is not None:
            self.voice.release()
        self._stopping = True
        for tr in self.channels.values():
            tr.stale = True
            self._send(tr, t, False)

    def close(self) -> None:
        for s in self._socks.values():
            s.close()
        self._socks.clear()
